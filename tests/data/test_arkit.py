"""Handheld recordings with the device's pose (casmag.data.realdata.load_arkit, ``casmag convert
X.mat``): frame conventions checked where the path crosses itself, the publishing paper's
odometry protocol, and errors that name the file and the field."""

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from casmag.cli.main import main
from casmag.data.realdata import (
    ARKIT_SENSOR_TO_BODY_DEG,
    arkit_protocol,
    convert,
    crossing_disagreement,
    load_arkit,
    planar_dead_reckoning,
)
from casmag.data.recording import read_recording
from casmag.errors import DataError
from casmag.strapdown import dead_reckon_pose, pose_increments, quat_conj, rotate

ROOT = Path(__file__).resolve().parents[2]
ARKIT = ROOT.parent / "shared" / "data" / "arkit"
needs_arkit = pytest.mark.skipif(
    not (ARKIT / "square.mat").is_file(),
    reason=f"handheld recordings not found at {ARKIT} (../shared beside the repository)",
)


def _world_field(P):
    """A smooth field [uT] in a z-up world."""
    x, y = P[:, 0], P[:, 1]
    return np.column_stack(
        [20 + 6 * np.sin(2.1 * x) * np.cos(1.7 * y), -5 + 5 * np.cos(1.3 * x), -40 + 3 * y]
    )


