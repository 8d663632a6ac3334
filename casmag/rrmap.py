"""The reduced-rank (Hilbert-space) GP field map inside the MAP problem.

The field is a linear model in basis-function weights (``casmag.reduced_rank``):

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

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import scipy.sparse as sps

from casmag.kernels import FIELD_DIM
from casmag.reduced_rank import HilbertBasis, default_margin, default_num_basis, domain_for

# Frequencies up to OMEGA_FACTOR / l. The covariance error of 4 / l (reduced_rank's default) is
# small, but positions depend on field gradients, which weight high frequencies by omega^2:
# on the base case, 4 / l (M = 110) put positions 1.8 mm from the exact GP's; 5 / l (M = 170)
# within 0.4 mm over seeds 1-5.
OMEGA_FACTOR = 5.0


@dataclass(frozen=True)
class MapLayout:
    """Where the map's unknowns and the data sit in the NLP's x and p vectors.

    P: offset of positions (N, d), column-major; W: offset of weights (SE: (M, 3)
    column-major, curl-free: (M,)); c: offset of the constant field or None; sigma_m: offset
    of sigma_m in p.
    """

    n_x: int
    n_p: int
    P: int
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


class GaussNewtonHessian(ca.Callback):
    """Gauss-Newton Hessian of 0.5 sum_k |(y_k - m(p_k)) / sigma_m|^2 (upper triangle).

    Inputs (x, p, lam_f, lam_g) as IPOPT's ``hess_lag``; the output is *not* scaled by
    lam_f (the caller multiplies). The sparsity pattern is fixed at construction; each call
    fills the values with vectorised numpy: O(N M) for the border, one BLAS product O(N M^2)
    for the weight block.
    """

    def __init__(
        self,
        name: str,
        basis: HilbertBasis,
        kernel: str,
        n: int,
        dim: int,
        layout: MapLayout,
        n_g: int = 0,
    ):
        ca.Callback.__init__(self)
        self.basis, self.kernel, self.n, self.dim, self.lay, self.n_g = (
            basis,
            kernel,
            n,
            dim,
            layout,
            n_g,
        )
        M = basis.num_basis
        self.n_w = M * FIELD_DIM if kernel == "se" else M
        self._pattern()
        self.construct(name, {})

    # ------------------------------------------------------------------ pattern
    def _pattern(self) -> None:
        N, d, M, lay = self.n, self.dim, self.basis.num_basis, self.lay
        k = np.arange(N)
        rows, cols = [], []
        pidx = [lay.P + a * N + k for a in range(d)]  # (N,) each

        def add(r: np.ndarray, c: np.ndarray) -> None:
            r, c = np.broadcast_arrays(np.asarray(r), np.asarray(c))
            rows.append(np.minimum(r, c).ravel())
            cols.append(np.maximum(r, c).ravel())

        # pose-pose (per sample, upper triangle of d x d)
        for a in range(d):
            for b in range(a, d):
                add(pidx[a], pidx[b])
        # pose-weight border
        widx = lay.W + np.arange(self.n_w)
        for a in range(d):
            add(pidx[a][:, None], widx[None, :])
        # weight-weight
        if self.kernel == "se":
            j = np.arange(M)
            iu = np.triu_indices(M)
            for c in range(FIELD_DIM):
                add(lay.W + c * M + j[iu[0]], lay.W + c * M + j[iu[1]])
        else:
            iu = np.triu_indices(M)
            add(lay.W + iu[0], lay.W + iu[1])
        if lay.c is not None:
            for b in range(FIELD_DIM):
                for a in range(d):
                    add(pidx[a], lay.c + b)
                add(widx, lay.c + b)
                add(np.array([lay.c + b]), np.array([lay.c + b]))
        self._rows = np.concatenate(rows)
        self._cols = np.concatenate(cols)
        nnz = self._rows.size
        A = sps.csc_matrix(
            (np.arange(1, nnz + 1, dtype=np.float64), (self._rows, self._cols)),
            shape=(lay.n_x, lay.n_x),
        )
        A.sort_indices()
        if A.nnz != nnz:
            raise RuntimeError("duplicate entries in the Gauss-Newton pattern")
        self._perm = A.data.astype(np.int64) - 1
        self._sp = ca.Sparsity(
            lay.n_x,
            lay.n_x,
            A.indptr.astype(np.int64).tolist(),
            A.indices.astype(np.int64).tolist(),
        )

    @property
    def nnz(self) -> int:
        return int(self._rows.size)

    # ------------------------------------------------------------------ callback API
    def get_n_in(self) -> int:
        return 4

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ["x", "p", "lam_f", "lam_g"][i]

    def get_name_out(self, i: int) -> str:
        return "triu_hess_gamma_x_x"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense([self.lay.n_x, self.lay.n_p, 1, self.n_g][i], 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return self._sp

    def eval(self, args: list[Any]) -> list[Any]:
        x = np.asarray(args[0]).ravel()
        p = np.asarray(args[1]).ravel()
        return [ca.DM(self._sp, self.values(x, p)[self._perm])]

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The Gauss-Newton entries in the order of the pattern's triplets."""
        N, d, M, lay = self.n, self.dim, self.basis.num_basis, self.lay
        P = x[lay.P : lay.P + N * d].reshape(N, d, order="F")
        wts = x[lay.W : lay.W + self.n_w]
        sigma = float(p[lay.sigma_m])
        _, Aw, D = field_and_jacobians(self.basis, self.kernel, P, wts)
        inv2 = 1.0 / sigma**2
        out = []
        # pose-pose: D^T D / sigma^2
        for a in range(d):
            for b in range(a, d):
                out.append(np.einsum("kc,kc->k", D[:, :, a], D[:, :, b]) * inv2)
        # pose-weight: D^T A / sigma^2
        for a in range(d):
            if self.kernel == "se":
                blk = D[:, :, a][:, :, None] * Aw[0][:, None, :]  # (N, 3, M), column c*M + j
                out.append(blk.reshape(N, -1) * inv2)
            else:
                acc = sum(D[:, b, a][:, None] * Aw[b] for b in range(FIELD_DIM))
                out.append(acc * inv2)
        # weight-weight: A^T A / sigma^2 (BLAS)
        iu = np.triu_indices(M)
        if self.kernel == "se":
            G = (Aw[0].T @ Aw[0]) * inv2
            out.extend([G[iu]] * FIELD_DIM)
        else:
            G = sum(g.T @ g for g in Aw) * inv2
            out.append(G[iu])
        # constant field c: J_c = -I / sigma per sample
        if lay.c is not None:
            for b in range(FIELD_DIM):
                for a in range(d):
                    out.append(D[:, b, a] * inv2)
                if self.kernel == "se":
                    v = np.zeros(self.n_w)
                    v[b * M : (b + 1) * M] = Aw[0].sum(axis=0) * inv2
                else:
                    v = Aw[b].sum(axis=0) * inv2
                out.append(v)
                out.append(np.array([N * inv2]))
        return np.concatenate([np.ravel(v) for v in out])
