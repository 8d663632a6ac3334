"""The solve of the planar model (casmag.model.planar) from arrays (:func:`solve_planar`)
and from a recording (:func:`solve_planar_recording`): the model as a
:class:`casmag.solver.staged.StagedModel` (:class:`PlanarStaged`), whose warm starts and
heading-bias starts casmag.solver.staged runs; hyperparameters from the data, the
wrong-basin check, the result."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from casmag import strapdown as sd
from casmag.data.recording import Recording, read_recording
from casmag.errors import DataError
from casmag.gp.fieldmap import map_arrays, tiled_map_arrays, unwhitened
from casmag.gp.hyper import estimate_hyperparameters
from casmag.gp.savedmap import SavedMap
from casmag.model.field import BoxOrTiles, left_map_box
from casmag.model.mapchoice import AUTO, MapChoice, box_needed, resolve_options
from casmag.model.planar import (
    PlanarStructure,
    cached_planar_nlp,
    dead_reckon_planar,
    dead_reckon_sessions,
    displacement_bias_coupling,
)
from casmag.model.rotated import ridge_weights, rotated_design, whiten
from casmag.model.rrmap import make_basis
from casmag.model.tiledmap import home_points, left_map_tiles, ridge_tile_weights, tile_grid
from casmag.nlp import Progress
from casmag.problem.imu import PlanarOptions
from casmag.problem.spec import SolverSpec
from casmag.result import Result
from casmag.result.metrics import heading_rms_deg, rmse_and_max
from casmag.solver.biasscan import heading_start
from casmag.solver.ekf import FilterMap, PlanarNav, filter_result, run_safely
from casmag.solver.localize import covered, off_map_flag
from casmag.solver.sessions import (
    Stacked,
    check_starts,
    require_first_poses,
    revisit_order,
    session_errors,
)
from casmag.solver.staged import (
    MAP_NOT_YET,
    PriorMap,
    Solved,
    StagedMap,
    StagedModel,
    StageProblem,
    Window,
    WindowPrior,
    anchored_at_truth,
    displacement_bias_sigma,
    heading_bias_starts,
    lattice_field,
    map_lengthscale,
    record_consider,
    solve_staged,
    truth_check,
    uncertainty,
)
from casmag.versions import versions

#: Keyframes per marginal-likelihood window and the most windows of the planar
#: recordings' hyperparameters (the values their figures were measured with).
PLANAR_HYPER_WINDOW = (30, 16)


def solve_planar(
    dfwd: np.ndarray,
    dleft: np.ndarray,
    dyaw: np.ndarray,
    mag: np.ndarray,
    options: PlanarOptions | None = None,
    truth: dict[str, np.ndarray] | None = None,
    t: np.ndarray | None = None,
    p0: np.ndarray | None = None,
    psi0: float = 0.0,
    progress: Progress | None = None,
    name: str = "planar",
    method: str = "map",
    starts: tuple[int, ...] = (0,),
    session_names: list[str] | None = None,
    prior_map: SavedMap | None = None,
    map_source: str = "",
    hold_map: bool = False,
) -> Result:
    """Planar odometry with heading plus magnetometer GP-SLAM from arrays.

    dfwd, dleft (N-1,) [m], dyaw (N-1,) [rad]: increments between samples; mag (N, 3):
    magnetometer in the heading-rotated body frame (tilt removed); t (N,) [s] (default one
    second per sample: the bias is then per step); p0 (2,), psi0: known start (default the
    truth's when given, else the origin and 0). truth: optional ``P`` (N, 2) and ``psi``
    (N,) for evaluation only.

    Solved from ``options.starts`` starts, keeping the lowest MAP cost: the dead reckoning
    (bias 0) and dead reckonings with a heading-rate bias b removed, b = +-k delta,
    delta turning the heading by ``options.start_heading_deg`` over the recording. One start
    (the dead reckoning) is the default: on the 186-sample loop walk, seeds 1-5, three starts
    lowered the MAP cost on seeds 1, 2 and 4 but the RMSE ratio only on seed 1 (0.34 ->
    0.18; seed 2 0.17 -> 0.21, seed 4 0.09 -> 0.20; two loops, seed 1: 0.29 -> 0.42): the
    lower-cost optimum of this model is not reliably nearer the truth. Each start runs the
    strategy of ``options.solver.warm_start`` (casmag.solver.staged: one batch, growing
    prefixes or coarse-to-fine).

    method: ``map`` (default) the MAP estimate; ``ekf`` the filter baseline with the same
    map box, hyperparameters and noise (casmag.solver.ekf; the box map only).

    starts: several sessions of one field stacked end to end, one map (the first sample of
    each; the increments before a session's first sample, and its time step, are not
    read): each has its own known start (rows of p0 (S, 2) and psi0 (S,), by default the
    truth's at its first sample) and heading-rate bias, and they are added one at a time
    in the given order (casmag.solver.staged.solve_sessions; solve_planar_sessions orders
    recordings first). ``info["sessions"]`` has each session's errors, named
    ``session_names``.

    prior_map: locate the recording against a saved 2-D map (casmag.gp.savedmap, read from
    ``map_source``) and update it: its box or tiles, kernel and hyperparameters, its
    posterior as the prior of the map (:func:`localisation_options`);
    ``info["localisation"]`` says how much of the estimate lies on ground the map has seen
    (casmag.solver.localize.covered), flagged ``off_map`` below half. The result's map is
    the updated one. ``hold_map``: the map held at its mean in every solve (the whole
    recording's with sigma_m widened by the map's standard deviation along the path,
    casmag.solver.staged.PriorMap.held_noise), not updated, and no map written."""
    options = options or PlanarOptions()
    if prior_map is not None:
        options = localisation_options(options, prior_map, map_source)
    U = np.column_stack([dfwd, dleft, dyaw]).astype(float)
    Y = np.asarray(mag, dtype=float)
    n = Y.shape[0]
    if U.shape != (n - 1, 3):
        raise ValueError(f"increments must have N-1 = {n - 1} rows, got {U.shape[0]}")
    starts = check_starts(starts, n)
    S = len(starts)
    ends = [*starts[1:], n]
    if S > 1 and method != "map":
        raise DataError(f"method {method}: one session at a time (several sessions: map)")
    if prior_map is not None and (S > 1 or method != "map"):
        raise DataError(f"{map_source or 'map'}: one recording is located by the MAP estimate")
    dt = np.ones(n - 1) if t is None else np.diff(np.asarray(t, dtype=float))
    if S > 1:  # the step into a session is not read; a positive value keeps the NLP finite
        dt[[a - 1 for a in starts[1:]]] = 1.0
    anchor_kind = "given"
    first = list(starts)
    if p0 is None:
        p0 = truth["P"][first] if truth is not None else np.zeros((S, 2))
        psi0 = truth["psi"][first] if truth is not None and "psi" in truth else psi0
        anchor_kind = "first true position" if truth is not None else "origin (no truth)"
    anchors = np.column_stack(
        [np.reshape(np.asarray(p0, float), (S, 2)), np.broadcast_to(np.ravel(psi0), (S,))]
    )
    p0, psi0 = anchors[0, :2], float(anchors[0, 2])
    P_dr, psi_dr = dead_reckon_sessions(U, anchors, starts)
    Y_local = sd.rotate(sd.quat_from_euler(0.0 * psi_dr, 0.0 * psi_dr, psi_dr), Y)
    options, choice, hyper = hyperparameters_and_map(
        options, P_dr, Y_local, 3 * n, box_needed(S, method, prior_map is not None)
    )
    sigma_f, ell, sigma_m, sigma_lin, estimated = hyper

    if method == "ekf":
        s = planar_structure(options, n, P_dr, float(ell), options.solver)
        if s.tiled:
            raise DataError("model.gp.form: the filter baseline needs the box map (reduced_rank)")
        nav = PlanarNav(
            U, dt, np.array([p0[0], p0[1], psi0]), options.sigma_disp, options.sigma_dyaw,
            options.sigma_anchor, options.sigma_psi0, options.bias_prior,
            options.bias_walk if options.bias == "random_walk" else 0.0,
        )  # fmt: skip
        fmap = FilterMap(
            s.hilbert_basis(), options.kernel, float(sigma_f), float(ell), sigma_m, sigma_lin
        )
        heading = None if truth is None else truth.get("psi")
        run = run_safely(nav, fmap, Y)
        result = filter_result(
            nav, fmap, Y, P_dr, None if truth is None else truth["P"],
            {"name": name, "samples": int(n), "bias_model": options.bias,
             "anchor": {"kind": anchor_kind, "position": [float(v) for v in p0],
                        "heading_rad": float(psi0), "sigma": options.sigma_anchor}},
            motion="planar", run=run, duration=None if t is None else float(np.ptp(t)),
        )  # fmt: skip
        psi = None if run is None else run.states[:, 2]
        result.arrays.update(
            t=np.arange(n, dtype=float) if t is None else np.asarray(t, dtype=float),
            psi_odometry=psi_dr,
            psi_estimate=psi,
            psi_true=None if heading is None else np.asarray(heading, dtype=float),
        )
        if heading is not None:
            result.details["heading_rms_deg_before"] = heading_rms_deg(psi_dr, heading)
            if psi is not None:
                result.details["heading_rms_deg_after"] = heading_rms_deg(psi, heading)
        return result
    model = PlanarStaged(
        options, U, dt, Y, p0, psi0, P_dr, Y_local.mean(axis=0), sigma_m, float(sigma_f),
        float(ell), sigma_lin, progress, starts, anchors,
        None if prior_map is None else PriorMap.of(prior_map, held=hold_map),
    )  # fmt: skip
    ws = options.solver.warm_start
    duration = float(dt[: ends[0] - 1].sum())  # of the first session: its starts' biases
    biases = heading_bias_starts(options.starts, options.start_heading_deg, duration)
    scan = heading_start(
        model, duration, options.kernel, (sigma_f, ell, sigma_m),
        prior_map is not None or not options.solver.warm_start.evidence,
    )  # fmt: skip
    # one more start, one batch: the heading-rate bias of the field's evidence
    staged, strategy = solve_staged(model, ws, biases, None if scan is None else scan.bias)
    final = staged.final
    sol, nlp, s = final.sol, final.nlp, final.structure
    hyper = {"sigma_f": float(sigma_f), "lengthscale": float(ell), "sigma_m": sigma_m}
    flags: list[dict[str, Any]] = []
    if truth is not None and "psi" in truth:
        true_states = {"P": np.asarray(truth["P"], float), "psi": np.asarray(truth["psi"], float)}
        true_first = np.column_stack([true_states["P"][first], true_states["psi"][first]])
        flag = (
            truth_check(model, final, true_states, truth["P"], P_dr)
            if anchored_at_truth(anchors, true_first)
            else None
        )
        if flag is not None:
            flags.append(flag)
    if sol.success:
        if s.tiled:
            box = left_map_tiles(s.tiles(), sol.x["P"])
        else:
            basis = s.hilbert_basis()
            box = left_map_box(basis.domain.center, basis.domain.half_width, sol.x["P"])
        if box is not None:
            flags.append(box)
    P_true = None if truth is None else np.asarray(truth["P"], dtype=float)
    sigma_b = displacement_bias_sigma(U[:, :2], options.displacement_bias, starts)
    u_summary, P_cov, P_cov_plain = uncertainty(
        final, P_true, model.final_sigma_m(sigma_m), options.solver,
        None if sigma_b is None
        else lambda f: displacement_bias_consider(f, U, options.sigma_disp, sigma_b, starts),
    )  # fmt: skip
    record_consider(u_summary, sigma_b, options.displacement_bias)
    before = after = (None, None)
    hb_deg = ha_deg = None
    if truth is not None:
        before = rmse_and_max(P_dr, truth["P"])
        if "psi" in truth:
            hb_deg = heading_rms_deg(psi_dr, truth["psi"])
        if sol.success:
            after = rmse_and_max(sol.x["P"], truth["P"])
        if sol.success and "psi" in truth:
            ha_deg = heading_rms_deg(sol.x["psi"], truth["psi"])
    result = Result(
        motion="planar",
        flags=flags,
        status=sol.status,
        success=sol.success,
        iterations=sol.iterations,
        build_seconds=nlp.build_seconds,
        solve_seconds=sum(so.sol.solve_seconds for so in staged.solves),
        rmse_before=before[0],
        max_before=before[1],
        rmse_after=after[0],
        max_after=after[1],
        details={"heading_rms_deg_before": hb_deg, "heading_rms_deg_after": ha_deg},
        odometry_bias=[float(v) for v in sol.x["bias"].ravel()] if sol.success else None,
        hyperparameters=hyper,
        cost_blocks=sol.cost_blocks(),
        # each start's strategy (growing prefixes, coarse-to-fine, one batch); one kept
        stages=staged.records(),
        cost_per_iteration=sol.cost_per_iteration,
        uncertainty=u_summary,
        info={
            "name": name,
            "samples": int(n),
            "num_basis": s.map_unknowns,
            "map": {**structure_map_info(s), **MAP_NOT_YET},
            "anchor": {
                "kind": anchor_kind,
                "position": [float(v) for v in p0],
                "heading_rad": float(psi0),
                "sigma": options.sigma_anchor,
                **({"sessions": [[float(v) for v in row] for row in anchors]} if S > 1 else {}),
            },
            "bias_model": options.bias,
            "kernel": options.kernel,
            **hyperparameter_info(estimated, sigma_lin, options.sigma_lin is not None),
            "warm_start": strategy,
            "bias_scan": None if scan is None else scan.to_dict(),
            **({} if choice is None else {"map_choice": choice.to_dict()}),
        },
        convergence=[sol.trace("GP-SLAM")],
        arrays={
            **(structure_map_arrays(s, options.kernel, hyper, sol) if sol.success else {}),
            "t": np.arange(n, dtype=float) if t is None else np.asarray(t, dtype=float),
            "P_odometry": P_dr,
            "psi_odometry": psi_dr,
            "P_estimate": sol.x["P"],
            "P_cov": P_cov,
            "P_cov_uninflated": P_cov_plain,
            "psi_estimate": sol.x["psi"].ravel(),
            "P_true": None if truth is None else truth["P"],
            "psi_true": None
            if truth is None or "psi" not in truth
            else np.asarray(truth["psi"], dtype=float),
        },
    )
    if S > 1:
        bounds = list(zip(starts, ends, strict=True))
        names = session_names or [f"session {i + 1}" for i in range(S)]
        biases = (
            [model.session_bias(sol.x["bias"], i, a, e) for i, (a, e) in enumerate(bounds)]
            if sol.success
            else None
        )
        P_true = None if truth is None else np.asarray(truth["P"], float)
        result.info["sessions"] = session_errors(bounds, result, names, P_true, biases)
    frame = (
        f"anchored at the {anchor_kind}: {[float(v) for v in p0]}, heading {float(psi0)} rad "
        f"(sigma {options.sigma_anchor} m)"
    )
    result.map_maker = StagedMap(final, options.kernel, hyper, frame, structure_map_info(s), 2)
    if prior_map is not None:
        P_located = sol.x["P"] if sol.success else None
        located(result, prior_map, map_source, P_located, hold_map, model.noise_on_held_map)
    return result


def localisation_options(options: Any, saved: SavedMap, source: str, motion: str = "planar") -> Any:
    """The options (PlanarOptions, or the pose model's with ``motion`` ``pose``) of a
    recording located against a saved map: its kernel and hyperparameters, none estimated,
    and (pose) its dimension. The box or tiles are the saved map's (the staged model's
    ``prior_map``); the warm start stays the model's (growing prefixes by default: each
    prefix is located against the saved map, not against what the recording alone would
    map)."""
    where = source or "map"
    saved.require_posterior(where)
    if motion == "planar" and saved.dim != 2:
        raise DataError(f"{where}: a {saved.dim}-D map cannot locate a planar recording")
    form = getattr(options, "form", "reduced_rank")
    if form not in (saved.form, AUTO):
        raise DataError(
            f"{where}: model.gp.form {form}: a recording is located on the saved map, "
            f"which is {'tiled' if saved.tiles is not None else 'one box (reduced_rank)'}"
        )
    changes: dict[str, Any] = {
        "form": saved.form,
        "kernel": saved.kernel, "sigma_f": saved.sigma_f, "lengthscale": saved.lengthscale,
        "sigma_m": saved.sigma_m,
    }  # fmt: skip
    if motion == "pose":
        changes["map_dim"] = saved.dim
    return dataclasses.replace(options, **changes)


def _updated_from(maker: Callable[[], tuple[Any, dict[str, Any]]], source: str) -> tuple:
    """A result's map maker whose record (``info["map"]``) names the map it updated."""
    field_map, record = maker()
    return field_map, {**record, "updated_from": source}


def located(
    result: Result, saved: SavedMap, source: str, P: np.ndarray | None, held: bool = False,
    noise: tuple[float, float] | None = None,
) -> None:  # fmt: skip
    """``info["localisation"]`` (the map, its frame and size, the share of the estimate on
    ground it has seen, whether the map was ``updated``) and ``info["map"]["updated_from"]``
    of a result located against a saved map; the ``off_map`` flag when that share is below
    half. ``held`` (``--hold-map``): no map is written; ``noise``: the widened sigma_m and
    the map's std along the path it was widened by (casmag.solver.staged.PriorMap.held_noise;
    None when the whole recording's solve was not reached)."""
    on_map = None if P is None else float(covered(saved, P[:, : saved.dim]).mean())
    result.info["localisation"] = {
        "map": source, "frame": saved.frame, "map_unknowns": saved.size, "covered": on_map,
        "updated": not held,
    }  # fmt: skip
    if held:
        if noise is not None:
            result.info["localisation"].update(sigma_m_used=noise[0], map_std_on_path=noise[1])
        form = result.map_maker.form if isinstance(result.map_maker, StagedMap) else {}
        result.map_maker = None  # the saved map, unchanged: nothing new to write
        result.info["map"] = {**form, "saved": False, "reason": "located against a saved map, held"}
    else:
        result.info["map"]["updated_from"] = source
    if isinstance(result.map_maker, StagedMap):  # the updated map, in the saved map's frame
        form = {**result.map_maker.form, "updated_from": source}
        result.map_maker = dataclasses.replace(result.map_maker, frame=saved.frame, form=form)
    elif result.map_maker is not None:  # the IMU model's (its frame already the saved map's)
        result.map_maker = functools.partial(_updated_from, result.map_maker, source)
    flag = None if on_map is None else off_map_flag(on_map)
    if flag is not None:
        result.flags.append(flag)


def _anchor_state(anchor: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
    return np.asarray(anchor["P"])[0], float(np.ravel(anchor["psi"])[0])


def planar_structure(
    options: PlanarOptions,
    k: int,
    around: np.ndarray,
    ell: float,
    solver: Any,
    starts: tuple[int, ...] = (0,),
    field: tuple[float, float] | None = None,
) -> PlanarStructure:
    """The first k samples' problem with the IPOPT settings ``solver``, its map (box or
    tiles, for the lengthscale ``ell``) around the positions ``around``; ``starts``: the
    first sample of each session; ``field``: sigma_f and sigma_m, from which a lattice of
    bumps takes its spacing unless ``model.gp.bump_spacing`` gives it
    (casmag.model.tiledmap.bump_spacing)."""
    common = {
        "n": k, "bias": options.bias, "kernel": options.kernel,
        "solver": solver.model_dump_json(), "starts": tuple(a for a in starts if a < k),
    }  # fmt: skip
    if options.form == "tiled":
        grid = tile_grid(
            around, ell, reach=options.margin, basis=options.tile_basis,
            lattice=options.bump_spacing, field=field,
        )  # fmt: skip
        return PlanarStructure(**common, basis=None, grid=grid, home=home_points(grid, around))
    hb = make_basis(options.kernel, around, ell, options.num_basis, options.margin)
    return PlanarStructure(
        **common,
        basis=(tuple(hb.domain.center), tuple(hb.domain.half_width), hb.num_basis),
        curvature=options.curvature,
    )


class PlanarStaged(StagedModel):
    """The planar model on one recording as the warm-start strategies see it
    (casmag.solver.staged): states P (k, 2), psi (k,), bias (one row, or k-1 for a random
    walk). The full problem's box is laid around the dead reckoning ``P_dr``; tiles always
    around the start (their Hessian pattern follows it, so a solve from the truth lays its
    own tiles, whose prior on the weights of unvisited tiles adds nothing at the optimum)."""

    def __init__(
        self, options: PlanarOptions, U: np.ndarray, dt: np.ndarray, Y: np.ndarray,
        p0: np.ndarray, psi0: float, P_dr: np.ndarray, c0: np.ndarray, sigma_m: float,
        sigma_f: float, ell: float, sigma_lin: float, progress: Progress | None = None,
        starts: tuple[int, ...] = (0,), anchors: np.ndarray | None = None,
        prior_map: PriorMap | None = None,
    ) -> None:  # fmt: skip
        """``starts``, ``anchors`` (S, 3: x, y, psi): several sessions, each from its own
        known start (``U`` row start - 1 not read); one session from ``p0``, ``psi0``.
        ``prior_map``: a saved map as the map's prior (localisation): every solve's map is
        its box or tiles, held at its mean in a prefix (and in the turn search), under its
        posterior instead of the GP prior in the whole recording's solve
        (casmag.solver.staged.PriorMap.solve_inputs)."""
        self.progress = progress
        self.prior_map = prior_map
        self.options, self.U, self.dt, self.Y = options, U, dt, Y
        self.p0, self.psi0, self.P_dr, self.c0 = p0, psi0, P_dr, c0
        self.n, self.solver, self.lengthscale = Y.shape[0], options.solver, ell
        self.sigma_m, self.sigma_f = sigma_m, sigma_f
        self.session_starts = tuple(int(a) for a in starts)
        self.anchors = (
            np.array([[p0[0], p0[1], psi0]]) if anchors is None else np.asarray(anchors, float)
        )
        if self.anchors.shape != (len(self.session_starts), 3):
            raise ValueError(f"anchors: one row (x, y, psi) per session, got {self.anchors.shape}")
        self.params: dict[str, Any] = {
            "sigma_disp": options.sigma_disp,
            "sigma_dyaw": options.sigma_dyaw,
            "sigma_bias0": options.bias_prior,
            "sigma_anchor": options.sigma_anchor,
            "sigma_psi0": options.sigma_psi0,
            "anchor": self.anchors,
            "sigma_m": sigma_m,
            "sigma_f": sigma_f,
            "sigma_lin": sigma_lin,
        }
        if options.bias == "random_walk":
            self.params["bias_walk"] = options.bias_walk

    def _bias_rows(self, k: int) -> int:
        S = len(self.sessions(k))
        return k - S if self.options.bias == "random_walk" else S

    def session_bias(self, bias: np.ndarray, s: int, a: int, e: int) -> np.ndarray:
        """Session s's bias rows (its samples [a, e)) of the states' ``bias``."""
        if self.options.bias == "random_walk":
            return bias[a - s : e - 1 - s]
        return bias[s : s + 1]

    def start(self, k: int, bias: float = 0.0) -> dict[str, np.ndarray]:
        U0 = self.U[: k - 1].copy()
        U0[:, 2] -= bias * self.dt[: k - 1]
        S = len(self.sessions(k))
        P0, psi_0 = dead_reckon_sessions(U0, self.anchors[:S], self.session_starts[:S])
        return {"P": P0, "psi": psi_0, "bias": np.full((self._bias_rows(k), 1), bias)}

    def world_readings(self, states: dict[str, np.ndarray]) -> np.ndarray:
        """The readings turned by their heading: y = Rz(psi)^T (m + c)."""
        psi = np.ravel(states["psi"])
        zero = np.zeros_like(psi)
        return sd.rotate(sd.quat_from_euler(zero, zero, psi), self.Y[: psi.size])

    def states(self, solved: Solved) -> dict[str, np.ndarray]:
        x = solved.sol.x
        return {"P": x["P"], "psi": x["psi"].ravel(), "bias": x["bias"]}

    def extend(self, states: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        """The states continued by the odometry with each session's last bias removed; a
        session the first m samples do not reach starts at its known start, bias 0."""
        P, psi, bias, dt = states["P"], np.ravel(states["psi"]), states["bias"], self.dt
        m = P.shape[0]
        Ps, psis, biases = [P], [psi], []
        for s, (a, e) in enumerate(self.sessions(k)):
            if e <= m:  # solved whole
                biases.append(self.session_bias(bias, s, a, e))
                continue
            if a < m:  # continued from its last solved sample
                own = self.session_bias(bias, s, a, m)
                b = float(own[-1, 0]) if own.size else 0.0
                p_a, psi_a, first = P[m - 1], float(psi[m - 1]), m - 1
            else:  # new: from its known start
                own = np.zeros((0, 1))
                b, p_a, psi_a, first = 0.0, self.anchors[s, :2], float(self.anchors[s, 2]), a
            rest = self.U[first : e - 1].copy()
            rest[:, 2] -= b * dt[first : e - 1]
            Pr, psr = dead_reckon_planar(rest, p_a, psi_a)
            skip = 1 if a < m else 0
            Ps.append(Pr[skip:])
            psis.append(psr[skip:])
            extra = (
                (e - 1 - s) - (a - s) - own.shape[0]
                if self.options.bias == "random_walk"
                else 1 - own.shape[0]
            )
            biases.append(np.vstack([own, np.full((extra, 1), b)]))
        return {"P": np.vstack(Ps), "psi": np.concatenate(psis), "bias": np.vstack(biases)}

    # ------------------------------------------------------------ sliding windows
    sample_states = ("P", "psi")

    def step_lengths(self) -> np.ndarray:
        return np.linalg.norm(self.U[:, :2], axis=1)

    def _window_structure(self, k: int, solver: SolverSpec) -> PlanarStructure:
        """A window of k samples: a constant bias increment, the box around the whole dead
        reckoning (as the translational windows': a window whose path leaves it ends the
        smoother)."""
        if self.options.form == "tiled":
            raise ValueError("sliding windows need model.gp.form reduced_rank, not tiled")
        if len(self.session_starts) > 1:
            raise ValueError("sliding windows: one session at a time, not several")
        s = planar_structure(self.options, k, self.P_dr, self.lengthscale, solver)
        s = dataclasses.replace(s, bias="constant", window=True)
        if self.prior_map is not None:
            s = dataclasses.replace(s, basis=self.prior_map.basis)
        return s

    def window_prior(self) -> WindowPrior:
        if self.prior_map is not None:
            return self.prior_map.window_prior()
        basis = self._window_structure(2, self.solver).hilbert_basis()
        return WindowPrior.gp(basis, self.options.kernel, self.params["sigma_lin"], self.sigma_m)

    def _window_odometry(self, a: int, k: int, bias: dict[str, np.ndarray]) -> np.ndarray:
        U = self.U[a : a + k - 1].copy()
        U[:, 2] -= float(np.ravel(bias["bias"])[0]) * self.dt[a : a + k - 1]
        return U

    def window_start(
        self, a: int, k: int, anchor: dict[str, np.ndarray] | None,
        carried: dict[str, np.ndarray] | None, bias: dict[str, np.ndarray],
    ) -> dict[str, np.ndarray]:  # fmt: skip
        U = self._window_odometry(a, k, bias)
        if carried is None:
            p0, psi0 = (self.p0, self.psi0) if anchor is None else _anchor_state(anchor)
            P, psi = dead_reckon_planar(U, p0, psi0)
        else:
            m = carried["P"].shape[0]
            Pr, psr = dead_reckon_planar(U[m - 1 :], carried["P"][-1], float(carried["psi"][-1]))
            P = np.vstack([carried["P"], Pr[1:]])
            psi = np.concatenate([np.ravel(carried["psi"]), psr[1:]])
        return {"P": P, "psi": psi, "bias": np.zeros((1, 1))}

    def solve_window(self, w: Window) -> Solved:
        # The anchor prior takes the standard deviations (anchor_sigma), not anchor_cov.
        a, k, start, bias, prior, solver = w.first, w.samples, w.start, w.bias, w.prior, w.solver
        s_k = self._window_structure(k, solver)
        nlp_k = cached_planar_nlp(s_k)
        p0, psi0 = (self.p0, self.psi0) if w.anchor is None else _anchor_state(w.anchor)
        params = {
            **self.params,
            "U": self._window_odometry(a, k, bias),
            "dt": self.dt[a : a + k - 1].reshape(-1, 1),
            "Y": self.Y[a : a + k],
            "lengthscale": self.lengthscale,
            "anchor": np.array([[p0[0], p0[1], psi0]]),
            "map_mean": prior.mean.reshape(-1, 1),
            "map_precision": prior.Lam,
        }
        if w.bias_cov is not None:  # the marginal standard deviation
            params["sigma_bias0"] = float(np.sqrt(w.bias_cov["bias"][0, 0]))
        if w.anchor_sigma is not None:  # one standard deviation for both axes: the larger
            params["sigma_anchor"] = float(np.max(w.anchor_sigma["P"]))
            params["sigma_psi0"] = float(np.ravel(w.anchor_sigma["psi"])[0])
        basis = s_k.hilbert_basis()
        psi = np.ravel(start["psi"])
        J = rotated_design(
            basis, self.options.kernel, start["P"], heading_rotations(psi), self.sigma_f,
            self.lengthscale,
        )  # fmt: skip
        x0 = {
            "P": start["P"],
            "psi": psi.reshape(-1, 1),
            "bias": np.zeros((1, 1)),
            **prior.start(J, self.Y[a : a + k].reshape(-1), basis.num_basis),
        }
        sol = nlp_k.solve(params, x0, progress=self.progress)
        return Solved(sol, nlp_k, s_k, self.lengthscale, first=a)

    def anchor_indices(self, solved: Solved, j: int) -> dict[str, np.ndarray]:
        entries, k = solved.nlp.x_layout.entries, solved.structure.n
        return {
            "P": entries["P"].offset + j + k * np.arange(2),  # column-major (k, 2)
            "psi": entries["psi"].offset + np.array([j]),
        }

    def window_design(self, solved: Solved, m: int) -> tuple[np.ndarray, np.ndarray]:
        x, a = solved.sol.x, solved.first
        R = heading_rotations(np.ravel(x["psi"])[:m])
        basis = solved.structure.hilbert_basis()
        J = rotated_design(
            basis, self.options.kernel, x["P"][:m], R, self.sigma_f, self.lengthscale
        )
        return J, self.Y[a : a + m].reshape(-1)

    def joined(self, states: dict[str, np.ndarray], bias: dict[str, np.ndarray]) -> dict:
        b = float(np.ravel(bias["bias"])[0])
        return {
            "P": states["P"],
            "psi": np.ravel(states["psi"]),
            "bias": np.full((self._bias_rows(states["P"].shape[0]), 1), b),
        }

    def _initial_map(self, s_k: PlanarStructure, P0: np.ndarray, Y0: np.ndarray, ell: float):
        """The NLP's map unknowns fitted to the field Y0 (in the map frame) at P0: the
        tiles' weights, or the box's whitened weights."""
        kernel, sigma_m, sigma_f = self.options.kernel, self.sigma_m, self.sigma_f
        if s_k.tiled:  # whitened (casmag.model.tiledmap.RotatedTiledModel)
            tiles = s_k.tiles()
            w = ridge_tile_weights(tiles, P0, Y0, self.c0, sigma_m, sigma_f, ell)
            return w / np.sqrt(tiles.prior_variances(sigma_f, ell))[:, None]
        basis_k = s_k.hilbert_basis()
        w = ridge_weights(basis_k, kernel, P0, Y0, self.c0, sigma_m, sigma_f, ell)
        return whiten(basis_k, kernel, sigma_f, ell, w)

    turns = True

    def turned(self, states: dict[str, np.ndarray], k: int, turn: float) -> dict[str, np.ndarray]:
        """(StagedModel.turned) The headings turned, each step by the turn at its start,
        and the bias by the rate removed, so that the odometry's residuals stay as they
        were."""
        t = np.concatenate([[0.0], np.cumsum(self.dt[: k - 1])])
        theta = turn * t / t[-1]
        P = np.asarray(states["P"], float)
        c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
        d = np.diff(P, axis=0)
        steps = np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]])
        return {
            "P": np.vstack([P[:1], P[:1] + np.cumsum(steps, axis=0)]),
            "psi": np.ravel(states["psi"]) + theta,
            "bias": np.asarray(states["bias"], float) - turn / t[-1],
        }

    def solve(
        self, k: int, start: dict[str, np.ndarray], solver: SolverSpec, lengthscale: float
    ) -> Solved:
        sol, nlp_k, s_k = self.stage_problem(k, start, solver, lengthscale).solve(self.progress)
        return Solved(sol, nlp_k, s_k, lengthscale)

    def stage_problem(
        self, k: int, start: dict[str, np.ndarray], solver: SolverSpec, lengthscale: float,
        structure: PlanarStructure | None = None, coarse: bool = False,
    ) -> StageProblem:  # fmt: skip
        params_k = {
            **self.params,
            "U": self.U[: k - 1],
            "dt": self.dt[: k - 1].reshape(-1, 1),
            "Y": self.Y[:k],
            "lengthscale": lengthscale,
        }
        params_k["anchor"] = self.anchors[: len(self.sessions(k))]
        tiled = self.options.form == "tiled"
        around = self.P_dr if k == self.n and not tiled else start["P"]
        # tiles for the stage's lengthscale (coarse-to-fine; map_lengthscale) and a prefix's
        # coarsest lattice (lattice_field), a box for the assumed one
        s_k = structure or planar_structure(
            self.options, k, around, map_lengthscale(tiled, self.lengthscale, lengthscale),
            solver, self.session_starts,
            None if coarse else lattice_field(k, self.n, (self.sigma_f, self.sigma_m)),
        )  # fmt: skip
        psi_0 = np.asarray(start["psi"], float).ravel()
        x0 = {"P": start["P"], "psi": psi_0.reshape(-1, 1), "bias": start["bias"]}
        held: tuple[str, ...] = ()
        if self.prior_map is None:
            Y0 = sd.rotate(sd.quat_from_euler(0.0 * psi_0, 0.0 * psi_0, psi_0), self.Y[:k])
            x0["W"] = self._initial_map(s_k, start["P"], Y0, lengthscale)
            x0["c"] = self.c0.reshape(3, 1)
        else:  # the saved map's box or tiles under its posterior
            s_k, prior_params, map0, held = self.prior_map.solve_inputs(
                s_k, start["P"], heading_rotations(psi_0), self.Y[:k], self.sigma_f,
                lengthscale, hold=k < self.n or coarse,
            )  # fmt: skip
            params_k.update(prior_params)
            x0.update(map0)
            if self.prior_map.held and k == self.n:  # --hold-map: the map's noise added
                params_k["sigma_m"] = self.held_sigma_m(start["P"])
        return StageProblem(s_k, cached_planar_nlp, params_k, x0, 2, tuple(held))


