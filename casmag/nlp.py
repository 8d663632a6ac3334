"""A small builder for MAP problems as CasADi NLPs with named variables, parameters and cost
blocks, solved by IPOPT.

Build first, solve second: :class:`NLPBuilder` collects symbols and named cost blocks;
:meth:`NLPBuilder.build` creates the IPOPT solver once; :meth:`NLP.solve` is then called any
number of times with new parameter values and initial guesses (including multipliers, for
warm starts), which is what sweeps and windowing rely on.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from casmag import interrupt, memory
from casmag.problem.spec import SolverSpec

#: A solve's progress callback: (iteration, cost, max-norm of the step, seconds).
Progress = Callable[[int, float, float, float], None]

#: IPOPT's status when :meth:`NLP.solve` with ``stop_when_stalled`` stopped it.
STALLED = "User_Requested_Stop"
#: Stalled: the objective changed by at most this fraction of max(1, |f|) over
#: STALL_ITERATIONS consecutive iterations (no progress measurable in double precision).
STALL_RELATIVE = 1e-12
STALL_ITERATIONS = 3
#: The status of a solve refused before it started, or stopped, because its memory would
#: exceed ``solver.memory_budget`` (casmag.memory).
MEMORY_STATUS = "Memory_Budget_Exceeded"


class _Progress(ca.Callback):
    """IPOPT iteration callback: hands (iteration, cost, step norm, seconds) to ``sink``
    when one is set for the current solve, and stops IPOPT (status :data:`STALLED`) when
    ``stop_when_stalled`` is set and the objective has stopped changing, or when the
    process's resident memory has passed ``budget`` bytes (``over_budget`` then set)."""

    def __init__(self, n_x: int, n_p: int, budget: int | None = None):
        ca.Callback.__init__(self)
        self._sizes = {"x": n_x, "f": 1, "g": 0, "lam_x": n_x, "lam_g": 0, "lam_p": n_p}
        self.sink: Callable[[int, float, float, float], None] | None = None
        self.stop_when_stalled = False
        self.stop_when: Callable[[], bool] | None = None
        self.budget = budget
        self._reset()
        self.construct("casmag_progress", {})

    def _reset(self) -> None:
        self._k, self._x, self._t0 = 0, None, time.perf_counter()
        self._costs: list[float] = []
        self.over_budget = False

    def start(
        self,
        sink: Callable[[int, float, float, float], None] | None,
        stop_when_stalled: bool,
        stop_when: Callable[[], bool] | None = None,
    ) -> None:
        self.sink = sink
        self.stop_when_stalled = stop_when_stalled
        self.stop_when = stop_when
        self._reset()

    def _stalled(self, cost: float) -> bool:
        self._costs.append(cost)
        last = self._costs[-(STALL_ITERATIONS + 1) :]
        if len(last) <= STALL_ITERATIONS:
            return False
        return max(last) - min(last) <= STALL_RELATIVE * max(1.0, abs(cost))

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self._sizes[ca.nlpsol_out(i)], 1)

    def eval(self, args: list[Any]) -> list[Any]:
        cost = float(args[1])
        if self.sink is not None:
            x = np.asarray(args[0]).ravel()
            step = 0.0 if self._x is None else float(np.max(np.abs(x - self._x)))
            self.sink(self._k, cost, step, time.perf_counter() - self._t0)
            self._x = x
        self._k += 1
        if self.budget is not None and memory.rss_bytes() > self.budget:
            self.over_budget = True
        stop = (
            interrupt.pending()
            or self.over_budget
            or (self.stop_when_stalled and self._stalled(cost))
            or (self.stop_when is not None and self.stop_when())
        )
        return [1 if stop else 0]


@dataclass(frozen=True)
class _Entry:
    name: str
    shape: tuple[int, int]
    offset: int

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]


