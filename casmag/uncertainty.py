"""Posterior uncertainty of the positions: the Laplace approximation at the MAP.

Around the MAP estimate x*, the posterior is approximated by N(x*, H^-1), where H is the
Hessian of the objective (the negative log-posterior) at x* (:meth:`casmag.nlp.NLP.hessian`:
IPOPT's Hessian, with the Gauss-Newton term for the reduced-rank magnetometer block). The
positions are linear in the knot corrections, p_k = q_k + sum_j A_kj c_j (casmag.knots), so

    cov(p_k) = sum_{j, j'} A_kj A_kj' cov(c_j, c_j'),

with cov(c) the knot block of H^-1: every other unknown (map, bias, estimated
hyperparameters) is marginalised, not conditioned on. Hyperparameters held fixed are taken as
known, so their uncertainty is not in the covariance.

The NEES (normalised estimation error squared) e_k^T cov(p_k)^-1 e_k, e_k = p_k - p_true,
has expected value d (the position dimension) when the covariance is honest: a mean NEES well
above d means over-confidence, well below d under-confidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from casmag.knots import Knots
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

    def summary(self, P_est: np.ndarray, P_true: np.ndarray | None) -> dict[str, float | None]:
        """Mean 1-sigma radius, and against truth the mean and median NEES with the expected
        value d and the fraction of samples inside the 95 % ellipse."""
        d = self.cov.shape[1]
        out: dict[str, float | None] = {
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
            )
        return out


class NotPositiveDefinite(ValueError):
    """The Hessian at the solution is not positive definite (no Laplace approximation)."""


def position_uncertainty(
    nlp: NLP, sol: Solution, params: dict, knots: Knots, dim: int, sigma_o: float = 0.0
) -> PositionUncertainty:
    """Laplace covariances of the positions at the solution ``sol`` of ``nlp``.

    The Hessian is factored densely (the unknowns are the knots, the bias, the map weights
    and estimated hyperparameters: a few thousand at most with knots), then solved for the
    knot columns only. Between knots the odometry random walk (per-step standard deviation
    sigma_o) adds its Brownian-bridge variance sigma_o^2 s (k - s) / k per axis, s steps
    after a knot of an interval of k steps: the knot model leaves that part of the odometry
    noise out of the unknowns. Raises NotPositiveDefinite when the factorisation fails.
    (The Hessian does not depend on the bias value, in which the odometry block is
    quadratic, so the total bias a growing or sliding solve leaves in ``sol.x`` is harmless.)
    """
    x = {k: v for k, v in sol.x.items() if k in nlp.x_layout.entries}
    H = nlp.hessian(x, params).toarray()
    entry = nlp.x_layout.entries["C"]
    K = knots.count
    cols = entry.offset + np.arange(K * dim)  # column-major (K, d): axis a at a*K + j
    try:
        factor = sla.cho_factor(H, lower=True, check_finite=True)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise NotPositiveDefinite(
            f"Hessian at the solution is not positive definite ({exc})"
        ) from None
    E = np.zeros((H.shape[0], cols.size))
    E[cols, np.arange(cols.size)] = 1.0
    cov_c = sla.cho_solve(factor, E)[cols, :]  # (K d, K d)
    A = knots.matrix  # sparse (N, K)
    N = knots.n
    cov = np.empty((N, dim, dim))
    for a in range(dim):
        for b in range(dim):
            block = cov_c[a * K : (a + 1) * K, b * K : (b + 1) * K]
            cov[:, a, b] = _row_quadratic(A, block)
    s_in = np.arange(N) - knots.samples[knots.left]
    k_in = knots.samples[knots.left + 1] - knots.samples[knots.left]
    bridge = sigma_o**2 * s_in * (k_in - s_in) / k_in
    cov += bridge[:, None, None] * np.eye(dim)
    return PositionUncertainty(0.5 * (cov + np.swapaxes(cov, 1, 2)))


def _row_quadratic(A, B: np.ndarray) -> np.ndarray:
    """(N,) diag(A B A^T) for a sparse or dense A (N, K) and dense B (K, K)."""
    AB = A @ B
    if hasattr(A, "multiply"):
        return np.asarray(A.multiply(AB).sum(axis=1)).ravel()
    return np.sum(np.asarray(A) * AB, axis=1)