def displacement_bias_consider(
    final: Solved, U: np.ndarray, sigma_disp: float, sigma_b: float,
    starts: tuple[int, ...] = (0,),
) -> np.ndarray:  # fmt: skip
    """The consider parameters of a planar solve (casmag.solver.uncertainty.
    position_uncertainty's ``consider``): a body-frame displacement bias per step, forward
    and left, each of standard deviation ``sigma_b`` (casmag.solver.staged.
    displacement_bias_sigma), through the odometry's cross Hessian at the solution
    (casmag.model.planar.displacement_bias_coupling). Odometry scale errors of 0.5-1 % are
    the error that stays on the simulated walks (README, Planar and pose uncertainty): the
    map cannot see a scale, so the MAP keeps the odometry's and a covariance without it is
    too confident wherever the path is far from its anchor."""
    x, layout = final.sol.x, final.nlp.x_layout
    H_P, H_psi, _ = displacement_bias_coupling(x["P"], x["psi"], U, sigma_disp, starts)
    n = H_psi.shape[0]
    C = np.zeros((layout.size, 2))
    off_P, off_psi = layout.entries["P"].offset, layout.entries["psi"].offset
    for a in range(2):  # P packed by column (NLP layouts: order F)
        C[off_P + a * n + np.arange(n)] = H_P[:, a, :]
    C[off_psi + np.arange(n)] = H_psi
    return sigma_b * C


