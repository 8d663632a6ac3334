"""Real-data protocol (casmag.data.realdata, casmag convert), the Laplace position uncertainty
(casmag.solver.uncertainty) and the homogeneous-field fallback of `casmag slam`."""

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import tiny_walk

import casmag
from casmag.cli.main import main
from casmag.data.realdata import (
    Protocol,
    Sequence,
    align,
    clock_offset,
    coarse_to_fine_argmax,
    convert,
    heading_of_motion,
    load_sequence,
    planar_dead_reckoning,
    planar_increments,
)
from casmag.data.recording import dataset_to_recording_arrays, write_recording
from casmag.data.simulate import simulate_problem
from casmag.errors import DataError
from casmag.solver.recslam import slam

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data" / "magnetic-data" / "invensense"
needs_shared = pytest.mark.skipif(
    not (SHARED / "1-time.csv").is_file(),
    reason=f"real data not found at {SHARED} (../shared beside the repository)",
)


def _field(P):
    """A smooth synthetic field (uT) over the plane."""
    x, y = P[:, 0], P[:, 1]
    return np.column_stack(
        [
            20 + 6 * np.sin(2.1 * x) * np.cos(1.7 * y),
            -5 + 5 * np.cos(1.3 * x + 0.4) + 3 * np.sin(2.5 * y),
            -40 + 4 * np.sin(1.9 * x - 1.1 * y),
        ]
    )


