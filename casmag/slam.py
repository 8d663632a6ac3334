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
from casmag.reduced_rank import Domain, HilbertBasis
from casmag.rrmap import GaussNewtonHessian, MapLayout, field_and_jacobians, make_basis
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
    form: str = "exact"
    basis: tuple | None = None  # reduced rank: (center, half_width, num_basis)
    constant_field: bool = False

    @classmethod
    def of(cls, problem: Problem, data: Dataset) -> Structure:
        m = problem.spec.model
        basis = None
        if m.gp.form == "reduced_rank":
            hb = make_basis(
                problem.assumed_kernel,
                data.dead_reckoning(),
                problem.assumed_lengthscale,
                m.gp.num_basis,
                m.gp.margin,
            )
            basis = (tuple(hb.domain.center), tuple(hb.domain.half_width), hb.num_basis)
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
            form=m.gp.form,
            basis=basis,
            constant_field=m.gp.sigma_lin is not None,
        )

    def hilbert_basis(self) -> HilbertBasis:
        return _hilbert_basis(self.basis)


@lru_cache(maxsize=8)
def _hilbert_basis(key: tuple) -> HilbertBasis:
    """The reduced-rank basis of a structure, built once per (center, half_width, M)."""
    center, half_width, num_basis = key
    return HilbertBasis(Domain(np.array(center), np.array(half_width)), num_basis)


def _hyper(builder: NLPBuilder, name: str, estimated: bool) -> ca.MX:
    """A positive hyperparameter: exp of a variable when estimated, else a parameter."""
    if estimated:
        return ca.exp(builder.variable(f"log_{name}", (1, 1)))
    return builder.parameter(name, (1, 1))


def build_translational(s: Structure) -> NLP:
    """Build the translational GP-SLAM NLP for a structure (use :func:`cached_nlp`)."""
    b = NLPBuilder()
    P = b.variable("P", (s.n, s.dim))
    bias = b.variable("bias", (1, s.dim)) if s.estimate_bias else ca.MX.zeros(1, s.dim)
    sigma_f, ell, sigma_m = (_hyper(b, h, h in s.estimate) for h in HYPERPARAMETERS)

    U = b.parameter("U", (s.n - 1, s.dim))
    Y = b.parameter("Y", (s.n, FIELD_DIM))
    anchor = b.parameter("anchor", (1, s.dim))
    sigma_o = b.parameter("sigma_o", (1, 1))
    sigma_a = b.parameter("sigma_anchor", (1, 1))

    b.cost("odometry", TranslationalOdometry(s.dim).cost(P, U, bias, sigma_o))
    if s.form == "reduced_rank":
        return _build_reduced_rank(b, s, P, bias, Y, anchor, sigma_f, ell, sigma_m, sigma_a)
    M = b.variable("M", (s.n, FIELD_DIM))
    b.cost("magnetometer", 0.5 * ca.sumsqr((Y - M) / sigma_m))
    prior = ExactGPPrior(get_kernel(s.kernel), s.n, s.dim, s.jitter)
    b.cost("gp_prior", 0.5 * prior.quadratic(P, M, sigma_f, ell))
    if s.logdet:
        b.cost("gp_logdet", 0.5 * prior.log_det(P, sigma_f, ell))
    b.cost("anchor", 0.5 * ca.sumsqr((P[0, :] - anchor) / sigma_a))
    if s.bias_prior:
        sigma_b = b.parameter("sigma_bias", (1, 1))
        b.cost("bias_prior", 0.5 * ca.sumsqr(bias / sigma_b))
    return b.build(SolverSpec.model_validate_json(s.solver), name="casmag_translational")


def _build_reduced_rank(
    b: NLPBuilder,
    s: Structure,
    P: ca.MX,
    bias: ca.MX,
    Y: ca.MX,
    anchor: ca.MX,
    sigma_f: ca.MX,
    ell: ca.MX,
    sigma_m: ca.MX,
    sigma_a: ca.MX,
) -> NLP:
    """Reduced-rank map: weights W (SE, (M, 3)) or w (curl-free, (M, 1)), optional constant
    field c; magnetometer residuals mapped over the samples with the weights broadcast."""
    basis = s.hilbert_basis()
    M = basis.num_basis
    W = b.variable("W", (M, FIELD_DIM) if s.kernel == "se" else (M, 1))
    c = b.variable("c", (FIELD_DIM, 1)) if s.constant_field else ca.MX.zeros(FIELD_DIM, 1)
    field = basis.field_sx(s.kernel, position_dim=s.dim)
    x, y, sig = ca.SX.sym("x", s.dim), ca.SX.sym("y", FIELD_DIM), ca.SX.sym("sigma_m")
    w_sx = ca.SX.sym("w", *W.shape)
    c_sx = ca.SX.sym("c", FIELD_DIM)
    resid = ca.Function("mag_residual", [x, y, w_sx, c_sx, sig], [(y - field(x, w_sx, c_sx)) / sig])
    E = resid.map(s.n, "serial")(P.T, Y.T, W, c, sigma_m)
    b.cost("magnetometer", 0.5 * ca.sumsqr(E))
    S = basis.prior_variances(s.kernel, sigma_f, ell)  # (M, 1)
    n_cols = W.shape[1]
    b.cost("gp_prior", 0.5 * ca.sum1(ca.sum2(W**2 / ca.repmat(S, 1, n_cols))))
    if {"sigma_f", "lengthscale"} & set(s.estimate):
        b.cost("gp_logdet", 0.5 * n_cols * ca.sum1(ca.log(S)))
    if s.constant_field:
        sigma_lin = b.parameter("sigma_lin", (1, 1))
        b.cost("constant_field_prior", 0.5 * ca.sumsqr(c / sigma_lin))
    b.cost("anchor", 0.5 * ca.sumsqr((P[0, :] - anchor) / sigma_a))
    if s.bias_prior:
        sigma_b = b.parameter("sigma_bias", (1, 1))
        b.cost("bias_prior", 0.5 * ca.sumsqr(bias / sigma_b))
    solver = SolverSpec.model_validate_json(s.solver)
    gn = None
    if solver.hessian in ("auto", "gauss-newton"):
        n_x, n_p = b.sizes
        layout = MapLayout(
            n_x=n_x,
            n_p=n_p,
            P=b.offset("P"),
            W=b.offset("W"),
            c=b.offset("c") if s.constant_field else None,
            sigma_m=b.offset("sigma_m", "p"),
        )
        gn = (
            "magnetometer",
            GaussNewtonHessian("mag_gauss_newton", basis, s.kernel, s.n, s.dim, layout),
        )
    return b.build(solver, name="casmag_translational_rr", gauss_newton=gn)


