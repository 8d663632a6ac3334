"""ROS bags in (casmag.data.rosbag, ``casmag convert BAG``): bags written here with rosbags
from a known trajectory and field read back as the same recording; IMU messages integrated
into increments that casmag's strapdown turns back into the known motion; the command's
listing, errors and output; a converted bag solved as its CSV twin is."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from threadpoolctl import threadpool_limits

pytest.importorskip("rosbags")

import casmag
from casmag.cli.main import main
from casmag.data.recording import read_recording, write_recording
from casmag.data.rosbag import (
    MAG_UNIT_SCALE,
    imu_increments,
    list_topics,
    read_bag,
    wrap_angle,
)
from casmag.data.simulate import simulate_problem
from casmag.errors import DataError
from casmag.strapdown import (
    gravity_vector,
    quat_angle,
    quat_conj,
    quat_exp,
    quat_from_euler,
    quat_mul,
    rotate,
    strapdown,
)

ROOT = Path(__file__).resolve().parents[2]
EPOCH = 1_700_000_000 * 10**9
"""A header stamp origin [ns] far from zero, as real bags have (2023)."""
REL = 1e-9


# --------------------------------------------------------------------------- writing bags
def _typestore(ros: int):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)


class _Msgs:
    """Message builders of one typestore (ROS 1 headers carry a sequence number)."""

    def __init__(self, ros: int):
        self.ros, self.ts = ros, _typestore(ros)
        self.T = self.ts.types

    def header(self, ns: int, frame: str = "sensor"):
        H = self.T["std_msgs/msg/Header"]
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        extra = {"seq": 0} if "seq" in H.__dataclass_fields__ else {}
        return H(stamp=stamp, frame_id=frame, **extra)

    def vec(self, v):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def pose(self, p, q):
        G = self.T
        return G["geometry_msgs/msg/Pose"](
            position=G["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=G["geometry_msgs/msg/Quaternion"](
                x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])
            ),
        )

    def magnetic_field(self, ns, b):
        return self.T["sensor_msgs/msg/MagneticField"](
            header=self.header(ns),
            magnetic_field=self.vec(b),
            magnetic_field_covariance=np.zeros(9),
        )

    def odometry(self, ns, p, q):
        G = self.T
        return G["nav_msgs/msg/Odometry"](
            header=self.header(ns, "odom"),
            child_frame_id="base",
            pose=G["geometry_msgs/msg/PoseWithCovariance"](
                pose=self.pose(p, q), covariance=np.zeros(36)
            ),
            twist=G["geometry_msgs/msg/TwistWithCovariance"](
                twist=G["geometry_msgs/msg/Twist"](
                    linear=self.vec((0, 0, 0)), angular=self.vec((0, 0, 0))
                ),
                covariance=np.zeros(36),
            ),
        )

    def pose_stamped(self, ns, p, q):
        return self.T["geometry_msgs/msg/PoseStamped"](
            header=self.header(ns, "world"), pose=self.pose(p, q)
        )

    def imu(self, ns, w, a):
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(ns),
            orientation=self.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9),
            angular_velocity=self.vec(w),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=self.vec(a),
            linear_acceleration_covariance=np.zeros(9),
        )

    def string(self, text):
        return self.T["std_msgs/msg/String"](data=text)


def _write_bag(path: Path, ros: int, topics: dict, seed: int = 0) -> Path:
    """A bag at path (ROS 1: path.bag, ROS 2: the folder path) holding topics: name ->
    (message type, [(stamp ns, message), ...]). Each message is recorded 0-20 ms after its
    stamp (a seeded delay), so that reading by record time would be caught."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2

    rng = np.random.default_rng(seed)
    ts = _typestore(ros)
    if ros == 1:
        path, writer = path.with_suffix(".bag"), Writer1(path.with_suffix(".bag"))
        serialize = ts.serialize_ros1
    else:
        writer, serialize = Writer2(path, version=9), ts.serialize_cdr
    with writer:
        for topic, (msgtype, messages) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            for ns, msg in messages:
                delay = int(rng.integers(0, 20_000_000))
                writer.write(conn, ns + delay, serialize(msg, msgtype))
    return path


