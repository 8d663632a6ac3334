"""The planar position covariance's consider parameters: a body-frame displacement bias the
model does not estimate (casmag.model.planar.displacement_bias_coupling,
casmag.solver.planar.displacement_bias_consider)."""

from pathlib import Path

import numpy as np
import pytest
from small_problems import planar_room_field

from casmag.data.imusim import simulate_planar
from casmag.model.planar import displacement_bias_coupling
from casmag.problem.imu import load_planar_options
from casmag.solver.planar import solve_planar


def _residuals(P, psi, U, b, sigma, steps):
    """The odometry's displacement residuals (m, 2) with the step read as u - b."""
    c, s = np.cos(psi[steps]), np.sin(psi[steps])
    u = U[steps, :2] - b
    step = np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1]])
    return (P[steps + 1] - P[steps] - step) / sigma


def test_the_coupling_is_the_odometry_cross_hessian():
    """Against the mixed second differences of the odometry's displacement cost in the
    states and the bias, away from the optimum (so the residual's own term counts), two
    sessions (the step between them not read)."""
    rng = np.random.default_rng(3)
    n, sigma, starts = 9, 0.02, (0, 5)
    P, psi = rng.normal(size=(n, 2)), rng.normal(size=n)
    U = rng.normal(scale=0.5, size=(n - 1, 3))
    H_P, H_psi, steps = displacement_bias_coupling(P, psi, U, sigma, starts)
    assert steps.tolist() == [0, 1, 2, 3, 5, 6, 7]
    x0 = np.concatenate([P.ravel(), psi])

    def f(x, b):
        r = _residuals(x[: 2 * n].reshape(n, 2), x[2 * n :], U, b, sigma, steps)
        return 0.5 * np.sum(r * r)

    h = 1e-4
    H = np.empty((x0.size, 2))
    for i, ei in enumerate(np.eye(x0.size)):
        for j, ej in enumerate(np.eye(2)):
            H[i, j] = (
                f(x0 + h * ei, h * ej) - f(x0 + h * ei, -h * ej)
                - f(x0 - h * ei, h * ej) + f(x0 - h * ei, -h * ej)
            ) / (4 * h * h)  # fmt: skip
    np.testing.assert_allclose(H_P.reshape(2 * n, 2), H[: 2 * n], rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(H_psi, H[2 * n :], rtol=1e-5, atol=1e-3)
    assert np.abs(H_psi).max() > 100.0  # not all zero


@pytest.mark.slow
def test_the_consider_variance_is_the_maps_response_to_a_bias():
    """The planar room walk (one loop, the box map, hyperparameters held): the variance
    the consider parameters add at each sample is the squared shift of the MAP when the
    odometry carries that bias, forward plus sideways (re-solved with a tenth of it,
    scaled: the response is linear there), to first order; the estimate is the same."""
    d = simulate_planar(
        2, planar_room_field(), size=(2.0, 1.5), loops=1, heading_bias_deg=0.5,
        disp_noise=0.002,
    )  # fmt: skip
    base = ["model.sigma_disp=0.002", f"model.sigma_dyaw={np.radians(0.05)}"]
    truth = {"P": d.P, "psi": d.psi}
    first = solve_planar(*d.U.T, d.Y, load_planar_options(None, base), truth=truth, t=d.t)
    h = first.hyperparameters
    held = [
        *base,
        f"model.gp.sigma_f={h['sigma_f']}",
        f"model.gp.lengthscale={h['lengthscale']}",
        f"model.magnetometer.sigma_m={h['sigma_m']}",
        "solver.tol=1e-8",
    ]
    fraction = 0.01
    sigma_b = fraction * float(np.median(np.linalg.norm(d.U[:, :2], axis=1)))

    def run(U, *sets):
        opts = load_planar_options(None, [*held, *sets])
        r = solve_planar(*U.T, d.Y, opts, truth=truth, t=d.t)
        assert r.success, r.status
        return r

    plain = run(d.U, "model.displacement_bias=0")
    wide = run(d.U, f"model.displacement_bias={fraction}")
    np.testing.assert_allclose(wide.arrays["P_estimate"], plain.arrays["P_estimate"])
    added = np.trace(wide.arrays["P_cov"] - plain.arrays["P_cov"], axis1=1, axis2=2)
    shift2 = np.zeros(d.P.shape[0])
    for axis in range(2):  # the odometry reads u + db, i.e. a bias of -db in u - b
        U = d.U.copy()
        U[:, axis] += 0.1 * sigma_b
        moved = run(U, "model.displacement_bias=0").arrays["P_estimate"]
        shift2 += 100.0 * np.sum((moved - plain.arrays["P_estimate"]) ** 2, axis=1)
    far = shift2 > 0.25 * shift2.max()
    assert far.sum() > 10
    # Measured 2026-12-02: the response through the Laplace covariance's own Hessian is
    # 5 % short of the re-solved shift for the forward bias (cosine 0.99) and 23-24 %
    # for the sideways one (cosine 0.91), so the added variance is 0.72 of the squared
    # shifts over these samples (first order, not exact), and follows them along the path.
    ratio = added[far].sum() / shift2[far].sum()
    assert 0.6 < ratio < 1.1, ratio
    assert np.corrcoef(added, shift2)[0, 1] > 0.9  # measured 0.96
    assert np.all(added > -1e-12)
    assert wide.uncertainty["sigma_mean"] > plain.uncertainty["sigma_mean"]
    taken = wide.uncertainty["consider"]["displacement_bias"]
    assert taken == {"sigma_per_step_m": pytest.approx(sigma_b), "fraction_of_step": fraction}
    assert "consider" not in plain.uncertainty


@pytest.mark.slow
def test_the_pose_models_held_displacement_bias_is_taken_in():
    """The pose walk (80 samples, seed 2): the held displacement bias as a consider
    parameter (its Hessian columns, casmag.solver.pose.displacement_bias_consider) widens
    every position's covariance and leaves the estimate as it was; 0 turns it off."""
    import casmag
    from casmag.problem.oriented import load_oriented_problem

    sets = ["seed=2", "simulation.trajectory.samples=80"]
    walk = Path(__file__).resolve().parents[2] / "problems/pose/walk.yaml"
    plain = casmag.solve(load_oriented_problem(walk, [*sets, "model.displacement_bias=0"]))
    wide = casmag.solve(load_oriented_problem(walk, sets))
    assert plain.success and wide.success
    np.testing.assert_allclose(wide.arrays["P_estimate"], plain.arrays["P_estimate"])
    added = wide.arrays["P_cov"] - plain.arrays["P_cov"]
    assert np.all(np.linalg.eigvalsh(added).min(axis=1) > -1e-10)
    grows = np.trace(added, axis1=1, axis2=2)
    assert grows[-1] > 10 * grows[1] > 0.0  # the anchor holds the start, not the far end
    assert wide.uncertainty["nees_mean"] < plain.uncertainty["nees_mean"]
    assert wide.uncertainty["consider"]["displacement_bias"]["fraction_of_step"] == 0.01
