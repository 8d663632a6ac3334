"""Warm starts from partial solves: the growing-prefix strategy.

A long recording's dead reckoning drifts by many lengthscales, and GP-SLAM converges only
from starts within about a lengthscale of the truth (paper Table 5; measured on a 6 m x 6 m
walk: 4,000 samples with 0.8 m of final drift converge, 16,000 with 3.5 m would need a map
box three times the room). The growing strategy solves the first ``first_samples`` samples,
then prefixes ``growth`` times longer, up to the whole recording. Each stage

- removes the odometry bias estimated so far from the increments, so the remaining drift of
  the new samples is what the bias estimate left, not the raw bias;
- starts from the previous stage's trajectory, continued by the bias-corrected odometry
  (shifted to join it), with the map fitted there;
- fits the reduced-rank map's box around that start, so the basis covers the room, not the
  drift.

The final stage is the full MAP problem on all samples; earlier stages only supply its
initial guess, so each stops after ``stage_max_iter`` iterations at most. A stage that fails
otherwise is reported with IPOPT's status and ends the solve.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from casmag.config import Problem
from casmag.nlp import NLP, Solution
from casmag.simulate import Dataset
from casmag.translational import Structure, solve_translational


@dataclass(frozen=True)
class Stage:
    """One partial solve: samples used, IPOPT's outcome, the bias estimate it left."""

    samples: int
    status: str
    success: bool
    iterations: int
    solve_seconds: float
    build_seconds: float
    bias: list[float] | None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def stage_lengths(n: int, first: int, growth: float) -> list[int]:
    """Prefix lengths first, first * growth, ... ending with n (the last stage is at least
    ``growth`` / 2 times the one before, so no stage is a sliver)."""
    sizes = []
    k = float(first)
    while k * np.sqrt(growth) < n:
        sizes.append(int(k))
        k *= growth
    return [*sizes, n]


def continued(previous: np.ndarray, dead_reckoning: np.ndarray) -> np.ndarray:
    """(n, d) positions: ``previous`` (m, d) for the first m samples, then the dead
    reckoning shifted so that it continues from the last previous position."""
    m = previous.shape[0]
    shift = previous[-1] - dead_reckoning[m - 1]
    return np.vstack([previous, dead_reckoning[m:] + shift])


def solve_growing(
    problem: Problem, data: Dataset, progress: Any = None
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure, Dataset, list[Stage]]:
    """Solve with growing prefixes. Returns the final stage's solution, NLP,
    hyperparameters, field and structure as :func:`casmag.translational.solve_translational` does
    (``sol.x["bias"]`` is the total per-step bias), the data set the final stage solved
    (increments with the earlier stages' bias removed) and the stages."""
    ws = problem.spec.solver.warm_start
    bias_total = np.zeros(data.dim)
    positions: np.ndarray | None = None
    stages: list[Stage] = []
    estimate_bias = problem.spec.model.odometry.estimate_bias
    lengths = stage_lengths(data.n_samples, ws.first_samples, ws.growth)
    stage_problem = problem.with_overrides([f"solver.max_iter={ws.stage_max_iter}"])
    for n in lengths:
        last = n == lengths[-1]
        part = data.prefix(n).debiased(bias_total)
        start = None if positions is None else continued(positions, part.dead_reckoning())
        sol, nlp, hyper, field, structure = solve_translational(
            problem if last else stage_problem, part, progress, start
        )
        bias = sol.x.get("bias")
        if estimate_bias and bias is not None:
            bias_total = bias_total + np.ravel(bias)
        stages.append(
            Stage(
                samples=n,
                status=sol.status,
                success=sol.success,
                iterations=sol.iterations,
                solve_seconds=sol.solve_seconds,
                build_seconds=nlp.build_seconds,
                bias=[float(v) for v in bias_total] if estimate_bias else None,
            )
        )
        if not (sol.success or (not last and sol.status == "Maximum_Iterations_Exceeded")):
            break
        positions = sol.x["P"]
    if estimate_bias:
        sol.x["bias"] = bias_total.reshape(1, -1)
    return sol, nlp, hyper, field, structure, part, stages