def _yaw_quat(yaw):
    """(n, 4) quaternions (w first) of headings [rad] about z."""
    yaw = np.asarray(yaw, dtype=float)
    return np.column_stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)])


# --------------------------------------------------------------------------- a planar loop
def _loop(seed: int = 4, n: int = 121, hz: float = 20.0):
    """A loop over 3 m x 2 m (0.1 m up and down) in 6 s sampled at ``hz``: stamps (n,) [ns];
    the true pose P (n, 3) [m], yaw (n,) [rad, heading of motion, through +-pi]; an odometry
    that drifts from it (seeded random walks of 1 cm and 0.01 rad per step); a made-up field
    B (n, 3) [T] at the true positions with 0.05 uT noise."""
    rng = np.random.default_rng(seed)
    s = 2 * math.pi * np.arange(n) / (n - 1)
    P = np.column_stack([1.5 * np.cos(s), np.sin(s), 0.1 * np.sin(2 * s)])
    yaw = np.arctan2(np.cos(s), -1.5 * np.sin(s))  # the tangent's direction
    P_odo = P + np.cumsum(rng.normal(0.0, 0.01, (n, 3)), axis=0)
    yaw_odo = yaw + np.cumsum(rng.normal(0.0, 0.01, n))
    B = 1e-6 * np.column_stack(
        [
            20 + 6 * np.sin(2.1 * P[:, 0]) * np.cos(1.7 * P[:, 1]),
            -5 + 5 * np.cos(1.3 * P[:, 0] + 0.4),
            -40 + 4 * np.sin(1.9 * P[:, 0] - 1.1 * P[:, 1]),
        ]
    )
    B = B + 0.05e-6 * rng.standard_normal(B.shape)
    ns = EPOCH + np.round(np.arange(n) * 1e9 / hz).astype(np.int64)
    return ns, P, yaw, P_odo, yaw_odo, B


def _loop_bag(path: Path, ros: int, mag_every: int = 2):
    """The loop as a bag: /odom (Odometry, every sample), /mag (MagneticField, every
    ``mag_every``-th sample), /truth (PoseStamped, every sample), /chatter (String)."""
    ns, P, yaw, P_odo, yaw_odo, B = _loop()
    m = _Msgs(ros)
    q, q_odo = _yaw_quat(yaw), _yaw_quat(yaw_odo)
    mag = np.arange(0, ns.size, mag_every)
    topics = {
        "/odom": (
            "nav_msgs/msg/Odometry",
            [(int(ns[k]), m.odometry(int(ns[k]), P_odo[k], q_odo[k])) for k in range(ns.size)],
        ),
        "/mag": (
            "sensor_msgs/msg/MagneticField",
            [(int(ns[k]), m.magnetic_field(int(ns[k]), B[k])) for k in mag],
        ),
        "/truth": (
            "geometry_msgs/msg/PoseStamped",
            [(int(ns[k]), m.pose_stamped(int(ns[k]), P[k], q[k])) for k in range(ns.size)],
        ),
        "/chatter": ("std_msgs/msg/String", [(int(ns[0]), m.string("hello"))]),
    }
    return _write_bag(path, ros, topics), mag


