"""Pose odometry of real sequences (casmag.data.realdata.convert with ``motion="pose"``,
``casmag convert SOURCE --motion pose``): exact increments of the true 3-D pose, white
noise, a body-z rotation-rate bias sized for the requested drift, and the magnetometer in
the body frame."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from casmag.cli.main import main
from casmag.data.realdata import (
    Protocol,
    Sequence,
    align,
    convert,
    heading_of_motion,
    load_sequence,
    uniform,
)
from casmag.data.recording import read_recording, write_recording
from casmag.strapdown import (
    dead_reckon_pose,
    euler_from_quat,
    pose_increments,
    quat_conj,
    quat_from_euler,
    quat_log,
    quat_mul,
    rotate,
)

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data" / "magnetic-data" / "invensense"
needs_shared = pytest.mark.skipif(
    not (SHARED / "1-time.csv").is_file(),
    reason=f"real data not found at {SHARED} (../shared beside the repository)",
)


def _world(P):
    """A smooth 3-D field [uT] in a z-up world."""
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    return np.column_stack(
        [
            20 + 6 * np.sin(2.1 * x) * np.cos(1.7 * y) + 2 * z,
            -5 + 5 * np.cos(1.3 * x + 0.4) + 3 * np.sin(2.5 * y),
            -40 + 4 * np.sin(1.9 * x - 1.1 * y) - 3 * z,
        ]
    )


def _posed_sequence(n=2000, rate=50.0):
    """A device carried round a 3-D loop with varying roll, pitch and yaw, its magnetometer
    the world field at its position (world frame, as the loaders give it)."""
    t = np.arange(n) / rate
    P = np.column_stack(
        [1.5 * np.cos(0.13 * t) + 0.2 * np.sin(0.5 * t), np.sin(0.21 * t), 0.3 * np.sin(0.4 * t)]
    )
    Q = quat_from_euler(0.3 * np.sin(0.7 * t), 0.2 * np.cos(0.5 * t), 0.9 * t + np.sin(0.3 * t))
    return Sequence("posed", t, P[:, :2], _world(P), quat=Q, z=P[:, 2]), P, Q


def _planar_sequence(n=2000, rate=50.0):
    t = np.arange(n) / rate
    P = np.column_stack([1.5 * np.cos(0.13 * t) + 0.2 * np.sin(0.5 * t), np.sin(0.21 * t)])
    return Sequence("planar", t, P, _world(np.column_stack([P, np.zeros(n)])))


def _same_rotation(Q1, Q2, atol):
    np.testing.assert_allclose(np.abs(np.sum(Q1 * Q2, axis=1)), 1.0, atol=atol)


def test_pose_convert_of_a_posed_sequence_is_exact_without_noise():
    """Noise-free increments with the recorded bias removed dead-reckon to the truth; the
    body-frame magnetometer turned by the true orientation is the world field; the final
    drift is the one asked for."""
    seq, P, Q = _posed_sequence()
    p = Protocol(motion="pose", drift=0.3, noise=0.0, heading_noise=0.0, seed=4, align=False)
    conv = convert(seq, p)
    a, od = conv.arrays, conv.record["odometry"]
    idx = np.arange(0, P.shape[0], 5)
    assert a["pose"].shape == (idx.size - 1, 7) and a["Y"].shape == (idx.size, 3)
    np.testing.assert_allclose(a["P_true"], P[idx], atol=1e-15)
    _same_rotation(a["q_true"], Q[idx], 1e-12)
    b = od["rotation_rate_bias_per_step"]
    assert b != 0.0
    assert od["rotation_rate_bias_deg_s"] == pytest.approx(np.degrees(b) * 10.0)
    Pd, Qd = dead_reckon_pose(a["pose"], a["P_true"][0], a["q_true"][0], bias_w=[0.0, 0.0, b])
    np.testing.assert_allclose(Pd, a["P_true"], atol=1e-9)
    _same_rotation(Qd, a["q_true"], 1e-9)
    np.testing.assert_allclose(rotate(a["q_true"], a["Y"]), _world(P[idx]), atol=1e-12)
    assert od["final_drift"] == pytest.approx(0.3, rel=1e-3)
    Pb, _ = dead_reckon_pose(a["pose"], a["P_true"][0], a["q_true"][0])
    assert np.linalg.norm(Pb[-1] - a["P_true"][-1]) == pytest.approx(od["final_drift"])
    assert od["rmse"] < od["max"] == pytest.approx(np.linalg.norm(Pb - P[idx], axis=1).max())
    # Deterministic for a seed; the bias's sign drawn from it.
    assert np.array_equal(convert(seq, p).arrays["pose"], a["pose"])
    given = [replace(p, seed=s, heading_rate_bias=0.01) for s in range(6)]
    biases = [convert(seq, q).record["odometry"] for q in given]
    signs = {np.sign(od["rotation_rate_bias_per_step"]) for od in biases}
    assert signs == {-1.0, 1.0}


def test_pose_noise_and_a_given_rate_bias():
    """White noise sigma on each displacement component and heading_noise on each axis of
    the rotation increment, about the body z bias given in rad/s."""
    seq, _, _ = _posed_sequence(n=20000)
    p = Protocol(
        motion="pose",
        step_noise=0.02,
        heading_noise=0.004,
        heading_rate_bias=0.05,
        seed=1,
        align=False,
    )
    conv = convert(seq, p)
    a, od = conv.arrays, conv.record["odometry"]
    b = od["rotation_rate_bias_per_step"]
    assert abs(b) == pytest.approx(0.05 / 10.0)
    assert abs(od["rotation_rate_bias_deg_s"]) == pytest.approx(np.degrees(0.05))
    assert od["noise_per_step"] == 0.02 and od["rotation_noise_per_step"] == 0.004
    U0 = pose_increments(a["P_true"], a["q_true"])
    dp = a["pose"][:, :3] - U0[:, :3]
    assert np.allclose(dp.std(axis=0), 0.02, rtol=0.05) and np.allclose(
        dp.mean(axis=0), 0, atol=1e-3
    )
    rot = quat_log(quat_mul(quat_conj(U0[:, 3:]), a["pose"][:, 3:]))  # noise + bias
    assert np.allclose(rot.std(axis=0), 0.004, rtol=0.05)
    np.testing.assert_allclose(rot.mean(axis=0), [0.0, 0.0, b], atol=2e-4)
    np.testing.assert_allclose(np.linalg.norm(a["pose"][:, 3:], axis=1), 1.0, atol=1e-14)


def test_pose_without_orientation_is_level_along_the_heading_of_motion(tmp_path):
    """A planar sequence with a world-frame magnetometer: z = 0, roll = pitch = 0, yaw the
    heading of motion, the magnetometer R(q)^T times the world field; writes and reads back
    as a pose recording."""
    seq = _planar_sequence()
    conv = convert(seq, Protocol(motion="pose", drift=0.4, seed=2, align=False))
    a = conv.arrays
    P = seq.loc[::5]
    assert np.all(a["P_true"][:, 2] == 0.0)
    np.testing.assert_allclose(a["P_true"][:, :2], P, atol=0)
    euler = euler_from_quat(a["q_true"])
    np.testing.assert_allclose(euler[:, :2], 0.0, atol=1e-12)
    yaw = heading_of_motion(P)
    np.testing.assert_allclose(np.angle(np.exp(1j * (euler[:, 2] - yaw))), 0.0, atol=1e-12)
    np.testing.assert_allclose(rotate(a["q_true"], a["Y"]), seq.mag[::5], atol=1e-12)
    assert conv.record["odometry"]["final_drift"] == pytest.approx(0.4, rel=1e-3)
    write_recording(tmp_path / "r.csv", **a)
    rec = read_recording(tmp_path / "r.csv")
    assert rec.motion == "pose"
    np.testing.assert_allclose(rec.increments, a["pose"], atol=0)


def test_align_and_uniform_keep_the_pose_with_the_positions():
    seq, P, Q = _posed_sequence(n=200)
    late = align(seq, -3)  # magnetometer 3 samples late
    np.testing.assert_array_equal(late.quat, seq.quat[:-3])
    np.testing.assert_array_equal(late.z, seq.z[:-3])
    np.testing.assert_array_equal(late.mag, seq.mag[3:])
    early = align(seq, 4)
    np.testing.assert_array_equal(early.quat, seq.quat[4:])
    np.testing.assert_array_equal(early.z, seq.z[4:])
    # Jittered stamps: the pose on the uniform grid, slerped (at the stamps themselves the
    # recorded orientation).
    rng = np.random.default_rng(0)
    t = seq.t + 0.004 * rng.uniform(-1, 1, seq.t.size)
    jittered = Sequence("j", t, seq.loc, seq.mag, quat=Q, z=P[:, 2])
    u = uniform(jittered)
    assert u.resampled is not None and u.quat.shape == (u.t.size, 4)
    np.testing.assert_allclose(np.linalg.norm(u.quat, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(u.z, np.interp(u.t, t, P[:, 2]), atol=1e-15)
    truth = quat_from_euler(
        0.3 * np.sin(0.7 * u.t), 0.2 * np.cos(0.5 * u.t), 0.9 * u.t + np.sin(0.3 * u.t)
    )
    _same_rotation(u.quat, truth, 1e-5)


@needs_shared
def test_convert_cli_pose_on_a_robot_sequence(tmp_path):
    out = tmp_path / "1.csv"
    res = CliRunner().invoke(
        main,
        ["convert", str(SHARED / "1"), "--motion", "pose", "--no-align", "--out", str(out)],
    )
    assert res.exit_code == 0, res.output
    rec = read_recording(out)
    assert rec.motion == "pose" and rec.increments.shape == (rec.n_samples - 1, 7)
    assert rec.P_true.shape == (rec.n_samples, 3) and np.all(rec.P_true[:, 2] == 0.0)
    np.testing.assert_allclose(euler_from_quat(rec.q_true)[:, :2], 0.0, atol=1e-12)
    seq = load_sequence(SHARED / "1")
    stride = round(seq.rate / 10.0)
    np.testing.assert_allclose(rotate(rec.q_true, rec.Y), seq.mag[::stride], atol=1e-9)
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["protocol"]["motion"] == "pose"
    assert record["odometry"]["final_drift"] == pytest.approx(0.5, rel=1e-3)
