"""Recordings: one CSV file per walk, read into arrays and written back.

A recording has a header row and one data row per magnetometer sample. Columns (order free,
names case-sensitive, whitespace around header names ignored):

``t``
    time [s], never decreasing.
motion input, exactly one group of :data:`MOTION_COLUMNS`
    ``dx,dy`` or ``dx,dy,dz``: world-frame position increment since the previous row [m];
    ``dfwd,dleft,dyaw``: body-frame displacement [m] and heading increment [rad] since the
    previous row; ``dqw,dqx,dqy,dqz,dvx,dvy,dvz``: strapdown IMU increments over the interval
    ending at the row (rotation quaternion, velocity increment [m/s]), sensor frame;
    ``dpx,dpy,dpz,dqw,dqx,dqy,dqz``: 6-DoF pose odometry since the previous row, Hamilton
    quaternions w first with q the body-to-world rotation: ``dp = R(q_prev)^T (p - p_prev)``
    [m] (body frame of the previous row) and ``dq = q_prev^-1 q`` (a unit quaternion), so
    ``p = p_prev + R(q_prev) dp``, ``q = q_prev dq``.
    The first row's increments are ignored (they may be empty or NaN).
``mx,my,mz``
    magnetometer in the sensor frame, any consistent unit.
optional truth, for evaluation only, in complete groups
    ``x_true,y_true[,z_true]`` [m], ``yaw_true`` [rad], ``qw_true,qx_true,qy_true,qz_true``
    (unit quaternion, w first).

Rows as sensors write them. A field left empty means "not sampled at this row"; each group
(the motion input, ``mx,my,mz``, each truth group) is given whole or not at all on a row.
A row identical to the previous one (a logger writing twice) is dropped; other rows with
the same time stamp are merged into one (motion increments summed, pose and IMU increments
composed in row order, the other values averaged). When the motion input and the
magnetometer are on different rows (two rates in one file), the dead reckoning is
integrated at the motion rows, interpolated linearly in time to the magnetometer rows and
turned back into increments between them (planar: in the body frame at the earlier row's
heading; pose: orientations interpolated by slerp, displacements in the earlier row's body
frame); truth is interpolated the same way (quaternion truth must be on every
magnetometer row); magnetometer rows after the last motion row are dropped. The reader
says what it did in ``Recording.notes`` (warnings in result.json). IMU recordings keep the
IMU's rows instead: a magnetometer on other rows (slower, or with time stamps of its own)
is interpolated to them in the frame of the gyroscope's attitude, so that a turn between
its samples does not shrink the field (:func:`_magnetometer_to_imu_rows`; its own samples
are kept in ``Recording.mag_samples`` for its noise, and the IMU model counts an average
over several rows as the samples it holds). The IMU's sample times must be uniform for
the IMU model (one interval T): when an interval differs from the median by more than
:data:`IMU_PERIOD_TOLERANCE` and the increments follow a uniform rate rather than the
stamps (the stamps jitter), the rows are kept and moved to a fitted uniform grid
(``retimed``); otherwise (samples taken at irregular times, a dropped sample, a gap) the
recording is resampled onto a uniform grid over its span (:func:`_imu_to_uniform_rows`):
the increments integrated at the recorded times (velocity sums and orientations, as
strapdown integration composes them), interpolated to the grid (linearly; orientations by
slerp) and turned back into increments between grid times; the magnetometer and the truth
interpolated the same way; the rows as recorded are kept in ``Recording.imu_samples`` and
``Recording.mag_samples`` for the noise at rest.

Every problem with a file raises :class:`~casmag.errors.DataError` as one line naming the
file, the row (header = row 1, first data row = row 2) or column, and the reason.

ROS bags become recordings in this format with :mod:`casmag.data.rosbag` (``casmag convert
BAG``: each message its own row, magnetometer in microtesla, times from header stamps).
"""

from __future__ import annotations

import csv
import difflib
import os
import re
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from casmag.data.simulate import Dataset
from casmag.errors import DataError, one_line
from casmag.strapdown import (
    quat_conj,
    quat_exp,
    quat_log,
    quat_mul,
    quat_normalize,
    quat_prefix,
    rotate,
)

MOTION_COLUMNS: dict[str, tuple[str, ...]] = {
    "translation2": ("dx", "dy"),
    "translation3": ("dx", "dy", "dz"),
    "planar": ("dfwd", "dleft", "dyaw"),
    "imu": ("dqw", "dqx", "dqy", "dqz", "dvx", "dvy", "dvz"),
    "pose": ("dpx", "dpy", "dpz", "dqw", "dqx", "dqy", "dqz"),
}
"""Column names of each motion input (``translation2``/``translation3`` are the 2-D/3-D forms
of the ``translation`` input). ``imu`` and ``pose`` share the ``dq`` columns."""

TIME_COLUMN = "t"
MAGNETOMETER_COLUMNS: tuple[str, ...] = ("mx", "my", "mz")
POSITION_TRUTH_COLUMNS: tuple[str, ...] = ("x_true", "y_true", "z_true")
YAW_TRUTH_COLUMN = "yaw_true"
QUATERNION_TRUTH_COLUMNS: tuple[str, ...] = ("qw_true", "qx_true", "qy_true", "qz_true")
QUATERNION_TOLERANCE = 1e-3
"""Largest accepted | |q| - 1 | of a truth quaternion row or a pose rotation increment."""

# Motion input name -> (required columns, optional columns), in write order.
_MOTION_GROUPS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "translation": (MOTION_COLUMNS["translation2"], ("dz",)),
    "planar": (MOTION_COLUMNS["planar"], ()),
    "imu": (MOTION_COLUMNS["imu"], ()),
    "pose": (MOTION_COLUMNS["pose"], ()),
}
_KNOWN_COLUMNS: tuple[str, ...] = (
    TIME_COLUMN,
    *MOTION_COLUMNS["translation3"],
    *MOTION_COLUMNS["planar"],
    *MOTION_COLUMNS["imu"],
    *MOTION_COLUMNS["pose"][:3],
    *MAGNETOMETER_COLUMNS,
    *POSITION_TRUTH_COLUMNS,
    YAW_TRUTH_COLUMN,
    *QUATERNION_TRUTH_COLUMNS,
)
_MIN_ROWS = 2
#: Largest relative difference of an IMU recording's sample interval from the median
#: before it is resampled onto a uniform grid: the IMU model takes one T, and a 1 % error
#: in one interval's T puts 0.1 m/s^2 of gravity into that interval's velocity update,
#: about a hundred times a MEMS accelerometer's white noise at 100 Hz.
IMU_PERIOD_TOLERANCE = 0.01
MAX_ABS_VALUE = 1e100
"""Largest magnitude a recording's value may have: sums over a million rows and their
squares (distances, residuals) must stay finite in float64 (about 1.8e308)."""

RESOLUTION = 1e12
"""Largest ratio of a motion column's summed magnitude (how far the dead reckoning can
reach) to its median non-zero step: beyond it a step is lost in float64 rounding (16
digits) next to the position, so the dead reckoning stops moving."""

