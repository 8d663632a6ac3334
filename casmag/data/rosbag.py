"""ROS bags in: a ROS 1 ``.bag`` file or a ROS 2 bag folder turned into a recording CSV.

Bags are read with the pure-Python ``rosbags`` package, an optional dependency
(``pip install casmag[bags]``); casmag imports it only when a bag is read. Bags that carry
no message definitions are read with the ROS 1 Noetic (``.bag``) or ROS 2 Humble (folder)
definitions. The caller names one topic per role:

magnetometer
    ``sensor_msgs/msg/MagneticField``: ``magnetic_field`` in tesla, sensor frame, written as
    ``mx,my,mz`` in microtesla (times ``mag_unit_scale``, default :data:`MAG_UNIT_SCALE` =
    1e6), casmag's unit for real data.
odometry
    ``nav_msgs/msg/Odometry`` (``pose.pose``) or ``geometry_msgs/msg/PoseStamped``
    (``pose``): poses in a world frame (z up), turned into the increments between
    consecutive messages. ``translational``: world-frame ``dx,dy`` [m] (z ignored);
    ``translational3``: ``dx,dy,dz``; ``planar``: ``dfwd,dleft`` [m], the displacement in
    the body frame at the earlier pose's yaw, and ``dyaw`` [rad], the yaw change wrapped to
    (-pi, pi] (roll, pitch and z ignored).
imu
    ``sensor_msgs/msg/Imu``: ``angular_velocity`` [rad/s] and ``linear_acceleration``
    (specific force) [m/s^2] in the sensor frame, integrated between consecutive messages k,
    k+1 (interval T) into the strapdown increments of :mod:`casmag.strapdown` by the
    trapezoid rule: ``dq = Exp(T (w_k + w_{k+1}) / 2)`` (w first) and
    ``dv = (T / 2) (a_k + R(dq) a_{k+1})``, the velocity increment in the sensor frame at
    the interval's start. Both are exact for a constant rotation rate and a constant
    world-frame acceleration; otherwise the error per interval is of order T^3. The
    magnetometer is taken to be in the IMU's frame.
truth (optional)
    ``nav_msgs/msg/Odometry`` or ``geometry_msgs/msg/PoseStamped``, for evaluation:
    ``x_true,y_true`` (``z_true`` for translational3 and IMU) [m]; ``yaw_true`` [rad] for
    planar (unwrapped along the messages); ``qw_true..qz_true`` for IMU (the pose's
    orientation, the sensor frame to the world frame). The pose is taken as the sensor's
    (no lever arm or mounting rotation is applied).

Time: each message's ``header.stamp`` (sec + nanosec 1e-9 s), not the time the bag
recorded it; ``t`` [s] is the stamp minus t0, the earliest stamp written (the first row's),
so ``t`` starts at 0 (taken in integer nanoseconds, then divided by 1e9: no digits are lost
to the epoch's size). t0 is kept in :attr:`BagRecording.record` (``t0_stamp``, sec.nanosec).
Messages of a topic are taken in stamp order.

Rows (casmag.data.recording): with odometry, each message is its own row (odometry rows
with the increment since the previous odometry message, zero on the first; magnetometer
rows; truth rows), messages of different roles sharing a stamp on one row, all sorted by
time; the recording reader brings the dead reckoning and the truth to the magnetometer's
rows. Magnetometer messages before the first or after the last odometry message cannot be
placed and are left out, as are truth messages beyond the one bracketing each end. Two
messages of one topic with the same stamp are written as two rows, which the reader merges.
With an IMU, rows are complete (IMU recordings take complete rows only): one per IMU message
within the magnetometer's (and the truth's) time span, with the magnetometer interpolated
linearly in time and the truth positions linearly, its orientation by slerp; IMU messages
sharing a stamp are averaged first.

Every problem raises :class:`~casmag.errors.DataError` as one line naming the bag, the
topic and the reason.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from casmag.data.recording import (
    MAGNETOMETER_COLUMNS,
    MOTION_COLUMNS,
    POSITION_TRUTH_COLUMNS,
    QUATERNION_TOLERANCE,
    QUATERNION_TRUTH_COLUMNS,
    TIME_COLUMN,
    YAW_TRUTH_COLUMN,
    _write_atomic,
)
from casmag.errors import DataError, one_line
from casmag.strapdown import euler_from_quat, quat_conj, quat_exp, quat_log, quat_mul, rotate

MAG_UNIT_SCALE = 1e6
"""Tesla (``sensor_msgs/msg/MagneticField``) to microtesla (casmag's unit for real data)."""

MOTIONS: tuple[str, ...] = ("translational", "translational3", "planar")
"""Motion inputs made from an odometry topic (an IMU topic gives the IMU input)."""

MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"
POSE_TYPES: tuple[str, ...] = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped")
"""Message types an odometry or truth topic may have."""

INSTALL = "pip install casmag[bags]"

_ROLE_TYPES: dict[str, tuple[str, ...]] = {
    "magnetometer": (MAGNETIC_FIELD,),
    "odometry": POSE_TYPES,
    "imu": (IMU,),
    "truth": POSE_TYPES,
}
_MIN_ROWS = 2


@dataclass(frozen=True)
class BagRecording:
    """A bag as recording rows, ready to write (:meth:`write`).

    path: the bag; columns: the CSV header (casmag.data.recording); rows: (R, C) float64
    values in column order, NaN where a row does not carry a group (an empty field); motion:
    the recording's motion input (``translation``, ``planar`` or ``imu``); record: how the
    rows were made (topics, types, message counts used and left out, t0, unit scale,
    integration rule), JSON-ready; notes: what was left out or merged, one sentence each.
    """

    path: str
    columns: tuple[str, ...]
    rows: np.ndarray
    motion: str
    record: dict[str, Any] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def write(self, out: str | Path) -> None:
        """Write the recording CSV atomically (a temporary file beside ``out``, then renamed
        over it): values in shortest round-trip form, NaN as an empty field."""
        lines = [",".join(self.columns)]
        lines += [
            ",".join("" if v != v else repr(v) for v in row)  # v != v: NaN, an empty field
            for row in self.rows.tolist()
        ]
        _write_atomic(str(out), "\n".join(lines) + "\n")


@dataclass(frozen=True)
class _Series:
    """One topic's messages in stamp order: ns (n,) int64 header stamps [ns]; values (n, k)
    float64 (MagneticField: field [T]; Imu: angular velocity [rad/s], acceleration [m/s^2];
    poses: x, y, z [m], qw, qx, qy, qz)."""

    topic: str
    msgtype: str
    ns: np.ndarray
    values: np.ndarray


# --------------------------------------------------------------------------- reading
def _error(path: Any, topic: str | None, reason: str) -> DataError:
    where = f"{path}: topic '{topic}'" if topic else f"{path}"
    return DataError(one_line(f"{where}: {reason}"))


def _bag_path(path: str | Path) -> Path:
    """The path rosbags opens: a ``.bag`` file, or the folder of a ROS 2 bag (given as the
    folder or its metadata.yaml)."""
    p = Path(path)
    if p.name == "metadata.yaml":
        p = p.parent
    if not p.exists():
        raise _error(path, None, "not found")
    if (p.suffix == ".bag" and p.is_file()) or (p / "metadata.yaml").is_file():
        return p
    raise _error(path, None, "not a ROS 1 .bag file or a ROS 2 bag folder (with metadata.yaml)")


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` names a ROS bag: a ``.bag`` file, a folder with a ``metadata.yaml``
    or that ``metadata.yaml`` itself (checked by name only; reading checks the rest)."""
    p = Path(path)
    return p.suffix == ".bag" or p.name == "metadata.yaml" or (p / "metadata.yaml").is_file()


@contextmanager
def _open(path: str | Path) -> Iterator[Any]:
    """An open rosbags AnyReader; its errors (and a missing rosbags) as one-line DataError."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.highlevel.anyreader import AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise _error(path, None, f"reading ROS bags needs the rosbags package: {INSTALL}") from None
    bag = _bag_path(path)
    store = get_typestore(Stores.ROS1_NOETIC if bag.suffix == ".bag" else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([bag], default_typestore=store)
        reader.open()
    except (AnyReaderError, OSError) as exc:
        raise _error(path, None, f"cannot read the bag ({_reason(exc)})") from None
    try:
        yield reader
    except (AnyReaderError, OSError) as exc:
        raise _error(path, None, f"cannot read the bag ({_reason(exc)})") from None
    finally:
        reader.close()


def _reason(exc: BaseException) -> str:
    """The first line of an error's message (rosbags quotes YAML errors over lines)."""
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _topic_types(reader: Any) -> dict[str, tuple[str, int]]:
    """Topic -> (message type(s), message count) of an open reader."""
    out: dict[str, tuple[str, int]] = {}
    for topic, info in reader.topics.items():
        types = sorted({c.msgtype for c in info.connections}) or [info.msgtype or "?"]
        out[topic] = (", ".join(types), int(info.msgcount))
    return out


def list_topics(path: str | Path) -> list[tuple[str, str, int]]:
    """The bag's topics as (topic, message type, message count), by topic name (a topic
    written with several types lists them joined by commas)."""
    with _open(path) as reader:
        return [(topic, kind, n) for topic, (kind, n) in sorted(_topic_types(reader).items())]


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _values(msgtype: str, msg: Any) -> tuple[float, ...]:
    if msgtype == MAGNETIC_FIELD:
        b = msg.magnetic_field
        return (b.x, b.y, b.z)
    if msgtype == IMU:
        w, a = msg.angular_velocity, msg.linear_acceleration
        return (w.x, w.y, w.z, a.x, a.y, a.z)
    pose = msg.pose.pose if msgtype == POSE_TYPES[0] else msg.pose
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z, q.w, q.x, q.y, q.z)


def _read(path: str | Path, roles: dict[str, str]) -> tuple[dict[str, _Series], str]:
    """Each role's topic (role -> topic) checked and read; also the bag's format name."""
    with _open(path) as reader:
        topics = _topic_types(reader)
        for role, topic in roles.items():
            if topic not in topics:
                have = ", ".join(f"{t} ({k})" for t, (k, _) in sorted(topics.items()))
                raise _error(
                    path,
                    topic,
                    f"not in the bag (the {role} topic; the bag has: {have or 'no topics'})",
                )
            kind, count = topics[topic]
            allowed = _ROLE_TYPES[role]
            if kind not in allowed:
                raise _error(
                    path,
                    topic,
                    f"is {kind}; the {role} topic must be {' or '.join(allowed)}",
                )
            if count == 0:
                raise _error(path, topic, f"has no messages (the {role} topic)")
        wanted = set(roles.values())
        connections = [c for c in reader.connections if c.topic in wanted]
        stamps: dict[str, list[int]] = {t: [] for t in wanted}
        values: dict[str, list[tuple[float, ...]]] = {t: [] for t in wanted}
        for conn, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, conn.msgtype)
            stamps[conn.topic].append(_stamp_ns(msg))
            values[conn.topic].append(_values(conn.msgtype, msg))
        series = {}
        for topic in wanted:
            kind = topics[topic][0]
            series[topic] = _series(path, topic, kind, stamps[topic], values[topic])
        return series, "ROS 1" if not reader.is2 else "ROS 2"


def _series(
    path: Any, topic: str, kind: str, stamps: list[int], values: list[tuple[float, ...]]
) -> _Series:
    """One topic's messages checked (finite values, stamps not all equal) and put in stamp
    order."""
    ns = np.asarray(stamps, dtype=np.int64)
    V = np.asarray(values, dtype=np.float64)
    if ns.size == 0:
        raise _error(path, topic, "has no messages")
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise _error(
            path,
            topic,
            f"message {i + 1} (stamp {_seconds(ns[i])} s) has a non-finite value "
            f"({', '.join(map(repr, V[i].tolist()))})",
        )
    if ns.size > 1 and np.all(ns == ns[0]):
        raise _error(
            path,
            topic,
            f"all {ns.size} messages have the same header stamp ({_seconds(ns[0])} s): "
            "stamps not set?",
        )
    order = np.argsort(ns, kind="stable")
    return _Series(topic, kind, ns[order], V[order])


def _seconds(ns: Any) -> str:
    """A stamp in nanoseconds as exact seconds text (sec.nanosec)."""
    sec, nsec = divmod(abs(int(ns)), 1_000_000_000)
    return f"{'-' if int(ns) < 0 else ''}{sec}.{nsec:09d}"


def _orientation(path: Any, s: _Series) -> np.ndarray:
    """(n, 4) unit quaternions (w first) of a pose series, normalised; a quaternion off unit
    norm by more than QUATERNION_TOLERANCE (an unset orientation) is refused."""
    q = s.values[:, 3:7]
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= QUATERNION_TOLERANCE))
    if bad.size:
        i = int(bad[0])
        raise _error(
            path,
            s.topic,
            f"the pose at stamp {_seconds(s.ns[i])} s has an orientation of norm "
            f"{norm[i]:.6g}, not a unit quaternion (orientation not set?)",
        )
    return q / norm[:, None]


def _yaw(q: np.ndarray) -> np.ndarray:
    """(n,) yaw [rad] of (n, 4) quaternions (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    return euler_from_quat(q)[:, 2]


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles [rad] wrapped to (-pi, pi]."""
    return math.pi - np.mod(math.pi - np.asarray(a, dtype=np.float64), 2.0 * math.pi)


# --------------------------------------------------------------------------- increments
def pose_increments(
    P: np.ndarray, yaw: np.ndarray | None, motion: str
) -> tuple[tuple[str, ...], np.ndarray]:
    """Odometry increments between consecutive poses and their column names.

    P: (n, 3) positions [m] in the world frame; yaw: (n,) headings [rad] (planar only).
    translational: (n-1, 2) dx, dy; translational3: (n-1, 3) dx, dy, dz [m], world frame;
    planar: (n-1, 3) dfwd, dleft [m] (the step in the body frame at the earlier pose's
    yaw) and dyaw [rad] wrapped to (-pi, pi].
    """
    d = np.diff(P, axis=0)
    if motion == "translational":
        return MOTION_COLUMNS["translation2"], d[:, :2]
    if motion == "translational3":
        return MOTION_COLUMNS["translation3"], d
    if motion != "planar" or yaw is None:
        raise ValueError(f"motion {motion!r} (one of {', '.join(MOTIONS)}; planar needs yaw)")
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    U = np.column_stack(
        [c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], wrap_angle(np.diff(yaw))]
    )
    return MOTION_COLUMNS["planar"], U


def imu_increments(T: np.ndarray, W: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Strapdown increments (casmag.strapdown) of IMU samples by the trapezoid rule.

    T: (n-1,) intervals [s]; W: (n, 3) angular velocity [rad/s]; A: (n, 3) specific force
    [m/s^2], both in the sensor frame at their sample. Returns (n-1, 7): dq (w first) =
    Exp(T (w_k + w_{k+1}) / 2), the rotation from the sensor frame at the interval's start to
    the one at its end, and dv = (T / 2) (a_k + R(dq) a_{k+1}), the velocity increment in
    the sensor frame at the interval's start [m/s]. Exact for a constant rotation rate and a
    constant world-frame specific force (then R(dq) a_{k+1} = a_k).
    """
    T = np.asarray(T, dtype=np.float64)[:, None]
    dq = quat_exp(0.5 * T * (W[:-1] + W[1:]))
    dv = 0.5 * T * (A[:-1] + rotate(dq, A[1:]))
    return np.hstack([dq, dv])


def slerp(ts: np.ndarray, Q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(m, 4) unit quaternions interpolated at times t (within [ts[0], ts[-1]]) along the
    shortest rotation between the samples Q (n, 4) at strictly increasing times ts; exact
    at a sample's time."""
    i = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 2)
    s = ((t - ts[i]) / (ts[i + 1] - ts[i]))[:, None]
    step = quat_log(quat_mul(quat_conj(Q[i]), Q[i + 1]))
    return quat_mul(Q[i], quat_exp(s * step))


def _merge_equal(ns: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Samples sharing a stamp averaged into one; also how many were merged away."""
    starts = np.flatnonzero(np.r_[True, np.diff(ns) > 0])
    if starts.size == ns.size:
        return ns, V, 0
    counts = np.diff(np.r_[starts, ns.size])[:, None]
    return ns[starts], np.add.reduceat(V, starts, axis=0) / counts, ns.size - starts.size


# --------------------------------------------------------------------------- rows
def _layout(groups: list[tuple[str, tuple[str, ...]]]) -> tuple[tuple[str, ...], dict]:
    """Header and each group's column indices (time first)."""
    columns = [TIME_COLUMN]
    where = {}
    for name, cols in groups:
        where[name] = list(range(len(columns), len(columns) + len(cols)))
        columns += cols
    return tuple(columns), where


def _event_rows(
    columns: tuple[str, ...],
    where: dict[str, list[int]],
    events: list[tuple[str, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of messages (group, ns (n,), values (n, k)), one per message, groups sharing a
    stamp on one row (a group's second message at a stamp starts another row): each row's
    stamp (R,) [ns] and its values (R, C), NaN where a row has no value of a group (the time
    column is left to the caller)."""
    ns = np.concatenate([e[1] for e in events])
    gid = np.concatenate([np.full(e[1].size, j) for j, e in enumerate(events)])
    order = np.lexsort((gid, ns))
    ns_s, g_s = ns[order], gid[order]
    # Occurrence of each message among those of its group at its stamp: 0, 1, ...
    run = np.r_[True, (ns_s[1:] != ns_s[:-1]) | (g_s[1:] != g_s[:-1])]
    rank = np.arange(ns_s.size) - np.maximum.accumulate(np.where(run, np.arange(ns_s.size), 0))
    keys, row = np.unique(np.column_stack([ns_s, rank]), axis=0, return_inverse=True)
    row = row.ravel()
    A = np.full((keys.shape[0], len(columns)), np.nan)
    position = np.empty_like(order)
    position[order] = np.arange(order.size)
    start = 0
    for name, stamps, V in events:
        rows = row[position[start : start + stamps.size]]
        A[np.ix_(rows, where[name])] = V
        start += stamps.size
    return keys[:, 0], A


def _bracket(ns: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Indices of sorted stamps within [lo, hi] plus the nearest one beyond each end."""
    first = max(int(np.searchsorted(ns, lo, side="right")) - 1, 0)
    last = min(int(np.searchsorted(ns, hi, side="left")), ns.size - 1)
    return np.arange(first, last + 1)


def read_bag(
    path: str | Path,
    magnetometer: str,
    odometry: str | None = None,
    imu: str | None = None,
    truth: str | None = None,
    motion: str | None = None,
    mag_unit_scale: float = MAG_UNIT_SCALE,
) -> BagRecording:
    """A bag's topics as recording rows (module docstring): magnetometer, exactly one of
    odometry (with ``motion``: ``translational`` (default), ``translational3`` or
    ``planar``) and imu (``motion`` None), and optional truth, all topic names.

    mag_unit_scale: multiplies the magnetometer's values (default 1e6: tesla to
    microtesla). Raises DataError (one line: the bag, the topic, the reason) for a topic not
    in the bag, of the wrong type or without messages, too few messages to make two rows, a
    non-finite value, or a missing rosbags package.
    """
    if (odometry is None) == (imu is None):
        raise _error(
            path,
            None,
            "give an odometry topic or an IMU topic (exactly one)",
        )
    if imu is not None and motion is not None:
        raise _error(
            path, None, f"motion '{motion}' is for odometry; an IMU topic gives the IMU input"
        )
    motion = motion or "translational"
    if imu is None and motion not in MOTIONS:
        raise _error(path, None, f"unknown motion '{motion}' (one of {', '.join(MOTIONS)})")
    if not (math.isfinite(mag_unit_scale) and mag_unit_scale > 0):
        raise _error(path, None, f"mag_unit_scale must be positive (got {mag_unit_scale!r})")
    roles = {"magnetometer": magnetometer}
    if odometry is not None:
        roles["odometry"] = odometry
    if imu is not None:
        roles["imu"] = imu
    if truth is not None:
        roles["truth"] = truth
    series, fmt = _read(path, roles)
    mag = series[magnetometer]
    if imu is not None:
        rec = _imu_rows(path, series[imu], mag, series[truth] if truth else None, mag_unit_scale)
    else:
        assert odometry is not None
        rec = _odometry_rows(
            path, series[odometry], mag, series[truth] if truth else None, motion, mag_unit_scale
        )
    columns, ns, rows, kind, record, notes = rec
    t0 = int(ns[0])
    rows[:, 0] = (ns - t0) / 1e9  # integer nanoseconds from t0 (exact), in seconds
    record = {
        "source": str(path),
        "format": fmt,
        "topics": {
            role: {"topic": topic, "type": series[topic].msgtype, **record.get(role, {})}
            for role, topic in roles.items()
        },
        "t0_stamp": _seconds(t0),
        "time": "header.stamp minus t0_stamp [s]",
        "motion": motion if imu is None else "imu",
        "mag_unit_scale": mag_unit_scale,
        "rows": int(rows.shape[0]),
        **({"imu_integration": "trapezoid"} if imu is not None else {}),
        "notes": list(notes),
    }
    return BagRecording(str(path), columns, rows, kind, record, tuple(notes))


def _odometry_rows(
    path: Any,
    odo: _Series,
    mag: _Series,
    truth: _Series | None,
    motion: str,
    scale: float,
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, str, dict, list[str]]:
    """Odometry, magnetometer and truth messages each on their own rows (module docstring)."""
    notes: list[str] = []
    if odo.ns.size < _MIN_ROWS:
        raise _error(path, odo.topic, f"needs at least {_MIN_ROWS} odometry messages (has 1)")
    yaw = _yaw(_orientation(path, odo)) if motion == "planar" else None
    names, U = pose_increments(odo.values[:, :3], yaw, motion)
    U = np.vstack([np.zeros((1, U.shape[1])), U])  # the dead reckoning starts at the first
    lo, hi = int(odo.ns[0]), int(odo.ns[-1])
    inside = (mag.ns >= lo) & (mag.ns <= hi)
    if inside.sum() < _MIN_ROWS:
        raise _error(
            path,
            mag.topic,
            f"needs at least {_MIN_ROWS} magnetometer messages within the odometry's time span "
            f"({_seconds(lo)} to {_seconds(hi)} s; {int(inside.sum())} of {mag.ns.size} are)",
        )
    if not inside.all():
        notes.append(
            f"{int((~inside).sum())} of {mag.ns.size} magnetometer messages ({mag.topic}) "
            "before the first or after the last odometry message were left out"
        )
    groups = [("motion", names), ("mag", MAGNETOMETER_COLUMNS)]
    events = [("motion", odo.ns, U), ("mag", mag.ns[inside], scale * mag.values[inside])]
    used = {
        "odometry": {"messages": int(odo.ns.size), "used": int(odo.ns.size)},
        "magnetometer": {"messages": int(mag.ns.size), "used": int(inside.sum())},
    }
    if truth is not None:
        idx = _bracket(truth.ns, lo, hi)
        dim = 3 if motion == "translational3" else 2
        cols = POSITION_TRUTH_COLUMNS[:dim]
        V = truth.values[idx, :dim]
        if motion == "planar":
            cols = (*cols, YAW_TRUTH_COLUMN)
            V = np.column_stack([V, np.unwrap(_yaw(_orientation(path, truth)))[idx]])
        groups.append(("truth", cols))
        events.append(("truth", truth.ns[idx], V))
        used["truth"] = {"messages": int(truth.ns.size), "used": int(idx.size)}
    columns, where = _layout(groups)
    ns, rows = _event_rows(columns, where, events)
    kind = "planar" if motion == "planar" else "translation"
    return columns, ns, rows, kind, used, notes


def _imu_rows(
    path: Any, imu: _Series, mag: _Series, truth: _Series | None, scale: float
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, str, dict, list[str]]:
    """Complete rows at the IMU's stamps within the magnetometer's (and truth's) time span:
    increments, magnetometer interpolated linearly, truth positions linearly and
    orientations by slerp (module docstring)."""
    notes: list[str] = []
    ns, V, merged = _merge_equal(imu.ns, imu.values)
    if merged:
        notes.append(
            f"{merged} IMU messages ({imu.topic}) repeat the previous message's stamp and "
            "were averaged with it"
        )
    mag_ns, mag_V, mag_merged = _merge_equal(mag.ns, mag.values)
    if mag_merged:
        notes.append(
            f"{mag_merged} magnetometer messages ({mag.topic}) repeat the previous message's "
            "stamp and were averaged with it"
        )
    lo, hi, span = int(mag_ns[0]), int(mag_ns[-1]), "magnetometer's"
    if truth is not None:
        q_truth = _orientation(path, truth)
        truth_ns, truth_V, _ = _merge_equal(truth.ns, np.hstack([truth.values[:, :3], q_truth]))
        lo, hi, span = (
            max(lo, int(truth_ns[0])),
            min(hi, int(truth_ns[-1])),
            "magnetometer's and truth's",
        )
    keep = (ns >= lo) & (ns <= hi)
    if keep.sum() < _MIN_ROWS:
        raise _error(
            path,
            imu.topic,
            f"needs at least {_MIN_ROWS} IMU messages within the {span} time span "
            f"({_seconds(lo)} to {_seconds(hi)} s; {int(keep.sum())} of {imu.ns.size} are)",
        )
    if not keep.all():
        notes.append(
            f"{int((~keep).sum())} of {ns.size} IMU messages ({imu.topic}) outside the {span} "
            "time span were left out"
        )
    ns, V = ns[keep], V[keep]
    t = (ns - ns[0]) / 1e9  # seconds from the first row (t0)
    inc = imu_increments(np.diff(t), V[:, :3], V[:, 3:])
    inc = np.vstack([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], inc])  # the first row's: ignored
    tm = (mag_ns - ns[0]) / 1e9
    Y = scale * np.column_stack([np.interp(t, tm, mag_V[:, k]) for k in range(3)])
    columns = [TIME_COLUMN, *MOTION_COLUMNS["imu"], *MAGNETOMETER_COLUMNS]
    blocks = [np.zeros((ns.size, 1)), inc, Y]  # the time column: read_bag fills it
    used = {
        "imu": {"messages": int(imu.ns.size), "used": int(ns.size)},
        "magnetometer": {
            "messages": int(mag.ns.size),
            "used": int(_bracket(mag.ns, int(ns[0]), int(ns[-1])).size),
        },
    }
    if truth is not None:
        tt = (truth_ns - ns[0]) / 1e9
        P = np.column_stack([np.interp(t, tt, truth_V[:, k]) for k in range(3)])
        Q = slerp(tt, truth_V[:, 3:], t) if tt.size > 1 else np.repeat(truth_V[:, 3:], t.size, 0)
        columns += [*POSITION_TRUTH_COLUMNS, *QUATERNION_TRUTH_COLUMNS]
        blocks += [P, Q]
        used["truth"] = {
            "messages": int(truth.ns.size),
            "used": int(_bracket(truth.ns, int(ns[0]), int(ns[-1])).size),
        }
    return tuple(columns), ns, np.hstack(blocks), "imu", used, notes