class _Layout:
    """Names and places of matrix-shaped symbols stacked column-major into one vector."""

    def __init__(self) -> None:
        self.entries: dict[str, _Entry] = {}
        self.symbols: list[ca.MX] = []
        self.size = 0

    def add(self, name: str, shape: tuple[int, int]) -> ca.MX:
        if name in self.entries:
            raise ValueError(f"symbol {name!r} defined twice")
        sym = ca.MX.sym(name, *shape)
        self.entries[name] = _Entry(name, shape, self.size)
        self.symbols.append(sym)
        self.size += shape[0] * shape[1]
        return sym

    def pack(self, values: Mapping[str, Any], default: float | None = None) -> np.ndarray:
        out = np.full(self.size, np.nan if default is None else default)
        for name, e in self.entries.items():
            if name in values:
                v = np.asarray(values[name], dtype=float)
                if v.size == 1 and e.size != 1:
                    v = np.full(e.shape, float(v))
                if v.shape != e.shape and v.size == e.size and 1 in e.shape:
                    v = v.reshape(e.shape)
                if v.shape != e.shape:
                    raise ValueError(f"{name}: expected shape {e.shape}, got {v.shape}")
                out[e.offset : e.offset + e.size] = v.reshape(-1, order="F")
            elif default is None:
                raise ValueError(f"no value given for {name!r}")
        return out

    def unpack(self, vector: Any) -> dict[str, np.ndarray]:
        v = np.asarray(vector, dtype=float).ravel()
        return {
            n: v[e.offset : e.offset + e.size].reshape(e.shape, order="F")
            for n, e in self.entries.items()
        }

    def vector(self) -> ca.MX:
        return ca.vertcat(*[ca.vec(s) for s in self.symbols]) if self.symbols else ca.MX(0, 1)