# A number as the recording format writes it: ASCII digits, an optional sign, point and
# exponent; nan and inf(inity) are read so that the checks below can name them. float()
# alone also takes underscores (1_000) and non-ASCII digits, which no CSV writer produces.
_NUMBER = re.compile(
    r"\s*(?:[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf|infinity))\s*",
    re.IGNORECASE | re.ASCII,
)
# Characters of plain numbers (no letters but the exponent's): text made of these alone
# needs no field-by-field check.
_PLAIN = re.compile(r"[^0-9eE.+\-,\s]", re.ASCII)


@dataclass(frozen=True)
class Recording:
    """One recording as float64 arrays.

    path: the file it came from; t: (N,) times [s], strictly increasing; motion:
    ``"translation"``, ``"planar"``, ``"imu"`` or ``"pose"``; increments: (N-1, k) motion
    columns of rows 2..N (the first row's are dropped), in the order of
    ``increment_names``; Y: (N, 3) magnetometer (field units). Truth, None when the file
    has none: P_true (N, 2) or (N, 3) positions [m], yaw_true (N,) heading [rad], q_true
    (N, 4) orientation quaternion (w, x, y, z). notes: what reading changed (rows sharing
    a time stamp merged, odometry and magnetometer at different rates brought to the
    magnetometer's rows), each a warning ``{"check", "column", "reason"}``
    (casmag.data.checks). mag_samples: an IMU recording's magnetometer samples (times (M,),
    values (M, 3)) as written, when they were interpolated to the rows (on other rows than
    the IMU's, or the IMU resampled onto a uniform grid; None otherwise; :attr:`mag_share`);
    imu_samples: its IMU rows as written (times (K,), increments (K-1, 7) of rows 2..K) when
    they were resampled (the noise at rest is estimated from these).
    """

    path: str
    t: np.ndarray
    motion: str
    increments: np.ndarray
    increment_names: tuple[str, ...]
    Y: np.ndarray
    P_true: np.ndarray | None = None
    yaw_true: np.ndarray | None = None
    q_true: np.ndarray | None = None
    notes: tuple[dict[str, str], ...] = ()
    mag_samples: tuple[np.ndarray, np.ndarray] | None = None
    imu_samples: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def n_samples(self) -> int:
        """Number of rows N (magnetometer samples; IMU: IMU samples)."""
        return self.Y.shape[0]

    @property
    def mag_share(self) -> float:
        """Magnetometer samples per row, at most 1: 1 when the magnetometer was measured on
        every row; for an IMU recording whose magnetometer was on other rows (``mag_samples``:
        its own times and values, interpolated to the IMU's rows), the ratio of the rates
        (the rows' median interval over the magnetometer's), or its samples within the
        rows' time span per row interval when fewer (samples lost)."""
        if self.mag_samples is None:
            return 1.0
        tm = self.mag_samples[0]
        inside = int(np.count_nonzero((tm >= self.t[0]) & (tm <= self.t[-1])))
        rates = float(np.median(np.diff(self.t)) / np.median(np.diff(tm)))
        return min(1.0, rates, inside / (self.n_samples - 1))

    @property
    def dim(self) -> int:
        """Spatial dimension: 2 or 3 for translation, 2 for planar, 3 for imu and pose."""
        if self.motion == "translation":
            return self.increments.shape[1]
        return 2 if self.motion == "planar" else 3

    @property
    def has_truth(self) -> bool:
        """Whether any truth (positions, yaw or quaternions) was recorded."""
        return any(x is not None for x in (self.P_true, self.yaw_true, self.q_true))

    def to_dataset(self, anchor: str = "truth") -> Dataset:
        """The translational data set: U = increments (N-1, d), Y (N, 3), anchor (d,).

        ``anchor``: ``truth`` (default), the first true position when the recording has
        one, else the origin; ``origin``: the origin (the estimate in the odometry's frame;
        compare with the truth after an alignment, casmag.result.evaluation). Raises DataError for
        motion inputs the solver does not support yet (planar, imu, pose).
        """
        if self.motion != "translation":
            raise DataError(
                one_line(
                    f"{self.path}: motion input '{self.motion}' is not supported by this solver yet"
                )
            )
        dim = self.dim
        if self.P_true is not None and self.P_true.shape[1] != dim:
            raise DataError(
                one_line(
                    f"{self.path}: true positions are {self.P_true.shape[1]}-D but the "
                    f"translation input is {dim}-D"
                )
            )
        start = np.zeros(dim)
        if anchor == "truth" and self.P_true is not None:
            start = self.P_true[0].copy()
        return Dataset(U=self.increments, Y=self.Y, anchor=start, P_true=self.P_true)


# --------------------------------------------------------------------------- reading
def _error(path: str, where: str, reason: str) -> DataError:
    text = f"{path}: {where}: {reason}" if where else f"{path}: {reason}"
    return DataError(one_line(text))


def _names(columns: Sequence[str]) -> str:
    return ", ".join(columns)


def _read_text(path: str) -> str:
    try:
        with open(path, encoding="utf-8-sig") as f:
            return f.read()
    except UnicodeDecodeError as exc:
        raise _error(path, "", f"cannot read file (not UTF-8 text: {exc.reason})") from None
    except OSError as exc:
        raise _error(path, "", f"cannot read file ({exc.strerror or exc})") from None


def _parse_header(path: str, line: str) -> list[str]:
    try:
        fields = next(csv.reader([line]), [])
    except csv.Error as exc:
        raise _error(path, "row 1", f"cannot parse the header ({exc})") from None
    if not line.strip():
        raise _error(path, "row 1", "empty header row (expected column names)")
    names = [name.strip() for name in fields]
    if path.lower().endswith((".yaml", ".yml")) or line.strip() == "---":
        raise _error(
            path,
            "",
            "not a CSV recording (it reads as YAML: a problem file is solved by casmag "
            "solve FILE, casmag.solve)",
        )
    if line.lstrip().startswith("#"):
        raise _error(
            path, "row 1", "a comment line; the first row must be the header (remove comments)"
        )
    if all(_is_number(name) for name in names):
        raise _error(
            path,
            "row 1",
            "holds numbers, not column names: the first row must be the header (e.g. "
            f"{_names((TIME_COLUMN, *MOTION_COLUMNS['translation2'], *MAGNETOMETER_COLUMNS))})",
        )
    if len(names) == 1:
        for sep, what in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars"), (" ", "spaces")):
            if sep in names[0].strip():
                raise _error(
                    path,
                    "row 1",
                    f"the columns are separated by {what}; casmag reads comma-separated "
                    "values (save the file as CSV with commas)",
                )
    seen: dict[str, int] = {}
    for i, name in enumerate(names, start=1):
        if not name:
            raise _error(path, f"column {i}", "empty column name in the header")
        if name in seen:
            raise _error(
                path, f"column '{name}'", f"duplicate column name (columns {seen[name]} and {i})"
            )
        seen[name] = i
    for name in names:
        if name not in _KNOWN_COLUMNS:
            raise _error(path, f"column '{name}'", f"unknown column{_column_hint(name)}")
    return names


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


#: Names other logs give the time and magnetometer columns: time, timestamp, stamp,
#: seconds, time_s; mag_x, magx, mag.x, magnetometer_x, bx (and y, z).
_TIME_ALIASES = ("time", "timestamp", "stamp", "seconds", "time_s", "t_s", "sec")
_MAG_ALIAS = re.compile(r"^(?:mag(?:netometer|netic)?(?:_field)?[_.\-]?|b|m_)([xyz])(?:_ut)?$")