def _close(actual, expected, rel=REL):
    """|actual - expected| <= rel x the largest |expected| (elementwise, one scale)."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    scale = max(float(np.abs(expected).max()), 1e-300)
    err = float(np.abs(actual - expected).max())
    assert err <= rel * scale, f"max error {err:.3g} > {rel:g} x {scale:.3g}"


def _planar_dead_reckoning(U):
    """(n, 3) x, y [m], heading [rad] of planar increments from (0, 0, 0) (the reference of
    the recording format: dfwd, dleft in the body frame at the earlier heading)."""
    out = np.zeros((U.shape[0] + 1, 3))
    for k, (f, l, dyaw) in enumerate(U):
        h = out[k, 2]
        out[k + 1] = out[k] + [
            f * math.cos(h) - l * math.sin(h),
            f * math.sin(h) + l * math.cos(h),
            dyaw,
        ]
    return out


@pytest.mark.parametrize("ros", [1, 2])
@pytest.mark.parametrize("motion", ["translational", "translational3", "planar"])
def test_a_bag_reads_back_as_its_arrays(tmp_path, ros, motion):
    """Odometry at 20 Hz, magnetometer at 10 Hz, truth at 20 Hz: the CSV read back gives
    the odometry's dead reckoning (from its first pose, in its frame for planar), the field
    in microtesla and the truth at the magnetometer's stamps, to 1e-9 relative."""
    bag, mag = _loop_bag(tmp_path / "loop", ros)
    ns, P, yaw, P_odo, yaw_odo, B = _loop()
    out = tmp_path / "loop.csv"
    rec_bag = read_bag(bag, "/mag", odometry="/odom", truth="/truth", motion=motion)
    rec_bag.write(out)
    rec = read_recording(out)
    assert rec.motion == ("planar" if motion == "planar" else "translation")
    assert rec.n_samples == mag.size
    _close(rec.t, (ns[mag] - ns[0]) / 1e9)  # header stamps, from the first
    _close(rec.Y, MAG_UNIT_SCALE * B[mag])
    assert 20 < np.median(np.abs(rec.Y[:, 2])) < 50  # microtesla
    if motion == "planar":
        dr = _planar_dead_reckoning(rec.increments)
        c, s = math.cos(yaw_odo[0]), math.sin(yaw_odo[0])
        d = P_odo[mag, :2] - P_odo[0, :2]
        expected = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        _close(dr[:, :2], expected)
        assert np.abs(wrap_angle(dr[:, 2] - (yaw_odo[mag] - yaw_odo[0]))).max() <= REL * math.pi
        assert np.abs(wrap_angle(rec.yaw_true - yaw[mag])).max() <= REL * math.pi
        assert np.all(np.abs(np.diff(rec.yaw_true)) < 1.0)  # unwrapped through +-pi
        _close(rec.P_true, P[mag, :2])
    else:
        dim = 3 if motion == "translational3" else 2
        dr = np.vstack([np.zeros(dim), np.cumsum(rec.increments, axis=0)])
        _close(dr, P_odo[mag, :dim] - P_odo[0, :dim])
        _close(rec.P_true, P[mag, :dim])
    assert [n["check"] for n in rec.notes] == ["resampled"]  # odometry at twice the rate
    record = rec_bag.record
    assert record["format"] == f"ROS {ros}" and record["t0_stamp"] == "1700000000.000000000"
    assert record["topics"]["magnetometer"] == {
        "topic": "/mag",
        "type": "sensor_msgs/msg/MagneticField",
        "messages": mag.size,
        "used": mag.size,
    }


def test_messages_beyond_the_odometry_are_left_out(tmp_path):
    """Magnetometer messages before the first odometry message cannot be placed: left out
    and said; the first row is then the first odometry message (t = 0)."""
    ns, _, _, P_odo, yaw_odo, B = _loop()
    m = _Msgs(2)
    q = _yaw_quat(yaw_odo)
    topics = {
        "/odom": (
            "geometry_msgs/msg/PoseStamped",
            [(int(ns[k]), m.pose_stamped(int(ns[k]), P_odo[k], q[k])) for k in range(10, 60)],
        ),
        "/mag": (
            "sensor_msgs/msg/MagneticField",
            [(int(ns[k]), m.magnetic_field(int(ns[k]), B[k])) for k in range(0, 80, 2)],
        ),
    }
    bag = _write_bag(tmp_path / "b", 2, topics)
    rec_bag = read_bag(bag, "/mag", odometry="/odom")
    assert rec_bag.notes == (
        "15 of 40 magnetometer messages (/mag) before the first or after the last odometry "
        "message were left out",
    )
    rec_bag.write(tmp_path / "b.csv")
    rec = read_recording(tmp_path / "b.csv")
    _close(rec.t, (ns[10:60:2] - ns[10]) / 1e9)
    _close(rec.Y, 1e6 * B[10:60:2])
    _close(np.cumsum(rec.increments, axis=0), P_odo[12:60:2, :2] - P_odo[10, :2])
    assert [n["check"] for n in rec.notes] == ["resampled"]  # odometry at twice the rate


