"""The library entry points: :func:`solve` a problem, get a :class:`~casmag.result.Result`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from casmag.config import Problem, load_problem
from casmag.errors import ProblemError
from casmag.metrics import rmse_and_max
from casmag.result import Result
from casmag.simulate import Dataset, simulate_problem
from casmag.slam import HYPERPARAMETERS, field_on_grid, solve_translational
from casmag.versions import versions
from casmag.windowing import Stage, continued, solve_growing


def solve(
    problem: Problem | str | Path | dict[str, Any],
    data: Dataset | None = None,
    progress: Callable[[int, float, float, float], None] | None = None,
    initial_positions: np.ndarray | None = None,
) -> Result:
    """Solve a GP-SLAM problem and return its result.

    problem: a Problem, a YAML path or a dictionary (validated with :func:`load_problem`).
    data: the data set to use; simulated from the problem (with its seed) when omitted.
    progress: called after every IPOPT iteration with (iteration, cost, max-norm of the
    step, seconds since the solve started).
    initial_positions: (N, d) start of a plain batch solve (default: the dead reckoning).
    A failed solve is returned with ``success = False`` and IPOPT's ``status``; its error
    fields are None, so a failure is never mistaken for a result.
    """
    problem = load_problem(problem)
    data = simulate_problem(problem) if data is None else data
    ws = problem.spec.solver.warm_start
    stages: list[Stage] = []
    if ws.strategy == "growing" and data.n_samples > ws.first_samples:
        sol, nlp, hyper, field, structure, solved, stages = solve_growing(problem, data, progress)
    elif ws.strategy in ("sliding", "coarse-to-fine"):
        from casmag.sliding import solve_coarse_to_fine, solve_sliding

        staged = solve_sliding if ws.strategy == "sliding" else solve_coarse_to_fine
        sol, nlp, hyper, field, structure, solved, stages = staged(problem, data, progress)
    else:
        sol, nlp, hyper, field, structure = solve_translational(
            problem, data, progress, initial_positions
        )
        solved = data

    P_odo = data.dead_reckoning()
    P_est = sol.x["P"]
    if solved.n_samples < data.n_samples:  # a growing stage failed: not a result
        P_est = continued(P_est, P_odo)
        field = np.vstack([field, np.full((data.n_samples - field.shape[0], 3), np.nan)])
    before = after = (None, None)
    if data.P_true is not None:
        before = rmse_and_max(P_odo, data.P_true)
        if sol.success:
            after = rmse_and_max(P_est, data.P_true)
    bias = sol.x.get("bias")
    uncertainty, cov, cov_plain = _uncertainty(
        problem, nlp, sol, structure, solved, P_est, data.P_true
    )
    grid_x = grid_y = field_grid = None
    if sol.success:
        grid_x, grid_y = _grid(P_est, problem.assumed_lengthscale)
        pts = np.column_stack([grid_x.ravel(), grid_y.ravel()])
        field_grid = field_on_grid(structure, sol, hyper, pts, problem.spec.model.gp.jitter, P_est)
    from casmag import __version__

    info = {
        "name": problem.name,
        "source": problem.source,
        "seed": problem.spec.seed,
        "n_samples": data.n_samples,
        "kernel": problem.assumed_kernel,
        "gp_form": problem.spec.model.gp.form,
        "num_basis": None if structure.basis is None else structure.basis[2],
        "estimated": sorted(problem.spec.model.estimate),
        "estimate_bias": problem.spec.model.odometry.estimate_bias,
        "hessian": problem.spec.solver.hessian,
        "knot_every": problem.spec.model.trajectory.knot_every,
        "warm_start": [st.to_dict() for st in stages],
        "linear_solver": problem.spec.solver.linear_solver,
        "casmag": __version__,
        "casadi": ca.__version__,
        "versions": versions(),
    }
    initial = {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_m": problem.assumed_sigma_m,
    }
    start = sol.stats.get("estimate_start")
    if start is not None:  # the joint MAP's start of its estimated hyperparameters
        info["estimate_start"] = start
        initial.update(start["values"])
    return Result(
        info=info,
        status=sol.status,
        success=sol.success,
        iterations=sol.iterations,
        build_seconds=nlp.build_seconds,
        solve_seconds=sol.solve_seconds,
        rmse_before=before[0],
        max_before=before[1],
        rmse_after=after[0],
        max_after=after[1],
        hyperparameters={h: hyper[h] for h in HYPERPARAMETERS},
        hyperparameters_initial=initial,
        odometry_bias=None if bias is None else [float(v) for v in np.ravel(bias)],
        odometry_bias_true=None
        if data.bias_true is None
        else [float(v) for v in np.ravel(data.bias_true)],
        cost_blocks={
            n: {"before": sol.blocks_before[n], "after": sol.blocks_after[n]}
            for n in sol.blocks_before
        },
        cost_per_iteration=sol.cost_per_iteration,
        constraint_violation_per_iteration=sol.inf_pr_per_iteration,
        uncertainty=uncertainty,
        arrays={
            "P_cov": cov,
            "P_cov_uninflated": cov_plain,
            "P_odometry": P_odo,
            "P_estimate": P_est,
            "P_true": data.P_true,
            "M_estimate": field,
            "Y": data.Y,
            "map_x": grid_x,
            "map_y": grid_y,
            "map_field": None if field_grid is None else field_grid.reshape(*grid_x.shape, 3),
        },
    )


# Largest number of unknowns for which the Laplace covariance is computed (a dense factor
# of the Hessian: 12,000 unknowns take 1.2 GB).
UNCERTAINTY_MAX_UNKNOWNS = 12_000


def _uncertainty(
    problem: Problem,
    nlp: Any,
    sol: Any,
    structure: Any,
    solved: Dataset,
    P_est: np.ndarray,
    P_true: np.ndarray | None,
) -> tuple[dict[str, Any] | None, np.ndarray | None, np.ndarray | None]:
    """Laplace position covariances at the solution (casmag.uncertainty) and their summary
    (mean 1-sigma, NEES against truth); None when switched off or the solve failed. With
    ``solver.uncertainty_inflation`` other than ``none`` the covariance is the sandwich for
    correlated magnetometer residuals; the summary then has ``inflation`` (tau, residual
    RMS and factor per session and component) and ``uninflated`` (the plain Laplace
    summary), and the third value is the plain covariance (else None)."""
    if not (sol.success and problem.spec.solver.uncertainty):
        return None, None, None
    if solved.n_samples != P_est.shape[0]:
        return None, None, None
    from casmag.slam import field_estimate, parameters_and_guess
    from casmag.uncertainty import (
        NotPositiveDefinite,
        magnetometer_correction,
        position_uncertainty,
        residual_inflation,
    )

    if nlp.x_layout.size > UNCERTAINTY_MAX_UNKNOWNS:
        reason = f"{nlp.x_layout.size} unknowns > {UNCERTAINTY_MAX_UNKNOWNS}"
        return {"error": f"not computed: {reason}"}, None, None
    params, _ = parameters_and_guess(problem, solved, structure)
    method = problem.spec.solver.uncertainty_inflation
    sigma_o = problem.assumed_sigma_odometry
    try:
        u0 = position_uncertainty(nlp, sol, params, structure.knots, structure.dim, sigma_o)
        if method == "none":
            return u0.summary(P_est, P_true), u0.cov, None
        R = solved.Y - field_estimate(structure, sol, P_est)
        sigma_m = problem.assumed_sigma_m
        inflation = residual_inflation(R, structure.knots.bounds, sigma_m, method)
        u = u0
        if inflation.active:
            factors = inflation.factors(solved.n_samples)
            meat = magnetometer_correction(nlp, sol, structure, factors, sigma_m)
            u = position_uncertainty(
                nlp, sol, params, structure.knots, structure.dim, sigma_o, meat=meat
            )
    except NotPositiveDefinite as exc:
        return {"error": str(exc)}, None, None
    summary = u.summary(P_est, P_true)
    summary["inflation"] = inflation.to_dict()
    summary["uninflated"] = u0.summary(P_est, P_true)
    return summary, u.cov, u0.cov


def _grid(P: np.ndarray, lengthscale: float, points: int = 90) -> tuple[np.ndarray, np.ndarray]:
    """A square grid over the positions' bounding box plus one lengthscale."""
    lo, hi = P[:, :2].min(axis=0) - lengthscale, P[:, :2].max(axis=0) + lengthscale
    return np.meshgrid(np.linspace(lo[0], hi[0], points), np.linspace(lo[1], hi[1], points))


