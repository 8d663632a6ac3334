"""The translational GP-SLAM MAP problem (paper Section 3.1, Eq. 3 and 5-8) as one NLP.

Unknowns: positions P (N, d), the field M (N, 3) at the samples, optionally a per-step
odometry bias b (1, d) and the log-hyperparameters log sigma_f, log l, log sigma_m.
Named cost blocks (negative log-densities):

- ``odometry``: 0.5 sum_k |(p_{k+1} - p_k - (u_k - b)) / sigma_o|^2
- ``magnetometer``: 0.5 sum_k |(y_k - m_k) / sigma_m|^2 (Eq. 3 with R = I)
  [+ 3 N log sigma_m when sigma_m is estimated]
- ``gp_prior``: 0.5 m^T K(P)^-1 m (Eq. 6)
- ``gp_logdet``: 0.5 log|K(P)| (Eq. 6), when sigma_f or l is estimated
- ``anchor``: 0.5 |(p_0 - a) / sigma_a|^2
- ``bias_prior``: 0.5 |b / sigma_b|^2, when a bias prior is set

Data and fixed settings are NLP parameters, so one build serves every seed and every value
of a fixed hyperparameter; the build is cached by the problem's structure.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import casadi as ca
import numpy as np

from casmag.config import Problem, SolverSpec
from casmag.gp import ExactGPPrior
from casmag.kernels import FIELD_DIM, get_kernel
from casmag.motion import TranslationalOdometry
from casmag.nlp import NLP, NLPBuilder, Solution
from casmag.simulate import Dataset

HYPERPARAMETERS = ("sigma_f", "lengthscale", "sigma_m")


@dataclass(frozen=True)
class Structure:
    """Everything that changes the symbolic problem (and so needs a new build)."""

    n: int
    dim: int
    kernel: str
    estimate: tuple[str, ...]
    estimate_bias: bool
    bias_prior: bool
    jitter: float
    logdet: bool
    solver: str  # SolverSpec as JSON (hashable)

    @classmethod
    def of(cls, problem: Problem, data: Dataset) -> Structure:
        m = problem.spec.model
        return cls(
            n=data.n_samples,
            dim=data.dim,
            kernel=problem.assumed_kernel,
            estimate=tuple(sorted(m.estimate)),
            estimate_bias=m.odometry.estimate_bias,
            bias_prior=m.odometry.bias_prior_sigma is not None,
            jitter=m.gp.jitter,
            logdet=bool({"sigma_f", "lengthscale"} & set(m.estimate))
            if m.gp.logdet is None
            else m.gp.logdet,
            solver=problem.spec.solver.model_dump_json(),
        )


def _hyper(builder: NLPBuilder, name: str, estimated: bool) -> ca.MX:
    """A positive hyperparameter: exp of a variable when estimated, else a parameter."""
    if estimated:
        return ca.exp(builder.variable(f"log_{name}", (1, 1)))
    return builder.parameter(name, (1, 1))


def build_translational(s: Structure) -> NLP:
    """Build the translational GP-SLAM NLP for a structure (use :func:`cached_nlp`)."""
    b = NLPBuilder()
    P = b.variable("P", (s.n, s.dim))
    M = b.variable("M", (s.n, FIELD_DIM))
    bias = b.variable("bias", (1, s.dim)) if s.estimate_bias else ca.MX.zeros(1, s.dim)
    sigma_f, ell, sigma_m = (_hyper(b, h, h in s.estimate) for h in HYPERPARAMETERS)

    U = b.parameter("U", (s.n - 1, s.dim))
    Y = b.parameter("Y", (s.n, FIELD_DIM))
    anchor = b.parameter("anchor", (1, s.dim))
    sigma_o = b.parameter("sigma_o", (1, 1))
    sigma_a = b.parameter("sigma_anchor", (1, 1))

    b.cost("odometry", TranslationalOdometry(s.dim).cost(P, U, bias, sigma_o))
    b.cost("magnetometer", 0.5 * ca.sumsqr((Y - M) / sigma_m))
    if "sigma_m" in s.estimate:
        b.cost("magnetometer", s.n * FIELD_DIM * ca.log(sigma_m))
    prior = ExactGPPrior(get_kernel(s.kernel), s.n, s.dim, s.jitter)
    b.cost("gp_prior", 0.5 * prior.quadratic(P, M, sigma_f, ell))
    if s.logdet:
        b.cost("gp_logdet", 0.5 * prior.log_det(P, sigma_f, ell))
    b.cost("anchor", 0.5 * ca.sumsqr((P[0, :] - anchor) / sigma_a))
    if s.bias_prior:
        sigma_b = b.parameter("sigma_bias", (1, 1))
        b.cost("bias_prior", 0.5 * ca.sumsqr(bias / sigma_b))
    return b.build(SolverSpec.model_validate_json(s.solver), name="casmag_translational")


@lru_cache(maxsize=8)
def cached_nlp(structure: Structure) -> NLP:
    """The built NLP for a structure, built once per process."""
    return build_translational(structure)


def parameters_and_guess(
    problem: Problem, data: Dataset, s: Structure
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Parameter values and the initial guess (dead reckoning, measured field, zero bias,
    hyperparameters at their assumed values)."""
    m = problem.spec.model
    hyper = {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_m": problem.assumed_sigma_m,
    }
    params: dict[str, Any] = {
        "U": data.U,
        "Y": data.Y,
        "anchor": data.anchor.reshape(1, -1),
        "sigma_o": problem.assumed_sigma_odometry,
        "sigma_anchor": m.anchor.sigma,
    }
    if s.bias_prior:
        params["sigma_bias"] = m.odometry.bias_prior_sigma
    x0: dict[str, Any] = {"P": data.dead_reckoning(), "M": data.Y}
    if s.estimate_bias:
        x0["bias"] = np.zeros((1, s.dim))
    for h, value in hyper.items():
        if h in s.estimate:
            x0[f"log_{h}"] = np.log(value)
        else:
            params[h] = value
    return params, x0


def solve_translational(problem: Problem, data: Dataset) -> tuple[Solution, NLP, dict[str, float]]:
    """Solve the problem on a data set. Returns the solution, the NLP and the final
    hyperparameters (estimated or fixed)."""
    s = Structure.of(problem, data)
    nlp = cached_nlp(s)
    params, x0 = parameters_and_guess(problem, data, s)
    sol = nlp.solve(params, x0)
    hyper = {
        h: float(np.exp(sol.x[f"log_{h}"][0, 0])) if h in s.estimate else float(params[h])
        for h in HYPERPARAMETERS
    }
    return sol, nlp, hyper
