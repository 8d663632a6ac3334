"""The Laplace covariance's inflation for correlated magnetometer residuals
(casmag.solver.uncertainty: autocorrelation time, sandwich covariance with the long-run
variance)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2
from small_problems import tiny_walk

import casmag
from casmag import linalg
from casmag.data.simulate import simulate_problem
from casmag.model.translational import parameters
from casmag.solver import uncertainty
from casmag.solver.translational import solve_translational
from casmag.solver.uncertainty import (
    autocorrelation_time,
    magnetometer_correction,
    nees_consistency,
    position_uncertainty,
    residual_inflation,
    whitened_correction,
)

ROOT = Path(__file__).resolve().parents[2]


def _ar1(n: int, phi: float, sd: float, rng: np.random.Generator, cols: int = 3) -> np.ndarray:
    """AR(1) noise of marginal standard deviation sd: tau = (1 + phi) / (1 - phi)."""
    e = rng.normal(size=(n, cols)) * sd * np.sqrt(1.0 - phi**2)
    x = np.empty((n, cols))
    x[0] = rng.normal(size=cols) * sd
    for k in range(1, n):
        x[k] = phi * x[k - 1] + e[k]
    return x


def test_nees_range_covers_an_honest_covariance_with_smooth_errors():
    # Position errors that are N(0, I) at every sample but smooth along the path (AR(1),
    # tau 99): an honest unit covariance. The mean NEES of one trajectory scatters widely,
    # and the range from its correlation time must cover the expected 2 about 95 % of the
    # time, where the range that takes the samples as independent would not.
    rng = np.random.default_rng(11)
    covered, naive = 0, 0
    trials = 200
    for _ in range(trials):
        e = _ar1(1500, 0.98, 1.0, rng, 2)
        q = np.sum(e**2, axis=1)
        r = nees_consistency(q, 2)
        lo, hi = r["nees_interval_95"]
        covered += lo <= 2.0 <= hi
        assert r["nees_independent"] == pytest.approx(1500 / r["nees_tau"])
        n = q.size
        naive += chi2.ppf(0.025, 2 * n) / n <= np.mean(q) <= chi2.ppf(0.975, 2 * n) / n
    assert covered / trials >= 0.88, covered
    assert naive / trials <= 0.5, naive
    # White chi-squared values: tau about 1 and a narrow range around 2.
    q = rng.chisquare(2, size=4000)
    r = nees_consistency(q, 2)
    assert r["nees_tau"] < 1.5
    lo, hi = r["nees_interval_95"]
    assert lo < 2.0 < hi and hi - lo < 0.35


def test_autocorrelation_time_of_ar1_and_white_noise():
    rng = np.random.default_rng(0)
    for phi in (0.5, 0.8, 0.9):
        expected = (1 + phi) / (1 - phi)
        taus = [autocorrelation_time(_ar1(20_000, phi, 1.0, rng, 1)[:, 0]) for _ in range(3)]
        assert abs(np.mean(taus) / expected - 1.0) < 0.15, (phi, taus)
    white = [autocorrelation_time(rng.normal(size=5_000)) for _ in range(5)]
    assert 0.8 < np.mean(white) < 1.25, white
    assert autocorrelation_time(np.ones(10)) == 1.0
    assert autocorrelation_time(np.arange(3.0)) == 1.0


def test_residual_inflation_factors():
    rng = np.random.default_rng(1)
    R = np.vstack([_ar1(3000, 0.8, 2.0, rng), rng.normal(size=(2000, 3)) * 0.5])
    bounds = [(0, 3000), (3000, 5000)]
    inf = residual_inflation(R, bounds, sigma_m=1.0, method="long-run")
    assert inf.tau.shape == (2, 3)
    # Session 1: tau about 9 and variance 4 against sigma_m^2 = 1: lambda about 36 (the
    # estimate from 3,000 samples scatters: measured 31-55).
    assert np.all((inf.lam[0] > 20) & (inf.lam[0] < 70)), inf.lam
    # Session 2: white and below sigma_m: no inflation.
    assert np.all(inf.lam[1] == 1.0)
    corr = residual_inflation(R, bounds, sigma_m=1.0, method="correlation")
    np.testing.assert_allclose(corr.lam[0], corr.tau[0])
    f = inf.factors(5000)
    assert f.shape == (5000, 3) and np.all(f[:3000] == inf.lam[0]) and np.all(f[3000:] == 1)
    assert not residual_inflation(R, bounds, 1.0, "none").active
    with pytest.raises(ValueError):
        residual_inflation(R, bounds, 1.0, "bogus")


@pytest.mark.parametrize(
    "overrides",
    [
        [],
        ["model.gp.kernel=curl_free"],
        ["model.gp.sigma_lin=5.0"],
        ["model.gp.form=exact", "simulation.trajectory.samples=50"],
    ],
    ids=["rr-se", "rr-curl-free", "rr-constant-field", "exact"],
)
def test_magnetometer_correction_is_the_magnetometer_gauss_newton_block(overrides):
    """Weights 0 remove the magnetometer block (the Hessian at sigma_m -> infinity), weights
    1/2 halve it (the Hessian at sigma_m sqrt 2)."""
    prob = tiny_walk(overrides)
    data = simulate_problem(prob)
    sol, nlp, _, _, s = solve_translational(prob, data)
    assert sol.success
    params = parameters(prob, data, s)
    x = {k: v for k, v in sol.x.items() if k in nlp.x_layout.entries}
    H = nlp.hessian(x, params).toarray()
    sm = params["sigma_m"]
    n = data.n_samples
    zero = magnetometer_correction(nlp, sol, s, np.zeros((n, 3)), sm)
    H_inf = nlp.hessian(x, {**params, "sigma_m": 1e9}).toarray()
    scale = np.abs(H).max()
    assert np.abs(H + zero.toarray() - H_inf).max() < 1e-9 * scale
    half = magnetometer_correction(nlp, sol, s, np.full((n, 3), 0.5), sm)
    H_half = nlp.hessian(x, {**params, "sigma_m": sm * np.sqrt(2.0)}).toarray()
    assert np.abs(H + half.toarray() - H_half).max() < 1e-9 * scale
    assert abs(magnetometer_correction(nlp, sol, s, np.ones((n, 3)), sm)).max() == 0.0


def _walk(samples: int = 800):
    return casmag.load_problem(
        ROOT / "problems/bench/walk.yaml",
        [
            "seed=3",
            f"simulation.trajectory.samples={samples}",
            "simulation.trajectory.area=[2.0, 2.0]",
            "solver.warm_start.strategy=none",
        ],
    )


def test_no_inflation_on_white_noise():
    """White magnetometer noise: tau near 1, residuals below sigma_m, factor 1, the
    covariance is the plain Laplace one (NEES measured 1.74, expected 2)."""
    res = casmag.solve(_walk())
    u = res.uncertainty
    assert res.success and u["inflation"]["method"] == "long-run"
    assert np.all(np.asarray(u["inflation"]["factor"]) == 1.0)
    assert np.all(np.asarray(u["inflation"]["tau"]) < 1.5)
    assert u["nees_mean"] == pytest.approx(u["uninflated"]["nees_mean"])
    assert 0.5 * u["nees_expected"] <= u["nees_mean"] <= 2.0 * u["nees_expected"]
    np.testing.assert_array_equal(res.arrays["P_cov"], res.arrays["P_cov_uninflated"])


def test_inflation_makes_correlated_noise_honest():
    """AR(1) magnetometer noise (phi 0.9, tau 19) of the assumed marginal sigma_m: the plain
    Laplace covariance is over-confident (measured NEES 11.1, expected 2); the sandwich with
    the residuals' long-run variance is not (measured 2.2)."""
    prob = _walk()
    data = simulate_problem(prob)
    rng = np.random.default_rng(0)
    sd = prob.assumed_sigma_m
    data = dataclasses.replace(data, Y=data.M_true + _ar1(data.n_samples, 0.9, sd, rng))
    res = casmag.solve(prob, data)
    assert res.success
    u = res.uncertainty
    d = u["nees_expected"]
    plain = u["uninflated"]["nees_mean"]
    assert plain > 2.0 * d
    assert 0.5 * d <= u["nees_mean"] <= 2.0 * d
    assert abs(np.log(u["nees_mean"] / d)) < abs(np.log(plain / d))
    assert np.all(np.asarray(u["inflation"]["tau"]) > 5.0)
    assert u["sigma_mean"] > u["uninflated"]["sigma_mean"]
    assert res.verdict["checks"]["covariance_against_truth"]["passed"] is True
    none = casmag.solve(prob.with_overrides(["solver.uncertainty_inflation=none"]), data)
    assert "inflation" not in none.uncertainty
    assert none.uncertainty["nees_mean"] == pytest.approx(plain)


