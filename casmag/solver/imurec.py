"""GP-SLAM on an IMU recording (``dqw,dqx,dqy,dqz,dvx,dvy,dvz`` columns): the IMU model
of the IMU problem files (casmag.solver.imu: strapdown, the IMU-only adjustment, GP-SLAM
with its warm starts), on the recording's data (casmag.data.imurec). ``casmag slam``
(casmag.solver.recslam) takes this path for such recordings.

Settings come from a problem file's ``model`` and ``solver`` sections
(:class:`casmag.problem.imu.ImuRecordingSpec`) and ``--set`` overrides. What the model
needs and a simulation would have given is taken from the recording: the sample rate
(the keyframes take the nearest whole number of IMU intervals to ``model.keyframe_rate``),
and the white noise of the gyroscope, the accelerometer and the magnetometer from the
rest at the start when ``model.imu`` and ``model.magnetometer`` leave it null
(casmag.data.imurec.rest_noise; ``info["defaults"]`` records the estimates and which were
used). The GP hyperparameters are estimated as for IMU problems (``estimate``, the
default). The bias random walks cannot be estimated: the biases are constant unless the
file gives ``model.imu.bias: random_walk`` with both walks.

Several IMU recordings of one field share one map (:func:`slam_imu_sessions`, ``casmag slam
A.csv B.csv``): each starts from its own first true pose and rest, keeps its own biases, and
the sessions are solved together in the given order (casmag.solver.imu).

The magnetometer's lag behind the motion is estimated on the path solved (:func:`imu_lag`:
GP-SLAM's when the map was solved, else the IMU-only adjustment) and reported in
``info["magnetometer_lag"]`` (``estimate``: the lag left there, ``steps``: each estimate),
with a warning when it is significant, and a significant one left on GP-SLAM's path makes
the verdict untrusted (casmag.result.verdict). ``--mag-lag SECONDS`` removes a known lag (0:
none); ``--mag-lag auto``, the default of ``casmag slam`` for IMU recordings
(casmag.solver.recslam.DEFAULT_MAG_LAG), estimates it first on the IMU-only adjustment (it
does not read the magnetometer, but drifts) and removes a significant one before the map
is solved, then once more on the path solved, solving again when a lag is still clear
there (one recording; several sessions get each one's estimate reported).

A recording is located against a saved map of one box (``casmag slam REC --map MAP``,
casmag.solver.imu.located_stages): the map's kernel and hyperparameters, the recording's
own noise; the map updated by it, or held at its mean (``--hold-map``).

Not done here: no filter baseline (``--method ekf``), no tiled maps (the IMU model has
none), no Laplace covariance (casmag.solver.imu.IMU_NO_COVARIANCE)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from casmag import strapdown as sd
from casmag.data.checks import announce
from casmag.data.clock import LagEstimate, estimate_lag, lag_warning, shift_magnetometer
from casmag.data.imurec import RestNoise, imu_data, rest_noise, rest_warnings
from casmag.data.imusim import ImuData, stack_sessions
from casmag.data.recording import Recording
from casmag.errors import DataError
from casmag.gp.savedmap import SavedMap
from casmag.problem.imu import (
    IMU_SOLVER_KEYS,
    ImuProblem,
    ImuRecordingSpec,
    load_recording_spec,
    recording_imu_problem,
    refuse_unused_solver_keys,
)
from casmag.problem.spec import as_overrides
from casmag.result import Result
from casmag.solver.imu import solve_imu
from casmag.solver.oriented import constant_magnetometer, lag_record, refuse_constant_field
from casmag.solver.planar import located
from casmag.solver.sessions import require_first_poses
from casmag.solver.staged import PriorMap

#: The noise settings a recording's rest gives when the problem leaves them null: (section
#: of ``model``, key; the estimate's field of casmag.data.imurec.RestNoise has the key's name).
REST_DEFAULTS = (
    ("imu", "gyro_noise_density"),
    ("imu", "acc_noise_density"),
    ("magnetometer", "sigma_m"),
)


def _with_rest_noise(
    spec: ImuRecordingSpec, rec: Recording, noise: RestNoise
) -> tuple[ImuRecordingSpec, list[str]]:
    """``spec`` with the noise settings it leaves null set to the rest's estimates, and
    their keys. An estimate of zero (a sensor that repeats one value at rest) is refused
    naming the key: the noise must then be given."""
    model, used = spec.model, []
    for section, key in REST_DEFAULTS:
        block = getattr(model, section)
        if getattr(block, key) is not None:
            continue
        if section == "magnetometer" and model.gp.form == "none":
            continue
        value = getattr(noise, key)
        if np.isnan(value):
            raise DataError(
                f"{rec.path}: model.{section}.{key}: the rest at the start "
                f"({noise.samples} IMU intervals) holds fewer than two samples of this sensor, "
                "so its noise cannot be estimated there; give it, or lengthen "
                "model.initial.rest_seconds"
            )
        if not value > 0.0:
            raise DataError(
                f"{rec.path}: model.{section}.{key}: the sensor repeats one value over the "
                "rest at the start, so its noise cannot be estimated there; give it"
            )
        block = block.model_copy(update={key: value})
        model = model.model_copy(update={section: block})
        used.append(f"model.{section}.{key}")
    return spec.model_copy(update={"model": model}), used


#: Fewest magnetometer samples per keyframe interval (:func:`check_magnetometer_rate`); below
#: one, a sample's clock running a little slow would refuse a magnetometer at the keyframe
#: rate.
MIN_MAG_PER_KEYFRAME = 0.9


def check_magnetometer_rate(rec: Recording, prob: ImuProblem) -> None:
    """Refuse (DataError naming ``model.keyframe_rate``) keyframes closer together than the
    magnetometer's samples: a magnetometer slower than the keyframes (interpolated to the
    IMU's samples, ``rec.mag_share``) would give neighbouring keyframes the same sample."""
    per_keyframe = prob.substeps * rec.mag_share
    if per_keyframe >= MIN_MAG_PER_KEYFRAME:
        return
    rate = prob.imu_rate * rec.mag_share
    raise DataError(
        f"{rec.path}: model.keyframe_rate: the magnetometer gives about {rate:.3g} samples "
        f"per second, fewer than the {prob.imu_rate / prob.substeps:.3g} keyframes per second, "
        "so neighbouring keyframes would share its samples; set model.keyframe_rate to at "
        f"most {rate:.3g}"
    )


