"""Recordings with the 6-DoF pose input (casmag.data.recording): dpx,dpy,dpz,dqw,dqx,dqy,dqz."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from casmag.data.recording import MOTION_COLUMNS, read_recording, write_recording
from casmag.errors import DataError
from casmag.strapdown import quat_conj, quat_exp, quat_mul, quat_normalize, rotate

POSE = ",".join(MOTION_COLUMNS["pose"])
IMU = ",".join(MOTION_COLUMNS["imu"])


def _write(tmp_path: Path, header: str, rows: list[str], name: str = "pose.csv") -> Path:
    path = tmp_path / name
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def _num(value: float) -> str:
    """value in shortest round-trip form."""
    return repr(float(value))


def _error(path: Path) -> str:
    with pytest.raises(DataError) as info:
        read_recording(path)
    msg = str(info.value)
    assert "\n" not in msg and "\r" not in msg
    assert msg.startswith(f"{path}: ")
    return msg


def _increments(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Pose increments (n-1, 7) between consecutive poses: dp = R(q_prev)^T (p - p_prev),
    dq = q_prev^-1 q."""
    dp = rotate(quat_conj(Q[:-1]), np.diff(P, axis=0))
    return np.column_stack([dp, quat_mul(quat_conj(Q[:-1]), Q[1:])])


def _dead_reckon(inc: np.ndarray, p0: np.ndarray, q0: np.ndarray):
    """p_k = p_{k-1} + R(q_{k-1}) dp_k, q_k = q_{k-1} dq_k, one row at a time."""
    P, Q = [np.asarray(p0, dtype=float)], [np.asarray(q0, dtype=float)]
    for row in inc:
        P.append(P[-1] + rotate(Q[-1], row[:3]))
        Q.append(quat_mul(Q[-1], row[3:]))
    return np.array(P), np.array(Q)


def _smooth_trajectory(rng: np.random.Generator, n: int, dt: float):
    """Positions (n, 3) and unit quaternions (n, 4) of a smooth random 6-DoF walk."""
    rate = np.cumsum(0.1 * rng.standard_normal((n, 3)), axis=0) * dt  # rotation per step
    Q = [quat_normalize(rng.standard_normal(4))]
    for k in range(1, n):
        Q.append(quat_normalize(quat_mul(Q[-1], quat_exp(rate[k]))))
    velocity = np.cumsum(0.2 * rng.standard_normal((n, 3)), axis=0)
    P = 10.0 * rng.standard_normal(3) + np.cumsum(velocity * dt, axis=0)
    return P, np.array(Q)


# --------------------------------------------------------------------------- round trip
def test_pose_round_trip_dead_reckons_to_the_truth(tmp_path):
    rng = np.random.default_rng(7)
    n, dt = 300, 0.05
    P, Q = _smooth_trajectory(rng, n, dt)
    inc = _increments(P, Q)
    Y = rng.standard_normal((n, 3))
    path = tmp_path / "pose.csv"
    write_recording(path, np.arange(n) * dt, Y, pose=inc, P_true=P, q_true=Q)
    assert path.read_text().splitlines()[0] == (
        f"t,{POSE},mx,my,mz,x_true,y_true,z_true,qw_true,qx_true,qy_true,qz_true"
    )
    rec = read_recording(path)
    assert rec.motion == "pose" and rec.dim == 3 and rec.notes == ()
    assert rec.increment_names == MOTION_COLUMNS["pose"]
    assert rec.increment_names == ("dpx", "dpy", "dpz", "dqw", "dqx", "dqy", "dqz")
    assert rec.increments.shape == (n - 1, 7)
    np.testing.assert_allclose(rec.increments, inc, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rec.P_true, P)
    np.testing.assert_array_equal(rec.q_true, Q)
    P_dr, Q_dr = _dead_reckon(rec.increments, rec.P_true[0], rec.q_true[0])
    np.testing.assert_allclose(P_dr, P, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Q_dr, Q, rtol=0, atol=1e-9)


