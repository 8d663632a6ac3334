"""Trajectory as dead reckoning plus a drift correction at knots.

The positions of all N samples are

    p_i = q_i + (1 - a_i) c_{j(i)} + a_i c_{j(i)+1},

with q the dead-reckoned positions (the odometry integrated from the anchor), c (K, d) the
correction at K knots (one every ``every`` samples, plus the last sample) and a_i the
sample's fraction of the way between its two knots. With ``every = 1`` this is the paper's
formulation (one free position per sample), only shifted by q.

Between two knots the correction changes linearly, so the odometry residual of every step in
that interval is the same, (c_{j+1} - c_j) / k_j + b for k_j steps and per-step bias b, and
their sum of squares collapses to one residual per interval:

    0.5 |c_{j+1} - c_j + k_j b|^2 / (k_j sigma_o^2).

Several sessions stacked in one sample axis (``starts``, casmag.solver.multisession) each get their
own chain: the first and last sample of every session are knots, no sample lies between a
session's last knot and the next session's first, and the odometry cost skips that
interval and uses the session's own bias b_s.

This is the MAP problem restricted to piecewise-linear drift corrections. It keeps the
odometry within an interval as measured (its noise there is not corrected: about
sigma_o sqrt(k) / 2 at the middle of an interval), and it shrinks the pose block and the
dense pose-weight border of the reduced-rank map's Hessian from N d to K d rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla


@dataclass(frozen=True)
class Knots:
    """Knot placement for ``n`` samples: samples 0, every, 2 every, ... and n - 1; with
    several sessions (``starts``: first sample of each), the same within every session."""

    n: int
    every: int = 1
    starts: tuple[int, ...] = (0,)

    def __post_init__(self) -> None:
        if self.n < 2 or self.every < 1:
            raise ValueError(f"need n >= 2 and every >= 1, got n={self.n}, every={self.every}")
        if self.starts[0] != 0 or any(b - a < 2 for a, b in self.bounds):
            raise ValueError(f"sessions must start at 0 and hold >= 2 samples, got {self.starts}")

    @property
    def bounds(self) -> list[tuple[int, int]]:
        """(first, end) sample range of each session."""
        return list(zip(self.starts, [*self.starts[1:], self.n], strict=True))

    @cached_property
    def samples(self) -> np.ndarray:
        """(K,) sample index of each knot."""
        parts = []
        for a, b in self.bounds:
            idx = np.arange(a, b, self.every)
            parts.append(idx if idx[-1] == b - 1 else np.append(idx, b - 1))
        return np.concatenate(parts)

    @cached_property
    def session_of_interval(self) -> np.ndarray:
        """(K - 1,) session of each knot interval, -1 for the gap between two sessions."""
        s = self.samples
        session = np.searchsorted(np.asarray(self.starts), s[:-1], side="right") - 1
        gap = np.isin(s[1:], np.asarray(self.starts))
        return np.where(gap, -1, session)

    @property
    def count(self) -> int:
        return int(self.samples.size)

    @cached_property
    def steps(self) -> np.ndarray:
        """(K - 1,) number of odometry steps between consecutive knots."""
        return np.diff(self.samples)

    @cached_property
    def left(self) -> np.ndarray:
        """(n,) index of the knot at or before each sample (at most K - 2)."""
        j = np.searchsorted(self.samples, np.arange(self.n), side="right") - 1
        return np.minimum(j, self.count - 2)

    @cached_property
    def alpha(self) -> np.ndarray:
        """(n,) fraction of the way from the left knot to the right one."""
        j = self.left
        s = self.samples
        return (np.arange(self.n) - s[j]) / (s[j + 1] - s[j])

    @cached_property
    def matrix(self) -> sps.csr_matrix:
        """(n, K) interpolation matrix A, p = q + A c."""
        rows = np.repeat(np.arange(self.n), 2)
        cols = np.column_stack([self.left, self.left + 1]).ravel()
        vals = np.column_stack([1.0 - self.alpha, self.alpha]).ravel()
        A = sps.csr_matrix((vals, (rows, cols)), shape=(self.n, self.count))
        A.eliminate_zeros()
        return A

    def casadi_matrix(self) -> ca.DM:
        A = self.matrix.tocsc()
        A.sort_indices()
        sp = ca.Sparsity(self.n, self.count, A.indptr.astype(np.int64).tolist(), A.indices.tolist())
        return ca.DM(sp, A.data)

    def positions(self, dead_reckoning: np.ndarray, correction: np.ndarray) -> np.ndarray:
        """(n, d) positions from the dead reckoning (n, d) and knot corrections (K, d)."""
        return dead_reckoning + self.matrix @ correction

    def fit(self, dead_reckoning: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """(K, d) knot corrections whose positions are closest (least squares) to the given
        ones; exact at the knots when every sample is a knot."""
        A = self.matrix.tocsc()
        return np.column_stack(
            [
                spla.lsqr(A, positions[:, a] - dead_reckoning[:, a], atol=1e-12, btol=1e-12)[0]
                for a in range(positions.shape[1])
            ]
        )

    def odometry_cost(self, correction: ca.MX, bias: ca.MX, sigma_o: ca.MX) -> ca.MX:
        """0.5 sum_j |c_{j+1} - c_j + k_j b_s(j)|^2 / (k_j sigma_o^2) on (K, d) corrections,
        with bias (S, d), one row per session (the gap between sessions has no term)."""
        session = self.session_of_interval
        j = np.flatnonzero(session >= 0)
        k = ca.DM(self.steps[j].astype(float).reshape(-1, 1))
        if len(self.starts) == 1:
            K = self.count
            d_corr = correction[1:K, :] - correction[0 : K - 1, :]
            drift = ca.mtimes(k, bias)
        else:
            d_corr = correction[(j + 1).tolist(), :] - correction[j.tolist(), :]
            E = np.zeros((j.size, len(self.starts)))
            E[np.arange(j.size), session[j]] = self.steps[j]
            drift = ca.mtimes(ca.DM(E), bias)
        resid = (d_corr + drift) / ca.repmat(ca.sqrt(k), 1, correction.shape[1])
        return 0.5 * ca.sumsqr(resid) / sigma_o**2
