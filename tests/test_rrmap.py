"""Reduced-rank map in the NLP: the Gauss-Newton Hessian against a CasADi reference, and the
reduced-rank solution against the exact GP."""

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import casmag
from casmag.kernels import FIELD_DIM
from casmag.simulate import simulate_problem
from casmag.slam import Structure, cached_nlp, parameters_and_guess

ROOT = Path(__file__).resolve().parents[1]


def _small(kernel, constant=True, n=10):
    data = {
        "seed": 4,
        "simulation": {"trajectory": {"samples": n}, "field": {"kernel": kernel}},
        "model": {"gp": {"form": "reduced_rank", "num_basis": 24}},
    }
    if constant:
        data["model"]["gp"]["sigma_lin"] = 0.5
    return casmag.load_problem(data)


@pytest.mark.parametrize("kernel", ["se", "curl_free"])
@pytest.mark.parametrize("constant", [False, True])
def test_gauss_newton_hessian_matches_casadi_reference(kernel, constant):
    """triu(J^T J) of the magnetometer residuals, J from CasADi on a reference residual
    written here, equals the numpy callback at a random point."""
    prob = _small(kernel, constant)
    data = simulate_problem(prob)
    s = Structure.of(prob, data)
    nlp = cached_nlp(s)
    gn = nlp.keep[1]
    params, x0 = parameters_and_guess(prob, data, s)
    rng = np.random.default_rng(11)
    x = nlp.x_layout.pack(x0) + 0.01 * rng.standard_normal(nlp.x_layout.size)
    p = nlp.p_layout.pack(params)

    # Reference: e_k = (y_k - m(p_k)) / sigma_m with the basis' own CasADi field function.
    xs = ca.SX.sym("x", nlp.x_layout.size)
    v = {
        n: xs[e.offset : e.offset + e.size].reshape(e.shape)
        for n, e in nlp.x_layout.entries.items()
    }
    field = s.hilbert_basis().field_sx(kernel, position_dim=2)
    c = v["c"] if constant else ca.DM.zeros(FIELD_DIM)
    sigma = params["sigma_m"]
    Y = data.Y
    res = [(Y[k] - field(v["P"][k, :].T, v["W"], c)) / sigma for k in range(data.n_samples)]
    J = ca.jacobian(ca.vertcat(*res), xs)
    ref = ca.Function("ref", [xs], [ca.triu(ca.mtimes(J.T, J))])(x)
    got = gn(x, p, 1.0, ca.DM.zeros(0, 1))
    np.testing.assert_allclose(
        np.array(ca.densify(got)), np.array(ca.densify(ref)), rtol=1e-9, atol=1e-9
    )


def test_reduced_rank_matches_exact_on_base_case():
    """The paper's base case (seed 1): reduced-rank positions within 1 mm of the exact GP's."""
    exact = casmag.solve(ROOT / "problems/paper/base.yaml")
    rr = casmag.load_problem(ROOT / "problems/paper/base.yaml", ["model.gp.form=reduced_rank"])
    r = casmag.solve(rr)
    assert exact.success and r.success, (exact.status, r.status)
    diff = np.abs(r.arrays["P_estimate"] - exact.arrays["P_estimate"]).max()
    assert diff < 1e-3
    # The field at the samples agrees to 0.2 % of sigma_f (measured 5e-5 on seeds 1 and 2).
    assert np.abs(r.arrays["M_estimate"] - exact.arrays["M_estimate"]).max() < 2e-4
    assert r.rmse_after <= 0.005


def test_curl_free_reduced_rank_solves_base_case():
    prob = casmag.load_problem(
        ROOT / "problems/paper/base.yaml",
        ["simulation.field.kernel=curl_free", "model.gp.form=reduced_rank"],
    )
    r = casmag.solve(prob)
    assert r.success, r.status
    assert r.rmse_after <= 0.005


def test_sigma_m_estimation_is_refused():
    with pytest.raises(casmag.ProblemError, match="unbounded as sigma_m"):
        casmag.load_problem({"seed": 1, "model": {"estimate": ["sigma_m"]}})


def test_reduced_rank_refuses_sigma_f_and_lengthscale_estimation():
    with pytest.raises(casmag.ProblemError, match="unbounded"):
        casmag.load_problem(
            {"seed": 1, "model": {"gp": {"form": "reduced_rank"}, "estimate": ["lengthscale"]}}
        )


def test_gauss_newton_needs_reduced_rank():
    with pytest.raises(casmag.ProblemError, match="gauss-newton needs"):
        casmag.load_problem({"seed": 1, "solver": {"hessian": "gauss-newton"}})


def test_div_free_has_no_reduced_rank_form():
    with pytest.raises(casmag.ProblemError, match="div_free"):
        casmag.load_problem(
            {"seed": 1, "model": {"gp": {"form": "reduced_rank", "kernel": "div_free"}}}
        )