class NLPBuilder:
    """Collects variables, parameters and named cost blocks of a MAP problem.

    Each cost block is a scalar expression, by convention a negative log-density (halved
    squared residual norms plus normalisation terms), so blocks add up to the objective.
    """

    def __init__(self) -> None:
        self._x = _Layout()
        self._p = _Layout()
        self._lbx: dict[str, float] = {}
        self._ubx: dict[str, float] = {}
        self.blocks: dict[str, ca.MX] = {}
        self.residuals: dict[str, ca.MX] = {}
        self.curved: set[str] = set()  # residual blocks that keep their exact Hessian
        self.quadratics: dict[str, tuple[int, ca.MX]] = {}
        self._callbacks: list[ca.Callback] = []

    def retain(self, callback: ca.Callback) -> ca.Callback:
        """Keep a Python callback alive as long as the built NLP (CasADi holds no reference)."""
        self._callbacks.append(callback)
        return callback

    def variable(
        self, name: str, shape: tuple[int, int], lb: float = -np.inf, ub: float = np.inf
    ) -> ca.MX:
        """A decision variable of the given (rows, cols) shape."""
        self._lbx[name], self._ubx[name] = lb, ub
        return self._x.add(name, shape)

    def parameter(self, name: str, shape: tuple[int, int]) -> ca.MX:
        """A parameter: data or a fixed setting, given a value at each solve."""
        return self._p.add(name, shape)

    def cost(self, name: str, expr: ca.MX) -> None:
        """Add a named scalar cost block; adding to an existing name accumulates."""
        if expr.shape != (1, 1):
            raise ValueError(f"cost block {name!r} must be scalar, got {expr.shape}")
        self.blocks[name] = self.blocks[name] + expr if name in self.blocks else expr

    def residual(self, name: str, r: ca.MX, curvature: bool = False) -> None:
        """Add the block 0.5 |r|^2 and remember r: its Hessian can then be taken as J^T J
        (``residuals`` of :meth:`build`), sparse and symbolic. The IMU residuals need it:
        their exact Hessian is indefinite in the weakly determined drift directions, and
        IPOPT's inertia correction then stalls (measured: 90 iterations at a cost plateau).
        ``curvature``: the block keeps its exact Hessian unless ``solver.hessian`` is
        ``gauss-newton`` (:meth:`gauss_newton_residuals`): the planar and pose odometry,
        where J^T J alone made IPOPT converge only linearly once the map had pulled the
        path off its dead reckoning (measured on a 1,500-sample planar floor walk: 131
        iterations at full steps, the dual infeasibility falling 6 % per iteration,
        against 22 with the exact block)."""
        self.residuals[name] = ca.vec(r)
        if curvature:
            self.curved.add(name)
        self.cost(name, 0.5 * ca.sumsqr(r))

    def gauss_newton_residuals(self, hessian: str) -> dict[str, ca.MX]:
        """The residual blocks whose Hessian is J^T J under ``solver.hessian`` = hessian:
        every one under ``gauss-newton``; under ``auto`` and ``hybrid`` those not declared
        with ``curvature``; none under ``exact``."""
        if hessian == "gauss-newton":
            return dict(self.residuals)
        if hessian in ("auto", "hybrid"):
            return {n: r for n, r in self.residuals.items() if n not in self.curved}
        return {}

    def quadratic(self, name: str, first: str, z: ca.MX, mean: ca.MX, precision: ca.MX) -> None:
        """Add the block 0.5 (z - mean)^T precision (z - mean) on the unknowns z, which are
        the x entries from the variable ``first`` on (declared one after another), with the
        symmetric ``precision`` a parameter; its Hessian is that parameter, placed in the
        Hessian as it is (CasADi's symbolic Hessian of a dense quadratic form of 897
        unknowns took 68 s to build, and J^T J of its Cholesky residual a dense product at
        every evaluation)."""
        r = z - mean
        self.quadratics[name] = (self.offset(first), precision)
        self.cost(name, 0.5 * ca.dot(r, ca.mtimes(precision, r)))

    def x_vector(self) -> ca.MX:
        """The variables declared so far, stacked (a prefix of the final x)."""
        return self._x.vector()

    def p_vector(self) -> ca.MX:
        """The parameters declared so far, stacked (a prefix of the final p)."""
        return self._p.vector()

    def offset(self, name: str, of: str = "x") -> int:
        """Position of a variable (of="x") or parameter (of="p") in its stacked vector."""
        return (self._x if of == "x" else self._p).entries[name].offset

    @property
    def sizes(self) -> tuple[int, int]:
        return self._x.size, self._p.size

    def build(
        self,
        solver: SolverSpec,
        name: str = "casmag",
        gauss_newton: tuple[str | tuple[str, ...], ca.Function] | None = None,
        residuals: Mapping[str, ca.MX] | None = None,
    ) -> NLP:
        """Create the IPOPT solver once; returns an NLP that can be solved many times.

        gauss_newton: (block name or names, function (x, p, lam_f, lam_g) -> upper-triangular
        Hessian of those blocks). residuals: {block name: residual vector r} of blocks
        0.5 |r|^2 whose Hessian is taken as J^T J (symbolic, sparse). IPOPT then gets these
        plus CasADi's exact Hessian of all other blocks through ``hess_lag``.
        """
        t0 = time.perf_counter()
        x, p = self._x.vector(), self._p.vector()
        f = sum(self.blocks.values(), ca.MX(0))
        nlp = {"x": x, "p": p, "f": f}
        # IPOPT's own choice: every mode but limited-memory hands it a Hessian.
        hessian = "limited-memory" if solver.hessian == "limited-memory" else "exact"
        opts: dict[str, Any] = {
            "ipopt.max_iter": solver.max_iter,
            "ipopt.tol": solver.tol,
            "ipopt.print_level": solver.print_level,
            "ipopt.linear_solver": solver.linear_solver,
            "ipopt.hessian_approximation": hessian,
            "ipopt.sb": "yes",  # no IPOPT banner
            # No ipopt.opt from the working folder: every option comes from the problem
            # file, where it is checked (casmag.problem.ipopt).
            "ipopt.option_file_name": "",
            "print_time": False,
        }
        residuals = dict(residuals or {})
        if (gauss_newton is not None or residuals or self.quadratics) and hessian == "exact":
            special = set(residuals) | set(self.quadratics)
            if gauss_newton is not None:
                names = gauss_newton[0]
                special |= {names} if isinstance(names, str) else set(names)
            others = sum((e for n, e in self.blocks.items() if n not in special), ca.MX(0))
            lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 0)
            H = ca.triu(ca.hessian(others, x)[0])
            for r in residuals.values():
                J = ca.jacobian(r, x)
                H = H + ca.triu(ca.mtimes(J.T, J))
            for offset, precision in self.quadratics.values():
                nz, n_x = precision.shape[0], x.shape[0]
                H = H + ca.diagcat(
                    ca.MX(offset, offset), ca.triu(precision), ca.MX(n_x - offset - nz, 0)
                )
            if gauss_newton is not None:
                H = H + gauss_newton[1](x, p, lam_f, lam_g)
            opts["hess_lag"] = ca.Function(
                "hess_lag",
                [x, p, lam_f, lam_g],
                [lam_f * H],
                ["x", "p", "lam_f", "lam_g"],
                ["triu_hess_gamma_x_x"],
            )
        opts.update({f"ipopt.{k}": v for k, v in solver.ipopt.items()})
        progress = _Progress(self._x.size, self._p.size, memory.budget_bytes(solver.memory_budget))
        opts["iteration_callback"] = progress
        ipopt = ca.nlpsol(name, "ipopt", nlp, opts)
        names = list(self.blocks)
        blocks = ca.Function(f"{name}_blocks", [x, p], [self.blocks[n] for n in names])
        return NLP(
            solver=ipopt,
            keep=gauss_newton,
            callbacks=list(self._callbacks),
            progress=progress,
            block_names=names,
            blocks_fn=blocks,
            x_layout=self._x,
            p_layout=self._p,
            lbx=self._x.pack(self._lbx),
            ubx=self._x.pack(self._ubx),
            build_seconds=time.perf_counter() - t0,
        )


