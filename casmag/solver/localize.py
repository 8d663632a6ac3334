"""Localisation against a saved map: map a place once, localise later recordings in it.

``casmag slam REC --map MAP`` (:func:`localise`) solves the MAP of a recording's path
against a saved map (casmag.gp.savedmap): the kernel, the basis and the hyperparameters are
the map's. Three steps on the NLP of one window structure, the map's box or its tiles
(a tiled map's NLP laid around where each solve's path starts: the tiles' Hessian pattern,
casmag.model.tiledmap):

1. windows over the recording (:func:`locate_windows`), each located against the map held
   at its posterior mean, from where the previous one ended (IPOPT factorises a window's
   path alone): their path starts
2. one solve over the whole recording, the map still held, which estimates the odometry
   bias. The map's own uncertainty enters as magnetometer noise: sigma_m is widened to
   sqrt(sigma_m^2 + s^2), s the RMS of the map's posterior standard deviation along the
   windows' path (``info.localisation.sigma_m_used``, ``map_std_on_path``), so a map that
   knows little does not give a confident path.
3. the map updated by the recording: the same recording solved again from step 2 with the
   map's unknowns free under the saved posterior (mean and dense precision) as their prior
   (block ``map_prior``) and the map's own sigma_m. The map learns where the recording goes
   beyond it, and the path follows. The result's map (``map.npz``) is the updated one, its
   precision marginal over the new path; the position covariance is a mapping run's, with
   the correction for correlated magnetometer residuals. ``update=False`` (``--hold-map``)
   stops after step 2; a failed update keeps step 2's result with a warning.

Measured on the real robot field (a map of sequences 1, 2 and 4 at 0.5 m drift, 3,675 map
unknowns; sequences 3 and 5 at 1.5 m; README): step 2 reaches 0.053 and 0.022 m, step 3
0.010 and 0.011 m, against 0.010 and 0.009 m with all five sessions solved together. The
update's dense prior makes each of its iterations cost about 6 s there; it took 7.

The recording's anchor must be in the map's frame (``SavedMap.frame``; ``casmag slam``'s
default anchors both at the first true pose of recordings with truth). Positions the
estimate puts outside the map's box (or off its tiles), or where the map's posterior
standard deviation is above half its prior's (ground the map never saw), carry no map
information: their share is ``info.localisation.covered`` and below :data:`MIN_COVERED`
the result is flagged ``off_map``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from casmag.data.simulate import Dataset
from casmag.errors import DataError
from casmag.gp.fieldmap import map_grid
from casmag.gp.savedmap import SavedMap, map_from_solution
from casmag.model.translational import WindowStructure
from casmag.problem.spec import Problem
from casmag.result import Result
from casmag.result.evaluation import anchor_info
from casmag.result.metrics import rmse_and_max
from casmag.solver.uncertainty import (
    NotPositiveDefinite,
    laplace_positions,
    magnetometer_correction,
    position_uncertainty,
)
from casmag.solver.windowing import ACCEPTED, continued, window_size, window_starts
from casmag.versions import __version__, versions

OFF_MAP = "Off_Map_Dead_Reckoning"
"""Status of a window that left the map (its box or tiles): kept as its start (the dead reckoning
continued from the previous window), and the next window tries the map again."""

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
        basis=saved.basis_key if saved.tiles is None else None,
        knot_every=min(m.trajectory.knot_every, n - 1),
        constant_field=saved.constant_field,
        estimate_bias=m.odometry.estimate_bias,
        solver=solver.model_dump_json(),
        share_columns=False,
        grid=saved.tiles,
    )


@dataclass
class Located:
    """The windows located against the map: positions (N, d) [m], each sample from the
    last window that committed it (the dead reckoning when ``completed`` is False);
    ``stages`` one record each (as a result's ``stages``); ``completed``: every window
    reached an accepted IPOPT outcome (a window off the map counts, keeping its dead
    reckoning with status :data:`OFF_MAP`). Otherwise the failing window is the last
    record."""

    positions: np.ndarray
    stages: list[dict[str, Any]]
    completed: bool

    @property
    def iterations(self) -> int:
        return sum(st["iterations"] for st in self.stages)


def locate_windows(
    problem: Problem, data: Dataset, s: WindowStructure, overlap: int, mean: np.ndarray
) -> Located:
    """Windows of ``s.n`` samples overlapping by ``overlap``, located in time order against the
    map held at its mean ``mean`` (the plain reduced-rank or tiled NLP with the map's
    unknowns fixed: IPOPT factorises a window's path alone; no bias is estimated in a
    window). Each window starts at the previous one's estimate of its first sample, from the
    previous one's path on the overlap continued by the odometry. A window whose path leaves
    the map (box or tiles) keeps that start (no map information there) and the next one
    tries the map again; any other failure ends the windows."""
    N, n = data.n_samples, s.n
    starts = window_starts(N, n, overlap)
    knots = s.knots
    m = problem.spec.model
    held = ("W", "c") if s.constant_field else ("W",)
    unknowns = s.unknowns(mean)
    last_nlp = None  # the previous window's NLP (a box map's is the same one throughout)
    params = {
        "sigma_o": problem.assumed_sigma_odometry,
        "sigma_anchor": m.anchor.sigma,
        "sigma_m": problem.assumed_sigma_m,
        # the held map's own prior is a constant of the window's cost
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_lin": 1.0,
    }
    P_est = np.full((N, data.dim), np.nan)
    stages: list[dict[str, Any]] = []
    anchor = np.asarray(data.anchor, dtype=float)
    previous: np.ndarray | None = None  # the previous window's path from this start on
    for k, start in enumerate(starts):
        end, nxt = start + n, starts[k + 1] if k + 1 < len(starts) else N
        Q = np.vstack([anchor, anchor + np.cumsum(data.U[start : end - 1], axis=0)])
        P0 = Q if previous is None else continued(previous, Q)
        C0 = knots.fit(Q, P0)
        P0 = knots.positions(Q, C0)
        window = {**params, "Q": Q, "Y": data.Y[start:end], "anchor": anchor.reshape(1, -1)}
        nlp = s.placed(P0).nlp(fixed_map=True)  # a tiled map's laid around the start
        sol = nlp.solve(window, {"C": C0, **unknowns}, fixed=held)
        P, status = knots.positions(Q, sol.x["C"]), sol.status
        if status in ACCEPTED and not s.covers(P):
            P, status = P0, OFF_MAP  # off the map: its start, and the next window tries again
        stages.append(
            {
                "name": "window",
                "start": start,
                "samples": n,
                "status": status,
                "success": sol.success,
                "iterations": sol.iterations,
                "solve_seconds": sol.solve_seconds,
                "build_seconds": 0.0 if nlp is last_nlp else nlp.build_seconds,
                "lengthscale": problem.assumed_lengthscale,
                "bias": None,
            }
        )
        last_nlp = nlp
        if status not in (*ACCEPTED, OFF_MAP):
            return Located(data.dead_reckoning(), stages, False)
        P_est[start:nxt] = P[: nxt - start]
        if nxt < N:
            anchor, previous = P[nxt - start], P[nxt - start :]
    return Located(P_est, stages, True)


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
    update: bool = True,
) -> Result:
    """The path of ``data`` located against ``saved`` (module docstring); the problem gives
    the motion model's settings (odometry noise, knots, bias, anchor, solver), the map its
    kernel and hyperparameters. ``update`` False: the map held (steps 1 and 2 only). A
    failed solve is returned with ``success`` False and IPOPT's status; a failed update
    keeps step 2's result, with a warning."""
    saved.require_posterior(map_source)
    if saved.dim != data.dim:
        raise DataError(
            f"{map_source or 'map'}: a {saved.dim}-D map cannot locate a {data.dim}-D recording"
        )
    if getattr(data, "n_sessions", 1) > 1:
        raise DataError(f"{map_source or 'map'}: localises one recording at a time")
    problem = map_problem(problem, saved)
    m = problem.spec.model
    N = data.n_samples
    started = time.perf_counter()

    # 1. The windows, located against the map from the first on. Windows of a second or
    #    two cannot tell a bias from a shifted map position: the bias is left to the solve
    #    over the whole recording.
    ws, steps = problem.spec.solver.warm_start, np.linalg.norm(data.U, axis=1)
    n, overlap = window_size(ws, steps, problem.assumed_lengthscale, N)
    windows = replace(_structure(problem, data, saved, n), estimate_bias=False)
    sm = locate_windows(problem, data, windows, overlap, saved.mean.reshape(-1, 1))

    # 2. One solve over the whole recording, the map held at its mean, the magnetometer's
    #    noise widened by the map's own uncertainty along the smoother's path.
    s = replace(_structure(problem, data, saved, N), solver=problem.spec.solver.model_dump_json())
    s = s.placed(sm.positions)
    nlp = s.nlp(fixed_map=True)
    knots = s.knots
    U = data.U
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
        "bias_mean": np.zeros((1, data.dim)),
        "bias_precision": np.eye(data.dim) * model_prec,
    }
    x0: dict[str, Any] = {"C": knots.fit(Q, sm.positions), **saved.unknowns()}
    if s.estimate_bias:
        x0["bias"] = np.zeros((1, data.dim))
    held = ("W", "c") if saved.constant_field else ("W",)
    sol = nlp.solve(params, x0, progress=progress, fixed=held)
    solves = [("batch", nlp, sol)]

    # 3. The map updated by the recording: the same recording solved again from step 2 with
    #    the map free under the saved posterior as its prior, sigma_m the map's own.
    updated = None
    if update and sol.success:
        s = s.placed(knots.positions(Q, sol.x["C"]))  # a tiled map's laid where step 2 ended
        nlp_u = s.nlp()
        params_u = {
            **params,
            "sigma_m": saved.sigma_m,
            "map_mean": saved.mean.reshape(-1, 1),
            "map_precision": saved.precision,
        }
        x0_u = {**sol.x, **saved.unknowns()}
        sol_u = nlp_u.solve(
            params_u, {k: x0_u[k] for k in nlp_u.x_layout.entries}, progress=progress
        )
        solves.append(("map_update", nlp_u, sol_u))
        if sol_u.success:
            updated = (nlp_u, sol_u, params_u)
    # the map's mean, its standard deviation (the saved map's where the update's has none:
    # an upper bound, data only shrink it) and the map to write
    mean_map, std_map, new_map = saved, saved, None
    map_record = {"saved": False, "reason": "located against a saved map, held"}
    if updated is not None:
        nlp, sol, params = updated
        mean_map, new_map, map_record = _updated_map(nlp, sol, params, saved, map_source)
        std_map = new_map or saved
    P_est = knots.positions(Q, sol.x["C"])
    bias = sol.x["bias"].ravel() if s.estimate_bias else np.zeros(data.dim)
    seconds = time.perf_counter() - started

    records = [
        {
            "name": name,
            "start": 0,
            "samples": N,
            "status": st.status,
            "success": st.success,
            "iterations": st.iterations,
            "solve_seconds": st.solve_seconds,
            "build_seconds": p.build_seconds,
            "lengthscale": saved.lengthscale,
            "bias": [float(v) for v in st.x["bias"].ravel()] if s.estimate_bias else None,
        }
        for name, p, st in solves
    ]
    P_odo = data.dead_reckoning()
    before = after = (None, None)
    if data.P_true is not None:
        before = rmse_and_max(P_odo, data.P_true)
        if sol.success:
            after = rmse_and_max(P_est, data.P_true)
    arrays, uncertainty, flags, warnings = {}, None, [], []
    on_map = None
    off = [st for st in sm.stages if st["status"] == OFF_MAP]
    if sol.success:
        if not sm.completed:
            last = sm.stages[-1]
            flags.append(
                {
                    "name": "start_lost",
                    "reason": f"the window-by-window location failed at sample {last['start']} "
                    f"({last['status']}): the whole-recording solve started from the dead "
                    "reckoning",
                    "evidence": {"first_sample": last["start"], "status": last["status"]},
                }
            )
        if update and updated is None:
            failed = solves[-1][2]
            warnings.append(
                {
                    "check": "map_update",
                    "column": "",
                    "reason": f"the map update failed ({failed.status}): the result is located "
                    "against the map held at its mean",
                }
            )
        if off:
            warnings.append(
                {
                    "check": "off_map_windows",
                    "column": "",
                    "reason": f"{len(off)} of {len(sm.stages)} windows left the map "
                    f"(first at sample {off[0]['start']}) and kept their dead reckoning",
                }
            )
        on_map = float(covered(saved, P_est).mean())
        flag = off_map_flag(on_map)
        if flag is not None:
            flags.append(flag)
        try:
            if updated is not None:  # the map's unknowns free: as for a mapping run
                sol.x["P"] = P_est
                reuse: dict[str, Any] = {}
                uncertainty, arrays["P_cov"], arrays["P_cov_uninflated"] = laplace_positions(
                    lambda meat: position_uncertainty(
                        nlp,
                        sol,
                        params,
                        knots,
                        data.dim,
                        params["sigma_o"],
                        meat=meat,
                        reuse=reuse,
                    ),
                    lambda: data.Y - mean_map.field(P_est),
                    lambda factors: magnetometer_correction(
                        nlp, sol, s, factors, saved.sigma_m, params
                    ),
                    knots.bounds,
                    saved.sigma_m,
                    problem.spec.solver.uncertainty_inflation,
                    P_est,
                    data.P_true,
                )
            else:
                u = position_uncertainty(nlp, sol, params, knots, data.dim, params["sigma_o"])
                uncertainty = u.summary(P_est, data.P_true)
                uncertainty["inflation"] = {"active": False, "method": "none (plain Laplace)"}
                arrays["P_cov"] = u.cov
        except NotPositiveDefinite as exc:
            uncertainty = {"error": str(exc)}
        arrays["M_estimate"] = mean_map.field(P_est)
        grid, pts = map_grid(P_est, saved.lengthscale)
        shape = (*grid["map_x"].shape, 3)
        arrays.update(
            grid,
            map_field=mean_map.field(pts).reshape(shape),
            map_std=std_map.std(pts).reshape(shape),
            map_prior_std=saved.prior_std(pts).reshape(shape),
        )
    info = {
        "name": problem.name,
        "source": problem.source,
        "n_samples": N,
        "kernel": saved.kernel,
        "gp_form": saved.form,
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
            "windows_off_map": len(off),
            "covered": on_map,
            "sigma_m_used": sigma_m,
            "map_std_on_path": map_std,
            "updated": updated is not None,
            "seconds": seconds,
        },
        "map": map_record,
        "casmag": __version__,
        "versions": versions(),
    }
    return Result(
        info=info,
        status=sol.status,
        success=sol.success,
        flags=flags,
        iterations=sm.iterations + sum(st.iterations for _, _, st in solves),
        build_seconds=sum(p.build_seconds for _, p, _ in solves),
        solve_seconds=sum(st.solve_seconds for _, _, st in solves),
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
        stages=[*sm.stages, *records],
        cost_per_iteration=sol.cost_per_iteration,
        constraint_violation_per_iteration=sol.inf_pr_per_iteration,
        uncertainty=uncertainty,
        warnings=warnings,
        convergence=[st.trace(f"localisation, {name}") for name, _, st in solves],
        arrays={
            "P_odometry": P_odo,
            "P_estimate": P_est,
            "P_true": data.P_true,
            "Y": data.Y,
            **arrays,
        },
        field_map=new_map,
    )


def _updated_map(
    nlp: Any, sol: Any, params: dict[str, Any], saved: SavedMap, source: str
) -> tuple[SavedMap, SavedMap | None, dict[str, Any]]:
    """After the update: the map's mean (the saved map with the solution's weights), the
    updated map (that mean, and the precision marginal over the path,
    casmag.gp.savedmap.map_from_solution; None when it is not positive definite) and the
    record for ``info["map"]``."""
    x = {n: sol.x[n] for n in nlp.x_layout.entries}
    mean = replace(
        saved, mean=np.concatenate([np.ravel(x[n], order="F") for n in ("W", "c") if n in x])
    )
    try:
        basis = saved.basis_key if saved.tiles is None else saved.tiles
        new = map_from_solution(
            nlp, x, params, saved.kernel, basis, saved.hyperparameters(), saved.frame,
            position_dim=saved.dim,
        )  # fmt: skip
        new.cholesky()
    except (np.linalg.LinAlgError, RuntimeError, DataError) as exc:
        reason = f"updated posterior not positive definite ({exc})"
        return mean, None, {"saved": False, "updated_from": source, "reason": reason}
    return new, new, {"saved": True, "updated_from": source}