# --------------------------------------------------------------------------- recordings
KNOT_SECONDS = 1.0
"""Default knot spacing of ``casmag slam`` [s]: one drift-correction knot per second ..."""
LONG_RECORDING = 20_000
LONG_KNOT_SECONDS = 5.0
"""... and one per 5 s above LONG_RECORDING samples: at 64,000 samples (10 Hz) one knot per
second made a 35-million-entry Hessian border (13 GB, stopped after 9 minutes); one per 5 s
solved in 308 s and 2.9 GB with RMSE 8.0 m -> 9.6 mm (make bench-scale)."""

ODOMETRY_NOISE_FRACTION = 0.02
"""Default odometry noise of ``casmag slam``: 2 % of the median step length, per axis."""

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
    overrides: str | tuple[str, ...] | list[str] = (),
) -> tuple[Problem, dict[str, Any]]:
    """The problem ``casmag slam`` solves on a recording, and how its values were chosen.

    Defaults: reduced-rank squared-exponential map with a constant field; sigma_f,
    lengthscale and sigma_m estimated from the data by the windowed marginal likelihood at
    the dead-reckoned positions (casmag.hyper; the windows are short, so their drift is
    small); odometry noise ODOMETRY_NOISE_FRACTION of the median step; one knot per
    KNOT_SECONDS (LONG_KNOT_SECONDS above LONG_RECORDING samples); growing warm starts. A
    problem file (its ``model`` and ``solver`` sections) overrides any of these;
    hyperparameters it leaves null are still estimated.
    """
    from casmag.config import as_overrides, read_yaml
    from casmag.hyper import estimate_hyperparameters, field_evidence, noise_correlation_time

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
            "gp": {"form": "reduced_rank", "kernel": "se"},
            "trajectory": {"knot_every": max(1, round(knot_seconds / dt))},
            "odometry": {"sigma": sigma_o, "estimate_bias": True},
            "anchor": {"sigma": 1.0e-3},
        },
        "solver": {"warm_start": {"strategy": "growing"}},
    }
    merged = _merge(base, user)
    kernel = merged["model"]["gp"].get("kernel") or "se"
    merged["model"]["gp"]["kernel"] = kernel
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
    if (
        merged["model"]["gp"].get("sigma_lin") is None
        and merged["model"]["gp"]["form"] == "reduced_rank"
    ):
        sigma_lin = float(np.abs(data.Y.mean(axis=0)).max() + data.Y.std())
        merged["model"]["gp"]["sigma_lin"] = sigma_lin if sigma_lin > 0 else scale
    how["estimated"] = missing
    return load_problem(merged, overrides, source=source), how


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
    from casmag.errors import DataError

    raise DataError(
        f"{source}: mx, my, mz: the magnetometer is constant (every row the same), so GP-SLAM "
        "has no field to correct the drift with; without --no-field-check the result is the "
        "odometry (Odometry_Only)"
    )


