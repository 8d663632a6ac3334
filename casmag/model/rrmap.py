"""The reduced-rank (Hilbert-space) GP field map inside the MAP problem.

The field is a linear model in basis-function weights (``casmag.gp.reduced_rank``):

- ``se``: m(x) = W^T phi(x) + c, W (M, 3), one weight column per field component;
- ``curl_free``: m(x) = grad phi(x)^T w + c, w (M,) weights of the scalar potential;

with an optional constant field c ~ N(0, sigma_lin^2 I) (Solin et al. 2018). The prior block
is diagonal: 0.5 sum_j |w_j|^2 / S_j(theta) [+ 0.5 n_c sum_j log S_j(theta) when the
hyperparameters are estimated], so sigma_f and l stay estimable at O(M) cost.

Every magnetometer residual couples one pose with all M weights, so the Lagrangian Hessian
has a dense weight block and a dense pose-weight border. CasADi's automatic Hessian of the
mapped residuals costs O(N M^2) operations in its virtual machine; :class:`GaussNewtonHessian`
instead forms the Gauss-Newton Hessian of the magnetometer block with numpy (BLAS for the
M x M block) and hands it to IPOPT through ``hess_lag``, added to CasADi's exact Hessian of
the other (cheap, sparse) blocks.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import scipy.sparse as sps

from casmag import memory
from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import HilbertBasis, default_margin, default_num_basis, domain_for
from casmag.model.knots import Knots

# Frequencies up to OMEGA_FACTOR / l. The covariance error of 4 / l (reduced_rank's default) is
# small, but positions depend on field gradients, which weight high frequencies by omega^2:
# on the base case, 4 / l (M = 110) put positions 1.8 mm from the exact GP's; 5 / l (M = 170)
# within 0.4 mm over seeds 1-5.
OMEGA_FACTOR = 5.0


@dataclass(frozen=True)
class MapLayout:
    """Where the map's unknowns and the data sit in the NLP's x and p vectors.

    C: offset of the knot corrections (K, d) in x, column-major (casmag.model.knots; the positions
    are P = Q + A C); Q, Y: offsets of the dead-reckoned positions (N, d) (None: the
    positions are A C, the variables themselves with one knot per sample) and of the
    magnetometer samples (N, 3) in p, column-major; W: offset of
    weights (SE: (M, 3) column-major, curl-free: (M,)); c: offset of the constant field or
    None; sigma_m: offset of sigma_m in p.
    """

    n_x: int
    n_p: int
    C: int
    Q: int | None
    Y: int
    W: int
    c: int | None
    sigma_m: int


def make_basis(
    kernel: str, X: np.ndarray, lengthscale: float, num_basis: int | None, margin: float | None
) -> HilbertBasis:
    """The basis for a map around positions X (N, d): the bounding box grown by ``margin``
    (default 3 l), M basis functions (default: frequencies up to OMEGA_FACTOR / l)."""
    margin = default_margin(lengthscale) if margin is None else margin
    domain = domain_for(kernel, X, lengthscale, margin)
    if num_basis is None:
        num_basis = default_num_basis(domain, lengthscale, omega_factor=OMEGA_FACTOR)
    return HilbertBasis(domain, num_basis)


def field_and_jacobians(
    basis: HilbertBasis, kernel: str, P: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Field without the constant (N, 3), the weight Jacobian rows, and dm/dp (N, 3, d).

    Weight Jacobian: SE: [phi] (one (N, M) array, the same for every component);
    curl-free: [G_x, G_y, G_z], G_b (N, M) = d phi / dx_b.
    """
    N, d = P.shape
    if kernel == "se":
        Phi = basis.phi(P)
        W = weights.reshape(-1, FIELD_DIM, order="F")
        grads = basis.grad_phi(P)  # (N, D, M)
        D = np.stack([grads[:, a, :] @ W for a in range(d)], axis=2)  # (N, 3, d)
        return Phi @ W, [Phi], D
    w = weights.ravel()
    grads = basis.grad_phi(P)
    G = [grads[:, b, :] for b in range(FIELD_DIM)]
    H = basis.second_derivatives(P)
    D = np.empty((N, FIELD_DIM, d))
    for b in range(FIELD_DIM):
        for a in range(d):
            D[:, b, a] = H[(min(a, b), max(a, b))] @ w
    return np.stack([g @ w for g in G], axis=1), G, D


