"""Magnetic loop closures: pairs of samples at the same place, found by the field's signature
along the path, before any map is solved.

Dead reckoning drifts; where a path returns to ground it crossed before, the drift since
the first visit can exceed the map's lengthscale, and then GP-SLAM started from the dead
reckoning follows a long valley to a wrong optimum (measured on the handwriting scenario:
IMU-only paths 0.13-0.15 m from the truth against a lengthscale of about 0.1 m). The field
itself says where the path returns: the world-frame field along a stretch of path is a
signature of the place. :func:`magnetic_closures` compares every stretch with every earlier
one that does not overlap it and keeps the pairs whose signatures agree far better than
the rest (a distinctiveness test against the median and against the second-best place),
in runs along both visits (a returning path matches over a stretch, not at one sample).

The pairs then pull the two visits together in the dead reckoning's adjustment
(``closure`` block, casmag.model.builder.LoopClosures), which makes GP-SLAM's start
(casmag.solver.imu.closure_start); GP-SLAM itself does not carry them. A wrong pair still
costs more than time: it gives a wrong start, from which GP-SLAM can settle in a wrong
optimum (measured with forced wrong pairs, problems/imu/README.md, step 3).

Measured (2026-11-26) on the IMU-only adjustments of the IMU scenarios (problems/imu), with
the lengthscale set to the scenarios' (0.1 m for handwriting and rectangle, 0.12 m spiral,
0.2 m square table, 0.3 m outdoor); a pair is right when its true distance is below a third
of the lengthscale: handwriting seeds 1, 2, 3, 4, 9, 11, 12, 15, 17, 20: 85-89 pairs each,
at most 13 mm apart in truth (the IMU-only paths put them 6-16 cm apart), none wrong;
rectangle seeds 1, 2, 3, 17: 158-160 each, none wrong; spiral (which passes between its own
turns, never over them), square table and outdoor (fields that vary little) seeds 1, 2, 3,
17: none. Among the stretches whose best match was wrong, the best signature distance was
at least 0.07 of the median (rectangle), against 0.05 accepted. Not yet measured on real
recordings: on the handheld ARKit ``library`` dead reckoning (weak field, planar) with a
0.3 m lengthscale, most accepted pairs were metres apart in truth, so the finder serves the
IMU model only for now.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Half-width of the compared stretch, in lengthscales of travel (at the median speed).
WINDOW_LENGTHSCALES = 1.5
#: A stretch's best match is accepted when its mean squared field difference is below this
#: fraction of the median over all non-overlapping pairs of stretches...
MATCH_COST = 0.05
#: ...and below this fraction of the best match elsewhere (more than a half-width away).
MATCH_RATIO = 0.5
#: Stretches must move at least this many lengthscales (a device at rest matches anywhere
#: its field happens to agree).
MIN_TRAVEL_LENGTHSCALES = 1.0
#: Most keyframes compared: the signature matrix is K x K.
MAX_KEYFRAMES = 4000


@dataclass
class Closures:
    """Closure pairs (i, j), i < j keyframe indices at the same place, with what was used
    to find them (``info``: window, thresholds, counts; for result.json)."""

    pairs: np.ndarray  # (m, 2) int
    info: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.pairs.shape[0])


def _runs(first: np.ndarray, second: np.ndarray, min_run: int) -> np.ndarray:
    """Mask of the pairs (sorted by ``second``) that belong to a run of at least ``min_run``
    consecutive ``second`` indices whose ``first`` indices advance by 0-2 each step (both
    visits moving along the same stretch)."""
    keep = np.zeros(first.size, dtype=bool)
    start = 0
    for k in range(1, first.size + 1):
        broken = (
            k == first.size
            or second[k] != second[k - 1] + 1
            or not 0 <= first[k] - first[k - 1] <= 2
        )
        if broken:
            if k - start >= min_run:
                keep[start:k] = True
            start = k
    return keep


def magnetic_closures(
    P: np.ndarray,
    F: np.ndarray,
    lengthscale: float,
) -> Closures:
    """Closure pairs of a path P (K, 3 or 2) with the world-frame field F (K, 3) measured
    along it (the magnetometer rotated by the path's orientations), for a map of the given
    lengthscale. See the module's documentation for the test; pairs are the centres of
    matched stretches."""
    P = np.asarray(P, dtype=float)
    F = np.asarray(F, dtype=float)
    K = P.shape[0]
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    moving = steps[steps > 1e-3 * lengthscale]
    info: dict[str, Any] = {
        "window_lengthscales": WINDOW_LENGTHSCALES,
        "match_cost": MATCH_COST,
        "match_ratio": MATCH_RATIO,
    }
    none = Closures(np.zeros((0, 2), dtype=int), info)
    if K > MAX_KEYFRAMES or moving.size == 0:
        info["skipped"] = "too many keyframes" if K > MAX_KEYFRAMES else "no motion"
        return none
    h = int(np.ceil(WINDOW_LENGTHSCALES * lengthscale / np.median(moving)))
    h = max(2, min(h, K // 8))
    info["half_window"] = h
    n = K - 2 * h
    if n < 4 * h + 3:
        info["skipped"] = "path too short for two stretches"
        return none
    # Mean squared field difference of the stretches centred at i + h and j + h.
    D = np.sum((F[:, None, :] - F[None, :, :]) ** 2, axis=-1)
    S = np.zeros((n, n))
    for s in range(2 * h + 1):
        S += D[s : s + n, s : s + n]
    S /= 2 * h + 1
    travel = np.concatenate([[0.0], np.cumsum(steps)])
    moves = (travel[2 * h :] - travel[: K - 2 * h]) > MIN_TRAVEL_LENGTHSCALES * lengthscale
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    valid = (jj - ii > 4 * h + 1) & moves[:, None] & moves[None, :]
    if not valid.any():
        info["skipped"] = "no two moving stretches apart in time"
        return none
    S = np.where(valid, S, np.inf)
    median = float(np.median(S[valid]))
    info["median_cost"] = median
    best_i = np.argmin(S, axis=0)
    best = S[best_i, np.arange(n)]
    far = np.abs(np.arange(n)[:, None] - best_i[None, :]) > h
    second = np.min(np.where(far, S, np.inf), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(best) & (best < MATCH_COST * median) & (best < MATCH_RATIO * second)
    j = np.flatnonzero(ok)
    i = best_i[j]
    keep = _runs(i, j, h)
    pairs = np.stack([i[keep] + h, j[keep] + h], axis=1).astype(int)
    info.update(candidates=int(ok.sum()), pairs=int(pairs.shape[0]))
    return Closures(pairs, info)