@pytest.mark.parametrize("overrides", [[], ["model.gp.form=tiled", "model.gp.kernel=curl_free"]])
def test_the_sparse_factor_gives_the_dense_covariance(overrides, monkeypatch):
    """Above DENSE_MAX_UNKNOWNS the Hessian is factored sparsely and solved only for the
    pairs of neighbouring knots, in chunks of knots and the next one: forced here on the
    tiny walk (reduced-rank box and tiled map), with chunks of three knots, it gives the
    dense path's covariance of every sample, plain and with a sandwich correction (the
    magnetometer information halved), to 1e-9 of its largest entry."""
    prob = tiny_walk(overrides)
    data = simulate_problem(prob)
    sol, nlp, _, _, s = solve_translational(prob, data)
    assert sol.success, sol.status
    params = parameters(prob, data, s)
    sigma_o = params["sigma_o"]
    if s.form == "tiled":
        x = nlp.x_layout.pack({k: v for k, v in sol.x.items() if k in nlp.x_layout.entries})
        _, J = nlp.keep[1].residual_jacobian(x, nlp.p_layout.pack(params))
        meat = whitened_correction(J, np.full((data.n_samples, 3), 2.0))
    else:
        meat = magnetometer_correction(
            nlp, sol, s, np.full((data.n_samples, 3), 2.0), params["sigma_m"]
        )
    n_x = nlp.x_layout.size
    monkeypatch.setattr(uncertainty, "SPARSE_CHUNK_BYTES", 8 * n_x * 2 * 4)  # 3 knots a chunk
    for m in (None, meat, meat.toarray()):
        dense = position_uncertainty(nlp, sol, params, s.knots, s.dim, sigma_o, meat=m)
        sparse = position_uncertainty(
            nlp, sol, params, s.knots, s.dim, sigma_o, meat=m, dense_max=0
        )
        scale = np.abs(dense.cov).max()
        assert np.abs(sparse.cov - dense.cov).max() < 1e-9 * scale
    assert np.all(np.linalg.eigvalsh(dense.cov) > 0)


