"""The rotated map block's residual Jacobian (casmag.model.rotated.RotatedFieldGaussNewton
.residual_jacobian), which the planar and pose models' Laplace covariance uses: its
residuals are the block's cost, J^T e its gradient (central differences of the block), and
J^T J the Gauss-Newton Hessian the block gives IPOPT."""

from pathlib import Path

import numpy as np
import pytest

import casmag.solver.staged as staged
from casmag.model.rotated import rotated_design, window_unknowns
from casmag.model.rrmap import field_and_jacobians, make_basis
from casmag.problem.oriented import load_oriented_problem
from casmag.solver.oriented import solve_oriented
from casmag.solver.planar import heading_rotations

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module", params=["planar", "pose"])
def final_solve(request):
    """The last solve of a 30-sample planar (se kernel) or pose (curl-free) problem."""
    seen = {}
    record = staged.sample_state_uncertainty

    def spy(nlp, sol, *args, **kwargs):
        seen.update(nlp=nlp, sol=sol)
        return record(nlp, sol, *args, **kwargs)

    path = ROOT / "problems" / request.param / "walk.yaml"
    problem = load_oriented_problem(path, ["simulation.trajectory.samples=30"])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(staged, "sample_state_uncertainty", spy)
        result = solve_oriented(problem)
    assert result.success and seen
    nlp, sol = seen["nlp"], seen["sol"]
    x = nlp.x_layout.pack({k: v for k, v in sol.x.items() if k in nlp.x_layout.entries})
    return nlp, x, nlp.p_layout.pack(sol.params), result


def test_residuals_are_the_block_and_jacobian_its_gradient(final_solve):
    nlp, x, p, _ = final_solve
    block = nlp.keep[1]
    e, J = block.residual_jacobian(x, p)
    assert J.shape == (e.size, x.size)
    cost = nlp.evaluate_blocks(x, p)["magnetometer"]
    assert 0.5 * float(np.sum(e**2)) == pytest.approx(cost, rel=1e-12)
    grad = J.T @ e.ravel()
    rng = np.random.default_rng(0)
    for i in rng.choice(x.size, 25, replace=False):
        h = 1e-6 * max(1.0, abs(x[i]))
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        fd = (
            nlp.evaluate_blocks(up, p)["magnetometer"]
            - nlp.evaluate_blocks(down, p)["magnetometer"]
        ) / (2 * h)
        assert grad[i] == pytest.approx(fd, rel=1e-5, abs=1e-6 * max(1.0, np.abs(grad).max()))


def test_gauss_newton_hessian_is_jacobian_squared(final_solve):
    import scipy.sparse as sp

    nlp, x, p, _ = final_solve
    block = nlp.keep[1]
    mode = block.mode
    block.set_mode("gauss-newton")
    try:
        values = block.values(x, p)
    finally:
        block.set_mode(mode)
    rows, cols = block._rows, block._cols  # the pattern the values fill
    upper = sp.coo_matrix((values, (rows, cols)), shape=(x.size, x.size)).toarray()
    _, J = block.residual_jacobian(x, p)
    JtJ = np.triu((J.T @ J).toarray())
    np.testing.assert_allclose(upper, JtJ, atol=1e-9 * np.abs(JtJ).max())


def test_the_result_carries_an_honest_shaped_covariance(final_solve):
    _, _, _, result = final_solve
    u, cov = result.uncertainty, result.arrays["P_cov"]
    n, d = result.arrays["P_estimate"].shape
    assert cov.shape == (n, d, d) and u["nees_expected"] == d
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2))
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # the first pose is anchored (1 mm): its standard deviation is the anchor's
    assert np.sqrt(cov[0, 0, 0]) < 2e-3 < np.sqrt(cov[-1, 0, 0])
    assert "inflation" in u and u["uninflated"]["nees_expected"] == d


@pytest.mark.parametrize("kernel", ["se", "curl_free"])
def test_rotated_design_is_the_reading_of_the_map(kernel):
    """rotated_design: y_k = R_k^T (m(p_k) + c) stacked is J [vec(V); c], V the whitened
    weights (the window map's unknowns), for both kernels, planar positions."""
    rng = np.random.default_rng(3)
    P, psi = rng.uniform(0.0, 2.0, (7, 2)), rng.uniform(-3.0, 3.0, 7)
    basis = make_basis(kernel, P, 0.5, None, None)
    S = basis.prior_variances(kernel, 1.3, 0.5)
    V = rng.normal(size=(basis.num_basis, 3 if kernel == "se" else 1))
    c = rng.normal(size=3)
    m, _, _ = field_and_jacobians(basis, kernel, P, (V * np.sqrt(S)[:, None]).ravel(order="F"))
    R = heading_rotations(psi)
    y = np.einsum("kji,kj->ki", R, m + c)
    J = rotated_design(basis, kernel, P, R, 1.3, 0.5)
    assert J.shape == (21, window_unknowns(basis, kernel))
    z = np.concatenate([V.ravel(order="F"), c])
    np.testing.assert_allclose(J @ z, y.ravel(), atol=1e-12 * np.abs(y).max())
