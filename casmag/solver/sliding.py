"""Sliding windows: a warm start for the batch of the translational model (the planar,
pose and IMU models' windows are the same scheme written over their window methods:
casmag.solver.staged.solve_sliding; the translational model's growing prefixes and
coarse-to-fine schedule are casmag.solver.staged's too, through
casmag.solver.translational.TranslationalStaged).

GP-SLAM from the dead reckoning converges only when the drift is within about a lengthscale
of the truth (paper Table 5).

Sliding windows (:func:`fixed_lag_smoother`, :func:`solve_sliding`). Windows of ``n``
samples, consecutive ones overlapping by ``o``, are solved in time order. The map is a
reduced-rank GP (casmag.model.rrmap) on one box for the whole recording, carried from window to
window as a Gaussian prior on its weights z:

    0.5 (z - mu)^T Lambda (z - mu),   Lambda_0 = diag(1 / S(l)),  mu_0 = 0,

and after each window the samples it commits (those before the next window starts) enter
the prior as linear-Gaussian observations at their estimated positions (an information
filter on the weights: Lambda += J^T J / sigma_m^2, Lambda mu += J^T y / sigma_m^2), so no
sample is counted twice. Each window

- integrates its odometry from the previous window's estimate of its first sample (anchored
  there) with the bias estimated so far removed, and estimates the remaining bias;
- starts from the previous window's trajectory on the overlap, continued by that odometry,
  and from the prior's posterior mean of the weights given those positions;
- (``window_bias_prior: laplace``, the default) has the previous window's bias estimate as
  a Gaussian prior: mean that estimate (zero on the window's own bias, which is the increment
  on the bias already removed) and precision the inverse of its Laplace marginal covariance
  at the previous solve (the bias block of the inverse Gauss-Newton Hessian, which contains
  that window's own prior, so the information accumulates like a filter's). The first window
  has only the model's ``bias_prior_sigma``. Without it (``none``) each window re-estimated
  the bias increment from its few samples alone, and the increments random-walked: on
  problems/paper/base.yaml (l = 0.1 m) with 10-sample windows the total reached
  (-11, 23) mm/step against the true (1, 1), 420 window iterations and a smoother RMSE of
  8.4 cm; with the prior (1.00, 1.03) mm/step, 148 iterations, 5.2 mm.

Window length (``window: auto``, :func:`auto_window`): the samples the dead reckoning needs
to travel ``window_lengthscales`` (1.375) assumed lengthscales at its median step, clamped
to casmag.solver.windowing.AUTO_WINDOW (12 to 40 samples); ``overlap: auto`` is half the
window. Measured with the bias prior (README, Windowing): on the Table 5 spiral (l = 0.4 m,
8 steps per lengthscale) at 3.4 l of drift and 1 mm noise, 12-sample windows reached the
basin in 20 of 20 seeds (at most 105 iterations in all), 14 in 19 of 20 (at most 229), 16
in 5 of 8 and 20 in 1 of 5: a longer window drifts further before the map pulls it back. On
base.yaml (l = 0.1 m, 2 steps per lengthscale) 8-sample windows took 198-234 iterations and
10-sample ones missed the basin in one of three seeds, 12-16 did neither: hence the floor
of 12. The ceiling of 40 is not measured. The first window has no previous bias estimate;
at 5.1 l of drift it is where the remaining failures start (it stops at
``window_max_iter``).

Window data, the anchor, the map prior (mu, Lambda) and the bias prior are CasADi
parameters and the window length is fixed (the last window ends at the last sample and
overlaps its predecessor by more), so one NLP serves every window: it is built once per
(length, box, basis) and cached. IPOPT's bound multipliers are all zero here (the window
has no bounds or constraints), so the warm start is the primal point only.

The smoother alone gives a trajectory for recordings too long for one batch (the map is
carried, the memory is one window plus an M x M prior); :func:`solve_sliding` starts the
full batch (the problem's own model: exact GP or reduced rank) from it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from casmag.data.simulate import Dataset
from casmag.errors import ProblemError
from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import HilbertBasis, cached_basis
from casmag.model.builder import cached_slam
from casmag.model.field import ReducedRankField, WindowField
from casmag.model.knots import Knots
from casmag.model.rrmap import field_and_jacobians, make_basis
from casmag.model.translational import (
    Structure,
    TranslationalMotion,
)
from casmag.nlp import NLP, Solution
from casmag.problem.spec import Problem
from casmag.solver.translational import solve_translational
from casmag.solver.windowing import (
    ACCEPTED,
    bias_covariance,
    continued,
    window_size,
    window_starts,
)

LEFT_BOX = "Left_Map_Box"
"""Status of a window whose positions left the map's box (IPOPT itself stopped normally)."""