@dataclass
class Solution:
    """Outcome of one IPOPT solve. x, lam_x: by variable name; stats: IPOPT's statistics."""

    x: dict[str, np.ndarray]
    lam_x: np.ndarray
    status: str
    success: bool
    iterations: int
    solve_seconds: float
    objective: float
    cost_per_iteration: list[float]
    inf_pr_per_iteration: list[float]
    blocks_before: dict[str, float]
    blocks_after: dict[str, float]
    stats: dict[str, Any] = field(repr=False, default_factory=dict)
    rounds: int = 1  # IPOPT runs summed in this solution (re-centred solves)
    inf_du_per_iteration: list[float] = field(default_factory=list)
    # What it was solved with (NLP.solve): the parameter values and the variables held
    # fixed; the Laplace covariance evaluates the Hessian there (casmag.solver.uncertainty).
    params: Mapping[str, Any] | None = field(default=None, repr=False)
    fixed: tuple[str, ...] = ()

    def cost_blocks(self) -> dict[str, dict[str, float]]:
        """Each named cost block at the initial guess and at the solution, as a result's
        ``cost_blocks``: ``{name: {"before": ..., "after": ...}}``."""
        return {
            n: {"before": self.blocks_before[n], "after": self.blocks_after[n]}
            for n in self.blocks_before
        }

    def trace(self, stage: str) -> dict[str, Any]:
        """This solve's convergence record for a result's ``convergence`` list: the stage's
        name, IPOPT's status and iterations, and per iteration (iteration 0 first) the
        objective, the primal infeasibility (0 for casmag's unconstrained NLPs) and the dual
        infeasibility (the gradient's scaled max-norm, what the tolerance is checked on)."""
        return {
            "stage": stage,
            "status": self.status,
            "iterations": self.iterations,
            "objective": list(self.cost_per_iteration),
            "inf_pr": list(self.inf_pr_per_iteration),
            "inf_du": list(self.inf_du_per_iteration),
        }


def lowest_cost(
    solutions: Sequence[Solution], costs: Sequence[float | None] | None = None
) -> int | None:
    """Index of the successful solution with the lowest MAP cost (``costs``, by default
    each solution's objective), None when none succeeded: how every choice among several
    starts is made (two starts of a recording, heading-bias starts, hyperparameter starts)."""
    values = [s.objective for s in solutions] if costs is None else list(costs)
    ok = [i for i, s in enumerate(solutions) if s.success]
    return min(ok, key=lambda i: values[i]) if ok else None


