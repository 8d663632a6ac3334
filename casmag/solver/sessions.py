"""What several sessions of one field share, whatever their motion model: the order they
are added in (:func:`revisit_order`) and each session's errors in a result
(:func:`session_errors`). The translational sessions are solved by
casmag.solver.multisession, the staged models' (planar) by casmag.solver.staged.solve_sessions."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from casmag.result.metrics import rmse_and_max
from casmag.solver.uncertainty import PositionUncertainty


def revisit_fraction(P: np.ndarray, radius: float, min_gap: int) -> float:
    """Fraction of samples with another sample within ``radius`` that is more than
    ``min_gap`` samples away in time: how often a path returns to where it has been."""
    tree = cKDTree(P)
    hits = 0
    for i, near in enumerate(tree.query_ball_point(P, radius)):
        hits += any(abs(j - i) > min_gap for j in near)
    return hits / P.shape[0]


def revisit_order(paths: Sequence[np.ndarray], lengthscale: float) -> list[int]:
    """The order several sessions are added in (one map, casmag.solver.multisession and
    casmag.solver.staged.solve_sessions): by decreasing revisit fraction of their
    dead-reckoned ``paths`` (radius l, more than the samples needed to travel 4 l apart),
    so that the first session alone already closes loops; ties keep the given order."""
    scores = []
    for P in paths:
        P = np.asarray(P, dtype=float)
        step = float(np.median(np.linalg.norm(np.diff(P, axis=0), axis=1))) or 1.0
        gap = int(np.ceil(4.0 * lengthscale / step))
        scores.append(revisit_fraction(P, lengthscale, gap))
    return sorted(range(len(paths)), key=lambda i: -scores[i])


def session_errors(
    bounds: Sequence[tuple[int, int]],
    result: Any,
    names: Sequence[str],
    P_true: np.ndarray | None,
    biases: Sequence[np.ndarray] | None = None,
    biases_true: Sequence[np.ndarray] | None = None,
) -> list[dict[str, Any]]:
    """Per-session rows of a stacked solve (``info["sessions"]``): first sample, samples,
    RMSE and max error before and after (with truth), the position uncertainty's summary
    (with a covariance), the estimated and true odometry bias of each session (``biases``:
    one array per session)."""
    arrays = result.arrays
    rows = []
    for s, (i, j) in enumerate(bounds):
        row: dict[str, Any] = {"name": names[s], "first_sample": int(i), "n_samples": int(j - i)}
        P_est = None if arrays.get("P_estimate") is None else arrays["P_estimate"][i:j]
        truth = None if P_true is None else P_true[i:j]
        if truth is not None:
            before = rmse_and_max(arrays["P_odometry"][i:j], truth)
            row["rmse_before"], row["max_before"] = before
            if result.success:
                row["rmse_after"], row["max_after"] = rmse_and_max(P_est, truth)
        cov = arrays.get("P_cov")
        if cov is not None:
            row["uncertainty"] = PositionUncertainty(cov[i:j]).summary(P_est, truth)
            plain = arrays.get("P_cov_uninflated")
            if plain is not None:  # the Laplace covariance before the inflation
                row["uncertainty_uninflated"] = PositionUncertainty(plain[i:j]).summary(
                    P_est, truth
                )
        row["odometry_bias"] = None if biases is None else [float(v) for v in np.ravel(biases[s])]
        row["odometry_bias_true"] = (
            None if biases_true is None else [float(v) for v in np.ravel(biases_true[s])]
        )
        rows.append(row)
    return rows
