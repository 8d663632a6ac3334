"""GP-SLAM on recordings: the problem ``casmag slam`` solves (its defaults estimated from
the data), the check that the field carries position information, and one recording
(:func:`slam`) or several of the same field with one map (:func:`slam_sessions`).

It sits above :mod:`casmag.solver.api` (one solve) and :mod:`casmag.solver.multisession` (sessions
added one at a time, two starts kept by cost)."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from casmag.data.checks import announce, model_warnings, recording_warnings
from casmag.data.clock import estimate_lag, lag_warning, with_lag_removed
from casmag.data.recording import Recording, read_recording
from casmag.data.simulate import Dataset
from casmag.errors import DataError, ProblemError
from casmag.gp.hyper import estimate_hyperparameters, field_evidence, noise_correlation_time
from casmag.gp.savedmap import SavedMap, load_map
from casmag.model.mapchoice import (
    AUTO,
    TRANSLATIONAL_BOX_FLOPS_LIMIT,
    box_needed,
    choose_map,
)
from casmag.problem.spec import (
    Problem,
    as_overrides,
    load_problem,
    parse_override,
    read_yaml,
    section_overrides,
)
from casmag.result import Result
from casmag.result.evaluation import anchor_info
from casmag.result.metrics import rmse_and_max
from casmag.result.verdict import revisit_pairs
from casmag.solver.api import solve
from casmag.solver.ekf import localise_filter, translational_filter_result
from casmag.solver.imurec import slam_imu, slam_imu_sessions
from casmag.solver.localize import localise
from casmag.solver.multisession import (
    FIRST_PREFIX,
    session_rows,
    solve_recording_starts,
    solve_sessions,
    stack,
)
from casmag.solver.oriented import (
    CONSTANT_FIELD,
    constant_magnetometer,
    lag_record,
    refuse_constant_field,
    slam_oriented,
    slam_oriented_sessions,
)
from casmag.solver.staged import TRUTH_START_RATIO, wrong_basin_flag
from casmag.solver.translational import solve_translational
from casmag.solver.uncertainty import PositionUncertainty
from casmag.versions import __version__, versions

KNOT_SECONDS = 1.0
"""Default knot spacing of ``casmag slam`` [s]: one drift-correction knot per second ..."""
LONG_RECORDING = 20_000
LONG_KNOT_SECONDS = 5.0
"""... and one per 5 s above LONG_RECORDING samples: at 64,000 samples (10 Hz) one knot per
second made a 35-million-entry Hessian border (13 GB, stopped after 9 minutes); one per 5 s
solved in 308 s and 2.9 GB with RMSE 8.0 m -> 9.6 mm (make bench-scale)."""

GROWTH = 2.0
"""Growth of ``casmag slam``'s growing prefixes on a translational recording (4,000, 8,000,
16,000, ... samples; the solver's default growth is 4). Measured on 16,000-sample walks in a
dipole field over 6 x 6 m (casmag.experiments.dipolewalk, 2026-12-01, each run alone),
growth 4 -> 2: seed 1, 0.5 m drift: 161 -> 101 s wall, RMSE 0.0157 -> 0.0134 m (26 -> 14
iterations in the full stage); seed 1, 1.5 m: 159 -> 105 s, 0.0146 -> 0.0142 m; seed 3:
76 -> 61 s, 0.0198 -> 0.0199 m; seed 2 on tiles: 312 -> 389 s, 0.113 m either way (its box,
now chosen: 202 s, 0.017 m at growth 2). Each longer prefix starts closer to its optimum, so
the full problem, the costly one, takes fewer iterations."""

ODOMETRY_NOISE_FRACTION = 0.02
"""Default odometry noise of ``casmag slam``: 2 % of the median step length, per axis."""

#: Where a problem names its map's form.
FORM_PATH = ("model", "gp", "form")

HYPER_PATHS = {
    "sigma_f": ("model", "gp", "sigma_f"),
    "lengthscale": ("model", "gp", "lengthscale"),
    "sigma_m": ("model", "magnetometer", "sigma_m"),
}


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def recording_problem(
    data: Dataset,
    times: np.ndarray,
    name: str,
    problem: str | Path | None = None,
    overrides: str | Sequence[str] | Mapping[str, Any] = (),
    given: Mapping[str, Any] | None = None,
    box_only: str | None = None,
) -> tuple[Problem, dict[str, Any]]:
    """The problem ``casmag slam`` solves on a recording, and how its values were chosen.

    Defaults: reduced-rank squared-exponential map with a constant field; sigma_f,
    lengthscale and sigma_m estimated from the data by the windowed marginal likelihood at
    the dead-reckoned positions (casmag.gp.hyper; the windows are short, so their drift is
    small); odometry noise ODOMETRY_NOISE_FRACTION of the median step; one knot per
    KNOT_SECONDS (LONG_KNOT_SECONDS above LONG_RECORDING samples); growing warm starts,
    prefixes GROWTH times longer. A problem file (its ``model`` and ``solver`` sections)
    overrides any of these; hyperparameters it leaves null (or sets to ``estimate``, as
    for the planar and pose models) are still estimated. ``given``: settings that override
    the problem file's too (a saved map's kernel and hyperparameters).

    The map: unless ``model.gp.form`` is given (or is ``auto``), the box, or the tiles
    with the curl-free kernel (its hyperparameters estimated again) where the box would be
    capped, too costly or over the memory budget (casmag.model.mapchoice; the choice and
    why in ``how["map_choice"]``). A kernel or ``num_basis`` given, sliding windows and
    ``box_only`` (why the caller needs the box: several sessions, a saved map, the
    filter) keep the box.
    """
    overrides = as_overrides(overrides)
    check_recording_overrides(overrides)
    user: dict[str, Any] = {}
    source = name
    if problem is not None:
        user = read_yaml(Path(problem))
        source = str(problem)
        if "simulation" in user:
            raise ProblemError(source, "simulation", "has no meaning for a recording; remove it")
    dt = float(np.median(np.diff(times)))
    knot_seconds = KNOT_SECONDS if data.n_samples <= LONG_RECORDING else LONG_KNOT_SECONDS
    steps = np.linalg.norm(data.U, axis=1)
    sigma_o = max(ODOMETRY_NOISE_FRACTION * float(np.median(steps)), 1e-6)
    base: dict[str, Any] = {
        "seed": 0,
        "name": name,
        "description": f"GP-SLAM on the recording {name}",
        "model": {
            "trajectory": {"knot_every": max(1, round(knot_seconds / dt))},
            "odometry": {"sigma": sigma_o, "estimate_bias": True},
            "anchor": {"sigma": 1.0e-3},
        },
        "solver": {"warm_start": {"strategy": "growing", "growth": GROWTH}},
    }
    merged = _merge(_merge(base, user), dict(given or {}))
    # ``estimate`` (in the file or as --set) means what null means here: from the data.
    from_data = {".".join(path) for path in HYPER_PATHS.values()}
    kept, chosen = [], {}
    for text in overrides:
        key, value = parse_override(text)
        if ".".join(key) in from_data and value == "estimate":
            _set(merged, tuple(key), None)
        elif tuple(key) == FORM_PATH and value == AUTO:
            _set(merged, FORM_PATH, None)
        else:
            kept.append(text)
            chosen[tuple(key)] = value
    overrides = kept
    if _get(merged, FORM_PATH) == AUTO:
        _set(merged, FORM_PATH, None)
    auto_form = _get(merged, FORM_PATH) is None and FORM_PATH not in chosen

    def setting(path: tuple[str, ...]) -> Any:
        """A setting as the problem will hold it: an override's value, else the merged."""
        return chosen[path] if path in chosen else _get(merged, path)

    kernel_given = setting(("model", "gp", "kernel"))
    if auto_form and box_only is None:
        if kernel_given not in (None, "curl_free"):
            box_only = f"model.gp.kernel {kernel_given} given"
        elif setting(("model", "gp", "num_basis")) is not None:
            box_only = "model.gp.num_basis given"
        elif setting(("solver", "warm_start", "strategy")) == "sliding":
            box_only = "sliding windows carry one box"
        elif kernel_given is None and any(
            setting(HYPER_PATHS[h]) not in (None, "estimate") for h in ("sigma_f", "lengthscale")
        ):
            box_only = "sigma_f or lengthscale given for the se kernel"
    for path in HYPER_PATHS.values():
        if _get(merged, path) == "estimate":
            _set(merged, path, None)
    # the tiles take the curl-free kernel unless another was given (as when auto chooses them)
    kernel = kernel_given or ("curl_free" if setting(FORM_PATH) == "tiled" else "se")
    merged["model"].setdefault("gp", {})["kernel"] = kernel
    how: dict[str, Any] = {
        "odometry_sigma": "problem file"
        if user.get("model", {}).get("odometry", {}).get("sigma") is not None
        else f"{ODOMETRY_NOISE_FRACTION:g} x median step"
    }
    missing = [h for h, path in HYPER_PATHS.items() if _get(merged, path) is None]
    scale = float(np.abs(data.Y).max()) or 1.0
    if constant_magnetometer(data.Y):
        # Every row the same: no spread to estimate from (the marginal likelihood's noise
        # goes to 0 and its matrices become singular) and no position information.
        how["field_evidence"] = {"homogeneous": True, "constant": True, "reason": CONSTANT_FIELD}
        how["noise_correlation_samples"] = None
        nominal = {
            "sigma_f": 1e-3 * scale,
            "lengthscale": max(float(np.ptp(data.dead_reckoning(), axis=0).max()), 1e-3),
            "sigma_m": 1e-3 * scale,
        }
        if missing:
            how["marginal_likelihood"] = {"not_estimated": CONSTANT_FIELD, **nominal}
        for h in missing:
            _set(merged, HYPER_PATHS[h], nominal[h])
    else:
        est = estimate_hyperparameters(data.dead_reckoning(), data.Y, kernel)
        if auto_form:
            ell = setting(HYPER_PATHS["lengthscale"]) or est.lengthscale
            every = int(_get(merged, ("model", "trajectory", "knot_every")) or 1)
            choice = choose_map(
                kernel,
                data.dead_reckoning(),
                float(ell),
                (-(-data.n_samples // every) + 2) * data.dim,
                margin=setting(("model", "gp", "margin")),
                memory_budget=setting(("solver", "memory_budget")),
                box_only=box_only,
                flops_limit=TRANSLATIONAL_BOX_FLOPS_LIMIT,
            )
            how["map_choice"] = choice.to_dict()
            _set(merged, FORM_PATH, choice.form)
            if choice.kernel != kernel:  # the tiles' curl-free kernel: its own estimate
                kernel = choice.kernel
                merged["model"]["gp"]["kernel"] = kernel
                est = estimate_hyperparameters(data.dead_reckoning(), data.Y, kernel)
        how["field_evidence"] = field_evidence(data.dead_reckoning(), data.Y, kernel, est).to_dict()
        # Diagnostic: magnetometer residuals correlated over tau samples make a white-noise
        # sigma_m over-confident by about sqrt(tau) (measured on real sequence 5: tau 2.0).
        how["noise_correlation_samples"] = noise_correlation_time(
            data.dead_reckoning(), data.Y, kernel, est
        )
        if missing:
            how["marginal_likelihood"] = {
                "sigma_f": est.sigma_f,
                "lengthscale": est.lengthscale,
                "sigma_m": est.sigma_m,
                "windows": est.n_windows,
                "samples": est.n_samples,
                "converged": est.converged,
            }
            for h in missing:
                _set(merged, HYPER_PATHS[h], getattr(est, h))
    if _get(merged, FORM_PATH) is None:  # no field to choose a map for
        _set(merged, FORM_PATH, "reduced_rank")
    if merged["model"]["gp"].get("sigma_lin") is None and setting(FORM_PATH) in (
        "reduced_rank",
        "tiled",
    ):
        sigma_lin = float(np.abs(data.Y.mean(axis=0)).max() + data.Y.std())
        merged["model"]["gp"]["sigma_lin"] = sigma_lin if sigma_lin > 0 else scale
    how["estimated"] = missing
    return load_problem(merged, overrides, source=source), how


#: Top-level problem keys a recording's problem does not use: its data come from the file.
RECORDING_IGNORES = ("simulation", "seed")


def check_recording_overrides(overrides: list[str]) -> None:
    """Refuse ``--set`` keys a solve on a recording would ignore (ProblemError naming the
    key): the simulation settings and the seed, which only simulated data use."""
    for text in overrides:
        path, _ = parse_override(text)
        if path[0] in RECORDING_IGNORES:
            raise ProblemError(
                "--set",
                ".".join(path),
                f"{path[0]} has no meaning for a recording (its data come from the file); "
                "remove it",
            )


def _evidence_text(how: dict[str, Any]) -> str:
    ev = how["field_evidence"]
    if ev.get("constant"):
        return CONSTANT_FIELD
    return (
        f"log Bayes factor {ev['log_bayes_factor']:.1f} <= 0 for a GP map against a constant "
        "field, so the field carries no position information; result is the odometry"
    )


def odometry_only(problem: Problem, data: Dataset, reason: str) -> Result:
    """The dead reckoning as the result, with its own uncertainty: the anchor plus the
    odometry random walk plus, with a bias prior sigma_b, the bias's drift,
    cov(p_k) = (sigma_anchor^2 + k sigma_o^2 + k^2 sigma_b^2) I. A bias the model takes as
    unknown without a prior makes that unbounded: no covariance, said so."""
    P = data.dead_reckoning()
    sigma_o = problem.assumed_sigma_odometry
    odometry = problem.spec.model.odometry
    k = np.arange(data.n_samples, dtype=float)
    u: PositionUncertainty | None = None
    summary: dict[str, Any]
    if odometry.estimate_bias and odometry.bias_prior_sigma is None:
        summary = {
            "error": "not computed: odometry only with an unknown bias (no "
            "model.odometry.bias_prior_sigma), the position uncertainty is unbounded"
        }
    else:
        sigma_b = odometry.bias_prior_sigma if odometry.estimate_bias else 0.0
        var = problem.spec.model.anchor.sigma**2 + sigma_o**2 * k + (sigma_b * k) ** 2
        u = PositionUncertainty(var[:, None, None] * np.eye(data.dim))
        summary = u.summary(P, data.P_true)
    hyper = problem.assumed_hyperparameters
    return Result.odometry_only(
        "translational",
        {
            "name": problem.name,
            "source": problem.source,
            "n_samples": data.n_samples,
            "anchor": anchor_info(data, problem.spec.model.anchor.sigma),
            "fallback": reason,
            "casmag": __version__,
            "versions": versions(),
        },
        P,
        data.P_true,
        arrays={"Y": data.Y, "P_cov": None if u is None else u.cov},
        hyperparameters=hyper,
        hyperparameters_initial=dict(hyper),
        odometry_bias_true=None
        if data.bias_true is None
        else [float(v) for v in np.ravel(data.bias_true)],
        uncertainty=summary,
    )


def _get(d: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def _set(d: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    for key in path[:-1]:
        d = d.setdefault(key, {})
    d[path[-1]] = value


def solve_from_starts(
    problem: Problem,
    data: Dataset,
    progress: Callable[[int, float, float, float], None] | None = None,
) -> Result:
    """:func:`solve` with the growing warm start (``casmag slam``'s default) where that is
    one batch (at most ``solver.warm_start.first_samples`` samples): the batch from the dead
    reckoning, growing prefixes from casmag.solver.multisession.FIRST_PREFIX samples and,
    where the field's evidence chooses an odometry bias, the batch from the dead reckoning
    with that bias removed (casmag.solver.biasscan) are all solved and the start with the
    lowest MAP cost is kept (:func:`casmag.solver.multisession.solve_recording_starts`,
    casmag.solver.staged.solve_starts); the final solve starts from its positions.
    No start is right every time on the real field (sequence 5: the batch reached 0.012 m
    at 0.5 m drift where growing stopped at 0.418 m, growing 0.011 m at 1.5 m drift where
    the batch stopped at 0.944 m; sequences 2 and 3 at 1.5 m: only the evidence bias reached
    the truth's basin), and the lowest cost picked the right one in each.
    The starts are the first records of ``stages`` (name ``start``, with ``start``,
    ``cost``, ``kept``; the evidence bias's with its ``scan``); their iterations are added
    to ``iterations``. Other strategies, longer recordings and recordings of at most 2 x
    FIRST_PREFIX samples are solved by :func:`solve` as they are.
    """
    ws = problem.spec.solver.warm_start
    if (
        ws.strategy != "growing"
        or data.n_samples > ws.first_samples
        or data.n_samples <= 2 * FIRST_PREFIX
        or data.n_sessions > 1
    ):
        return solve(problem, data, progress)
    P0, starts = solve_recording_starts(problem, data)
    batch = problem.with_overrides(["solver.warm_start.strategy=none"])
    result = solve(batch, data, progress, initial_positions=P0)
    result.stages = starts + result.stages
    result.iterations += sum(st["iterations"] for st in starts)
    result.judge()  # again, with the starts (the verdict's ``starts`` check)
    return result


#: ``mag_lag`` when none is given, per motion input: an IMU recording's clear lag is removed
#: (``auto``, casmag.solver.imurec). Measured (casmag.experiments.imurecbench --lag): with
#: the magnetometer 0.2 s late the rectangle went from 77 mm (IMU-only 131 mm) to 8.1 mm and
#: handwriting from the iteration limit to 3.7 mm; without a lag, on every IMU scenario at
#: seeds 1 and 2, nothing was removed, the same estimates, -2 to +3 s of wall time. The
#: other recordings keep the lag (estimated on the dead reckoning, reported): removing it
#: brought the wrong real-robot estimates further from the truth (README, Recording format).
DEFAULT_MAG_LAG: dict[str, str] = {"imu": "auto"}

#: The estimators of casmag.solver.recslam.slam (``method``): the MAP, or the filter baseline.
METHODS = ("map", "ekf")

#: Where a recording's estimate starts (casmag.solver.recslam.slam's ``anchor``).
ANCHORS = ("truth", "origin")


def slam(
    recording: str | Path,
    problem: str | Path | None = None,
    overrides: str | Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, float, float, float], None] | None = None,
    field_check: bool = True,
    on_warning: Callable[[str], None] | None = None,
    anchor: str = "truth",
    mag_lag: float | str | None = None,
    refit_noise: bool = False,
    map_file: str | Path | None = None,
    method: str = "map",
    hold_map: bool = False,
    **sections: Mapping[str, Any],
) -> Result:
    """GP-SLAM on a recording (CSV, see casmag.data.recording) with the defaults of
    :func:`recording_problem`. Without truth in the recording the RMSE fields are None.

    field_check: first test whether the field carries position information at all
    (casmag.gp.hyper.field_evidence: windowed marginal likelihood of a GP map against a
    homogeneous field, BIC-penalised, at the dead-reckoned positions). When it does not,
    GP-SLAM has nothing to correct the drift with and can only add error (the paper's Table
    1 at sigma_f = 0.001), so the result is the odometry itself (:func:`odometry_only`),
    with ``info["fallback"]`` saying why. Otherwise the MAP is started twice
    (:func:`solve_from_starts`).

    Plausibility checks (casmag.data.checks: time unit, speed, field unit, sigma_m against the
    field's variation, lengthscale against the path) go to ``result.warnings``, and each
    line to ``on_warning`` before the solve.

    A planar recording (``dfwd,dleft,dyaw``) is solved with the planar heading model, a
    pose recording (``dpx,...,dqz``) with the pose model (:func:`slam_oriented`), an IMU
    recording (``dqw,...,dvz``) with the IMU model (casmag.solver.imurec.slam_imu).
    ``sections``: settings as keyword arguments, e.g. ``model={"gp": {"lengthscale":
    0.3}}``, applied after ``overrides`` (:func:`casmag.problem.spec.section_overrides`).

    anchor: where the estimate starts: ``truth`` (default) the first true pose when the
    recording has truth, else the origin; ``origin`` the origin (heading 0) always, the
    odometry's frame (then compare with the truth after an alignment, casmag.result.evaluation).
    ``info["anchor"]`` records which.

    The magnetometer's lag behind the motion is estimated from the dead reckoning
    (casmag.data.clock) and recorded in ``info["magnetometer_lag"]``, with a warning when it is a
    sample or more; ``mag_lag`` [s] removes a lag (``casmag slam --mag-lag``; 0 keeps the
    magnetometer as recorded) before anything else; None: :data:`DEFAULT_MAG_LAG` (``auto``
    for IMU recordings); ``mag_lag="auto"`` removes the estimated one when it is
    ``significant``, the problem made again on the shifted data (every motion model; IMU
    recordings: estimated on the IMU-only adjustment, casmag.solver.imurec.imu_lag; planar
    and pose recordings: with the field turned along the dead-reckoned heading,
    casmag.solver.oriented).
    ``refit_noise`` (translational recordings, sigma_m estimated): estimate sigma_m again
    where the path returns and solve again with it when that is clearly larger
    (:func:`refit_sigma_m`). Neither is the default: together they brought the right
    estimates on the real robot sequences about three times closer and made the wrong ones
    worse (casmag.data.clock, :func:`refit_sigma_m`).

    map_file: a saved map (``map.npz`` of an earlier run, casmag.gp.savedmap; translational,
    planar and pose recordings): the recording is located against it and the map updated by
    it (casmag.solver.localize.localise; ``hold_map``: located against the map held at its
    mean, no update; with ``method`` ``ekf`` by the filter, which also updates the map:
    casmag.solver.ekf.localise_filter; a planar or pose recording by the model's growing
    prefixes on the map held and one solve under the map's posterior,
    casmag.solver.planar.solve_planar, casmag.solver.pose.solve_pose), with the map's
    kernel and hyperparameters, instead of mapped from scratch.

    method: ``map`` (default) the MAP estimate above; ``ekf`` the filter baseline
    (casmag.solver.ekf: an EKF with the same map, hyperparameters and noise in its state,
    translational and planar recordings), for comparison."""
    if method not in METHODS:
        raise DataError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if method != "map" and refit_noise:
        raise DataError(f"method {method}: --refit-noise is for the MAP estimate")
    if hold_map and (map_file is None or method != "map"):
        raise DataError("--hold-map: for the MAP estimate against a saved map (--map)")
    if anchor not in ANCHORS:
        raise DataError(f"anchor: expected one of {', '.join(ANCHORS)}, got {anchor!r}")
    overrides = [*as_overrides(overrides), *section_overrides(sections)]
    check_recording_overrides(overrides)
    if isinstance(mag_lag, str) and mag_lag != "auto":
        raise DataError(f"mag_lag: expected seconds or 'auto', got {mag_lag!r}")
    raw = read_recording(recording)
    if mag_lag is None:
        mag_lag = DEFAULT_MAG_LAG.get(raw.motion)
    auto = mag_lag == "auto"
    rec = with_lag_removed(raw, None if auto else mag_lag)
    saved = None if map_file is None else load_map(map_file)
    if saved is not None:
        saved.require_posterior(str(map_file))
    given = None if saved is None else {"model": _map_model(saved)}
    if rec.motion == "imu":
        if method != "map":
            raise DataError(
                f"{recording}: an IMU recording is solved by the MAP estimate (--method ekf "
                "is for other recordings)"
            )
        refuse_translational_options(recording, refit_noise, rec.motion)
        return slam_imu(
            rec, problem, overrides, progress, field_check, on_warning, anchor, mag_lag, saved,
            "" if map_file is None else str(map_file), hold_map,
        )  # fmt: skip
    if saved is not None and method != "map":
        saved.require_box(str(map_file), f"locate a recording by --method {method}")
    if rec.motion in ("planar", "pose"):
        if saved is not None and method != "map":
            raise DataError(
                f"{map_file}: --method {method} locates translational recordings; a "
                f"{rec.motion} one is located by the MAP estimate"
            )
        refuse_translational_options(recording, refit_noise, rec.motion)
        return slam_oriented(
            rec, problem, overrides, progress, field_check, on_warning, anchor, mag_lag, method,
            saved, "" if map_file is None else str(map_file), hold_map,
        )  # fmt: skip
    data = rec.to_dataset(anchor)
    keep_box = box_needed(1, method, saved is not None)
    prob, how = recording_problem(
        data, rec.t, Path(recording).stem, problem, overrides, given, keep_box
    )
    lag = estimate_lag(rec.t, data.dead_reckoning(), rec.Y, _assumed(prob))
    removed = None if auto else mag_lag
    if auto and lag is not None and lag.significant:
        # --mag-lag auto: a clear lag is removed, the problem made again on the shifted data.
        removed = lag.lag_seconds
        rec = with_lag_removed(raw, removed, "estimated from the dead reckoning")
        data = rec.to_dataset(anchor)
        prob, how = recording_problem(
            data, rec.t, Path(recording).stem, problem, overrides, given, keep_box
        )
    found = _plausibility(rec, data, prob) + (lag_warning(lag) if not removed else [])
    announce(recording, found, on_warning)
    if not field_check and how["field_evidence"].get("constant"):
        refuse_constant_field(recording)
    if saved is not None and method == "ekf":
        result = localise_filter(prob, data, saved, str(map_file), float(np.ptp(rec.t)))
    elif saved is not None:
        result = localise(prob, data, saved, progress, str(map_file), update=not hold_map)
    elif field_check and how["field_evidence"]["homogeneous"]:
        result = odometry_only(prob, data, "homogeneous field: " + _evidence_text(how))
    elif method == "ekf":
        result = translational_filter_result(prob, data, float(np.ptp(rec.t)))
    else:
        result = solve_from_starts(prob, data, progress)
        if refit_noise and "sigma_m" in how["estimated"]:
            result = refit_sigma_m(prob, data, result, progress)
        if anchor == "truth":
            truth_check(prob, data, result)
    result.info["recording"] = str(recording)
    result.info["defaults"] = how
    result.info["magnetometer_lag"] = lag_record(lag, removed)
    result.warnings = found + list(result.warnings or [])
    return result


def _map_cost(result: Result) -> float:
    """A result's MAP cost: the sum of its cost blocks at the solution."""
    return float(sum(b["after"] for b in result.cost_blocks.values()))


def truth_start(prob: Problem, data: Dataset, result: Result) -> tuple[dict[str, Any], Any] | None:
    """A diagnostic that uses the truth (None without it, or when ``result`` failed): the
    same MAP problem, one batch, solved from the true positions. Returns its record (status,
    iterations, seconds and, when it succeeded, its MAP cost, ``cost_above_result``: its
    cost minus the result's, above 0 the model prefers the estimate to the neighbourhood of
    the truth and no start or solver setting can fix the error, below 0 the solve missed a
    better optimum; its RMSE and max error against the truth) and its Solution."""
    if data.P_true is None or not result.success or not result.cost_blocks:
        return None
    batch = prob.with_overrides(["solver.warm_start.strategy=none"])
    t0 = time.perf_counter()
    sol, *_ = solve_translational(batch, data, initial_positions=data.P_true)
    out: dict[str, Any] = {
        "status": sol.status,
        "success": sol.success,
        "iterations": sol.iterations,
        "seconds": time.perf_counter() - t0,
    }
    if sol.success:
        rmse, mx = rmse_and_max(sol.x["P"], data.P_true)
        cost = float(sol.objective)
        out.update(cost=cost, cost_above_result=cost - _map_cost(result), rmse=rmse, max=mx)
    return out, sol


def truth_check(prob: Problem, data: Dataset, result: Result) -> None:
    """With truth (evaluation; the translational counterpart of
    casmag.solver.staged.truth_check, which the planar and pose models run): when ``result``
    succeeded at a position RMSE above TRUTH_START_RATIO of the dead reckoning's,
    :func:`truth_start`; a MAP cost lower there by more than one flags ``wrong_basin``
    (casmag.solver.staged.wrong_basin_flag) and the verdict is made again. The diagnostic
    goes to ``info["truth_start"]``. Measured on the real robot sequences at 1.5 m drift
    (results/real): sequences 2 and 3 ended at 0.76 and 0.72 of the drift with covariances
    that put the truth at a mean NEES of 2,165 and 4,542, trusted; from the truth the same
    problem reaches costs 130 and 195 lower."""
    before, after = result.rmse_before, result.rmse_after
    if before is None or after is None or after <= TRUTH_START_RATIO * max(before, 1e-12):
        return
    made = truth_start(prob, data, result)
    if made is None:
        return
    result.info["truth_start"], sol = made
    flag = wrong_basin_flag(_map_cost(result), sol, data.P_true, after / before)
    if flag is not None:
        result.flags = [*(result.flags or []), flag]
        result.judge()


def _map_model(saved: SavedMap) -> dict[str, Any]:
    """The ``model`` settings a saved map fixes (kernel and hyperparameters)."""
    return {
        "gp": {
            "kernel": saved.kernel,
            "sigma_f": saved.sigma_f,
            "lengthscale": saved.lengthscale,
        },
        "magnetometer": {"sigma_m": saved.sigma_m},
    }


def refuse_translational_options(
    recording: str | Path, refit_noise: bool, motion: str = "planar"
) -> None:
    """DataError for ``refit_noise`` on a recording that is not translational."""
    if refit_noise:
        raise DataError(
            f"{recording}: --refit-noise is for translational recordings; this one is {motion}"
        )


def _assumed(prob: Problem) -> SimpleNamespace:
    return SimpleNamespace(
        sigma_f=prob.assumed_sigma_f,
        lengthscale=prob.assumed_lengthscale,
        sigma_m=prob.assumed_sigma_m,
    )


#: sigma_m is estimated again from the revisits when their noise exceeds this many times the
#: first estimate (:func:`refit_sigma_m`).
REFIT_FACTOR = 1.5
#: Revisit pairs needed for that estimate.
REFIT_MIN_PAIRS = 30


def revisit_noise(
    P: np.ndarray, Y: np.ndarray, M: np.ndarray, lengthscale: float
) -> tuple[float, int]:
    """(noise per magnetometer component that does not repeat where the path returns, pairs):
    RMS over revisit pairs (casmag.result.verdict.revisit_pairs) of the difference of their
    residuals y - m(p), over sqrt(2). The map's own variation between the two samples
    cancels in the difference; what remains is what the same place does not give twice
    (sensor noise, and the errors a white-noise model cannot hold: a tilt, a height, a
    timing error). NaN without pairs."""
    pairs = revisit_pairs(P, lengthscale)
    if pairs.shape[0] == 0:
        return float("nan"), 0
    E = np.asarray(Y, dtype=float) - np.asarray(M, dtype=float)
    d = E[pairs[:, 0]] - E[pairs[:, 1]]
    return float(np.sqrt(np.mean(d**2) / 2.0)), int(pairs.shape[0])


def refit_sigma_m(
    prob: Problem,
    data: Dataset,
    first: Result,
    progress: Callable[[int, float, float, float], None] | None = None,
) -> Result:
    """The magnetometer noise estimated again where the path returns, and the MAP solved
    again from ``first`` with it when it is clearly larger.

    The windowed marginal likelihood (casmag.gp.hyper) sees the noise within a few seconds;
    errors that stay for seconds (the sensor's height and tilt, a timing error) it reads as
    field. Where the path returns, they do not repeat: :func:`revisit_noise` at the first
    estimate measures them. When that exceeds REFIT_FACTOR x sigma_m (on REFIT_MIN_PAIRS
    pairs or more), the problem is solved again from the first estimate's positions with
    sigma_m = the revisit noise, and that result is kept when it succeeds.
    ``info["sigma_m_refit"]`` records the figures and the decision.

    Measured on the real robot sequences (``casmag convert --no-align``, seeds = sequence
    numbers; RMSE before -> after, the default against ``--mag-lag auto --refit-noise``):
    the marginal likelihood gives 0.33-0.77 uT, the revisits 0.8-1.4 uT. At 0.5 m of drift
    sequence 5 0.286 -> 0.069 against 0.021 m, sequence 3 0.293 -> 0.059 against 0.026 m,
    but sequence 2 0.281 -> 0.146 against 0.199 m and sequence 4 0.288 -> 0.27 against
    0.36 m (its lengthscale estimate shrank with the lag removed, 0.21 -> 0.16 m, and the
    run took 8 min); at 1.5 m sequence 5 reached 0.077 m from 0.863 m. Either alone changed
    little (the refit alone: 0.083 and 0.057 m on sequences 5 and 3). From a wrong first
    estimate a softer magnetometer lets the path wander further: a simulated walk with a
    slow magnetometer error went 0.135 -> 0.23 m, and 0.96 m after the refit. Hence not
    the default."""
    rec: dict[str, Any] = {"first": prob.assumed_sigma_m, "factor": REFIT_FACTOR}
    a = first.arrays or {}
    ell = (first.hyperparameters or {}).get("lengthscale")
    if not first.success or a.get("M_estimate") is None or not ell:
        first.info["sigma_m_refit"] = {**rec, "refit": False, "reason": "no estimate"}
        return first
    noise, pairs = revisit_noise(a["P_estimate"], a["Y"], a["M_estimate"], float(ell))
    rec.update(revisit=noise, pairs=pairs)
    if pairs < REFIT_MIN_PAIRS or not noise > REFIT_FACTOR * prob.assumed_sigma_m:
        first.info["sigma_m_refit"] = {**rec, "refit": False}
        return first
    again = prob.with_overrides(
        [f"model.magnetometer.sigma_m={noise!r}", "solver.warm_start.strategy=none"]
    )
    second = solve(again, data, progress, initial_positions=a["P_estimate"])
    rec.update(refit=True, status=second.status, iterations=second.iterations)
    if not second.success:
        first.info["sigma_m_refit"] = {**rec, "kept": "first"}
        return first
    second.iterations += first.iterations
    second.stages = first.stages_named("start") + second.stages
    second.info["sigma_m_refit"] = {**rec, "kept": "refit"}
    return second


def _plausibility(rec: Recording, data: Dataset, prob: Problem) -> list[dict[str, str]]:
    """What reading the recording changed (rows merged or resampled), then casmag.data.checks on
    it and on the lengthscale its problem uses."""
    found = [*rec.notes, *recording_warnings(rec.t, rec.increments, rec.Y, rec.motion)]
    return found + model_warnings(
        data.dead_reckoning(), rec.Y, prob.assumed_lengthscale, prob.assumed_sigma_m
    )


def slam_sessions(
    recordings: Sequence[str | Path],
    problem: str | Path | None = None,
    overrides: str | Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, float, float, float], None] | None = None,
    field_check: bool = True,
    name: str | None = None,
    on_warning: Callable[[str], None] | None = None,
    mag_lag: float | str | None = None,
) -> Result:
    """GP-SLAM on several recordings of the same field with one shared map
    (:func:`slam`'s defaults, computed on all sessions together). The stacked
    result's RMSE is over all samples; ``info["sessions"]`` has each session's. The
    plausibility checks of :func:`slam` run on every recording (``recording`` in each
    warning). Planar and pose recordings are solved with their models' sessions
    (casmag.solver.oriented.slam_oriented_sessions), IMU recordings with the IMU model's
    (casmag.solver.imurec.slam_imu_sessions); recordings of different motion kinds
    together are refused. ``mag_lag``: None (:data:`DEFAULT_MAG_LAG`: each IMU recording's
    clear lag removed), ``auto`` (IMU recordings) or 0 (as recorded); a lag in seconds
    belongs to one recording (DataError)."""
    overrides = as_overrides(overrides)
    check_recording_overrides(overrides)

    recs = [read_recording(r) for r in recordings]
    kinds = {r.motion for r in recs}
    if mag_lag is None and len(kinds) == 1:  # mixed kinds are refused below
        mag_lag = DEFAULT_MAG_LAG.get(recs[0].motion)
    if kinds == {"imu"}:
        return slam_imu_sessions(recs, problem, overrides, progress, on_warning, mag_lag)
    if mag_lag not in (None, 0, 0.0):
        raise DataError(
            f"mag_lag: {mag_lag!r} with several {recs[0].motion} recordings: solve each alone "
            "with --mag-lag (several recordings take it for IMU recordings: auto or 0)"
        )
    if any(r.motion != "translation" for r in recs):
        return slam_oriented_sessions(recs, problem, overrides, progress, on_warning)
    datasets = [r.to_dataset() for r in recs]
    data = stack(datasets)
    label = name or "+".join(Path(r).stem for r in recordings)
    # One time axis for the defaults (the sample period): the sessions end to end.
    times, offset = [], 0.0
    for r in recs:
        times.append(r.t - r.t[0] + offset)
        offset = times[-1][-1] + float(np.median(np.diff(r.t)))
    # The growing warm start cuts prefixes of one trajectory; sessions are one batch.
    prob, how = recording_problem(
        data,
        np.concatenate(times),
        label,
        problem,
        ["solver.warm_start.strategy=none", *overrides] if data.n_sessions > 1 else overrides,
        box_only=box_needed(data.n_sessions, "map", False),
    )
    found = []
    for path, rec, d in zip(recordings, recs, datasets, strict=True):
        own = _plausibility(rec, d, prob)
        announce(path, own, on_warning)
        found.extend({**w, "recording": str(path)} for w in own)
    if prob.spec.model.gp.form != "reduced_rank" and data.n_sessions > 1:
        raise ProblemError(
            prob.source, "model.gp.form", "several sessions need the reduced-rank map"
        )
    if not field_check and how["field_evidence"].get("constant"):
        refuse_constant_field(", ".join(map(str, recordings)))
    if field_check and how["field_evidence"]["homogeneous"]:
        result = odometry_only(prob, data, "homogeneous field: " + _evidence_text(how))
        order = list(range(len(datasets)))
    else:
        result, data, order = solve_sessions(prob, datasets, progress)
    names = [Path(recordings[i]).stem for i in order]
    result.info["recordings"] = [str(recordings[i]) for i in order]
    result.info["defaults"] = how
    result.info["sessions"] = session_rows(data, result, names)
    result.warnings = found
    result.judge()  # again, with each session's errors
    return result
