"""Localisation against a saved map: map a place once, localise later recordings in it.

``casmag slam REC --map MAP`` (:func:`localise`) solves the MAP of a recording's path
against a saved map (casmag.gp.savedmap): the kernel, the basis and the hyperparameters are
the map's, and the map is held at its posterior mean. Two steps, each on the plain
reduced-rank NLP of one window structure with the map's unknowns fixed (IPOPT factorises
the path's knots and the odometry bias alone, so a step costs what the path costs, not
what the map does):

1. the fixed-lag smoother (casmag.solver.sliding) over the recording: each window is
   located against the map from where the previous one ended; its path and odometry bias
   start
2. one solve over the whole recording.

The map's own uncertainty enters as magnetometer noise: sigma_m is widened to
sqrt(sigma_m^2 + s^2), s the RMS of the map's posterior standard deviation along the
smoother's path (``info.localisation.sigma_m_used``, ``map_std_on_path``), so a map that
knows little does not give a confident path. The new recording does not update the map:
the saved precision is dense (n_z x n_z) and as a prior inside the NLP its Hessian block
made a window solve take minutes at the real field's 3,675 unknowns; an update in
low-rank form is not built. The filter (``casmag slam REC --map MAP --method ekf``,
casmag.solver.ekf.localise_filter) carries the map's posterior in its state and does
update it.

The recording's anchor must be in the map's frame (``SavedMap.frame``; ``casmag slam``'s
default anchors both at the first true pose of recordings with truth). Positions the
estimate puts outside the map's box, or where the map's posterior standard deviation is
above half its prior's (ground the map never saw), carry no map information: their share
is ``info.localisation.covered`` and below :data:`MIN_COVERED` the result is flagged
``off_map``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from casmag.data.simulate import Dataset
from casmag.errors import DataError
from casmag.gp.fieldmap import map_grid
from casmag.gp.savedmap import SavedMap
from casmag.model.knots import Knots
from casmag.problem.spec import Problem
from casmag.result import Result
from casmag.result.evaluation import anchor_info
from casmag.result.metrics import rmse_and_max
from casmag.solver.sliding import (
    OFF_MAP,
    WindowStructure,
    auto_window,
    batch_stage,
    fixed_lag_smoother,
    window_nlp,
)
from casmag.solver.uncertainty import NotPositiveDefinite, position_uncertainty
from casmag.versions import __version__, versions

#: Below this share of the estimated path on mapped ground the result is flagged ``off_map``.
MIN_COVERED = 0.5

#: A position is on mapped ground when the map's posterior standard deviation there (mean
#: over the components) is below this fraction of its prior standard deviation.
COVERED_STD_RATIO = 0.5


def map_problem(problem: Problem, saved: SavedMap) -> Problem:
    """The problem with the map's kernel and hyperparameters, none estimated."""
    return problem.with_overrides(
        [
            f"model.gp.kernel={saved.kernel}",
            f"model.gp.sigma_f={saved.sigma_f!r}",
            f"model.gp.lengthscale={saved.lengthscale!r}",
            f"model.magnetometer.sigma_m={saved.sigma_m!r}",
            "model.estimate=[]",
        ]
    )


def _structure(problem: Problem, data: Dataset, saved: SavedMap, n: int) -> WindowStructure:
    m = problem.spec.model
    ws = problem.spec.solver.warm_start
    solver = problem.spec.solver.model_copy(update={"max_iter": ws.window_max_iter})
    return WindowStructure(
        n=n,
        dim=data.dim,
        kernel=saved.kernel,
        basis=saved.basis_key,
        knot_every=min(m.trajectory.knot_every, n - 1),
        constant_field=saved.constant_field,
        estimate_bias=m.odometry.estimate_bias,
        solver=solver.model_dump_json(),
        share_columns=False,
    )


def covered(saved: SavedMap, P: np.ndarray) -> np.ndarray:
    """(n,) whether each position is on mapped ground (module docstring)."""
    ratio = saved.std(P).mean(axis=1) / saved.prior_std(P).mean(axis=1)
    return saved.inside(P) & (ratio < COVERED_STD_RATIO)


