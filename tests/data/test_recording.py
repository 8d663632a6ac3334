"""Recordings (casmag.data.recording): CSV round trips, conversion to a Dataset, one-line errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from casmag.data.recording import (
    MOTION_COLUMNS,
    Recording,
    dataset_to_recording_arrays,
    read_recording,
    write_recording,
)
from casmag.data.simulate import Dataset
from casmag.errors import DataError
from casmag.strapdown import quat_mul, rotate

GOOD_HEADER = "t,dx,dy,mx,my,mz"
GOOD_ROWS = ["0,,,1,2,3", "1,0.1,0.2,1.1,2.1,3.1", "2,0.1,0.2,1.2,2.2,3.2"]


def _write(tmp_path: Path, text: str, name: str = "rec.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _csv(header: str, rows: list[str]) -> str:
    return "\n".join([header, *rows]) + "\n"


def _error(path: Path | str) -> str:
    with pytest.raises(DataError) as info:
        read_recording(path)
    msg = str(info.value)
    assert "\n" not in msg and "\r" not in msg
    assert Path(path).name in msg
    return msg


def _random_walk(rng: np.random.Generator, n: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    P = np.cumsum(rng.standard_normal((n, d)), axis=0)
    return P, np.diff(P, axis=0)


def _unit_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# --------------------------------------------------------------------------- round trips
def test_round_trip_translation_2d_with_truth(tmp_path):
    rng = np.random.default_rng(0)
    n = 50
    t = np.cumsum(rng.uniform(0.01, 0.1, n))
    P, U = _random_walk(rng, n, 2)
    Y = rng.standard_normal((n, 3))
    path = tmp_path / "walk.csv"
    write_recording(path, t, Y, dxy=U, P_true=P)
    rec = read_recording(path)
    assert isinstance(rec, Recording)
    assert rec.path == str(path)
    assert rec.motion == "translation"
    assert rec.increment_names == MOTION_COLUMNS["translation2"] == ("dx", "dy")
    assert rec.n_samples == n and rec.dim == 2 and rec.has_truth
    np.testing.assert_array_equal(rec.t, t)
    np.testing.assert_array_equal(rec.increments, U)
    np.testing.assert_array_equal(rec.Y, Y)
    np.testing.assert_array_equal(rec.P_true, P)
    assert rec.yaw_true is None and rec.q_true is None
    for array in (rec.t, rec.increments, rec.Y, rec.P_true):
        assert array.dtype == np.float64
    header = path.read_text().splitlines()[0]
    assert header == "t,dx,dy,mx,my,mz,x_true,y_true"
    # No temporary files are left next to the recording.
    assert sorted(os.listdir(tmp_path)) == ["walk.csv"]


def test_round_trip_translation_3d_without_truth(tmp_path):
    rng = np.random.default_rng(0)
    n = 20
    t = np.arange(n) * 0.1
    _, U = _random_walk(rng, n, 3)
    Y = 40.0 * rng.standard_normal((n, 3))
    path = tmp_path / "walk3.csv"
    write_recording(path, t, Y, dxy=U)
    rec = read_recording(path)
    assert rec.increment_names == ("dx", "dy", "dz")
    assert rec.increments.shape == (n - 1, 3)
    assert rec.dim == 3 and not rec.has_truth
    np.testing.assert_array_equal(rec.t, t)
    np.testing.assert_array_equal(rec.increments, U)
    np.testing.assert_array_equal(rec.Y, Y)
    assert rec.P_true is None and rec.yaw_true is None and rec.q_true is None


def test_round_trip_planar_with_yaw(tmp_path):
    rng = np.random.default_rng(0)
    n = 30
    t = 100.0 + np.arange(n) * 0.02
    planar = rng.standard_normal((n - 1, 3))
    Y = rng.standard_normal((n, 3))
    P, _ = _random_walk(rng, n, 2)
    yaw = rng.uniform(-np.pi, np.pi, n)
    path = tmp_path / "planar.csv"
    write_recording(path, t, Y, planar=planar, P_true=P, yaw_true=yaw)
    rec = read_recording(path)
    assert rec.motion == "planar"
    assert rec.increment_names == MOTION_COLUMNS["planar"] == ("dfwd", "dleft", "dyaw")
    assert rec.dim == 2 and rec.has_truth
    np.testing.assert_array_equal(rec.increments, planar)
    np.testing.assert_array_equal(rec.Y, Y)
    np.testing.assert_array_equal(rec.P_true, P)
    np.testing.assert_array_equal(rec.yaw_true, yaw)
    assert rec.yaw_true.shape == (n,)


def test_round_trip_imu_with_quaternion(tmp_path):
    rng = np.random.default_rng(0)
    n = 25
    t = np.arange(n) * 0.01
    imu = np.hstack([_unit_quaternions(rng, n - 1), rng.standard_normal((n - 1, 3))])
    Y = rng.standard_normal((n, 3))
    P, _ = _random_walk(rng, n, 3)
    q = _unit_quaternions(rng, n)
    path = tmp_path / "imu.csv"
    write_recording(path, t, Y, imu=imu, P_true=P, q_true=q)
    rec = read_recording(path)
    assert rec.motion == "imu"
    assert rec.increment_names == MOTION_COLUMNS["imu"]
    assert rec.increments.shape == (n - 1, 7)
    assert rec.dim == 3
    np.testing.assert_array_equal(rec.increments, imu)
    np.testing.assert_array_equal(rec.P_true, P)
    np.testing.assert_array_equal(rec.q_true, q)
    assert rec.q_true.shape == (n, 4)


def test_write_overwrites_existing_file(tmp_path):
    path = tmp_path / "rec.csv"
    path.write_text("old content\n")
    t = np.array([0.0, 1.0, 2.0])
    write_recording(path, t, np.ones((3, 3)), dxy=np.ones((2, 2)))
    assert read_recording(path).n_samples == 3
    assert sorted(os.listdir(tmp_path)) == ["rec.csv"]


# --------------------------------------------------------------------------- reading details
def test_column_order_whitespace_and_first_row(tmp_path):
    text = _csv(
        " mz , t ,my,dy, dx ,mx,y_true,x_true",
        ["0,0,2,nan,,1,5,4", "-1, 1, -2, 0.5, 0.25, -3, 6, 7", "-1,2,-2,0.5,0.25,-3,6,7"],
    )
    rec = read_recording(_write(tmp_path, text))
    np.testing.assert_array_equal(rec.t, [0, 1, 2])
    assert rec.increment_names == ("dx", "dy")
    np.testing.assert_array_equal(rec.increments, [[0.25, 0.5], [0.25, 0.5]])
    np.testing.assert_array_equal(rec.Y[0], [1, 2, 0])
    np.testing.assert_array_equal(rec.Y[1], [-3, -2, -1])
    np.testing.assert_array_equal(rec.P_true[0], [4, 5])


def test_crlf_trailing_blank_lines_and_bom(tmp_path):
    path = tmp_path / "win.csv"
    path.write_bytes(("\ufeff" + "\r\n".join([GOOD_HEADER, *GOOD_ROWS]) + "\r\n\r\n").encode())
    rec = read_recording(path)
    assert rec.n_samples == 3


def test_first_row_increments_may_be_any_finite_number(tmp_path):
    rec = read_recording(_write(tmp_path, _csv(GOOD_HEADER, ["0,9,-9,1,2,3", *GOOD_ROWS[1:]])))
    np.testing.assert_array_equal(rec.increments, [[0.1, 0.2], [0.1, 0.2]])


def test_reads_100k_rows(tmp_path):
    rng = np.random.default_rng(0)
    n = 100_000
    t = np.arange(n) * 0.01
    P, U = _random_walk(rng, n, 2)
    Y = rng.standard_normal((n, 3))
    path = tmp_path / "big.csv"
    write_recording(path, t, Y, dxy=U, P_true=P)
    rec = read_recording(path)
    assert rec.n_samples == n
    np.testing.assert_array_equal(rec.increments, U)
    np.testing.assert_array_equal(rec.P_true, P)


# --------------------------------------------------------------------------- to_dataset
def test_to_dataset_with_truth(tmp_path):
    rng = np.random.default_rng(0)
    n = 10
    P, U = _random_walk(rng, n, 2)
    Y = rng.standard_normal((n, 3))
    path = tmp_path / "rec.csv"
    write_recording(path, np.arange(n, dtype=float), Y, dxy=U, P_true=P)
    data = read_recording(path).to_dataset()
    assert isinstance(data, Dataset)
    assert data.U.shape == (n - 1, 2) and data.Y.shape == (n, 3) and data.anchor.shape == (2,)
    np.testing.assert_array_equal(data.U, U)
    np.testing.assert_array_equal(data.Y, Y)
    np.testing.assert_array_equal(data.anchor, P[0])
    np.testing.assert_array_equal(data.P_true, P)
    assert data.M_true is None and data.bias_true is None
    np.testing.assert_allclose(data.dead_reckoning(), P, atol=1e-12)


def test_to_dataset_without_truth_anchors_at_origin(tmp_path):
    rng = np.random.default_rng(0)
    n = 8
    _, U = _random_walk(rng, n, 3)
    path = tmp_path / "rec.csv"
    write_recording(path, np.arange(n, dtype=float), rng.standard_normal((n, 3)), dxy=U)
    data = read_recording(path).to_dataset()
    assert data.U.shape == (n - 1, 3) and data.dim == 3
    np.testing.assert_array_equal(data.anchor, np.zeros(3))
    assert data.P_true is None


@pytest.mark.parametrize(
    ("kind", "width"),
    [("planar", 3), ("imu", 7)],
)
def test_to_dataset_rejects_planar_and_imu(tmp_path, kind, width):
    rng = np.random.default_rng(0)
    n = 5
    U = rng.standard_normal((n - 1, width))
    if kind == "imu":
        U[:, :4] = _unit_quaternions(rng, n - 1)
    path = tmp_path / f"{kind}.csv"
    write_recording(path, np.arange(n, dtype=float), rng.standard_normal((n, 3)), **{kind: U})
    rec = read_recording(path)
    with pytest.raises(DataError) as info:
        rec.to_dataset()
    msg = str(info.value)
    assert msg == f"{path}: motion input '{kind}' is not supported by this solver yet"


def test_dataset_to_recording_arrays_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    n = 12
    P, U = _random_walk(rng, n, 2)
    data = Dataset(U=U, Y=rng.standard_normal((n, 3)), anchor=P[0], P_true=P)
    path = tmp_path / "sim.csv"
    write_recording(path, **dataset_to_recording_arrays(data, dt=0.5))
    back = read_recording(path)
    np.testing.assert_array_equal(back.t, np.arange(n) * 0.5)
    back_data = back.to_dataset()
    np.testing.assert_array_equal(back_data.U, data.U)
    np.testing.assert_array_equal(back_data.Y, data.Y)
    np.testing.assert_array_equal(back_data.anchor, data.anchor)


# --------------------------------------------------------------------------- file errors
def test_missing_file(tmp_path):
    msg = _error(tmp_path / "nope.csv")
    assert "cannot read" in msg


def test_directory_is_unreadable(tmp_path):
    folder = tmp_path / "folder.csv"
    folder.mkdir()
    msg = _error(folder)
    assert "cannot read" in msg


def test_not_utf8(tmp_path):
    path = tmp_path / "binary.csv"
    path.write_bytes(b"t,dx\xff\xfe\n")
    msg = _error(path)
    assert "cannot read" in msg


def test_empty_file(tmp_path):
    assert "empty file" in _error(_write(tmp_path, ""))


def test_whitespace_only_file(tmp_path):
    assert "empty file" in _error(_write(tmp_path, "\n  \n"))


def test_header_only(tmp_path):
    msg = _error(_write(tmp_path, GOOD_HEADER + "\n"))
    assert "needs at least 2 rows" in msg


def test_one_data_row(tmp_path):
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, GOOD_ROWS[:1])))
    assert "needs at least 2 rows" in msg and "got 1" in msg


# --------------------------------------------------------------------------- header errors
def test_missing_time_column(tmp_path):
    msg = _error(_write(tmp_path, _csv("dx,dy,mx,my,mz", ["0,0,1,2,3", "1,1,1,2,3"])))
    assert "missing column 't'" in msg


@pytest.mark.parametrize("dropped", ["mx", "my", "mz"])
def test_missing_magnetometer_column(tmp_path, dropped):
    names = [c for c in GOOD_HEADER.split(",") if c != dropped]
    rows = ["0" + ",1" * (len(names) - 1), "1" + ",1" * (len(names) - 1)]
    msg = _error(_write(tmp_path, _csv(",".join(names), rows)))
    assert "magnetometer" in msg and dropped in msg


def test_no_motion_input(tmp_path):
    msg = _error(_write(tmp_path, _csv("t,mx,my,mz", ["0,1,2,3", "1,1,2,3"])))
    assert "no motion input: expected one of dx,dy | dfwd,dleft,dyaw | dqw,...,dvz" in msg


def test_mixed_motion_inputs(tmp_path):
    header = "t,dx,dy,dfwd,dleft,dyaw,mx,my,mz"
    msg = _error(_write(tmp_path, _csv(header, ["0,0,0,0,0,0,1,2,3", "1,0,0,0,0,0,1,2,3"])))
    assert "mixed motion inputs" in msg
    assert "translation (dx, dy)" in msg and "planar (dfwd, dleft, dyaw)" in msg


def test_incomplete_translation(tmp_path):
    msg = _error(_write(tmp_path, _csv("t,dx,mx,my,mz", ["0,0,1,2,3", "1,0,1,2,3"])))
    assert "incomplete translation input" in msg and "missing column dy" in msg


def test_dz_without_dx_dy(tmp_path):
    msg = _error(_write(tmp_path, _csv("t,dz,mx,my,mz", ["0,0,1,2,3", "1,0,1,2,3"])))
    assert "missing columns dx, dy" in msg


def test_incomplete_imu(tmp_path):
    header = "t,dqw,dqx,dqy,dqz,mx,my,mz"
    msg = _error(_write(tmp_path, _csv(header, ["0,1,0,0,0,1,2,3", "1,1,0,0,0,1,2,3"])))
    assert "incomplete imu input" in msg and "dvx, dvy, dvz" in msg


def test_incomplete_planar(tmp_path):
    header = "t,dfwd,dyaw,mx,my,mz"
    msg = _error(_write(tmp_path, _csv(header, ["0,0,0,1,2,3", "1,0,0,1,2,3"])))
    assert "incomplete planar input" in msg and "dleft" in msg


def test_incomplete_position_truth(tmp_path):
    header = GOOD_HEADER + ",x_true"
    msg = _error(_write(tmp_path, _csv(header, [r + ",0" for r in GOOD_ROWS])))
    assert "incomplete truth group" in msg and "y_true" in msg


def test_incomplete_quaternion_truth(tmp_path):
    header = GOOD_HEADER + ",qw_true,qx_true,qy_true"
    msg = _error(_write(tmp_path, _csv(header, [r + ",1,0,0" for r in GOOD_ROWS])))
    assert "incomplete truth group" in msg and "qz_true" in msg


def test_truth_dimension_must_match_translation(tmp_path):
    header = GOOD_HEADER + ",x_true,y_true,z_true"
    msg = _error(_write(tmp_path, _csv(header, [r + ",0,0,0" for r in GOOD_ROWS])))
    assert "3-D" in msg and "2-D" in msg


def test_unknown_column(tmp_path):
    header = GOOD_HEADER + ",temperature"
    msg = _error(_write(tmp_path, _csv(header, [r + ",20" for r in GOOD_ROWS])))
    assert "unknown column" in msg and "'temperature'" in msg


def test_names_are_case_sensitive(tmp_path):
    msg = _error(_write(tmp_path, _csv("t,DX,dy,mx,my,mz", GOOD_ROWS)))
    assert "unknown column" in msg and "'DX'" in msg and "did you mean 'dx'" in msg


def test_a_bare_coordinate_column_is_not_matched_to_the_magnetometer(tmp_path):
    msg = _error(_write(tmp_path, _csv("t,x,y,mx,my,mz", GOOD_ROWS)))
    assert "'x'" in msg and "mx" not in msg.split("unknown column")[1]
    assert "'x_true'" in msg and "'dx'" in msg


def test_close_names_only_are_suggested(tmp_path):
    msg = _error(_write(tmp_path, _csv("t,dx,dy,mxx,my,mz", GOOD_ROWS)))
    assert "did you mean 'mx'" in msg
    msg = _error(_write(tmp_path, _csv("t,dx,dy,mx,my,mz,foo", [r + ",1" for r in GOOD_ROWS])))
    assert "did you mean" not in msg and "known columns: t, dx" in msg


@pytest.mark.parametrize(("sep", "what"), [(";", "semicolons"), ("\t", "tabs")])
def test_another_delimiter_is_named(tmp_path, sep, what):
    text = _csv(GOOD_HEADER, GOOD_ROWS).replace(",", sep)
    msg = _error(_write(tmp_path, text))
    assert f"separated by {what}" in msg and "row 1" in msg and msg.count("\n") == 0


def test_a_file_without_header_is_named_as_such(tmp_path):
    msg = _error(_write(tmp_path, _csv(GOOD_ROWS[1], GOOD_ROWS[2:])))
    assert "row 1" in msg and "holds numbers, not column names" in msg
    assert "duplicate" not in msg


def test_duplicate_column(tmp_path):
    header = GOOD_HEADER + ",mx"
    msg = _error(_write(tmp_path, _csv(header, [r + ",1" for r in GOOD_ROWS])))
    assert "duplicate column" in msg and "'mx'" in msg


def test_empty_column_name(tmp_path):
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER + ",", [r + "," for r in GOOD_ROWS])))
    assert "column 7" in msg and "empty column name" in msg


# --------------------------------------------------------------------------- value errors
def test_non_numeric_value(tmp_path):
    rows = [GOOD_ROWS[0], "1,0.1,abc,1,2,3", GOOD_ROWS[2]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 3" in msg and "column 'dy'" in msg and "not a number" in msg and "abc" in msg


def test_non_numeric_value_in_first_row(tmp_path):
    rows = ["zero,,,1,2,3", *GOOD_ROWS[1:]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 2" in msg and "column 't'" in msg


def test_empty_value_outside_first_row_motion(tmp_path):
    rows = [GOOD_ROWS[0], GOOD_ROWS[1], "2,0.1,0.2,1.2,,3.2"]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 4" in msg and "column 'my'" in msg and "empty value" in msg


def test_empty_magnetometer_value_in_first_row(tmp_path):
    rows = ["0,,,,2,3", *GOOD_ROWS[1:]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 2" in msg and "column 'mx'" in msg and "empty value" in msg


def test_empty_motion_value_in_second_row(tmp_path):
    rows = [GOOD_ROWS[0], "1,,0.2,1.1,2.1,3.1", GOOD_ROWS[2]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 3" in msg and "column 'dx'" in msg and "empty value" in msg


def test_nan_value(tmp_path):
    rows = [GOOD_ROWS[0], "1,0.1,0.2,1.1,2.1,NaN", GOOD_ROWS[2]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 3" in msg and "column 'mz'" in msg and "NaN" in msg


def test_nan_time_in_first_row(tmp_path):
    rows = ["nan,,,1,2,3", *GOOD_ROWS[1:]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 2" in msg and "column 't'" in msg and "NaN" in msg


def test_inf_value(tmp_path):
    rows = [*GOOD_ROWS[:2], "2,0.1,-inf,1.2,2.2,3.2"]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 4" in msg and "column 'dy'" in msg and "infinite" in msg


def test_inf_in_first_row_motion(tmp_path):
    rows = ["0,inf,,1,2,3", *GOOD_ROWS[1:]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 2" in msg and "column 'dx'" in msg and "infinite" in msg


def test_time_not_increasing(tmp_path):
    rows = [*GOOD_ROWS, "3,0,0,1,2,3", "2.5,0,0,1,2,3", "1,0,0,1,2,3"]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 6" in msg and "2.5" in msg and "3.0" in msg and "'t'" in msg


def test_rows_of_one_time_stamp_are_merged(tmp_path):
    rows = [GOOD_ROWS[0], "1,0.1,0.2,1,2,3", "1,0.3,0.4,3,4,5", "2,0.1,0.2,1.2,2.2,3.2"]
    rec = read_recording(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    np.testing.assert_array_equal(rec.t, [0, 1, 2])
    np.testing.assert_allclose(rec.increments, [[0.4, 0.6], [0.1, 0.2]])  # summed
    np.testing.assert_allclose(rec.Y[1], [2, 3, 4])  # averaged
    assert [n["check"] for n in rec.notes] == ["duplicate_time"]
    assert "1 rows repeat the previous row's time stamp" in rec.notes[0]["reason"]


def test_imu_increments_of_one_time_stamp_are_composed(tmp_path):
    """Two IMU rows of one time stamp are one interval: dq = dq1 dq2 and dv = dv1 + R(dq1)
    dv2 (what strapdown integration over a zero interval gives), not their sums."""
    rng = np.random.default_rng(5)
    dq = _unit_quaternions(rng, 3)
    dv = rng.standard_normal((3, 3))
    times = [0.01, 0.01, 0.02]
    rows = ["0,,,,,,,,1,2,3"] + [
        ",".join(repr(float(v)) for v in [times[k], *dq[k], *dv[k], 1.0, 2.0, 3.0 + k])
        for k in range(3)
    ]
    header = "t," + ",".join(MOTION_COLUMNS["imu"]) + ",mx,my,mz"
    rec = read_recording(_write(tmp_path, _csv(header, rows)))
    np.testing.assert_array_equal(rec.t, [0.0, 0.01, 0.02])
    q12 = quat_mul(dq[0], dq[1])
    np.testing.assert_allclose(rec.increments[0, :4], q12 / np.linalg.norm(q12), atol=1e-12)
    np.testing.assert_allclose(rec.increments[0, 4:], dv[0] + rotate(dq[0], dv[1]), atol=1e-12)
    np.testing.assert_allclose(rec.increments[1], np.r_[dq[2], dv[2]], atol=1e-12)
    assert "motion increments composed" in rec.notes[0]["reason"]


def test_time_going_back_is_refused(tmp_path):
    rows = [GOOD_ROWS[0], "1,0.1,0.2,1,2,3", "0.5,0.1,0.2,1,2,3"]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 4" in msg and "before the previous row's 1.0" in msg


def _two_rates(motion: str, n: int = 41):
    """A curving walk: poses at 20 Hz; odometry rows at 20 Hz, magnetometer rows at 10 Hz
    between them (t = 0.025 + 0.1 k), one file with empty cells. Returns the CSV text and
    the true poses at the magnetometer rows."""
    t = np.arange(n) * 0.05
    psi = 0.8 * t
    pos = np.column_stack([np.sin(psi) / 0.8 * 0.5, (1 - np.cos(psi)) / 0.8 * 0.5])
    rows = []
    tm = np.arange(0.025, t[-1] - 0.1, 0.1)
    events = [(ti, "odo", i) for i, ti in enumerate(t)] + [
        (ti, "mag", i) for i, ti in enumerate(tm)
    ]
    for ti, kind, i in sorted(events):
        if kind == "odo":
            if motion == "planar":
                d = pos[i] - pos[i - 1] if i else np.zeros(2)
                h = psi[i - 1] if i else 0.0
                inc = [np.cos(h) * d[0] + np.sin(h) * d[1], -np.sin(h) * d[0] + np.cos(h) * d[1]]
                inc.append(psi[i] - psi[i - 1] if i else 0.0)
            else:
                inc = list(pos[i] - pos[i - 1]) if i else [0.0, 0.0]
            rows.append([f"{ti:.4f}", *(f"{v:.12g}" for v in inc), "", "", "", "", ""])
        else:
            x, y = np.interp(ti, t, pos[:, 0]), np.interp(ti, t, pos[:, 1])
            rows.append([f"{ti:.4f}", *([""] * (3 if motion == "planar" else 2)), "1", "2", "3",
                         f"{x:.12g}", f"{y:.12g}"])  # fmt: skip
    names = "dfwd,dleft,dyaw" if motion == "planar" else "dx,dy"
    header = f"t,{names},mx,my,mz,x_true,y_true"
    return _csv(header, [",".join(r) for r in rows]), tm


@pytest.mark.parametrize("motion", ["translation", "planar"])
def test_odometry_and_magnetometer_at_two_rates_are_brought_to_the_magnetometer_rows(
    tmp_path, motion
):
    text, tm = _two_rates(motion)
    rec = read_recording(_write(tmp_path, text))
    np.testing.assert_allclose(rec.t, tm, atol=1e-9)
    assert rec.motion == motion and rec.increments.shape == (
        tm.size - 1,
        3 if motion == "planar" else 2,
    )
    if motion == "planar":
        from casmag.model.planar import dead_reckon_planar

        P, _ = dead_reckon_planar(rec.increments, rec.P_true[0], 0.8 * tm[0])
    else:
        P = rec.P_true[0] + np.vstack([np.zeros(2), np.cumsum(rec.increments, axis=0)])
    # the dead reckoning at the magnetometer rows, up to linear interpolation between 20 Hz
    # odometry rows on a 0.6 m circle
    assert np.abs(P - rec.P_true).max() < 2e-3
    assert [n["check"] for n in rec.notes] == ["resampled"]
    assert "odometry on 40 rows and magnetometer on" in rec.notes[0]["reason"]


def test_magnetometer_rows_after_the_last_odometry_row_are_dropped(tmp_path):
    rows = [GOOD_ROWS[0], "1,0.1,0.2,,,", "1.5,,,1,2,3", "2,0.1,0.2,1.2,2.2,3.2", "3,,,1,2,3"]
    rec = read_recording(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    np.testing.assert_array_equal(rec.t, [0, 1.5, 2])
    np.testing.assert_allclose(rec.increments, [[0.15, 0.3], [0.05, 0.1]])
    assert "1 magnetometer rows after the last odometry row were dropped" in rec.notes[0]["reason"]


def test_a_group_given_in_part_is_refused(tmp_path):
    rows = [GOOD_ROWS[0], "1,0.1,,1,2,3", GOOD_ROWS[2]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 3, column 'dy': empty value (the columns dx, dy are given together" in msg


@pytest.mark.parametrize(
    ("row", "fields"),
    [("1,0.1,0.2,1.1,2.1", 5), ("1,0.1,0.2,1.1,2.1,3.1,7", 7)],
)
def test_wrong_number_of_fields(tmp_path, row, fields):
    rows = [GOOD_ROWS[0], row, GOOD_ROWS[2]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 3" in msg and f"has {fields} fields, expected 6" in msg


def test_blank_row_in_the_middle(tmp_path):
    rows = [GOOD_ROWS[0], "", *GOOD_ROWS[1:]]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows)))
    assert "row 3" in msg and "empty row" in msg


def test_quaternion_truth_not_unit(tmp_path):
    header = GOOD_HEADER + ",qw_true,qx_true,qy_true,qz_true"
    quats = [",1,0,0,0", ",0.6,0.8,0,0", ",0.6,0.8,0.1,0"]
    rows = [r + q for r, q in zip(GOOD_ROWS, quats, strict=True)]
    msg = _error(_write(tmp_path, _csv(header, rows)))
    assert "row 4" in msg and "quaternion" in msg and "norm" in msg


def test_quaternion_truth_within_tolerance_is_accepted(tmp_path):
    header = GOOD_HEADER + ",qw_true,qx_true,qy_true,qz_true"
    quats = [",1,0,0,0", ",1.0009,0,0,0", ",0,0,0,0.9991"]
    rows = [r + q for r, q in zip(GOOD_ROWS, quats, strict=True)]
    rec = read_recording(_write(tmp_path, _csv(header, rows)))
    assert rec.q_true.shape == (3, 4)


def test_error_names_file_and_reports_first_problem_only(tmp_path):
    rows = [GOOD_ROWS[0], "1,x,0.2,1,2,3", "2,y,0.2,1,2,3"]
    msg = _error(_write(tmp_path, _csv(GOOD_HEADER, rows), name="first.csv"))
    assert msg.startswith(str(tmp_path / "first.csv") + ": row 3")
    assert "row 4" not in msg


# --------------------------------------------------------------------------- write errors
def _write_error(tmp_path: Path, **kwargs) -> str:
    path = tmp_path / "out.csv"
    args = {"t": np.arange(3.0), "Y": np.zeros((3, 3)), "dxy": np.zeros((2, 2))}
    args.update(kwargs)
    args = {k: v for k, v in args.items() if v is not None}
    with pytest.raises(DataError) as info:
        write_recording(path, args.pop("t"), args.pop("Y"), **args)
    msg = str(info.value)
    assert "\n" not in msg and "out.csv" in msg
    assert not path.exists()
    assert os.listdir(tmp_path) == []
    return msg


def test_write_needs_exactly_one_motion_input(tmp_path):
    assert "exactly one motion input" in _write_error(tmp_path, dxy=None)
    assert "exactly one motion input" in _write_error(tmp_path, planar=np.zeros((2, 3)))


def test_write_checks_shapes(tmp_path):
    assert "dxy" in _write_error(tmp_path, dxy=np.zeros((3, 2)))
    assert "Y" in _write_error(tmp_path, Y=np.zeros((3, 2)))
    assert "P_true" in _write_error(tmp_path, P_true=np.zeros((3, 4)))


def test_write_checks_values(tmp_path):
    assert "t" in _write_error(tmp_path, t=np.array([0.0, 2.0, 1.0]))
    assert "NaN" in _write_error(tmp_path, Y=np.full((3, 3), np.nan))
    assert "q_true" in _write_error(tmp_path, q_true=np.ones((3, 4)))


def test_write_into_missing_folder(tmp_path):
    path = tmp_path / "no" / "such" / "folder.csv"
    with pytest.raises(DataError) as info:
        write_recording(path, np.arange(3.0), np.zeros((3, 3)), dxy=np.zeros((2, 2)))
    assert "cannot write" in str(info.value) and "folder.csv" in str(info.value)


@pytest.mark.parametrize(
    ("header", "name", "casmag_name"),
    [
        ("time,dx,dy,mx,my,mz", "time", "t"),
        ("timestamp,dx,dy,mx,my,mz", "timestamp", "t"),
        ("t,dx,dy,mag_x,my,mz", "mag_x", "mx"),
        ("t,dx,dy,mx,magY,mz", "magY", "my"),
        ("t,dx,dy,mx,my,Bz", "Bz", "mz"),
    ],
)
def test_other_logs_names_for_time_and_field_are_named(tmp_path, header, name, casmag_name):
    msg = _error(_write(tmp_path, _csv(header, GOOD_ROWS)))
    assert f"column '{name}': unknown column (casmag names this column '{casmag_name}')" in msg


def test_a_problem_file_given_as_a_recording_is_named(tmp_path):
    path = tmp_path / "walk.yaml"
    path.write_text("# a problem\nseed: 1\n")
    msg = _error(path)
    assert "not a CSV recording (it reads as YAML" in msg and "casmag solve FILE" in msg


def test_a_comment_line_before_the_header_is_named(tmp_path):
    msg = _error(_write(tmp_path, "# logged by an app\n" + _csv(GOOD_HEADER, GOOD_ROWS)))
    assert "row 1: a comment line; the first row must be the header" in msg