def test_an_unobservable_bias_is_refused_by_both_factors():
    """Without a field (sigma_m 1e6) a free odometry bias is unobservable: the Hessian is
    singular to machine precision, and the dense factor (the positions ordered last) and
    the sparse one both say so instead of giving a covariance."""
    prob = tiny_walk(["model.magnetometer.sigma_m=1.0e6"])
    data = simulate_problem(prob)
    sol, nlp, _, _, s = solve_translational(prob, data)
    params = parameters(prob, data, s)
    for dense_max in (None, 0):
        with pytest.raises(uncertainty.NotPositiveDefinite, match="positive definite"):
            position_uncertainty(
                nlp, sol, params, s.knots, s.dim, params["sigma_o"], dense_max=dense_max
            )


def test_dense_product_of_a_sparse_correction(monkeypatch):
    """dense_product gives S @ Z for a sparse S expanded in slabs of rows (forced here to
    two rows a slab), for a sparse S below the fill it expands (a diagonal of 60, 1.7 %
    filled: the sparse product) and for a dense S."""
    import scipy.sparse as sp

    rng = np.random.default_rng(3)
    n = 9
    dense = rng.standard_normal((n, n))
    dense[np.abs(dense) < 0.5] = 0.0
    monkeypatch.setattr(linalg, "DENSE_SLAB_BYTES", 8 * n * 2)
    diagonal = sp.diags(rng.standard_normal(60)).tocsc()
    assert diagonal.nnz < linalg.DENSE_PRODUCT_FILL * 60 * 60
    for S in (sp.csr_matrix(dense), diagonal, dense):
        Z = rng.standard_normal((S.shape[1], 4))
        want = (S.toarray() if hasattr(S, "toarray") else S) @ Z
        np.testing.assert_allclose(linalg.dense_product(S, Z), want, rtol=1e-13)