def test_write_refuses_a_non_unit_rotation_increment(tmp_path):
    path = tmp_path / "out.csv"
    inc = np.zeros((2, 7))
    inc[:, 3] = [1.0, 1.01]
    with pytest.raises(DataError) as info:
        write_recording(path, np.arange(3.0), np.zeros((3, 3)), pose=inc)
    assert "pose" in str(info.value) and "rotation increment 1" in str(info.value)
    assert not path.exists()


# --------------------------------------------------------------------------- detection
ROWS_POSE = ["0,,,,,,,,1,2,3", "1,0.1,0.2,0.3,1,0,0,0,1,2,3", "2,0.1,0.2,0.3,0.6,0.8,0,0,1,2,3"]
ROWS_IMU = ["0,,,,,,,,1,2,3", "1,1,0,0,0,0.1,0.2,0.3,1,2,3", "2,0.6,0.8,0,0,0.1,0.2,0.3,1,2,3"]


def test_dp_and_dq_columns_are_the_pose_input(tmp_path):
    rec = read_recording(_write(tmp_path, f"t,{POSE},mx,my,mz", ROWS_POSE))
    assert rec.motion == "pose" and rec.dim == 3
    np.testing.assert_array_equal(
        rec.increments, [[0.1, 0.2, 0.3, 1, 0, 0, 0], [0.1, 0.2, 0.3, 0.6, 0.8, 0, 0]]
    )


def test_dq_and_dv_columns_are_the_imu_input(tmp_path):
    rec = read_recording(_write(tmp_path, f"t,{IMU},mx,my,mz", ROWS_IMU))
    assert rec.motion == "imu" and rec.increment_names == MOTION_COLUMNS["imu"]


def test_dp_dq_and_dv_columns_are_mixed_inputs(tmp_path):
    header = f"t,{POSE},dvx,dvy,dvz,mx,my,mz"
    rows = ["0" + ",0" * 10 + ",1,2,3", "1,0,0,0,1,0,0,0,0,0,0,1,2,3"]
    msg = _error(_write(tmp_path, header, rows))
    assert "mixed motion inputs" in msg and "give exactly one" in msg
    assert "imu (dqw, dqx, dqy, dqz, dvx, dvy, dvz)" in msg
    assert "pose (dpx, dpy, dpz, dqw, dqx, dqy, dqz)" in msg


def test_dq_columns_alone_name_what_both_inputs_lack(tmp_path):
    rows = ["0,1,0,0,0,1,2,3", "1,1,0,0,0,1,2,3"]
    msg = _error(_write(tmp_path, "t,dqw,dqx,dqy,dqz,mx,my,mz", rows))
    assert msg.endswith(
        "incomplete imu input (missing columns dvx, dvy, dvz) or pose input (missing "
        "columns dpx, dpy, dpz) (have dqw, dqx, dqy, dqz)"
    )


def test_incomplete_pose_input_names_the_missing_column(tmp_path):
    rows = ["0,0,0,1,0,0,0,1,2,3", "1,0,0,1,0,0,0,1,2,3"]
    msg = _error(_write(tmp_path, "t,dpx,dpy,dqw,dqx,dqy,dqz,mx,my,mz", rows))
    assert msg.endswith(
        "incomplete pose input: missing column dpz (have dpx, dpy, dqw, dqx, dqy, dqz)"
    )
    msg = _error(_write(tmp_path, "t,dpx,dpy,dpz,mx,my,mz", ["0,0,0,0,1,2,3"] * 2))
    assert "incomplete pose input: missing columns dqw, dqx, dqy, dqz" in msg


def test_dq_columns_with_a_translation_input_are_mixed(tmp_path):
    rows = ["0,0,0,1,0,0,0,1,2,3", "1,0,0,1,0,0,0,1,2,3"]
    msg = _error(_write(tmp_path, "t,dx,dy,dqw,dqx,dqy,dqz,mx,my,mz", rows))
    assert "mixed motion inputs: translation (dx, dy) and imu or pose (dqw, dqx, dqy, dqz)" in msg


def test_no_motion_input_lists_the_pose_input(tmp_path):
    msg = _error(_write(tmp_path, "t,mx,my,mz", ["0,1,2,3", "1,1,2,3"]))
    assert msg.endswith(
        "no motion input: expected one of dx,dy | dfwd,dleft,dyaw | dqw,...,dvz | dpx,...,dqz"
    )


