"""The magnetometer's lag behind the motion, estimated without truth (casmag.data.clock) and
removed on request (casmag slam --mag-lag)."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import tiny_walk

from casmag.cli.main import main
from casmag.data.clock import estimate_lag, shift_magnetometer
from casmag.data.realdata import planar_increments
from casmag.data.recording import dataset_to_recording_arrays, read_recording, write_recording
from casmag.data.simulate import simulate_problem
from casmag.solver.oriented import oriented_lag, oriented_lag_removed
from casmag.solver.recslam import slam


def _walk(lag_samples: int, drift: float = 0.3, seed: int = 0):
    """A 10 Hz walk over a smooth field (uT) whose magnetometer lags the motion by
    ``lag_samples`` samples, and a dead reckoning drifting ``drift`` m."""
    rng = np.random.default_rng(seed)
    n = 1200
    t = np.arange(n) / 10.0
    P = np.column_stack([2.5 * np.cos(0.3 * t) + 0.5 * np.sin(1.1 * t), 1.5 * np.sin(0.4 * t)])
    x, y = P[:, 0], P[:, 1]
    F = np.column_stack(
        [20 + 6 * np.sin(3.1 * x) * np.cos(2.7 * y), -5 + 5 * np.cos(2.3 * x), -40 + 4 * y]
    )
    k = np.clip(np.arange(n) - lag_samples, 0, n - 1)  # sample k: the field at k - lag
    Y = F[k] + 0.05 * rng.standard_normal(F.shape)
    P_dr = P + np.outer(t / t[-1], [drift, -0.5 * drift])
    return t, P_dr, Y


@pytest.mark.parametrize("lag_samples", [0, 2, 3, -2])
def test_the_lag_is_found_from_the_dead_reckoning(lag_samples):
    t, P_dr, Y = _walk(lag_samples)
    est = estimate_lag(t, P_dr, Y)
    assert est.lag_seconds == pytest.approx(lag_samples / 10.0, abs=0.041)
    assert est.significant is (lag_samples != 0)
    # Removing it leaves nothing to find.
    again = estimate_lag(t, P_dr, shift_magnetometer(t, Y, est.lag_seconds))
    assert abs(again.lag_seconds) <= 0.041 and not again.significant


def _turning_walk(lag_samples: int, seed: int = 0, attitude_lags: bool = True):
    """The walk of :func:`_walk` without drift, its heading along the path, the magnetometer
    in the body frame lagging by ``lag_samples``: its field and attitude those of the earlier
    time, or (``attitude_lags`` false) the earlier field in the row's own attitude.
    (t, P, psi, Y_body)."""
    t, P, _ = _walk(0, drift=0.0, seed=seed)
    dP = np.gradient(P, axis=0)
    psi = np.unwrap(np.arctan2(dP[:, 1], dP[:, 0]))
    x, y = P[:, 0], P[:, 1]
    F = np.column_stack(
        [20 + 6 * np.sin(3.1 * x) * np.cos(2.7 * y), -5 + 5 * np.cos(2.3 * x), -40 + 4 * y]
    )
    k = np.clip(np.arange(t.size) - lag_samples, 0, t.size - 1)
    h = psi[k] if attitude_lags else psi
    c, s = np.cos(h), np.sin(h)
    F = F[k]
    body = np.column_stack([c * F[:, 0] + s * F[:, 1], -s * F[:, 0] + c * F[:, 1], F[:, 2]])
    rng = np.random.default_rng(seed)
    return t, P, psi, body + 0.05 * rng.standard_normal(body.shape)


def _pose_increments(P: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """(N-1, 7) pose increments of a level path with heading psi: dp in the previous body
    frame, dq the turn about z since it."""
    dp = np.column_stack([planar_increments(P, psi)[:, :2], np.zeros(P.shape[0] - 1)])
    half = 0.5 * np.diff(psi)
    dq = np.column_stack([np.cos(half), np.zeros((half.size, 2)), np.sin(half)])
    return np.column_stack([dp, dq])


@pytest.mark.parametrize("motion", ["planar", "pose"])
@pytest.mark.parametrize("attitude_lags", [True, False])
def test_a_body_frame_lag_is_found_and_removed(tmp_path, motion, attitude_lags):
    """Planar and pose recordings: the lag of a body-frame magnetometer, whether its
    attitude lags with its position (a late sensor) or is its row's own (a late position),
    is found along the dead reckoning, told apart, and removed: the field turned into the
    world frame afterwards is the lag-free recording's."""
    t, P, psi, Y = _turning_walk(3, attitude_lags=attitude_lags)
    path = tmp_path / f"{motion}.csv"
    if motion == "planar":
        write_recording(path, t, Y, planar=planar_increments(P, psi), P_true=P, yaw_true=psi)
    else:
        write_recording(path, t, Y, pose=_pose_increments(P, psi), P_true=P)
    rec = read_recording(path)
    est = oriented_lag(rec)
    assert est.significant and est.lag_seconds == pytest.approx(0.3, abs=0.041)
    assert est.attitude_lags is attitude_lags
    fixed = oriented_lag_removed(rec, est)
    again = oriented_lag(fixed)
    assert not again.significant and abs(again.lag_seconds) <= 0.041
    inside = slice(10, -10)  # two noise draws of 0.05 apart: at most about 0.3 over 3,500
    assert np.abs(rec.Y - _turning_walk(0)[3])[inside].max() > 6.0
    np.testing.assert_allclose(fixed.Y[inside], _turning_walk(0)[3][inside], atol=0.4)
    t, P, psi, Y = _turning_walk(0)
    write_recording(path, t, Y, planar=planar_increments(P, psi), P_true=P, yaw_true=psi)
    assert not oriented_lag(read_recording(path)).significant


