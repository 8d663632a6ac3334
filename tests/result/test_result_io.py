"""A saved result reads back: Result.load(folder) gives the same statistics and arrays."""

import json

import numpy as np
import pytest

import casmag
from casmag.errors import DataError
from casmag.result import ARRAYS_FILE, Result


def test_a_saved_result_loads_back_exactly(tmp_path):
    result = casmag.solve(casmag.load_problem("problems/paper/base.yaml", ["seed=2"]))
    result.save(tmp_path / "out", figures=False)
    assert (tmp_path / "out" / ARRAYS_FILE).is_file()
    back = Result.load(tmp_path / "out")
    assert back.to_dict() == json.loads((tmp_path / "out" / "result.json").read_text())
    assert back.status == result.status and back.rmse_after == result.rmse_after
    assert back.convergence[0]["inf_du"] == result.convergence[0]["inf_du"]
    saved = {k for k, v in result.arrays.items() if v is not None}
    assert set(back.arrays) == saved
    for key in saved:
        assert np.array_equal(back.arrays[key], result.arrays[key]), key


def test_load_names_the_file_that_is_not_a_result(tmp_path):
    with pytest.raises(DataError, match=r"result\.json: cannot read"):
        Result.load(tmp_path)
    (tmp_path / "result.json").write_text(json.dumps({"status": "x"}))
    with pytest.raises(DataError, match="not a casmag result"):
        Result.load(tmp_path)


def test_the_package_exports_the_recording_entry_points():
    from casmag.solver.recslam import slam, slam_sessions

    assert casmag.slam is slam and casmag.slam_sessions is slam_sessions
    assert {"solve", "slam", "slam_sessions", "load_problem", "Result"} <= set(casmag.__all__)


def test_every_motion_model_gives_one_result_class_loaded_back_by_one_reader(tmp_path):
    from small_problems import planar_room_field

    from casmag.data.imusim import simulate_planar
    from casmag.problem.imu import load_imu_problem
    from casmag.solver.imu import solve_imu
    from casmag.solver.planar import solve_planar

    d = simulate_planar(4, planar_room_field(), size=(2.0, 1.5), loops=1, disp_noise=0.002)
    planar = solve_planar(*d.U.T, d.Y, t=d.t, truth={"P": d.P, "psi": d.psi})
    planar.save(tmp_path / "planar", figures=False)
    tiny = ["simulation.scenario.loops=1", "model.gp.form=none"]
    imu = solve_imu(load_imu_problem("problems/imu/rectangle.yaml", tiny))
    imu.save(tmp_path / "imu", figures=False)
    for motion, original in (("planar", planar), ("imu", imu)):
        assert type(original) is Result and original.motion == motion
        back = casmag.load_result(tmp_path / motion)
        assert type(back) is Result and back.motion == motion
        assert back.status == original.status and back.verdict == original.verdict
        assert back.details.keys() == original.details.keys()
        assert back.stages == json.loads(json.dumps(original.stages))
        np.testing.assert_array_equal(back.arrays["P_estimate"], original.arrays["P_estimate"])
    assert imu.stage("imu_only")["status"] == imu.status  # no map: the IMU-only adjustment
    assert imu.rmse_before == imu.details["errors"]["imu_only"]["rmse"]
    header = (tmp_path / "planar" / "trajectory.csv").read_text().splitlines()[0]
    assert header.startswith("k,t,x_odo,y_odo,psi_odo,x_est,y_est,psi_est,x_true")
    assert (tmp_path / "imu" / "biases.md").is_file()


def test_a_result_saved_in_the_layout_before_the_one_result_still_loads(tmp_path):
    """IMU and planar result.json files written before the one Result (errors per stage at
    the top level; heading errors, ``bias`` and ``num_basis`` at the top level)."""
    imu = {
        "info": {"name": "old", "keyframes": 10},
        "status": "Solve_Succeeded",
        "success": True,
        "iterations": 12,
        "status_imu_only": "Solve_Succeeded",
        "iterations_imu_only": 7,
        "rounds_imu_only": 1,
        "failed_stage": None,
        "build_seconds": 1.0,
        "solve_seconds": 2.0,
        "solve_seconds_imu_only": 0.5,
        "gp_slam_passes": [{"status": "Solve_Succeeded", "iterations": 12}],
        "errors": {
            "strapdown": {"rmse": 1.0, "max": 2.0},
            "imu_only": {"rmse": 0.1, "max": 0.2},
            "gp_slam": {"rmse": 0.01, "max": 0.02},
        },
        "biases": {"gyro": {}, "acc": {}},
        "hyperparameters": {"sigma_f": 1.0},
        "hyperparameters_source": "given",
        "cost_blocks": {"imu_only": {"imu": {"before": 3.0, "after": 1.0}}, "gp_slam": {}},
        "cost_per_iteration": [1.0],
        "cost_per_iteration_imu_only": [3.0, 1.0],
        "map_decision": "map",
        "flags": [],
    }
    planar = {
        "status": "Solve_Succeeded",
        "success": True,
        "iterations": 9,
        "build_seconds": 1.0,
        "solve_seconds": 1.0,
        "rmse_before": 0.5,
        "max_before": 1.0,
        "rmse_after": 0.05,
        "max_after": 0.1,
        "heading_rms_deg_before": 5.0,
        "heading_rms_deg_after": 0.5,
        "bias": [0.001],
        "hyperparameters": {},
        "num_basis": 120,
        "cost_blocks": {},
        "cost_per_iteration": [],
        "info": {"name": "old planar"},
    }
    for name, data in (("imu", imu), ("planar", planar)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "result.json").write_text(json.dumps(data))
    r = Result.load(tmp_path / "imu")
    assert r.motion == "imu" and (r.rmse_before, r.rmse_after) == (0.1, 0.01)
    assert (
        r.stage("imu_only")["iterations"] == 7 and r.stages_named("gp_slam")[0]["iterations"] == 12
    )
    assert r.stage("imu_only")["cost_blocks"] == {"imu": {"before": 3.0, "after": 1.0}}
    assert r.details["map_decision"] == "map" and r.details["errors"]["strapdown"]["rmse"] == 1.0
    old = {k: planar[k] for k in ("status", "success", "iterations", "build_seconds")}
    old |= {k: planar[k] for k in ("solve_seconds", "rmse_before", "max_before", "rmse_after")}
    old |= {"max_after": 0.1, "hyperparameters": {}, "cost_blocks": {}, "cost_per_iteration": []}
    old["info"] = {
        "two_starts": [{"start": "dead reckoning", "cost": 5.0, "kept": True}],
        "warm_start": [{"samples": 400, "iterations": 9}, {"samples": 800, "iterations": 4}],
    }
    (tmp_path / "translational").mkdir()
    (tmp_path / "translational" / "result.json").write_text(json.dumps(old))
    t = Result.load(tmp_path / "translational")
    assert [s["name"] for s in t.stages] == ["start", "prefix", "prefix"]
    assert t.info["warm_start"] == "growing"
    assert t.stages[2] == {"name": "prefix", "samples": 800, "iterations": 4}
    p = Result.load(tmp_path / "planar")
    assert p.motion == "planar" and p.odometry_bias == [0.001] and p.info["num_basis"] == 120
    assert p.details == {"heading_rms_deg_before": 5.0, "heading_rms_deg_after": 0.5}
