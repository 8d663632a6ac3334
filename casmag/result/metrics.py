"""Trajectory error metrics. Positions in metres; no alignment is applied: the estimate is
compared with the truth in the frame fixed by the anchor, as in the paper's tables."""

from __future__ import annotations

import numpy as np


def position_errors(P_est: np.ndarray, P_true: np.ndarray) -> np.ndarray:
    """(N,) Euclidean position error [m] of each sample, without alignment."""
    P_est, P_true = np.asarray(P_est, dtype=float), np.asarray(P_true, dtype=float)
    if P_est.shape != P_true.shape:
        raise ValueError(f"shape mismatch: estimate {P_est.shape}, truth {P_true.shape}")
    return np.linalg.norm(P_est - P_true, axis=1)


def rmse_and_max(P_est: np.ndarray, P_true: np.ndarray) -> tuple[float, float]:
    """(RMSE, max error) of positions [m], without alignment."""
    e = position_errors(P_est, P_true)
    return float(np.sqrt(np.mean(e**2))), float(e.max())


def heading_rms_deg(psi_est: np.ndarray, psi_true: np.ndarray) -> float:
    """RMS heading error [deg], each difference wrapped to (-pi, pi]."""
    d = np.angle(np.exp(1j * (np.ravel(psi_est) - np.ravel(psi_true))))
    return float(np.degrees(np.sqrt(np.mean(d**2))))