# --------------------------------------------------------------------------- values
def test_a_non_unit_rotation_increment_is_refused(tmp_path):
    rows = [*ROWS_POSE, "3,0.1,0.2,0.3,0.6,0.8,0.1,0,1,2,3"]
    msg = _error(_write(tmp_path, f"t,{POSE},mx,my,mz", rows))
    assert "row 5, column 'dqw'" in msg
    assert "pose rotation increment (dqw, dqx, dqy, dqz) has norm 1.00499" in msg
    assert "expected 1 within 0.001" in msg


def test_a_rotation_increment_within_tolerance_is_normalised(tmp_path):
    rows = [*ROWS_POSE, "3,0.1,0.2,0.3,0,0,0,1.0009", "4,0,0,0,0.9992,0,0,0"]
    rows = [r + ",1,2,3" if r.count(",") == 7 else r for r in rows]
    rec = read_recording(_write(tmp_path, f"t,{POSE},mx,my,mz", rows))
    np.testing.assert_array_equal(rec.increments[2:, 3:], [[0, 0, 0, 1], [1, 0, 0, 0]])
    np.testing.assert_array_equal(rec.increments[2, :3], [0.1, 0.2, 0.3])


def test_a_first_row_that_is_not_a_rotation_is_ignored(tmp_path):
    rows = ["0,5,5,5,0,0,0,0,1,2,3", *ROWS_POSE[1:]]
    rec = read_recording(_write(tmp_path, f"t,{POSE},mx,my,mz", rows))
    assert rec.increments.shape == (2, 7)


def test_resolution_is_checked_on_the_displacements(tmp_path):
    rows = [*ROWS_POSE, "3,1e12,0.2,0.3,1,0,0,0,1,2,3"]
    msg = _error(_write(tmp_path, f"t,{POSE},mx,my,mz", rows))
    assert "row 5, column 'dpx'" in msg and "beyond what the numerics can carry" in msg


def test_rotation_columns_are_not_resolution_checked(tmp_path):
    # dqx: median step 1e-14 and a sum near 0.8, beyond RESOLUTION were it a displacement
    rows = [ROWS_POSE[0]] + [f"{k},0.1,0.2,0.3,1,1e-14,0,0,1,2,3" for k in range(1, 5)]
    rows.append("5,0.1,0.2,0.3,0.6,0.8,0,0,1,2,3")
    rec = read_recording(_write(tmp_path, f"t,{POSE},mx,my,mz", rows))
    assert rec.increments.shape == (5, 7)