def _synthetic_sequence(lag: int = 0, n: int = 3000, rate: float = 50.0, seed: int = 0):
    """A robot looping over 3 m x 2 m at 0.3 m/s; the magnetometer sample k is the field at
    the position of sample k + lag (negative lag: the magnetometer is late)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    P = np.column_stack([1.5 * np.cos(0.13 * t) + 0.2 * np.sin(0.5 * t), np.sin(0.21 * t)])
    k = np.clip(np.arange(n) + lag, 0, n - 1)
    mag = _field(P[k]) + 0.05 * rng.standard_normal((n, 3))
    return Sequence("synthetic", t, P, mag)


def test_clock_offset_finds_a_known_lag():
    seq = _synthetic_sequence(lag=-7)
    hyper = SimpleNamespace(sigma_f=4.0, lengthscale=0.8, sigma_m=0.05)
    shift, record = clock_offset(seq, max_shift=0.3, stride=5, hyper=hyper)
    assert shift == -7
    assert record["shift_seconds"] == pytest.approx(-7 / 50)
    assert record["log_marginal_gain"] > 10
    aligned = align(seq, shift)
    assert np.array_equal(aligned.mag[:100], seq.mag[7:107])
    assert np.array_equal(aligned.loc[:100], seq.loc[:100])
    assert aligned.loc.shape[0] == aligned.mag.shape[0] == seq.t.shape[0] - 7


@pytest.mark.parametrize("top", [0, 3, 17, 22, 40, 50])
def test_the_clock_search_finds_the_top_of_a_hump_with_fewer_evaluations(top):
    """coarse_to_fine_argmax on one smooth hump over 51 shifts (zero at 25, step 5): the
    top wherever it lies, the ends included, zero evaluated, fewer than 51 evaluations."""
    calls = []

    def f(i):
        calls.append(i)
        return -((i - top) ** 2) + 0.1 * np.cos(i)

    best, values = coarse_to_fine_argmax(f, 51, 25, 5)
    assert 25 in values and len(set(calls)) == len(calls) < 25
    assert best == max(range(51), key=f)


def test_convert_translational_drift_and_determinism():
    seq = _synthetic_sequence()
    p = Protocol(drift=0.5, noise=0.0, seed=3, align=False)
    a, b = convert(seq, p), convert(seq, p)
    assert np.array_equal(a.arrays["dxy"], b.arrays["dxy"])
    assert a.record["odometry"]["final_drift"] == pytest.approx(0.5, rel=1e-9)
    assert a.record["samples"] == 600  # 50 Hz -> 10 Hz
    c = convert(seq, Protocol(drift=0.5, noise=0.0, seed=4, align=False))
    assert not np.allclose(c.arrays["dxy"], a.arrays["dxy"])  # another bias direction


def test_planar_increments_dead_reckon_back_and_drift_is_hit():
    seq = _synthetic_sequence()
    P = seq.loc[::5]
    psi = heading_of_motion(P)
    U = planar_increments(P, psi)
    assert np.allclose(planar_dead_reckoning(U, P[0], psi[0]), P, atol=1e-9)
    conv = convert(seq, Protocol(drift=1.5, seed=2, motion="planar", align=False))
    assert conv.record["odometry"]["final_drift"] == pytest.approx(1.5, rel=1e-6)
    assert conv.arrays["planar"].shape == (conv.record["samples"] - 1, 3)
    # The magnetometer is rotated into the heading frame: |y| is unchanged.
    Y = seq.mag[::5]
    assert np.allclose(np.linalg.norm(conv.arrays["Y"], axis=1), np.linalg.norm(Y, axis=1))


def test_constant_field_replaces_the_magnetometer():
    seq = _synthetic_sequence()
    conv = convert(seq, Protocol(field="constant", constant_noise=1.0, seed=1, align=False))
    Y = conv.arrays["Y"]
    assert np.allclose(Y.mean(axis=0), seq.mag[::5].mean(axis=0), atol=0.2)
    assert np.allclose(Y.std(axis=0), 1.0, atol=0.1)


def test_load_sequence_errors_name_the_file(tmp_path):
    with pytest.raises(DataError, match=r"1-time\.csv: file not found"):
        load_sequence(tmp_path / "1")
    np.savetxt(tmp_path / "1-time.csv", np.arange(20) * 0.02)
    np.savetxt(tmp_path / "1-loc.csv", np.zeros((20, 3)), delimiter=",")
    np.savetxt(tmp_path / "1-mag.csv", np.zeros((20, 3)), delimiter=",")
    with pytest.raises(DataError, match=r"1-loc\.csv: has 3 columns, expected 2"):
        load_sequence(tmp_path / "1")
    np.savetxt(tmp_path / "1-loc.csv", np.zeros((19, 2)), delimiter=",")
    with pytest.raises(DataError, match=r"1-loc\.csv: has 19 rows"):
        load_sequence(tmp_path / "1")


def test_convert_cli_writes_recording_and_record(tmp_path):
    seq = _synthetic_sequence()
    for name, A in (("time", seq.t[:, None]), ("loc", seq.loc), ("mag", seq.mag)):
        np.savetxt(tmp_path / f"7-{name}.csv", A, delimiter=",")
    out = tmp_path / "rec.csv"
    r = CliRunner().invoke(
        main, ["convert", str(tmp_path / "7"), "--out", str(out), "--drift", "0.3", "--no-align"]
    )
    assert r.exit_code == 0, r.output
    rec = casmag.data.recording.read_recording(out)
    assert rec.n_samples == 600 and rec.has_truth
    assert json.loads(out.with_suffix(".json").read_text())["odometry"]["final_drift"] > 0.25
    bad = CliRunner().invoke(
        main, ["convert", str(tmp_path / "9"), "--out", str(tmp_path / "x.csv")]
    )
    assert bad.exit_code == 2
    assert "9-time.csv: file not found" in bad.output
    assert len(bad.output.strip().splitlines()) == 1
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.slow
@needs_shared
def test_real_sequence_magnetometer_lags_the_motion_capture():
    """Measured: the magnetometer of sequence 1 is 0.26 s late; aligning it gains hundreds
    of nats of marginal likelihood. Without the truth (casmag.data.clock, on the dead reckoning
    of the recorded timing with 0.5 m of drift) the same lag is found to 0.05 s."""
    from casmag.data.clock import estimate_lag

    seq = load_sequence(SHARED / "1")
    _, record = clock_offset(seq)
    assert -0.4 <= record["shift_seconds"] <= -0.1
    assert record["log_marginal_gain"] > 100
    a = convert(seq, Protocol(drift=0.5, seed=1, align=False)).arrays
    P_dr = np.vstack([a["P_true"][0], a["P_true"][0] + np.cumsum(a["dxy"], axis=0)])
    est = estimate_lag(a["t"], P_dr, a["Y"])
    assert est.significant
    assert est.lag_seconds == pytest.approx(-record["shift_seconds"], abs=0.05)


@needs_shared
def test_every_real_problem_file_loads(tmp_path):
    from casmag.experiments.realbench import load_real_problem, sequence_path

    files = sorted((ROOT / "problems/real").glob("*.yaml"))
    assert len(files) == 29
    motions = []
    for f in files:
        spec = load_real_problem(f)
        motions += [r.motion for r in spec.recordings]
        for i in range(len(spec.recordings)):
            prefix = sequence_path(spec, f, i)
            assert prefix.with_name(f"{prefix.name}-time.csv").is_file(), f
    # sequences 1-5 as planar odometry at two drifts and as pose odometry at one
    assert (motions.count("planar"), motions.count("pose")) == (10, 5)


def test_laplace_covariance_without_field_information_is_the_odometry_random_walk():
    """With an uninformative magnetometer (sigma_m huge) and no bias, the posterior of the
    positions is the anchor plus the odometry random walk: var(p_k) = sigma_a^2 + k sigma_o^2
    per axis, also between knots (the Brownian-bridge term)."""
    prob = tiny_walk(["model.magnetometer.sigma_m=1.0e6", "model.odometry.estimate_bias=false"])
    res = casmag.solve(prob)
    assert res.success
    cov = res.arrays["P_cov"]
    sa, so = prob.spec.model.anchor.sigma, prob.assumed_sigma_odometry
    expected = sa**2 + so**2 * np.arange(cov.shape[0])
    assert np.allclose(cov[:, 0, 0], expected, rtol=1e-4)
    assert np.allclose(cov[:, 1, 1], expected, rtol=1e-4)
    assert np.allclose(cov[:, 0, 1], 0.0, atol=1e-6 * expected.max())


def test_laplace_uncertainty_is_written_and_shrinks_with_a_map(tmp_path):
    res = casmag.solve(tiny_walk())
    assert res.success
    u = res.uncertainty
    assert u["nees_mean"] is not None and u["nees_expected"] == 2.0
    res.save(tmp_path / "out")
    header = (tmp_path / "out" / "trajectory.csv").read_text().splitlines()[0].split(",")
    assert header[-3:] == ["sigma_x", "sigma_y", "cov_xy"]
    no_bias = "model.odometry.estimate_bias=false"
    mapped = casmag.solve(tiny_walk([no_bias])).uncertainty
    flat = casmag.solve(tiny_walk(["model.magnetometer.sigma_m=1.0e6", no_bias])).uncertainty
    # The field pins the positions: the 1-sigma is smaller than with the odometry alone.
    assert mapped["sigma_mean"] < 0.75 * flat["sigma_mean"]  # measured: 0.59
    assert mapped["sigma_mean"] < u["sigma_mean"]  # a free bias adds uncertainty
    # Without a field a free bias is unobservable: no Laplace approximation, said so.
    unobservable = casmag.solve(tiny_walk(["model.magnetometer.sigma_m=1.0e6"]))
    assert "not positive definite" in unobservable.uncertainty["error"]
    assert "P_cov" not in unobservable.arrays or unobservable.arrays["P_cov"] is None


def _recording(tmp_path, constant: bool):
    data = simulate_problem(tiny_walk(["simulation.trajectory.samples=600"]))
    arrays = dataset_to_recording_arrays(data, dt=0.1)
    if constant:
        rng = np.random.default_rng(5)
        arrays["Y"] = data.Y.mean(axis=0) + 2e-3 * rng.standard_normal(data.Y.shape)
    path = tmp_path / ("flat.csv" if constant else "field.csv")
    write_recording(path, **arrays)
    return path


@pytest.mark.slow
def test_slam_falls_back_to_odometry_in_a_homogeneous_field(tmp_path):
    res = slam(_recording(tmp_path, constant=True))
    assert res.status == "Odometry_Only" and res.success
    assert "homogeneous field" in res.info["fallback"]
    assert res.rmse_after == res.rmse_before
    # The bias is unknown and has no prior: the odometry's uncertainty is unbounded.
    assert "unbounded" in res.uncertainty["error"]
    ev = res.info["defaults"]["field_evidence"]
    assert ev["homogeneous"] and ev["log_bayes_factor"] <= 0
    forced = slam(_recording(tmp_path, constant=True), field_check=False)
    assert forced.status != "Odometry_Only"


def test_slam_keeps_the_map_when_the_field_varies(tmp_path):
    res = slam(_recording(tmp_path, constant=False))
    assert res.status == "Solve_Succeeded"
    assert res.info["defaults"]["field_evidence"]["log_bayes_factor"] > 10


def test_truth_start_diagnostic_reaches_the_same_optimum_on_an_easy_recording(tmp_path):
    """casmag.experiments.realbench.truth_start: the MAP solved again from the true trajectory. On a
    simulated walk whose field GP-SLAM resolves, both starts end at the same optimum: the
    same cost to IPOPT's tolerance and the same positions."""
    from casmag.experiments.realbench import truth_start

    path = _recording(tmp_path, constant=False)
    res = slam(path)
    assert res.success
    t = truth_start(path, None, res)
    assert t["success"]
    assert abs(t["cost_above_result"]) < 1e-3 * t["cost"]
    assert t["rmse"] == pytest.approx(res.rmse_after, rel=0.02, abs=1e-4)
    assert t["rmse"] < 0.5 * res.rmse_before


