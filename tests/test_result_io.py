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
    from casmag.recslam import slam, slam_sessions

    assert casmag.slam is slam and casmag.slam_sessions is slam_sessions
    assert {"solve", "slam", "slam_sessions", "load_problem", "Result"} <= set(casmag.__all__)


def test_every_result_class_is_loaded_back_and_load_result_tells_them_apart(tmp_path):
    from small_problems import planar_room_field

    from casmag.imuconfig import load_imu_problem
    from casmag.imusim import simulate_planar
    from casmag.imuslam import ImuResult, solve_imu
    from casmag.planar import PlanarResult, solve_planar

    d = simulate_planar(4, planar_room_field(), size=(2.0, 1.5), loops=1, disp_noise=0.002)
    planar = solve_planar(*d.U.T, d.Y, t=d.t, truth={"P": d.P, "psi": d.psi})
    planar.save(tmp_path / "planar", figures=False)
    tiny = ["simulation.scenario.loops=1", "model.gp.form=none"]
    imu = solve_imu(load_imu_problem("problems/imu/rectangle.yaml", tiny))
    imu.save(tmp_path / "imu", figures=False)
    for folder, cls, original in (("planar", PlanarResult, planar), ("imu", ImuResult, imu)):
        back = casmag.load_result(tmp_path / folder)
        assert type(back) is cls and back.status == original.status
        assert back.verdict == original.verdict
        np.testing.assert_array_equal(back.arrays["P_estimate"], original.arrays["P_estimate"])
        assert type(cls.load(tmp_path / folder)) is cls
        with pytest.raises(DataError, match=f"a {folder} result; read it with"):
            Result.load(tmp_path / folder)