#: Rate [Hz] of the series the lag is estimated on (:func:`imu_lag`). The recording's own
#: rate (100-1,000 Hz) would make each window's GP hundreds of points; the keyframes (5 Hz)
#: resolve the lag only to 0.04 s steps with low gains. Measured on simulated recordings
#: (rectangle, handwriting; lags of -0.1 to 0.2 s put in): at 20 Hz within 0.03 s of
#: the lag put in, 1.2 s per estimate; at 5 Hz within 0.04 s, gains a third to a twentieth.
LAG_RATE = 20.0

#: The paths a lag is estimated on, in the order tried by ``--mag-lag auto``: (name in
#: ``info["magnetometer_lag"]``, the result's arrays of its keyframe positions and
#: orientations).
LAG_PATHS = {"IMU-only adjustment": "imu_only", "GP-SLAM": "estimate"}


def imu_lag(
    t: np.ndarray, data: ImuData, arrays: Mapping[str, Any], path: str = "estimate"
) -> LagEstimate | None:
    """The magnetometer's lag behind a path of the IMU model's result
    (casmag.data.clock.estimate_lag; None when the path is too short for two of its
    windows or missing): its keyframe poses (``arrays`` ``t``, ``P_<path>``, ``Q_<path>``)
    carried to every sample of a :data:`LAG_RATE` series, positions by linear
    interpolation and orientations by the gyroscope's increments from the last keyframe,
    the magnetometer ``data.Y`` (sample times ``t``) turned into the map frame there.
    ``imu_only``: the IMU-only adjustment, which does not read the magnetometer (so it does
    not take up the lag it measures) but drifts; ``estimate``: GP-SLAM's."""
    if arrays.get(f"P_{path}") is None or arrays.get(f"Q_{path}") is None:
        return None
    tk, P, Q = (np.asarray(arrays[k], dtype=float) for k in ("t", f"P_{path}", f"Q_{path}"))
    step = max(1, round(1.0 / (LAG_RATE * data.T)))
    kf = np.searchsorted(t, tk - 0.5 * data.T)  # the keyframes' samples
    rows = np.arange(kf[0], kf[-1] + 1, step)
    # the gyroscope's orientation from the first sample
    Qsd = sd.quat_prefix(np.vstack([[1.0, 0.0, 0.0, 0.0], data.dq[: t.size - 1]]))
    last = np.searchsorted(kf, rows, side="right") - 1  # each row's keyframe at or before it
    Qr = sd.quat_mul(sd.quat_mul(Q[last], sd.quat_conj(Qsd[kf[last]])), Qsd[rows])
    Pr = np.column_stack([np.interp(t[rows], tk, P[:, j]) for j in range(3)])
    return estimate_lag(t[rows], Pr, sd.rotate(sd.quat_normalize(Qr), data.Y[rows]))