def off_map_flag(on_map: float) -> dict[str, Any] | None:
    """The ``off_map`` flag when less than MIN_COVERED of the path is on mapped ground."""
    if on_map >= MIN_COVERED:
        return None
    return {
        "name": "off_map",
        "reason": f"only {on_map:.0%} of the estimated path lies on ground the map has seen "
        f"(limit {MIN_COVERED:.0%}): the rest is dead reckoning",
        "evidence": {"covered": on_map, "limit": MIN_COVERED},
    }


def localise(
    problem: Problem,
    data: Dataset,
    saved: SavedMap,
    progress: Any = None,
    map_source: str = "",
) -> Result:
    """The path of ``data`` located against ``saved`` (module docstring); the problem gives
    the motion model's settings (odometry noise, knots, bias, anchor, solver), the map its
    kernel and hyperparameters. A failed solve is returned with ``success`` False and
    IPOPT's status."""
    if saved.dim != data.dim:
        raise DataError(
            f"{map_source or 'map'}: a {saved.dim}-D map cannot locate a {data.dim}-D recording"
        )
    if getattr(data, "n_sessions", 1) > 1:
        raise DataError(f"{map_source or 'map'}: localises one recording at a time")
    problem = map_problem(problem, saved)
    m = problem.spec.model
    N = data.n_samples
    prior = (saved.mean.reshape(-1, 1), saved.precision)
    started = time.perf_counter()

    # 1. The fixed-lag smoother, located against the map from its first window on.
    n, _ = auto_window(problem, data)
    # Windows of a second or two cannot tell a bias from a shifted map position: the bias
    # is left to the solve over the whole recording.
    windows = replace(_structure(problem, data, saved, n), estimate_bias=False)
    sm = fixed_lag_smoother(problem, data, structure=windows, prior=prior, fixed_map=True)

    # 2. One solve over the whole recording, the map held at its mean, the magnetometer's
    #    noise widened by the map's own uncertainty along the smoother's path.
    s = replace(_structure(problem, data, saved, N), solver=problem.spec.solver.model_dump_json())
    nlp = window_nlp(s, fixed_map=True)
    knots = Knots(N, s.knot_every)
    U = data.U - sm.bias
    anchor = np.asarray(data.anchor, dtype=float).reshape(1, -1)
    Q = np.vstack([anchor, anchor + np.cumsum(U, axis=0)])
    map_std = float(np.sqrt(np.mean(saved.std(sm.positions) ** 2)))
    sigma_m = float(np.hypot(saved.sigma_m, map_std))
    model_prec = 0.0 if m.odometry.bias_prior_sigma is None else m.odometry.bias_prior_sigma**-2
    params = {
        "Q": Q,
        "Y": data.Y,
        "anchor": anchor,
        "sigma_o": problem.assumed_sigma_odometry,
        "sigma_anchor": m.anchor.sigma,
        "sigma_m": sigma_m,
        "sigma_f": saved.sigma_f,
        "lengthscale": saved.lengthscale,
        "sigma_lin": 1.0,
        # the model's prior is on the total bias; the smoother's estimate is already removed
        "bias_mean": -sm.bias.reshape(1, -1),
        "bias_precision": np.eye(data.dim) * model_prec,
    }
    x0: dict[str, Any] = {"C": knots.fit(Q, sm.positions), **saved.unknowns()}
    if s.estimate_bias:
        x0["bias"] = np.zeros((1, data.dim))
    held = ("W", "c") if saved.constant_field else ("W",)
    sol = nlp.solve(params, x0, progress=progress, fixed=held)
    P_est = knots.positions(Q, sol.x["C"])
    bias = sm.bias + (sol.x["bias"].ravel() if s.estimate_bias else 0.0)
    seconds = time.perf_counter() - started

    stage = batch_stage(sol, nlp, N, saved.lengthscale, bias if s.estimate_bias else None)
    P_odo = data.dead_reckoning()
    before = after = (None, None)
    if data.P_true is not None:
        before = rmse_and_max(P_odo, data.P_true)
        if sol.success:
            after = rmse_and_max(P_est, data.P_true)
    arrays, uncertainty, flags, warnings = {}, None, [], []
    on_map = None
    if sol.success:
        off = [st for st in sm.windows if st.status == OFF_MAP]
        if not sm.completed:
            last = sm.windows[-1]
            flags.append(
                {
                    "name": "start_lost",
                    "reason": f"the window-by-window location failed at sample {last.start} "
                    f"({last.status}): the whole-recording solve started from the dead "
                    "reckoning",
                    "evidence": {"first_sample": last.start, "status": last.status},
                }
            )
        if off:
            warnings.append(
                {
                    "check": "off_map_windows",
                    "column": "",
                    "reason": f"{len(off)} of {len(sm.windows)} windows left the map's box "
                    f"(first at sample {off[0].start}) and kept their dead reckoning",
                }
            )
        on_map = float(covered(saved, P_est).mean())
        flag = off_map_flag(on_map)
        if flag is not None:
            flags.append(flag)
        try:
            u = position_uncertainty(nlp, sol, params, knots, data.dim, params["sigma_o"])
            uncertainty = u.summary(P_est, data.P_true)
            uncertainty["inflation"] = {"active": False, "method": "none (plain Laplace)"}
            arrays["P_cov"] = u.cov
        except NotPositiveDefinite as exc:
            uncertainty = {"error": str(exc)}
        arrays["M_estimate"] = saved.field(P_est)
        grid, pts = map_grid(P_est, saved.lengthscale)
        shape = (*grid["map_x"].shape, 3)
        arrays.update(
            grid,
            map_field=saved.field(pts).reshape(shape),
            map_std=saved.std(pts).reshape(shape),
            map_prior_std=saved.prior_std(pts).reshape(shape),
        )
    info = {
        "name": problem.name,
        "source": problem.source,
        "n_samples": N,
        "kernel": saved.kernel,
        "gp_form": "reduced_rank",
        "num_basis": saved.num_basis,
        "estimated": [],
        "estimate_bias": s.estimate_bias,
        "knot_every": s.knot_every,
        "warm_start": "sliding (map prior)",
        "anchor": anchor_info(data, m.anchor.sigma),
        "localisation": {
            "map": map_source,
            "frame": saved.frame,
            "map_unknowns": saved.size,
            "smoother_completed": sm.completed,
            "windows_off_map": sum(st.status == OFF_MAP for st in sm.windows),
            "covered": on_map,
            "sigma_m_used": sigma_m,
            "map_std_on_path": map_std,
            "seconds": seconds,
        },
        "map": {"saved": False, "reason": "located against a saved map, held fixed"},
        "casmag": __version__,
        "versions": versions(),
    }
    return Result(
        info=info,
        status=sol.status,
        success=sol.success,
        flags=flags,
        iterations=sm.iterations + sol.iterations,
        build_seconds=nlp.build_seconds,
        solve_seconds=sol.solve_seconds,
        rmse_before=before[0],
        max_before=before[1],
        rmse_after=after[0],
        max_after=after[1],
        hyperparameters=saved.hyperparameters(),
        hyperparameters_initial=saved.hyperparameters(),
        odometry_bias=[float(v) for v in bias] if s.estimate_bias else None,
        odometry_bias_true=None
        if data.bias_true is None
        else [float(v) for v in np.ravel(data.bias_true)],
        cost_blocks=sol.cost_blocks(),
        stages=[st.to_dict() for st in [*sm.windows, stage]],
        cost_per_iteration=sol.cost_per_iteration,
        constraint_violation_per_iteration=sol.inf_pr_per_iteration,
        uncertainty=uncertainty,
        warnings=warnings,
        convergence=[sol.trace("localisation, final solve")],
        arrays={
            "P_odometry": P_odo,
            "P_estimate": P_est,
            "P_true": data.P_true,
            "Y": data.Y,
            **arrays,
        },
    )
