"""What several sessions of one field share, whatever their motion model: the order they
are added in (:func:`revisit_order`), recordings stacked end to end (:class:`Stacked`,
:func:`require_first_poses`) and each session's errors in a result (:func:`session_errors`).
The translational sessions are solved by casmag.solver.multisession, the staged models'
(planar, pose) by casmag.solver.staged.solve_sessions."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from casmag.errors import DataError
from casmag.result.metrics import rmse_and_max
from casmag.solver.uncertainty import PositionUncertainty


def check_starts(starts: Sequence[int], n: int) -> tuple[int, ...]:
    """The first sample of each session of n stacked samples, checked: the first at 0,
    each session at least 2 samples (ValueError)."""
    out = tuple(int(a) for a in starts)
    ends = [*out[1:], n]
    if not out or out[0] != 0 or any(e - a < 2 for a, e in zip(out, ends, strict=True)):
        raise ValueError(f"starts: sessions start at 0 and hold >= 2 samples each, got {out}")
    return out


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


@dataclass
class Stacked:
    """Recordings of one motion input stacked end to end in a given order: increments ``U``
    (N-1, k) with a no-motion row ``gap`` before each later session (not read by the
    models), magnetometer ``Y``, one time axis ``t`` (each session shifted to start one
    median sample period after the previous one ended), ``starts`` and ``names``."""

    U: np.ndarray
    Y: np.ndarray
    t: np.ndarray
    starts: tuple[int, ...]
    names: list[str]

    @classmethod
    def of(cls, recs: Sequence[Any], gap: Sequence[float]) -> Stacked:
        row = np.asarray(gap, dtype=float).reshape(1, -1)
        U = np.vstack([u for r in recs for u in (r.increments, row)][:-1])
        starts = tuple(int(a) for a in np.cumsum([0] + [r.n_samples for r in recs[:-1]]))
        times, offset = [], 0.0
        for r in recs:
            times.append(r.t - r.t[0] + offset)
            offset = times[-1][-1] + float(np.median(np.diff(r.t)))
        names = [Path(r.path).stem for r in recs]
        return cls(U, np.vstack([r.Y for r in recs]), np.concatenate(times), starts, names)


def require_first_poses(recs: Sequence[Any], motion: str, needs: str) -> None:
    """Every recording of several sessions of one map is of ``motion`` and has the truth
    columns its known first pose is read from (``needs``: which, for the message;
    DataError naming the recording)."""
    for rec in recs:
        if rec.motion != motion:
            raise DataError(f"{rec.path}: motion input is {rec.motion!r}, expected {motion!r}")
        heading = rec.yaw_true if motion == "planar" else rec.q_true
        if rec.P_true is None or heading is None:
            raise DataError(
                f"{rec.path}: several sessions need each one's first position and heading in "
                f"the common frame: truth columns ({needs}) are missing"
            )
