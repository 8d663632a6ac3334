"""The library entry points: :func:`solve` a problem, get a :class:`~casmag.result.Result`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from casmag.config import Problem, load_problem
from casmag.metrics import rmse_and_max
from casmag.result import Result
from casmag.simulate import Dataset, simulate_problem
from casmag.slam import HYPERPARAMETERS, field_on_grid, solve_translational


def solve(
    problem: Problem | str | Path | dict[str, Any],
    data: Dataset | None = None,
    progress: Callable[[int, float, float, float], None] | None = None,
) -> Result:
    """Solve a GP-SLAM problem and return its result.

    problem: a Problem, a YAML path or a dictionary (validated with :func:`load_problem`).
    data: the data set to use; simulated from the problem (with its seed) when omitted.
    progress: called after every IPOPT iteration with (iteration, cost, max-norm of the
    step, seconds since the solve started).
    A failed solve is returned with ``success = False`` and IPOPT's ``status``; its error
    fields are None, so a failure is never mistaken for a result.
    """
    problem = load_problem(problem)
    data = simulate_problem(problem) if data is None else data
    sol, nlp, hyper, field, structure = solve_translational(problem, data, progress)

    P_odo = data.dead_reckoning()
    P_est = sol.x["P"]
    before = after = (None, None)
    if data.P_true is not None:
        before = rmse_and_max(P_odo, data.P_true)
        if sol.success:
            after = rmse_and_max(P_est, data.P_true)
    bias = sol.x.get("bias")
    grid_x = grid_y = field_grid = None
    if sol.success:
        grid_x, grid_y = _grid(P_est, problem.assumed_lengthscale)
        pts = np.column_stack([grid_x.ravel(), grid_y.ravel()])
        field_grid = field_on_grid(structure, sol, hyper, pts, problem.spec.model.gp.jitter)
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
        "linear_solver": problem.spec.solver.linear_solver,
        "casmag": __version__,
        "casadi": ca.__version__,
    }
    initial = {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_m": problem.assumed_sigma_m,
    }
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
        odometry_bias_true=None if data.bias_true is None else [float(v) for v in data.bias_true],
        cost_blocks={
            n: {"before": sol.blocks_before[n], "after": sol.blocks_after[n]}
            for n in sol.blocks_before
        },
        cost_per_iteration=sol.cost_per_iteration,
        constraint_violation_per_iteration=sol.inf_pr_per_iteration,
        arrays={
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


def _grid(P: np.ndarray, lengthscale: float, points: int = 90) -> tuple[np.ndarray, np.ndarray]:
    """A square grid over the positions' bounding box plus one lengthscale."""
    lo, hi = P[:, :2].min(axis=0) - lengthscale, P[:, :2].max(axis=0) + lengthscale
    return np.meshgrid(np.linspace(lo[0], hi[0], points), np.linspace(lo[1], hi[1], points))