# --------------------------------------------------------------------------- rows merged
def test_pose_increments_of_one_time_stamp_are_composed(tmp_path):
    rng = np.random.default_rng(3)
    P = rng.standard_normal((4, 3))
    Q = quat_normalize(rng.standard_normal((4, 4)))
    inc = _increments(P, Q)
    times = [0.0, 1.0, 1.0, 2.0]  # rows 2 and 3 of the data share a time stamp
    rows = [f"0,{',' * 6},1,2,3"] + [
        ",".join(map(_num, [times[k + 1], *inc[k], 1.0, 2.0, 3.0 + k])) for k in range(3)
    ]
    rec = read_recording(_write(tmp_path, f"t,{POSE},mx,my,mz", rows))
    np.testing.assert_array_equal(rec.t, [0.0, 1.0, 2.0])
    composed = _increments(P[[0, 2]], Q[[0, 2]])[0]  # the pose change from row 1 to row 3
    np.testing.assert_allclose(rec.increments[0], composed, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rec.increments[1], inc[2], rtol=0, atol=1e-12)
    assert np.abs(composed[:3] - (inc[0, :3] + inc[1, :3])).max() > 0.1  # not a sum
    np.testing.assert_allclose(rec.Y[1], [1.0, 2.0, 3.5])
    assert [n["check"] for n in rec.notes] == ["duplicate_time"]
    assert "motion increments composed" in rec.notes[0]["reason"]
    P_dr, Q_dr = _dead_reckon(rec.increments, P[0], Q[0])
    np.testing.assert_allclose(P_dr, P[[0, 2, 3]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(Q_dr, Q[[0, 2, 3]], rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- two rates
OMEGA = np.array([0.3, -0.2, 0.7])  # body rate [rad/s]
V_BODY = np.array([1.0, 0.2, -0.1])  # body velocity [m/s]


def _helix(t: np.ndarray, p0: np.ndarray, q0: np.ndarray):
    """Poses at times t of constant body rate OMEGA and body velocity V_BODY from (p0, q0):
    q(t) = q0 exp(OMEGA t), p(t) = p0 + R(q0) r(t) with r' = R(exp(OMEGA t)) V_BODY."""
    w = np.linalg.norm(OMEGA)
    axis = OMEGA / w
    v_par = axis * (axis @ V_BODY)
    v_perp = V_BODY - v_par
    r = (
        np.outer(t, v_par)
        + np.outer(np.sin(w * t) / w, v_perp)
        + np.outer((1 - np.cos(w * t)) / w, np.cross(axis, v_perp))
    )
    Q = quat_mul(q0, quat_exp(np.outer(t, OMEGA)))
    return p0 + rotate(q0, r), Q


def test_pose_at_two_rates_is_brought_to_the_magnetometer_rows(tmp_path):
    rng = np.random.default_rng(11)
    p0, q0 = rng.standard_normal(3), quat_normalize(rng.standard_normal(4))
    # Times as n / 70 s: motion rows at 10 Hz (n = 7 j), magnetometer rows at 7 Hz
    # (n = 10 k); both on one row every second.
    motion_n, mag_n = set(range(0, 281, 7)), set(range(0, 281, 10))
    n_all = np.array(sorted(motion_n | mag_n))
    t_all = n_all / 70.0
    P, Q = _helix(t_all, p0, q0)
    motion_rows = np.array([n in motion_n for n in n_all])
    inc = _increments(P[motion_rows], Q[motion_rows])
    rows, j = [], 0
    for i, n in enumerate(n_all):
        fields = [_num(t_all[i])]
        if n in motion_n:
            fields += [""] * 7 if j == 0 else [_num(v) for v in inc[j - 1]]
            j += 1
        else:
            fields += [""] * 7
        if n in mag_n:
            fields += ["1", "2", "3", *map(_num, P[i]), *map(_num, Q[i])]
        else:
            fields += [""] * 10
        rows.append(",".join(fields))
    header = f"t,{POSE},mx,my,mz,x_true,y_true,z_true,qw_true,qx_true,qy_true,qz_true"
    rec = read_recording(_write(tmp_path, header, rows))

    t_mag = np.array(sorted(mag_n)) / 70.0
    np.testing.assert_array_equal(rec.t, t_mag)
    assert rec.motion == "pose" and rec.increments.shape == (t_mag.size - 1, 7)
    assert [n["check"] for n in rec.notes] == ["resampled"]
    assert "odometry on 40 rows and magnetometer on 29" in rec.notes[0]["reason"]
    np.testing.assert_allclose(np.linalg.norm(rec.increments[:, 3:], axis=1), 1.0, atol=1e-15)
    P_dr, Q_dr = _dead_reckon(rec.increments, rec.P_true[0], rec.q_true[0])
    # Slerp between the 10 Hz orientations is exact for a constant rate.
    np.testing.assert_allclose(Q_dr, rec.q_true, rtol=0, atol=1e-9)
    # Each position is the linear interpolation of the path between two motion rows
    # dt = 0.1 s apart, off by at most dt^2 / 8 max|p''| = dt^2 / 8 |OMEGA x V_BODY|
    # (1.0e-3 m); the increments re-express it exactly, so nothing accumulates.
    bound = 0.1**2 / 8 * np.linalg.norm(np.cross(OMEGA, V_BODY))
    error = np.linalg.norm(P_dr - rec.P_true, axis=1)
    assert error.max() <= bound + 1e-9
    assert error.max() > 0.5 * bound  # the rows between motion rows are interpolated
    np.testing.assert_allclose(error[::7], 0.0, atol=1e-9)  # the rows shared with motion