def _final_path(result: Result) -> str:
    """The name (:data:`LAG_PATHS`) of the path a result's lag is estimated on: GP-SLAM's
    when its map was solved, else the IMU-only adjustment."""
    solved = result.success and result.arrays.get("P_estimate") is not None
    if solved and result.details.get("map_decision") == "map":
        return "GP-SLAM"
    return "IMU-only adjustment"


def slam_imu(
    rec: Recording,
    problem: str | Path | Mapping[str, Any] | None = None,
    overrides: str | Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, float, float, float], None] | None = None,
    field_check: bool = True,
    on_warning: Callable[[str], None] | None = None,
    anchor: str = "truth",
    mag_lag: float | str | None = None,
    saved: SavedMap | None = None,
    map_source: str = "",
    hold_map: bool = False,
) -> Result:
    """GP-SLAM on an IMU recording (module docstring). A constant magnetometer carries no
    position information: the map is left out and the result is the IMU-only adjustment
    (with ``field_check`` off, DataError). ``anchor``: ``truth`` starts at the first true
    position and heading (when the recording has them; the errors are then against the
    truth), ``origin`` at position 0 and heading 0 (no errors). ``mag_lag``: seconds
    already removed from ``rec`` (recorded), or ``auto`` (module docstring). ``saved``:
    locate the recording against this map (read from ``map_source``; its frame is the
    recording's first true pose's, as the map's was), updated by it or, with
    ``hold_map``, held at its mean."""
    overrides = as_overrides(overrides)
    refuse_unused_solver_keys(overrides, "casmag slam on an imu recording", IMU_SOLVER_KEYS)
    spec = load_recording_spec(ImuRecordingSpec, problem, overrides)
    source = str(problem) if isinstance(problem, (str, Path)) else "--set"
    if saved is not None:
        spec = _on_saved_map(spec, saved, map_source)
    constant = constant_magnetometer(rec.Y)
    if constant and saved is not None:
        raise DataError(f"{rec.path}: mx,my,mz: a constant magnetometer cannot be located")
    if constant:
        if not field_check:
            refuse_constant_field(rec.path)
        spec = _without_map(spec)
    rest_seconds = spec.model.initial.rest_seconds
    data, n = imu_data(rec, rest_seconds, anchor)
    noise = rest_noise(rec, data.T, n)
    spec, used = _with_rest_noise(spec, rec, noise)
    prob = recording_imu_problem(spec, source, 1.0 / data.T)
    check_magnetometer_rate(rec, prob)
    found: list[dict[str, Any]] = []

    def warn(items: list[dict[str, Any]]) -> None:
        announce(rec.path, items, on_warning)
        found.extend(items)

    warn([*rec.notes, *rest_warnings(noise, rest_seconds)])
    auto = mag_lag == "auto"
    removed, steps = (0.0 if auto else mag_lag or 0.0), []
    Y0 = data.Y

    def estimate(res: Result, name: str) -> LagEstimate | None:
        lag = imu_lag(rec.t, data, res.arrays, LAG_PATHS[name])
        steps.append({"path": name, "estimate": None if lag is None else lag.to_dict()})
        return lag

    def remove(lag: LagEstimate | None) -> bool:
        nonlocal data, removed
        if not auto or lag is None or not lag.significant:
            return False
        removed += lag.lag_seconds
        steps[-1]["removed_seconds"] = lag.lag_seconds
        data = dataclasses.replace(data, Y=shift_magnetometer(rec.t, Y0, removed))
        return True

    if auto and not constant:  # the IMU-only adjustment first: it does not read the field
        first = solve_imu(recording_imu_problem(_without_map(spec), source, 1.0 / data.T), data)
        remove(estimate(first, "IMU-only adjustment"))
    prior = None if saved is None else PriorMap.of(saved, held=hold_map)
    result = solve_imu(prob, data, progress, prior)
    lag = None
    if not constant:  # on the path solved; auto: once more when a lag is still clear there
        lag = estimate(result, _final_path(result))
        if remove(lag):
            result = solve_imu(prob, data, progress, prior)
            lag = estimate(result, _final_path(result))
    if auto and removed:
        warn([_shifted(removed)])
    if not auto:  # the lag left on the path solved
        warn(lag_warning(lag, f"the {steps[-1]['path']} path" if steps else ""))
    result.info.update(
        name=Path(rec.path).stem,
        recording=str(rec.path),
        defaults={"rest": noise.to_dict(), "from_rest": used},
        magnetometer_lag={
            **lag_record(lag, removed),
            "path": steps[-1]["path"] if steps else None,
            "steps": steps,
        },
    )
    result.info["anchor"]["start"] = anchor  # truth: the first true pose; origin
    if constant:
        result.info["fallback"] = "constant magnetometer: the IMU-only adjustment, no map"
    if saved is not None:
        noise = (result.details.get("schedules") or [{}])[0].get("held_noise")
        held = None if noise is None else (noise["sigma_m_used"], noise["map_std_on_path"])
        located(result, saved, map_source, result.arrays.get("P_estimate"), hold_map, held)
    result.warnings = found + list(result.warnings or [])
    result.judge()  # again, with the lag left on the path solved
    return result


