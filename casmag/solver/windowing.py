"""The pieces of the warm starts shared by every motion model (the strategies themselves are
casmag.solver.staged's; the windows of a localisation against a saved map are
casmag.solver.localize's): prefix lengths and the growing loop (:func:`grow`), window
lengths and starts, the lengthscale schedule, and the Laplace block of a window's unknowns.

Growing prefixes: a long recording's dead reckoning drifts by many lengthscales, and
GP-SLAM converges only from starts within about a lengthscale of the truth (paper Table 5;
measured on a 6 m x 6 m walk: 4,000 samples with 0.8 m of final drift converge, 16,000
with 3.5 m would need a map box three times the room). The growing strategy solves the
first ``first_samples`` samples, then prefixes ``growth`` times longer, up to the whole
recording. Each stage

- removes the odometry bias estimated so far from the increments, so the remaining drift of
  the new samples is what the bias estimate left, not the raw bias;
- starts from the previous stage's trajectory, continued by the bias-corrected odometry
  (shifted to join it), with the map fitted there;
- fits the reduced-rank map's box around that start, so the basis covers the room, not the
  drift.

The final stage is the full MAP problem on all samples; earlier stages only supply its
initial guess, so each stops after ``stage_max_iter`` iterations at most. A stage that fails
otherwise is reported with IPOPT's status and ends the solve (:func:`continues`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from casmag.nlp import NLP, Solution

ACCEPTED = ("Solve_Succeeded", "Solved_To_Acceptable_Level", "Maximum_Iterations_Exceeded")
"""IPOPT outcomes after which a window or stage hands its point on (an early stage need not
converge: it only starts the next)."""

AUTO_WINDOW = (12, 40)
"""Range [samples] that ``window: auto`` is clamped to (:func:`window_size`). Measured on
the translational model with the Laplace bias prior: on the Table 5 spiral (l = 0.4 m,
8 steps per lengthscale) at 3.4 l of drift and 1 mm noise, 12-sample windows reached the
basin in 20 of 20 seeds (at most 105 iterations in all), 14 in 19 of 20 (at most 229), 16
in 5 of 8 and 20 in 1 of 5: a longer window drifts further before the map pulls it back.
On problems/paper/base.yaml (l = 0.1 m, 2 steps per lengthscale) 8-sample windows took
198-234 iterations and 10-sample ones missed the basin in one of three seeds, 12-16 did
neither: hence the floor of 12. The ceiling of 40 is not measured."""


def window_size(ws: Any, steps: np.ndarray, lengthscale: float, n: int) -> tuple[int, int]:
    """(window, overlap) in samples for the warm start ``ws`` (a WarmStartSpec) on ``n``
    samples whose odometry steps have the lengths ``steps`` [m]. ``window: auto``: the
    samples the dead reckoning needs to travel ``window_lengthscales`` assumed lengthscales
    at its median step, round(k l / median |u|) + 1, clamped to :data:`AUTO_WINDOW` (and to
    the recording); ``overlap: auto``: half the window. Raises ValueError, naming the key,
    when the overlap does not fit the window the recording allows."""
    k = ws.window_samples
    if k is None:
        step = float(np.median(steps)) if np.size(steps) else 0.0
        travel = ws.window_lengthscales * lengthscale
        k = AUTO_WINDOW[1] if step <= 0 else round(travel / step) + 1
        k = int(np.clip(k, *AUTO_WINDOW))
    k = min(k, n)
    overlap = max(1, k // 2) if ws.overlap == "auto" else ws.overlap_samples
    if overlap is None or not 1 <= overlap < k:
        raise ValueError(
            f"solver.warm_start.overlap: at least 1 sample and shorter than the window "
            f"(got {overlap} of {k} samples)"
        )
    return k, overlap


def window_starts(n: int, window: int, overlap: int) -> list[int]:
    """First samples of the windows: 0, window - overlap, ..., and n - window (the last
    window ends at the last sample). One window [0] when n <= window."""
    if n <= window:
        return [0]
    step = window - overlap
    starts = list(range(0, n - window, step))
    return [*starts, n - window]


def bias_covariance(
    nlp: NLP,
    sol: Solution,
    params: dict[str, Any],
    fixed: tuple[str, ...] = (),
    names: tuple[str, ...] = ("bias",),
) -> np.ndarray:
    """Laplace covariance of a window's bias at its solution: the block of the variables
    ``names`` (stacked in that order, each column-major) of the inverse Gauss-Newton Hessian
    of the window objective (so it is the marginal, with the trajectory and the map
    integrated out, and it includes the window's own bias prior); variables in ``fixed`` are
    held known (conditioned on, not integrated out)."""
    entries = [nlp.x_layout.entries[name] for name in names]
    idx = np.concatenate([e.offset + np.arange(e.size) for e in entries])
    return laplace_block(nlp, sol, params, idx, fixed)


def laplace_block(
    nlp: NLP,
    sol: Solution,
    params: dict[str, Any],
    idx: np.ndarray,
    fixed: tuple[str, ...] = (),
) -> np.ndarray:
    """The block ``idx`` (indices into the NLP's x vector, none of them in ``fixed``) of the
    inverse Gauss-Newton Hessian of the objective at a solution: the Laplace marginal
    covariance of those unknowns (:func:`bias_covariance`)."""
    import scipy.sparse.linalg as spla

    H = nlp.hessian(sol.x, params)
    if fixed:  # held variables are known: condition on them (drop their rows and columns)
        held = np.zeros(H.shape[0], dtype=bool)
        for name in fixed:
            f = nlp.x_layout.entries[name]
            held[f.offset : f.offset + f.size] = True
        keep = np.flatnonzero(~held)
        H = H[keep][:, keep]
        where = np.full(held.size, -1)
        where[keep] = np.arange(keep.size)
    else:
        where = np.arange(H.shape[0])
    idx = where[np.asarray(idx, dtype=np.int64)]
    E = np.zeros((H.shape[0], idx.size))
    E[idx, np.arange(idx.size)] = 1.0
    X = spla.splu(H.tocsc()).solve(E)
    cov = X[idx, :]
    return 0.5 * (cov + cov.T)


@dataclass(frozen=True)
class Stage:
    """One partial solve: samples used, IPOPT's outcome, the bias estimate it left; a
    result's ``stages`` record (``name`` prefix: a growing prefix, the last the full
    problem)."""

    samples: int
    status: str
    success: bool
    iterations: int
    solve_seconds: float
    build_seconds: float
    bias: list[float] | None
    name: str = "prefix"

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, **{k: v for k, v in self.__dict__.items() if k != "name"}}


def stage_lengths(n: int, first: int, growth: float) -> list[int]:
    """Prefix lengths first, first * growth, ... ending with n (the last stage is at least
    ``growth`` / 2 times the one before, so no stage is a sliver)."""
    sizes = []
    k = float(first)
    while k * np.sqrt(growth) < n:
        sizes.append(int(k))
        k *= growth
    return [*sizes, n]


def lengthscale_schedule(lengthscale: float, start: float, stages: int) -> list[float]:
    """Geometric schedule from ``start`` times ``lengthscale`` down to ``lengthscale`` (the
    coarse-to-fine strategy's, casmag.solver.staged)."""
    return [float(v) for v in lengthscale * start ** np.linspace(1.0, 0.0, stages)]


State = TypeVar("State")


def continues(sol: Solution, last: bool) -> bool:
    """Whether growing prefixes go on after a solve: it succeeded, or it stopped at the
    iteration limit before the last stage (an earlier stage only starts the next); any other
    failure ends the growth."""
    return sol.success or (not last and sol.status == "Maximum_Iterations_Exceeded")


def grow(
    sizes: list[int], solve_stage: Callable[[int, State | None, bool], tuple[Solution, State]]
) -> list[tuple[int, Solution, State]]:
    """The growing-prefix loop of every motion model: ``solve_stage(k, previous, last)``
    solves the first k samples (keyframes) from the previous stage's state (None for the
    first) and returns its solution and state. Returns (k, solution, state) of each stage
    solved, the last being the full problem unless a stage ended the growth
    (:func:`continues`)."""
    out: list[tuple[int, Solution, State]] = []
    state: State | None = None
    for k in sizes:
        last = k == sizes[-1]
        sol, state = solve_stage(k, state, last)
        out.append((k, sol, state))
        if not continues(sol, last):
            break
    return out


def continued(previous: np.ndarray, dead_reckoning: np.ndarray) -> np.ndarray:
    """(n, d) positions: ``previous`` (m, d) for the first m samples, then the dead
    reckoning shifted so that it continues from the last previous position."""
    m = previous.shape[0]
    shift = previous[-1] - dead_reckoning[m - 1]
    return np.vstack([previous, dead_reckoning[m:] + shift])
