"""The MAP against the filter baseline over seeds (casmag.experiments.peers)."""

import pytest

from casmag.experiments.peers import DEFAULT_FILE, markdown, run_seed, summary


def test_one_seed_of_the_peers_setting_runs_both_methods():
    """A short walk of the benchmark's setting: both methods give an error below the dead
    reckoning's, timed, and the summary counts them."""
    row = run_seed(DEFAULT_FILE, 3, overrides=("simulation.trajectory.samples=200",))
    assert row["samples"] == 200 and row["before"] > 0.2
    for method in ("map", "ekf"):
        assert row[method]["rmse"] < row["before"], (method, row)
        assert row[method]["wall_seconds"] > 0 and row[method]["real_time_factor"] > 0
    assert row["ekf"]["status"] == "Filter_Completed"
    s = summary([row])
    assert s["compared"] == 1
    ratio = row["map"]["rmse"] / row["ekf"]["rmse"]
    assert s["map_at_most_half_of_ekf"] == int(ratio <= 0.5)
    assert "| 3 |" in markdown([row], s, "peers")


@pytest.mark.slow
def test_one_seed_as_pose_odometry_runs_both_methods():
    """The same setting as pose odometry (6-DoF increments, a rotation noise, a body-frame
    displacement bias): both methods locate below the dead reckoning and report the
    attitude error."""
    row = run_seed(DEFAULT_FILE, 3, overrides=("simulation.trajectory.samples=120",), motion="pose")
    assert row["motion"] == "pose" and row["samples"] == 120 and row["before"] > 0.05
    for method in ("map", "ekf"):
        assert row[method]["rmse"] < row["before"], (method, row)
        assert row[method]["attitude_rms_deg"] is not None
    assert row["map"]["status"] == "Solve_Succeeded"
    assert row["ekf"]["status"] == "Filter_Completed"