# --------------------------------------------------------------------------- IMU
def _imu_motion(t):
    """A constant body rotation rate w (rad/s) and constant world acceleration a (m/s^2)
    from q0, p0, v0: the true q (n, 4), p (n, 3), v (n, 3) at times t [s] and the IMU's
    angular velocity (n, 3) and specific force (n, 3) in the sensor frame."""
    w = np.array([0.1, -0.2, 0.5])
    a = np.array([0.3, -0.1, 0.05])
    q0 = quat_from_euler(0.1, -0.05, 0.3)
    p0, v0 = np.array([1.0, 2.0, 0.5]), np.array([0.5, 0.2, 0.0])
    q = quat_mul(q0, quat_exp(t[:, None] * w))
    p = p0 + t[:, None] * v0 + 0.5 * t[:, None] ** 2 * a
    v = v0 + t[:, None] * a
    f = rotate(quat_conj(q), a - gravity_vector())  # R(q)^T (a - g)
    return q, p, v, np.tile(w, (t.size, 1)), f


@pytest.mark.parametrize("ros", [1, 2])
def test_imu_increments_integrate_to_the_known_motion(tmp_path, ros):
    """IMU at 100 Hz for 3 s, magnetometer at 40 Hz (a field linear in time), truth at the
    IMU's stamps. The trapezoid rule is exact for a constant rotation rate and a constant
    world-frame acceleration (dq = Exp(w T); R(dq) a_{k+1} = a_k, so dv = T a_k = the
    integral), and so is the strapdown step (Eq. 1) for it: integrating the written dq, dv
    from the first true state must return the true poses up to rounding, 1e-9 m and rad
    (rounding over 300 steps is ~1e-13)."""
    n = 301
    ns = EPOCH + np.arange(n, dtype=np.int64) * 10_000_000
    t = (ns - ns[0]) / 1e9
    q, p, v, W, F = _imu_motion(t)
    ns_mag = EPOCH - 50_000_000 + np.arange(126, dtype=np.int64) * 25_000_000  # -0.05 .. 3.075 s
    tm = (ns_mag - ns[0]) / 1e9
    B0, B1 = np.array([20e-6, -5e-6, -40e-6]), np.array([1e-6, 2e-6, -0.5e-6])
    Bm = B0 + tm[:, None] * B1
    m = _Msgs(ros)
    topics = {
        "/imu": (
            "sensor_msgs/msg/Imu",
            [(int(ns[k]), m.imu(int(ns[k]), W[k], F[k])) for k in range(n)],
        ),
        "/mag": (
            "sensor_msgs/msg/MagneticField",
            [(int(s), m.magnetic_field(int(s), b)) for s, b in zip(ns_mag, Bm, strict=True)],
        ),
        "/truth": (
            "nav_msgs/msg/Odometry",
            [(int(ns[k]), m.odometry(int(ns[k]), p[k], q[k])) for k in range(n)],
        ),
    }
    bag = _write_bag(tmp_path / "imu", ros, topics)
    read_bag(bag, "/mag", imu="/imu", truth="/truth").write(tmp_path / "imu.csv")
    rec = read_recording(tmp_path / "imu.csv")
    assert rec.motion == "imu" and rec.n_samples == n and rec.notes == ()
    _close(rec.t, t)
    _close(rec.Y, 1e6 * (B0 + t[:, None] * B1))  # linear in time: interpolated exactly
    _close(rec.P_true, p)
    assert quat_angle(rec.q_true, q).max() <= REL
    T = float(np.mean(np.diff(rec.t)))
    assert np.ptp(np.diff(rec.t)) < 1e-12
    P, V, Q = strapdown(
        rec.P_true[0], v[0], rec.q_true[0], rec.increments[:, :4], rec.increments[:, 4:], T
    )
    assert np.abs(P - p).max() <= REL
    assert np.abs(V - v).max() <= REL
    assert quat_angle(Q, q).max() <= REL