def heading_rotations(psi: np.ndarray) -> np.ndarray:
    """(N, 3, 3) body-to-map rotations Rz(psi) of headings psi (N,)."""
    c, s = np.cos(psi), np.sin(psi)
    R = np.zeros((psi.size, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def hyperparameters_from_data(
    options: Any, P: np.ndarray, Y_map: np.ndarray
) -> tuple[float, float, float, float, list[str]]:
    """(sigma_f, lengthscale, sigma_m, sigma_lin, names estimated) of a recording model
    whose magnetometer turns with the body (planar, pose): the options' values, those set
    to ``estimate`` by the windowed marginal likelihood of the field Y_map (turned into the
    map frame along the dead reckoning) on the dead-reckoned path P; sigma_lin from the
    data unless given (the largest |mean| of a component plus the field's spread)."""
    values = {h: getattr(options, h) for h in ("sigma_f", "lengthscale", "sigma_m")}
    estimated = [h for h, v in values.items() if v == "estimate"]
    if estimated:
        est = estimate_hyperparameters(
            P, Y_map, kernel=options.kernel,
            window=PLANAR_HYPER_WINDOW[0], max_windows=PLANAR_HYPER_WINDOW[1],
        )  # fmt: skip
        values.update({h: getattr(est, h) for h in estimated})
    sigma_lin = options.sigma_lin
    if sigma_lin is None:
        sigma_lin = float(np.abs(Y_map.mean(axis=0)).max() + Y_map.std()) or 1.0
    return (
        float(values["sigma_f"]), float(values["lengthscale"]), float(values["sigma_m"]),
        float(sigma_lin), estimated,
    )  # fmt: skip


def hyperparameters_and_map(
    options: Any,
    P: np.ndarray,
    Y_map: np.ndarray,
    state_unknowns: int,
    box_only: str | None,
    positions: Callable[[Any, float], np.ndarray] | None = None,
) -> tuple[Any, MapChoice | None, tuple[float, float, float, float, list[str]]]:
    """The options with the map's form resolved (casmag.model.mapchoice.resolve_options,
    box or tiles for the map laid around ``positions(options, lengthscale)``, default P,
    against ``state_unknowns`` pose unknowns), the choice, and the hyperparameters
    (:func:`hyperparameters_from_data`): estimated again when the tiles changed the
    kernel to curl-free, whose hyperparameters differ from the SE kernel's."""
    hyper = hyperparameters_from_data(options, P, Y_map)
    kernel, ell = options.kernel, hyper[1]
    X = P if positions is None else positions(options, ell)
    options, choice = resolve_options(options, X, ell, state_unknowns, box_only)
    if options.kernel != kernel:
        hyper = hyperparameters_from_data(options, P, Y_map)
    return options, choice, hyper


def hyperparameter_info(estimated: list[str], sigma_lin: float, given: bool) -> dict[str, Any]:
    """``info`` entries of a recording model's result: where the hyperparameters and
    sigma_lin came from, and the versions."""
    how = "marginal likelihood on the dead-reckoned path"
    return {
        "hyperparameters": "given" if not estimated else f"{', '.join(estimated)}: {how}",
        "sigma_lin": {"value": sigma_lin, "source": "given" if given else "data"},
        "casadi": ca.__version__,
        "versions": versions(),
    }


def structure_map_arrays(s: BoxOrTiles, kernel: str, hyper: dict[str, float], sol: Any) -> dict:
    """The solved planar map (the planar model's, or a pose model's with ``map_dim`` 2) on
    a grid with its posterior std (casmag.gp.fieldmap), for map.png (the tiled map's field
    alone); ``s`` a PlanarStructure or PoseStructure."""
    P = sol.x["P"][:, :2]
    if s.tiled:
        tiles = s.tiles()
        W = sol.x["W"].T * np.sqrt(tiles.prior_variances(hyper["sigma_f"], hyper["lengthscale"]))
        return tiled_map_arrays(tiles, W, sol.x["c"], hyper["lengthscale"], P)
    basis = s.hilbert_basis()
    W = unwhitened(basis, kernel, hyper, sol.x["W"])
    return map_arrays(basis, kernel, W, sol.x["c"], hyper, P)


def structure_map_info(s: BoxOrTiles) -> dict[str, Any]:
    """The map of the kept solve (a PlanarStructure's or PoseStructure's): its form and
    size."""
    if s.tiled:
        tiles = s.tiles()
        return {
            "form": "tiled",
            "tiles": tiles.num_tiles,
            "functions_per_tile": tiles.per_tile,
            "spacing_m": tiles.grid.spacing,
        }
    basis = s.hilbert_basis()
    return {
        "form": "reduced_rank",
        "num_basis": basis.num_basis,
        "box_center": [float(v) for v in basis.domain.center],
        "box_half_width": [float(v) for v in basis.domain.half_width],
    }


def solve_planar_recording(
    path: Any,
    options: PlanarOptions | None = None,
    progress: Progress | None = None,
    anchor: str = "truth",
    method: str = "map",
    prior_map: SavedMap | None = None,
    map_source: str = "",
    hold_map: bool = False,
) -> Result:
    """Solve a planar recording (``dfwd,dleft,dyaw`` columns, ``casmag.data.recording``: a path,
    or a Recording already read); truth columns, when present, are used for evaluation
    only, and (``anchor`` ``truth``, the default) for the first pose; ``origin``: the
    origin, heading 0. ``prior_map``: locate it against a saved map (:func:`solve_planar`)."""
    rec = path if isinstance(path, Recording) else read_recording(path)
    path = rec.path
    if rec.motion != "planar":
        raise DataError(
            f"{path}: motion input is {rec.motion!r}, the planar model needs dfwd,dleft,dyaw"
        )
    cols = {name: rec.increments[:, i] for i, name in enumerate(rec.increment_names)}
    truth = None
    if rec.P_true is not None:
        truth = {"P": rec.P_true[:, :2]}
        if rec.yaw_true is not None:
            truth["psi"] = rec.yaw_true
    result = solve_planar(
        cols["dfwd"],
        cols["dleft"],
        cols["dyaw"],
        rec.Y,
        options,
        truth=truth,
        t=rec.t,
        progress=progress,
        name=Path(path).stem,
        method=method,
        prior_map=prior_map,
        map_source=map_source,
        hold_map=hold_map,
        **({"p0": np.zeros(2), "psi0": 0.0} if anchor == "origin" else {}),
    )
    if anchor == "origin":
        result.info["anchor"]["kind"] = "origin"
    result.info["recording"] = str(path)
    return result


def solve_planar_sessions(
    recordings: list[Any],
    options: PlanarOptions | None = None,
    progress: Progress | None = None,
    name: str | None = None,
) -> Result:
    """Several planar recordings of one field (paths, or Recordings already read), one
    map: each session keeps its own trajectory and heading-rate bias and starts at its
    first true pose, so every recording needs truth columns with a heading (``yaw``) in
    the common frame. They are added one at a time (casmag.solver.staged.solve_sessions),
    the one whose dead reckoning revisits itself most first
    (casmag.solver.sessions.revisit_order, with the lengthscale of ``options`` or the one
    the data's marginal likelihood gives for the sessions in the order given). The
    result's arrays are the sessions stacked in that order; ``info["sessions"]`` has each
    session's errors and bias, ``info["session_order"]`` the order (indices into
    ``recordings``)."""
    options = options or PlanarOptions()
    recs = [r if isinstance(r, Recording) else read_recording(r) for r in recordings]
    require_first_poses(recs, "planar", "x, y and yaw")
    paths, fields = [], []
    for rec in recs:
        P, psi = dead_reckon_planar(rec.increments, rec.P_true[0, :2], float(rec.yaw_true[0]))
        paths.append(P)
        fields.append(sd.rotate(sd.quat_from_euler(0.0 * psi, 0.0 * psi, psi), rec.Y))
    ell = hyperparameters_from_data(options, np.vstack(paths), np.vstack(fields))[1]
    order = revisit_order(paths, ell)
    ordered = [recs[i] for i in order]
    st = Stacked.of(ordered, np.zeros(3))
    result = solve_planar(
        st.U[:, 0], st.U[:, 1], st.U[:, 2], st.Y, options,
        truth={"P": np.vstack([r.P_true[:, :2] for r in ordered]),
               "psi": np.concatenate([r.yaw_true for r in ordered])},
        t=st.t, progress=progress, name=name or "+".join(Path(r.path).stem for r in recs),
        starts=st.starts, session_names=st.names,
    )  # fmt: skip
    result.info["session_order"] = order
    result.info["recordings"] = [str(r.path) for r in ordered]
    return result
