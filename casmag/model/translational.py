"""The translational GP-SLAM MAP problem (paper Section 3.1, Eq. 3 and 5-8) as one NLP.

Unknowns: the positions P (N, d) as dead reckoning Q plus a drift correction C (K, d) at
knots, P = Q + A C (casmag.model.knots; one knot per sample by default, which is the paper's
formulation), the field M (N, 3) at the samples (exact GP) or basis weights W (reduced
rank), optionally a per-step odometry bias b (1, d) and the log-hyperparameters
log sigma_f, log l. Named cost blocks (negative log-densities):

- ``odometry``: 0.5 sum_k |(p_{k+1} - p_k - (u_k - b)) / sigma_o|^2, which on the knots is
  0.5 sum_j |c_{j+1} - c_j + k_j b|^2 / (k_j sigma_o^2)
- ``magnetometer``: 0.5 sum_k |(y_k - m_k) / sigma_m|^2 (Eq. 3 with R = I)
- ``gp_prior``: 0.5 m^T K(P)^-1 m (Eq. 6)
- ``gp_logdet``: 0.5 log|K(P)| (Eq. 6), when sigma_f or l is estimated
- ``anchor``: 0.5 |(p_0 - a) / sigma_a|^2
- ``bias_prior``: 0.5 |b / sigma_b|^2, when a bias prior is set

Data and fixed settings are NLP parameters, so one build serves every seed and every value
of a fixed hyperparameter; the build is cached by the problem's structure. The NLP is
:class:`TranslationalMotion` with the structure's field model (casmag.model.field), put
together by the one builder (casmag.model.builder).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import casadi as ca
import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

from casmag.data.simulate import Dataset
from casmag.gp.fieldmap import field_at, reduced_rank_std
from casmag.gp.kernels import FIELD_DIM, get_kernel
from casmag.gp.localmaps import cached_tiles
from casmag.gp.reduced_rank import HilbertBasis, cached_basis
from casmag.gp.savedmap import tiled_std_given_path
from casmag.gp.tiles import TileGrid
from casmag.model.builder import FieldModel, MotionModel, Pose, cached_slam, uncached_slam
from casmag.model.field import ExactField, ReducedRankField, TiledField, WindowField
from casmag.model.knots import Knots
from casmag.model.rrmap import field_and_jacobians, make_basis
from casmag.model.tiledmap import home_points, ridge_tile_weights, tile_grid
from casmag.nlp import NLP, NLPBuilder, Solution
from casmag.problem.spec import Problem


@dataclass(frozen=True)
class Structure:
    """Everything that changes the symbolic problem (and so needs a new build)."""

    n: int
    dim: int
    kernel: str
    estimate: tuple[str, ...]
    estimate_bias: bool
    bias_prior: bool
    jitter: float
    logdet: bool
    solver: str  # SolverSpec as JSON (hashable)
    form: str = "exact"
    basis: tuple | None = None  # reduced rank: (center, half_width, num_basis)
    constant_field: bool = False
    knot_every: int = 1
    starts: tuple[int, ...] = (0,)  # first sample of each session (casmag.solver.multisession)
    grid: TileGrid | None = None  # form "tiled": the tiles around the initial positions
    home: tuple[int, ...] = ()  # form "tiled": each sample's nearest grid point there

    @classmethod
    def of(cls, problem: Problem, data: Dataset, positions: np.ndarray | None = None) -> Structure:
        """The structure of a problem on a data set; a reduced-rank map's box is fitted
        around ``positions`` (default: the dead reckoning)."""
        m = problem.spec.model
        basis, tiles, home = None, None, ()
        X0 = data.dead_reckoning() if positions is None else positions
        if m.gp.form == "reduced_rank":
            hb = make_basis(
                problem.assumed_kernel, X0, problem.assumed_lengthscale, m.gp.num_basis, m.gp.margin
            )
            basis = (tuple(hb.domain.center), tuple(hb.domain.half_width), hb.num_basis)
        elif m.gp.form == "tiled":
            tiles = tile_grid(
                X0,
                problem.assumed_lengthscale,
                m.gp.tile_spacing,
                m.gp.margin,
                m.gp.tile_basis,
                field=(problem.assumed_sigma_f, problem.assumed_sigma_m),
            )
            home = home_points(tiles, X0)
        return cls(
            n=data.n_samples,
            dim=data.dim,
            kernel=problem.assumed_kernel,
            estimate=tuple(sorted(m.estimate)),
            estimate_bias=m.odometry.estimate_bias,
            bias_prior=m.odometry.bias_prior_sigma is not None,
            jitter=m.gp.jitter,
            logdet=bool({"sigma_f", "lengthscale"} & set(m.estimate))
            if m.gp.logdet is None
            else m.gp.logdet,
            solver=problem.spec.solver.model_dump_json(exclude={"uncertainty"}),
            form=m.gp.form,
            basis=basis,
            constant_field=m.gp.sigma_lin is not None,
            knot_every=m.trajectory.knot_every,
            starts=tuple(int(i) for i in data.starts),
            grid=tiles,
            home=home,
        )

    def hilbert_basis(self) -> HilbertBasis:
        return cached_basis(self.basis)

    @property
    def tiled(self) -> bool:
        return self.form == "tiled"

    @property
    def knots(self) -> Knots:
        return Knots(self.n, self.knot_every, self.starts)

    @property
    def sessions(self) -> int:
        return len(self.starts)

    def motion(self) -> TranslationalMotion:
        return TranslationalMotion(
            self.n,
            self.dim,
            self.knot_every,
            self.starts,
            self.estimate_bias,
            "sigma" if self.bias_prior else "none",
        )

    def field(self) -> FieldModel:
        if self.form == "reduced_rank":
            return ReducedRankField(self.kernel, self.basis, self.estimate, self.constant_field)
        if self.form == "tiled":
            assert self.grid is not None
            return TiledField(self.grid, self.home, self.constant_field)
        return ExactField(self.kernel, self.jitter, self.estimate, self.logdet)


@dataclass(frozen=True)
class TranslationalMotion(MotionModel):
    """Positions P = Q + A C: the dead reckoning Q (parameter) plus corrections C at knots
    (casmag.model.knots), a per-session odometry bias (when estimated), the blocks
    ``odometry``, ``anchor`` (each session's first position) and ``bias_prior``:
    ``sigma`` (zero mean, ``sigma_bias``) or ``gaussian`` (``bias_mean``,
    ``bias_precision``: a window's prior carried from the earlier windows)."""

    n: int
    dim: int
    knot_every: int = 1
    starts: tuple[int, ...] = (0,)
    estimate_bias: bool = False
    bias_prior: str = "none"  # "none", "sigma" or "gaussian"
    name = "translational"

    @property
    def knots(self) -> Knots:
        return Knots(self.n, self.knot_every, self.starts)

    def declare(self, b: NLPBuilder) -> Pose:
        knots, S = self.knots, len(self.starts)
        C = b.variable("C", (knots.count, self.dim))
        bias = b.variable("bias", (S, self.dim)) if self.estimate_bias else ca.MX.zeros(S, self.dim)
        Q = b.parameter("Q", (self.n, self.dim))
        own = {
            "bias": bias,
            "anchor": b.parameter("anchor", (S, self.dim)),
            "sigma_o": b.parameter("sigma_o", (1, 1)),
            "sigma_anchor": b.parameter("sigma_anchor", (1, 1)),
        }
        if self.bias_prior == "sigma":
            own["sigma_bias"] = b.parameter("sigma_bias", (1, 1))
        elif self.bias_prior == "gaussian":
            own["bias_mean"] = b.parameter("bias_mean", (S, self.dim))
            own["bias_precision"] = b.parameter("bias_precision", (self.dim, self.dim))
        P = Q + (C if self.knot_every == 1 else ca.mtimes(knots.casadi_matrix(), C))
        b.cost("odometry", knots.odometry_cost(C, bias, own["sigma_o"]))
        return Pose(P, self.n, self.dim, "C", "Q", knots, own=own)

    def close(self, b: NLPBuilder, pose: Pose) -> None:
        own, P = pose.own, pose.positions
        first = P[0, :] if len(self.starts) == 1 else P[list(self.starts), :]
        b.cost("anchor", 0.5 * ca.sumsqr((first - own["anchor"]) / own["sigma_anchor"]))
        if self.bias_prior == "sigma":
            b.cost("bias_prior", 0.5 * ca.sumsqr(own["bias"] / own["sigma_bias"]))
        elif self.bias_prior == "gaussian":
            db = own["bias"] - own["bias_mean"]
            b.cost("bias_prior", 0.5 * ca.mtimes(ca.mtimes(db, own["bias_precision"]), db.T))


# ---------------------------------------------------------------- sliding windows


@dataclass(frozen=True)
class WindowStructure:
    """A window of the translational sliding windows (casmag.solver.translational,
    casmag.solver.staged.solve_sliding) or of the localisation against a saved map
    (casmag.solver.localize): everything that changes its NLP (and so needs a new build).

    ``basis``: (center, half_width, num_basis) of the map's reduced-rank box;
    ``share_columns`` False: one precision over every weight (a saved map's). A saved
    tiled map (localisation only): ``basis`` None, ``grid`` its tiles (curl-free) and
    ``home`` each sample's nearest grid point where the NLP is laid (TiledField, built
    for each placement and not cached)."""

    n: int
    dim: int
    kernel: str
    basis: tuple | None
    knot_every: int
    constant_field: bool
    estimate_bias: bool
    solver: str  # SolverSpec as JSON
    share_columns: bool = True
    grid: TileGrid | None = None
    home: tuple[int, ...] = ()

    @property
    def form(self) -> str:
        """The window's map, ``reduced_rank`` or ``tiled`` (casmag.solver.uncertainty reads
        it)."""
        return "reduced_rank" if self.grid is None else "tiled"

    def placed(self, P: np.ndarray) -> WindowStructure:
        """A tiled map's structure laid around positions P (n, d) (its ``home``); a box
        map's as it is."""
        if self.grid is None:
            return self
        return replace(self, home=home_points(self.grid, P))

    def covers(self, P: np.ndarray) -> bool:
        """Every position P (n, d) is finite and on the map: inside its box, or with every
        tile of its cell present."""
        P = np.asarray(P, dtype=float)
        if not np.all(np.isfinite(P)):
            return False
        if self.grid is not None:
            return bool(np.all(cached_tiles(self.grid).inside(P)))
        center, half = (np.asarray(v)[: self.dim] for v in self.basis[:2])
        return bool(np.all(P >= center - half) and np.all(P <= center + half))

    @property
    def shared_prior(self) -> bool:
        """SE map without a constant field (and ``share_columns``): the three weight
        columns share one design matrix, so one M x M precision serves all of them."""
        return self.share_columns and self.kernel == "se" and not self.constant_field

    def hilbert_basis(self) -> HilbertBasis:
        return cached_basis(self.basis)

    @property
    def knots(self) -> Knots:
        return Knots(self.n, self.knot_every)

    def motion(self) -> TranslationalMotion:
        """One session; the bias (when estimated) under the Gaussian carried from the
        earlier windows."""
        bias_prior = "gaussian" if self.estimate_bias else "none"
        return TranslationalMotion(
            self.n, self.dim, self.knot_every, (0,), self.estimate_bias, bias_prior
        )

    def fixed_field(self) -> FieldModel:
        """The map of a window located against a known map: the plain reduced-rank or
        tiled map (no ``map_prior`` block), whose weights the solve holds fixed."""
        if self.grid is not None:
            return TiledField(self.grid, self.home, self.constant_field)
        return ReducedRankField(self.kernel, self.basis, constant_field=self.constant_field)

    def field(self) -> FieldModel:
        if self.grid is not None:
            return TiledField(self.grid, self.home, self.constant_field, saved_prior=True)
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
        if self.grid is not None:
            n_w = cached_tiles(self.grid).num_weights
        elif self.shared_prior:
            return (self.basis[2], FIELD_DIM)
        else:
            n_w = self.basis[2] * (FIELD_DIM if self.kernel == "se" else 1)
        return (n_w + (FIELD_DIM if self.constant_field else 0), 1)

    def nlp(self, fixed_map: bool = False) -> NLP:
        """The window NLP, built once per process (a tiled map's for each placement, not
        kept); ``fixed_map``: the one of :meth:`fixed_field`."""
        build = cached_slam if self.grid is None else uncached_slam
        return build(self.motion(), self.fixed_field() if fixed_map else self.field(),
                     self.solver)  # fmt: skip

    def design(self, P: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The map as a linear model of the prior's unknowns Z at positions P (n, d):
        (J, T) with the samples Y (n, 3) = J Z (+ noise) column by column. Shared SE
        prior: J = Phi (n, M), T = Y; otherwise J (3n, n_z) component-major and
        T = vec(Y) (3n, 1)."""
        basis = self.hilbert_basis()
        M = basis.num_basis
        n_w = M * FIELD_DIM if self.kernel == "se" else M
        _, A, _ = field_and_jacobians(basis, self.kernel, P, np.zeros(n_w))
        if self.shared_prior:
            return A[0], Y
        n = P.shape[0]
        J = np.zeros((FIELD_DIM * n, self.prior_shape[0]))
        for q in range(FIELD_DIM):
            rows = slice(q * n, (q + 1) * n)
            if self.kernel == "se":
                J[rows, q * M : (q + 1) * M] = A[0]
            else:
                J[rows, :M] = A[q]
            if self.constant_field:
                J[rows, n_w + q] = 1.0
        return J, Y.reshape(-1, 1, order="F")

    def prior_precision(
        self, sigma_f: float, lengthscale: float, sigma_lin: float | None
    ) -> np.ndarray:
        """Lambda_0: the GP prior's diagonal precision diag(1 / S(l)) on the weights (and
        1 / sigma_lin^2 on a constant field)."""
        S = np.asarray(
            self.hilbert_basis().prior_variances(self.kernel, sigma_f, lengthscale)
        ).ravel()
        if self.shared_prior:
            return np.diag(1.0 / S)
        inv = 1.0 / (np.tile(S, FIELD_DIM) if self.kernel == "se" else S)
        if self.constant_field:
            inv = np.concatenate([inv, np.full(FIELD_DIM, float(sigma_lin) ** -2)])
        return np.diag(inv)

    def unknowns(self, Z: np.ndarray) -> dict[str, np.ndarray]:
        """The NLP's map unknowns (``W``, and ``c`` with a constant field) from Z of
        :attr:`prior_shape`."""
        if self.shared_prior:
            return {"W": Z}
        if self.grid is not None:
            tiles, z = cached_tiles(self.grid), np.ravel(Z)
            out = {"W": z[: tiles.num_weights].reshape(tiles.per_tile, -1, order="F")}
            if self.constant_field:
                out["c"] = z[tiles.num_weights :].reshape(-1, 1)
            return out
        M = self.basis[2]
        n_w = M * FIELD_DIM if self.kernel == "se" else M
        z = Z.ravel()
        out = {"W": z[:n_w].reshape((M, FIELD_DIM) if self.kernel == "se" else (M, 1), order="F")}
        if self.constant_field:
            out["c"] = z[n_w:].reshape(-1, 1)
        return out


def initial_weights(
    s: Structure,
    P: np.ndarray,
    Y: np.ndarray,
    sigma_m: float,
    sigma_f: float,
    lengthscale: float,
    c0: np.ndarray,
) -> np.ndarray:
    """Ridge fit of the map weights to the data at the initial positions (the posterior mean
    of the weights given P): (A^T A / sigma_m^2 + diag(1 / S))^-1 A^T (y - c0) / sigma_m^2.
    For the tiled map, (m, T), by a sparse direct solve
    (:func:`casmag.model.tiledmap.ridge_tile_weights`)."""
    if s.form == "tiled":
        assert s.grid is not None
        return ridge_tile_weights(cached_tiles(s.grid), P, Y, c0, sigma_m, sigma_f, lengthscale)
    basis = s.hilbert_basis()
    S = basis.prior_variances(s.kernel, sigma_f, lengthscale)
    M = basis.num_basis
    zero = np.zeros(M * FIELD_DIM if s.kernel == "se" else M)
    _, A, _ = field_and_jacobians(basis, s.kernel, P, zero)
    R = Y - c0
    if s.kernel == "se":
        G = A[0].T @ A[0] / sigma_m**2 + np.diag(1.0 / S)
        return np.linalg.solve(G, A[0].T @ R / sigma_m**2)
    G = sum(a.T @ a for a in A) / sigma_m**2 + np.diag(1.0 / S)
    rhs = sum(A[q].T @ R[:, q] for q in range(FIELD_DIM)) / sigma_m**2
    return np.linalg.solve(G, rhs).reshape(-1, 1)


def positions(s: Structure, sol: Solution, dead_reckoning: np.ndarray) -> np.ndarray:
    """(N, d) estimated positions: the dead reckoning plus the knot corrections."""
    return s.knots.positions(dead_reckoning, sol.x["C"])


def field_estimate(s: Structure, sol: Solution, P: np.ndarray) -> np.ndarray:
    """(N, 3) estimated field at the estimated positions P."""
    if s.form == "tiled":
        return _tiled_field(s, sol, P)
    if s.form != "reduced_rank":
        return sol.x["M"]
    basis = s.hilbert_basis()
    m, _, _ = field_and_jacobians(basis, s.kernel, P, sol.x["W"].ravel(order="F"))
    return m + (sol.x["c"].ravel() if s.constant_field else 0.0)


def _tiled_field(s: Structure, sol: Solution, X: np.ndarray) -> np.ndarray:
    """(G, 3) the tiled map's field (with its constant) at points X (G, d)."""
    assert s.grid is not None
    m = cached_tiles(s.grid).field(X, sol.x["W"].T)
    return m + (sol.x["c"].ravel() if s.constant_field else 0.0)


def field_on_grid(
    s: Structure,
    sol: Solution,
    hyper: dict[str, float],
    grid: np.ndarray,
    jitter: float,
    P: np.ndarray,
) -> np.ndarray:
    """(G, 3) estimated field at grid points (G, d): the reduced-rank map itself, or for the
    exact GP the posterior mean given the estimated field at the estimated positions P,
    K(grid, P) K(P, P)^-1 m."""
    if s.form == "tiled":
        return _tiled_field(s, sol, grid)
    if s.form == "reduced_rank":
        m = field_at(s.hilbert_basis(), s.kernel, grid, sol.x["W"])
        return m + (sol.x["c"].ravel() if s.constant_field else 0.0)
    kernel = get_kernel(s.kernel)
    M = sol.x["M"]
    sf, ell = hyper["sigma_f"], hyper["lengthscale"]
    K = kernel.matrix(P, P, sf, ell)
    K = K + jitter * kernel.variance(sf, ell) * np.eye(K.shape[0])
    Ks = kernel.matrix(grid, P, sf, ell)
    if kernel.output_dim == 1:
        return Ks @ np.linalg.solve(K, M)
    mean = Ks @ np.linalg.solve(K, M.ravel(order="F"))
    return mean.reshape(FIELD_DIM, -1).T


#: Most samples for which :func:`field_std_on_grid` computes the exact GP's posterior std
#: (a dense (3 N)^2 factor: 3,000 samples take 650 MB).
EXACT_STD_MAX_SAMPLES = 3_000


def field_std_on_grid(
    s: Structure,
    hyper: dict[str, float],
    grid: np.ndarray,
    P: np.ndarray,
    jitter: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The map's posterior standard deviation per field component at grid points (G, d),
    given the magnetometer at the estimated positions P (the positions taken as known), and
    its prior standard deviation there, both (G, 3): where the two are close no sample
    informs the map. Reduced rank: from the weights' posterior precision
    A^T A / sigma_m^2 + diag(1 / S) (the constant field left out: every sample informs it);
    exact GP: k(x, x) - k(x, P) (K + sigma_m^2 I)^-1 k(P, x). None for an exact GP above
    EXACT_STD_MAX_SAMPLES samples. Tiled map: the same posterior given P on its tiles
    (casmag.gp.savedmap.tiled_std_given_path; NaN off the tiles, None above
    TILED_STD_MAX_WEIGHTS weights)."""
    if s.form == "tiled":
        assert s.grid is not None
        return tiled_std_given_path(s.grid, hyper, P, grid)
    if s.form == "reduced_rank":
        return reduced_rank_std(s.hilbert_basis(), s.kernel, hyper, P, grid)
    sf, ell, sm = hyper["sigma_f"], hyper["lengthscale"], hyper["sigma_m"]
    if P.shape[0] > EXACT_STD_MAX_SAMPLES:
        return None
    kernel = get_kernel(s.kernel)
    K = kernel.matrix(P, P, sf, ell)
    K = K + (jitter * kernel.variance(sf, ell) + sm**2) * np.eye(K.shape[0])
    L = np.linalg.cholesky(K)
    var0 = kernel.variance(sf, ell)
    post = []
    for rows in np.array_split(np.arange(grid.shape[0]), max(1, grid.shape[0] // 500)):
        Ks = kernel.matrix(grid[rows], P, sf, ell)  # (g, N) or (3 g, 3 N)
        V = scipy.linalg.solve_triangular(L, Ks.T, lower=True)
        var = var0 - (V**2).sum(axis=0)
        post.append(
            np.repeat(var[:, None], FIELD_DIM, 1)
            if kernel.output_dim == 1
            else var.reshape(FIELD_DIM, -1).T
        )
    std = np.sqrt(np.maximum(np.vstack(post), 0.0))
    return std, np.full_like(std, np.sqrt(var0))


def cached_nlp(structure: Structure, cache: bool = True) -> NLP:
    """The built NLP for a structure, built once per process (``cache`` False: built anew
    and not kept, e.g. a tiled map's pattern moved for one solve)."""
    build = cached_slam if cache else uncached_slam
    return build(structure.motion(), structure.field(), structure.solver)


def parameters(problem: Problem, data: Dataset, s: Structure) -> dict[str, Any]:
    """The NLP's parameter values: the dead reckoning, the data, the anchor and the noise
    levels, and the hyperparameters the problem does not estimate at their assumed values
    (the guess is :func:`parameters_and_guess`'s)."""
    m = problem.spec.model
    params: dict[str, Any] = {
        "Q": data.dead_reckoning(),
        "Y": data.Y,
        "anchor": np.asarray(data.anchor, dtype=float).reshape(s.sessions, -1),
        "sigma_o": problem.assumed_sigma_odometry,
        "sigma_anchor": m.anchor.sigma,
    }
    if s.bias_prior:
        params["sigma_bias"] = m.odometry.bias_prior_sigma
    if s.form in ("reduced_rank", "tiled") and s.constant_field:
        params["sigma_lin"] = m.gp.sigma_lin
    for h, value in _assumed(problem).items():
        if h not in s.estimate:
            params[h] = value
    return params


def _assumed(problem: Problem) -> dict[str, float]:
    return {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_m": problem.assumed_sigma_m,
    }


def parameters_and_guess(
    problem: Problem,
    data: Dataset,
    s: Structure,
    initial_positions: np.ndarray | None = None,
    hyper_start: dict[str, float] | None = None,
    lengthscale: float | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """:func:`parameters` and the initial guess: the dead reckoning (or the knot
    corrections closest to ``initial_positions``), the field fitted there, zero bias,
    hyperparameters at their assumed values (estimated ones at ``hyper_start`` where it
    names them, see :func:`estimate_start`). ``lengthscale``: a fixed lengthscale other
    than the assumed one (a coarse-to-fine stage), set in the parameters and used for the
    fit; the map's basis stays the assumed lengthscale's."""
    params = parameters(problem, data, s)
    hyper = _assumed(problem)
    if lengthscale is not None:
        params["lengthscale"] = hyper["lengthscale"] = lengthscale
    Q = params["Q"]
    if initial_positions is None:
        P0, C0 = Q, np.zeros((s.knots.count, s.dim))
    else:
        C0 = s.knots.fit(Q, initial_positions)
        P0 = s.knots.positions(Q, C0)
    x0: dict[str, Any] = {"C": C0}
    if s.form in ("reduced_rank", "tiled"):
        c0 = data.Y.mean(axis=0) if s.constant_field else np.zeros(FIELD_DIM)
        x0["W"] = initial_weights(
            s, P0, data.Y, hyper["sigma_m"], hyper["sigma_f"], hyper["lengthscale"], c0
        )
        if s.constant_field:
            x0["c"] = c0.reshape(-1, 1)
    else:
        x0["M"] = data.Y
    if s.estimate_bias:
        x0["bias"] = np.zeros((s.sessions, s.dim))
    for h, value in hyper.items():
        if h in s.estimate:
            x0[f"log_{h}"] = np.log((hyper_start or {}).get(h, value))
    return params, x0