def _on_saved_map(spec: ImuRecordingSpec, saved: SavedMap, where: str) -> ImuRecordingSpec:
    """``spec`` with the map's kernel and hyperparameters (none estimated), after checking
    that the map can locate an IMU recording: one box (the IMU model has no tiles), 3-D,
    and a map form the model asked for (reduced_rank)."""
    saved.require_posterior(where)
    saved.require_box(where, "locate an IMU recording")
    if saved.dim != 3:
        raise DataError(f"{where}: a {saved.dim}-D map cannot locate an IMU recording (3-D)")
    gp = spec.model.gp
    if gp.form != "reduced_rank":
        raise DataError(
            f"{where}: model.gp.form {gp.form}: an IMU recording is located on the saved "
            "map, which is one box (reduced_rank)"
        )
    change = {"kernel": saved.kernel, "sigma_f": saved.sigma_f, "lengthscale": saved.lengthscale}
    gp = gp.model_copy(update=change)
    return spec.model_copy(update={"model": spec.model.model_copy(update={"gp": gp})})


def _session_lag(
    rec: Recording, data: ImuData, arrays: Mapping[str, Any], row: Mapping[str, Any], path: str
) -> LagEstimate | None:
    """One session's lag (:func:`imu_lag` on ``path``) on its keyframes of the stacked
    result (``row``: its ``info["sessions"]`` entry), their times on the recording's own
    clock."""
    a = int(row["first_keyframe"])
    e = a + int(row["keyframes"])
    key = LAG_PATHS[path]
    if arrays.get(f"P_{key}") is None:
        return None
    t = np.asarray(arrays["t"], dtype=float)[a:e]
    own = {"t": rec.t[0] + t - t[0]}
    own |= {f"{v}_{key}": np.asarray(arrays[f"{v}_{key}"])[a:e] for v in ("P", "Q")}
    return imu_lag(rec.t, data, own, key)


