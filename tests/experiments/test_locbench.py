"""The map-once-locate-later benchmark's later recording (casmag.experiments.locbench)."""

from pathlib import Path

import numpy as np
import pytest

from casmag import strapdown as sd
from casmag.experiments.locbench import LATER, later_recording, table
from casmag.problem.oriented import load_oriented_problem
from casmag.solver.oriented import simulate_oriented

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("motion", ["planar", "pose"])
def test_the_later_recording_has_the_same_path_and_its_own_odometry_errors(motion):
    problem = load_oriented_problem(
        ROOT / f"problems/{motion}/walk.yaml", ["simulation.trajectory.samples=200"]
    )
    rec, _ = simulate_oriented(problem)
    later = later_recording(rec, 1)
    np.testing.assert_array_equal(later.P_true, rec.P_true)
    assert later.path.endswith("-later")
    dU = later.increments - rec.increments
    # the displacement bias, within the noise's standard error over 199 steps
    np.testing.assert_allclose(dU[:, :2].mean(axis=0), LATER["bias_p"], atol=1e-3)
    h = float(np.median(np.diff(rec.t)))
    if motion == "planar":
        turn = dU[:, 2]
    else:  # the rotation added to each increment, about the body z axis
        turn = 2.0 * np.arcsin(sd.quat_mul(sd.quat_conj(rec.increments[:, 3:]),
                                           later.increments[:, 3:])[:, 3])  # fmt: skip
    assert turn.mean() == pytest.approx(LATER["bias_w"] * h, abs=4e-4)
    assert 0.03 < np.std(later.Y - rec.Y) < 0.07


def test_the_table_has_a_row_per_seed_and_the_medians():
    row = {"rmse_before": 0.5, "rmse_after": 0.04, "seconds": 9.0, "nees_mean": 2.1}
    runs = [
        {"motion": "planar", "seed": s, "scratch": dict(row), "joint": dict(row),
         "located": {**row, "map_std_ratio": 0.7}, "held": {**row, "rmse_after": 0.05}}
        for s in (1, 2)
    ]  # fmt: skip
    text = table(runs)
    assert text.count("| planar |") == 2
    assert "located 0.040 m in 9.0 s" in text and "held 0.050 m in 9.0 s" in text
    assert text.splitlines()[4].count("|") == 11  # ten columns
    assert "model.gp.form" not in text.splitlines()[0]
    assert table(runs, "tiled").splitlines()[0].endswith("model.gp.form tiled")


def test_the_later_imu_recording_has_the_same_path_and_its_own_biases(tmp_path):
    """The IMU rows' later recording (the scenario with another seed and LATER_IMU's biases)
    traces the same path and reads the same field, with other sensor errors."""
    import yaml

    from casmag.experiments.locbench import LATER_IMU, _imu_recording
    from casmag.problem.imu import load_imu_problem

    scenario = ROOT / "problems/imu/rectangle.yaml"
    first = _imu_recording(load_imu_problem(scenario, ["seed=1"]), tmp_path, "a")
    later_problem = load_imu_problem(scenario, ["seed=1001", *LATER_IMU])
    later = _imu_recording(later_problem, tmp_path, "b")
    assert later.motion == first.motion == "imu"
    np.testing.assert_array_equal(later.t, first.t)
    np.testing.assert_allclose(later.P_true, first.P_true, atol=1e-12)
    given = yaml.safe_load(scenario.read_text())["simulation"]["imu"]["gyro_bias"]
    assert later_problem.simulation.imu.gyro_bias != given
    assert not np.array_equal(later.increments, first.increments)


def test_the_imu_table_has_a_row_per_seed_and_the_medians_in_millimetres():
    row = {"status": "Solve_Succeeded", "rmse_before": 0.14, "rmse_after": 0.004, "seconds": 30.0}
    runs = [
        {"motion": "imu", "scenario": "rectangle", "seed": s, "keyframes": 239,
         "map_run": {**row, "rmse_after": 0.005},
         "scratch": dict(row), "joint": dict(row), "located": {**row, "rmse_after": 0.003},
         "held": dict(row)}
        for s in (1, 2)
    ]  # fmt: skip
    text = table(runs)
    assert text.startswith("# Map once, locate later (IMU recordings)")
    assert text.count("| rectangle |") == 2
    assert "| 239 | 5.0 | 140.0 | 4.0 (30) | 3.0 (30) |" in text
    assert "located 3.0 mm in 30 s" in text and "Not successful: none" in text
    runs[1]["held"] = {**row, "status": "Maximum_Iterations_Exceeded", "rmse_after": None}
    text = table(runs)
    assert "| - (30) |" in text and "seed 2 held (Maximum_Iterations_Exceeded)" in text