def test_the_knot_factor_gives_the_inverse_blocks():
    """_KnotFactor (the dense Cholesky factor with the knot unknowns ordered last) gives
    the knot block of H^-1, the columns H^-1 E and E^T H^-1 C of a random positive
    definite H whose knot unknowns sit in its middle, as a plain inverse does."""
    import scipy.sparse as sp

    rng = np.random.default_rng(11)
    n, k, position = 23, 7, 5
    A = rng.standard_normal((n, n))
    H = A @ A.T + n * np.eye(n)
    C = rng.standard_normal((n, 2))
    inv = np.linalg.inv(H)
    cols = position + np.arange(k)
    factor = uncertainty._KnotFactor(sp.csc_matrix(H), k, position)
    np.testing.assert_allclose(factor.block, inv[np.ix_(cols, cols)], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(factor.columns(), inv[:, cols], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(factor.cross(C), inv[cols] @ C, rtol=1e-10, atol=1e-14)
    H[0, 0] = -1.0
    with pytest.raises(uncertainty.NotPositiveDefinite):
        uncertainty._KnotFactor(sp.csc_matrix(H), k, position)
    # singular to machine precision (rank n - 1): refused, also where LAPACK's
    # factorisation in the factor's order goes on with a pivot at rounding level
    perm = np.concatenate([np.setdiff1d(np.arange(n), cols), cols])
    went_on = 0
    for seed in range(10):
        B = np.random.default_rng(seed).standard_normal((n, n - 1))
        S = B @ B.T
        try:
            np.linalg.cholesky(S[np.ix_(perm, perm)])
            went_on += 1
        except np.linalg.LinAlgError:
            pass
        with pytest.raises(uncertainty.NotPositiveDefinite):
            uncertainty._KnotFactor(sp.csc_matrix(S), k, position)
    assert went_on > 0


def test_the_sandwich_reuses_the_plain_covariance_solve(monkeypatch):
    """With ``reuse``, the second covariance of a solution (the sandwich) evaluates and
    factors no Hessian, and equals the one computed from scratch."""
    prob = tiny_walk([])
    data = simulate_problem(prob)
    sol, nlp, _, _, s = solve_translational(prob, data)
    params = parameters(prob, data, s)
    meat = magnetometer_correction(
        nlp, sol, s, np.full((data.n_samples, 3), 2.0), params["sigma_m"]
    )
    fresh = position_uncertainty(nlp, sol, params, s.knots, s.dim, params["sigma_o"], meat=meat)
    reuse: dict = {}
    plain = position_uncertainty(nlp, sol, params, s.knots, s.dim, params["sigma_o"], reuse=reuse)
    assert "factor" in reuse

    def no_hessian(*args, **kwargs):
        raise AssertionError("the Hessian was evaluated again")

    monkeypatch.setattr(nlp, "hessian", no_hessian)
    again = position_uncertainty(
        nlp, sol, params, s.knots, s.dim, params["sigma_o"], meat=meat, reuse=reuse
    )
    np.testing.assert_allclose(again.cov, fresh.cov, rtol=1e-12, atol=0)
    assert not np.allclose(again.cov, plain.cov)