def _without_map(spec: ImuRecordingSpec) -> ImuRecordingSpec:
    """``spec`` with the map left out (``model.gp.form: none``): the IMU-only adjustment."""
    gp = spec.model.gp.model_copy(update={"form": "none"})
    return spec.model_copy(update={"model": spec.model.model_copy(update={"gp": gp})})


def _shifted(seconds: float) -> dict[str, str]:
    """The warning that ``--mag-lag auto`` removed ``seconds`` of lag."""
    return {
        "check": "magnetometer_lag",
        "column": "mx,my,mz",
        "reason": f"shifted by {seconds:.3g} s (a lag removed, estimated by --mag-lag auto)",
    }


def _pooled(noises: Sequence[RestNoise]) -> RestNoise:
    """The rests' noise estimates pooled over several recordings: each density and sigma_m
    the root mean square of the recordings' (each a per-sample deviation), the samples
    summed, the largest specific force and turn."""
    rms = lambda key: float(np.sqrt(np.mean([getattr(v, key) ** 2 for v in noises])))  # noqa: E731
    return RestNoise(
        gyro_noise_density=rms("gyro_noise_density"),
        acc_noise_density=rms("acc_noise_density"),
        sigma_m=rms("sigma_m"),
        samples=sum(v.samples for v in noises),
        specific_force=max(v.specific_force for v in noises),
        turned_deg=max(v.turned_deg for v in noises),
    )