def _alias(name: str) -> str | None:
    """casmag's name for a time or magnetometer column named as other logs name it."""
    low = name.strip().lower()
    if low in _TIME_ALIASES:
        return "t"
    m = _MAG_ALIAS.match(low)
    return f"m{m.group(1)}" if m else None


def _column_hint(name: str) -> str:
    """A suggestion for an unknown column: a known name that differs only in case or is
    close (difflib ratio 0.75 or more, names of 3 or more characters), or what a bare
    coordinate name would mean; else the known names."""
    by_case = [c for c in _KNOWN_COLUMNS if c.lower() == name.lower()]
    if by_case:
        return f" (did you mean '{by_case[0]}'?)"
    if f"{name.lower()}_true" in _KNOWN_COLUMNS:
        return (
            f" (a true position is '{name.lower()}_true'; an odometry increment 'd{name.lower()}')"
        )
    alias = _alias(name)
    if alias is not None:
        return f" (casmag names this column '{alias}')"
    close = difflib.get_close_matches(name, _KNOWN_COLUMNS, n=1, cutoff=0.75)
    if close and len(name) >= 3:
        return f" (did you mean '{close[0]}'?)"
    return f" (known columns: {_names(_KNOWN_COLUMNS)})"


def _motion_group(path: str, present: set[str]) -> tuple[str, tuple[str, ...]]:
    """The motion input name and its columns in the file, checked for completeness.

    An input is recognised by its own columns; the columns it shares with other inputs
    (``dq*``: imu and pose) decide nothing alone."""
    group_cols = {
        motion: (*required, *optional) for motion, (required, optional) in _MOTION_GROUPS.items()
    }
    owners = {c: tuple(m for m, cols in group_cols.items() if c in cols) for c in present}
    found = {
        motion: [c for c in cols if c in present]
        for motion, cols in group_cols.items()
        if any(c in present and len(owners[c]) == 1 for c in cols)
    }
    # Shared columns none of whose inputs is recognised: "imu or pose".
    shared: dict[tuple[str, ...], list[str]] = {}
    for c in dict.fromkeys(c for cols in group_cols.values() for c in cols):
        if c in present and len(owners[c]) > 1 and not any(m in found for m in owners[c]):
            shared.setdefault(owners[c], []).append(c)
    if not found and not shared:
        raise _error(
            path,
            "",
            "no motion input: expected one of dx,dy | dfwd,dleft,dyaw | dqw,...,dvz | dpx,...,dqz",
        )
    entries = [(motion, cols) for motion, cols in found.items()]
    entries += [(" or ".join(motions), cols) for motions, cols in shared.items()]
    if len(entries) > 1:
        groups = " and ".join(f"{motion} ({_names(cols)})" for motion, cols in entries)
        raise _error(path, "", f"mixed motion inputs: {groups}; give exactly one")
    if shared:  # e.g. dq* alone: name what each input that uses them lacks
        motions, cols = next(iter(shared.items()))
        lacks = []
        for m in motions:
            missing = [c for c in _MOTION_GROUPS[m][0] if c not in present]
            plural = "s" if len(missing) > 1 else ""
            lacks.append(f"{m} input (missing column{plural} {_names(missing)})")
        raise _error(path, "", f"incomplete {' or '.join(lacks)} (have {_names(cols)})")
    motion, cols = entries[0]
    required, optional = _MOTION_GROUPS[motion]
    missing = [c for c in required if c not in present]
    if missing:
        plural = "s" if len(missing) > 1 else ""
        raise _error(
            path,
            "",
            f"incomplete {motion} input: missing column{plural} {_names(missing)} "
            f"(have {_names(cols)})",
        )
    return motion, tuple(c for c in (*required, *optional) if c in present)


def _check_columns(path: str, names: list[str]) -> tuple[str, tuple[str, ...]]:
    present = set(names)
    if TIME_COLUMN not in present:
        raise _error(path, "", f"missing column '{TIME_COLUMN}' (time)")
    missing = [c for c in MAGNETOMETER_COLUMNS if c not in present]
    if missing:
        plural = "s" if len(missing) > 1 else ""
        raise _error(path, "", f"missing magnetometer column{plural} {_names(missing)}")
    motion, motion_cols = _motion_group(path, present)
    # Truth groups: positions need x_true and y_true (z_true optional); quaternions all four.
    groups = [
        (POSITION_TRUTH_COLUMNS, POSITION_TRUTH_COLUMNS[:2]),
        (QUATERNION_TRUTH_COLUMNS, QUATERNION_TRUTH_COLUMNS),
    ]
    for group, required in groups:
        have = [c for c in group if c in present]
        missing = [c for c in required if c not in present]
        if have and missing:
            plural = "s" if len(missing) > 1 else ""
            raise _error(
                path,
                "",
                f"incomplete truth group: missing column{plural} {_names(missing)} "
                f"(have {_names(have)})",
            )
    if motion == "translation":
        d_motion = len(motion_cols)
        d_truth = sum(c in present for c in POSITION_TRUTH_COLUMNS)
        if d_truth and d_truth != d_motion:
            raise _error(
                path,
                "",
                f"true positions are {d_truth}-D but the translation input is {d_motion}-D "
                f"({_names(motion_cols)})",
            )
    return motion, motion_cols


def _locate_bad_value(
    path: str, rows: list[list[str]], names: list[str], every_row: bool = False
) -> DataError | None:
    """The error for the first field that is not a plain number (None when all are); rows
    made of digits, signs, points and exponents alone are looked at field by field only
    with ``every_row``."""
    for i, fields in enumerate(rows):
        plain = _PLAIN.search(",".join(fields)) is None and all(f.strip() for f in fields)
        if plain and not every_row:
            continue
        for j, value in enumerate(fields):
            if _NUMBER.fullmatch(value):
                continue
            where = f"row {i + 2}, column '{names[j]}'"
            if not value.strip():
                return _error(path, where, "empty value")
            return _error(path, where, f"not a number ({value.strip()!r})")
    return None


def _parse_values(
    path: str, rows: list[list[str]], names: list[str], time_idx: int, motion_idx: list[int]
) -> tuple[np.ndarray, np.ndarray]:
    """(N, n_columns) float64 values and the (N, n_columns) mask of empty fields, which
    become NaN: a sensor not sampled at that row (every column but the time). The first
    row's motion increments (ignored) may also be NaN."""
    absent = np.zeros((len(rows), len(names)), dtype=bool)
    for i, fields in enumerate(rows):
        if "" in fields or any(not f.strip() for f in fields):
            for j, value in enumerate(fields):
                if j != time_idx and not value.strip():
                    fields[j] = "nan"
                    absent[i, j] = True
    error = _locate_bad_value(path, rows, names)
    if error is not None:
        raise error
    try:
        A = np.array(rows, dtype=np.float64)
    except ValueError:
        error = _locate_bad_value(path, rows, names, every_row=True)
        raise (error or _error(path, "", "cannot convert the values to numbers")) from None
    bad = ~np.isfinite(A) & ~absent  # a NaN written as such is an error, an empty field not
    bad[0, motion_idx] = np.isinf(A[0, motion_idx])
    if bad.any():
        i, j = np.argwhere(bad)[0]
        kind = "NaN" if np.isnan(A[i, j]) else "infinite"
        raise _error(path, f"row {i + 2}, column '{names[j]}'", f"value is {kind}")
    with np.errstate(invalid="ignore"):
        huge = np.abs(A) > MAX_ABS_VALUE
    if huge.any():
        i, j = np.argwhere(huge)[0]
        raise _error(
            path,
            f"row {i + 2}, column '{names[j]}'",
            f"value {A[i, j]:g} is beyond what the numerics can carry "
            f"(|value| <= {MAX_ABS_VALUE:g})",
        )
    return A, absent


