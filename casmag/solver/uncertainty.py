"""Posterior uncertainty of the positions: the Laplace approximation at the MAP.

Around the MAP estimate x*, the posterior is approximated by N(x*, H^-1), where H is the
Hessian of the objective (the negative log-posterior) at x* (:meth:`casmag.nlp.NLP.hessian`:
IPOPT's Hessian, with the Gauss-Newton term for the reduced-rank magnetometer block). The
positions are linear in the knot corrections, p_k = q_k + sum_j A_kj c_j (casmag.model.knots), so

    cov(p_k) = sum_{j, j'} A_kj A_kj' cov(c_j, c_j'),

with cov(c) the knot block of H^-1: every other unknown (map, bias, estimated
hyperparameters) is marginalised, not conditioned on. Hyperparameters held fixed are taken as
known, so their uncertainty is not in the covariance.

The NEES (normalised estimation error squared) e_k^T cov(p_k)^-1 e_k, e_k = p_k - p_true,
has expected value d (the position dimension) when the covariance is honest: a mean NEES well
above d means over-confidence, well below d under-confidence.

Correlated magnetometer residuals (``solver.uncertainty_inflation``). The magnetometer block
assumes white noise of standard deviation sigma_m. On the real field the residuals at the MAP
are correlated along the path (the map's own error, which the reduced-rank GP cannot follow),
and N correlated residuals carry about the information of N / tau independent ones, tau their
integrated autocorrelation time: the plain Laplace covariance H^-1 is then over-confident
(mean NEES 6-17 for an expected 2 on the real five-session problem at 0.5 m drift). With
``long-run`` (the default) the covariance is the sandwich (robust, HAC) covariance of the MAP
estimate under that misspecification,

    cov(x) = H^-1 B H^-1,    B = H + sum_kc (lambda_kc - 1) J_kc^T J_kc / sigma_m^2,

where J_kc is the gradient of the magnetometer residual of sample k, component c: the
magnetometer part of the score's covariance uses the residuals' long-run variance s^2 tau
(the spectral density at frequency zero) instead of sigma_m^2, lambda = max(1, s^2 tau /
sigma_m^2), with s^2 the residuals' variance at the solution and tau
(:func:`autocorrelation_time`, Geyer's initial monotone sequence estimator) computed per
session and field component (:func:`residual_inflation`, :func:`magnetometer_correction`).
``correlation`` uses lambda = max(1, tau) (sigma_m taken as right), ``none`` gives H^-1.
White noise gives tau near 1 and s below sigma_m (the fit absorbs part of it), so lambda = 1
and the covariance is H^-1: synthetic problems are unchanged. The truth is never used.
Measured on the real field, five sessions with one map (problems/real/sessions-drift*.yaml):
mean NEES per session 5.2-16.7 plain, 0.78-2.94 with ``long-run`` (all samples: 9.7-10.3
plain, 1.77 with ``long-run``; inside the 95 % ellipse 52-53 % -> 92-93 %); at 0.5 m drift
0.48-1.44 with ``correlation``, and 3.9-11.8 when the magnetometer information was scaled by
1 / lambda inside H instead (the posterior of a model with correlated noise, not the error
of this estimate). One pooled lambda per component over the sessions gave 0.89-3.25.
A single session's map fits its own residuals more closely (RMS 0.4-1.2 uT against
sigma_m = 2 uT, tau 1.6-10), so lambda is 1-2.4 there: sequence 5 (the one that revisits
itself most) mean NEES 1.94 -> 1.40 at 0.5 m drift and 1.57 -> 1.18 at 1.5 m; where a single
session stays near its odometry (NEES 68-5,195) the error is an unobservable drift, not
correlated noise, and the inflation does not change that.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps

from casmag.gp.kernels import FIELD_DIM
from casmag.linalg import dense_product
from casmag.model.knots import Knots
from casmag.model.rrmap import MapModel, field_and_jacobians
from casmag.nlp import NLP, Solution


@dataclass
class PositionUncertainty:
    """cov (N, d, d) [m^2] per sample; ``sigma`` (N, d) the marginal standard deviations."""

    cov: np.ndarray

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.einsum("kii->ki", self.cov))

    def nees(self, P_est: np.ndarray, P_true: np.ndarray) -> np.ndarray:
        """(N,) NEES of each position against the truth."""
        e = P_est - P_true
        return np.einsum("ki,ki->k", e, np.linalg.solve(self.cov, e[..., None])[..., 0])

    def summary(self, P_est: np.ndarray, P_true: np.ndarray | None) -> dict[str, Any]:
        """Mean 1-sigma radius, and against truth the mean and median NEES with the expected
        value d, the fraction of samples inside the 95 % ellipse and the range a mean NEES
        takes with 95 % probability when the covariance is honest
        (:func:`nees_consistency`)."""
        d = self.cov.shape[1]
        out: dict[str, Any] = {
            "sigma_mean": float(np.mean(np.sqrt(np.trace(self.cov, axis1=1, axis2=2)))),
            "sigma_max": float(np.max(np.sqrt(np.trace(self.cov, axis1=1, axis2=2)))),
            "nees_expected": float(d),
            "nees_mean": None,
            "nees_median": None,
            "inside_95": None,
        }
        if P_true is not None:
            from scipy.stats import chi2

            q = self.nees(P_est, P_true)
            out.update(
                nees_mean=float(np.mean(q)),
                nees_median=float(np.median(q)),
                inside_95=float(np.mean(q <= chi2.ppf(0.95, d))),
                **nees_consistency(q, d),
            )
        return out


def nees_consistency(q: np.ndarray, d: int) -> dict[str, Any]:
    """How far a mean NEES may stray from d by chance. Errors along a trajectory are smooth,
    so neighbouring NEES values are not independent: the series q (N,) has an integrated
    autocorrelation time tau (:func:`autocorrelation_time`, at least 1) and carries about
    n = N / tau independent values. With an honest covariance each is chi-squared with d
    degrees of freedom, so the mean of n of them is chi2(n d) / n: ``nees_interval_95`` is
    its central 95 % interval, the range of mean NEES that does not contradict the
    covariance. Measured on the real five-session problem (problems/real/sessions-*.yaml):
    tau 190-470 samples per session, 4-9 independent values, intervals from about
    [0.55, 4.4] to [0.9, 3.5] around the expected 2."""
    from scipy.stats import chi2

    q = np.asarray(q, dtype=float)
    tau = max(1.0, autocorrelation_time(q))
    n = q.size / tau
    a = 0.025
    return {
        "nees_tau": float(tau),
        "nees_independent": float(n),
        "nees_interval_95": [float(chi2.ppf(a, n * d) / n), float(chi2.ppf(1 - a, n * d) / n)],
    }


class NotPositiveDefinite(ValueError):
    """The Hessian at the solution is not positive definite (no Laplace approximation)."""


def position_uncertainty(
    nlp: NLP,
    sol: Solution,
    params: dict,
    knots: Knots,
    dim: int,
    sigma_o: float = 0.0,
    meat: np.ndarray | None = None,
    var: str = "C",
    fixed: tuple[str, ...] = (),
    dense_max: int | None = None,
    reuse: dict[str, Any] | None = None,
    consider: np.ndarray | None = None,
    consider_fixed: dict[str, float] | None = None,
) -> PositionUncertainty:
    """Laplace covariances of the positions at the solution ``sol`` of ``nlp``: the
    unknowns ``var`` (K, dim) at the knots (``C``: the translational model's knot
    corrections; ``P`` with one knot per sample: the positions of the planar and pose
    models, every sample an unknown).

    The Hessian is factored densely up to ``dense_max`` unknowns (default
    :data:`DENSE_MAX_UNKNOWNS`) and solved for the knot columns; above, it is factored
    sparsely and solved for the covariance of each pair of neighbouring knots only
    (:func:`_knot_covariance_sparse`: the same figures, memory that grows with the
    factor's fill, not with the square of the unknowns). Between knots the odometry random
    walk (per-step standard deviation sigma_o) adds its Brownian-bridge variance
    sigma_o^2 s (k - s) / k per axis, s steps after a knot of an interval of k steps: the
    knot model leaves that part of the odometry noise out of the unknowns. Raises
    NotPositiveDefinite when the factorisation fails.
    (The Hessian does not depend on the bias value, in which the odometry block is
    quadratic, so the total bias a growing or sliding solve leaves in ``sol.x`` is harmless.)
    meat: an (n_x, n_x) matrix B - H, dense or sparse (:func:`magnetometer_correction`,
    :func:`whitened_correction`): the sandwich covariance H^-1 B H^-1 of the knots instead
    of H^-1 (the covariance of the MAP estimate when the score's covariance is B, not H).
    fixed: variables the solve held at their start values (NLP.solve's ``fixed``):
    conditioned on, not marginalised.
    reuse: a dict kept between calls for the same solution (the plain covariance, then the
    sandwich): the dense path keeps its factor there (:class:`_KnotFactor`), so the second
    call neither evaluates nor factors the Hessian again.
    consider: (n_x, q) C = H_xb S_b for q parameters b the solve held at zero (not
    unknowns: the data cannot tell them apart from the path) with prior covariance S_b
    S_b^T and cross Hessian H_xb: their uncertainty is taken in as consider parameters,
    H^-1 C C^T H^-1 added to the covariance (the MAP moves by -H^-1 H_xb db for a db).
    consider_fixed: variables among ``fixed`` taken in the same way, each with a prior
    standard deviation: C from their columns of the Hessian.
    """
    dense_max = DENSE_MAX_UNKNOWNS if dense_max is None else dense_max
    x = {k: v for k, v in sol.x.items() if k in nlp.x_layout.entries}
    entries = nlp.x_layout.entries
    free = np.ones(nlp.x_layout.size, dtype=bool)
    for name in fixed:
        free[entries[name].offset + np.arange(entries[name].size)] = False
    keep = np.flatnonzero(free)
    if meat is not None:
        meat = meat[keep][:, keep] if hasattr(meat, "tocsr") else meat[np.ix_(free, free)]
    if consider is not None:
        consider = np.asarray(consider, dtype=float)[keep]
    H_full = None
    if consider_fixed:
        H_full = nlp.hessian(x, params).tocsc()
        columns = []
        for name, sigma in consider_fixed.items():
            if name not in fixed:
                raise ValueError(f"consider_fixed: {name} is not held fixed")
            cols = entries[name].offset + np.arange(entries[name].size)
            columns.append(float(sigma) * H_full[keep][:, cols].toarray())
        extra = np.hstack(columns)
        consider = extra if consider is None else np.hstack([consider, extra])
    position = keep.searchsorted(entries[var].offset)
    if keep.size > dense_max:
        H = (nlp.hessian(x, params) if H_full is None else H_full)[keep][:, keep]
        cov = _knot_covariance_sparse(H.tocsc(), meat, knots, dim, position, consider)
    else:
        factor = None if reuse is None else reuse.get("factor")
        if factor is None:
            H = (nlp.hessian(x, params) if H_full is None else H_full)[keep][:, keep]
            factor = _KnotFactor(H, knots.count * dim, position)
            if reuse is not None:
                reuse["factor"] = factor
        cov = _knot_covariance_dense(factor, meat, knots, dim, consider)
    N = knots.n
    s_in = np.arange(N) - knots.samples[knots.left]
    k_in = knots.samples[knots.left + 1] - knots.samples[knots.left]
    bridge = sigma_o**2 * s_in * (k_in - s_in) / k_in
    cov += bridge[:, None, None] * np.eye(dim)
    return PositionUncertainty(0.5 * (cov + np.swapaxes(cov, 1, 2)))


class _KnotFactor:
    """A dense Cholesky factor of the Hessian H (sparse, n x n) with its k knot unknowns
    (rows ``position`` .. ``position`` + k - 1) ordered last, H_p = L L^T. The knot block
    of H^-1 is then that of H_p^-1 = L^-T L^-1, and since L^-1 [0; I_k] = [0; Y] with Y =
    L_kk^-1 the inverse of the factor's trailing k x k block, it is Y^T Y: one triangular
    inverse of k x k after the factorisation, where solving H Z = E for the k knot columns
    costs 2 n^2 k more. Measured 2026-12-06 on the 1,500-sample planar walk over 30 x 20 m
    (10,124 unknowns, 3,000 of them positions; the Hessian's evaluation included), three
    pairs of runs against the solve for the knot columns: 15.1-15.8 s -> 7.3-10.3 s
    (medians 15.3 -> 7.6 s), the same covariance to 3e-13. The columns Z = H^-1 E themselves
    (n x k: the sandwich covariance's Z^T B Z) are solved only when asked for
    (:meth:`columns`). Raises NotPositiveDefinite when the factorisation fails or the
    Hessian is singular to machine precision (:func:`_check_pivots`)."""

    def __init__(self, H: Any, k: int, position: int) -> None:
        n = H.shape[0]
        cols = position + np.arange(k)  # column-major (K, d): axis a at a*K + j
        self.perm = np.concatenate([np.setdiff1d(np.arange(n), cols), cols])
        at = np.empty(n, dtype=np.int64)
        at[self.perm] = np.arange(n)  # where each unknown goes
        coo = H.tocoo()  # the symmetric permutation of the sparse matrix, then dense in
        # LAPACK's order (factored without a copy)
        Hp = sps.csc_matrix((coo.data, (at[coo.row], at[coo.col])), shape=(n, n))
        Hp = Hp.toarray(order="F")
        diagonal = Hp.diagonal().copy()
        try:
            self.L, _ = sla.cho_factor(Hp, lower=True, overwrite_a=True, check_finite=True)
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise _not_positive_definite(exc) from None
        _check_pivots(self.L.diagonal() ** 2, diagonal)
        self.k = k
        self.Y = sla.solve_triangular(self.L[n - k :, n - k :], np.eye(k), lower=True)
        #: (k, k) the knot block of H^-1
        self.block = self.Y.T @ self.Y
        self._Z: np.ndarray | None = None

    def columns(self) -> np.ndarray:
        """(n, k) Z = H^-1 E, E the knot columns of the identity (in H's own order)."""
        if self._Z is None:
            n, k = self.L.shape[0], self.k
            V = np.zeros((n, k))
            V[n - k :] = self.Y
            Zp = sla.solve_triangular(self.L, V, lower=True, trans="T", overwrite_b=True)
            self._Z = np.empty_like(Zp)
            self._Z[self.perm] = Zp
        return self._Z

    def cross(self, C: np.ndarray) -> np.ndarray:
        """(k, q) Z^T C = E^T H^-1 C for C (n, q): Y^T times the last k rows of L^-1 C_p."""
        n = self.L.shape[0]
        V = sla.solve_triangular(self.L, np.asarray(C, dtype=float)[self.perm], lower=True)
        return self.Y.T @ V[n - self.k :]


def _not_positive_definite(exc: Any) -> NotPositiveDefinite:
    return NotPositiveDefinite(f"Hessian at the solution is not positive definite ({exc})")


#: Smallest ratio of a factor's pivot to its unknown's diagonal entry taken as information
#: (:func:`_check_pivots`); rounding leaves singular matrices' pivots at 1e-11 of their
#: entries and below (measured there).
PIVOT_RATIO_MIN = 1e-10


def _check_pivots(pivots: np.ndarray, diagonal: np.ndarray) -> None:
    """NotPositiveDefinite when a factor's pivot (the squared Cholesky pivot, or LU's with
    symmetric pivoting) is below :data:`PIVOT_RATIO_MIN` of its unknown's diagonal entry:
    that unknown is, to machine precision, a combination of those factored before it
    (its conditional variance 1e10 times its own scale), and whether the factorisation
    fails there or goes on with a pivot of either sign depends on the order of the
    unknowns. Measured: the tiny walk with no field (sigma_m 1e6) and a free odometry
    bias (smallest eigenvalue -2e-11 against a largest of 3e7) fails in its own order and
    with its positions last goes on with a last pivot of 9e-11; random 23 x 23 matrices
    of rank 22 (seeds 0-199) went on in 108 of 200 draws, their smallest pivots at most
    8.4e-12 of their entries."""
    ratio = np.asarray(pivots, dtype=float) / np.asarray(diagonal, dtype=float)
    if not np.all(ratio > PIVOT_RATIO_MIN):
        i = int(np.argmin(ratio))
        raise _not_positive_definite(
            f"a pivot of {float(pivots[i]):.3g} against its diagonal entry "
            f"{float(diagonal[i]):.3g}: numerically singular"
        )


def _knot_covariance_dense(
    factor: _KnotFactor, meat: Any, knots: Knots, dim: int,
    consider: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(N, d, d) covariances of the samples from the factor of H (:class:`_KnotFactor`):
    the knot block of H^-1, plus Z^T meat Z for the sandwich and (Z^T C)(Z^T C)^T for
    the consider parameters (:func:`position_uncertainty`)."""
    K = knots.count
    cov_c = factor.block
    if meat is not None:
        Z = factor.columns()
        cov_c = cov_c + Z.T @ dense_product(meat, Z)
    if consider is not None:
        G = factor.cross(consider)
        cov_c = cov_c + G @ G.T
    A = knots.matrix  # sparse (N, K)
    cov = np.empty((knots.n, dim, dim))
    for a in range(dim):
        for b in range(dim):
            block = cov_c[a * K : (a + 1) * K, b * K : (b + 1) * K]
            cov[:, a, b] = _row_quadratic(A, block)
    return cov


#: Bytes of the dense right-hand sides one sparse solve of :func:`_knot_covariance_sparse`
#: may hold (they set how many knots a chunk takes).
SPARSE_CHUNK_BYTES = 256 * 2**20


def _knot_covariance_sparse(
    H: Any, meat: Any, knots: Knots, dim: int, position: int,
    consider: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(N, d, d) covariances of the samples from a sparse LU factor of H (diagonal
    pivoting, so its pivots are positive exactly when H is positive definite): a sample
    reads at most its two neighbouring knots (casmag.model.knots), so only the covariance
    of each pair of neighbouring knots is needed. The samples are taken in chunks of their
    left knots, each solved for those knots and the next; memory is the factor plus one
    chunk's
    right-hand sides (:data:`SPARSE_CHUNK_BYTES`), whatever the number of knots."""
    import scipy.sparse.linalg as spla

    n, K = H.shape[0], knots.count
    try:
        lu = spla.splu(
            H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )  # fmt: skip
    except RuntimeError as exc:  # an exactly singular factor
        raise _not_positive_definite(exc) from None
    pivots = lu.U.diagonal()
    if not (np.all(np.isfinite(pivots)) and np.all(pivots > 0)):
        raise _not_positive_definite(f"a pivot of {pivots.min():.3g}")
    # U's j-th pivot is unknown argsort(perm_c)[j]'s (on a diagonally dominant matrix
    # U_jj / H_jj came to 0.997-1 so, and to 5e-6-7e5 read through perm_c itself)
    _check_pivots(pivots, H.diagonal()[np.argsort(lu.perm_c)])
    A = knots.matrix.tocsr()  # (N, K), each row on its left knot and the next
    left = np.asarray(knots.left)
    chunk = max(1, SPARSE_CHUNK_BYTES // (8 * n * dim) - 1)
    cov = np.empty((knots.n, dim, dim))
    for j0 in range(0, K, chunk):
        j1 = min(K, j0 + chunk)
        lo, hi = j0, min(K, j1 + 1)
        span = np.arange(lo, hi)
        cols = position + np.concatenate([a * K + span for a in range(dim)])
        E = np.zeros((n, cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        Z = lu.solve(E)
        G = Z[cols, :]
        if meat is not None:
            G = G + Z.T @ dense_product(meat, Z)
        if consider is not None:
            Gc = Z.T @ consider
            G = G + Gc @ Gc.T
        rows = np.flatnonzero((left >= j0) & (left < j1))
        Ar = A[rows][:, lo:hi]
        m = span.size
        for a in range(dim):
            for b in range(dim):
                block = G[a * m : (a + 1) * m, b * m : (b + 1) * m]
                cov[rows, a, b] = _row_quadratic(Ar, block)
    return cov


def _row_quadratic(A, B: np.ndarray) -> np.ndarray:
    """(N,) diag(A B A^T) for a sparse or dense A (N, K) and dense B (K, K)."""
    AB = A @ B
    if hasattr(A, "multiply"):
        return np.asarray(A.multiply(AB).sum(axis=1)).ravel()
    return np.sum(np.asarray(A) * AB, axis=1)


#: Largest number of unknowns whose Hessian :func:`position_uncertainty` factors densely
#: (12,000 unknowns take 1.2 GB); above, it factors it sparsely.
DENSE_MAX_UNKNOWNS = 12_000

#: Largest number of unknowns for which the Laplace covariance of a model with a state at
#: every sample (planar, pose) is computed: densely (the sparse path would solve for two
#: columns a sample).
UNCERTAINTY_MAX_UNKNOWNS = DENSE_MAX_UNKNOWNS

#: Largest number of unknowns for which the translational model's Laplace covariance is
#: computed (sparsely above DENSE_MAX_UNKNOWNS: its knots are few, so the columns solved
#: for are too).
KNOT_UNCERTAINTY_MAX_UNKNOWNS = 200_000

#: Largest number of map unknowns whose posterior precision is saved (a dense n_z x n_z
#: matrix: 290 MB at 6,000, 108 MB at the real field's 3,675).
MAP_MAX_UNKNOWNS = 6_000


def saved_field_map(
    nlp: NLP,
    sol: Solution,
    params: dict[str, Any],
    kernel: str,
    basis: tuple,
    hyper: dict[str, float],
    frame: str,
    whitened: bool = False,
    position_dim: int | None = None,
    max_unknowns: int = UNCERTAINTY_MAX_UNKNOWNS,
) -> tuple[Any, dict[str, Any]]:
    """The map of a solved reduced-rank NLP to save (casmag.gp.savedmap.map_from_solution,
    conditioned on the variables the solve held, ``sol.fixed``) and a record of it for a
    result's ``info["map"]``: ``{"saved": True, "posterior": True, "unknowns", "kernel"}``;
    the mean alone (``"posterior": False`` and the ``reason``) when the map has more
    unknowns than :data:`MAP_MAX_UNKNOWNS` or the NLP more than ``max_unknowns``, when it
    builds no Hessian, or when the posterior is not positive definite; ``{"saved": False,
    "reason"}`` for a failed solve. ``whitened``: the NLP solves for the whitened weights
    (planar, pose, IMU); ``position_dim``: the positions the map is read at (default the
    box's dimension)."""
    from casmag.errors import DataError
    from casmag.gp.savedmap import map_from_solution

    if not sol.success:
        return None, {"saved": False, "reason": "the solve failed"}
    n_z = sum(sol.x[n].size for n in ("W", "c") if n in sol.x)
    x = {n: sol.x[n] for n in nlp.x_layout.entries}
    record = {"saved": True, "posterior": True, "unknowns": n_z, "kernel": kernel}

    def mean_only(reason: str) -> tuple[Any, dict[str, Any]]:
        saved = map_from_solution(
            nlp, x, params, kernel, basis, hyper, frame, tuple(sol.fixed), whitened,
            position_dim, posterior=False,
        )  # fmt: skip
        return saved, {**record, "posterior": False, "reason": f"mean alone: {reason}"}

    if n_z > MAP_MAX_UNKNOWNS or nlp.x_layout.size > max_unknowns:
        return mean_only(
            f"{n_z} map unknowns, {nlp.x_layout.size} in all (limits {MAP_MAX_UNKNOWNS}, "
            f"{max_unknowns}) for a dense precision"
        )
    if (missing := without_hessian(nlp)) is not None:
        return mean_only(f"no precision ({missing['error']})")
    try:
        saved = map_from_solution(
            nlp, x, params, kernel, basis, hyper, frame, tuple(sol.fixed), whitened, position_dim
        )
        saved.cholesky()
    except (np.linalg.LinAlgError, RuntimeError, DataError) as exc:
        return mean_only(f"posterior not positive definite ({exc})")
    return saved, record


def without_hessian(nlp: NLP) -> dict[str, Any] | None:
    """The summary ``{"error": reason}`` when the NLP builds no Hessian to take the Laplace
    covariance from (``solver.hessian: limited-memory``), else None."""
    if nlp.solver.has_function("nlp_hess_l"):
        return None
    return {"error": "not computed: solver.hessian limited-memory builds no Hessian"}


def laplace_positions(
    covariance: Callable[[np.ndarray | None], PositionUncertainty],
    residuals: Callable[[], np.ndarray],
    correction: Callable[[np.ndarray], np.ndarray],
    bounds: list[tuple[int, int]],
    sigma_m: float,
    method: str,
    P_est: np.ndarray,
    P_true: np.ndarray | None,
) -> tuple[dict[str, Any], np.ndarray, np.ndarray | None]:
    """The Laplace position covariance of any motion model with the correction for
    correlated magnetometer residuals (module docstring): ``covariance(meat)`` the
    covariance with a Hessian correction (None: H^-1), ``residuals()`` the magnetometer
    residuals y - m (N, 3) at the solution, ``correction(factors)`` the Hessian correction
    B - H for per-sample, per-component factors (N, 3) (:func:`magnetometer_correction`,
    :func:`whitened_correction`); ``bounds`` the sessions' sample ranges. Returns the
    summary (with ``inflation`` and ``uninflated`` unless ``method`` is ``none``), the
    covariance and the plain one (None for ``none``). Raises NotPositiveDefinite."""
    u0 = covariance(None)
    if method == "none":
        return u0.summary(P_est, P_true), u0.cov, None
    inflation = residual_inflation(residuals(), bounds, sigma_m, method)
    u = u0
    if inflation.active:
        u = covariance(correction(inflation.factors(P_est.shape[0])))
    summary = u.summary(P_est, P_true)
    summary["inflation"] = inflation.to_dict()
    summary["uninflated"] = u0.summary(P_est, P_true)
    return summary, u.cov, u0.cov


def sample_state_uncertainty(
    nlp: NLP,
    sol: Solution,
    P_est: np.ndarray,
    P_true: np.ndarray | None,
    sigma_m: float,
    method: str,
    consider: np.ndarray | None = None,
    consider_fixed: dict[str, float] | None = None,
) -> tuple[dict[str, Any], np.ndarray | None, np.ndarray | None]:
    """:func:`laplace_positions` for a model whose positions ``P`` are unknowns at every
    sample and whose magnetometer block is read through a rotation (the planar and pose
    models: casmag.model.rotated, the block's Jacobian from its Hessian callback,
    RotatedFieldGaussNewton.residual_jacobian), at the parameters it was solved with and
    conditioned on the variables it held fixed (``sol.params``, ``sol.fixed``). Returns
    (summary, covariance, plain covariance); the summary is ``{"error": reason}`` (and the
    covariances None) when the Hessian is too large to factor densely or not positive
    definite. ``consider``, ``consider_fixed``: parameters held at zero whose uncertainty
    both covariances take in (:func:`position_uncertainty`)."""
    params, fixed = sol.params, sol.fixed
    if params is None:
        return {"error": "not computed: the solution records no parameters"}, None, None
    if nlp.x_layout.size > UNCERTAINTY_MAX_UNKNOWNS:
        reason = f"{nlp.x_layout.size} unknowns > {UNCERTAINTY_MAX_UNKNOWNS}"
        return {"error": f"not computed: {reason}"}, None, None
    if (missing := without_hessian(nlp)) is not None:
        return missing, None, None
    n, d = P_est.shape
    knots = Knots(n, 1)
    block = nlp.keep[1] if nlp.keep is not None else None
    if not hasattr(block, "residual_jacobian"):
        return {"error": "not computed: the magnetometer block gives no Jacobian"}, None, None
    state: dict[str, Any] = {}
    reuse: dict[str, Any] = {}  # the plain covariance's factor, read again by the sandwich

    def residuals() -> np.ndarray:
        x = nlp.x_layout.pack({k: v for k, v in sol.x.items() if k in nlp.x_layout.entries})
        e, state["J"] = block.residual_jacobian(x, nlp.p_layout.pack(params))
        return sigma_m * e

    try:
        return laplace_positions(
            lambda meat: position_uncertainty(
                nlp,
                sol,
                dict(params),
                knots,
                d,
                meat=meat,
                var="P",
                fixed=fixed,
                consider=consider,
                consider_fixed=consider_fixed,
                reuse=reuse,
            ),
            residuals,
            lambda factors: whitened_correction(state["J"], factors),
            knots.bounds,
            sigma_m,
            method,
            P_est,
            P_true,
        )
    except NotPositiveDefinite as exc:
        return {"error": str(exc)}, None, None


def whitened_correction(J: Any, factors: np.ndarray) -> np.ndarray:
    """Sparse (n_x, n_x) B - H = sum_kc (factors_kc - 1) J_kc^T J_kc for the Jacobian J
    (3N, n_x) of whitened residuals (y - m) / sigma_m stacked sample by sample."""
    import scipy.sparse as sp

    v = np.asarray(factors, dtype=float).ravel() - 1.0  # (N, 3) row-major: sample-major
    return sp.csr_matrix(J.T @ sp.diags(v) @ J)


# ----------------------------------------------------------------- correlated residuals
INFLATION_METHODS = ("none", "correlation", "long-run")


def autocorrelation_time(r: np.ndarray) -> float:
    """Integrated autocorrelation time tau = 1 + 2 sum_{k>=1} rho_k of a sequence (its
    mean removed), by Geyer's (1992) initial monotone sequence estimator: the sums of
    adjacent autocorrelations Gamma_m = rho_2m + rho_2m+1 are summed while positive, each
    capped at the previous one, tau = -1 + 2 sum_m Gamma_m. White noise gives about 1, an
    AR(1) sequence (1 + phi) / (1 - phi). At least 1 is not enforced here (negative
    correlation gives tau < 1); 1.0 for fewer than 4 samples or a constant sequence."""
    x = np.asarray(r, dtype=float).ravel()
    n = x.size
    x = x - x.mean()
    var = float(np.dot(x, x)) / max(n, 1)
    if n < 4 or var <= 0.0:
        return 1.0
    f = np.fft.rfft(x, 2 * n)
    acov = np.fft.irfft(f * np.conj(f), 2 * n)[:n] / n
    rho = acov / acov[0]
    m = (n - 1) // 2
    gamma = rho[0 : 2 * m : 2] + rho[1 : 2 * m : 2]
    total, last = 0.0, np.inf
    for g in gamma:
        if g <= 0.0:
            break
        last = min(last, float(g))
        total += last
    return -1.0 + 2.0 * total


@dataclass
class Inflation:
    """Per session (rows) and field component (columns): the residuals' autocorrelation time
    ``tau``, their standard deviation ``rms`` at the solution (mean removed) and the factor
    ``lam`` by which the magnetometer variance sigma_m^2 is inflated in the sandwich's
    score covariance."""

    method: str
    sigma_m: float
    bounds: list[tuple[int, int]]
    tau: np.ndarray
    rms: np.ndarray
    lam: np.ndarray

    def factors(self, n: int) -> np.ndarray:
        """(n, 3) factor lambda of every magnetometer residual (sample, component)."""
        w = np.ones((n, self.lam.shape[1]))
        for s, (a, b) in enumerate(self.bounds):
            w[a:b] = self.lam[s]
        return w

    @property
    def active(self) -> bool:
        return bool(np.any(self.lam != 1.0))

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "sigma_m": self.sigma_m,
            "tau": self.tau.tolist(),
            "residual_rms": self.rms.tolist(),
            "factor": self.lam.tolist(),
            "factor_mean": float(np.mean(self.lam)),
            "active": self.active,
        }


def residual_inflation(
    R: np.ndarray, bounds: list[tuple[int, int]], sigma_m: float, method: str = "long-run"
) -> Inflation:
    """The magnetometer variance inflation of each session and component from the
    residuals R (N, 3) = y - m(p) at the solution (see the module docstring)."""
    if method not in INFLATION_METHODS:
        raise ValueError(f"inflation method {method!r} is not one of {INFLATION_METHODS}")
    S, c = len(bounds), R.shape[1]
    tau, rms = np.ones((S, c)), np.zeros((S, c))
    for s, (a, b) in enumerate(bounds):
        for j in range(c):
            tau[s, j] = autocorrelation_time(R[a:b, j])
            rms[s, j] = float(np.std(R[a:b, j]))
    if method == "none":
        lam = np.ones((S, c))
    elif method == "correlation":
        lam = np.maximum(1.0, tau)
    else:
        lam = np.maximum(1.0, tau * rms**2 / sigma_m**2)
    return Inflation(method, float(sigma_m), list(bounds), tau, rms, lam)


def magnetometer_correction(
    nlp: NLP,
    sol: Solution,
    structure,
    weights: np.ndarray,
    sigma_m: float,
    params: dict | None = None,
) -> np.ndarray:
    """Sparse (n_x, n_x) change of the Hessian when the Gauss-Newton information of each
    magnetometer residual (sample k, component c) is scaled by weights[k, c]:
    sum_kc (weights_kc - 1) J_kc^T J_kc / sigma_m^2, with J_kc the residual's gradient.

    Tiled map: the block's own Jacobian of its whitened residuals at the solution
    (casmag.model.tiledmap; ``params`` the solve's parameters, whose sigma_m it reads).

    Reduced-rank map (casmag.model.rrmap): J_kc reaches the knots through dm_c/dp_k and the
    interpolation matrix A, the weights through the basis row (SE: component c's column of
    W; curl-free: the shared potential) and the constant field c_c. Exact GP: the residual
    y_kc - M_kc, so only the diagonal of the M block changes."""
    import scipy.sparse as sp

    n_x = nlp.x_layout.size
    E = nlp.x_layout.entries
    if structure.form == "tiled":
        if params is None:
            raise ValueError("a tiled map's correction needs the solve's parameters")
        x = nlp.x_layout.pack({k: v for k, v in sol.x.items() if k in E})
        _, J = nlp.keep[1].residual_jacobian(x, nlp.p_layout.pack(params))
        return whitened_correction(J, weights)
    V = (np.asarray(weights, dtype=float) - 1.0) / sigma_m**2  # (N, 3)
    if structure.form != "reduced_rank":
        e = E["M"]
        N = e.shape[0]
        idx = e.offset + np.arange(N * FIELD_DIM)  # column-major (N, 3)
        return sp.csr_matrix((V.ravel(order="F"), (idx, idx)), shape=(n_x, n_x))

    knots, d, kernel = structure.knots, structure.dim, structure.kernel
    basis = structure.hilbert_basis()
    M, K = basis.num_basis, knots.count
    wts = sol.x["W"].ravel(order="F")
    P = sol.x["P"]
    cidx = E["C"].offset + np.arange(K * d)
    w0 = E["W"].offset
    c0 = E["c"].offset if "c" in E else None
    A = knots.matrix
    parts: list[tuple[np.ndarray, ...]] = []
    # Each component's weight block, summed over the chunks before it is placed (placed per
    # chunk, the duplicates took about 3 GB on a 16,000-sample walk before they were summed).
    blocks: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    step = MapModel.CHUNK // 4
    for s0 in range(0, knots.n, step):
        r = slice(s0, min(knots.n, s0 + step))
        _, Aw, D = field_and_jacobians(basis, kernel, P[r], wts)
        Ar = A[r]
        for comp in range(FIELD_DIM):
            v = V[r, comp]
            if not np.any(v):
                continue
            Jp = sp.hstack([sp.diags(D[:, comp, a]) @ Ar for a in range(d)]).tocsr()
            if kernel == "se":
                Jw, widx = Aw[0], w0 + comp * M + np.arange(M)
            else:
                Jw, widx = Aw[comp], w0 + np.arange(M)
            if c0 is not None:
                Jd = np.column_stack([Jw, np.ones(Jw.shape[0])])
                didx = np.append(widx, c0 + comp)
            else:
                Jd, didx = Jw, widx
            VJp = sp.diags(v) @ Jp
            Hpd = np.asarray(VJp.T @ Jd)
            parts.append(_placed((Jp.T @ VJp).tocoo(), cidx, cidx))
            parts.append(_placed(sp.coo_matrix(Hpd), cidx, didx))
            parts.append(_placed(sp.coo_matrix(Hpd.T), didx, cidx))
            block = Jd.T @ (v[:, None] * Jd)
            if comp in blocks:
                blocks[comp][0][...] += block
            else:
                blocks[comp] = (block, didx)
    for block, didx in blocks.values():
        parts.append(_placed(sp.coo_matrix(block), didx, didx))
    if not parts:
        return sp.csr_matrix((n_x, n_x))
    rows, cols, vals = (np.concatenate(t) for t in zip(*parts, strict=True))
    return sp.csr_matrix((vals, (rows, cols)), shape=(n_x, n_x))  # duplicates summed


def _placed(block: Any, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, ...]:
    """(row, column, value) of a sparse block placed at the unknowns ``rows`` x ``cols``."""
    return rows[block.row], cols[block.col], block.data