@dataclass
class NLP:
    """A built MAP problem; call :meth:`solve` with parameter values and an initial guess."""

    solver: ca.Function
    block_names: list[str]
    blocks_fn: ca.Function
    x_layout: _Layout
    p_layout: _Layout
    lbx: np.ndarray
    ubx: np.ndarray
    build_seconds: float
    keep: Any = None  # objects the solver calls back into (kept alive)
    callbacks: list[Any] = field(default_factory=list)  # numpy blocks (kept alive)
    progress: _Progress | None = None
    _nonzeros: int | None = field(default=None, repr=False)

    def evaluate_blocks(self, x: np.ndarray, p: np.ndarray) -> dict[str, float]:
        values = self.blocks_fn(x, p)
        values = values if isinstance(values, (list, tuple)) else [values]
        return {n: float(v) for n, v in zip(self.block_names, values, strict=True)}

    def hessian(self, x: Mapping[str, Any], params: Mapping[str, Any]) -> Any:
        """The Hessian of the objective at x (named variables) as a symmetric scipy CSC
        matrix: IPOPT's own ``nlp_hess_l`` with lam_f = 1, where a numpy map block (casmag.
        rrmap) contributes its Gauss-Newton term J^T J, which is positive semi-definite (the
        Hessian of a Laplace approximation; at a MAP with small residuals it is the exact one
        to first order)."""
        import scipy.sparse as sp

        h = self.solver.get_function("nlp_hess_l")
        mode_owner = (
            self.keep[1] if self.keep is not None and hasattr(self.keep[1], "mode") else None
        )
        mode = mode_owner.mode if mode_owner is not None else None
        if mode_owner is not None:
            mode_owner.mode = "gauss-newton"
        try:
            H = h(self.x_layout.pack(x), self.p_layout.pack(params), 1.0, np.zeros(0))
        finally:
            if mode_owner is not None:
                mode_owner.mode = mode
                if hasattr(mode_owner, "reset"):
                    mode_owner.reset()
        H = H.sparse() if hasattr(H, "sparse") else H
        upper = sp.csc_matrix(H)
        return (upper + sp.triu(upper, k=1).T).tocsc()

    def hessian_nonzeros(self) -> int:
        """Non-zeros of the upper-triangular Hessian IPOPT factorises (its pattern is fixed
        when the NLP is built); with ``solver.hessian: limited-memory`` (no Hessian) those
        of the constraint Jacobian plus the diagonal that stands in for it."""
        if self._nonzeros is None:
            if self.solver.has_function("nlp_hess_l"):
                pattern = self.solver.get_function("nlp_hess_l").sparsity_out(0)
                self._nonzeros = int(pattern.nnz())
            else:
                jac = self.solver.get_function("nlp_jac_g").sparsity_out("jac_g_x")
                self._nonzeros = int(jac.nnz()) + self.x_layout.size
        return self._nonzeros

    def _refused(
        self, x0: np.ndarray, before: dict[str, float], estimate: int, budget: int
    ) -> Solution:
        """The failed solution of a solve refused by the memory budget: x0 unchanged."""
        message = memory.over_budget_message(estimate, budget, self.hessian_nonzeros())
        return Solution(
            x=self.x_layout.unpack(x0),
            lam_x=np.zeros(x0.size),
            status=MEMORY_STATUS,
            success=False,
            iterations=0,
            solve_seconds=0.0,
            objective=float(sum(before.values())),
            cost_per_iteration=[],
            inf_pr_per_iteration=[],
            blocks_before=before,
            blocks_after=before,
            stats={"return_status": MEMORY_STATUS, "success": False, "memory": message},
        )

    def solve(
        self,
        params: Mapping[str, Any],
        x0: Mapping[str, Any],
        lam_x0: np.ndarray | None = None,
        progress: Callable[[int, float, float, float], None] | None = None,
        stop_when_stalled: bool = False,
        fixed: Collection[str] = (),
        stop_when: Callable[[], bool] | None = None,
    ) -> Solution:
        """Solve for the given parameters from the initial guess x0 (every variable named).

        progress: called after every IPOPT iteration with (iteration, cost, max-norm of the
        step, seconds since the solve started). stop_when_stalled: stop IPOPT (status
        :data:`STALLED`) once the objective no longer changes measurably (STALL_RELATIVE
        over STALL_ITERATIONS iterations), for a caller that re-centres and solves again.
        fixed: variables held at their x0 values (bounds lbx = ubx; IPOPT takes them out of
        the problem it factorises), e.g. a known map's weights. stop_when: asked after every
        iteration; True stops IPOPT (status :data:`STALLED`), for a caller that rebuilds.
        """
        p = self.p_layout.pack(params)
        x0v = self.x_layout.pack(x0)
        lbx, ubx = self.lbx, self.ubx
        if fixed:
            lbx, ubx = lbx.copy(), ubx.copy()
            for name in fixed:
                e = self.x_layout.entries[name]
                lbx[e.offset : e.offset + e.size] = x0v[e.offset : e.offset + e.size]
                ubx[e.offset : e.offset + e.size] = x0v[e.offset : e.offset + e.size]
        args: dict[str, Any] = {"x0": x0v, "p": p, "lbx": lbx, "ubx": ubx}
        if lam_x0 is not None:
            args["lam_x0"] = lam_x0
        before = self.evaluate_blocks(x0v, p)
        budget = None if self.progress is None else self.progress.budget
        if budget is not None:
            estimate = memory.solve_estimate(self.hessian_nonzeros())
            if estimate > budget:  # refused before IPOPT starts: nothing allocated for it
                return self._refused(x0v, before, estimate, budget)
        if self.progress is not None:
            self.progress.start(progress, stop_when_stalled, stop_when)
        if self.keep is not None and hasattr(self.keep[1], "reset"):
            self.keep[1].reset()
        t0 = time.perf_counter()
        over_budget = False
        try:
            with interrupt.deferred():  # a signal stops IPOPT, then is raised
                out = self.solver(**args)
        finally:
            if self.progress is not None:
                over_budget = self.progress.over_budget
                self.progress.start(None, False)
        seconds = time.perf_counter() - t0
        stats = self.solver.stats()
        dropped = getattr(self.keep[1], "dropped", None) if self.keep is not None else None
        if dropped:  # a tiled map's samples that moved beyond its Hessian's pattern
            stats["hessian_terms_dropped"] = int(max(dropped))
        xopt = np.asarray(out["x"]).ravel()
        iters = stats.get("iterations", {})
        if over_budget:
            stats["return_status"], stats["success"] = MEMORY_STATUS, False
            stats["memory"] = memory.over_budget_message(None, budget, self.hessian_nonzeros())
        return Solution(
            x=self.x_layout.unpack(xopt),
            lam_x=np.asarray(out["lam_x"]).ravel(),
            status=str(stats.get("return_status", "unknown")),
            success=bool(stats.get("success", False)),
            iterations=int(stats.get("iter_count", -1)),
            solve_seconds=seconds,
            objective=float(out["f"]),
            cost_per_iteration=[float(v) for v in iters.get("obj", [])],
            inf_pr_per_iteration=[float(v) for v in iters.get("inf_pr", [])],
            inf_du_per_iteration=[float(v) for v in iters.get("inf_du", [])],
            blocks_before=before,
            blocks_after=self.evaluate_blocks(xopt, p),
            stats=stats,
            params=params,
            fixed=tuple(fixed),
        )


def merge_rounds(rounds: Sequence[Solution]) -> Solution:
    """Solutions of one problem solved in rounds, each from the last one's x (re-centred or
    rebuilt between them), as one: the last round's outcome with the iterations, seconds
    and per-iteration records of all of them (``rounds`` says how many)."""
    last = rounds[-1]
    return dataclasses.replace(
        last,
        iterations=sum(s.iterations for s in rounds),
        solve_seconds=sum(s.solve_seconds for s in rounds),
        cost_per_iteration=[v for s in rounds for v in s.cost_per_iteration],
        inf_pr_per_iteration=[v for s in rounds for v in s.inf_pr_per_iteration],
        inf_du_per_iteration=[v for s in rounds for v in s.inf_du_per_iteration],
        blocks_before=rounds[0].blocks_before,
        rounds=sum(s.rounds for s in rounds),
    )