def test_imu_trapezoid_error_on_a_turning_walk_is_third_order():
    """A walk on a circle, the sensor turning with it (yaw rate w = 0.5 rad/s, speed 1 m/s):
    the specific force is constant in the sensor frame, so the world-frame acceleration
    turns and the trapezoid is no longer exact. Against the exact increments (dq = Exp(w T),
    dv = the integral of R(tau) f), the rotation is exact and the velocity increment is off
    by the trapezoid rule's error on a rotating vector, (w T)^2 / 12 of the horizontal
    force times T (to leading order): at most 1.01 x that bound, and at least half of it
    (the rule is second order, not better)."""
    w, T, speed = 0.5, 0.01, 1.0
    f = np.array([0.0, speed * w, -gravity_vector()[2]])  # centripetal (left) and gravity
    n = 50
    W = np.tile([0.0, 0.0, w], (n, 1))
    A = np.tile(f, (n, 1))
    inc = imu_increments(np.full(n - 1, T), W, A)
    exact_dq = quat_exp(np.array([0.0, 0.0, w * T]))
    assert quat_angle(inc[:, :4], exact_dq).max() <= 1e-15
    # The integral of Rz(w tau) f over [0, T], in closed form.
    s, c = math.sin(w * T), math.cos(w * T)
    exact_dv = np.array([-(1 - c) / w * f[1], s / w * f[1], T * f[2]])
    err = np.abs(inc[:, 4:] - exact_dv).max()
    bound = (w * T) ** 2 / 12 * f[1] * T
    assert 0.5 * bound <= err <= 1.01 * bound, (err, bound)


def test_imu_stamps_shared_by_two_messages_are_averaged(tmp_path):
    """Two IMU messages with one stamp would sum two quaternions in the reader: they are
    averaged into one row, and said."""
    m = _Msgs(2)
    ns = EPOCH + np.array([0, 10, 10, 20, 30], dtype=np.int64) * 1_000_000
    W = np.array([[0, 0, 0.1], [0, 0, 0.2], [0, 0, 0.4], [0, 0, 0.3], [0, 0, 0.3]])
    A = np.tile([0.0, 0.0, 9.81], (5, 1))
    topics = {
        "/imu": (
            "sensor_msgs/msg/Imu",
            [(int(s), m.imu(int(s), w, a)) for s, w, a in zip(ns, W, A, strict=True)],
        ),
        "/mag": (
            "sensor_msgs/msg/MagneticField",
            [(int(s), m.magnetic_field(int(s), [1e-5, 2e-5, 3e-5])) for s in (ns[0], ns[-1])],
        ),
    }
    rec = read_bag(_write_bag(tmp_path / "b", 2, topics), "/mag", imu="/imu")
    assert rec.rows.shape[0] == 4
    assert rec.notes[0].startswith("1 IMU messages (/imu) repeat")
    expected = imu_increments(
        np.full(3, 0.01), np.array([W[0], (W[1] + W[2]) / 2, W[3], W[4]]), A[:4]
    )
    _close(rec.rows[1:, 1:8], expected)


# --------------------------------------------------------------------------- errors
@pytest.fixture(scope="module")
def loop_bags(tmp_path_factory):
    """The loop as a ROS 2 folder and a ROS 1 file."""
    folder = tmp_path_factory.mktemp("bags")
    return {ros: _loop_bag(folder / f"loop{ros}", ros)[0] for ros in (1, 2)}