OFF_MAP = "Off_Map_Dead_Reckoning"
"""Status of a window of a smoother on a known map (``fixed_map``) that left the map: kept
as its dead reckoning, and the next window tries the map again."""


def inside(P: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Every position (n, d) within the box [lo, hi]."""
    return bool(np.all(np.isfinite(P)) and np.all(P >= lo) and np.all(P <= hi))


@dataclass(frozen=True)
class WindowStage:
    """One window or stage: where it sits, IPOPT's outcome, the bias estimate it left.

    name: ``window``, ``lengthscale`` (a coarse-to-fine stage) or ``batch``; start, samples:
    first sample and number of samples; lengthscale [m] used; bias: total per-step bias [m]
    estimated so far (None when not estimated); bias_sigma: its standard deviation per axis
    [m] that the next window takes as prior (window_bias_prior laplace; else None)."""

    name: str
    start: int
    samples: int
    status: str
    success: bool
    iterations: int
    solve_seconds: float
    build_seconds: float
    lengthscale: float
    bias: list[float] | None
    bias_sigma: list[float] | None = None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class WindowStructure:
    """Everything that changes the window NLP (and so needs a new build)."""

    n: int
    dim: int
    kernel: str
    basis: tuple  # (center, half_width, num_basis)
    knot_every: int
    constant_field: bool
    estimate_bias: bool
    solver: str  # SolverSpec as JSON
    share_columns: bool = True  # False: one precision over every weight (a saved map's)

    @property
    def shared_prior(self) -> bool:
        """SE map without a constant field (and ``share_columns``): the three weight
        columns share one design matrix, so one M x M precision serves all of them."""
        return self.share_columns and self.kernel == "se" and not self.constant_field

    def hilbert_basis(self) -> HilbertBasis:
        return cached_basis(self.basis)

    def motion(self) -> TranslationalMotion:
        """The translational model of one window: one session, the bias (when estimated)
        under the Gaussian carried from the earlier windows."""
        bias_prior = "gaussian" if self.estimate_bias else "none"
        return TranslationalMotion(
            self.n, self.dim, self.knot_every, (0,), self.estimate_bias, bias_prior
        )

    def fixed_field(self) -> ReducedRankField:
        """The map of a window located against a known map: the plain reduced-rank map
        (no ``map_prior`` block), whose weights the solve holds fixed."""
        return ReducedRankField(self.kernel, self.basis, constant_field=self.constant_field)

    def field(self) -> WindowField:
        return WindowField(
            self.kernel,
            self.basis,
            constant_field=self.constant_field,
            prior_shape=self.prior_shape,
            shared_prior=self.shared_prior,
        )

    @property
    def prior_shape(self) -> tuple[int, int]:
        """Shape of the prior's unknowns Z: W (M, 3) when shared, else the stacked
        [vec(W); c] (n_z, 1)."""
        M = self.basis[2]
        if self.shared_prior:
            return (M, FIELD_DIM)
        n_w = M * FIELD_DIM if self.kernel == "se" else M
        return (n_w + (FIELD_DIM if self.constant_field else 0), 1)


def window_nlp(s: WindowStructure, fixed_map: bool = False) -> NLP:
    """The window NLP for a structure, built once per process; ``fixed_map``: the one of
    :meth:`WindowStructure.fixed_field`."""
    return cached_slam(s.motion(), s.fixed_field() if fixed_map else s.field(), s.solver)


def prior_design(s: WindowStructure, P: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The map as a linear model of the prior's unknowns Z at positions P (n, d):
    (J, T) with the samples Y (n, 3) = J Z (+ noise) column by column. Shared SE prior:
    J = Phi (n, M), T = Y; otherwise J (3n, n_z) component-major and T = vec(Y) (3n, 1)."""
    basis = s.hilbert_basis()
    M = basis.num_basis
    n_w = M * FIELD_DIM if s.kernel == "se" else M
    _, A, _ = field_and_jacobians(basis, s.kernel, P, np.zeros(n_w))
    if s.shared_prior:
        return A[0], Y
    n = P.shape[0]
    n_z = s.prior_shape[0]
    J = np.zeros((FIELD_DIM * n, n_z))
    for q in range(FIELD_DIM):
        rows = slice(q * n, (q + 1) * n)
        if s.kernel == "se":
            J[rows, q * M : (q + 1) * M] = A[0]
        else:
            J[rows, :M] = A[q]
        if s.constant_field:
            J[rows, n_w + q] = 1.0
    return J, Y.reshape(-1, 1, order="F")


def prior_precision(s: WindowStructure, problem: Problem) -> np.ndarray:
    """Lambda_0: the GP prior's diagonal precision diag(1 / S(l)) on the weights (and
    1 / sigma_lin^2 on a constant field)."""
    basis = s.hilbert_basis()
    S = np.asarray(
        basis.prior_variances(s.kernel, problem.assumed_sigma_f, problem.assumed_lengthscale)
    ).ravel()
    if s.shared_prior:
        return np.diag(1.0 / S)
    d = np.concatenate([np.tile(S, FIELD_DIM)] if s.kernel == "se" else [S])
    inv = 1.0 / d
    if s.constant_field:
        inv = np.concatenate([inv, np.full(FIELD_DIM, problem.spec.model.gp.sigma_lin**-2)])
    return np.diag(inv)


def _unpack_z(s: WindowStructure, Z: np.ndarray) -> dict[str, np.ndarray]:
    if s.shared_prior:
        return {"W": Z}
    M = s.basis[2]
    n_w = M * FIELD_DIM if s.kernel == "se" else M
    z = Z.ravel()
    out = {"W": z[:n_w].reshape((M, FIELD_DIM) if s.kernel == "se" else (M, 1), order="F")}
    if s.constant_field:
        out["c"] = z[n_w:].reshape(-1, 1)
    return out


BIAS_PRIOR_INFLATION = 1.0
"""Factor on the previous window's bias covariance before it becomes the next window's
prior. 1: none, so the overlap's samples inform the bias twice (other values not measured)."""


def auto_window(problem: Problem, data: Dataset) -> tuple[int, int]:
    """(window, overlap) in samples (casmag.solver.windowing.window_size, from the
    odometry's step lengths and the assumed lengthscale)."""
    ws = problem.spec.solver.warm_start
    steps = np.linalg.norm(data.U, axis=1)
    n, overlap = window_size(ws, steps, problem.assumed_lengthscale, data.n_samples)
    if overlap is None or not 1 <= overlap < n:
        raise ProblemError(
            problem.source,
            "solver.warm_start.overlap",
            f"overlap must be at least 1 sample and shorter than the window "
            f"(got {overlap} of {n} samples)",
        )
    return n, overlap


@dataclass
class SmootherResult:
    """The fixed-lag smoother's output.

    positions: (N, d) [m], each sample from the last window that committed it; bias: (d,)
    total per-step odometry bias [m] (zeros when not estimated); windows: one
    :class:`WindowStage` each; map_mean, map_precision: the weight prior after every
    committed sample (the map, in the basis of ``structure``); completed: every window
    reached an accepted IPOPT outcome inside the map's box. Otherwise the failing window's
    status is the last in ``windows`` (IPOPT's, or ``Left_Map_Box``) and positions and bias
    are the dead reckoning and zero: a failed smoother hands the batch the plain start."""

    positions: np.ndarray
    bias: np.ndarray
    windows: list[WindowStage]
    structure: WindowStructure
    map_mean: np.ndarray
    map_precision: np.ndarray
    completed: bool

    @property
    def iterations(self) -> int:
        return sum(w.iterations for w in self.windows)


def window_structure(
    problem: Problem, data: Dataset, n: int, box_positions: np.ndarray | None = None
) -> WindowStructure:
    """The window NLP's structure: ``n`` samples, the problem's kernel and knots, and a
    reduced-rank basis on a box around ``box_positions`` (default: the whole dead reckoning,
    so that the box holds the truth wherever the drift took the odometry)."""
    m = problem.spec.model
    kernel = problem.assumed_kernel
    if kernel == "div_free":
        raise ProblemError(
            problem.source,
            "solver.warm_start.strategy",
            "sliding windows need a reduced-rank map (kernel se or curl_free, not div_free)",
        )
    X = data.dead_reckoning() if box_positions is None else box_positions
    hb = make_basis(kernel, X, problem.assumed_lengthscale, m.gp.num_basis, m.gp.margin)
    ws = problem.spec.solver.warm_start
    solver = problem.spec.solver.model_copy(update={"max_iter": ws.window_max_iter})
    return WindowStructure(
        n=n,
        dim=data.dim,
        kernel=kernel,
        basis=(tuple(hb.domain.center), tuple(hb.domain.half_width), hb.num_basis),
        knot_every=min(m.trajectory.knot_every, n - 1),
        constant_field=m.gp.sigma_lin is not None,
        estimate_bias=m.odometry.estimate_bias,
        solver=solver.model_dump_json(),
    )


def fixed_lag_smoother(
    problem: Problem,
    data: Dataset,
    progress: Any = None,
    box_positions: np.ndarray | None = None,
    structure: WindowStructure | None = None,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
    fixed_map: bool = False,
) -> SmootherResult:
    """Run the sliding windows of ``problem.spec.solver.warm_start`` over ``data`` (module
    docstring). The map is the reduced-rank form of the problem's kernel and
    hyperparameters (assumed values; none is estimated in the windows).

    structure: the window NLP's structure (default :func:`window_structure`, whose window
    length it must have); prior: the map's prior before the first window as (mean,
    precision) in the structure's ``prior_shape`` (default: the GP prior, zero mean), e.g.
    a saved map (casmag.solver.localize). fixed_map (with a prior): every window is the
    plain reduced-rank NLP with the map held at the prior's mean (its unknowns fixed, so
    IPOPT factorises the window's path and bias alone; the dense precision never enters an
    NLP) and the prior is not updated: a known map located against, window by window."""
    ws = problem.spec.solver.warm_start
    N = data.n_samples
    n, overlap = auto_window(problem, data)
    starts = window_starts(N, n, overlap)
    s = window_structure(problem, data, n, box_positions) if structure is None else structure
    nlp = window_nlp(s, fixed_map)
    m = problem.spec.model
    sigma_m = problem.assumed_sigma_m
    if fixed_map and prior is None:
        raise ValueError("a fixed map needs its prior (mean, precision)")
    frozen = ("W", "c") if s.constant_field else ("W",)
    frozen = frozen if fixed_map else ()
    # a held map's own prior is a constant of the window's cost; sigma_lin only enters it
    fixed_params = {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_lin": 1.0,
    }
    if prior is None:
        Lam = prior_precision(s, problem)
        eta = np.zeros(s.prior_shape)
    else:
        Lam = prior[1]
        eta = Lam @ prior[0]
    bias_total = np.zeros(data.dim)
    # The model's prior on the total bias (zero mean) enters the first window; with the
    # laplace bias prior every later window starts from the previous one's posterior.
    model_prec = 0.0 if m.odometry.bias_prior_sigma is None else m.odometry.bias_prior_sigma**-2
    bias_prec = np.eye(data.dim) * model_prec
    bias_mean = np.zeros((1, data.dim))
    laplace = ws.window_bias_prior == "laplace" and s.estimate_bias
    knots = Knots(s.n, s.knot_every)
    center, half = (np.asarray(v)[: data.dim] for v in s.basis[:2])
    box_lo, box_hi = center - half, center + half
    P_est = np.full((N, data.dim), np.nan)
    windows: list[WindowStage] = []
    anchor = data.anchor.astype(float)
    previous: np.ndarray | None = None  # previous window's positions from this start on
    completed = True
    for k, start in enumerate(starts):
        end = start + n
        nxt = starts[k + 1] if k + 1 < len(starts) else N
        U = data.U[start : end - 1] - bias_total
        Q = np.vstack([anchor, anchor + np.cumsum(U, axis=0)])
        Y = data.Y[start:end]
        P0 = Q if previous is None else continued(previous, Q)
        C0 = knots.fit(Q, P0)
        P0 = knots.positions(Q, C0)
        if fixed_map:
            mean = Z0 = prior[0]
        else:
            J, T = prior_design(s, P0, Y)
            mean = np.linalg.solve(Lam, eta)
            Z0 = np.linalg.solve(Lam + J.T @ J / sigma_m**2, eta + J.T @ T / sigma_m**2)
        params = {
            "Q": Q,
            "Y": Y,
            "anchor": anchor.reshape(1, -1),
            "sigma_o": problem.assumed_sigma_odometry,
            "sigma_anchor": m.anchor.sigma,
            "sigma_m": sigma_m,
            "bias_mean": bias_mean,
            "bias_precision": bias_prec,
            **(fixed_params if fixed_map else {"map_mean": mean, "map_precision": Lam}),
        }
        x0: dict[str, Any] = {"C": C0, **_unpack_z(s, Z0)}
        if s.estimate_bias:
            x0["bias"] = np.zeros((1, data.dim))
        sol = nlp.solve(params, x0, progress=progress, fixed=frozen)
        status = sol.status
        P = knots.positions(Q, sol.x["C"])
        if status in ACCEPTED and not inside(P, box_lo, box_hi):
            # The map is zero outside its box: a window there has lost the room.
            status = LEFT_BOX
        ok = status in ACCEPTED
        if fixed_map and status == LEFT_BOX:
            # Off a known map: no map information here, the window keeps its dead reckoning
            # (continued from the previous window) and the next one tries the map again.
            P, ok, status = P0, True, OFF_MAP
        bias_sigma = None
        if ok:
            if s.estimate_bias:
                bias_total = bias_total + sol.x["bias"].ravel()
            if laplace:
                # The next window's odometry has bias_total removed, so the prior on its
                # bias (an increment) is centred on zero, i.e. on this window's estimate.
                cov = bias_covariance(nlp, sol, params, frozen) * BIAS_PRIOR_INFLATION
                bias_mean = np.zeros((1, data.dim))
                if np.all(np.isfinite(cov)) and np.linalg.eigvalsh(cov).min() > 0:
                    bias_prec = np.linalg.inv(cov)
                    bias_sigma = [float(v) for v in np.sqrt(np.diag(cov))]
                else:  # singular Hessian: no information to hand on
                    bias_prec = np.zeros((data.dim, data.dim))
            local = slice(0, nxt - start)
            P_est[start:nxt] = P[local]
            if not fixed_map:
                J, T = prior_design(s, P[local], Y[local])
                Lam = Lam + J.T @ J / sigma_m**2
                eta = eta + J.T @ T / sigma_m**2
            if nxt < N:
                anchor = P[nxt - start]
                previous = P[nxt - start :]
        windows.append(
            WindowStage(
                name="window",
                start=start,
                samples=n,
                status=status,
                success=sol.success,
                iterations=sol.iterations,
                solve_seconds=sol.solve_seconds,
                build_seconds=nlp.build_seconds if k == 0 else 0.0,
                lengthscale=problem.assumed_lengthscale,
                bias=[float(v) for v in bias_total] if s.estimate_bias else None,
                bias_sigma=bias_sigma,
            )
        )
        if not ok:
            completed = False
            break
    if not completed:  # a window failed: start from the dead reckoning
        P_est, bias_total = data.dead_reckoning(), np.zeros(data.dim)
    return SmootherResult(
        positions=P_est,
        bias=bias_total,
        windows=windows,
        structure=s,
        map_mean=prior[0] if fixed_map else np.linalg.solve(Lam, eta),
        map_precision=Lam,
        completed=completed,
    )


def batch_stage(
    sol: Solution, nlp: NLP, n: int, lengthscale: float, bias: Any, name: str = "batch"
) -> WindowStage:
    """A solve over all n samples (the batch, or a coarse-to-fine stage) as a stage."""
    return WindowStage(
        name=name,
        start=0,
        samples=n,
        status=sol.status,
        success=sol.success,
        iterations=sol.iterations,
        solve_seconds=sol.solve_seconds,
        build_seconds=nlp.build_seconds,
        lengthscale=lengthscale,
        bias=None if bias is None else [float(v) for v in np.ravel(bias)],
    )


def solve_sliding(
    problem: Problem, data: Dataset, progress: Any = None
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure, Dataset, list[WindowStage]]:
    """Sliding windows, then the full batch from their trajectory (with the bias they
    estimated removed from the odometry; ``sol.x["bias"]`` is the total). Returns what
    :func:`casmag.solver.translational.solve_translational_strategy` returns; the stages
    end with the batch."""
    sm = fixed_lag_smoother(problem, data)
    solved = data.debiased(sm.bias)
    sol, nlp, hyper, field, structure = solve_translational(problem, solved, progress, sm.positions)
    if problem.spec.model.odometry.estimate_bias and "bias" in sol.x:
        sol.x["bias"] = sol.x["bias"] + sm.bias.reshape(1, -1)
    stage = batch_stage(sol, nlp, data.n_samples, hyper["lengthscale"], sol.x.get("bias"))
    return sol, nlp, hyper, field, structure, solved, [*sm.windows, stage]