def derivative_order(input_dim: int) -> Callable[..., tuple[int, ...]]:
    """o(a, b, ...): the multi-index of HilbertBasis.derivatives that differentiates once
    along each axis named (o() the basis functions themselves)."""

    def o(*axes: int) -> tuple[int, ...]:
        t = [0] * input_dim
        for a in axes:
            t[a] += 1
        return tuple(t)

    return o


def curvature_terms(
    basis: HilbertBasis, kernel: str, P: np.ndarray, weights: np.ndarray, R: np.ndarray
) -> tuple[dict[tuple[int, int], np.ndarray], list[np.ndarray]]:
    """The second-order part of the Hessian of 0.5 |r|^2, r = y - m(p; w) - c, per sample:
    sum_c r_c d^2 m_c / dp_a dp_b for a <= b ((N,) each) and sum_c r_c d^2 m_c / dp_a dw
    ((N, n_w) per a, in the weight layout of :func:`field_and_jacobians`). The Hessian is
    J^T J minus these (m is linear in w and c, so no other block has curvature)."""
    N, d = P.shape
    o = derivative_order(basis.input_dim)
    pairs = [(a, b) for a in range(d) for b in range(a, d)]
    if kernel == "se":
        W = weights.reshape(-1, FIELD_DIM, order="F")
        der = basis.derivatives(P, [o(a, b) for a, b in pairs] + [o(a) for a in range(d)])
        s2 = {(a, b): np.einsum("kc,kc->k", der[o(a, b)] @ W, R) for a, b in pairs}
        rows = [(R[:, :, None] * der[o(a)][:, None, :]).reshape(N, -1) for a in range(d)]
        return s2, rows
    w = weights.ravel()
    orders = {o(c, a, b) for c in range(FIELD_DIM) for a, b in pairs}
    orders |= {o(c, a) for c in range(FIELD_DIM) for a in range(d)}
    der = basis.derivatives(P, sorted(orders))
    s2 = {(a, b): sum((der[o(c, a, b)] @ w) * R[:, c] for c in range(FIELD_DIM)) for a, b in pairs}
    rows = [sum(R[:, c : c + 1] * der[o(c, a)] for c in range(FIELD_DIM)) for a in range(d)]
    return s2, rows