def read_recording(path: str | Path) -> Recording:
    """Read and validate a recording CSV file (see the module docstring for the format).

    Raises DataError (one line: file, row or column, reason) for any problem with the file.
    """
    path = str(path)
    text = _read_text(path)
    lines = text.split("\n")
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise _error(path, "", "empty file (expected a header row and data rows)")
    names = _parse_header(path, lines[0])
    motion, motion_cols = _check_columns(path, names)
    data_lines = lines[1:]
    if len(data_lines) < _MIN_ROWS:
        raise _error(
            path,
            "",
            f"needs at least {_MIN_ROWS} rows of data (got {len(data_lines)})",
        )

    n_cols = len(names)
    rows = [line.split(",") for line in data_lines]
    lengths = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    wrong = np.flatnonzero(lengths != n_cols)
    if wrong.size:
        i = int(wrong[0])
        if not data_lines[i].strip():
            raise _error(path, f"row {i + 2}", f"empty row (expected {n_cols} fields)")
        raise _error(
            path, f"row {i + 2}", f"has {lengths[i]} fields, expected {n_cols} (as the header)"
        )

    col = {name: j for j, name in enumerate(names)}
    A, absent = _parse_values(path, rows, names, col[TIME_COLUMN], [col[c] for c in motion_cols])

    t = A[:, col[TIME_COLUMN]]
    steps = np.diff(t)
    backwards = np.flatnonzero(~(steps >= 0))
    if backwards.size:
        k = int(backwards[0]) + 1
        raise _error(
            path,
            f"row {k + 2}",
            f"time {float(t[k])!r} is before the previous row's {float(t[k - 1])!r} "
            f"(column '{TIME_COLUMN}' must not decrease)",
        )
    if motion == "pose":
        _normalise_rotation_increments(path, A, absent, [col[c] for c in motion_cols[3:]])
    truth_cols = [c for c in (*POSITION_TRUTH_COLUMNS, YAW_TRUTH_COLUMN) if c in col]
    if QUATERNION_TRUTH_COLUMNS[0] in col:
        truth_cols += list(QUATERNION_TRUTH_COLUMNS)
    A, notes, raw = _regularise(path, A, absent, col, motion, motion_cols, truth_cols)
    t = A[:, col[TIME_COLUMN]]

    def columns(group: Sequence[str]) -> np.ndarray | None:
        if not all(c in col for c in group):
            return None
        return np.ascontiguousarray(A[:, [col[c] for c in group]])

    q_true = columns(QUATERNION_TRUTH_COLUMNS)
    if q_true is not None:
        rows = np.arange(q_true.shape[0])
        _refuse_non_unit(path, q_true, rows, "", "truth quaternion", QUATERNION_TRUTH_COLUMNS)

    position_cols = [c for c in POSITION_TRUTH_COLUMNS if c in col]
    increments = columns(motion_cols)
    assert increments is not None
    if motion in ("translation", "planar"):
        _check_resolution(path, increments[1:], motion_cols)
    elif motion == "pose":  # the dq columns are near 1 and not summed
        _check_resolution(path, increments[1:, :3], motion_cols[:3])
    return Recording(
        path=path,
        t=t.copy(),
        motion=motion,
        increments=increments[1:].copy(),
        increment_names=motion_cols,
        Y=columns(MAGNETOMETER_COLUMNS),
        P_true=columns(position_cols) if position_cols else None,
        yaw_true=A[:, col[YAW_TRUTH_COLUMN]].copy() if YAW_TRUTH_COLUMN in col else None,
        q_true=q_true,
        notes=tuple(notes),
        **raw,
    )


def _normalise_rotation_increments(
    path: str, A: np.ndarray, absent: np.ndarray, qi: list[int]
) -> None:
    """Refuse a rotation increment (columns qi, rows after the first) that is not a unit
    quaternion within QUATERNION_TOLERANCE; normalise the others in place. Rows given in
    part are left to :func:`_regularise`, which names the empty value."""
    rows = np.flatnonzero(~absent[:, qi].any(axis=1))
    rows = rows[rows > 0]  # the first row's increments are ignored
    Q = A[np.ix_(rows, qi)]
    names = MOTION_COLUMNS["pose"][3:]
    _refuse_non_unit(path, Q, rows, f", column '{names[0]}'", "pose rotation increment", names)
    A[np.ix_(rows, qi)] = Q / np.linalg.norm(Q, axis=1, keepdims=True)


def _refuse_non_unit(
    path: str, Q: np.ndarray, rows: np.ndarray, where: str, what: str, names: Sequence[str]
) -> None:
    """DataError for the first quaternion of Q (n, 4) (columns ``names``, read from data rows
    ``rows``) whose norm is not 1 within QUATERNION_TOLERANCE (``where``: after the row in
    the message)."""
    norm = np.linalg.norm(Q, axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= QUATERNION_TOLERANCE))
    if bad.size:
        i = int(bad[0])
        raise _error(
            path,
            f"row {int(rows[i]) + 2}{where}",
            f"{what} ({_names(names)}) has norm {float(norm[i]):.6g}, expected 1 within "
            f"{QUATERNION_TOLERANCE:g}",
        )


