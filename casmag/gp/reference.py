"""The exact (dense) GP prior on the field at the sample points (paper Eq. 6).

With the field m at the N sample points as unknowns, the prior block of the MAP objective is

    0.5 m^T K(P, theta)^-1 m  [+ 0.5 log|K(P, theta)| when hyperparameters are estimated],

with K built from the kernel at the estimated positions P. The quadratic form uses a
differentiable sparse LDL solve on MX, so CasADi differentiates it to any order. The NLPs no
longer use this graph (its Hessian costs O(N^3) virtual-machine operations per evaluation):
they use the numpy blocks of casmag.model.exact, and this form is their test reference.
"""

from __future__ import annotations

import math

import casadi as ca

from casmag.gp.kernels import FIELD_DIM, Kernel


class ExactGPPrior:
    """Builds K(P, sigma_f, l) once as an SX function and adds the prior blocks.

    kernel: the covariance; n: number of samples; dim: position dimension (2 or 3);
    jitter: added to the diagonal, relative to the prior variance k(0).
    """

    def __init__(self, kernel: Kernel, n: int, dim: int, jitter: float = 1e-6, linsol: str = "ldl"):
        self.kernel, self.n, self.dim, self.linsol = kernel, n, dim, linsol
        P = ca.SX.sym("P", n, dim)
        ell = ca.SX.sym("lengthscale")
        # Unit-magnitude correlation matrix C(P, l), K = sigma_f^2 C; factoring sigma_f out keeps
        # det(C) representable for the log-determinant.
        C = kernel.matrix(P, P, 1.0, ell)
        variance = kernel.matrix(ca.SX.zeros(1, dim), ca.SX.zeros(1, dim), 1.0, ell)[0, 0]
        C = C + jitter * variance * ca.SX.eye(C.shape[0])
        self._C = ca.Function("gp_correlation", [P, ell], [C])
        self._variance = ca.Function("gp_variance", [ell], [variance])
        self.block = logdet_block_size(jitter, C.shape[0])

    def correlation(self, P: ca.MX, lengthscale: ca.MX) -> ca.MX:
        return self._C(P, lengthscale)

    def quadratic(self, P: ca.MX, M: ca.MX, sigma_f: ca.MX, lengthscale: ca.MX) -> ca.MX:
        """m^T K^-1 m for the (N, 3) field M at positions P (N, dim)."""
        C = self.correlation(P, lengthscale)
        if self.kernel.output_dim == 1:
            # Same covariance for each component: sum_c m_c^T C^-1 m_c.
            return ca.sum1(ca.sum2(M * ca.solve(C, M, self.linsol))) / sigma_f**2
        m = ca.vec(M)  # component-major, matching the kernel's block order
        return ca.dot(m, ca.solve(C, m, self.linsol)) / sigma_f**2

    def log_det(self, P: ca.MX, sigma_f: ca.MX, lengthscale: ca.MX) -> ca.MX:
        """log|K| of the full 3N x 3N field covariance."""
        C = self.correlation(P, lengthscale)
        copies = FIELD_DIM if self.kernel.output_dim == 1 else 1
        n_total = self.n * FIELD_DIM
        # The kernels have a constant diagonal k(0): log|C| = rows log k(0) + log|C / k(0)|.
        v = self._variance(lengthscale)
        scaled = C.shape[0] * ca.log(v) + block_log_det(C / v, self.block)
        return n_total * 2 * ca.log(sigma_f) + copies * scaled


#: Smallest determinant a diagonal block of the factorisation may reach (log): well above
#: the log of the smallest normal double, -708.
_LOG_DET_FLOOR = -600.0


def logdet_block_size(jitter: float, n: int) -> int:
    """Block size of :func:`block_log_det` for an n x n matrix with unit diagonal plus
    ``jitter``: its eigenvalues, and those of every Schur complement, are at least the
    jitter, so the determinant of a b x b block is at least jitter^b; b is the largest size
    that keeps jitter^b above exp(_LOG_DET_FLOOR) (jitter below machine epsilon counts as
    machine epsilon). The diagonal of a Schur complement is at most 1 + jitter, so no block
    overflows."""
    floor = max(jitter, 2.0**-52)
    if floor >= 1.0:  # eigenvalues at least 1: no block can underflow
        return n
    return max(1, min(n, int(_LOG_DET_FLOOR / math.log(floor))))


def block_log_det(A: ca.MX, block: int) -> ca.MX:
    """log|A| of a symmetric positive definite A by a block LDL^T: the leading block B's
    log det plus that of the Schur complement D - E^T B^-1 E, recursively. Built from
    ``det`` of blocks and the differentiable ``solve``, so CasADi differentiates it to any
    order."""
    total = 0
    S = A
    while S.shape[0] > block:
        B, E, D = S[:block, :block], S[:block, block:], S[block:, block:]
        total = total + ca.log(ca.det(B))
        S = D - ca.mtimes(E.T, ca.solve(B, E, "ldl"))
    return total + ca.log(ca.det(S))
