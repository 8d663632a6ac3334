"""TUM trajectory files: every saved result writes them, and evo (the trajectory tool robotics
users evaluate with) reads them back to casmag's own errors."""

import warnings

import numpy as np
import pytest
from small_problems import planar_room_field, tiny_imu, tiny_walk

import casmag
from casmag.data.imusim import simulate_planar
from casmag.data.recording import write_recording
from casmag.problem.imu import load_imu_problem
from casmag.result import TUM_FILES
from casmag.solver.imu import solve_imu

with warnings.catch_warnings():  # evo's own imports (pandas, seaborn) may warn
    warnings.simplefilter("ignore")
    from evo.core import metrics, sync
    from evo.tools import file_interface


def evo_ape_rmse(reference, estimate):
    """evo's absolute position error (translation part, no alignment), RMSE."""
    ref = file_interface.read_tum_trajectory_file(str(reference))
    est = file_interface.read_tum_trajectory_file(str(estimate))
    ref, est = sync.associate_trajectories(ref, est)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return ape.get_statistic(metrics.StatisticsType.rmse), ref, est


def _imu_result():
    """The desk rectangle's IMU-only adjustment (no map: a few seconds); its estimate is
    that adjustment, at the keyframes."""
    return solve_imu(load_imu_problem(tiny_imu(gp={"form": "none"})))


def _planar_result(tmp_path):
    d = simulate_planar(4, planar_room_field(), size=(2.0, 1.5), loops=1, disp_noise=0.002)
    rec = tmp_path / "walk.csv"
    write_recording(rec, d.t, d.Y, planar=d.U, P_true=d.P, yaw_true=d.psi)
    return casmag.slam(rec), d


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tum")
    planar, planar_data = _planar_result(tmp)
    out = {
        "translational": casmag.solve(tiny_walk()),
        "planar": planar,
        "imu": _imu_result(),
    }
    for name, r in out.items():
        assert r.success, (name, r.status)
        r.save(tmp / name, figures=False)
    return tmp, out, planar_data


@pytest.mark.parametrize("motion", ["translational", "planar", "imu"])
def test_evo_ape_on_the_tum_files_equals_rmse_after(results, motion):
    tmp, out, _ = results
    r = out[motion]
    folder = tmp / motion
    rmse, ref, est = evo_ape_rmse(folder / "truth.tum", folder / "trajectory.tum")
    assert ref.num_poses == est.num_poses == r.arrays["P_estimate"].shape[0]
    # The IMU result without a map has no rmse_after: its estimate is the IMU-only adjustment.
    after = r.rmse_after if motion != "imu" else r.details["errors"]["imu_only"]["rmse"]
    assert rmse == pytest.approx(after, rel=1e-12)
    # The dead reckoning (IMU: the IMU-only adjustment) is the "before".
    before = folder / ("imu_only.tum" if motion == "imu" else "odometry.tum")
    assert evo_ape_rmse(folder / "truth.tum", before)[0] == pytest.approx(r.rmse_before, rel=1e-12)
    if motion == "imu":  # the strapdown integration too
        strapdown = r.details["errors"]["strapdown"]["rmse"]
        assert evo_ape_rmse(folder / "truth.tum", folder / "strapdown.tum")[0] == pytest.approx(
            strapdown, rel=1e-12
        )


def test_every_trajectory_of_a_result_has_its_file(results):
    tmp, out, _ = results
    for motion, r in out.items():
        written = {p.name for p in (tmp / motion).glob("*.tum")}
        expected = {name for key, name in TUM_FILES.items() if r.arrays.get(key) is not None}
        assert written == expected, motion


def test_orientations_are_the_models_own(results):
    """IMU: the estimated quaternions (TUM order x y z w); planar: the heading as a rotation
    about z; translational: identity."""
    tmp, out, planar_data = results
    imu = np.loadtxt(tmp / "imu" / "trajectory.tum")
    Q = out["imu"].arrays["Q_estimate"]
    np.testing.assert_array_equal(imu[:, 4:], np.column_stack([Q[:, 1:], Q[:, 0]]))
    truth = np.loadtxt(tmp / "planar" / "truth.tum")
    yaw = 2.0 * np.arctan2(truth[:, 6], truth[:, 7])
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - planar_data.psi))), 0.0, atol=1e-12)
    np.testing.assert_array_equal(truth[:, 4:6], 0.0)
    trans = np.loadtxt(tmp / "translational" / "trajectory.tum")
    np.testing.assert_array_equal(trans[:, 4:], np.tile([0.0, 0.0, 0.0, 1.0], (len(trans), 1)))
    np.testing.assert_array_equal(trans[:, 3], 0.0)  # 2-D positions: z = 0