#: Top-level problem keys a recording's problem does not use: its data come from the file.
RECORDING_IGNORES = ("simulation", "seed")


def check_recording_overrides(overrides: list[str]) -> None:
    """Refuse ``--set`` keys a solve on a recording would ignore (ProblemError naming the
    key): the simulation settings and the seed, which only simulated data use."""
    from casmag.config import parse_override

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
    from casmag import __version__
    from casmag.uncertainty import PositionUncertainty

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
    before = after = (None, None)
    if data.P_true is not None:
        before = after = rmse_and_max(P, data.P_true)
    hyper = {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_m": problem.assumed_sigma_m,
    }
    return Result(
        info={
            "name": problem.name,
            "source": problem.source,
            "n_samples": data.n_samples,
            "fallback": reason,
            "casmag": __version__,
            "versions": versions(),
        },
        status="Odometry_Only",
        success=True,
        iterations=0,
        build_seconds=0.0,
        solve_seconds=0.0,
        rmse_before=before[0],
        max_before=before[1],
        rmse_after=after[0],
        max_after=after[1],
        hyperparameters=hyper,
        hyperparameters_initial=dict(hyper),
        odometry_bias=None,
        odometry_bias_true=None
        if data.bias_true is None
        else [float(v) for v in np.ravel(data.bias_true)],
        cost_blocks={},
        cost_per_iteration=[],
        constraint_violation_per_iteration=[],
        uncertainty=summary,
        arrays={
            "P_odometry": P,
            "P_estimate": P,
            "P_true": data.P_true,
            "Y": data.Y,
            "P_cov": None if u is None else u.cov,
        },
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


def solve_from_two_starts(
    problem: Problem,
    data: Dataset,
    progress: Callable[[int, float, float, float], None] | None = None,
) -> Result:
    """:func:`solve` with the growing warm start (``casmag slam``'s default) where that is
    one batch (at most ``solver.warm_start.first_samples`` samples): the batch from the dead
    reckoning and growing prefixes from casmag.multisession.FIRST_PREFIX samples are both
    solved and the start with the lower MAP cost is kept
    (:func:`casmag.multisession.solve_two_starts`); the final solve starts from its positions.
    Neither start is right every time on the real field (sequence 5: the batch reached
    0.012 m at 0.5 m drift where growing stopped at 0.418 m, growing 0.011 m at 1.5 m drift
    where the batch stopped at 0.944 m), and the lower cost picked the right one in both.
    ``info["two_starts"]`` records both starts (``start``, ``cost``, ``kept``); their
    iterations are added to ``iterations``. Other strategies, longer recordings and
    recordings of at most 2 x FIRST_PREFIX samples are solved by :func:`solve` as they are.
    """
    from casmag.multisession import FIRST_PREFIX, solve_two_starts

    ws = problem.spec.solver.warm_start
    if (
        ws.strategy != "growing"
        or data.n_samples > ws.first_samples
        or data.n_samples <= 2 * FIRST_PREFIX
        or data.n_sessions > 1
    ):
        return solve(problem, data, progress)
    P0, starts = solve_two_starts(problem, data)
    batch = problem.with_overrides(["solver.warm_start.strategy=none"])
    result = solve(batch, data, progress, initial_positions=P0)
    result.info["two_starts"] = starts
    result.iterations += sum(st["iterations"] for st in starts)
    return result


def slam(
    recording: str | Path,
    problem: str | Path | None = None,
    overrides: str | tuple[str, ...] | list[str] = (),
    progress: Callable[[int, float, float, float], None] | None = None,
    field_check: bool = True,
) -> Result:
    """GP-SLAM on a recording (CSV, see casmag.recording) with the defaults of
    :func:`recording_problem`. Without truth in the recording the RMSE fields are None.

    field_check: first test whether the field carries position information at all
    (casmag.hyper.field_evidence: windowed marginal likelihood of a GP map against a
    homogeneous field, BIC-penalised, at the dead-reckoned positions). When it does not,
    GP-SLAM has nothing to correct the drift with and can only add error (the paper's Table
    1 at sigma_f = 0.001), so the result is the odometry itself (:func:`odometry_only`),
    with ``info["fallback"]`` saying why. Otherwise the MAP is started twice
    (:func:`solve_from_two_starts`)."""
    from casmag.config import as_overrides
    from casmag.recording import read_recording

    overrides = as_overrides(overrides)
    check_recording_overrides(overrides)
    rec = read_recording(recording)
    data = rec.to_dataset()
    prob, how = recording_problem(data, rec.t, Path(recording).stem, problem, overrides)
    if not field_check and how["field_evidence"].get("constant"):
        refuse_constant_field(recording)
    if field_check and how["field_evidence"]["homogeneous"]:
        result = odometry_only(prob, data, "homogeneous field: " + _evidence_text(how))
    else:
        result = solve_from_two_starts(prob, data, progress)
    result.info["recording"] = str(recording)
    result.info["defaults"] = how
    return result
