"""Solving a translational problem: the batch MAP from the dead reckoning (or given
initial positions), with the estimated hyperparameters started from the windowed marginal
likelihood, the assumed values, or both kept by cost (``model.estimate_start``). The NLP
and its initial guess come from casmag.model.translational. The model as the warm-start
strategies of casmag.solver.staged see it (:class:`TranslationalStaged`: growing prefixes,
coarse-to-fine, sliding windows, several starts and sessions,
:func:`solve_translational_strategy`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from casmag.data.simulate import Dataset
from casmag.errors import ProblemError
from casmag.gp.hyper import estimate_conditional
from casmag.model.field import HYPERPARAMETERS
from casmag.model.rrmap import make_basis
from casmag.model.translational import (
    Structure,
    WindowStructure,
    cached_nlp,
    field_estimate,
    parameters,
    parameters_and_guess,
    positions,
)
from casmag.nlp import NLP, Solution, lowest_cost
from casmag.problem.spec import Problem, SolverSpec
from casmag.solver.staged import (
    Solved,
    Stage,
    StagedModel,
    Window,
    WindowPrior,
    map_lengthscale,
    solve_rehomed,
    solve_strategy,
)
from casmag.solver.windowing import continued


def estimate_start(
    problem: Problem, data: Dataset, s: Structure, initial_positions: np.ndarray | None = None
) -> dict[str, Any] | None:
    """Where the joint MAP starts the estimated sigma_f and lengthscale
    (``model.estimate_start``): None when neither is estimated; else a record with
    ``method``, ``values`` (the start of each estimated hyperparameter), ``assumed`` (the
    problem's values) and, for ``marginal_likelihood`` and ``both``, the estimate's details
    (casmag.gp.hyper.estimate_conditional at the initial positions, the other hyperparameters
    fixed at their assumed values, zero-mean field). With ``both`` the MAP is solved from
    ``values`` and from ``assumed`` (:func:`solve_translational`)."""
    free = [h for h in HYPERPARAMETERS if h in s.estimate and h != "sigma_m"]
    if not free:
        return None

    assumed = {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_m": problem.assumed_sigma_m,
    }
    method = problem.spec.model.estimate_start
    record: dict[str, Any] = {"method": method, "assumed": {h: assumed[h] for h in free}}
    if method == "assumed":
        record["values"] = {h: assumed[h] for h in free}
        return record
    P0 = data.dead_reckoning() if initial_positions is None else initial_positions
    est = estimate_conditional(
        P0, data.Y, s.kernel, assumed, free, sigma_lin=problem.spec.model.gp.sigma_lin or 0.0
    )
    record["values"] = {h: est.values[h] for h in free}
    record["marginal_likelihood"] = {
        "neg_log_marginal": est.neg_log_marginal,
        "windows": est.n_windows,
        "samples": est.n_samples,
        "converged": est.converged,
        "iterations": est.iterations,
    }
    return record


def _better_of_two_starts(
    nlp: NLP,
    sol: Solution,
    params: dict[str, Any],
    x0: dict[str, Any],
    start: dict[str, Any],
    progress: Any,
) -> Solution:
    """``estimate_start: both``: ``sol`` was solved from the marginal-likelihood start; solve
    again from the assumed values and keep the solution with the lower MAP cost (a
    successful solve before a failed one). Records both solves in ``start`` (``solves``,
    ``chosen``; ``values`` becomes the chosen start); the kept solution's solve_seconds is
    the sum of both solves."""
    ml = dict(start["values"])
    x0_assumed = dict(x0)
    for h, value in start["assumed"].items():
        x0_assumed[f"log_{h}"] = np.log(value)
    other = nlp.solve(params, x0_assumed, progress=progress)
    solves = {"marginal_likelihood": (ml, sol), "assumed": (dict(start["assumed"]), other)}
    names = list(solves)
    best_ok = lowest_cost([solves[k][1] for k in names])
    chosen = (
        names[best_ok]
        if best_ok is not None
        else min(names, key=lambda k: solves[k][1].objective)  # both failed: the lower
    )
    start["solves"] = {
        k: {
            "start": v,
            "objective": s.objective,
            "status": s.status,
            "iterations": s.iterations,
            "solve_seconds": s.solve_seconds,
        }
        for k, (v, s) in solves.items()
    }
    start["chosen"] = chosen
    start["values"] = solves[chosen][0]
    best = solves[chosen][1]
    best.solve_seconds = sol.solve_seconds + other.solve_seconds
    return best


def solve_translational(
    problem: Problem,
    data: Dataset,
    progress: Any = None,
    initial_positions: np.ndarray | None = None,
    lengthscale: float | None = None,
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure]:
    """Solve the problem on a data set. Returns the solution (``sol.x["P"]`` holds the
    estimated positions), the NLP, the final hyperparameters (estimated or fixed), the
    (N, 3) field estimate at the samples and the problem's structure. ``lengthscale``: a
    fixed lengthscale other than the assumed one (a coarse-to-fine stage: the map's basis
    stays the assumed lengthscale's, its weights are fitted at this one)."""
    s = Structure.of(problem, data, initial_positions)
    nlp = cached_nlp(s)
    start = estimate_start(problem, data, s, initial_positions)
    other = lengthscale is not None and lengthscale != problem.assumed_lengthscale
    if other and "lengthscale" in s.estimate:
        raise ProblemError(
            problem.source,
            "solver.warm_start.strategy",
            "coarse-to-fine fixes the lengthscale at each stage; it cannot be estimated",
        )
    params, x0 = parameters_and_guess(
        problem,
        data,
        s,
        initial_positions,
        None if start is None else start["values"],
        lengthscale if other else None,
    )
    sol, nlp, s = _solve(s, nlp, params, x0, progress)
    if start is not None and start["method"] == "both":
        sol = _better_of_two_starts(nlp, sol, params, x0, start, progress)
    if start is not None:
        sol.stats["estimate_start"] = start
    return _finish(s, nlp, sol, params)


def _finish(
    s: Structure, nlp: NLP, sol: Solution, params: dict[str, Any]
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure]:
    hyper = {
        h: float(np.exp(sol.x[f"log_{h}"][0, 0])) if h in s.estimate else float(params[h])
        for h in HYPERPARAMETERS
    }
    sol.x["P"] = positions(s, sol, params["Q"])
    return sol, nlp, hyper, field_estimate(s, sol, sol.x["P"]), s


def _solve_from(
    problem: Problem, data: Dataset, x: dict[str, Any], lengthscale: float, progress: Any
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure]:
    """The problem on ``data`` (its box around the dead reckoning) from a whole earlier
    solution ``x`` of the same structure, at a fixed ``lengthscale``."""
    s = Structure.of(problem, data)
    nlp = cached_nlp(s)
    params = parameters(problem, data, s)
    if "lengthscale" in params:  # fixed (coarse-to-fine refuses an estimated one)
        params["lengthscale"] = lengthscale
    x0 = {k: v for k, v in x.items() if k in nlp.x_layout.entries}
    sol, nlp, s = _solve(s, nlp, params, x0, progress)
    return _finish(s, nlp, sol, params)


def _solve(
    s: Structure, nlp: NLP, params: dict[str, Any], x0: dict[str, Any], progress: Any
) -> tuple[Solution, NLP, Structure]:
    """``nlp`` (``s``'s) solved from x0; a tiled map's is laid again around where its
    samples went when they leave its Hessian's pattern (casmag.solver.staged.solve_rehomed)."""
    Q = params["Q"]
    return solve_rehomed(
        s, lambda st, cache=True: nlp if st is s else cached_nlp(st, cache), params, x0,
        lambda sol: positions(s, sol, Q), progress=progress,
    )  # fmt: skip


@dataclass
class WindowSolve:
    """What a translational window leaves beside IPOPT's solution: the total per-step
    bias its odometry had removed ((1, d); its own ``bias`` is the increment on it)."""

    removed: np.ndarray


@dataclass
class TranslationalSolve:
    """What a translational solve leaves beside IPOPT's solution: the hyperparameters, the
    field at the samples, the data it solved (the increments with ``debias`` removed,
    one row per session) and that bias."""

    hyper: dict[str, float]
    field: np.ndarray
    data: Dataset
    debias: np.ndarray


class TranslationalStaged(StagedModel):
    """The translational model as the warm-start strategies see it (casmag.solver.staged):
    growing prefixes, coarse-to-fine, sliding windows, several starts kept by cost and
    several sessions run by the same code as the planar, pose and IMU models'. States:
    positions ``P`` and ``bias``, the total per-step odometry bias of each session reached
    (S, d). A solve removes its start's ``bias`` from the increments and estimates what is
    left (casmag.data.simulate.Dataset.debiased), from its start's positions (the dead
    reckoning: the plain batch, its box around the dead reckoning); a start that carries a
    solve's whole solution (``x``: a coarse-to-fine stage, the same samples again) starts
    the NLP there, the map's weights included. No heading-rate bias: the model has no
    heading. ``window_box``: the positions the sliding windows' map box is laid around
    (default the dead reckoning, so that it holds the truth wherever the drift took the
    odometry)."""

    def __init__(
        self,
        problem: Problem,
        data: Dataset,
        progress: Any = None,
        window_box: np.ndarray | None = None,
    ) -> None:
        self.problem, self.data, self.progress = problem, data, progress
        self.n, self.solver = data.n_samples, problem.spec.solver
        self.lengthscale = problem.assumed_lengthscale
        self.session_starts = tuple(int(i) for i in data.starts)
        self._window_box = window_box
        self._window_basis: tuple | None = None

    def _part(self, k: int, bias: np.ndarray) -> Dataset:
        part = self.data if k == self.n else self.data.prefix(k)
        return part.debiased(bias) if np.any(bias) else part

    def _bias(self, bias: np.ndarray | None, k: int) -> np.ndarray:
        """The per-session bias rows of the sessions the first k samples reach (zero for
        those not estimated yet)."""
        out = np.zeros((len(self.sessions(k)), self.data.dim))
        if bias is not None:
            b = np.reshape(bias, (-1, self.data.dim))[: out.shape[0]]
            out[: b.shape[0]] = b
        return out

    def start(self, k: int, bias: float | np.ndarray = 0.0) -> dict[str, np.ndarray]:
        """The dead reckoning of the first k samples with a per-step odometry ``bias``
        ((d,) or one row per session, casmag.solver.biasscan) removed; a scalar must be 0
        (the model has no heading to turn)."""
        b = np.asarray(bias, dtype=float)
        if b.ndim == 0 and b != 0.0:
            raise ValueError("the translational model has no heading to turn")
        rows = self._bias(None if b.ndim == 0 else b, k)
        return {"P": self._part(k, rows).dead_reckoning(), "bias": rows}

    def world_readings(self, states: dict[str, np.ndarray]) -> np.ndarray:
        """The readings of the samples ``states`` holds: the magnetometer does not turn."""
        return self.data.Y[: np.shape(states["P"])[0]]

    def states(self, solved: Solved) -> dict[str, np.ndarray]:
        if isinstance(solved.nominal, WindowSolve):  # the bias increment of the window
            bias = solved.sol.x.get("bias")
            return {"P": solved.sol.x["P"],
                    "bias": np.zeros((1, self.data.dim)) if bias is None else bias}  # fmt: skip
        own: TranslationalSolve = solved.nominal
        bias = solved.sol.x.get("bias")
        total = own.debias if bias is None else own.debias + np.reshape(bias, own.debias.shape)
        return {"P": solved.sol.x["P"], "bias": total}

    def extend(self, states: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        """The positions continued by the dead reckoning with each session's bias removed:
        joined to the last position in the session it reached, from its anchor in a
        session not reached."""
        bias = self._bias(states["bias"], k)
        P, m = np.asarray(states["P"]), states["P"].shape[0]
        DR = self._part(k, bias).dead_reckoning()
        out = [P[: min(m, k)]]
        for a, e in self.sessions(k):
            if e <= m:
                continue
            if a < m:  # the session m reached: joined to its last position
                out.append(DR[m:e] - DR[m - 1] + P[m - 1])
            else:
                out.append(DR[a:e])
        return {"P": np.vstack(out), "bias": bias}

    def continue_from(self, previous: Solved, k: int) -> dict[str, np.ndarray]:
        if k == previous.sol.x["P"].shape[0]:  # the same samples again: the whole solution
            own: TranslationalSolve = previous.nominal
            return {
                "P": previous.sol.x["P"], "bias": own.debias, "x": previous.sol.x,
                "solved": previous,
            }  # fmt: skip
        return super().continue_from(previous, k)

    def solve(
        self, k: int, start: dict[str, np.ndarray], solver: SolverSpec, lengthscale: float
    ) -> Solved:
        problem = self.problem
        if solver != problem.spec.solver:
            problem = Problem(spec=problem.spec.model_copy(update={"solver": solver}),
                              source=problem.source)  # fmt: skip
        if problem.spec.model.gp.form == "tiled":
            # Tiles for the stage's lengthscale (casmag.solver.staged.map_lengthscale).
            # Another stage's weights do not carry over: they are fitted again from its
            # positions, with the total bias it estimated removed (its states).
            ell = map_lengthscale(True, self.lengthscale, lengthscale)
            if ell != self.lengthscale:
                problem = problem.with_overrides([f"model.gp.lengthscale={ell}"])
            if "solved" in start and start["solved"].lengthscale != lengthscale:
                start = self.states(start["solved"])
        debias = self._bias(start.get("bias"), k)
        part = self._part(k, debias)
        P0 = np.asarray(start["P"])
        if "x" in start:
            sol, nlp, hyper, field, s = _solve_from(
                problem, part, start["x"], lengthscale, self.progress
            )
        else:
            initial = None if np.array_equal(P0, part.dead_reckoning()) else P0
            sol, nlp, hyper, field, s = solve_translational(
                problem, part, self.progress, initial, lengthscale
            )
        return Solved(
            sol, nlp, s, lengthscale, nominal=TranslationalSolve(hyper, field, part, debias)
        )

    # ------------------------------------------------------------ sliding windows
    # Each window is the translational model of its samples (WindowStructure: one session,
    # knots, the bias increment under a Gaussian prior) with the map a WindowField on one
    # box around the whole recording. Its first position is held to the previous window's
    # estimate there by the model's anchor prior (``model.anchor.sigma``, not that
    # estimate's Laplace marginal), and the prior on its bias increment is the inverse of
    # the previous window's whole Laplace covariance of it.

    def step_lengths(self) -> np.ndarray:
        return np.linalg.norm(self.data.U, axis=1)

    def _window_structure(self, k: int, solver: SolverSpec) -> WindowStructure:
        problem, m = self.problem, self.problem.spec.model
        kernel = problem.assumed_kernel
        if len(self.session_starts) > 1:
            raise ValueError("sliding windows: one session at a time, not several")
        if kernel == "div_free":
            raise ProblemError(
                problem.source,
                "solver.warm_start.strategy",
                "sliding windows need a reduced-rank map (kernel se or curl_free, not div_free)",
            )
        if self._window_basis is None:
            X = self.data.dead_reckoning() if self._window_box is None else self._window_box
            hb = make_basis(kernel, X, problem.assumed_lengthscale, m.gp.num_basis, m.gp.margin)
            self._window_basis = (tuple(hb.domain.center), tuple(hb.domain.half_width),
                                  hb.num_basis)  # fmt: skip
        return WindowStructure(
            n=k,
            dim=self.data.dim,
            kernel=kernel,
            basis=self._window_basis,
            knot_every=min(m.trajectory.knot_every, k - 1),
            constant_field=m.gp.sigma_lin is not None,
            estimate_bias=m.odometry.estimate_bias,
            solver=solver.model_dump_json(),
        )

    def window_prior(self) -> WindowPrior:
        """The GP prior of the box's weights (and constant field), zero mean."""
        p = self.problem
        s = self._window_structure(2, self.solver)
        Lam = s.prior_precision(p.assumed_sigma_f, p.assumed_lengthscale, p.spec.model.gp.sigma_lin)
        return WindowPrior(np.zeros(s.prior_shape), Lam, p.assumed_sigma_m)

    def _window_odometry(
        self, a: int, k: int, anchor: dict[str, np.ndarray] | None, bias: dict[str, np.ndarray]
    ) -> np.ndarray:
        """The window's dead reckoning Q (k, d) with the total ``bias`` removed, from
        ``anchor`` (None: the recording's)."""
        p0 = np.asarray(self.data.anchor, dtype=float) if anchor is None else anchor["P"][0]
        U = self.data.U[a : a + k - 1] - np.reshape(bias["bias"], (-1, self.data.dim))[0]
        return np.vstack([p0, p0 + np.cumsum(U, axis=0)])

    def window_start(
        self, a: int, k: int, anchor: dict[str, np.ndarray] | None,
        carried: dict[str, np.ndarray] | None, bias: dict[str, np.ndarray],
    ) -> dict[str, np.ndarray]:  # fmt: skip
        Q = self._window_odometry(a, k, anchor, bias)
        P = Q if carried is None else continued(np.asarray(carried["P"]), Q)
        return {"P": P, "bias": np.zeros((1, self.data.dim))}

    def solve_window(self, w: Window) -> Solved:
        # The anchor is held by the model's anchor prior (anchor_sigma and anchor_cov unused).
        a, k, start, bias, prior, solver = w.first, w.samples, w.start, w.bias, w.prior, w.solver
        m, d = self.problem.spec.model, self.data.dim
        s = self._window_structure(k, solver)
        nlp = s.nlp()
        knots = s.knots
        Q = self._window_odometry(a, k, w.anchor, bias)
        C0 = knots.fit(Q, np.asarray(start["P"]))
        P0 = knots.positions(Q, C0)
        Y = self.data.Y[a : a + k]
        if w.bias_cov and "bias" in w.bias_cov:
            precision = np.linalg.inv(w.bias_cov["bias"])
        else:  # the first window: the model's prior on the total bias, zero mean
            sigma_b = m.odometry.bias_prior_sigma
            precision = np.eye(d) * (0.0 if sigma_b is None else sigma_b**-2)
        params = {
            "Q": Q,
            "Y": Y,
            "anchor": Q[:1],
            "sigma_o": self.problem.assumed_sigma_odometry,
            "sigma_anchor": m.anchor.sigma,
            "sigma_m": prior.sigma_m,
            "bias_mean": np.zeros((1, d)),
            "bias_precision": precision,
            "map_mean": prior.mean,
            "map_precision": prior.Lam,
        }
        x0: dict[str, Any] = {"C": C0, **s.unknowns(prior.posterior_mean(*s.design(P0, Y)))}
        if s.estimate_bias:
            x0["bias"] = np.zeros((1, d))
        sol = nlp.solve(params, x0, progress=self.progress)
        sol.x["P"] = knots.positions(Q, sol.x["C"])
        removed = np.reshape(bias["bias"], (1, d)).copy()
        return Solved(sol, nlp, s, self.lengthscale, nominal=WindowSolve(removed), first=a)

    def anchor_indices(self, solved: Solved, j: int) -> dict[str, np.ndarray]:
        return {}  # the positions are the knots' functions, and the anchor prior is fixed

    def window_design(self, solved: Solved, m: int) -> tuple[np.ndarray, np.ndarray]:
        a = solved.first
        return solved.structure.design(solved.sol.x["P"][:m], self.data.Y[a : a + m])

    def joined(self, states: dict[str, np.ndarray], bias: dict[str, np.ndarray]) -> dict:
        return {"P": states["P"], "bias": np.reshape(bias["bias"], (1, self.data.dim))}


def stage_record(
    model: TranslationalStaged, st: Stage, build_seconds: float | None = None
) -> dict[str, Any]:
    """A result's ``stages`` record of one solve of a strategy (``prefix``, ``lengthscale``,
    ``window`` or ``batch``): samples, IPOPT's outcome (a window's ``Left_Map_Box`` when its
    path left the map's box), seconds (``build_seconds``: the NLP's, default its own), the
    total bias it left (None when the bias is not estimated); the others' also the first
    sample and lengthscale, a window's also the standard deviations of the bias it handed
    the next window (``bias_sigma``, None when none)."""
    so, nlp = st.solved.sol, st.solved.nlp
    estimated = model.problem.spec.model.odometry.estimate_bias
    bias = model.states(st.solved)["bias"]
    if isinstance(st.solved.nominal, WindowSolve):  # the increment on what was removed
        bias = st.solved.nominal.removed + np.reshape(bias, (1, -1))
    record: dict[str, Any] = {
        "name": st.kind,
        "samples": st.samples,
        "status": st.status,
        "success": so.success,
        "iterations": so.iterations,
        "rounds": so.rounds,
        "solve_seconds": so.solve_seconds,
        "build_seconds": nlp.build_seconds if build_seconds is None else build_seconds,
        "bias": [float(v) for v in np.ravel(bias)] if estimated else None,
    }
    if st.kind != "prefix":
        record |= {"start": st.first, "lengthscale": st.lengthscale}
    if st.kind == "window":
        handed = None if st.handed is None else st.handed.get("bias")
        record["bias_sigma"] = None if handed is None else [float(v) for v in handed]
    return record


def solve_translational_strategy(
    problem: Problem, data: Dataset, progress: Any = None
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure, Dataset, list[dict[str, Any]]]:
    """The warm start ``solver.warm_start`` (growing, coarse-to-fine or sliding) of
    casmag.solver.staged on the translational model. Returns the last stage's solution
    (``sol.x["bias"]``: the total per-step bias), NLP, hyperparameters, field, structure,
    the data it solved (the increments with the earlier stages' bias removed) and every
    stage's record."""
    model = TranslationalStaged(problem, data, progress)
    stages = solve_strategy(model, problem.spec.solver.warm_start)
    last = stages[-1].solved
    own: TranslationalSolve = last.nominal
    sol = last.sol
    built: set[int] = set()  # an NLP re-solved (a window's) counts its build once
    records = []
    for st in stages:
        first = id(st.solved.nlp) not in built
        built.add(id(st.solved.nlp))
        records.append(stage_record(model, st, None if first else 0.0))
    if problem.spec.model.odometry.estimate_bias and "bias" in sol.x:
        sol.x["bias"] = model.states(last)["bias"]
    return sol, last.nlp, own.hyper, own.field, last.structure, own.data, records