def test_slam_keeps_the_lowest_cost_of_its_starts(tmp_path):
    """A recording longer than 2 x FIRST_PREFIX samples (and within one batch) is solved
    from the dead reckoning, from growing prefixes and (where the field's evidence chooses
    a bias) from the dead reckoning with that bias removed; the lowest MAP cost is kept and
    the final solve starts there."""
    data = simulate_problem(tiny_walk(["simulation.trajectory.samples=900"]))
    path = tmp_path / "long.csv"
    write_recording(path, **dataset_to_recording_arrays(data, dt=0.1))
    res = slam(path)
    assert res.success
    starts = res.stages_named("start")
    assert res.stages[: len(starts)] == starts  # the starts come first
    names = [st["start"] for st in starts]
    assert names[:2] == ["dead reckoning", "growing prefixes"]
    assert names[2:] in ([], ["evidence bias"])
    assert all("scan" in st for st in starts[2:])
    assert sum(st["kept"] for st in starts) == 1
    kept = min(starts, key=lambda st: st["cost"])
    assert kept["kept"]
    cost = sum(v["after"] for v in res.cost_blocks.values())
    assert cost <= kept["cost"] * (1 + 1e-5)  # IPOPT tolerance: measured 1.4e-6 above
    assert res.iterations >= sum(st["iterations"] for st in starts)


