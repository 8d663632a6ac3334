"""GP-SLAM on recordings whose magnetometer turns with the body (planar and pose odometry,
:func:`slam_oriented`: the magnetometer's lag, the field check, the model's solve), and the
planar and pose problem files, whose recording is simulated (:func:`solve_oriented`,
casmag.problem.oriented). ``casmag slam`` (casmag.solver.recslam) takes this path for such
recordings; it sits below :mod:`casmag.solver.api`, which solves a problem file of any kind."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from casmag.data.checks import announce, recording_warnings
from casmag.data.clock import LagEstimate, estimate_lag, lag_warning, with_lag_removed
from casmag.data.posesim import simulate_planar, simulate_pose
from casmag.data.recording import Recording
from casmag.errors import DataError
from casmag.gp.savedmap import SavedMap
from casmag.model.planar import dead_reckon_planar
from casmag.problem.imu import (
    STAGED_SOLVER_KEYS,
    load_planar_options,
    refuse_unused_solver_keys,
)
from casmag.problem.oriented import OrientedProblem
from casmag.problem.pose import load_pose_options
from casmag.problem.spec import as_overrides
from casmag.result import Result
from casmag.result.metrics import heading_rms_deg
from casmag.solver.planar import solve_planar_recording, solve_planar_sessions
from casmag.solver.pose import solve_pose_recording, solve_pose_sessions
from casmag.strapdown import dead_reckon_pose
from casmag.versions import __version__, versions

CONSTANT_FIELD = (
    "the magnetometer is constant (every row of mx, my, mz the same), so the field carries "
    "no position information; result is the odometry"
)


def constant_magnetometer(Y: np.ndarray) -> bool:
    """Whether every magnetometer row is the same (to 1e-12 of the largest component)."""
    Y = np.asarray(Y, dtype=float)
    spread = float(np.ptp(Y, axis=0).max()) if Y.size else 0.0
    return spread <= 1e-12 * float(np.abs(Y).max()) if Y.size else True


def refuse_constant_field(source: Any) -> None:
    """A solve forced on a constant magnetometer (no field check): one-line DataError."""
    raise DataError(
        f"{source}: mx, my, mz: the magnetometer is constant (every row the same), so GP-SLAM "
        "has no field to correct the drift with; without --no-field-check the result is the "
        "odometry (Odometry_Only)"
    )


def lag_record(lag: LagEstimate | None, applied: float | None) -> dict[str, Any]:
    """``info["magnetometer_lag"]``: the estimate (on the recording as read, or after a lag
    given with ``mag_lag``) and what was removed."""
    return {"removed_seconds": applied or 0.0, "estimate": None if lag is None else lag.to_dict()}


def _planar_frame(rec: Recording) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """The dead-reckoned path of a planar recording (from the origin) and its body-to-world
    rotations at fractional row numbers (the heading interpolated)."""
    P, psi = dead_reckon_planar(rec.increments, np.zeros(2), 0.0)
    rows = np.arange(psi.size, dtype=float)

    def frame(at: np.ndarray) -> np.ndarray:
        h = np.interp(at, rows, psi)
        c, s = np.cos(h), np.sin(h)
        R = np.zeros((h.size, 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        return R

    return P, frame


def _pose_frame(rec: Recording) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """The dead-reckoned path of a pose recording (from the origin) and its body-to-world
    rotations at fractional row numbers (the orientation interpolated, slerp)."""
    P, Q = dead_reckon_pose(rec.increments, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    rows = np.arange(Q.shape[0], dtype=float)
    slerp = Slerp(rows, Rotation.from_quat(Q[:, [1, 2, 3, 0]]))  # scipy: scalar last

    def frame(at: np.ndarray) -> np.ndarray:
        return slerp(np.clip(at, rows[0], rows[-1])).as_matrix()

    return P, frame


def oriented_lag(rec: Recording) -> LagEstimate | None:
    """The magnetometer lag of a recording whose magnetometer turns with the body, against
    its dead-reckoned path, under the two ways a body-frame field can be late
    (LagEstimate.attitude_lags): turned into the world frame with the dead-reckoned attitude
    of the time each shift moves it to, or of its own row. The one of larger likelihood gain
    is kept. Measured: on the robot sequences converted to planar and pose recordings with
    their recorded timing (``casmag convert --no-align``: a world-frame field turned into
    the body frame at its row) the row's attitude gives 0.24-0.28 s (gains 374-1,230) and
    the lagging attitude 0-0.08 s (gains 0-158); on a simulated turning walk whose body-frame
    magnetometer is 0.3 s late the lagging attitude finds 0.3 s, where the row's attitude
    runs to the end of the range searched (tests/data/test_clock.py)."""
    P, frame = _FRAMES[rec.motion](rec)
    rows = np.arange(P.shape[0], dtype=float)
    own_row = estimate_lag(rec.t, P, np.einsum("nij,nj->ni", frame(rows), rec.Y))
    lagging = estimate_lag(rec.t, P, rec.Y, frame=frame)
    if own_row is None or lagging is None:
        return None
    if lagging.gain >= own_row.gain:
        return dataclasses.replace(lagging, attitude_lags=True)
    return dataclasses.replace(own_row, attitude_lags=False)


def oriented_lag_removed(rec: Recording, lag: LagEstimate) -> Recording:
    """The recording with an estimated lag removed: the body-frame magnetometer shifted in
    time (casmag.data.clock.with_lag_removed) and, when its attitude is its row's own
    (``lag.attitude_lags`` false), turned from the dead-reckoned attitude of the row it
    came from into that of the row it goes to."""
    how = "estimated from the dead reckoning"
    if lag.attitude_lags is False:
        how += ", the attitude its row's own"
    out = with_lag_removed(rec, lag.lag_seconds, how)
    if lag.attitude_lags is False:
        P, frame = _FRAMES[rec.motion](rec)
        rows = np.arange(P.shape[0], dtype=float)
        R = frame(rows)
        Rs = frame(rows + lag.lag_seconds / lag.sample_interval)
        Y = np.einsum("nji,njk,nk->ni", R, Rs, out.Y)  # R_k^T R(k + lag) y
        out = dataclasses.replace(out, Y=Y)
    return out


def slam_oriented(
    rec: Recording,
    problem: str | Path | Mapping[str, Any] | None = None,
    overrides: str | Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, float, float, float], None] | None = None,
    field_check: bool = True,
    on_warning: Callable[[str], None] | None = None,
    anchor: str = "truth",
    mag_lag: float | str | None = None,
    method: str = "map",
    saved: SavedMap | None = None,
    map_source: str = "",
    hold_map: bool = False,
) -> Result:
    """A recording whose magnetometer turns with the body: planar (``dfwd,dleft,dyaw``,
    the planar model with a heading-rate bias, casmag.solver.planar) or pose odometry
    (``dpx,dpy,dpz,dqw,dqx,dqy,dqz``, the pose model, casmag.solver.pose). Settings from the
    problem file's (or mapping's) ``model``/``solver`` sections and ``model.KEY=...`` overrides
    (:class:`casmag.problem.imu.PlanarModelSpec`, :class:`casmag.problem.pose.PoseModelSpec`).
    A constant magnetometer carries no position information: the result is the dead
    reckoning, status ``Odometry_Only`` (with ``field_check`` off, DataError). The
    magnetometer's lag is estimated with the field turned into the map frame along the dead
    reckoning, and reported (``mag_lag``: what was removed before; ``auto``: the estimate
    is removed here when it is significant, as casmag.solver.recslam.slam does for a
    translational recording). ``method``: as for
    :func:`slam`. ``saved``: the recording is located against this saved map (read from
    ``map_source``) and updates it (casmag.solver.planar.solve_planar,
    casmag.solver.pose.solve_pose), or with ``hold_map`` is located against it held."""
    load, odometry_only, solve_recording = _ORIENTED[rec.motion]
    located = (
        {} if saved is None
        else {"prior_map": saved, "map_source": map_source, "hold_map": hold_map}
    )  # fmt: skip
    overrides = as_overrides(overrides)
    refuse_unused_solver_keys(
        overrides, f"casmag slam on a {rec.motion} recording", STAGED_SOLVER_KEYS
    )
    options = load(problem, overrides)
    constant = constant_magnetometer(rec.Y)
    lag = None if constant else oriented_lag(rec)  # a constant field has no lag to find
    removed = None if mag_lag == "auto" else mag_lag
    if mag_lag == "auto" and lag is not None and lag.significant:
        removed = lag.lag_seconds
        rec = oriented_lag_removed(rec, lag)
    found = [
        *rec.notes,
        *recording_warnings(rec.t, rec.increments, rec.Y, rec.motion),
        *(lag_warning(lag) if not removed else []),
    ]
    announce(rec.path, found, on_warning)
    if constant:
        if not field_check:
            refuse_constant_field(rec.path)
        result = odometry_only(rec, anchor)
    else:
        result = solve_recording(
            rec, options, progress=progress, anchor=anchor, method=method, **located
        )
    result.warnings = found
    result.info["magnetometer_lag"] = lag_record(lag, removed)
    a = result.arrays
    if rec.motion == "planar" and a.get("P_true") is not None and a.get("psi_true") is None:
        # True positions without a true heading: the heading column is written empty
        # (NaN), as trajectory.csv has a heading beside every position.
        a["psi_true"] = np.full(a["P_true"].shape[0], np.nan)
    return result


def _constant_field_info(rec: Recording, anchor: dict[str, Any]) -> dict[str, Any]:
    """``info`` of the dead-reckoning result of a recording whose magnetometer is constant."""
    return {
        "name": Path(rec.path).stem,
        "samples": int(rec.n_samples),
        "num_basis": 0,
        "anchor": anchor,
        "fallback": "homogeneous field: " + CONSTANT_FIELD,
        "recording": str(rec.path),
        "casmag": __version__,
        "versions": versions(),
    }


def pose_odometry_only(rec: Recording, anchor: str = "truth") -> Result:
    """The pose dead reckoning as the result of a recording whose magnetometer is constant
    (status ``Odometry_Only``), started where :func:`casmag.solver.pose.solve_pose` starts."""
    P_true = rec.P_true
    if P_true is not None and P_true.shape[1] == 2:
        P_true = np.column_stack([P_true, np.zeros(P_true.shape[0])])
    known = P_true is not None and anchor == "truth"
    p0 = P_true[0] if known else np.zeros(3)
    q0 = rec.q_true[0] if known and rec.q_true is not None else np.array([1.0, 0, 0, 0])
    P, Q = dead_reckon_pose(rec.increments, p0, q0)
    anchor_entry = {
        "kind": "first true position" if known else "origin",
        "position": [float(v) for v in p0],
        "quaternion": [float(v) for v in q0],
    }
    return Result.odometry_only(
        "pose",
        _constant_field_info(rec, anchor_entry),
        P,
        P_true,
        arrays={"t": rec.t, "Q_odometry": Q, "Q_estimate": Q, "Q_true": rec.q_true},
    )


def planar_odometry_only(rec: Recording, anchor: str = "truth") -> Result:
    """The planar dead reckoning as the result of a recording whose magnetometer is constant
    (status ``Odometry_Only``, the reason in ``info.fallback``), started where
    :func:`casmag.solver.planar.solve_planar` starts: the first true pose, else (or with
    ``anchor`` ``origin``) the origin."""
    P_true = None if rec.P_true is None else rec.P_true[:, :2]
    known = P_true is not None and anchor == "truth"
    p0 = P_true[0] if known else np.zeros(2)
    psi0 = float(rec.yaw_true[0]) if known and rec.yaw_true is not None else 0.0
    P, psi = dead_reckon_planar(rec.increments, np.asarray(p0, dtype=float), psi0)
    heading = None
    if P_true is not None and rec.yaw_true is not None:
        heading = heading_rms_deg(psi, rec.yaw_true)
    anchor_entry = {
        "kind": "first true position"
        if known
        else ("origin (no truth)" if P_true is None else "origin"),
        "position": [float(v) for v in p0],
        "heading_rad": psi0,
    }
    return Result.odometry_only(
        "planar",
        _constant_field_info(rec, anchor_entry),
        P,
        P_true,
        arrays={
            "t": rec.t,
            "psi_odometry": psi,
            "psi_estimate": psi,
            "psi_true": rec.yaw_true if P_true is not None else None,
        },
        details={"heading_rms_deg_before": heading, "heading_rms_deg_after": heading},
    )


#: The dead-reckoned path and attitude of a recording whose magnetometer turns with the
#: body, per motion input (:func:`oriented_lag`).
_FRAMES: dict[str, Callable[[Recording], tuple[np.ndarray, Callable]]] = {
    "planar": _planar_frame,
    "pose": _pose_frame,
}

#: The recordings whose magnetometer turns with the body, per motion input: (options
#: loader, dead-reckoning result, solve) for :func:`slam_oriented`.
_ORIENTED: dict[str, tuple[Callable[..., Any], ...]] = {
    "planar": (load_planar_options, planar_odometry_only, solve_planar_recording),
    "pose": (load_pose_options, pose_odometry_only, solve_pose_recording),
}


def simulate_oriented(problem: OrientedProblem) -> tuple[Recording, Any]:
    """The problem's simulated recording (named after the problem and its seed) and the
    simulation (casmag.data.posesim.PlanarRecording or PoseRecording: its true biases)."""
    spec, m = problem.spec, problem.spec.motion
    if m.kind == "planar":
        sim: Any = simulate_planar(
            spec.simulation, spec.seed, m.rate, m.heading_noise, m.heading_bias
        )
    else:
        sim = simulate_pose(
            spec.simulation, spec.seed, m.rate, m.rotation_noise, tuple(m.rate_bias),
            None if m.displacement_bias is None else tuple(m.displacement_bias),
            m.tilt_deg, m.height,
        )  # fmt: skip
    return sim.recording(f"{problem.name}-seed{spec.seed}"), sim


def solve_oriented(
    problem: OrientedProblem,
    progress: Callable[[int, float, float, float], None] | None = None,
    method: str = "map",
) -> Result:
    """Simulate the problem's recording and solve it (module docstring); ``method``:
    ``map`` or the filter baseline ``ekf`` (casmag.solver.recslam.slam). The result's
    ``info`` names the problem (``name``, ``source``, ``seed``, ``simulation``: the motion
    section); the true biases sit beside the estimated ones: ``odometry_bias_true`` (planar:
    the heading-rate bias; pose: the body-frame displacement bias) and, for pose,
    ``details.bias_w_true`` (the rate bias)."""
    rec, sim = simulate_oriented(problem)
    result = slam_oriented(rec, problem.sections, progress=progress, method=method)
    result.info.update(
        name=problem.name,
        source=problem.source,
        seed=problem.spec.seed,
        recording=None,
        simulation={"motion": problem.spec.motion.model_dump(mode="json")},
    )
    if problem.motion == "planar":
        result.odometry_bias_true = [float(sim.bias_w)]
    else:
        result.odometry_bias_true = [float(v) for v in sim.bias_p]
        result.details["bias_w_true"] = [float(v) for v in sim.bias_w]
    return result


def slam_oriented_sessions(
    recs: Sequence[Recording],
    problem: str | Path | Mapping[str, Any] | None = None,
    overrides: str | Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, float, float, float], None] | None = None,
    on_warning: Callable[[str], None] | None = None,
) -> Result:
    """Several planar or pose recordings of one field with one map
    (casmag.solver.planar.solve_planar_sessions, casmag.solver.pose.solve_pose_sessions),
    with :func:`slam_oriented`'s settings and each recording's plausibility warnings
    (``recording`` in each). Recordings of different motion inputs and a constant
    magnetometer are refused (such a recording has no field to share a map of;
    solved alone, its result is the odometry)."""
    motion = recs[0].motion
    for rec in recs:
        if rec.motion != motion:
            raise DataError(
                f"{rec.path}: motion input {rec.motion!r} beside {motion!r} in "
                f"{recs[0].path}: the sessions of one map share one motion model"
            )
    if motion not in _ORIENTED:
        raise DataError(
            f"{recs[0].path}: several sessions with one map take translational, planar or "
            f"pose recordings; the {motion} model solves one recording at a time"
        )
    load, _, _ = _ORIENTED[motion]
    overrides = as_overrides(overrides)
    refuse_unused_solver_keys(overrides, f"casmag slam on {motion} recordings", STAGED_SOLVER_KEYS)
    options = load(problem, overrides)
    found: list[dict[str, Any]] = []
    for rec in recs:
        if constant_magnetometer(rec.Y):
            raise DataError(
                f"{rec.path}: mx, my, mz: the magnetometer is constant (every row the same), "
                "so it has no field to share a map of; solve it alone (its result is the "
                "odometry) or leave it out"
            )
        own = [
            *rec.notes,
            *recording_warnings(rec.t, rec.increments, rec.Y, rec.motion),
            *lag_warning(oriented_lag(rec)),
        ]
        announce(rec.path, own, on_warning)
        found.extend({**w, "recording": str(rec.path)} for w in own)
    solve_sessions = solve_planar_sessions if motion == "planar" else solve_pose_sessions
    result = solve_sessions(list(recs), options, progress)
    result.warnings = found
    return result