@pytest.mark.parametrize("ros", [1, 2])
def test_list_topics(loop_bags, ros):
    assert list_topics(loop_bags[ros]) == [
        ("/chatter", "std_msgs/msg/String", 1),
        ("/mag", "sensor_msgs/msg/MagneticField", 61),
        ("/odom", "nav_msgs/msg/Odometry", 121),
        ("/truth", "geometry_msgs/msg/PoseStamped", 121),
    ]


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        (
            {"magnetometer": "/magnet", "odometry": "/odom"},
            "topic '/magnet': not in the bag (the magnetometer topic; the bag has: /chatter "
            "(std_msgs/msg/String), /mag",
        ),
        (
            {"magnetometer": "/odom", "odometry": "/odom"},
            "topic '/odom': is nav_msgs/msg/Odometry; the magnetometer topic must be "
            "sensor_msgs/msg/MagneticField",
        ),
        (
            {"magnetometer": "/mag", "odometry": "/mag"},
            "topic '/mag': is sensor_msgs/msg/MagneticField; the odometry topic must be "
            "nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped",
        ),
        (
            {"magnetometer": "/mag", "imu": "/odom"},
            "topic '/odom': is nav_msgs/msg/Odometry; the imu topic must be sensor_msgs/msg/Imu",
        ),
        (
            {"magnetometer": "/mag", "odometry": "/odom", "truth": "/chatter"},
            "topic '/chatter': is std_msgs/msg/String; the truth topic must be",
        ),
        ({"magnetometer": "/mag"}, "give an odometry topic or an IMU topic (exactly one)"),
        (
            {"magnetometer": "/mag", "odometry": "/odom", "motion": "sideways"},
            "unknown motion 'sideways'",
        ),
    ],
)
def test_bad_topics_are_one_line_naming_the_bag_and_topic(loop_bags, kwargs, needle):
    bag = loop_bags[2]
    with pytest.raises(DataError) as info:
        read_bag(bag, **kwargs)
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{bag}: ") and needle in text, text


def test_empty_topic_and_unreadable_bags(tmp_path):
    m = _Msgs(2)
    topics = {
        "/mag": ("sensor_msgs/msg/MagneticField", []),
        "/odom": (
            "geometry_msgs/msg/PoseStamped",
            [(EPOCH, m.pose_stamped(EPOCH, [0, 0, 0], [1, 0, 0, 0]))],
        ),
    }
    bag = _write_bag(tmp_path / "empty", 2, topics)
    with pytest.raises(
        DataError, match=r"empty: topic '/mag': has no messages \(the magnetometer topic\)"
    ):
        read_bag(bag, "/mag", odometry="/odom")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag")
    with pytest.raises(DataError, match=r"junk\.bag: cannot read the bag \(File magic is invalid"):
        list_topics(junk)
    with pytest.raises(DataError, match=r"none\.bag: not found"):
        list_topics(tmp_path / "none.bag")
    with pytest.raises(DataError, match=r"not a ROS 1 \.bag file or a ROS 2 bag folder"):
        list_topics(tmp_path)


def test_same_stamp_on_every_message_is_refused(tmp_path):
    """Header stamps never set: every message at 0 s would be merged into one row."""
    m = _Msgs(1)
    topics = {
        "/mag": (
            "sensor_msgs/msg/MagneticField",
            [(EPOCH + k, m.magnetic_field(0, [1e-5, 0, 0])) for k in range(3)],
        ),
        "/odom": (
            "geometry_msgs/msg/PoseStamped",
            [(EPOCH + k, m.pose_stamped(k * 10**8, [k, 0, 0], [1, 0, 0, 0])) for k in range(3)],
        ),
    }
    bag = _write_bag(tmp_path / "zero", 1, topics)
    with pytest.raises(
        DataError,
        match=r"topic '/mag': all 3 messages have the same header stamp \(0\.000000000 s\)",
    ):
        read_bag(bag, "/mag", odometry="/odom")


def test_planar_needs_an_orientation(tmp_path):
    m = _Msgs(2)
    topics = {
        "/mag": (
            "sensor_msgs/msg/MagneticField",
            [
                (EPOCH + k * 10**8, m.magnetic_field(EPOCH + k * 10**8, [1e-5, 0, 0]))
                for k in range(3)
            ],
        ),
        "/odom": (
            "geometry_msgs/msg/PoseStamped",
            [
                (EPOCH + k * 10**8, m.pose_stamped(EPOCH + k * 10**8, [k, 0, 0], [0, 0, 0, 0]))
                for k in range(3)
            ],
        ),
    }
    bag = _write_bag(tmp_path / "noq", 2, topics)
    read_bag(bag, "/mag", odometry="/odom")  # translational: positions only
    with pytest.raises(
        DataError,
        match=r"topic '/odom': the pose at stamp 1700000000\.000000000 s has an orientation "
        r"of norm 0",
    ):
        read_bag(bag, "/mag", odometry="/odom", motion="planar")