def slam_imu_sessions(
    recs: Sequence[Recording],
    problem: str | Path | Mapping[str, Any] | None = None,
    overrides: str | Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, float, float, float], None] | None = None,
    on_warning: Callable[[str], None] | None = None,
    mag_lag: float | str | None = None,
) -> Result:
    """GP-SLAM on several IMU recordings of one field with one map: each recording's data
    as :func:`slam_imu` makes it from its own rest and first true pose (truth columns
    with the orientation are needed: the sessions' common frame), one IMU rate (DataError
    naming the recording otherwise), the noise left null in the settings estimated over
    every rest (the root mean square of each rest's estimate), the sessions stacked in the
    given order (casmag.data.imusim.stack_sessions) and solved by casmag.solver.imu: all
    sessions together by the schedule ladder (the default, ``auto``), or added one at a time
    with a ``solver.warm_start`` strategy (casmag.solver.staged.solve_sessions).
    ``info["sessions"]`` has each recording's rows under its name; a constant
    magnetometer is refused (it has no field to share a map of). ``mag_lag`` ``auto``
    (``casmag slam``'s default for IMU recordings): each recording's lag estimated on its
    own IMU-only adjustment and removed when significant, before the sessions are stacked;
    None or 0: as recorded. Either way each session's lag left on the path solved is
    reported (``info["magnetometer_lag"]["sessions"]``) and judged by the verdict."""
    require_first_poses(recs, "imu", "x_true, y_true, z_true, qw_true..qz_true")
    overrides = as_overrides(overrides)
    refuse_unused_solver_keys(overrides, "casmag slam on imu recordings", IMU_SOLVER_KEYS)
    spec = load_recording_spec(ImuRecordingSpec, problem, overrides)
    source = str(problem) if isinstance(problem, (str, Path)) else "--set"
    rest_seconds = spec.model.initial.rest_seconds
    datas: list[ImuData] = []
    noises: list[RestNoise] = []
    found: list[dict[str, Any]] = []
    for rec in recs:
        if constant_magnetometer(rec.Y):
            raise DataError(
                f"{rec.path}: mx, my, mz: the magnetometer is constant (every row the same), "
                "so it has no field to share a map of; solve it alone or leave it out"
            )
        data, n = imu_data(rec, rest_seconds, "truth")
        if datas and abs(data.T - datas[0].T) > 1e-6 * datas[0].T:
            raise DataError(
                f"{rec.path}: t: sample interval {data.T:.6g} s beside {datas[0].T:.6g} s in "
                f"{recs[0].path}: the sessions of one map share one IMU rate"
            )
        noise = rest_noise(rec, data.T, n)
        _with_rest_noise(spec, rec, noise)  # a sensor without noise at rest: refused here
        own = [*rec.notes, *rest_warnings(noise, rest_seconds)]
        announce(rec.path, own, on_warning)
        found.extend({**w, "recording": str(rec.path)} for w in own)
        datas.append(dataclasses.replace(data, T=datas[0].T if datas else data.T))
        noises.append(noise)
    pooled = _pooled(noises)
    spec, used = _with_rest_noise(spec, recs[0], pooled)
    prob = recording_imu_problem(spec, source, 1.0 / datas[0].T)
    for rec in recs:
        check_magnetometer_rate(rec, prob)
    if mag_lag not in (None, 0, 0.0, "auto"):
        raise DataError(
            f"mag_lag: several recordings take 'auto' or 0, got {mag_lag!r} (a lag in "
            "seconds belongs to one recording)"
        )
    removed = [0.0] * len(recs)
    if mag_lag == "auto":  # each recording's own IMU-only adjustment: it does not read the field
        alone = recording_imu_problem(_without_map(spec), source, 1.0 / datas[0].T)
        for i, rec in enumerate(recs):
            lag = imu_lag(rec.t, datas[i], solve_imu(alone, datas[i]).arrays, "imu_only")
            if lag is not None and lag.significant:
                removed[i] = lag.lag_seconds
                datas[i] = dataclasses.replace(
                    datas[i], Y=shift_magnetometer(rec.t, datas[i].Y, removed[i])
                )
                announce(rec.path, [_shifted(removed[i])], on_warning)
                found.append({**_shifted(removed[i]), "recording": str(rec.path)})
    result = solve_imu(prob, stack_sessions(datas), progress)
    names = [Path(r.path).stem for r in recs]
    lags, path = [], _final_path(result)
    for row, name, rec, data, gone in zip(
        result.info["sessions"], names, recs, datas, removed, strict=True
    ):
        row["name"] = name
        lag = _session_lag(rec, data, result.arrays, row, path)
        lags.append(
            {
                "name": name,
                "removed_seconds": gone,
                "estimate": None if lag is None else lag.to_dict(),
            }
        )
        own = lag_warning(lag, f"the {path} path")
        announce(rec.path, own, on_warning)
        found.extend({**w, "recording": str(rec.path)} for w in own)
    result.info.update(
        name="+".join(names),
        recordings=[str(r.path) for r in recs],
        defaults={
            "rest": pooled.to_dict(),
            "rest_per_recording": [v.to_dict() for v in noises],
            "from_rest": used,
        },
        magnetometer_lag={
            **lag_record(None, None),
            "path": path,
            "auto": mag_lag == "auto",
            "sessions": lags,
        },
    )
    result.info["anchor"]["start"] = "truth"  # each session's first true pose
    result.warnings = found + list(result.warnings or [])
    result.judge()  # again, with each session's rows
    return result
