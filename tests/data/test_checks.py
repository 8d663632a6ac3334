"""Plausibility checks on recordings (casmag.data.checks): wrong units and columns are named in a
warning, on stderr and in result.json, and real recordings raise none."""

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from casmag.cli.main import main
from casmag.data.checks import model_warnings, recording_warnings
from casmag.data.recording import read_recording, write_recording

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "magnetic-data" / "invensense"


def _walk(n=400, hz=10.0, speed=0.5, seed=0):
    """A walk at ``speed`` m/s sampled at ``hz``, a microtesla field: t, increments, Y, P."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0.0, 0.1, n - 1))
    steps = speed / hz * np.column_stack([np.cos(heading), np.sin(heading)])
    P = np.vstack([np.zeros(2), np.cumsum(steps, axis=0)])
    Y = np.column_stack([20 + 5 * np.sin(P[:, 0]), -5 + 5 * np.cos(P[:, 1]), np.full(n, 40.0)])
    Y = Y + rng.normal(0.0, 0.5, Y.shape)
    return np.arange(n) / hz, steps, Y, P


def _checks(t, U, Y, motion="translation"):
    return {w["check"] for w in recording_warnings(t, U, Y, motion)}


def test_a_plausible_walk_raises_nothing():
    t, U, Y, P = _walk()
    assert _checks(t, U, Y) == set()
    assert model_warnings(P, Y, lengthscale=1.0, sigma_m=0.5) == []


def test_time_in_milliseconds_is_named():
    t, U, Y, _ = _walk()
    found = recording_warnings(1000.0 * t, U, Y, "translation")
    assert [w["check"] for w in found] == ["time_unit"]
    assert found[0]["column"] == "t" and "milliseconds" in found[0]["reason"]


def test_time_in_minutes_is_named_by_the_speed():
    t, U, Y, _ = _walk()
    found = recording_warnings(t / 60.0, U, Y, "translation")
    assert [w["check"] for w in found] == ["speed"] and "t in minutes" in found[0]["reason"]


@pytest.mark.parametrize("case", ["centimetres", "cumulative"])
def test_increments_in_centimetres_or_cumulative_are_named(case):
    t, U, Y, P = _walk()
    U = 100.0 * U if case == "centimetres" else P[1:]
    found = recording_warnings(t, U, Y, "translation")
    assert [w["check"] for w in found] == ["speed"]
    assert "centimetres" in found[0]["reason"] and "cumulative" in found[0]["reason"]


def test_planar_speed_uses_the_displacement_columns_only():
    t, U, Y, _ = _walk()
    planar = np.column_stack([np.linalg.norm(U, axis=1), np.zeros(len(U)), np.full(len(U), 0.5)])
    assert _checks(t, planar, Y, "planar") == set()  # a large heading column is not a speed
    planar[:, 0] *= 100.0
    assert _checks(t, planar, Y, "planar") == {"speed"}


def test_a_heading_increment_in_degrees_is_named():
    t, U, Y, _ = _walk()
    rng = np.random.default_rng(3)
    dyaw = rng.normal(0.0, 0.05, len(U))  # 0.5 rad/s turns at 10 Hz
    planar = np.column_stack([np.linalg.norm(U, axis=1), np.zeros(len(U)), dyaw])
    assert _checks(t, planar, Y, "planar") == set()
    planar[:, 2] = np.degrees(dyaw)
    found = recording_warnings(t, planar, Y, "planar")
    assert [w["check"] for w in found] == ["turn_rate"] and "degrees" in found[0]["reason"]


@pytest.mark.parametrize(("scale", "unit"), [(1e-6, "tesla"), (1e3, "nanotesla")])
def test_the_field_in_tesla_or_nanotesla_is_named(scale, unit):
    t, U, Y, _ = _walk()
    found = recording_warnings(t, U, scale * Y, "translation")
    assert [w["check"] for w in found] == ["field_unit"] and unit in found[0]["reason"]


def test_sigma_m_in_another_unit_and_bad_lengthscales_are_named():
    _, _, Y, P = _walk()
    found = model_warnings(P, Y / 100.0, lengthscale=1.0, sigma_m=0.5)  # gauss, sigma_m in uT
    assert [w["column"] for w in found] == ["model.magnetometer.sigma_m"]
    extent = float(np.ptp(P, axis=0).max())
    found = model_warnings(P, Y, lengthscale=2 * extent, sigma_m=0.5)
    assert [w["check"] for w in found] == ["lengthscale"] and "extent" in found[0]["reason"]
    found = model_warnings(P, Y, lengthscale=0.01, sigma_m=0.5)  # steps of 5 cm
    assert [w["check"] for w in found] == ["lengthscale"] and "step" in found[0]["reason"]


def test_slam_prints_the_warning_and_records_it(tmp_path):
    t, U, _, P = _walk(n=80)
    rec = tmp_path / "ms.csv"
    Y = np.tile([20.0, -5.0, 40.0], (80, 1))  # constant: the odometry is the result, fast
    write_recording(rec, 1000.0 * t, Y, dxy=U, P_true=P)
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["slam", str(rec), "--out", str(out), "-q", "--no-figures"])
    assert res.exit_code == 0, res.output
    line = f"casmag: warning: {rec}: t: median sample interval 100 s"
    assert res.stderr.startswith(line) and res.stderr.count("\n") == 1
    r = json.loads((out / "result.json").read_text())
    assert [w["check"] for w in r["warnings"]] == ["time_unit"]


@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data (real recordings) not found")
@pytest.mark.parametrize("motion", ["translational", "planar"])
@pytest.mark.parametrize("seq", [1, 2, 3, 4, 5])
def test_the_real_recordings_raise_no_warning(tmp_path, seq, motion):
    rec = tmp_path / f"seq{seq}.csv"
    convert = ["convert", str(SHARED / str(seq)), "--out", str(rec), "--no-align"]
    convert += ["--motion", motion]
    res = CliRunner().invoke(main, convert)  # the clock alignment changes no unit
    assert res.exit_code == 0, res.output
    r = read_recording(rec)
    assert recording_warnings(r.t, r.increments, r.Y, r.motion) == []
    if motion == "translational":
        P = np.vstack([np.zeros(2), np.cumsum(r.increments, axis=0)])
        assert model_warnings(P, r.Y, lengthscale=0.3, sigma_m=2.0) == []


def _recorded(n=60, seed=0):
    """A data set as a recording gives it: increments and a field in microtesla, no
    simulated field (M_true None)."""
    from casmag.data.simulate import Dataset

    rng = np.random.default_rng(seed)
    return Dataset(
        U=rng.normal(0.1, 0.01, (n - 1, 2)), Y=45.0 + rng.normal(0, 1, (n, 3)), anchor=np.zeros(2)
    )


GIVEN = {
    "model.gp.sigma_f": 5.0,
    "model.gp.lengthscale": 0.5,
    "model.magnetometer.sigma_m": 1.0,
    "model.odometry.sigma": 0.01,
}


@pytest.mark.parametrize(
    "key",
    [
        "model.gp.sigma_f",
        "model.gp.lengthscale",
        "model.magnetometer.sigma_m",
        "model.odometry.sigma",
    ],
)
def test_null_settings_on_data_not_simulated_are_refused(key):
    import casmag

    problem = casmag.load_problem(
        "problems/paper/base.yaml", {k: v for k, v in GIVEN.items() if k != key}
    )
    with pytest.raises(casmag.ProblemError) as err:
        casmag.solve(problem, data=_recorded())
    assert err.value.field == key
    assert "null takes the simulation's value" in str(err.value)
    assert "\n" not in str(err.value)


def test_settings_given_or_estimated_or_simulated_data_pass_the_check():
    import casmag
    from casmag.data.checks import refuse_simulation_truths
    from casmag.data.simulate import simulate_problem

    base = casmag.load_problem("problems/paper/base.yaml")
    refuse_simulation_truths(base, simulate_problem(base))  # its own simulation: the truth
    refuse_simulation_truths(casmag.load_problem("problems/paper/base.yaml", GIVEN), _recorded())
    estimated = casmag.load_problem(
        "problems/paper/base.yaml",
        {
            "model.estimate": ["sigma_f", "lengthscale"],
            "model.magnetometer.sigma_m": 1.0,
            "model.odometry.sigma": 0.01,
        },
    )
    refuse_simulation_truths(estimated, _recorded())


def test_slam_says_what_reading_the_recording_changed(tmp_path):
    t, U, _, P = _walk(n=80)
    Y = np.tile([20.0, -5.0, 40.0], (80, 1))  # constant: the odometry is the result, fast
    rec = tmp_path / "dup.csv"
    write_recording(rec, t, Y, dxy=U, P_true=P)
    lines = rec.read_text().splitlines()
    lines.insert(5, lines[4])  # a row written twice
    rec.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["slam", str(rec), "--out", str(out), "-q", "--no-figures"])
    assert res.exit_code == 0, res.output
    assert res.stderr.startswith(f"casmag: warning: {rec}: t: 1 rows repeat the previous row")
    r = json.loads((out / "result.json").read_text())
    assert [w["check"] for w in r["warnings"]] == ["duplicate_row"]
    assert r["info"]["n_samples"] == 80
    assert r["rmse_before"] == pytest.approx(0.0, abs=1e-9)  # the dead reckoning is intact