def test_without_rosbags_the_error_says_how_to_install(loop_bags, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags", None)  # import rosbags raises ImportError
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(DataError, match=r"needs the rosbags package: pip install casmag\[bags\]"):
        list_topics(loop_bags[2])


# --------------------------------------------------------------------------- command line
def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _lines(text):
    return [line for line in text.splitlines() if line.strip()]


@pytest.mark.parametrize("ros", [1, 2])
def test_cli_lists_topics_without_a_magnetometer_topic(loop_bags, tmp_path, ros):
    bag = loop_bags[ros]
    out = tmp_path / "rec.csv"
    for args in ([], ["--out", out], ["--odometry", "/odom", "--out", out]):
        res = _run(["convert", bag, *args])
        assert res.exit_code == 2
        listing = _lines(res.stdout)
        assert listing[0] == f"{bag}: 4 topics"
        assert listing[2].split() == ["/mag", "sensor_msgs/msg/MagneticField", "61"]
        assert listing[3].split() == ["/odom", "nav_msgs/msg/Odometry", "121"]
        err = _lines(res.stderr)
        assert len(err) == 1 and "--magnetometer TOPIC is missing" in err[0], res.stderr
    res = _run(["convert", bag, "--magnetometer", "/mag", "--out", out])
    assert res.exit_code == 2 and len(_lines(res.stdout)) == 5
    assert _lines(res.stderr) == [
        f"casmag: error: {bag}: --odometry TOPIC or --imu TOPIC is missing (a "
        "nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped topic, or a sensor_msgs/msg/Imu "
        "topic); the bag's topics are listed above"
    ]
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--magnetometer", "/magnet", "--odometry", "/odom"], "topic '/magnet': not in the bag"),
        (
            ["--magnetometer", "/mag", "--odometry", "/odom", "--truth", "/gt"],
            "topic '/gt': not in the bag",
        ),
        (["--magnetometer", "/mag", "--imu", "/odom"], "topic '/odom': is nav_msgs/msg/Odometry"),
        (
            ["--magnetometer", "/mag", "--odometry", "/odom", "--drift", "0.5"],
            "--drift: not taken by a ROS bag",
        ),
        (["--magnetometer", "/mag", "--odometry", "/odom", "--imu", "/x"], "--odometry and --imu"),
        (
            ["--magnetometer", "/mag", "--imu", "/x", "--motion", "planar"],
            "--motion planar: not taken with --imu",
        ),
    ],
)
def test_cli_bad_topic_is_one_line_exit_2(loop_bags, tmp_path, args, needle):
    out = tmp_path / "rec.csv"
    res = _run(["convert", loop_bags[2], *args, "--out", out])
    assert res.exit_code == 2
    lines = _lines(res.output)
    assert len(lines) == 1 and needle in lines[0], res.output
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.mark.parametrize("ros", [1, 2])
def test_cli_writes_the_recording(loop_bags, tmp_path, ros):
    out = tmp_path / "rec.csv"
    args = ["--magnetometer", "/mag", "--odometry", "/odom", "--truth", "/truth"]
    res = _run(["convert", loop_bags[ros], *args, "--motion", "planar", "--out", out])
    assert res.exit_code == 0, res.output
    assert _lines(res.stdout) == [
        f"wrote {out}: 121 rows (planar) from 61 magnetometer, 121 odometry, 121 truth "
        "messages, t = 0 at stamp 1700000000.000000000 s"
    ]
    assert res.stderr == ""
    rec = read_recording(out)
    assert rec.motion == "planar" and rec.n_samples == 61 and rec.yaw_true is not None
    direct = read_bag(loop_bags[ros], "/mag", "/odom", truth="/truth", motion="planar")
    assert json.loads(out.with_suffix(".json").read_text()) == direct.record
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.csv", "rec.json"]


