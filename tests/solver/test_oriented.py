"""Planar and pose problem files solved through the library's one entry point
(casmag.solve): the recording is simulated and solved as casmag slam solves one."""

from pathlib import Path

import numpy as np
import pytest

import casmag
from casmag.problem.oriented import load_oriented_problem
from casmag.solver.oriented import simulate_oriented, solve_oriented

ROOT = Path(__file__).resolve().parents[2]
TINY = ["simulation.trajectory.samples=40"]


def test_casmag_solve_takes_a_pose_problem_and_refuses_data():
    problem = load_oriented_problem(ROOT / "problems/pose/walk.yaml", TINY)
    result = casmag.solve(problem)
    assert result.motion == "pose" and result.success
    assert (
        result.info["name"] == "pose-walk" and result.info["simulation"]["motion"]["kind"] == "pose"
    )
    assert result.details["bias_w_true"] == [0.0, 0.0, 2.0e-3]
    rec, _ = simulate_oriented(problem)
    np.testing.assert_array_equal(result.arrays["P_true"], rec.P_true)
    with pytest.raises(TypeError, match="simulates its recording"):
        casmag.solve(problem, data=object())


def test_the_filter_baseline_runs_on_a_planar_problem():
    problem = load_oriented_problem(ROOT / "problems/planar/walk.yaml", TINY)
    result = solve_oriented(problem, method="ekf")
    assert result.motion == "planar" and result.status == "Filter_Completed"
    assert result.odometry_bias_true == [2.0e-3]
    assert result.rmse_after is not None