def _synthetic_mat(path, n=400, rate=10.0, seed=0):
    """A device walked twice round a loop, held with a varying tilt and yaw, its
    magnetometer the world field seen in sensor axes (turned by -ARKIT_SENSOR_TO_BODY_DEG
    about z from the pose's axes)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    a = 2 * np.pi * 2 * t / t[-1]
    P = np.column_stack([2 * np.cos(a), np.sin(a), 0.05 * np.sin(3 * a)])
    yaw = a + np.pi / 2 + 0.2 * np.sin(5 * a)
    R = Rotation.from_euler("ZYX", np.column_stack([yaw, 0.2 * np.sin(a), 0.1 * np.cos(2 * a)]))
    world = _world_field(P)
    body = R.inv().apply(world)
    turn = np.radians(ARKIT_SENSOR_TO_BODY_DEG)
    c, s = np.cos(turn), np.sin(turn)
    A = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    sensor = body @ A  # A^T body per row
    q = R.as_quat()[:, [3, 0, 1, 2]]
    m = sensor + 0.01 * rng.standard_normal(sensor.shape)
    scipy.io.savemat(path, {"t": t, "dPos": np.diff(P, axis=0), "quat": q, "m": m})
    return P, yaw, world


def test_load_arkit_undoes_the_pose_and_the_sensor_axes(tmp_path):
    P, yaw, world = _synthetic_mat(tmp_path / "walk.mat")
    seq = load_arkit(tmp_path / "walk.mat")
    np.testing.assert_allclose(seq.loc, P[:, :2] - P[0, :2], atol=1e-12)  # from the origin
    np.testing.assert_allclose(seq.mag, world, atol=0.05)
    np.testing.assert_allclose(np.angle(np.exp(1j * (seq.heading - yaw))), 0.0, atol=1e-9)


def test_convert_follows_the_publishing_protocol(tmp_path):
    """Heading-rate bias 0.005 rad/s, noise 0.01 m and 0.01 rad per step; without noise and
    bias the increments dead-reckon back to the truth along the device's heading, and the
    planar magnetometer is the world field turned by the heading."""
    P, yaw, world = _synthetic_mat(tmp_path / "walk.mat")
    seq = load_arkit(tmp_path / "walk.mat")
    conv = convert(seq, arkit_protocol(seed=3))
    od = conv.record["odometry"]
    assert abs(od["heading_rate_bias_per_step"]) * conv.record["rate"] == pytest.approx(0.005)
    assert od["noise_per_step"] == 0.01 and od["heading_noise_per_step"] == 0.01
    clean = convert(seq, arkit_protocol(heading_rate_bias=0.0, step_noise=0.0, heading_noise=0.0))
    U = clean.arrays["planar"]
    np.testing.assert_allclose(planar_dead_reckoning(U, P[0, :2], yaw[0]), P[:, :2], atol=1e-9)
    c, s = np.cos(yaw), np.sin(yaw)
    Y = clean.arrays["Y"]
    turned = np.column_stack([c * Y[:, 0] - s * Y[:, 1], s * Y[:, 0] + c * Y[:, 1], Y[:, 2]])
    np.testing.assert_allclose(turned, world, atol=0.05)
    # A final drift asked for replaces the bias: found by bisection as for other sequences.
    drifted = convert(seq, arkit_protocol(seed=3, drift=2.0))
    assert drifted.record["odometry"]["final_drift"] == pytest.approx(2.0, rel=1e-3)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.pop("quat"), "no field 'quat'"),
        (lambda d: d.update(m=d["m"][:-1]), "field 'm' has 399 rows, expected 400"),
        (lambda d: d.update(quat=2 * d["quat"]), "field 'quat' row 1 is not a unit quaternion"),
        (lambda d: d["m"].__setitem__((5, 1), np.nan), "field 'm' row 6 has a non-finite value"),
    ],
)
def test_load_arkit_errors_name_the_file_and_the_field(tmp_path, change, message):
    _synthetic_mat(tmp_path / "walk.mat")
    d = {k: v for k, v in scipy.io.loadmat(tmp_path / "walk.mat", squeeze_me=True).items()}
    d = {k: np.array(v, dtype=float) for k, v in d.items() if not k.startswith("__")}
    change(d)
    scipy.io.savemat(tmp_path / "bad.mat", d)
    with pytest.raises(DataError, match=r"bad\.mat") as e:
        load_arkit(tmp_path / "bad.mat")
    assert message in str(e.value)


def test_convert_cli_on_a_mat_file(tmp_path):
    _synthetic_mat(tmp_path / "walk.mat")
    out = tmp_path / "walk.csv"
    res = CliRunner().invoke(main, ["convert", str(tmp_path / "walk.mat"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    rec = read_recording(out)
    assert rec.motion == "planar" and rec.yaw_true is not None and rec.Y.shape == (400, 3)
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["protocol"]["heading_rate_bias"] == 0.005 and "clock" not in record
    res = CliRunner().invoke(main, ["convert", str(tmp_path / "none.mat"), "--out", str(out)])
    assert res.exit_code != 0 and "none.mat: file not found" in res.output


@needs_arkit
@pytest.mark.parametrize("name", ["square", "library"])
def test_shared_handheld_recordings_agree_with_themselves_where_the_path_crosses(name):
    """The chosen sensor-to-pose rotation makes the world field agree with itself where the
    path crosses itself, better than any other quarter turn or the transposed pose."""
    seq = load_arkit(ARKIT / f"{name}.mat")
    chosen, pairs = crossing_disagreement(seq.loc, seq.mag)
    assert pairs > 1000
    d = scipy.io.loadmat(ARKIT / f"{name}.mat", squeeze_me=True)
    R = Rotation.from_quat(d["quat"][:, [1, 2, 3, 0]]).as_matrix()
    P = np.vstack([np.zeros(3), np.cumsum(d["dPos"], axis=0)])[:, :2]
    for inverse in (False, True):
        Rm = np.transpose(R, (0, 2, 1)) if inverse else R
        for deg in (0.0, 90.0, -90.0, 180.0):
            if deg == ARKIT_SENSOR_TO_BODY_DEG and not inverse:
                continue
            c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
            A = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            M = np.einsum("kij,jl,kl->ki", Rm, A, d["m"])
            other, _ = crossing_disagreement(P, M)
            assert chosen < 0.75 * other, (deg, inverse, chosen, other)


def test_load_arkit_gives_the_3d_pose_and_the_body_frame_magnetometer(tmp_path):
    """Heights from the cumulative increments, the recorded orientation, and R(q)^T times
    the world field is the magnetometer turned from the sensor's into the pose's axes."""
    P, _, _ = _synthetic_mat(tmp_path / "walk.mat")
    d = scipy.io.loadmat(tmp_path / "walk.mat", squeeze_me=True)
    seq = load_arkit(tmp_path / "walk.mat")
    np.testing.assert_allclose(seq.z, P[:, 2] - P[0, 2], atol=1e-12)
    np.testing.assert_allclose(seq.quat, d["quat"], atol=1e-12)
    turn = np.radians(ARKIT_SENSOR_TO_BODY_DEG)
    c, s = np.cos(turn), np.sin(turn)
    body = d["m"] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    np.testing.assert_allclose(rotate(quat_conj(seq.quat), seq.mag), body, atol=1e-12)
    conv = convert(seq, arkit_protocol(motion="pose", step_noise=0.0, heading_noise=0.0))
    np.testing.assert_allclose(conv.arrays["Y"], body, atol=1e-12)
    od = conv.record["odometry"]
    assert abs(od["rotation_rate_bias_per_step"]) * conv.record["rate"] == pytest.approx(0.005)


@needs_arkit
def test_convert_cli_pose_on_the_shared_square(tmp_path):
    """``--motion pose`` on a handheld recording: a pose recording whose true increments
    dead-reckon to the truth and whose body-frame magnetometer, turned back by the true
    orientation, agrees with itself where the path crosses (better than without the
    rotation or with its transpose): the frame convention of the pose input."""
    out = tmp_path / "square.csv"
    res = CliRunner().invoke(
        main, ["convert", str(ARKIT / "square.mat"), "--motion", "pose", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    rec = read_recording(out)
    record = json.loads(out.with_suffix(".json").read_text())
    n = rec.n_samples
    assert rec.motion == "pose" and rec.increments.shape == (n - 1, 7)
    assert rec.P_true.shape == (n, 3) and rec.q_true.shape == (n, 4)
    assert np.ptp(rec.P_true[:, 2]) > 0.05  # the recorded heights, not a plane
    od = record["odometry"]
    assert abs(od["rotation_rate_bias_per_step"]) * record["rate"] == pytest.approx(0.005)
    assert od["noise_per_step"] == 0.01 and od["rotation_noise_per_step"] == 0.01
    P, _ = dead_reckon_pose(pose_increments(rec.P_true, rec.q_true), rec.P_true[0], rec.q_true[0])
    np.testing.assert_allclose(P, rec.P_true, atol=1e-9)
    world, pairs = crossing_disagreement(rec.P_true[:, :2], rotate(rec.q_true, rec.Y))
    assert pairs > 1000 and world < 2.5  # measured 1.83 uT
    for other in (rec.Y, rotate(quat_conj(rec.q_true), rec.Y)):
        assert world < 0.75 * crossing_disagreement(rec.P_true[:, :2], other)[0]