def test_cli_bag_flags_are_refused_for_other_sources(tmp_path):
    """convert's other sources keep their behaviour; the bag flags are named when given."""
    res = _run(["convert", tmp_path / "7", "--magnetometer", "/mag", "--out", tmp_path / "x.csv"])
    assert res.exit_code == 2 and "--magnetometer: for ROS bags only" in res.output
    res = _run(
        ["convert", tmp_path / "7", "--motion", "translational3", "--out", tmp_path / "x.csv"]
    )
    assert res.exit_code == 2 and "--motion translational3: for ROS bags only" in res.output
    res = _run(["convert", tmp_path / "7"])
    assert res.exit_code == 2 and "Missing option '--out'" in res.output
    res = _run(["convert", tmp_path / "7", "--out", tmp_path / "x.csv"])
    assert res.exit_code == 2 and "7-time.csv: file not found" in res.output
    assert len(_lines(res.output)) == 1


def test_converted_bag_solves_as_its_csv(tmp_path):
    """A simulated walk (300 samples at 10 Hz) as a ROS 2 bag (odometry poses, the field in
    tesla, truth) and as a CSV written directly from the same arrays (increments
    np.diff(P_odo), field x 1e6, t from the same stamps): casmag slam gives the same
    rmse_after on both (1e-9)."""
    prob = casmag.load_problem(
        ROOT / "problems/bench/walk.yaml",
        ["seed=3", "simulation.trajectory.samples=300", "simulation.trajectory.area=[2.0, 2.0]"],
    )
    data = simulate_problem(prob)
    n = data.n_samples
    ns = EPOCH + np.arange(n, dtype=np.int64) * 100_000_000
    P_odo = np.column_stack(
        [np.vstack([data.anchor, data.anchor + np.cumsum(data.U, axis=0)]), np.zeros(n)]
    )
    P_true = np.column_stack([data.P_true, np.zeros(n)])
    B = 1e-6 * data.Y  # the simulated field, taken as microtesla, in tesla
    m = _Msgs(2)
    one = [1.0, 0.0, 0.0, 0.0]
    topics = {
        "/odom": (
            "nav_msgs/msg/Odometry",
            [(int(ns[k]), m.odometry(int(ns[k]), P_odo[k], one)) for k in range(n)],
        ),
        "/mag": (
            "sensor_msgs/msg/MagneticField",
            [(int(ns[k]), m.magnetic_field(int(ns[k]), B[k])) for k in range(n)],
        ),
        "/truth": (
            "geometry_msgs/msg/PoseStamped",
            [(int(ns[k]), m.pose_stamped(int(ns[k]), P_true[k], one)) for k in range(n)],
        ),
    }
    bag = _write_bag(tmp_path / "walk", 2, topics)
    converted = tmp_path / "converted.csv"
    args = ["--magnetometer", "/mag", "--odometry", "/odom", "--truth", "/truth"]
    assert _run(["convert", bag, *args, "--out", converted]).exit_code == 0
    direct = tmp_path / "direct.csv"
    t = (ns - ns[0]) / 1e9
    write_recording(direct, t, B * 1e6, dxy=np.diff(P_odo[:, :2], axis=0), P_true=P_true[:, :2])
    rmse = []
    # One BLAS thread: both solves do the same arithmetic (the thread count changes the
    # last digits, 1e-8 relative here), and small matrices do not wait on busy cores.
    with threadpool_limits(1):
        for rec in (converted, direct):
            out = tmp_path / f"out-{rec.stem}"
            res = _run(["slam", rec, "--out", out, "-q", "--no-figures"])
            assert res.exit_code == 0, res.output
            rmse.append(json.loads((out / "result.json").read_text())["rmse_after"])
    assert rmse[0] == pytest.approx(rmse[1], rel=1e-9, abs=0)
    assert rmse[0] > 0