class MapModel:
    """The magnetometer block's data in the NLP vectors: positions, weights, constant field,
    samples and noise at a point (x, p), per the layout, and the residual chunks."""

    CHUNK = 4096

    def __init__(
        self, basis: HilbertBasis, kernel: str, knots: Knots, dim: int, layout: MapLayout
    ) -> None:
        self.basis, self.kernel, self.knots, self.dim, self.lay = basis, kernel, knots, dim, layout
        self.n_w = basis.num_basis * (FIELD_DIM if kernel == "se" else 1)
        self._last_cost: tuple[np.ndarray, np.ndarray, float] | None = None

    def unpack(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """Positions P (N, d), weights (n_w,), constant field (3,), samples Y (N, 3),
        sigma_m at the NLP point."""
        kn, d, lay = self.knots, self.dim, self.lay
        N = kn.n
        C = x[lay.C : lay.C + kn.count * d].reshape(kn.count, d, order="F")
        if lay.Q is None:
            Q = np.zeros((N, d))
        else:
            Q = p[lay.Q : lay.Q + N * d].reshape(N, d, order="F")
        w = x[lay.W : lay.W + self.n_w]
        c = x[lay.c : lay.c + FIELD_DIM] if lay.c is not None else np.zeros(FIELD_DIM)
        Y = p[lay.Y : lay.Y + N * FIELD_DIM].reshape(N, FIELD_DIM, order="F")
        return kn.positions(Q, C), w, c, Y, float(p[lay.sigma_m])

    def chunks(self) -> list[slice]:
        N = self.knots.n
        return [slice(s, min(N, s + self.CHUNK)) for s in range(0, N, self.CHUNK)]

    def cost(self, x: np.ndarray, p: np.ndarray) -> float:
        """0.5 sum_k |(y_k - m(p_k) - c) / sigma_m|^2. The last point's value is kept: the
        Hessian callback's switch reads the cost at the point IPOPT just evaluated."""
        last = self._last_cost
        if last is not None and np.array_equal(last[0], x) and np.array_equal(last[1], p):
            return last[2]
        P, w, c, Y, sigma = self.unpack(x, p)
        total = 0.0
        for r in self.chunks():
            m = evaluate_map(self.basis, self.kernel, P[r], w)
            total += float(np.sum((Y[r] - m - c) ** 2))
        value = 0.5 * total / sigma**2
        self._last_cost = (np.array(x, copy=True), np.array(p, copy=True), value)
        return value

    def gradient(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """(n_x,) gradient of :meth:`cost` with respect to x (zero outside C, W and c)."""
        kn, d, lay = self.knots, self.dim, self.lay
        P, w, c, Y, sigma = self.unpack(x, p)
        g_P = np.empty((kn.n, d))
        g_w = np.zeros(self.n_w)
        g_c = np.zeros(FIELD_DIM)
        for r in self.chunks():
            m, Aw, D = field_and_jacobians(self.basis, self.kernel, P[r], w)
            R = Y[r] - m - c  # d cost / d m = -R / sigma^2
            g_P[r] = -np.einsum("kc,kca->ka", R, D)
            if self.kernel == "se":
                g_w -= (Aw[0].T @ R).ravel(order="F")
            else:
                g_w -= sum(Aw[b].T @ R[:, b] for b in range(FIELD_DIM))
            g_c -= R.sum(axis=0)
        out = np.zeros(lay.n_x)
        out[lay.C : lay.C + kn.count * d] = (kn.matrix.T @ g_P).ravel(order="F")
        out[lay.W : lay.W + self.n_w] = g_w
        if lay.c is not None:
            out[lay.c : lay.c + FIELD_DIM] = g_c
        return out / sigma**2


def _array(buffer: Any) -> np.ndarray:
    """A float64 view of a CasADi callback buffer (no copy)."""
    return np.frombuffer(buffer, dtype=np.float64)


def evaluate_map(
    basis: HilbertBasis, kernel: str, P: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """(N, 3) field of the map without its constant term at positions P (N, d)."""
    if kernel == "se":
        return basis.phi(P) @ weights.reshape(-1, FIELD_DIM, order="F")
    grads = basis.grad_phi(P)
    return np.stack([grads[:, b, :] @ weights.ravel() for b in range(FIELD_DIM)], axis=1)


class NumpyCost(ca.Callback):
    """A scalar cost block f(x, p) of the stacked NLP vectors evaluated with numpy:
    ``value(x, p) -> float`` and ``gradient(x, p) -> (n_x,)``, the gradient through a second
    callback (the data p are not differentiated). Its Hessian goes to IPOPT separately
    (a :class:`HessianCallback` in ``hess_lag``)."""

    def __init__(
        self,
        name: str,
        n_x: int,
        n_p: int,
        value: Callable[[np.ndarray, np.ndarray], float],
        gradient: Callable[[np.ndarray, np.ndarray], np.ndarray],
    ):
        ca.Callback.__init__(self)
        self.n_x, self.n_p, self.value = n_x, n_p, value
        self._grad = _NumpyGradient(f"{name}_grad", n_x, n_p, gradient)
        self.construct(name, {})

    def get_n_in(self) -> int:
        return 2

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense([self.n_x, self.n_p][i], 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(1, 1)

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg: list[Any], res: list[Any]) -> int:
        _array(res[0])[0] = self.value(_array(arg[0]).copy(), _array(arg[1]).copy())
        return 0

    def has_jacobian(self) -> bool:
        return True

    def get_jacobian(self, name: str, inames: list[str], onames: list[str], opts: dict) -> Any:
        return self._grad


class _NumpyGradient(ca.Callback):
    """Jacobian of :class:`NumpyCost`: inputs (x, p, f), outputs df/dx (1, n_x) dense and
    df/dp (1, n_p) structurally zero."""

    def __init__(self, name: str, n_x: int, n_p: int, gradient: Callable[..., np.ndarray]):
        ca.Callback.__init__(self)
        self.n_x, self.n_p, self.gradient = n_x, n_p, gradient
        self.construct(name, {})

    def get_n_in(self) -> int:
        return 3

    def get_n_out(self) -> int:
        return 2

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense([self.n_x, self.n_p, 1][i], 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        if i == 0:
            return ca.Sparsity.dense(1, self.n_x)
        return ca.Sparsity(1, self.n_p)

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg: list[Any], res: list[Any]) -> int:
        _array(res[0])[:] = self.gradient(_array(arg[0]).copy(), _array(arg[1]).copy())
        return 0


class MagnetometerCost(NumpyCost):
    """The magnetometer block f(x, p) = 0.5 sum_k |(y_k - m(p_k)) / sigma_m|^2 evaluated
    with numpy (BLAS), its gradient too.

    A CasADi graph of N mapped residuals costs O(N) to build and to differentiate (measured:
    36 s inside ``nlpsol`` at N = 16,000); this block is O(1) to build, and IPOPT gets its
    Hessian from :class:`GaussNewtonHessian`.
    """

    def __init__(self, name: str, model: MapModel):
        self.model = model
        super().__init__(name, model.lay.n_x, model.lay.n_p, model.cost, model.gradient)


class HessianCallback(ca.Callback):
    """A numpy Hessian block for IPOPT's ``hess_lag``: inputs (x, p, lam_f, lam_g), output
    the upper triangle in a pattern fixed at construction from (row, col) triplets, values
    from :meth:`values` in triplet order (not scaled by lam_f; the caller multiplies),
    written straight into CasADi's output buffer.

    ``mode``: ``gauss-newton`` (J^T J only), ``exact`` (plus the residuals' second-order
    terms) or ``hybrid``: Gauss-Newton while the block's cost falls fast, the exact Hessian
    once it falls by less than :attr:`SWITCH` of itself (and, where :attr:`SWITCH_UNITS` is
    set, by less than that many units of the cost) between two Hessian evaluations,
    :attr:`SWITCH_AFTER` times in a row (Fletcher and Xu's switch): Gauss-Newton is the
    safer step far from the solution, where large residuals make the exact Hessian
    indefinite and IPOPT's regularisation crawls; near it the exact Hessian converges
    quadratically where Gauss-Newton is only linear.
    ``exact_used`` records the choice per evaluation of the current solve."""

    MODES = ("gauss-newton", "exact", "hybrid")
    SWITCH = 0.2
    SWITCH_AFTER = 1
    SWITCH_UNITS = math.inf

    mode: str = "gauss-newton"
    exact_used: list[bool]
    _last_cost: float | None = None
    _slow: int = 0

    def set_mode(self, mode: str) -> None:
        """Choose the mode (one of :attr:`MODES`) for the next solves."""
        if mode not in self.MODES:
            raise ValueError(f"Hessian mode {mode!r} is not one of {self.MODES}")
        self.mode = mode
        self.reset()

    def reset(self) -> None:
        """Forget the previous solve (the hybrid switch starts with Gauss-Newton)."""
        self._last_cost = None
        self._slow = 0
        self.exact_used = []

    def _use_exact(self, cost: float) -> bool:
        """Whether this evaluation adds the second-order terms (the block's cost given)."""
        if self.mode != "hybrid":
            exact = self.mode == "exact"
        else:
            last, self._last_cost = self._last_cost, cost
            slow = last is not None and last - cost < min(self.SWITCH * last, self.SWITCH_UNITS)
            self._slow = self._slow + 1 if slow else 0
            exact = self._slow >= self.SWITCH_AFTER
        self.exact_used.append(exact)
        return exact

    def _set_pattern(self, rows: np.ndarray, cols: np.ndarray, n_x: int, n_p: int) -> None:
        memory.check_pattern(rows.size)  # before CasADi's copies of a pattern that won't fit
        self._rows, self._cols, self._n_x, self._n_p = rows, cols, n_x, n_p
        nnz = rows.size
        A = sps.csc_matrix(
            (np.arange(1, nnz + 1, dtype=np.float64), (rows, cols)), shape=(n_x, n_x)
        )
        A.sort_indices()
        if A.nnz != nnz:
            raise RuntimeError("duplicate entries in the Hessian pattern")
        self._perm = A.data.astype(np.int64) - 1
        self._sp = ca.Sparsity(
            n_x, n_x, A.indptr.astype(np.int64).tolist(), A.indices.astype(np.int64).tolist()
        )

    @property
    def nnz(self) -> int:
        return int(self._rows.size)

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def get_n_in(self) -> int:
        return 4

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ["x", "p", "lam_f", "lam_g"][i]

    def get_name_out(self, i: int) -> str:
        return "triu_hess_gamma_x_x"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense([self._n_x, self._n_p, 1, getattr(self, "n_g", 0)][i], 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return self._sp

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg: list[Any], res: list[Any]) -> int:
        # Raw buffers: building a DM from 10^7 numpy values takes 1.6 s, this a copy.
        x, p = _array(arg[0]), _array(arg[1])
        _array(res[0])[:] = self.values(x, p)[self._perm]
        return 0


class Pattern:
    """Upper-triangle (row, col) triplets of a Hessian block, collected in the order the
    values will come."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []

    def add(self, r: Any, c: Any) -> None:
        r, c = np.broadcast_arrays(np.asarray(r), np.asarray(c))
        self.rows.append(np.minimum(r, c).ravel())
        self.cols.append(np.maximum(r, c).ravel())

    def knot_chain(self, cidx: list[np.ndarray]) -> None:
        """The knot block A^T diag(s) A of positions interpolated between neighbouring
        knots: (j, j) and (j, j+1) within an axis; across two axes also (j+1, j). ``cidx``:
        the knot columns of each axis. Values: :func:`knot_chain_values`."""
        d = len(cidx)
        for a in range(d):
            for b in range(a, d):
                self.add(cidx[a], cidx[b])
                self.add(cidx[a][:-1], cidx[b][1:])
                if b > a:
                    self.add(cidx[a][1:], cidx[b][:-1])

    def constant_field(self, cidx: list[np.ndarray], widx: np.ndarray, c: int) -> None:
        """The constant field's rows: with the knots, the weights ``widx`` and itself.
        Values: :func:`constant_field_values`."""
        for b in range(FIELD_DIM):
            for a in range(len(cidx)):
                self.add(cidx[a], c + b)
            self.add(widx, c + b)
            self.add(np.array([c + b]), np.array([c + b]))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate(self.rows), np.concatenate(self.cols)


def knot_chain_values(
    knots: Knots,
    s_pp: dict[tuple[int, int], np.ndarray],
    d: int,
    scale: float,
    own: dict[tuple[int, int], np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Values of :meth:`Pattern.knot_chain`: A^T diag(s) A by bincount (diagonal and first
    off-diagonals), s_pp[a, b] (N,) the per-sample products of the position Jacobians;
    ``own[a, b]`` (K,), when given, added to the knots' diagonal."""
    left, alpha, K = knots.left, knots.alpha, knots.count
    out = []
    for a in range(d):
        for b in range(a, d):
            s = s_pp[a, b]
            diag = np.bincount(left, (1 - alpha) ** 2 * s, K) + np.bincount(
                left + 1, alpha**2 * s, K
            )
            if own is not None:
                diag = diag + own[a, b]
            off = np.bincount(left, (1 - alpha) * alpha * s, K - 1)
            out += [diag * scale, off * scale]
            if b > a:
                out.append(off * scale)
    return out


def constant_field_values(
    c_knot: np.ndarray, c_w: np.ndarray, n: int, scale: float
) -> list[np.ndarray]:
    """Values of :meth:`Pattern.constant_field`: c_knot (3, d, K) and c_w (3, n_w) the
    sums of the position and weight Jacobians per component, n samples."""
    out = []
    for b in range(FIELD_DIM):
        for a in range(c_knot.shape[1]):
            out.append(c_knot[b, a] * scale)
        out.append(np.ravel(c_w[b]) * scale)
        out.append(np.array([n * scale]))
    return out


class GaussNewtonHessian(HessianCallback):
    """Hessian of 0.5 sum_k |(y_k - m(p_k)) / sigma_m|^2 (upper triangle): Gauss-Newton
    J^T J, plus the residual-curvature terms (:func:`curvature_terms`) in mode ``exact``, or
    in mode ``hybrid`` once the cost stalls (:class:`HessianCallback`; measured: the exact
    Hessian from the start takes 199 iterations against 15 for Gauss-Newton on the
    curl-free base case; near the solution it converges fast where Gauss-Newton is linear:
    9 against 57 iterations on a 1,000-sample walk).

    The positions are p_k = q_k + sum_j A_kj c_j (casmag.model.knots), so the per-sample Jacobians
    D_k = dm/dp_k reach the knots through A: the knot block is A^T diag(D^T D) A (block
    tridiagonal), the knot-weight border A^T (D^T J_w) (dense, K d rows), the weight block
    J_w^T J_w (dense). Inputs (x, p, lam_f, lam_g) as IPOPT's ``hess_lag``; the output is
    *not* scaled by lam_f (the caller multiplies). The sparsity pattern is fixed at
    construction; each call fills the values with numpy over chunks of samples (memory
    O(chunk M)), one BLAS product per chunk for the weight block.
    """

    def __init__(self, name: str, model: MapModel, n_g: int = 0, mode: str = "gauss-newton"):
        ca.Callback.__init__(self)
        self.set_mode(mode)
        self.model, self.n_g = model, n_g
        self.basis, self.kernel, self.knots, self.dim, self.lay = (
            model.basis,
            model.kernel,
            model.knots,
            model.dim,
            model.lay,
        )
        self.n_w = model.n_w
        self._pattern()
        self.construct(name, {})

    # ------------------------------------------------------------------ pattern
    def _pattern(self) -> None:
        K, d, M, lay = self.knots.count, self.dim, self.basis.num_basis, self.lay
        j = np.arange(K)
        pat = Pattern()
        cidx = [lay.C + a * K + j for a in range(d)]  # (K,) each
        pat.knot_chain(cidx)
        # knot-weight border
        widx = lay.W + np.arange(self.n_w)
        for a in range(d):
            pat.add(cidx[a][:, None], widx[None, :])
        # weight-weight
        iu = np.triu_indices(M)
        if self.kernel == "se":
            for c in range(FIELD_DIM):
                pat.add(lay.W + c * M + iu[0], lay.W + c * M + iu[1])
        else:
            pat.add(lay.W + iu[0], lay.W + iu[1])
        if lay.c is not None:
            pat.constant_field(cidx, widx, lay.c)
        self._set_pattern(*pat.arrays(), lay.n_x, lay.n_p)

    def _se_chunk(
        self,
        P: np.ndarray,
        wts: np.ndarray,
        Yc: np.ndarray | None,
        Ar: Any,
        s_pp: dict[tuple[int, int], np.ndarray],
        r: slice,
    ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """One chunk of samples of the SE map: fills ``s_pp`` at rows ``r`` and returns
        phi (n, M), the border of each axis (k, 3 M) and dm/dp (n, 3, d); ``Yc`` the samples
        less the constant field for the exact Hessian's residual terms (None: Gauss-Newton).

        The border of axis a holds, for component c, A^T diag(dm_c/dp_a) phi minus, exact,
        A^T diag(r_c) dphi/dp_a: sparse products over the (n, M) basis arrays, each sample
        on its two knots, without forming the (n, 3 M) rows of the residuals' Jacobian
        (measured on a 16,000-sample walk, 787 functions, 1,600 knots: 2.3 -> 1.0 s per
        exact evaluation, 0.9 -> 0.6 s per Gauss-Newton one)."""
        d, M = self.dim, self.basis.num_basis
        o = derivative_order(self.basis.input_dim)
        pairs = [(a, b) for a in range(d) for b in range(a, d)]
        orders = [o()] + [o(a) for a in range(d)]
        if Yc is not None:
            orders += [o(a, b) for a, b in pairs]
        der = self.basis.derivatives(P, orders)
        W = wts.reshape(-1, FIELD_DIM, order="F")
        Phi = der[o()]
        D = np.stack([der[o(a)] @ W for a in range(d)], axis=2)  # (n, 3, d)
        R = None if Yc is None else Yc - Phi @ W
        for a, b in pairs:
            s_pp[a, b][r] = np.einsum("kc,kc->k", D[:, :, a], D[:, :, b])
            if R is not None:
                s_pp[a, b][r] -= np.einsum("kc,kc->k", der[o(a, b)] @ W, R)
        T = sps.csr_matrix(Ar.T)  # (k, n): each sample's column on its two knots
        cols = T.indices

        def weighted(v: np.ndarray) -> Any:
            return sps.csr_matrix((T.data * v[cols], cols, T.indptr), shape=T.shape)

        borders = []
        for a in range(d):
            blk = np.empty((T.shape[0], FIELD_DIM * M))
            for c in range(FIELD_DIM):
                part = weighted(D[:, c, a]) @ Phi
                if R is not None:
                    part -= weighted(R[:, c]) @ der[o(a)]
                blk[:, c * M : (c + 1) * M] = part
            borders.append(blk)
        return Phi, borders, D

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The Gauss-Newton entries in the order of the pattern's triplets."""
        kn, d, M, lay = self.knots, self.dim, self.basis.num_basis, self.lay
        N, K = kn.n, kn.count
        P, wts, c0, Y, sigma = self.model.unpack(x, p)
        inv2 = 1.0 / sigma**2
        chunks = self.model.chunks()
        # The cost IPOPT evaluated at this point (MapModel.cost keeps its last value).
        exact = self._use_exact(self.model.cost(x, p) if self.mode == "hybrid" else 0.0)
        left = kn.left
        A = kn.matrix
        pairs = [(a, b) for a in range(d) for b in range(a, d)]
        s_pp = {ab: np.empty(N) for ab in pairs}
        border = [np.zeros((K, self.n_w)) for _ in range(d)]
        G = np.zeros((M, M))
        c_knot = np.zeros((FIELD_DIM, d, K)) if lay.c is not None else None
        c_w = np.zeros((FIELD_DIM, self.n_w)) if lay.c is not None else None
        for r in chunks:
            j0, j1 = int(left[r.start]), int(left[r.stop - 1]) + 2
            Ar = A[r][:, j0:j1]
            if self.kernel == "se":
                Phi, rows_se, D = self._se_chunk(
                    P[r], wts, Y[r] - c0 if exact else None, Ar, s_pp, r
                )
                for a in range(d):
                    border[a][j0:j1] += rows_se[a]
                Aw = [Phi]
            else:
                m, Aw, D = field_and_jacobians(self.basis, self.kernel, P[r], wts)
                R = Y[r] - m - c0 if exact else None
                if exact:
                    s2, rows2 = curvature_terms(self.basis, self.kernel, P[r], wts, R)
                for a, b in pairs:
                    s_pp[a, b][r] = np.einsum("kc,kc->k", D[:, :, a], D[:, :, b])
                    if exact:
                        s_pp[a, b][r] -= s2[a, b]
                for a in range(d):
                    rows = sum(D[:, b, a][:, None] * Aw[b] for b in range(FIELD_DIM))
                    if exact:
                        rows = rows - rows2[a]
                    border[a][j0:j1] += Ar.T @ rows
            if self.kernel == "se":
                G += Aw[0].T @ Aw[0]
            else:
                G += sum(g.T @ g for g in Aw)
            if c_knot is not None:
                for b in range(FIELD_DIM):
                    for a in range(d):
                        c_knot[b, a, j0:j1] += Ar.T @ D[:, b, a]
                    if self.kernel == "se":
                        c_w[b, b * M : (b + 1) * M] += Aw[0].sum(axis=0)
                    else:
                        c_w[b] += Aw[b].sum(axis=0)
        out = knot_chain_values(kn, s_pp, d, inv2)
        out += [blk * inv2 for blk in border]
        iu = np.triu_indices(M)
        out.extend([G[iu] * inv2] * (FIELD_DIM if self.kernel == "se" else 1))
        if c_knot is not None:
            out += constant_field_values(c_knot, c_w, N, inv2)
        return np.concatenate([np.ravel(v) for v in out])
