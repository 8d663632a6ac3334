"""Motion models: the odometry cost block of the MAP problem.

Translational odometry (paper Eq. 1 reduced to translation): the increment u_k measured
between samples k and k+1 obeys

    p_{k+1} = p_k + u_k - b + e_k,   e_k ~ N(0, sigma_o^2 I),

with b an optional constant per-step bias that is estimated (the role the paper's gyroscope
and accelerometer biases play for the IMU). The residual of one step is a small SX function
mapped over all steps.
"""

from __future__ import annotations

import casadi as ca
import numpy as np


class TranslationalOdometry:
    """Per-step residual r_k = (p_{k+1} - p_k - (u_k - b)) / sigma_o in ``dim`` dimensions."""

    def __init__(self, dim: int = 2):
        self.dim = dim
        p, p_next, u, b = (ca.SX.sym(n, dim) for n in ("p", "p_next", "u", "b"))
        sigma = ca.SX.sym("sigma_o")
        self._residual = ca.Function(
            "odometry_residual", [p, p_next, u, b, sigma], [(p_next - p - (u - b)) / sigma]
        )

    def cost(self, P: ca.MX, U: ca.MX, b: ca.MX, sigma_o: ca.MX) -> ca.MX:
        """0.5 sum_k |r_k|^2 for positions P (N, dim), increments U (N-1, dim), bias b (1, dim)."""
        n_steps = U.shape[0]
        R = self._residual.map(n_steps)(
            P[:-1, :].T, P[1:, :].T, U.T, ca.repmat(b.T, 1, n_steps), sigma_o
        )
        return 0.5 * ca.sumsqr(R)

    @staticmethod
    def integrate(anchor: np.ndarray, U: np.ndarray, bias: np.ndarray | None = None) -> np.ndarray:
        """(N, dim) dead-reckoned positions from the anchor, optionally removing a bias."""
        steps = U if bias is None else U - np.asarray(bias)
        return np.vstack([anchor, anchor + np.cumsum(steps, axis=0)])
