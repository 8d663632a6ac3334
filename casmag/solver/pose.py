"""The solve of the pose-odometry model (casmag.model.pose) from arrays (:func:`solve_pose`)
and from a recording (:func:`solve_pose_recording`): hyperparameters from the data, the
model as a :class:`casmag.solver.staged.StagedModel` (:class:`PoseStaged`) whose warm
starts casmag.solver.staged runs, the truth-free and with-truth checks, the result."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from casmag import strapdown as sd
from casmag.data.recording import Recording, read_recording
from casmag.errors import DataError
from casmag.gp.savedmap import SavedMap
from casmag.model.field import left_map_box
from casmag.model.mapchoice import box_needed
from casmag.model.pose import (
    PoseStructure,
    cached_pose_nlp,
    nominal_parameters,
    orientations,
)
from casmag.model.rotated import ridge_weights, rotated_design, whiten
from casmag.model.rrmap import make_basis
from casmag.model.tiledmap import home_points, left_map_tiles, ridge_tile_weights, tile_grid
from casmag.nlp import Progress
from casmag.problem.pose import PoseOptions
from casmag.problem.spec import SolverSpec
from casmag.result import Result
from casmag.result.metrics import rmse_and_max
from casmag.solver.biasscan import heading_start
from casmag.solver.ekf import FilterMap, PoseNav, filter_result, run_safely
from casmag.solver.planar import (
    hyperparameter_info,
    hyperparameters_and_map,
    hyperparameters_from_data,
    localisation_options,
    located,
    structure_map_arrays,
    structure_map_info,
)
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

#: Fixed biases are held at zero with IPOPT's fixed variables.
_BIASES = ("bias_p", "bias_w")


def attitude_rms_deg(Q: np.ndarray, Q_true: np.ndarray) -> float:
    """RMS angle [deg] between two sequences of unit quaternions (N, 4)."""
    return float(np.degrees(np.sqrt(np.mean(sd.quat_angle(Q, Q_true) ** 2))))


#: ``map_dim: auto``: stretches of this many lengthscales of travel whose height range is
#: compared with the lengthscale (the dead reckoning's height drifts with the odometry
#: and the pitch over a whole recording; over a few lengthscales the drift is small).
HEIGHT_STRETCH_LENGTHSCALES = 5.0


def choose_map_dim(options: PoseOptions, P: np.ndarray, lengthscale: float) -> int:
    """The map's dimension: the option's, or (``auto``) 2 when, over stretches of
    :data:`HEIGHT_STRETCH_LENGTHSCALES` lengthscales of travel, the path's height varies by
    less than one lengthscale (the median stretch), across which the GP's own prior says the
    field changes little; else 3."""
    if options.map_dim != "auto":
        return int(options.map_dim)
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    reach = HEIGHT_STRETCH_LENGTHSCALES * lengthscale
    ranges = []
    for i in range(0, P.shape[0], max(1, P.shape[0] // 200)):
        j = int(np.searchsorted(travel, travel[i] + reach))
        ranges.append(float(np.ptp(P[i : max(j, i + 2), 2])))
    return 2 if float(np.median(ranges)) < lengthscale else 3


def solve_pose(
    U: np.ndarray,
    mag: np.ndarray,
    options: PoseOptions | None = None,
    truth: dict[str, np.ndarray] | None = None,
    t: np.ndarray | None = None,
    p0: np.ndarray | None = None,
    q0: np.ndarray | None = None,
    progress: Progress | None = None,
    name: str = "pose",
    method: str = "map",
    starts: tuple[int, ...] = (0,),
    session_names: list[str] | None = None,
    prior_map: SavedMap | None = None,
    map_source: str = "",
    hold_map: bool = False,
) -> Result:
    """Pose odometry plus magnetometer GP-SLAM from arrays.

    U (N-1, 7): increments dpx, dpy, dpz [m] (body frame of the earlier sample) and dqw,
    dqx, dqy, dqz (rotation increment) between samples; mag (N, 3): magnetometer in the
    body frame; t (N,) [s] (default one second per sample: the rate bias is then per step);
    p0 (3,), q0 (4,): the known first pose (default the truth's when given, else the origin
    and identity). truth: optional ``P`` (N, 3) and ``q`` (N, 4), for evaluation only.

    The warm start of ``solver.warm_start`` (the planar model's defaults: growing prefixes)
    from the dead reckoning, run by casmag.solver.staged on :class:`PoseStaged`: each stage
    starts from the previous one's estimate, continued by the odometry with the estimated
    biases removed.

    method: ``map`` (default) the MAP estimate; ``ekf`` the filter baseline
    (casmag.solver.ekf.PoseNav) with the batch's map box, hyperparameters and noise.

    starts: several sessions of one field stacked end to end, one map, as for
    casmag.solver.planar.solve_planar (p0 (S, 3) and q0 (S, 4): each session's first pose,
    by default the truth's; its own biases; added one at a time in the given order).

    prior_map: locate the recording against a saved map (read from ``map_source``) and
    update it, as casmag.solver.planar.solve_planar does (``hold_map``: held, not updated);
    the map's dimension is the saved map's."""
    options = options or PoseOptions()
    if prior_map is not None:
        options = localisation_options(options, prior_map, map_source, "pose")
    U = np.asarray(U, dtype=float)
    Y = np.asarray(mag, dtype=float)
    n = Y.shape[0]
    if U.shape != (n - 1, 7):
        raise ValueError(f"increments must be (N-1, 7) = ({n - 1}, 7), got {U.shape}")
    starts = check_starts(starts, n)
    S = len(starts)
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
        p0 = truth["P"][first] if truth is not None else np.zeros((S, 3))
        anchor_kind = "first true position" if truth is not None else "origin (no truth)"
    if q0 is None:
        identity = np.tile([1.0, 0, 0, 0], (S, 1))
        q0 = truth["q"][first] if truth is not None and "q" in truth else identity
    p0s = np.reshape(np.asarray(p0, dtype=float), (S, 3))
    q0s = sd.quat_normalize(np.reshape(np.asarray(q0, dtype=float), (S, 4)))
    p0, q0 = p0s[0], q0s[0]
    ends = [*starts[1:], n]
    P_dr, Q_dr = np.empty((n, 3)), np.empty((n, 4))
    for a, e, pa, qa in zip(starts, ends, p0s, q0s, strict=True):
        P_dr[a:e], Q_dr[a:e] = sd.dead_reckon_pose(U[a : e - 1], pa, qa)
    Y_map = sd.rotate(Q_dr, Y)
    options, choice, hyper = hyperparameters_and_map(
        options, P_dr, Y_map, 6 * n, box_needed(S, method, prior_map is not None),
        lambda o, ell: P_dr[:, : choose_map_dim(o, P_dr, ell)],
    )  # fmt: skip
    sigma_f, ell, sigma_m, sigma_lin, estimated = hyper
    dim = choose_map_dim(options, P_dr, ell)
    height = dim == 2 and options.height_sigma is not None
    c0 = Y_map.mean(axis=0)
    params: dict[str, Any] = {
        "U": U, "dt": dt.reshape(-1, 1), "Y": Y,
        "sigma_p": options.sigma_p, "sigma_r": options.sigma_r,
        "sigma_bp": options.bias_p_prior, "sigma_bw": options.bias_w_prior,
        "sigma_anchor": options.sigma_anchor, "sigma_att0": options.sigma_att0,
        "anchor_p": p0s, "anchor_q": q0s,
        "sigma_m": sigma_m, "sigma_f": sigma_f, "lengthscale": ell, "sigma_lin": sigma_lin,
        **({"sigma_height": options.height_sigma} if height else {}),
    }  # fmt: skip
    estimate = {"bias_p": options.estimate_bias_p, "bias_w": options.estimate_bias_w}
    fixed = [b for b in _BIASES if not estimate[b]]

    anchor_info = {
        "kind": anchor_kind,
        "position": [float(v) for v in p0],
        "quaternion": [float(v) for v in q0],
        "sigma": options.sigma_anchor,
    }
    if method == "ekf":
        if options.form == "tiled":
            raise DataError("model.gp.form: the filter baseline needs the box map (reduced_rank)")
        s_n = pose_structure(options, n, P_dr, ell, dim, height, options.solver)
        nav = PoseNav(
            U, dt, p0, q0, options.sigma_p, options.sigma_r, options.sigma_anchor,
            options.sigma_att0, options.bias_w_prior if options.estimate_bias_w else 1e-12,
            options.bias_p_prior if options.estimate_bias_p else None, position_dim=dim,
            height_sigma=options.height_sigma if height else None,
        )  # fmt: skip
        fmap = FilterMap(s_n.hilbert_basis(), options.kernel, sigma_f, ell, sigma_m, sigma_lin)
        run = run_safely(nav, fmap, Y)
        result = filter_result(
            nav, fmap, Y, P_dr, None if truth is None else np.asarray(truth["P"], float),
            {"name": name, "samples": int(n), "anchor": anchor_info}, motion="pose", run=run,
            duration=None if t is None else float(np.ptp(t)),
        )  # fmt: skip
        Q_f = None if run is None else nav.orientations(run.states)
        result.arrays.update(
            t=np.arange(n, dtype=float) if t is None else np.asarray(t, dtype=float),
            Q_odometry=Q_dr, Q_estimate=Q_f,
        )  # fmt: skip
        if truth is not None and "q" in truth:
            result.details["attitude_rms_deg_before"] = attitude_rms_deg(Q_dr, truth["q"])
            if Q_f is not None:
                result.details["attitude_rms_deg_after"] = attitude_rms_deg(Q_f, truth["q"])
        if run is not None:
            result.details["bias_w"] = [float(v) for v in run.states[-1, 6:9]]
        return result
    model = PoseStaged(
        options, U, dt, Y, p0, q0, P_dr, Q_dr, c0, params, dim, height, progress, starts,
        None if prior_map is None else PriorMap.of(prior_map, held=hold_map),
    )  # fmt: skip
    duration = float(dt[: ends[0] - 1].sum())  # of the first session: its starts' biases
    biases = heading_bias_starts(options.starts, options.start_heading_deg, duration)
    scan = heading_start(
        model, duration, options.kernel, (sigma_f, ell, sigma_m),
        prior_map is not None or not options.solver.warm_start.evidence,
    )  # fmt: skip
    ws = options.solver.warm_start
    # one more start, one batch: the heading-rate bias of the field's evidence
    staged, strategy = solve_staged(model, ws, biases, None if scan is None else scan.bias)
    final = staged.final
    sol, nlp, s, Q_nom = final.sol, final.nlp, final.structure, final.nominal
    Q_est = orientations(Q_nom, sol.x["D"])
    hyper = {"sigma_f": sigma_f, "lengthscale": ell, "sigma_m": sigma_m}
    flags: list[dict[str, Any]] = []
    if truth is not None and "q" in truth:
        Qt = sd.quat_normalize(np.asarray(truth["q"], dtype=float))
        true_states = {"P": np.asarray(truth["P"], float), "Q": Qt}
        same = sd.quat_angle(q0s, Qt[first]) < 1e-9  # q and -q are one attitude
        flag = (
            truth_check(model, final, true_states, truth["P"], P_dr)
            if anchored_at_truth(p0s, true_states["P"][first]) and same.all()
            else None
        )
        if flag is not None:
            flags.append(flag)
    if sol.success:
        if s.tiled:
            box = left_map_tiles(s.tiles(), sol.x["P"][:, :dim])
        else:
            basis = s.hilbert_basis()
            box = left_map_box(basis.domain.center, basis.domain.half_width, sol.x["P"][:, :dim])
        if box is not None:
            flags.append(box)
    P_true = None if truth is None else np.asarray(truth["P"], dtype=float)
    u_summary, P_cov, P_cov_plain = uncertainty(
        final, P_true, model.final_sigma_m(sigma_m), options.solver,
        consider_fixed=(held := displacement_bias_consider(U, options, starts)),
    )  # fmt: skip
    record_consider(u_summary, held and held["bias_p"], options.displacement_bias)
    before = after = (None, None)
    att_before = att_after = None
    if truth is not None:
        before = rmse_and_max(P_dr, truth["P"])
        if sol.success:
            after = rmse_and_max(sol.x["P"], truth["P"])
        if "q" in truth:
            att_before = attitude_rms_deg(Q_dr, truth["q"])
            att_after = attitude_rms_deg(Q_est, truth["q"]) if sol.success else None
    arrays: dict[str, Any] = {}
    if sol.success and dim == 2:
        arrays.update(structure_map_arrays(s, options.kernel, hyper, sol))
    arrays.update(
        t=np.arange(n, dtype=float) if t is None else np.asarray(t, dtype=float),
        P_odometry=P_dr, Q_odometry=Q_dr, P_estimate=sol.x["P"], Q_estimate=Q_est,
        P_cov=P_cov, P_cov_uninflated=P_cov_plain,
        P_true=None if truth is None else np.asarray(truth["P"], dtype=float),
        Q_true=None if truth is None or "q" not in truth else np.asarray(truth["q"], float),
    )  # fmt: skip
    form = {
        **structure_map_info(s),
        "dim": dim,
        "height_prior_m": options.height_sigma if height else None,
    }
    result = Result(
        motion="pose",
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
        details={
            "attitude_rms_deg_before": att_before,
            "attitude_rms_deg_after": att_after,
            "bias_p": [float(v) for v in sol.x["bias_p"].ravel()] if sol.success else None,
            "bias_w": [float(v) for v in sol.x["bias_w"].ravel()] if sol.success else None,
        },
        odometry_bias=[float(v) for v in sol.x["bias_p"].ravel()] if sol.success else None,
        hyperparameters=hyper,
        cost_blocks=sol.cost_blocks(),
        stages=staged.records(),
        cost_per_iteration=sol.cost_per_iteration,
        uncertainty=u_summary,
        info={
            "name": name,
            "samples": int(n),
            "num_basis": s.map_unknowns,
            "map": {**form, **MAP_NOT_YET},
            "anchor": anchor_info,
            "kernel": options.kernel,
            "biases_estimated": [b for b in _BIASES if b not in fixed],
            **hyperparameter_info(estimated, sigma_lin, options.sigma_lin is not None),
            "warm_start": strategy,
            "bias_scan": None if scan is None else scan.to_dict(),
            **({} if choice is None else {"map_choice": choice.to_dict()}),
        },
        convergence=[sol.trace("GP-SLAM")],
        arrays=arrays,
    )
    if S > 1:
        bounds = list(zip(starts, ends, strict=True))
        names = session_names or [f"session {i + 1}" for i in range(S)]
        biases_p = list(sol.x["bias_p"].reshape(-1, 3)) if sol.success else None
        P_true = None if truth is None else np.asarray(truth["P"], float)
        result.info["sessions"] = session_errors(bounds, result, names, P_true, biases_p)
        anchor_info["sessions"] = np.hstack([p0s, q0s]).tolist()  # x, y, z, qw, qx, qy, qz
    frame = (
        f"anchored at the {anchor_kind}: {anchor_info['position']}, attitude (w, x, y, z) "
        f"{anchor_info['quaternion']} (sigma {options.sigma_anchor} m)"
    )
    result.map_maker = StagedMap(final, options.kernel, hyper, frame, form, dim)
    if prior_map is not None:
        P_located = sol.x["P"] if sol.success else None
        located(result, prior_map, map_source, P_located, hold_map, model.noise_on_held_map)
    return result


def displacement_bias_consider(
    U: np.ndarray, options: PoseOptions, starts: tuple[int, ...] = (0,)
) -> dict[str, float] | None:
    """The held displacement bias as a consider parameter of the position covariance
    (casmag.solver.uncertainty.position_uncertainty's ``consider_fixed``): its standard
    deviation per body axis ``options.displacement_bias`` times the median step within
    the sessions; None when it is estimated or the fraction is 0 (the planar model's
    casmag.solver.planar.displacement_bias_consider)."""
    if options.estimate_bias_p:
        return None
    sigma = displacement_bias_sigma(np.asarray(U)[:, :3], options.displacement_bias, starts)
    return None if sigma is None else {"bias_p": sigma}


def pose_structure(
    options: PoseOptions, k: int, around: np.ndarray, ell: float, dim: int, height: bool,
    solver: Any, starts: tuple[int, ...] = (0,), field: tuple[float, float] | None = None,
) -> PoseStructure:  # fmt: skip
    """The first k samples' problem with the IPOPT settings ``solver``, its map (box or
    tiles, for the lengthscale ``ell``, in ``dim`` dimensions) around the positions
    ``around``; ``starts``: the first sample of each session; ``field``: sigma_f and
    sigma_m, for a lattice of bumps (casmag.solver.planar.planar_structure)."""
    common = {
        "n": k, "map_dim": dim, "kernel": options.kernel, "solver": solver.model_dump_json(),
        "curvature": options.curvature, "height": height,
        "starts": tuple(a for a in starts if a < k),
    }  # fmt: skip
    if options.form == "tiled":
        grid = tile_grid(
            around[:, :dim], ell, reach=options.margin, basis=options.tile_basis,
            lattice=options.bump_spacing, field=field,
        )  # fmt: skip
        return PoseStructure(
            **common, basis=None, grid=grid, home=home_points(grid, around[:, :dim])
        )
    hb = make_basis(options.kernel, around[:, :dim], ell, options.num_basis, options.margin)
    return PoseStructure(
        **common, basis=(tuple(hb.domain.center), tuple(hb.domain.half_width), hb.num_basis)
    )


class PoseStaged(StagedModel):
    """The pose model on one recording as the warm-start strategies see it
    (casmag.solver.staged): states P (k, 3), the nominal orientations Q (k, 4) the solve is
    linearised about (its unknowns D are the rotation errors, zero at the start) and the
    biases. The full problem's box is laid around the dead reckoning ``P_dr``, a prefix's
    around its start. A start with a heading-rate bias is the dead reckoning turned about
    the vertical (casmag.strapdown.turn_heading), its rate bias zero."""

    def __init__(
        self, options: PoseOptions, U: np.ndarray, dt: np.ndarray, Y: np.ndarray,
        p0: np.ndarray, q0: np.ndarray, P_dr: np.ndarray, Q_dr: np.ndarray, c0: np.ndarray,
        params: dict[str, Any], dim: int, height: bool, progress: Progress | None = None,
        starts: tuple[int, ...] = (0,), prior_map: PriorMap | None = None,
    ) -> None:  # fmt: skip
        """``starts``: several sessions, each from its known first pose (rows of
        ``params["anchor_p"]`` and ``params["anchor_q"]``; ``U`` row start - 1 not read).
        ``prior_map``: a saved map as the map's prior (as casmag.solver.planar.PlanarStaged)."""
        self.prior_map = prior_map
        self.options, self.U, self.dt, self.Y = options, U, dt, Y
        self.p0, self.q0, self.P_dr, self.Q_dr, self.c0 = p0, q0, P_dr, Q_dr, c0
        self.params, self.dim, self.height, self.progress = params, dim, height, progress
        self.n, self.solver = Y.shape[0], options.solver
        self.lengthscale = float(params["lengthscale"])
        self.fixed = [b for b in _BIASES if not getattr(options, f"estimate_{b}")]
        self.session_starts = tuple(int(a) for a in starts)

    def start(self, k: int, bias: float = 0.0) -> dict[str, np.ndarray]:
        P, Q = self.P_dr[:k], self.Q_dr[:k]
        if bias != 0.0:  # about the vertical: a body-frame rate is one only for a level body
            t = np.concatenate([[0.0], np.cumsum(self.dt[: k - 1])])
            P, Q, _ = sd.turn_heading(P, Q, t, bias)
        S = len(self.sessions(k))
        return {"P": P, "Q": Q, "bias_p": np.zeros((S, 3)), "bias_w": np.zeros((S, 3))}

    def world_readings(self, states: dict[str, np.ndarray]) -> np.ndarray:
        """The readings turned by their attitude: y = R(q)^T m."""
        Q = np.asarray(states["Q"])
        return sd.rotate(Q, self.Y[: Q.shape[0]])

    def states(self, solved: Solved) -> dict[str, np.ndarray]:
        x = solved.sol.x
        return {
            "P": x["P"], "Q": orientations(solved.nominal, x["D"]),
            "bias_p": x["bias_p"].reshape(-1, 3), "bias_w": x["bias_w"].reshape(-1, 3),
        }  # fmt: skip

    def extend(self, states: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        """The states continued by the odometry with each session's biases removed; a
        session the first m samples do not reach starts at its known first pose (its dead
        reckoning), biases 0."""
        P, Q = states["P"], states["Q"]
        b_p, b_w = np.reshape(states["bias_p"], (-1, 3)), np.reshape(states["bias_w"], (-1, 3))
        m = P.shape[0]
        if k == m:
            return dict(states)
        Ps, Qs, bps, bws = [P], [Q], [b_p], [b_w]
        for s, (a, e) in enumerate(self.sessions(k)):
            if e <= m:
                continue
            if a < m:  # continued from its last solved sample
                Pr, Qr = sd.dead_reckon_pose(
                    self.U[m - 1 : e - 1], P[-1], Q[-1], b_p[s], b_w[s], self.dt[m - 1 : e - 1]
                )
                Ps.append(Pr[1:])
                Qs.append(Qr[1:])
            else:  # new: its dead reckoning from its known first pose
                Ps.append(self.P_dr[a:e])
                Qs.append(self.Q_dr[a:e])
                bps.append(np.zeros((1, 3)))
                bws.append(np.zeros((1, 3)))
        return {"P": np.vstack(Ps), "Q": np.vstack(Qs), "bias_p": np.vstack(bps),
                "bias_w": np.vstack(bws)}  # fmt: skip

    turns = True

    def turned(self, states: dict[str, np.ndarray], k: int, turn: float) -> dict[str, np.ndarray]:
        """(StagedModel.turned) casmag.strapdown.turn_heading of the positions and
        orientations, the biases as they are (as :meth:`start` turns the dead reckoning)."""
        t = np.concatenate([[0.0], np.cumsum(self.dt[: k - 1])])
        P, Q, _ = sd.turn_heading(states["P"], states["Q"], t, -turn / t[-1])
        return {**states, "P": P, "Q": Q}

    def solve(
        self, k: int, start: dict[str, np.ndarray], solver: SolverSpec, lengthscale: float
    ) -> Solved:
        problem = self.stage_problem(k, start, solver, lengthscale)
        sol, nlp_k, s_k = problem.solve(self.progress)
        return Solved(sol, nlp_k, s_k, lengthscale, nominal=start["Q"])

    def stage_problem(
        self, k: int, start: dict[str, np.ndarray], solver: SolverSpec, lengthscale: float,
        structure: PoseStructure | None = None, coarse: bool = False,
    ) -> StageProblem:  # fmt: skip
        P0, Q0, dim, kernel = start["P"], start["Q"], self.dim, self.options.kernel
        # The full problem's box around the dead reckoning; tiles around the start (their
        # Hessian pattern follows it), as casmag.solver.planar.PlanarStaged lays them.
        tiled = self.options.form == "tiled"
        around = self.P_dr if k == self.n and not tiled else P0
        starts = self.session_starts[: len(self.sessions(k))]
        ell = map_lengthscale(tiled, self.lengthscale, lengthscale)
        sigma_m, sigma_f = self.params["sigma_m"], self.params["sigma_f"]
        s_k = structure or pose_structure(
            self.options, k, around, ell, dim, self.height, solver, starts,
            None if coarse else lattice_field(k, self.n, (sigma_f, sigma_m)),
        )  # fmt: skip
        params_k = {
            **self.params, "U": self.U[: k - 1], "dt": self.dt[: k - 1].reshape(-1, 1),
            "Y": self.Y[:k], "lengthscale": lengthscale, **nominal_parameters(Q0, starts),
            "anchor_p": self.params["anchor_p"][: len(starts)],
            "anchor_q": self.params["anchor_q"][: len(starts)],
        }  # fmt: skip
        x0 = {
            "P": P0, "D": np.zeros((k, 3)),
            "bias_p": np.reshape(start["bias_p"], (-1, 3)),
            "bias_w": np.reshape(start["bias_w"], (-1, 3)),
        }  # fmt: skip
        held: tuple[str, ...] = ()
        if self.prior_map is None:
            Yk = sd.rotate(Q0, self.Y[:k])
            if s_k.tiled:  # whitened (casmag.model.tiledmap.RotatedTiledModel)
                tiles = s_k.tiles()
                w = ridge_tile_weights(
                    tiles, P0[:, :dim], Yk, self.c0, sigma_m, sigma_f, lengthscale
                )
                x0["W"] = w / np.sqrt(tiles.prior_variances(sigma_f, lengthscale))[:, None]
            else:
                basis = s_k.hilbert_basis()
                w = ridge_weights(
                    basis, kernel, P0[:, :dim], Yk, self.c0, sigma_m, sigma_f, lengthscale
                )
                x0["W"] = whiten(basis, kernel, sigma_f, lengthscale, w)
            x0["c"] = self.c0.reshape(3, 1)
        else:  # the saved map's box or tiles under its posterior
            s_k, prior_params, map0, held = self.prior_map.solve_inputs(
                s_k, P0[:, :dim], sd.quat_to_rotmat(Q0), self.Y[:k], sigma_f, lengthscale,
                hold=k < self.n or coarse,
            )  # fmt: skip
            params_k.update(prior_params)
            x0.update(map0)
            if self.prior_map.held and k == self.n:  # --hold-map: the map's noise added
                params_k["sigma_m"] = self.held_sigma_m(start["P"])
        return StageProblem(s_k, cached_pose_nlp, params_k, x0, dim, (*self.fixed, *held))

    # ------------------------------------------------------------ sliding windows
    sample_states = ("P", "Q")

    def step_lengths(self) -> np.ndarray:
        return np.linalg.norm(self.U[:, :3], axis=1)

    def _window_structure(self, k: int, solver: SolverSpec) -> PoseStructure:
        """A window of k samples, its box around the whole dead reckoning (as the planar
        windows')."""
        if self.options.form == "tiled":
            raise ValueError("sliding windows need model.gp.form reduced_rank, not tiled")
        if len(self.session_starts) > 1:
            raise ValueError("sliding windows: one session at a time, not several")
        s = pose_structure(
            self.options, k, self.P_dr, self.lengthscale, self.dim, self.height, solver
        )
        s = dataclasses.replace(s, window=True)
        if self.prior_map is not None:
            s = dataclasses.replace(s, basis=self.prior_map.basis)
        return s

    def window_prior(self) -> WindowPrior:
        if self.prior_map is not None:
            return self.prior_map.window_prior()
        basis = self._window_structure(2, self.solver).hilbert_basis()
        sigma_lin, sigma_m = self.params["sigma_lin"], self.params["sigma_m"]
        return WindowPrior.gp(basis, self.options.kernel, sigma_lin, sigma_m)

    def _window_odometry(self, a: int, k: int, bias: dict[str, np.ndarray]) -> np.ndarray:
        """Increments of [a, a + k) with the total biases removed: dp - b_p, dq exp(-b_w dt)."""
        U = self.U[a : a + k - 1].copy()
        U[:, :3] -= np.ravel(bias["bias_p"])
        h = self.dt[a : a + k - 1].reshape(-1, 1)
        U[:, 3:7] = sd.quat_mul(
            sd.quat_normalize(U[:, 3:7]), sd.quat_exp(-h * np.ravel(bias["bias_w"]))
        )
        return U

    def _anchor(self, anchor: dict[str, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
        if anchor is None:
            return self.p0, self.q0
        return np.asarray(anchor["P"])[0], sd.quat_normalize(np.asarray(anchor["Q"])[0])

    def window_start(
        self, a: int, k: int, anchor: dict[str, np.ndarray] | None,
        carried: dict[str, np.ndarray] | None, bias: dict[str, np.ndarray],
    ) -> dict[str, np.ndarray]:  # fmt: skip
        U = self._window_odometry(a, k, bias)
        if carried is None:
            P, Q = sd.dead_reckon_pose(U, *self._anchor(anchor))
        else:
            m = carried["P"].shape[0]
            Pr, Qr = sd.dead_reckon_pose(U[m - 1 :], carried["P"][-1], carried["Q"][-1])
            P, Q = np.vstack([carried["P"], Pr[1:]]), np.vstack([carried["Q"], Qr[1:]])
        return {"P": P, "Q": Q, "bias_p": np.zeros(3), "bias_w": np.zeros(3)}

    def solve_window(self, w: Window) -> Solved:
        # The anchor prior takes the standard deviations (anchor_sigma), not anchor_cov.
        a, k, start, bias, prior, solver = w.first, w.samples, w.start, w.bias, w.prior, w.solver
        s_k = self._window_structure(k, solver)
        nlp_k = cached_pose_nlp(s_k)
        p0, q0 = self._anchor(w.anchor)
        P0, Q0 = start["P"], sd.quat_normalize(start["Q"])
        params = {
            **self.params, "U": self._window_odometry(a, k, bias),
            "dt": self.dt[a : a + k - 1].reshape(-1, 1), "Y": self.Y[a : a + k],
            "anchor_p": p0.reshape(1, 3), "anchor_q": q0.reshape(1, 4),
            "map_mean": prior.mean.reshape(-1, 1), "map_precision": prior.Lam,
            **nominal_parameters(Q0),
        }  # fmt: skip
        for key, sigma in (("bias_p", "sigma_bp"), ("bias_w", "sigma_bw")):
            if w.bias_cov is not None and key in w.bias_cov:  # one for every axis: the largest
                params[sigma] = float(np.sqrt(np.max(np.diag(w.bias_cov[key]))))
        if w.anchor_sigma is not None:
            params["sigma_anchor"] = float(np.max(w.anchor_sigma["P"]))
            params["sigma_att0"] = float(np.max(w.anchor_sigma["Q"]))
        basis = s_k.hilbert_basis()
        J = rotated_design(
            basis, self.options.kernel, P0[:, : self.dim], sd.quat_to_rotmat(Q0),
            self.params["sigma_f"], self.lengthscale,
        )  # fmt: skip
        x0 = {
            "P": P0, "D": np.zeros((k, 3)), "bias_p": np.zeros((1, 3)), "bias_w": np.zeros((1, 3)),
            **prior.start(J, self.Y[a : a + k].reshape(-1), basis.num_basis),
        }  # fmt: skip
        sol = nlp_k.solve(params, x0, progress=self.progress, fixed=self.fixed)
        return Solved(sol, nlp_k, s_k, self.lengthscale, nominal=Q0, first=a)

    def anchor_indices(self, solved: Solved, j: int) -> dict[str, np.ndarray]:
        entries, k = solved.nlp.x_layout.entries, solved.structure.n
        return {  # column-major (k, 3); D: the orientation's correction
            "P": entries["P"].offset + j + k * np.arange(3),
            "Q": entries["D"].offset + j + k * np.arange(3),
        }

    def window_design(self, solved: Solved, m: int) -> tuple[np.ndarray, np.ndarray]:
        states, a = self.states(solved), solved.first
        J = rotated_design(
            solved.structure.hilbert_basis(), self.options.kernel, states["P"][:m, : self.dim],
            sd.quat_to_rotmat(states["Q"][:m]), self.params["sigma_f"], self.lengthscale,
        )  # fmt: skip
        return J, self.Y[a : a + m].reshape(-1)

    def joined(self, states: dict[str, np.ndarray], bias: dict[str, np.ndarray]) -> dict:
        return {"P": states["P"], "Q": states["Q"], **bias}


def solve_pose_recording(
    path: Any,
    options: PoseOptions | None = None,
    progress: Progress | None = None,
    anchor: str = "truth",
    method: str = "map",
    prior_map: SavedMap | None = None,
    map_source: str = "",
    hold_map: bool = False,
) -> Result:
    """Solve a pose recording (``dpx,dpy,dpz,dqw,dqx,dqy,dqz`` columns: a path, or a
    Recording already read); truth columns (``x_true,y_true,z_true``,
    ``qw_true,...``), when present, are used for evaluation only and (``anchor`` ``truth``,
    the default) for the first pose; ``origin``: the origin and the identity. ``method``: as
    for :func:`solve_pose`; ``prior_map``: locate it against a saved map (:func:`solve_pose`)."""
    rec = path if isinstance(path, Recording) else read_recording(path)
    if rec.motion != "pose":
        raise DataError(
            f"{rec.path}: motion input is {rec.motion!r}, the pose model needs "
            "dpx,dpy,dpz,dqw,dqx,dqy,dqz"
        )
    truth = None
    if rec.P_true is not None:
        truth = {"P": _truth_3d(rec.P_true)}
        if rec.q_true is not None:
            truth["q"] = rec.q_true
    start = {"p0": np.zeros(3), "q0": np.array([1.0, 0, 0, 0])} if anchor == "origin" else {}
    result = solve_pose(
        rec.increments, rec.Y, options, truth=truth, t=rec.t, progress=progress,
        name=Path(rec.path).stem, method=method, prior_map=prior_map, map_source=map_source,
        hold_map=hold_map,
        **start,
    )  # fmt: skip
    if anchor == "origin":
        result.info["anchor"]["kind"] = "origin"
    result.info["recording"] = str(rec.path)
    return result


def solve_pose_sessions(
    recordings: list[Any],
    options: PoseOptions | None = None,
    progress: Progress | None = None,
    name: str | None = None,
) -> Result:
    """Several pose recordings of one field (paths, or Recordings already read), one map,
    as casmag.solver.planar.solve_planar_sessions: each session starts at its first true
    pose (truth columns with the quaternion), keeps its own biases, and the sessions are
    added one at a time, the most self-revisiting dead reckoning first."""
    options = options or PoseOptions()
    recs = [r if isinstance(r, Recording) else read_recording(r) for r in recordings]
    require_first_poses(recs, "pose", "x, y[, z] and qw, qx, qy, qz")
    truths = [_truth_3d(r.P_true) for r in recs]
    paths, fields = [], []
    for rec, P_true in zip(recs, truths, strict=True):
        P, Q = sd.dead_reckon_pose(rec.increments, P_true[0], sd.quat_normalize(rec.q_true[0]))
        paths.append(P)
        fields.append(sd.rotate(Q, rec.Y))
    ell = hyperparameters_from_data(options, np.vstack(paths), np.vstack(fields))[1]
    order = revisit_order(paths, ell)
    st = Stacked.of([recs[i] for i in order], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    result = solve_pose(
        st.U, st.Y, options,
        truth={"P": np.vstack([truths[i] for i in order]),
               "q": np.vstack([recs[i].q_true for i in order])},
        t=st.t, progress=progress, name=name or "+".join(Path(r.path).stem for r in recs),
        starts=st.starts, session_names=st.names,
    )  # fmt: skip
    result.info["session_order"] = order
    result.info["recordings"] = [str(recs[i].path) for i in order]
    return result


def _truth_3d(P: np.ndarray) -> np.ndarray:
    """True positions as (N, 3): a 2-D truth at height 0."""
    return P if P.shape[1] == 3 else np.column_stack([P, np.zeros(P.shape[0])])