@pytest.mark.slow
def test_mag_lag_auto_removes_a_planar_recordings_lag(tmp_path):
    """``--mag-lag auto`` on a planar recording removes the estimated lag before the solve
    (one pipeline for every motion model), notes it and does not warn of it."""
    t, P, psi, Y = _turning_walk(3)
    path = tmp_path / "late.csv"
    write_recording(path, t, Y, planar=planar_increments(P, psi), P_true=P, yaw_true=psi)
    quick = {"max_iter": 1, "uncertainty": False}
    lines: list[str] = []
    r = slam(path, on_warning=lines.append, field_check=False, solver=quick, mag_lag="auto")
    lag = r.info["magnetometer_lag"]
    assert lag["removed_seconds"] == lag["estimate"]["lag_seconds"]
    assert lag["removed_seconds"] == pytest.approx(0.3, abs=0.041)
    assert any("estimated from the dead reckoning" in ln for ln in lines)
    assert not any("appears to lag" in ln for ln in lines)
    assert lag["estimate"]["attitude_lags"] is True
    lines = []
    r = slam(path, on_warning=lines.append, field_check=False, solver=quick)
    assert r.info["magnetometer_lag"]["removed_seconds"] == 0.0
    assert any("appears to lag the motion by 0.3" in ln for ln in lines)


def test_too_short_a_recording_gives_no_estimate():
    t, P_dr, Y = _walk(0)
    assert estimate_lag(t[:150], P_dr[:150], Y[:150]) is None


@pytest.mark.slow
def test_slam_reports_a_lag_removes_it_on_request_or_when_asked_to_find_it(tmp_path):
    data = simulate_problem(tiny_walk(["simulation.trajectory.samples=600"]))
    arrays = dataset_to_recording_arrays(data, dt=0.1)
    arrays["Y"] = np.vstack([np.repeat(arrays["Y"][:3], 1, axis=0), arrays["Y"][:-3]])
    path = tmp_path / "late.csv"
    write_recording(path, **arrays)
    lines = []
    r = slam(path, on_warning=lines.append, field_check=False, solver={"max_iter": 1})
    lag = r.info["magnetometer_lag"]
    assert lag["removed_seconds"] == 0.0
    assert lag["estimate"]["lag_seconds"] == pytest.approx(0.3, abs=0.05)
    assert any("appears to lag the motion by 0.3" in ln for ln in lines)
    lines = []
    r = slam(
        path, on_warning=lines.append, field_check=False, solver={"max_iter": 1}, mag_lag="auto"
    )
    lag = r.info["magnetometer_lag"]
    assert lag["removed_seconds"] == lag["estimate"]["lag_seconds"]
    assert lag["removed_seconds"] == pytest.approx(0.3, abs=0.05)
    assert any("estimated from the dead reckoning" in ln for ln in lines)
    assert not any("appears to lag" in ln for ln in lines)
    np.testing.assert_allclose(r.arrays["Y"][10:-10], data.Y[10:-10], atol=0.05 * np.ptp(data.Y))
    out = tmp_path / "out"
    args = ["slam", str(path), "--out", str(out), "-q", "--mag-lag", "0.3"]
    res = CliRunner().invoke(main, [*args, "--no-field-check", "--set", "solver.max_iter=1"])
    assert res.exit_code == 1, res.output  # one iteration: the solve is not the point
    saved = json.loads((out / "result.json").read_text())
    assert saved["info"]["magnetometer_lag"]["removed_seconds"] == 0.3
    assert abs(saved["info"]["magnetometer_lag"]["estimate"]["lag_seconds"]) <= 0.05
    assert "appears to lag" not in res.output
    assert any(w["check"] == "magnetometer_lag" for w in saved["warnings"])
    res = CliRunner().invoke(
        main, ["slam", str(path), str(path), "--out", str(tmp_path / "o2"), "--mag-lag", "0.3"]
    )
    assert res.exit_code == 2 and "solve each alone with --mag-lag" in res.output
    res = CliRunner().invoke(
        main, ["slam", str(path), "--out", str(tmp_path / "o3"), "--mag-lag", "x"]
    )
    assert res.exit_code == 2 and "expected seconds or 'auto', got 'x'" in res.output


@pytest.mark.slow
def test_refit_noise_solves_again_with_the_noise_that_does_not_repeat(tmp_path):
    """A slow magnetometer error (period 60 s, 6 sigma_m): the windowed likelihood reads it
    as field, the revisits do not; with --refit-noise the MAP is solved again from the
    first estimate with their sigma_m, and info.sigma_m_refit says so."""
    problem = tiny_walk(["simulation.trajectory.samples=600"])
    data = simulate_problem(problem)
    arrays = dataset_to_recording_arrays(data, dt=0.1)
    t = 0.1 * np.arange(arrays["Y"].shape[0])
    slow = np.sin(2.0 * np.pi * t[:, None] / 60.0 + np.array([0.0, 2.0, 4.0]))
    arrays["Y"] = arrays["Y"] + 6.0 * problem.assumed_sigma_m * slow
    path = tmp_path / "slow.csv"
    write_recording(path, **arrays)
    r = slam(path, field_check=False, refit_noise=True)
    refit = r.info["sigma_m_refit"]
    assert refit["refit"] and refit["kept"] == "refit" and refit["pairs"] >= 30
    assert refit["revisit"] > 1.5 * refit["first"]
    assert r.hyperparameters["sigma_m"] == refit["revisit"]
    assert "sigma_m_refit" not in slam(path, field_check=False, solver={"max_iter": 1}).info
