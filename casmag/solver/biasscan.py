"""A start for the odometry bias from the field's evidence, without the truth.

A constant per-step odometry bias b turns the dead reckoning into a path that drifts
further from the truth with every step. Where the drift at the end is several lengthscales,
the MAP from the dead reckoning, and from growing prefixes, can end in a basin of its own:
on the real robot sequences at 1.5 m of drift (lengthscale 0.27 m) both ended at 0.63-0.65 m
on sequences 2 and 3, where a start from the truth reaches a lower MAP cost at 0.02-0.03 m
(README, Measured: real field).

The bias is a few numbers, and the magnetometer says which of them is right: with the right
b removed, the readings taken where the path returns agree, and a GP map explains them with
little noise. So for every b on a grid the dead reckoning with b removed is scored by the
negative log marginal likelihood of the readings there (turned into the world frame by its
heading or attitude) under a reduced-rank GP map (the SE kernel on each component, the
readings' mean taken out as the constant field, the problem's sigma_f and sigma_m), and the
start is the b with the lowest. The grid is the model's: the horizontal components of the
translational per-step bias, ``P(b)_k = DR_k - k b`` (:func:`drift_grid`; a vertical bias
is not scanned), or the heading-rate bias of the planar and pose models
(:func:`heading_grid`). Each model's ``start(k, bias)`` makes the candidate path
(casmag.solver.staged.StagedModel), so :func:`evidence_start` is one function for all.

The scan's map has SCAN_LENGTHSCALES times the problem's lengthscale, which smooths the
score between grid points and keeps the basis small, and it keeps one sample per
SAMPLE_LENGTHSCALES of its lengthscale along the path. Measured on the ten real robot
recordings (sequences 1-5, 0.5 and 1.5 m of drift, sigma_m 2 uT; the dead reckoning
corrected by the scanned bias against the truth): with these constants the correction
brought every one closer, 0.03-0.17 m against 0.28-0.87 m, in 1.5-4.0 s each. Other
settings missed some: every sample on a fixed grid (+-2 m of end drift, 21 x 21) at 1.85
times the lengthscale found 9 of 10 (on sequence 4 at 0.5 m the lowest score lay on the
grid's edge, 1.2 m from the truth), and at 3 times it 4 of 10; one sample per 0.2 scan
lengthscales found 8 of 10.

The score is a guide, not a verdict, so the scanned bias is one more start of the MAP,
solved as one batch, and kept only when its MAP cost is the lowest
(casmag.solver.multisession.drift_start for translational recordings, :func:`heading_start`
and casmag.solver.staged.solve_staged for planar and pose ones). With it, single real
robot recordings reached 1/4 of the drift on 6 of 10 (3 without), and robot sequence 5 as
pose odometry reached the truth's optimum (0.94 -> 0.236 m) where the dead reckoning's
growing prefixes ended at 1.18 m (README, Measured: real field; Pose odometry).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from casmag.gp.kernels import get_kernel
from casmag.gp.reduced_rank import Domain, HilbertBasis, default_num_basis

#: The scan map's lengthscale in lengthscales of the problem's (module docstring).
SCAN_LENGTHSCALES = 2.0

#: The drift the scan reaches at the end of the path, as a fraction of the dead-reckoned
#: path length: 0.08 (a 1.5 m drift over the robot's 30 m paths is 0.05).
REACH_FRACTION = 0.08

#: The scan keeps one sample per this many scan lengthscales of path (the scan's map does
#: not resolve finer, and each candidate costs N m^2 flops).
SAMPLE_LENGTHSCALES = 0.1

#: Grid spacing of the end drift, in scan lengthscales.
SPACING_LENGTHSCALES = 0.5

#: At most this many candidates along each axis; a longer reach widens the spacing.
MAX_PER_AXIS = 31

#: No scan when its map would need more basis functions than this (a building-scale
#: area): each candidate costs N x MAX_BASIS^2 flops. The robot recordings need 500-700.
MAX_BASIS = 1500

#: The largest heading turn over the recording a heading-rate candidate makes [rad].
MAX_TURN = float(np.pi)

#: At most this many heading-rate candidates.
MAX_TURNS = 361

#: A candidate's path and its readings in the world frame: positions (N, 2 or 3), (N, 3).
PathOf = Callable[[Any], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Grid:
    """Candidate start biases (``biases``, row-major over ``shape``; the centre one is no
    bias), the end drift of the outermost ``reach`` [m] and of neighbours ``spacing`` [m]
    apart (for a heading-rate bias: a path's length times half the heading it turns)."""

    biases: list[Any]
    shape: tuple[int, ...]
    reach: float
    spacing: float


def _arc(P: np.ndarray) -> np.ndarray:
    """The distance along the path at each sample [m]."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])


def _half(path: float, lengthscale: float) -> tuple[int, float, float]:
    """Candidates on each side of no bias, the reach and the spacing [m] of a path's grid."""
    reach = REACH_FRACTION * path
    ell = SCAN_LENGTHSCALES * float(lengthscale)
    half = min(max(1, int(np.ceil(reach / (SPACING_LENGTHSCALES * ell)))), (MAX_PER_AXIS - 1) // 2)
    return half, reach, reach / half


def drift_grid(dead_reckoning: np.ndarray, lengthscale: float) -> Grid:
    """Per-step odometry biases (d,) [m per step] of the translational model: their
    horizontal components on a square grid whose end drift reaches REACH_FRACTION of the
    path, SPACING_LENGTHSCALES scan lengthscales apart (at most MAX_PER_AXIS per axis)."""
    DR = np.asarray(dead_reckoning, dtype=float)
    n, d = DR.shape
    half, reach, spacing = _half(float(_arc(DR)[-1]), lengthscale)
    steps = np.arange(-half, half + 1) * spacing / max(n - 1, 1)
    biases = []
    for bx in steps:
        for by in steps:
            b = np.zeros(d)
            b[:2] = bx, by
            biases.append(b)
    return Grid(biases, (steps.size, steps.size), reach, spacing)


def heading_grid(dead_reckoning: np.ndarray, duration: float, lengthscale: float) -> Grid:
    """Heading-rate biases [rad/s] of the planar and pose models: the heading turned by up
    to +-MAX_TURN over ``duration`` [s], in steps that move the path's farthest point (r
    from its first position, horizontally) by SPACING_LENGTHSCALES scan lengthscales (at
    most MAX_TURNS candidates). The reach is that point's move at the largest turn (r
    MAX_TURN). A constant rate bias turns the heading far: robot sequence 5 as pose
    odometry (0.5 m of drift) turns 1.54 rad over its 166 s (0.0093 rad/s); `casmag slam`'s
    scan chose 0.0091 rad/s from 51 candidates in 0.5 s, and a scan of 57 candidates
    outside it brought the dead reckoning from 0.94 to 0.038 m RMSE."""
    P = np.asarray(dead_reckoning, dtype=float)[:, :2]
    r = float(np.linalg.norm(P - P[0], axis=1).max())
    step = SPACING_LENGTHSCALES * SCAN_LENGTHSCALES * float(lengthscale)
    half = min(max(1, int(np.ceil(MAX_TURN * r / step))), (MAX_TURNS - 1) // 2)
    turns = np.linspace(-MAX_TURN, MAX_TURN, 2 * half + 1)
    rates = [float(v) for v in turns / max(duration, 1e-12)]
    return Grid(rates, (turns.size,), r * MAX_TURN, r * MAX_TURN / half)


@dataclass(frozen=True)
class BiasScan:
    """The scan's chosen start ``bias`` (a Grid's), its score and the score of no bias
    (negative log marginal likelihoods, nats), the grid it chose from (``shape``, ``reach``
    and ``spacing`` [m]), whether the choice lies on the grid's edge, the scan map's
    lengthscale, the samples it kept and the seconds taken."""

    bias: Any
    score: float
    score_zero: float
    shape: tuple[int, ...]
    reach: float
    spacing: float
    at_edge: bool
    lengthscale: float
    samples: int
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        b = self.bias
        return {
            "bias": float(b) if np.ndim(b) == 0 else [float(v) for v in np.ravel(b)],
            "score": self.score,
            "score_zero": self.score_zero,
            "shape": list(self.shape),
            "reach_m": self.reach,
            "spacing_m": self.spacing,
            "at_edge": self.at_edge,
            "lengthscale": self.lengthscale,
            "samples": self.samples,
            "seconds": self.seconds,
        }


def evidence_score(
    basis: HilbertBasis, variances: np.ndarray, P: np.ndarray, Yc: np.ndarray, sigma_m: float
) -> float:
    """-log p(Yc | P) of readings Yc (N, c), their mean taken out, under the reduced-rank
    map (basis, prior ``variances`` of its weights, the same map on each of the c
    components) plus white noise sigma_m (Woodbury and the matrix determinant lemma)."""
    Phi = basis.phi(P)
    A = Phi.T @ Phi
    A[np.diag_indices_from(A)] += sigma_m**2 / variances
    try:
        L = scipy.linalg.cholesky(A, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return np.inf
    z = scipy.linalg.solve_triangular(L, Phi.T @ Yc, lower=True, check_finite=False)
    quad = (float(np.sum(Yc**2)) - float(np.sum(z**2))) / sigma_m**2
    (n, c), m = Yc.shape, variances.size
    # log|Phi V Phi^T + s^2 I| = log|A| + log|V| + (n - m) log s^2, A = Phi^T Phi + s^2 V^-1
    logdet = 2.0 * np.log(np.diag(L)).sum() + np.log(variances).sum() + (n - m) * np.log(sigma_m**2)
    return 0.5 * quad + 0.5 * c * (float(logdet) + n * np.log(2.0 * np.pi))


def scan_bias(
    grid: Grid, path_of: PathOf, sigma_f: float, lengthscale: float, sigma_m: float
) -> BiasScan | None:
    """The grid's bias whose path (``path_of``: positions and world-frame readings) best
    explains the readings (module docstring). None when the scan's map would need more
    than MAX_BASIS basis functions, or the path does not move."""
    t0 = time.perf_counter()
    ell = SCAN_LENGTHSCALES * float(lengthscale)
    centre = len(grid.biases) // 2
    P0, _ = path_of(grid.biases[centre])
    arc = _arc(np.asarray(P0, dtype=float))
    if not arc[-1] > 0.0:  # the path does not move: no drift to scan
        return None
    keep = np.unique(np.searchsorted(arc, np.arange(0.0, arc[-1], SAMPLE_LENGTHSCALES * ell)))
    paths = []
    for b in grid.biases:
        P, Y = path_of(b)
        paths.append((np.asarray(P, dtype=float)[keep], np.asarray(Y, dtype=float)[keep]))
    every = np.vstack([P for P, _ in paths])
    dom = Domain.around(np.vstack([every.min(axis=0), every.max(axis=0)]), 3 * ell)
    if default_num_basis(dom, ell) > MAX_BASIS:
        return None
    basis = HilbertBasis(dom, lengthscale_for_default=ell)
    variances = np.asarray(basis.prior_variances("se", sigma_f, ell), dtype=float)
    scores = np.array(
        [evidence_score(basis, variances, P, Y - Y.mean(axis=0), sigma_m) for P, Y in paths]
    )
    best = int(np.argmin(scores))
    at = np.unravel_index(best, grid.shape)
    return BiasScan(
        bias=grid.biases[best],
        score=float(scores[best]),
        score_zero=float(scores[centre]),
        shape=grid.shape,
        reach=grid.reach,
        spacing=grid.spacing,
        at_edge=any(i in (0, size - 1) for i, size in zip(at, grid.shape, strict=True)),
        lengthscale=ell,
        samples=int(keep.size),
        seconds=time.perf_counter() - t0,
    )


def evidence_start(
    model: Any, grid: Grid, sigma_f: float, lengthscale: float, sigma_m: float, dim: int
) -> BiasScan | None:
    """:func:`scan_bias` over a staged model's starts (casmag.solver.staged.StagedModel:
    ``start(n, bias)`` the dead reckoning with the bias removed, ``world_readings(states)``
    the readings turned into the world frame by its heading or attitude), positions in the
    map's ``dim`` coordinates; None as there, or when the chosen bias does not explain the
    readings better than no bias by more than the BIC's price of the grid's dimensions
    (0.5 log(samples) nats each; then that start would be the dead reckoning's, and a solve
    from it would only cost time)."""

    def path_of(b: Any) -> tuple[np.ndarray, np.ndarray]:
        states = model.start(model.n, b)
        return np.asarray(states["P"])[:, :dim], model.world_readings(states)

    scan = scan_bias(grid, path_of, sigma_f, lengthscale, sigma_m)
    if scan is None or not np.any(scan.bias):
        return None
    price = 0.5 * len(grid.shape) * np.log(scan.samples)
    return scan if scan.score_zero - scan.score > price else None


def field_sigma(kernel: str, sigma_f: float, lengthscale: float) -> float:
    """The field's prior deviation per component under the kernel (sigma_f for SE, sigma_f
    / l for the curl-free kernel, whose sigma_f is its potential's)."""
    return float(np.sqrt(get_kernel(kernel).variance(sigma_f, lengthscale)))


def heading_start(
    model: Any,
    duration: float,
    kernel: str,
    hyper: tuple[float, float, float],
    skip: bool = False,
) -> BiasScan | None:
    """The heading-rate bias the field's evidence chooses (:func:`heading_grid` over the
    first ``duration`` [s]) for one more start of a planar or pose recording, ``hyper``
    (sigma_f, lengthscale, sigma_m) the map's, scored on the horizontal positions (a 3-D
    pose map's heights left out: the turn is about the vertical); None to ``skip`` (a
    recording located against a saved map, ``solver.warm_start.evidence`` false), for
    several sessions, and as :func:`evidence_start` says."""
    if len(model.session_starts) > 1 or skip:
        return None
    sigma_f, ell, sigma_m = (float(v) for v in hyper)
    grid = heading_grid(np.asarray(model.start(model.n, 0.0)["P"]), duration, ell)
    return evidence_start(model, grid, field_sigma(kernel, sigma_f, ell), ell, sigma_m, 2)
