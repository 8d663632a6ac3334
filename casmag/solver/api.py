"""The library entry points: :func:`solve` a problem, get a :class:`~casmag.result.Result`."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from casmag.data.checks import refuse_simulation_truths
from casmag.data.imusim import ImuData
from casmag.data.simulate import Dataset, simulate_problem
from casmag.errors import ProblemError
from casmag.gp.fieldmap import grid_over
from casmag.gp.localmaps import cached_tiles
from casmag.gp.savedmap import KERNELS, SavedMap
from casmag.model.field import HYPERPARAMETERS, left_map_box
from casmag.model.tiledmap import left_map_tiles
from casmag.model.translational import (
    field_estimate,
    field_on_grid,
    field_std_on_grid,
    parameters,
)
from casmag.problem.imu import ImuProblem, load_imu_problem
from casmag.problem.oriented import OrientedProblem, load_oriented_problem
from casmag.problem.spec import Problem, document_kind, load_problem, read_yaml
from casmag.result import Result
from casmag.result.evaluation import anchor_info
from casmag.result.metrics import rmse_and_max
from casmag.solver.imu import solve_imu
from casmag.solver.oriented import solve_oriented
from casmag.solver.staged import MAP_NOT_YET
from casmag.solver.translational import solve_translational, solve_translational_strategy
from casmag.solver.uncertainty import (
    KNOT_UNCERTAINTY_MAX_UNKNOWNS,
    NotPositiveDefinite,
    laplace_positions,
    magnetometer_correction,
    position_uncertainty,
    saved_field_map,
    without_hessian,
)
from casmag.solver.windowing import continued
from casmag.versions import __version__, versions


def solve(
    problem: Problem | ImuProblem | OrientedProblem | str | Path | dict[str, Any],
    data: Dataset | ImuData | None = None,
    progress: Callable[[int, float, float, float], None] | None = None,
    initial_positions: np.ndarray | None = None,
) -> Result:
    """Solve a GP-SLAM problem and return its result.

    problem: a Problem, a YAML path or a dictionary (validated with :func:`load_problem`).
    A problem of the IMU model (an ImuProblem, or a file or dictionary whose keys say so,
    casmag.problem.spec.document_kind) is solved by :func:`casmag.solver.imu.solve_imu` (a Result
    with ``motion`` imu); a planar or pose problem (an OrientedProblem, or a file or
    dictionary with a ``motion`` section) by :func:`casmag.solver.oriented.solve_oriented`
    (its recording simulated, ``data`` not taken); a table file or a real-data problem file
    is refused naming its entry point.
    data: the data set to use; simulated from the problem (with its seed) when omitted.
    Data not simulated (no ``M_true``, e.g. a recording) need the model's noise and GP
    settings given (or estimated): a null there means "the simulation's value" and is
    refused (ProblemError naming the key; casmag.data.checks.refuse_simulation_truths).
    progress: called after every IPOPT iteration with (iteration, cost, max-norm of the
    step, seconds since the solve started).
    initial_positions: (N, d) start of a plain batch solve (default: the dead reckoning).
    A failed solve is returned with ``success = False`` and IPOPT's ``status``; its error
    fields are None, so a failure is never mistaken for a result.
    """
    source = str(problem) if isinstance(problem, (str, Path)) else None
    if source is not None:  # read once: its keys say which kind it is
        problem = read_yaml(Path(source))
    kind = _kind(problem)
    if kind == "imu":
        return solve_imu(load_imu_problem(problem, source=source), data, progress)
    if kind == "oriented":
        if data is not None or initial_positions is not None:
            raise TypeError(
                "a planar or pose problem simulates its recording: solve a recording of "
                "your own with casmag.slam"
            )
        return solve_oriented(load_oriented_problem(problem, source=source), progress)
    if kind in ("table", "recording"):
        where = (
            "casmag.experiments.sweep (casmag sweep FILE)"
            if kind == "table"
            else "casmag solve FILE"
        )
        raise ProblemError(source or "<dict>", "", f"a {kind} file is not one problem; use {where}")
    problem = load_problem(problem, source=source)
    if data is None:
        data = simulate_problem(problem)
    else:
        refuse_simulation_truths(problem, data)
    ws = problem.spec.solver.warm_start
    stages: list[dict[str, Any]] = []
    if initial_positions is None and (
        ws.strategy in ("coarse-to-fine", "sliding")
        or (ws.strategy == "growing" and data.n_samples > ws.first_samples)
    ):
        sol, nlp, hyper, field, structure, solved, stages = solve_translational_strategy(
            problem, data, progress
        )
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
    grid_x = grid_y = field_grid = std_grid = None
    if sol.success:
        grid_x, grid_y = grid_over(P_est, problem.assumed_lengthscale)
        pts = np.column_stack([grid_x.ravel(), grid_y.ravel()])
        jitter = problem.spec.model.gp.jitter
        field_grid = field_on_grid(structure, sol, hyper, pts, jitter, P_est)
        std_grid = field_std_on_grid(structure, hyper, pts, P_est, jitter)

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
        "warm_start": ws.strategy if stages else "none",
        "linear_solver": problem.spec.solver.linear_solver,
        "anchor": anchor_info(data, problem.spec.model.anchor.sigma),
        "casmag": __version__,
        "casadi": ca.__version__,
        "versions": versions(),
    }
    flags = []
    if sol.success and structure.basis is not None:
        box = left_map_box(structure.basis[0], structure.basis[1], P_est)
        if box is not None:
            flags.append(box)
    if structure.grid is not None:
        tiles = cached_tiles(structure.grid)
        info["tiles"] = {
            "tiles": tiles.num_tiles,
            "per_tile": tiles.per_tile,
            "spacing": structure.grid.spacing,
            "hessian_terms_dropped": int(sol.stats.get("hessian_terms_dropped", 0)),
            "rounds": sol.rounds,  # > 1: laid again around where the samples went
        }
        outside = left_map_tiles(tiles, P_est) if sol.success else None
        if outside is not None:
            flags.append(outside)
    initial = problem.assumed_hyperparameters
    start = sol.stats.get("estimate_start")
    if start is not None:  # the joint MAP's start of its estimated hyperparameters
        info["estimate_start"] = start
        initial.update(start["values"])
    info["map"] = dict(MAP_NOT_YET)

    def map_maker() -> tuple[SavedMap | None, dict[str, Any]]:
        return _field_map(problem, nlp, sol, structure, solved, hyper, info["anchor"])

    return Result(
        info=info,
        status=sol.status,
        success=sol.success,
        flags=flags,
        map_maker=map_maker,
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
        cost_blocks=sol.cost_blocks(),
        stages=stages,
        cost_per_iteration=sol.cost_per_iteration,
        constraint_violation_per_iteration=sol.inf_pr_per_iteration,
        uncertainty=uncertainty,
        convergence=[sol.trace("GP-SLAM, final solve" if stages else "GP-SLAM")],
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
            "map_std": None if std_grid is None else std_grid[0].reshape(*grid_x.shape, 3),
            "map_prior_std": None if std_grid is None else std_grid[1].reshape(*grid_x.shape, 3),
        },
    )


def load_result(folder: str | Path) -> Result:
    """Any saved result folder (result.json, arrays.npz) of any motion model
    (:meth:`casmag.result.Result.load`)."""
    return Result.load(folder)


def _kind(problem: Any) -> str:
    """The document kind of what :func:`solve` was given (casmag.problem.spec.document_kind)."""
    if isinstance(problem, ImuProblem):
        return "imu"
    if isinstance(problem, OrientedProblem):
        return "oriented"
    if isinstance(problem, Mapping):
        return document_kind(problem)
    return "translational"


def _field_map(
    problem: Problem,
    nlp: Any,
    sol: Any,
    structure: Any,
    solved: Dataset,
    hyper: dict[str, float],
    anchor: dict[str, Any],
) -> tuple[SavedMap | None, dict[str, Any]]:
    """The map to save (casmag.gp.savedmap) and a record of it for ``info["map"]``: saved,
    or why not (a failed solve, a map form that has none to save, too many unknowns)."""
    if not sol.success:
        return None, {"saved": False, "reason": "the solve failed"}
    tiled = structure.form == "tiled"
    if not (tiled or structure.form == "reduced_rank") or structure.kernel not in KERNELS:
        form = f"{structure.form} ({structure.kernel})"
        return None, {"saved": False, "reason": f"no reduced-rank map to save: {form}"}
    params = parameters(problem, solved, structure)
    frame = f"anchored at the {anchor['kind']}: {anchor['position']} (sigma {anchor['sigma']} m)"
    return saved_field_map(
        nlp, sol, params, structure.kernel, structure.grid if tiled else structure.basis,
        hyper, frame, position_dim=solved.dim,
    )  # fmt: skip


def _uncertainty(
    problem: Problem,
    nlp: Any,
    sol: Any,
    structure: Any,
    solved: Dataset,
    P_est: np.ndarray,
    P_true: np.ndarray | None,
) -> tuple[dict[str, Any] | None, np.ndarray | None, np.ndarray | None]:
    """Laplace position covariances at the solution (casmag.solver.uncertainty) and their summary
    (mean 1-sigma, NEES against truth); None when switched off or the solve failed. With
    ``solver.uncertainty_inflation`` other than ``none`` the covariance is the sandwich for
    correlated magnetometer residuals; the summary then has ``inflation`` (tau, residual
    RMS and factor per session and component) and ``uninflated`` (the plain Laplace
    summary), and the third value is the plain covariance (else None)."""
    if not (sol.success and problem.spec.solver.uncertainty):
        return None, None, None
    if solved.n_samples != P_est.shape[0]:
        return None, None, None

    if nlp.x_layout.size > KNOT_UNCERTAINTY_MAX_UNKNOWNS:
        reason = f"{nlp.x_layout.size} unknowns > {KNOT_UNCERTAINTY_MAX_UNKNOWNS}"
        return {"error": f"not computed: {reason}"}, None, None
    if (missing := without_hessian(nlp)) is not None:
        return missing, None, None
    params = parameters(problem, solved, structure)
    sigma_o, sigma_m = problem.assumed_sigma_odometry, problem.assumed_sigma_m
    knots, dim = structure.knots, structure.dim

    def correction(factors: np.ndarray) -> np.ndarray:
        return magnetometer_correction(nlp, sol, structure, factors, sigma_m, params)

    reuse: dict[str, Any] = {}  # the plain covariance's solve, read again by the sandwich
    try:
        return laplace_positions(
            lambda meat: position_uncertainty(
                nlp, sol, params, knots, dim, sigma_o, meat=meat, reuse=reuse
            ),
            lambda: solved.Y - field_estimate(structure, sol, P_est),
            correction,
            knots.bounds,
            sigma_m,
            problem.spec.solver.uncertainty_inflation,
            P_est,
            P_true,
        )
    except NotPositiveDefinite as exc:
        return {"error": str(exc)}, None, None
