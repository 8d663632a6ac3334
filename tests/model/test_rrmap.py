"""Reduced-rank map in the NLP: the Gauss-Newton Hessian against a CasADi reference, and the
reduced-rank solution against the exact GP."""

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import casmag
from casmag.data.simulate import simulate_problem
from casmag.gp.kernels import FIELD_DIM
from casmag.model.translational import Structure, cached_nlp, parameters_and_guess
from casmag.problem.imu import load_imu_problem

ROOT = Path(__file__).resolve().parents[2]


def _small(kernel, constant=True, n=10, knot_every=1, hessian="auto"):
    data = {
        "seed": 4,
        "simulation": {"trajectory": {"samples": n}, "field": {"kernel": kernel}},
        "model": {
            "gp": {"form": "reduced_rank", "num_basis": 24},
            "trajectory": {"knot_every": knot_every},
        },
        "solver": {"hessian": hessian},
    }
    if constant:
        data["model"]["gp"]["sigma_lin"] = 0.5
    return casmag.load_problem(data)


@pytest.mark.parametrize("kernel", ["se", "curl_free"])
@pytest.mark.parametrize("constant", [False, True])
@pytest.mark.parametrize("knot_every", [1, 3])
@pytest.mark.parametrize("hessian", ["gauss-newton", "exact"])
def test_map_hessian_matches_casadi_reference(kernel, constant, knot_every, hessian):
    """The numpy callback at a random point equals CasADi's on a reference residual written
    here (positions interpolated between knots): triu(J^T J) for gauss-newton, the exact
    Hessian of 0.5 |e|^2 for exact."""
    prob = _small(kernel, constant, n=11, knot_every=knot_every, hessian=hessian)
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
    knots = s.knots
    A = knots.matrix.toarray()
    P = ca.DM(params["Q"]) + ca.mtimes(ca.DM(A), v["C"])
    res = [(Y[k] - field(P[k, :].T, v["W"], c)) / sigma for k in range(data.n_samples)]
    e = ca.vertcat(*res)
    if hessian == "exact":
        H = ca.hessian(0.5 * ca.sumsqr(e), xs)[0]
    else:
        J = ca.jacobian(e, xs)
        H = ca.mtimes(J.T, J)
    f = 0.5 * ca.sumsqr(e)
    ref = ca.Function("ref", [xs], [ca.triu(H), f, ca.gradient(f, xs)])
    H_ref, f_ref, g_ref = ref(x)
    got = gn(x, p, 1.0, ca.DM.zeros(0, 1))
    np.testing.assert_allclose(
        np.array(ca.densify(got)), np.array(ca.densify(H_ref)), rtol=1e-9, atol=1e-9
    )
    # The numpy magnetometer block and its gradient, as CasADi differentiates it in the NLP.
    xm, pm = ca.MX.sym("x", x.size), ca.MX.sym("p", p.size)
    block = gn.model
    from casmag.model.rrmap import MagnetometerCost

    mag = MagnetometerCost("mag_test", block)
    fg = ca.Function("fg", [xm, pm], [mag(xm, pm), ca.gradient(mag(xm, pm), xm)])
    f_got, g_got = fg(x, p)
    assert float(f_got) == pytest.approx(float(f_ref), rel=1e-10)
    np.testing.assert_allclose(np.array(g_got).ravel(), np.array(g_ref).ravel(), atol=1e-8)


def test_hybrid_hessian_switches_to_exact_when_the_cost_stalls():
    """auto: Gauss-Newton at the first evaluation and while the magnetometer cost falls by
    20 % or more per evaluation, the exact Hessian after; reset() starts over."""
    prob = _small("se", constant=False, n=11, knot_every=1, hessian="auto")
    data = simulate_problem(prob)
    s = Structure.of(prob, data)
    nlp = cached_nlp(s)
    H = nlp.keep[1]
    assert H.mode == "hybrid"
    params, x0 = parameters_and_guess(prob, data, s)
    x, p = nlp.x_layout.pack(x0), nlp.p_layout.pack(params)
    H.reset()
    first = H.values(x, p)
    again = H.values(x, p)  # same cost: stalled
    H.reset()
    H.mode = "gauss-newton"
    gn = H.values(x, p)
    H.mode = "exact"
    exact = H.values(x, p)
    H.mode = "hybrid"
    np.testing.assert_array_equal(first, gn)
    np.testing.assert_array_equal(again, exact)
    assert not np.array_equal(gn, exact)


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


@pytest.mark.slow
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


@pytest.mark.parametrize("hessian", ["gauss-newton", "hybrid"])
def test_gauss_newton_needs_reduced_rank(hessian):
    """The modes only a map read with numpy has are refused for the exact GP (whose
    Hessian is CasADi's), for the translational and the IMU model alike."""
    with pytest.raises(casmag.ProblemError, match=f"{hessian} needs"):
        casmag.load_problem({"seed": 1, "solver": {"hessian": hessian}})
    imu = ROOT / "problems" / "imu" / "rectangle.yaml"
    with pytest.raises(casmag.ProblemError, match=f"{hessian} needs"):
        load_imu_problem(imu, ["model.gp.form=exact", f"solver.hessian={hessian}"])
    casmag.load_problem({"seed": 1, "solver": {"hessian": "exact"}})  # CasADi's: taken


def test_div_free_has_no_reduced_rank_form():
    with pytest.raises(casmag.ProblemError, match="div_free"):
        casmag.load_problem(
            {"seed": 1, "model": {"gp": {"form": "reduced_rank", "kernel": "div_free"}}}
        )


@pytest.mark.parametrize("kernel", ["se", "curl_free"])
@pytest.mark.parametrize("hessian", ["gauss-newton", "exact"])
def test_map_hessian_is_the_same_over_chunks_of_samples(kernel, hessian, monkeypatch):
    """Samples taken in chunks whose edges fall between the two knots of a sample (4
    samples a chunk, a knot every 3) give the Hessian of one chunk, to rounding."""
    from casmag.model.rrmap import MapModel

    prob = _small(kernel, True, n=11, knot_every=3, hessian=hessian)
    data = simulate_problem(prob)
    s = Structure.of(prob, data)
    nlp = cached_nlp(s)
    H = nlp.keep[1]
    params, x0 = parameters_and_guess(prob, data, s)
    rng = np.random.default_rng(5)
    x = nlp.x_layout.pack(x0) + 0.01 * rng.standard_normal(nlp.x_layout.size)
    p = nlp.p_layout.pack(params)
    whole = H.values(x, p)
    monkeypatch.setattr(MapModel, "CHUNK", 4)
    assert len(H.model.chunks()) == 3
    np.testing.assert_allclose(H.values(x, p), whole, rtol=1e-12, atol=1e-12)