def initial_weights(
    s: Structure,
    P: np.ndarray,
    Y: np.ndarray,
    sigma_m: float,
    sigma_f: float,
    lengthscale: float,
    c0: np.ndarray,
) -> np.ndarray:
    """Ridge fit of the map weights to the data at the initial positions (the posterior mean
    of the weights given P): (A^T A / sigma_m^2 + diag(1 / S))^-1 A^T (y - c0) / sigma_m^2."""
    basis = s.hilbert_basis()
    S = basis.prior_variances(s.kernel, sigma_f, lengthscale)
    M = basis.num_basis
    zero = np.zeros(M * FIELD_DIM if s.kernel == "se" else M)
    _, A, _ = field_and_jacobians(basis, s.kernel, P, zero)
    R = Y - c0
    if s.kernel == "se":
        G = A[0].T @ A[0] / sigma_m**2 + np.diag(1.0 / S)
        return np.linalg.solve(G, A[0].T @ R / sigma_m**2)
    G = sum(a.T @ a for a in A) / sigma_m**2 + np.diag(1.0 / S)
    rhs = sum(A[q].T @ R[:, q] for q in range(FIELD_DIM)) / sigma_m**2
    return np.linalg.solve(G, rhs).reshape(-1, 1)


def field_estimate(s: Structure, sol: Solution) -> np.ndarray:
    """(N, 3) estimated field at the estimated positions."""
    if s.form != "reduced_rank":
        return sol.x["M"]
    basis = s.hilbert_basis()
    m, _, _ = field_and_jacobians(basis, s.kernel, sol.x["P"], sol.x["W"].ravel(order="F"))
    return m + (sol.x["c"].ravel() if s.constant_field else 0.0)


def field_on_grid(
    s: Structure, sol: Solution, hyper: dict[str, float], grid: np.ndarray, jitter: float
) -> np.ndarray:
    """(G, 3) estimated field at grid points (G, d): the reduced-rank map itself, or for the
    exact GP the posterior mean given the estimated field at the estimated positions,
    K(grid, P) K(P, P)^-1 m."""
    if s.form == "reduced_rank":
        basis = s.hilbert_basis()
        zero_c = np.zeros(FIELD_DIM)
        m, _, _ = field_and_jacobians(basis, s.kernel, grid, sol.x["W"].ravel(order="F"))
        return m + (sol.x["c"].ravel() if s.constant_field else zero_c)
    kernel = get_kernel(s.kernel)
    P, M = sol.x["P"], sol.x["M"]
    sf, ell = hyper["sigma_f"], hyper["lengthscale"]
    K = kernel.matrix(P, P, sf, ell)
    K = K + jitter * kernel.variance(sf, ell) * np.eye(K.shape[0])
    Ks = kernel.matrix(grid, P, sf, ell)
    if kernel.output_dim == 1:
        return Ks @ np.linalg.solve(K, M)
    mean = Ks @ np.linalg.solve(K, M.ravel(order="F"))
    return mean.reshape(FIELD_DIM, -1).T


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
    P0 = data.dead_reckoning()
    x0: dict[str, Any] = {"P": P0}
    if s.form == "reduced_rank":
        c0 = data.Y.mean(axis=0) if s.constant_field else np.zeros(FIELD_DIM)
        x0["W"] = initial_weights(
            s, P0, data.Y, hyper["sigma_m"], hyper["sigma_f"], hyper["lengthscale"], c0
        )
        if s.constant_field:
            x0["c"] = c0.reshape(-1, 1)
            params["sigma_lin"] = m.gp.sigma_lin
    else:
        x0["M"] = data.Y
    if s.estimate_bias:
        x0["bias"] = np.zeros((1, s.dim))
    for h, value in hyper.items():
        if h in s.estimate:
            x0[f"log_{h}"] = np.log(value)
        else:
            params[h] = value
    return params, x0


def solve_translational(
    problem: Problem, data: Dataset, progress: Any = None
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure]:
    """Solve the problem on a data set. Returns the solution, the NLP, the final
    hyperparameters (estimated or fixed), the (N, 3) field estimate at the samples and the
    problem's structure."""
    s = Structure.of(problem, data)
    nlp = cached_nlp(s)
    params, x0 = parameters_and_guess(problem, data, s)
    sol = nlp.solve(params, x0, progress=progress)
    hyper = {
        h: float(np.exp(sol.x[f"log_{h}"][0, 0])) if h in s.estimate else float(params[h])
        for h in HYPERPARAMETERS
    }
    return sol, nlp, hyper, field_estimate(s, sol), s