def _regularise(
    path: str,
    A: np.ndarray,
    absent: np.ndarray,
    col: dict[str, int],
    motion: str,
    motion_cols: Sequence[str],
    truth_cols: Sequence[str],
) -> tuple[np.ndarray, list[dict[str, str]], dict[str, Any]]:
    """The rows as the solver takes them, one per magnetometer sample (IMU: one per IMU
    sample), from rows as sensors write them (see :func:`read_recording`); the notes say
    what was changed; an IMU recording's samples as recorded when its rows were made from
    them by interpolation (``mag_samples``, ``imu_samples``: Recording's fields)."""
    notes: list[dict[str, str]] = []
    mi = [col[c] for c in motion_cols]
    yi = [col[c] for c in MAGNETOMETER_COLUMNS]
    groups = [(mi, motion_cols), (yi, MAGNETOMETER_COLUMNS)]
    for cols in (
        [c for c in POSITION_TRUTH_COLUMNS if c in truth_cols],
        [YAW_TRUTH_COLUMN] if YAW_TRUTH_COLUMN in truth_cols else [],
        [c for c in QUATERNION_TRUTH_COLUMNS if c in truth_cols],
    ):
        if cols:
            groups.append(([col[c] for c in cols], cols))
    for idx, names in groups:
        miss = absent[:, idx]
        partial = miss.any(axis=1) & ~miss.all(axis=1)
        if idx is mi:
            partial[0] = False  # the first row's increments are ignored
        if partial.any():
            i = int(np.flatnonzero(partial)[0])
            j = int(np.flatnonzero(miss[i])[0])
            raise _error(
                path,
                f"row {i + 2}, column '{names[j]}'",
                f"empty value (the columns {_names(names)} are given together: all or none)",
            )
    absent = absent.copy()
    absent[0, mi] = True  # the first row's increments are ignored (may be NaN)
    has_motion = ~absent[:, mi].any(axis=1)
    has_motion[0] = True  # the first row is where the dead reckoning starts
    has_mag = ~absent[:, yi].any(axis=1)
    same = np.r_[False, np.all((A[1:] == A[:-1]) | (absent[1:] & absent[:-1]), axis=1)]
    if same.any():  # a row written twice by the logger: one of them
        A, absent = A[~same], absent[~same]
        notes.append(
            {
                "check": "duplicate_row",
                "column": TIME_COLUMN,
                "reason": f"{int(same.sum())} rows repeat the previous row exactly and were "
                "dropped",
            }
        )
    A, absent, has_motion, has_mag, merged = _merge_equal_times(A, absent, col, motion, mi, yi)
    if merged:
        how = "composed" if motion in ("pose", "imu") else "summed"
        notes.append(
            {
                "check": "duplicate_time",
                "column": TIME_COLUMN,
                "reason": f"{merged} rows repeat the previous row's time stamp and were merged "
                f"into it (motion increments {how}, magnetometer and truth averaged)",
            }
        )
    if motion == "imu":
        raw: dict[str, Any] = {}
        if not (has_motion.all() and has_mag.all()):
            A, absent, raw["mag_samples"], note = _magnetometer_to_imu_rows(
                path, A, absent, col, mi, yi, has_motion, has_mag
            )
            notes.append(note)
        resampled, note, t = _imu_to_uniform_rows(A, absent, col, mi)  # one interval T
        if note is not None and note["check"] == "resampled":  # the rows as recorded
            raw["imu_samples"] = (t, A[1:, mi].copy())
            raw.setdefault("mag_samples", (t, A[:, yi].copy()))
        return resampled, notes + ([note] if note else []), raw
    if has_motion.all() and has_mag.all():
        return A, notes, {}
    A, notes = _to_magnetometer_rows(
        path, A, absent, col, motion, mi, yi, has_motion, has_mag, notes
    )
    return A, notes, {}