def test_jittered_time_stamps_are_brought_to_a_uniform_grid(tmp_path):
    seq = _synthetic_sequence()
    rng = np.random.default_rng(5)
    step = float(np.median(np.diff(seq.t)))
    t = seq.t + rng.uniform(-0.2, 0.2, seq.t.size) * step  # a phone's clock jitter
    for name, A in (("time", t[:, None]), ("loc", seq.loc), ("mag", seq.mag)):
        np.savetxt(tmp_path / f"3-{name}.csv", A, delimiter=",")
    read = load_sequence(tmp_path / "3")
    assert read.resampled is not None and read.resampled["interval_spread"] > 0.3
    intervals = np.diff(read.t)
    assert np.ptp(intervals) < 1e-9 * step and abs(intervals[0] - step) < 0.05 * step
    np.testing.assert_allclose(read.loc, np.column_stack(
        [np.interp(read.t, t, seq.loc[:, k]) for k in range(2)]))  # fmt: skip
    out = tmp_path / "rec.csv"
    r = CliRunner().invoke(main, ["convert", str(tmp_path / "3"), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert json.loads(out.with_suffix(".json").read_text())["resampled"]["rows"] == t.size


@pytest.mark.slow
@needs_shared
def test_the_real_benchmark_runs_the_filter_on_single_recordings(tmp_path):
    """``python -m casmag.experiments.realbench ... --method ekf``: the filter's row for a real
    recording (no truth start: that diagnostic is the MAP's); several sessions are refused."""
    from casmag.errors import DataError
    from casmag.experiments.realbench import solve_problem

    rows = solve_problem(ROOT / "problems/real/seq5-drift1.5.yaml", tmp_path / "r", method="ekf")
    (row,) = rows
    assert row["status"] == "Filter_Completed" and row["truth_start"] is None
    assert row["ratio"] < 1.0
    with pytest.raises(DataError, match="one recording at a time"):
        solve_problem(ROOT / "problems/real/sessions-drift0.5.yaml", tmp_path / "s", method="ekf")
