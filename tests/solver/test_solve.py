"""Solver tests against known answers (small problems, explicit tolerances)."""

from pathlib import Path

import numpy as np
import pytest
from problem_files import TRANSLATIONAL

import casmag
from casmag.data.simulate import simulate_problem, spiral
from casmag.model.builder import cached_slam

ROOT = Path(__file__).resolve().parents[2]
PROBLEM_FILES = TRANSLATIONAL


def _problem(**sections):
    data = {"seed": 3, **sections}
    return casmag.load_problem(data)


def test_spiral_spacing_and_length():
    from casmag.problem.spec import TrajectorySpec

    P = spiral(TrajectorySpec(samples=50, step=0.05, start_radius=0.05, pitch=0.03))
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    # Chords of a curved arc are slightly shorter than the arc step.
    assert np.all(steps <= 0.05 + 1e-6) and np.all(steps > 0.045)
    assert np.hypot(*P[0]) == pytest.approx(0.05, abs=1e-9)


def test_noise_free_without_bias_returns_truth():
    """No noise, no bias, nothing free to move: the MAP is the truth to solver precision."""
    prob = _problem(
        simulation={
            "trajectory": {"samples": 15},
            "odometry": {"noise": 0.0, "bias": [0.0, 0.0]},
            "magnetometer": {"noise": 0.0},
        },
        model={
            "odometry": {"sigma": 1e-5, "estimate_bias": False},
            "magnetometer": {"sigma_m": 1e-5},
        },
    )
    r = casmag.solve(prob)
    assert r.success, r.status
    np.testing.assert_allclose(r.arrays["P_estimate"], r.arrays["P_true"], atol=1e-6)
    np.testing.assert_allclose(r.arrays["M_estimate"], r.arrays["Y"], atol=1e-6)
    assert r.rmse_after < 1e-6


def test_noise_free_with_bias_removes_the_drift():
    """Exact data with a 2 %-of-distance odometry bias: the bias is estimated and the drift
    removed. The residual error is the estimator's (one field draw), not noise."""
    prob = _problem(
        simulation={
            "trajectory": {"samples": 41, "pitch": 0.03},
            "odometry": {"noise": 0.0},
            "magnetometer": {"noise": 0.0},
        },
        model={"odometry": {"sigma": 1e-5}, "magnetometer": {"sigma_m": 1e-5}},
    )
    r = casmag.solve(prob)
    assert r.success, r.status
    assert r.rmse_before > 0.02
    assert r.rmse_after < 0.2 * r.rmse_before
    np.testing.assert_allclose(r.odometry_bias, r.odometry_bias_true, rtol=0.3)


def test_build_once_reused_across_seeds():
    base = {"simulation": {"trajectory": {"samples": 13, "step": 0.047}}}  # a structure of its own
    before = cached_slam.cache_info()
    r1 = casmag.solve(casmag.load_problem({"seed": 1, **base}))
    r2 = casmag.solve(casmag.load_problem({"seed": 2, **base}))
    info = cached_slam.cache_info()
    assert info.misses - before.misses == 1 and info.hits - before.hits == 1
    assert r1.success and r2.success
    assert not np.allclose(r1.arrays["Y"], r2.arrays["Y"])


def test_seed_determines_data():
    p = casmag.load_problem({"seed": 5})
    a, b = simulate_problem(p), simulate_problem(p)
    np.testing.assert_array_equal(a.Y, b.Y)
    np.testing.assert_array_equal(a.U, b.U)


def test_odometry_noise_level_leaves_field_draw_unchanged():
    p1 = casmag.load_problem({"seed": 5})
    p2 = casmag.load_problem({"seed": 5}, ["simulation.odometry.noise=0.002"])
    np.testing.assert_array_equal(simulate_problem(p1).M_true, simulate_problem(p2).M_true)


@pytest.mark.parametrize("kernel", ["se", "curl_free", "div_free"])
def test_every_kernel_solves(kernel):
    prob = _problem(simulation={"trajectory": {"samples": 12}, "field": {"kernel": kernel}})
    r = casmag.solve(prob)
    assert r.success, r.status
    assert r.cost_blocks["gp_prior"]["after"] < r.cost_blocks["gp_prior"]["before"]


def test_hyperparameter_estimation_moves_towards_truth():
    """Start sigma_f 3x too large; the estimate must move towards the true 0.1."""
    prob = _problem(
        simulation={"trajectory": {"samples": 30}},
        model={"gp": {"sigma_f": 0.3}, "estimate": ["sigma_f"]},
    )
    r = casmag.solve(prob)
    assert r.success, r.status
    assert "gp_logdet" in r.cost_blocks
    assert abs(np.log(r.hyperparameters["sigma_f"] / 0.1)) < abs(np.log(0.3 / 0.1))


def test_solver_failure_is_reported_not_a_result():
    prob = _problem(simulation={"trajectory": {"samples": 12}}, solver={"max_iter": 1})
    r = casmag.solve(prob)
    assert not r.success
    assert r.status == "Maximum_Iterations_Exceeded"
    assert r.rmse_after is None and r.max_after is None


@pytest.mark.parametrize("path", PROBLEM_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_problem_file_smoke_runs_at_tiny_size(path):
    prob = casmag.load_problem(path, ["simulation.trajectory.samples=12"])
    r = casmag.solve(prob)
    assert r.success, r.status
    assert np.isfinite(r.rmse_after)


@pytest.mark.slow
def test_base_case_full_size():
    """The paper's base case (seed 1): RMSE after <= 5 mm within 100 iterations."""
    r = casmag.solve(ROOT / "problems/paper/base.yaml")
    assert r.success, r.status
    assert 0.04 <= r.rmse_before <= 0.10
    assert r.rmse_after <= 0.005
    assert r.iterations <= 100


def test_progress_callback_sees_every_iteration():
    calls = []
    prob = casmag.load_problem({"seed": 2, "simulation": {"trajectory": {"samples": 12}}})
    r = casmag.solve(prob, progress=lambda k, cost, step, s: calls.append((k, cost)))
    assert [k for k, _ in calls] == list(range(r.iterations + 1))
    np.testing.assert_allclose([c for _, c in calls], r.cost_per_iteration)


def test_the_library_solve_takes_an_imu_problem_and_names_the_entry_point_of_other_files():
    import yaml

    imu = yaml.safe_load(Path("problems/imu/rectangle.yaml").read_text())
    imu["simulation"]["scenario"]["loops"] = 1
    imu["model"]["gp"] = {"form": "none"}  # the IMU-only adjustment: a second
    r = casmag.solve(imu)
    assert r.motion == "imu" and r.stage("imu_only")["status"] == "Solve_Succeeded"
    with pytest.raises(casmag.ProblemError, match=r"use casmag\.experiments\.sweep"):
        casmag.solve("problems/paper/table1.yaml")
    with pytest.raises(casmag.ProblemError, match="use casmag solve FILE"):
        casmag.solve("problems/real/seq1-drift0.5.yaml")