def _merge_equal_times(
    A: np.ndarray,
    absent: np.ndarray,
    col: dict[str, int],
    motion: str,
    mi: list[int],
    yi: list[int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Rows of one time stamp as one row: present motion increments summed (pose: composed
    in row order, dp = dp1 + R(dq1) dp2, dq = dq1 dq2; IMU the same with dv for dp, as
    strapdown integration over a zero interval composes them), every other present value
    averaged.
    Returns the rows, their absent mask, which rows have motion and magnetometer, and how
    many rows were merged away."""
    t = A[:, col[TIME_COLUMN]]
    starts = np.flatnonzero(np.r_[True, np.diff(t) > 0])
    merged = A.shape[0] - starts.size
    if merged:
        present = ~absent
        values = np.where(present, A, 0.0)
        sums = np.add.reduceat(values, starts, axis=0)
        counts = np.add.reduceat(present.astype(np.int64), starts, axis=0)
        out = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
        out[:, mi] = np.where(counts[:, mi] > 0, sums[:, mi], np.nan)  # increments add up
        if motion == "pose":
            out[:, mi] = _compose_pose_rows(A[:, mi], present[:, mi[0]], starts, out[:, mi])
        elif motion == "imu":  # dq then dv: dv = dv1 + R(dq1) dv2 and dq = dq1 dq2 (Eq. 1)
            order = [*mi[4:], *mi[:4]]
            out[:, order] = _compose_pose_rows(
                A[:, order], present[:, mi[0]], starts, out[:, order]
            )
        out[:, col[TIME_COLUMN]] = t[starts]
        A, absent = out, counts == 0
        absent[:, col[TIME_COLUMN]] = False
    has_motion = ~absent[:, mi].any(axis=1)
    has_motion[0] = True
    return A, absent, has_motion, ~absent[:, yi].any(axis=1), merged


def _compose_pose_rows(
    U: np.ndarray, present: np.ndarray, starts: np.ndarray, summed: np.ndarray
) -> np.ndarray:
    """Pose increments U (rows, 7) composed in row order within each group of rows that
    starts at ``starts``, rows where ``present`` is False skipped; groups without any
    present row keep their value of ``summed`` (NaN)."""
    sizes = np.diff(np.r_[starts, U.shape[0]])
    dp = np.zeros((starts.size, 3))
    dq = np.tile([1.0, 0.0, 0.0, 0.0], (starts.size, 1))
    for j in range(int(sizes.max())):
        g = np.flatnonzero(sizes > j)
        g = g[present[starts[g] + j]]
        rows = U[starts[g] + j]
        dp[g] += rotate(dq[g], rows[:, :3])
        dq[g] = quat_mul(dq[g], rows[:, 3:])
    out = np.column_stack([dp, quat_normalize(dq)])
    return np.where(np.isnan(summed), summed, out)


def _integrate_pose(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 3) and orientations (n, 4) of pose increments U (n, 7) whose first row
    is the start (dp = 0, dq = 1): q_k = q_{k-1} dq_k, p_k = p_{k-1} + R(q_{k-1}) dp_k. The
    orientations are a prefix product (casmag.strapdown.quat_prefix)."""
    Q = quat_prefix(U[:, 3:])
    steps = np.vstack([np.zeros((1, 3)), rotate(Q[:-1], U[1:, :3])])
    return np.cumsum(steps, axis=0), Q


def _slerp(tk: np.ndarray, tm: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Orientations Q (n, 4) at the increasing times tm interpolated to the times tk (within
    tm's span) along the shortest arc between the neighbouring samples."""
    j = np.clip(np.searchsorted(tm, tk, side="right") - 1, 0, tm.size - 2)
    s = (tk - tm[j]) / (tm[j + 1] - tm[j])
    d = quat_mul(quat_conj(Q[j]), Q[j + 1])  # quat_log takes the shortest arc
    return quat_normalize(quat_mul(Q[j], quat_exp(s[:, None] * quat_log(d))))


def _grid_times(t: np.ndarray, period: float) -> tuple[np.ndarray, float] | None:
    """The time stamps t moved to a uniform grid of whole periods, and its period: the
    line t = t0 + period k fitted by least squares, k one period per row when every stamp
    is within half a period of that line, else each interval's whole number of ``period``
    (the median interval; a missing sample: two), refined; None when two stamps fall on one
    period."""
    k = np.arange(t.size, dtype=float)  # no sample missing: one period per row
    slope, t0 = np.polyfit(k, t, 1)
    if np.abs(t - (t0 + slope * k)).max() < 0.5 * slope:
        return t0 + slope * k, float(slope)
    k = np.r_[0.0, np.cumsum(np.maximum(1.0, np.round(np.diff(t) / period)))]
    for _ in range(3):  # each interval's whole periods first: the median drifts over a run
        slope, t0 = np.polyfit(k, t, 1)
        k = np.round((t - t0) / slope)
        if np.any(np.diff(k) < 1):
            return None
    return t0 + slope * k, float(slope)


def _stamps_jitter(dv: np.ndarray, stamped: np.ndarray, grid: np.ndarray) -> bool:
    """Whether an IMU's velocity increments dv (n, 3) were integrated over the intervals of
    a uniform grid (``grid``, n: whole periods) rather than over the stamped intervals
    (``stamped``, n): the specific force dv / interval (gravity at least) is smoother,
    summed squared differences between neighbouring rows, over the grid's intervals. Over
    its true intervals the force varies only with the motion and the noise; over wrong ones
    it also varies by gravity times the intervals' relative error."""
    by_stamps = np.diff(dv / stamped[:, None], axis=0)
    by_grid = np.diff(dv / grid[:, None], axis=0)
    return float(np.sum(by_grid**2)) < float(np.sum(by_stamps**2))


def _magnetometer_to_imu_rows(
    path: str,
    A: np.ndarray,
    absent: np.ndarray,
    col: dict[str, int],
    mi: list[int],
    yi: list[int],
    has_motion: np.ndarray,
    has_mag: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray], dict[str, str]]:
    """An IMU recording whose magnetometer is on other rows (another rate, or its own time
    stamps): the IMU's rows, each with the magnetometer interpolated to its time. The
    samples are turned into one frame by the gyroscope's attitude (G, integrated from the
    dq increments, by slerp between IMU rows at a sample's time, beyond the first or last
    IMU row continued at that interval's rate), interpolated linearly in
    that frame and turned back into the body frame of the row, so that a turn between two
    samples does not shrink the field. IMU rows before the first or after the last
    magnetometer sample are dropped (the first one kept is where the motion starts); truth
    on other rows is interpolated to the IMU rows (quaternions by slerp). Returns the
    rows, their absent mask, the magnetometer's own samples (times, values) and the note."""
    it = col[TIME_COLUMN]
    t = A[:, it]
    tm, Ym = t[has_mag], A[has_mag][:, yi]
    if tm.size < 2:
        raise _error(
            path,
            f"columns {_names(MAGNETOMETER_COLUMNS)}",
            f"needs at least 2 magnetometer samples (got {tm.size})",
        )
    rows = np.flatnonzero(has_motion)
    keep = rows[(t[rows] >= tm[0]) & (t[rows] <= tm[-1])]
    if keep.size < _MIN_ROWS:
        raise _error(
            path,
            "",
            f"needs at least {_MIN_ROWS} IMU rows within the magnetometer's time span "
            f"(got {keep.size})",
        )
    ti = t[rows]
    identity = np.array([[1.0, 0.0, 0.0, 0.0]])  # the first row: where the motion starts
    G = quat_prefix(np.vstack([identity, A[rows[1:]][:, mi[:4]]]))  # the gyro's attitude
    Gm = _slerp(tm, ti, G)  # beyond the IMU rows: carried on at the nearest interval's rate
    Z = rotate(Gm, Ym)
    tk = t[keep]
    at = np.column_stack([np.interp(tk, tm, Z[:, j]) for j in range(3)])
    out = A[keep].copy()
    gone = absent[keep].copy()
    out[:, yi] = rotate(quat_conj(G[np.searchsorted(rows, keep)]), at)
    gone[:, yi] = False
    out[0, mi] = np.nan  # the start: its increments are ignored
    quaternion = [col[c] for c in QUATERNION_TRUTH_COLUMNS if c in col]
    for name in (*POSITION_TRUTH_COLUMNS, YAW_TRUTH_COLUMN):
        if name not in col:
            continue
        j = col[name]
        have = ~absent[:, j]
        if have.sum() >= 2 and not have[keep].all():
            values = np.unwrap(A[have, j]) if name == YAW_TRUTH_COLUMN else A[have, j]
            out[:, j] = np.interp(tk, t[have], values)
            gone[:, j] = False
    if quaternion:
        have = ~absent[:, quaternion].any(axis=1)
        if have.sum() >= 2 and not have[keep].all():
            out[:, quaternion] = _slerp(tk, t[have], quat_normalize(A[have][:, quaternion]))
            gone[:, quaternion] = False
    n_mag = int(np.count_nonzero((tm >= tk[0]) & (tm <= tk[-1])))
    reason = (
        f"IMU increments on {keep.size} rows and the magnetometer on {tm.size} "
        f"({n_mag} within the IMU rows' span, about {n_mag / max(tk[-1] - tk[0], 1e-300):.4g} "
        f"Hz against {(keep.size - 1) / max(tk[-1] - tk[0], 1e-300):.4g} Hz): the magnetometer "
        "was interpolated to the IMU rows (in the gyroscope's frame), its noise counted per "
        "sample it has"
    )
    dropped = rows.size - keep.size
    if dropped:
        reason += f"; {dropped} IMU rows outside the magnetometer's time span were dropped"
    note = {"check": "resampled", "column": ", ".join(MAGNETOMETER_COLUMNS), "reason": reason}
    return out, gone, (tm.copy(), Ym.copy()), note


def _imu_to_uniform_rows(
    A: np.ndarray, absent: np.ndarray, col: dict[str, int], mi: list[int]
) -> tuple[np.ndarray, dict[str, str] | None, np.ndarray]:
    """An IMU recording's rows on a uniform time grid (module docstring), the note that
    says so, and the times of the rows as recorded that it believed (their stamps, or the
    fitted grid when the stamps jitter); the rows as they are (note None) when every
    interval is within
    :data:`IMU_PERIOD_TOLERANCE` of the median. The grid spans the first to the last time
    stamp; each recorded interval counts as the whole number of median intervals nearest to
    it, at least one (jitter: one each, the row count kept; a dropped sample: two).
    Velocity sums v_k = v_{k-1} + R(q_{k-1}) dv_k and orientations q_k = q_{k-1} dq_k are
    integrated at the recorded rows, interpolated to the grid (v linearly, q by slerp),
    and the grid's increments are dq = q_a^-1 q_b and dv = R(q_a)^T (v_b - v_a).

    Unless the time stamps jitter (:func:`_grid_times` fits a grid of whole periods to them,
    and :func:`_stamps_jitter` finds the velocity increments smoother over its intervals
    than over the stamped ones): an IMU sampled by its own clock and stamped by another's
    (a phone's operating system) integrates over uniform intervals whatever the stamps say,
    and resampling by the stamps would add the stamps' error to every increment (tiny desk
    recording, stamps jittered by up to 5 % of the interval: the accelerometer's noise at
    rest came out 31-40 times the simulated). Such rows are moved to the grid and kept as
    they are (note ``retimed``), or, when the grid shows a sample missing, resampled from
    the grid's times."""
    it = col[TIME_COLUMN]
    t = A[:, it]
    dt = np.diff(t)
    median = float(np.median(dt))
    off = np.abs(dt - median) > IMU_PERIOD_TOLERANCE * median
    if not off.any():
        return A, None, t.copy()
    i = int(np.argmax(np.abs(dt - median)))
    largest = f"(the largest: {dt[i]:.6g} s, up to t = {t[i + 1]:.6g} s)"
    grid = _grid_times(t, median)
    retimed = ""
    if grid is not None and _stamps_jitter(A[1:, mi[4:]], dt, np.diff(grid[0])):
        t, period = grid
        retimed = (
            "the velocity increments follow a uniform rate, not the time stamps (the stamps "
            f"jitter): each row moved to the nearest multiple of {period:.6g} s from the first "
            "stamp"
        )
        if np.allclose(np.diff(t), period, rtol=1e-6):  # no sample missing
            out = A.copy()
            out[:, it] = t
            reason = (
                f"{int(off.sum())} of {dt.size} sample intervals differ from the median "
                f"{median:.6g} s by more than {IMU_PERIOD_TOLERANCE:.0%} {largest}, but "
                f"{retimed}, the rows kept as they are"
            )
            return out, {"check": "retimed", "column": TIME_COLUMN, "reason": reason}, t
        dt = np.diff(t)
        median = period
    span = float(t[-1] - t[0])
    m = int(np.maximum(1, np.round(dt / median)).sum())  # a dropped sample: 2 intervals
    tk = t[0] + (span / m) * np.arange(m + 1)
    U = np.empty((A.shape[0], 7))
    U[:, :3], U[:, 3:] = A[:, mi[4:]], A[:, mi[:4]]  # (dv, dq) composes as (dp, dq)
    U[0] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    V, Q = _integrate_pose(U)
    q = _slerp(tk, t, Q)
    v = np.column_stack([np.interp(tk, t, V[:, j]) for j in range(3)])
    out = np.full((tk.size, A.shape[1]), np.nan)
    out[:, it] = tk
    out[1:, mi[:4]] = quat_normalize(quat_mul(quat_conj(q[:-1]), q[1:]))
    out[1:, mi[4:]] = rotate(quat_conj(q[:-1]), np.diff(v, axis=0))
    quaternion = [col[c] for c in QUATERNION_TRUTH_COLUMNS if c in col]
    for j in range(A.shape[1]):
        have = ~absent[:, j]
        if j in (it, *mi, *quaternion) or not have.any():
            continue
        values = np.unwrap(A[have, j]) if j == col.get(YAW_TRUTH_COLUMN) else A[have, j]
        out[:, j] = np.interp(tk, t[have], values)
    if quaternion:
        have = ~absent[:, quaternion].any(axis=1)
        if have.sum() >= 2:
            out[:, quaternion] = _slerp(tk, t[have], quat_normalize(A[have][:, quaternion]))
    note = {
        "check": "resampled",
        "column": TIME_COLUMN,
        "reason": (
            f"{int(off.sum())} of {dt.size} sample intervals differ from the median "
            f"{median:.6g} s by more than {IMU_PERIOD_TOLERANCE:.0%} {largest}: "
            + (f"{retimed}, and " if retimed else "")
            + "the IMU increments, the "
            f"magnetometer and the truth were resampled onto a uniform grid of {span / m:.6g} s "
            f"({tk.size} rows from {A.shape[0]})"
        ),
    }
    return out, note, t


def _to_magnetometer_rows(
    path: str,
    A: np.ndarray,
    absent: np.ndarray,
    col: dict[str, int],
    motion: str,
    mi: list[int],
    yi: list[int],
    has_motion: np.ndarray,
    has_mag: np.ndarray,
    notes: list[dict[str, str]],
) -> tuple[np.ndarray, list[dict[str, str]]]:
    """Odometry and magnetometer at different rates: the dead reckoning integrated at the
    odometry's rows, interpolated linearly in time to the magnetometer's rows, and turned
    back into increments between them (planar: body-frame displacement and heading
    change; pose: positions interpolated linearly and orientations by slerp, then
    body-frame displacement and rotation between them); truth interpolated the same way.
    Magnetometer rows after the last odometry row cannot be placed and are dropped."""
    t = A[:, col[TIME_COLUMN]]
    tm = t[has_motion]
    U = np.where(absent[:, mi], 0.0, A[:, mi])[has_motion]
    U[0] = 0.0
    if motion == "pose":
        U[0, 3] = 1.0  # the start: dp = 0, dq = identity
        positions, orientations = _integrate_pose(U)
        pose = positions
    elif motion == "planar":
        psi = np.cumsum(U[:, 2])
        heading = np.r_[0.0, psi[:-1]]
        step = np.column_stack(
            [
                np.cos(heading) * U[:, 0] - np.sin(heading) * U[:, 1],
                np.sin(heading) * U[:, 0] + np.cos(heading) * U[:, 1],
            ]
        )
        pose = np.column_stack([np.cumsum(step, axis=0), psi])
    else:
        pose = np.cumsum(U, axis=0)
    keep = has_mag & (t <= tm[-1])
    dropped = int(np.sum(has_mag & ~keep))
    if keep.sum() < _MIN_ROWS:
        raise _error(
            path,
            "",
            f"needs at least {_MIN_ROWS} magnetometer rows within the odometry's time span "
            f"(got {int(keep.sum())})",
        )
    tk = t[keep]
    at = np.column_stack([np.interp(tk, tm, pose[:, k]) for k in range(pose.shape[1])])
    if motion == "pose":
        q = _slerp(tk, tm, orientations)
        inc = np.column_stack(
            [
                rotate(quat_conj(q[:-1]), np.diff(at, axis=0)),
                quat_normalize(quat_mul(quat_conj(q[:-1]), q[1:])),
            ]
        )
    elif motion == "planar":
        d = np.diff(at[:, :2], axis=0)
        h = at[:-1, 2]
        inc = np.column_stack(
            [
                np.cos(h) * d[:, 0] + np.sin(h) * d[:, 1],
                -np.sin(h) * d[:, 0] + np.cos(h) * d[:, 1],
                np.diff(at[:, 2]),
            ]
        )
    else:
        inc = np.diff(at, axis=0)
    out = A[keep].copy()
    out[0, mi] = np.nan
    out[1:, mi] = inc
    for name in (*POSITION_TRUTH_COLUMNS, YAW_TRUTH_COLUMN, *QUATERNION_TRUTH_COLUMNS):
        if name not in col:
            continue
        j = col[name]
        have = ~absent[:, j]
        if have[keep].all():
            continue
        if name in QUATERNION_TRUTH_COLUMNS or have.sum() < 2:
            i = int(np.flatnonzero(keep & ~have)[0])
            raise _error(
                path,
                f"row {i + 2}, column '{name}'",
                "empty value (this truth is needed on every magnetometer row)",
            )
        values = A[have, j]
        if name == YAW_TRUTH_COLUMN:
            values = np.unwrap(values)
        out[:, j] = np.interp(tk, t[have], values)
    n_motion, n_mag = int(has_motion[1:].sum()), int(has_mag.sum())
    reason = (
        f"odometry on {n_motion} rows and magnetometer on {n_mag}: the dead reckoning was "
        f"interpolated in time to the magnetometer's rows"
    )
    if dropped:
        reason += f"; {dropped} magnetometer rows after the last odometry row were dropped"
    notes.append(
        {"check": "resampled", "column": ", ".join(MAGNETOMETER_COLUMNS), "reason": reason}
    )
    return out, notes


def _check_resolution(path: str, U: np.ndarray, names: Sequence[str]) -> None:
    """Refuse a motion column whose values sum beyond RESOLUTION times its median non-zero
    step, naming its largest value (U: increments of rows 3.. of the file)."""
    for j, name in enumerate(names):
        size = np.abs(U[:, j])
        steps = size[size > 0]
        if steps.size == 0:
            continue
        typical = float(np.median(steps))
        reach = float(size.sum())
        if reach > RESOLUTION * typical:
            i = int(np.argmax(size))
            raise _error(
                path,
                f"row {i + 3}, column '{name}'",
                f"value {float(U[i, j]):g} is beyond what the numerics can carry: the column "
                f"sums to {reach:g}, where its median step {typical:g} is lost in float64 "
                "rounding",
            )


# --------------------------------------------------------------------------- writing
def _as_array(
    path: str, name: str, value: Any, rows: int, widths: Sequence[int] | None
) -> np.ndarray:
    """value as a float64 array of shape (rows,) (widths None) or (rows, w), w in widths."""
    A = np.asarray(value, dtype=np.float64)
    if widths is None:
        ok = A.shape == (rows,)
        expected = f"({rows},)"
    else:
        ok = A.ndim == 2 and A.shape[0] == rows and A.shape[1] in widths
        expected = " or ".join(f"({rows}, {w})" for w in widths)
    if not ok:
        raise _error(path, name, f"has shape {A.shape}, expected {expected}")
    if not np.all(np.isfinite(A)):
        raise _error(path, name, "contains NaN or infinite values")
    return A


def write_recording(
    path: str | Path,
    t: np.ndarray,
    Y: np.ndarray,
    *,
    dxy: np.ndarray | None = None,
    planar: np.ndarray | None = None,
    imu: np.ndarray | None = None,
    pose: np.ndarray | None = None,
    P_true: np.ndarray | None = None,
    yaw_true: np.ndarray | None = None,
    q_true: np.ndarray | None = None,
) -> None:
    """Write a recording CSV file that :func:`read_recording` reads back exactly.

    t: (N,) strictly increasing times [s]; Y: (N, 3) magnetometer, a row of NaN where it
    was not sampled (written as empty cells: a magnetometer slower than the motion input;
    at least two rows sampled). Exactly one motion input,
    given for steps 1..N-1 (the first row's increments are written as 0, pose's dq as 1):
    dxy (N-1, 2) or (N-1, 3) world-frame position increments [m] (columns dx, dy[, dz]);
    planar (N-1, 3) body-frame dfwd, dleft [m] and dyaw [rad]; imu (N-1, 7) dqw..dqz, dvx..dvz;
    pose (N-1, 7) dpx..dpz [m], dqw..dqz (unit quaternions; module docstring for the convention).
    Optional truth: P_true (N, 2) or (N, 3) [m], yaw_true (N,) [rad], q_true (N, 4) unit
    quaternions (w, x, y, z). Values are written in shortest round-trip form. The file is
    written atomically (a temporary file in the same folder, then renamed over ``path``).
    Raises DataError for inconsistent inputs or when the file cannot be written.
    """
    path = str(path)
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < _MIN_ROWS:
        raise _error(path, "t", f"has shape {t.shape}, expected (N,) with N >= {_MIN_ROWS}")
    n = t.shape[0]
    t = _as_array(path, "t", t, n, None)
    if not np.all(np.diff(t) > 0):
        raise _error(path, "t", "times must increase strictly")

    motions = {"dxy": dxy, "planar": planar, "imu": imu, "pose": pose}
    given = [name for name, value in motions.items() if value is not None]
    if len(given) != 1:
        raise _error(
            path, "", f"give exactly one motion input of dxy, planar, imu, pose (got {len(given)})"
        )
    kind = given[0]
    widths = {"dxy": (2, 3), "planar": (3,), "imu": (7,), "pose": (7,)}[kind]
    U = _as_array(path, kind, motions[kind], n - 1, widths)
    if kind == "pose":
        off = np.abs(np.linalg.norm(U[:, 3:], axis=1) - 1.0)
        if np.any(off > QUATERNION_TOLERANCE):
            i = int(np.argmax(off > QUATERNION_TOLERANCE))
            raise _error(path, "pose", f"rotation increment {i} is not unit norm")
    if kind == "dxy":
        motion_names = MOTION_COLUMNS["translation2" if U.shape[1] == 2 else "translation3"]
    else:
        motion_names = MOTION_COLUMNS[kind]

    names: list[str] = [TIME_COLUMN, *motion_names, *MAGNETOMETER_COLUMNS]
    first = np.zeros((1, U.shape[1]))
    if kind == "pose":
        first[0, 3] = 1.0  # the identity rotation
    blocks: list[np.ndarray] = [t[:, None], np.vstack([first, U])]
    Y = np.asarray(Y, dtype=np.float64)
    unsampled = np.isnan(Y).all(axis=1) if Y.ndim == 2 else np.zeros(0, bool)
    if unsampled.sum() > n - 2:
        raise _error(path, "Y", "needs at least two sampled rows (rows of NaN are not sampled)")
    sampled = _as_array(path, "Y", np.where(unsampled[:, None], 0.0, Y), n, (3,))
    blocks.append(np.where(unsampled[:, None], np.nan, sampled))
    if P_true is not None:
        P = _as_array(path, "P_true", P_true, n, (2, 3))
        names += POSITION_TRUTH_COLUMNS[: P.shape[1]]
        blocks.append(P)
    if yaw_true is not None:
        names.append(YAW_TRUTH_COLUMN)
        blocks.append(_as_array(path, "yaw_true", yaw_true, n, None)[:, None])
    if q_true is not None:
        q = _as_array(path, "q_true", q_true, n, (4,))
        off = np.abs(np.linalg.norm(q, axis=1) - 1.0)
        if np.any(off > QUATERNION_TOLERANCE):
            i = int(np.argmax(off > QUATERNION_TOLERANCE))
            raise _error(path, "q_true", f"quaternion {i} is not unit norm")
        names += QUATERNION_TRUTH_COLUMNS
        blocks.append(q)

    A = np.hstack(blocks)
    if unsampled.any():  # empty cells where the magnetometer was not sampled
        body = "\n".join(",".join("" if v != v else repr(v) for v in row) for row in A.tolist())
    else:
        body = "\n".join(",".join(map(repr, row)) for row in A.tolist())
    _write_atomic(path, ",".join(names) + "\n" + body + "\n")


def _write_atomic(path: str, text: str) -> None:
    """Write text to a temporary file next to path, then rename it over path."""
    folder = os.path.dirname(os.path.abspath(path))
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{secrets.token_hex(6)}.tmp")
    try:
        # os.open applies the umask, so the file gets the usual permissions.
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        try:
            with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.remove(tmp)
            raise
    except OSError as exc:
        raise _error(path, "", f"cannot write file ({exc.strerror or exc})") from None


def dataset_to_recording_arrays(dataset: Dataset, dt: float = 1.0) -> dict[str, np.ndarray]:
    """Keyword arguments for :func:`write_recording` that store a translational data set.

    Times are 0, dt, 2 dt, ... [s]; the increments U become ``dxy``; P_true is included when
    the data set has it. (The anchor, M_true and bias_true are not stored; on reading, the
    anchor is the first true position, or the origin without truth.)
    """
    if not dt > 0:
        raise ValueError(f"dt must be positive (got {dt})")
    arrays: dict[str, np.ndarray] = {
        "t": np.arange(dataset.n_samples, dtype=np.float64) * dt,
        "Y": np.asarray(dataset.Y, dtype=np.float64),
        "dxy": np.asarray(dataset.U, dtype=np.float64),
    }
    if dataset.P_true is not None:
        arrays["P_true"] = np.asarray(dataset.P_true, dtype=np.float64)
    return arrays
