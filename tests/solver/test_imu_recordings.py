"""``casmag slam`` on an IMU recording (dqw..dqz, dvx..dvz): the IMU model on the recording's
data (casmag.data.imurec, casmag.solver.imurec), its noise from the rest at the start."""

import dataclasses
import itertools
import json

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import tiny_imu

from casmag import strapdown as sd
from casmag.cli.main import main
from casmag.data.clock import LagEstimate, shift_magnetometer
from casmag.data.imurec import imu_data, quantisation_floor, rest_noise, rest_warnings
from casmag.data.imusim import simulate_imu
from casmag.data.recording import read_recording, write_recording
from casmag.errors import DataError, ProblemError
from casmag.model.imu import keyframes
from casmag.problem.imu import ImuRecordingSpec, load_imu_problem, load_recording_spec
from casmag.solver import imurec
from casmag.solver.imu import _estimate_flag, solve_imu
from casmag.solver.imurec import imu_lag
from casmag.solver.recslam import slam, slam_sessions

#: The tiny desk rectangle (tests/small_problems.tiny_imu) with given hyperparameters,
#: constant biases and one batch: a 3-second solve.
GP = {"sigma_f": 0.3, "lengthscale": 0.2, "num_basis": 200}
#: No map: the IMU-only adjustment alone (all the lag estimate reads), a solve of seconds.
NO_MAP = ["model.gp.form=none"]


def _problem() -> dict:
    d = tiny_imu(gp=GP, imu={"bias": "constant"})
    d["solver"]["warm_start"] = {"strategy": "none"}
    return d


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The problem, its simulated data and the data written as an IMU recording."""
    prob = load_imu_problem(_problem())
    data = simulate_imu(prob)
    path = tmp_path_factory.mktemp("imu") / "desk.csv"
    tr = data.truth
    write_recording(path, tr.t, data.Y, imu=np.hstack([data.dq, data.dv]), P_true=tr.P, q_true=tr.Q)
    return prob, data, path


def _true_noise_model(prob) -> dict:
    """The problem's model section with the simulation's noise written out."""
    sim = prob.spec.simulation
    model = _problem()["model"]
    model["imu"] |= {
        "gyro_noise_density": sim.imu.gyro_noise_density,
        "acc_noise_density": sim.imu.acc_noise_density,
    }
    model["magnetometer"] = {"sigma_m": sim.magnetometer.noise}
    return model


def test_a_recording_is_solved_as_its_problem_file(recording):
    """The simulated data written as a recording and solved by ``slam`` with the same
    model give the estimate of the problem file (casmag imu), to round-off: the same
    start (first true pose, levelled attitude), rate, keyframes and noise."""
    prob, data, path = recording
    r1 = solve_imu(prob, data)
    r2 = slam(path, {"model": _true_noise_model(prob), "solver": _problem()["solver"]})
    assert r1.success and r2.success, (r1.status, r2.status)
    assert r2.motion == "imu" and r2.info["recording"] == str(path)
    assert r2.info["imu_rate_hz"] == pytest.approx(100.0) and r2.info["scenario"] is None
    assert r2.info["keyframe_rate_hz"] == pytest.approx(5.0)
    assert r2.info["defaults"]["from_rest"] == []
    a1, a2 = r1.arrays, r2.arrays
    # Round-off of the two paths' sums: up to 4.1e-9 m on an AMD EPYC with one BLAS
    # thread (2026-12-02), below 1e-9 m on the machine the test was written on.
    np.testing.assert_allclose(a2["P_estimate"], a1["P_estimate"], rtol=0, atol=1e-8)
    np.testing.assert_allclose(a2["P_true"], a1["P_true"], rtol=0, atol=0)
    assert r2.rmse_after == pytest.approx(r1.rmse_after, abs=1e-8)
    assert r2.details["errors"]["gp_slam"]["orientation_rms_deg"] is not None


def test_the_rest_at_the_start_gives_the_sensors_noise(recording):
    """At rest each sample's spread about the mean is the sensor's white noise: the
    densities and sigma_m come within 15 % of the simulation's (50 samples, 0.5 s)."""
    prob, data, path = recording
    rec = read_recording(path)
    sim = prob.spec.simulation
    noise = rest_noise(rec, data.T, 50)
    assert noise.gyro_noise_density == pytest.approx(sim.imu.gyro_noise_density, rel=0.15)
    assert noise.acc_noise_density == pytest.approx(sim.imu.acc_noise_density, rel=0.15)
    assert noise.sigma_m == pytest.approx(sim.magnetometer.noise, rel=0.15)
    assert noise.specific_force == pytest.approx(sd.GRAVITY, rel=0.01)
    assert noise.turned_deg < 0.5 and rest_warnings(noise, 0.5) == []
    moving = rest_noise(rec, data.T, 150)  # 1 s past the rest: the walk has begun
    assert [w["check"] for w in rest_warnings(moving, 1.5)] == ["not_at_rest"]


def test_a_quantised_magnetometer_is_at_least_its_rounding_noise():
    Y = np.round(np.random.default_rng(3).normal(size=(200, 3)), 2)
    assert quantisation_floor(Y) == pytest.approx(0.01 / np.sqrt(12.0), rel=1e-6)


def _cli(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_casmag_slam_solves_an_imu_recording_with_noise_from_the_rest(tmp_path, recording):
    """No noise given: the rest's estimates are used and recorded, the solve succeeds and
    GP-SLAM improves on the IMU-only adjustment; result.json and trajectory.csv are
    written."""
    _, _, path = recording
    out = tmp_path / "out"
    sets = [f"model.gp.{k}={v}" for k, v in GP.items()] + ["solver.warm_start.strategy=none"]
    res = _cli(["slam", path, "--out", out, "-q", *[a for s in sets for a in ("--set", s)]])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["motion"] == "imu" and r["success"] is True
    used = r["info"]["defaults"]["from_rest"]
    assert used == [
        "model.imu.gyro_noise_density",
        "model.imu.acc_noise_density",
        "model.magnetometer.sigma_m",
    ]
    assert r["info"]["anchor"]["start"] == "truth"
    assert r["rmse_after"] < 0.25 * r["rmse_before"]
    assert (out / "trajectory.csv").exists()


def _rewritten(path, tmp_path, **change):
    """The recording at ``path`` written again with some of its arrays changed."""
    rec = read_recording(path)
    arrays = {"t": rec.t, "Y": rec.Y, "imu": rec.increments, "P_true": rec.P_true}
    arrays |= {"q_true": rec.q_true, **change}
    out = tmp_path / "changed.csv"
    write_recording(out, arrays.pop("t"), arrays.pop("Y"), **arrays)
    return out


def test_a_dropped_sample_is_resampled_onto_the_uniform_grid(tmp_path, recording):
    """Every 7th time stamp left out, its increments composed into the next row's (what
    the IMU integrated over the longer interval): the reader puts the rows back on the
    uniform grid, with a note. Rows away from a dropped stamp come back as they were;
    the two rows either side of one compose to what was written (the integrated velocity
    and orientation at the recorded times are kept exactly)."""
    _, _, path = recording
    rec = read_recording(path)
    t, inc = rec.t, rec.increments  # inc[i]: from t[i] to t[i + 1]
    drop = np.arange(7, t.size - 1, 7)  # rows whose time stamp is left out
    keep = np.setdiff1d(np.arange(t.size), drop)
    joined = inc.copy()
    for i in drop:  # the interval t[i-1] -> t[i+1]: dv = dv1 + R(dq1) dv2, dq = dq1 dq2
        joined[i] = np.r_[
            sd.quat_mul(inc[i - 1, :4], inc[i, :4]),
            inc[i - 1, 4:] + sd.rotate(inc[i - 1, :4], inc[i, 4:]),
        ]
    rows = keep[1:] - 1  # the increment row that ends at each kept row
    out = _rewritten(path, tmp_path, t=t[keep], Y=rec.Y[keep], P_true=rec.P_true[keep],
                     q_true=rec.q_true[keep],
                     imu=joined[rows])  # fmt: skip
    back = read_recording(out)
    (note,) = [n for n in back.notes if n["check"] == "resampled"]
    assert "uniform grid of 0.01 s" in note["reason"]
    np.testing.assert_allclose(back.t, t, atol=1e-12)
    near = np.union1d(drop - 1, drop)  # the intervals either side of a dropped stamp
    far = np.setdiff1d(np.arange(inc.shape[0]), near)
    np.testing.assert_allclose(back.increments[far], inc[far], atol=1e-9)
    for i in drop:
        a, b = back.increments[i - 1], back.increments[i]
        np.testing.assert_allclose(sd.quat_mul(a[:4], b[:4]), joined[i, :4], atol=1e-9)
        np.testing.assert_allclose(a[4:] + sd.rotate(a[:4], b[4:]), joined[i, 4:], atol=1e-9)
        # and each half is close to what the IMU measured over it (smooth motion)
        np.testing.assert_allclose(back.increments[[i - 1, i], 4:], inc[[i - 1, i], 4:], atol=2e-3)


@pytest.mark.parametrize("jitter", [0.2, 0.4])
def test_jittered_time_stamps_of_a_uniform_imu_keep_its_rows(tmp_path, recording, jitter):
    """An IMU sampled uniformly, its time stamps jittered by up to ``jitter`` of the
    interval (another clock stamps them): the velocity increments follow the uniform rate,
    so the rows are kept as they are on the fitted uniform grid (``retimed``, the warning
    names it); the rest's noise is the uniform recording's (resampling by the stamps gave
    the accelerometer 114-139 times its noise at 0.2), and the solve is the uniform
    recording's."""
    _, data, path = recording
    rec = read_recording(path)
    rng = np.random.default_rng(3)
    jittered = rec.t + rng.uniform(-jitter, jitter, rec.t.size) * 0.01
    lines = []
    changed = _rewritten(path, tmp_path, t=jittered)
    back = read_recording(changed)
    (note,) = [n for n in back.notes if n["column"] == "t"]
    assert note["check"] == "retimed" and "the rows kept as they are" in note["reason"]
    np.testing.assert_array_equal(back.increments, rec.increments)
    np.testing.assert_allclose(np.diff(back.t), np.diff(back.t).mean(), rtol=1e-9)
    # the fitted grid: within a quarter of the jitter of the uniform times
    np.testing.assert_allclose(back.t, rec.t, atol=0.25 * jitter * 0.01)
    a, b = rest_noise(back, data.T, 50), rest_noise(rec, data.T, 50)
    assert a.acc_noise_density == pytest.approx(b.acc_noise_density, rel=1e-3)
    r = slam(changed, overrides=NO_MAP, on_warning=lines.append)
    r0 = slam(path, overrides=NO_MAP)
    assert r.success, r.status
    assert any("the stamps jitter" in line for line in lines)
    assert r.info["imu_rate_hz"] == pytest.approx(100.0, rel=1e-4)
    rmse = [x.details["errors"]["imu_only"]["rmse"] for x in (r, r0)]
    assert rmse[0] == pytest.approx(rmse[1], rel=0.01)


def test_jittered_stamps_with_a_missing_sample_are_moved_to_the_grid_then_resampled(
    tmp_path, recording
):
    """Stamps jittered by up to a fifth of the interval and every 37th sample missing (its
    increments composed into the next row's): the stamps are moved to the fitted grid, the
    missing samples resampled from there, the row count restored; the noise at rest comes
    from the rows on the grid's times, within 10 % of the uniform recording's."""
    _, data, path = recording
    rec = read_recording(path)
    t, inc = rec.t, rec.increments
    drop = np.arange(30, t.size - 1, 37)
    keep = np.setdiff1d(np.arange(t.size), drop)
    joined = inc.copy()
    for i in drop:
        joined[i] = np.r_[
            sd.quat_mul(inc[i - 1, :4], inc[i, :4]),
            inc[i - 1, 4:] + sd.rotate(inc[i - 1, :4], inc[i, 4:]),
        ]
    stamps = t[keep] + np.random.default_rng(5).uniform(-0.2, 0.2, keep.size) * 0.01
    out = _rewritten(path, tmp_path, t=stamps, Y=rec.Y[keep], P_true=rec.P_true[keep],
                     q_true=rec.q_true[keep], imu=joined[keep[1:] - 1])  # fmt: skip
    back = read_recording(out)
    (note,) = [n for n in back.notes if n["column"] == "t"]
    assert note["check"] == "resampled" and "the stamps jitter" in note["reason"]
    assert back.t.size == t.size
    a, b = rest_noise(back, data.T, 50), rest_noise(rec, data.T, 50)
    for key in ("gyro_noise_density", "acc_noise_density", "sigma_m"):
        assert getattr(a, key) == pytest.approx(getattr(b, key), rel=0.1), key


def test_an_imu_sampled_at_jittered_times_is_resampled(tmp_path):
    """An IMU whose samples really fall at jittered times (a 1 kHz simulation picked at
    10 ms +- 2 ms, the increments composed between picks; the stamps right): the increments
    follow the stamps, so the rows are resampled onto the uniform grid, not retimed. The
    noise at rest comes from the rows as recorded, within a fifth of the simulated (from
    the resampled rows it came out 0.67-0.82 of it at +-4 ms, seeds 1-3)."""
    d = _problem()
    d["simulation"]["imu"] = {"rate": 1000.0}
    prob = load_imu_problem(d)
    fine = simulate_imu(prob)
    rng = np.random.default_rng(4)
    n = (fine.n_samples - 3) // 10
    picks = 10 * np.arange(n) + np.r_[0, rng.integers(-2, 3, n - 2), 0]
    inc = []
    for a, b in itertools.pairwise(picks):
        q, v = np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3)
        for j in range(a, b):  # dv = dv1 + R(dq1) dv2, dq = dq1 dq2
            v = v + sd.rotate(q, fine.dv[j])
            q = sd.quat_mul(q, fine.dq[j])
        inc.append(np.r_[q / np.linalg.norm(q), v])
    tr = fine.truth
    path = tmp_path / "irregular.csv"
    write_recording(path, tr.t[picks], fine.Y[picks], imu=np.array(inc), P_true=tr.P[picks],
                    q_true=tr.Q[picks])  # fmt: skip
    back = read_recording(path)
    (note,) = [n for n in back.notes if n["column"] == "t"]
    assert note["check"] == "resampled" and "stamps jitter" not in note["reason"]
    np.testing.assert_allclose(np.diff(back.t), 0.01, rtol=1e-6)
    np.testing.assert_array_equal(back.imu_samples[0], tr.t[picks])
    sim, noise = prob.spec.simulation, rest_noise(back, 0.01, 50)
    assert noise.gyro_noise_density == pytest.approx(sim.imu.gyro_noise_density, rel=0.2)
    assert noise.acc_noise_density == pytest.approx(sim.imu.acc_noise_density, rel=0.2)
    assert noise.sigma_m == pytest.approx(sim.magnetometer.noise, rel=0.2)


def _two_streams(path, out, every, offset=0.0, values=None):
    """The recording at ``path`` written again with the magnetometer on every ``every``-th
    row only (the other rows' mx, my, mz left empty), or, with ``offset`` [s], on rows of
    its own at those rows' times plus ``offset`` (the IMU's rows without it), with
    ``values`` (N, 3) there when given."""
    header, *rows = path.read_text().splitlines()
    names = header.split(",")
    mag = [names.index(c) for c in ("mx", "my", "mz")]
    lines = [header]
    for i, line in enumerate(rows):
        f = line.split(",")
        own = [""] * len(f)
        own[0] = repr(float(f[0]) + offset)
        for k, j in enumerate(mag):
            own[j] = f[j] if values is None else repr(float(values[i, k]))
            f[j] = "" if i % every or offset else f[j]
        lines.append(",".join(f))
        if offset and i % every == 0:
            lines.append(",".join(own))
    out.write_text("\n".join(lines) + "\n")
    return out


def _spinning(tmp_path, offset, rate=2.0, n=301):
    """A device at rest turning about the vertical at ``rate`` rad/s (100 Hz) in a
    constant field, its magnetometer in the body frame on every row (N, 3), and ``offset``
    seconds later."""
    t = 0.01 * np.arange(n)

    def body_field(t):
        half = 0.5 * rate * t
        q = np.column_stack([np.cos(half), 0 * t, 0 * t, np.sin(half)])
        return q, sd.rotate(sd.quat_conj(q), np.array([20.0, 5.0, -40.0]))

    q, Y = body_field(t)
    imu = np.column_stack(
        [
            sd.quat_mul(sd.quat_conj(q[:-1]), q[1:]),
            np.tile([0.0, 0.0, sd.GRAVITY * 0.01], (n - 1, 1)),
        ]
    )
    path = tmp_path / "spin.csv"
    write_recording(path, t, Y, imu=imu, q_true=q)
    return path, Y, body_field(t + offset)[1]


@pytest.mark.parametrize("offset", [0.0, 0.004])
def test_a_slower_magnetometer_is_interpolated_in_the_gyroscope_frame(tmp_path, offset):
    """Magnetometer at 10 Hz beside a 100 Hz IMU (on every 10th row, or on rows of its own
    4 ms later), the device turning 0.2 rad between its samples: the IMU rows get the
    field interpolated in the gyroscope's frame, exact for a constant field (to 1e-9),
    where interpolating the body-frame values would shrink it by 0.1 uT. IMU rows before
    the first magnetometer sample are dropped. The note says so, and the share of
    magnetometer samples per row is recorded."""
    path, Y, later = _spinning(tmp_path, offset)
    rec = read_recording(_two_streams(path, tmp_path / "two.csv", 10, offset, later))
    a = 1 if offset else 0  # the first IMU row kept
    kept = slice(a, a + rec.t.size)
    np.testing.assert_allclose(rec.t, 0.01 * np.arange(301)[kept], atol=1e-12)
    np.testing.assert_allclose(rec.Y, Y[kept], atol=1e-9)
    naive = np.column_stack([np.interp(rec.t, rec.t[::10], Y[kept][::10, j]) for j in range(3)])
    assert np.abs(naive - Y[kept]).max() > 0.05
    assert rec.mag_share == pytest.approx(0.1, rel=0.05)  # within one sample of 30
    (note,) = [n for n in rec.notes if n["column"] == "mx, my, mz"]
    assert "interpolated to the IMU rows" in note["reason"]
    assert [n for n in rec.notes if n["column"] == "t"] == []  # the IMU rows stay uniform


def test_a_slower_magnetometer_keeps_its_noise_and_is_solved(tmp_path, recording):
    """The desk recording with the magnetometer at 25 Hz: the rest's sigma_m comes from its
    own samples (the interpolated rows would give less), the keyframes count 5 x 0.25
    samples in their average, and the recording is solved, GP-SLAM better than the IMU-only
    adjustment (13.9 mm against 28.5 mm; 4.9 mm with the magnetometer on every row)."""
    prob, data, path = recording
    slow = _two_streams(path, tmp_path / "slow.csv", 4)
    rec = read_recording(slow)
    noise = rest_noise(rec, data.T, 50).sigma_m
    assert noise == pytest.approx(prob.spec.simulation.magnetometer.noise, rel=0.3)
    assert rest_noise(dataclasses.replace(rec, mag_samples=None), data.T, 50).sigma_m < noise
    slow_data, _ = imu_data(rec, 0.5)
    assert slow_data.mag_share == pytest.approx(0.25, rel=0.05)
    kf = keyframes(slow_data, 20, 1e-3, 1e-2, samples=5)
    assert kf.sigma_scale == pytest.approx(1 / np.sqrt(5 * slow_data.mag_share))
    lines = []
    model = _true_noise_model(prob)
    del model["magnetometer"]
    r = slam(slow, {"model": model, "solver": _problem()["solver"]}, on_warning=lines.append)
    assert r.success, r.status
    assert any("interpolated to the IMU rows" in line for line in lines)
    assert r.info["defaults"]["from_rest"] == ["model.magnetometer.sigma_m"]
    errors = r.details["errors"]
    assert errors["gp_slam"]["rmse"] < 0.7 * errors["imu_only"]["rmse"]


@pytest.mark.parametrize(
    ("every", "needle"),
    [(40, "model.keyframe_rate: the magnetometer gives about 2.5 samples per second"),
     (100, "model.magnetometer.sigma_m: the rest at the start")],
)  # fmt: skip
def test_a_magnetometer_too_slow_for_the_keyframes_or_the_rest_is_refused(
    tmp_path, recording, every, needle
):
    _, _, path = recording
    with pytest.raises(DataError) as err:
        slam(_two_streams(path, tmp_path / "slow.csv", every))
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_a_sensor_constant_at_rest_must_be_given_its_noise(tmp_path, recording):
    _, _, path = recording
    inc = read_recording(path).increments.copy()
    inc[:60, :4] = [1.0, 0.0, 0.0, 0.0]  # the gyroscope reads exactly zero at rest
    with pytest.raises(DataError, match=r"model\.imu\.gyro_noise_density: .*give it"):
        slam(_rewritten(path, tmp_path, imu=inc))


@pytest.mark.parametrize(
    ("kwargs", "error", "needle"),
    [
        ({"overrides": ["model.initial.rest_seconds=0.05"]}, DataError, "rest_seconds"),
        ({"overrides": ["model.imu.bias=random_walk"]}, ProblemError, "gyro_bias_walk"),
        ({"overrides": ["model.magnetometer.samples=23"]}, ProblemError, "samples"),
        ({"method": "ekf"}, DataError, "--method ekf"),
        ({"refit_noise": True}, DataError, "--refit-noise"),
        ({"overrides": ["solver.uncertainty=true"]}, ProblemError, "solver.uncertainty"),
    ],
)
def test_what_an_imu_recording_cannot_take_is_refused_in_one_line(recording, kwargs, error, needle):
    _, _, path = recording
    with pytest.raises(error) as err:
        slam(path, **kwargs)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_planar_truth_positions_are_refused_and_origin_drops_the_truth(recording):
    _, data, path = recording
    rec = read_recording(path)
    with pytest.raises(DataError, match="z_true"):
        imu_data(dataclasses.replace(rec, P_true=rec.P_true[:, :2]), 0.5)
    at_origin, n = imu_data(rec, 0.5, anchor="origin")
    assert n == 50 and at_origin.truth is None
    np.testing.assert_array_equal(at_origin.p0, np.zeros(3))
    assert sd.euler_from_quat(at_origin.q0)[2] == pytest.approx(0.0, abs=1e-12)
    at_truth, _ = imu_data(rec, 0.5)
    np.testing.assert_allclose(at_truth.q0, data.q0, atol=1e-12)
    np.testing.assert_array_equal(at_truth.p0, data.p0)


def test_a_recording_estimate_worse_than_imu_only_is_flagged_without_a_truth_start(recording):
    """A recording's truth has no velocities or biases to start a solve from: an estimate
    more than 5 % worse than the IMU-only adjustment is flagged all the same, and one
    between the wrong-basin ratio and that is not."""
    _, _, path = recording
    rec_data, _ = imu_data(read_recording(path), 0.5)
    assert rec_data.truth.V is None and rec_data.b_w is None

    def errors(after):
        return {"imu_only": {"rmse": 0.1}, "gp_slam": {"rmse": after}}

    flag = _estimate_flag(None, rec_data, errors(0.2), None, None)
    assert flag["name"] == "worse_than_imu_only" and flag["evidence"]["ratio"] == 2.0
    assert _estimate_flag(None, rec_data, errors(0.104), None, None) is None


def test_a_recording_model_keeps_constant_biases_when_its_imu_section_gives_other_keys():
    spec = load_recording_spec(ImuRecordingSpec, {"model": {"imu": {"acc_bias_prior": 0.2}}})
    assert spec.model.imu.bias == "constant" and spec.model.imu.acc_bias_prior == 0.2
    given = load_recording_spec(ImuRecordingSpec, None, ["model.imu.gyro_noise_density=0.01"])
    assert given.model.imu.bias == "constant" and given.model.keyframe_rate == 5.0
    assert given.solver.max_iter == 150 and given.solver.warm_start.strategy == "auto"


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory):
    """The desk rectangle traced 8 times (32 s: the lag is estimated on 10-s windows),
    written as an IMU recording."""
    d = _problem()
    d["simulation"]["scenario"]["loops"] = 8
    data = simulate_imu(load_imu_problem(d))
    path = tmp_path_factory.mktemp("imu-long") / "desk8.csv"
    tr = data.truth
    write_recording(path, tr.t, data.Y, imu=np.hstack([data.dq, data.dv]), P_true=tr.P, q_true=tr.Q)
    return path


def _late(path, tmp_path, lag, name="late.csv"):
    """The recording with its magnetometer ``lag`` seconds late: row k reads the field of
    time t_k - lag."""
    rec = read_recording(path)
    Y = np.column_stack([np.interp(rec.t - lag, rec.t, rec.Y[:, j]) for j in range(3)])
    return _rewritten(path, tmp_path, Y=Y).rename(tmp_path / name)


@pytest.mark.parametrize("lag", [0.0, 0.15, -0.1])
def test_the_lag_is_found_on_a_path_of_keyframe_poses(tmp_path, long_recording, lag):
    """imu_lag on the true poses at the 5 Hz keyframes (as a result's arrays): the lag put
    into the magnetometer is found within 0.03 s, significant when it is one."""
    rec = read_recording(_late(long_recording, tmp_path, lag))
    data, _ = imu_data(rec, 0.5)
    kf = np.arange(0, rec.t.size, 20)
    arrays = {"t": rec.t[kf], "P_estimate": rec.P_true[kf], "Q_estimate": rec.q_true[kf]}
    est = imu_lag(rec.t, data, arrays)
    assert est.lag_seconds == pytest.approx(lag, abs=0.03)
    assert est.significant == (lag != 0.0)
    assert imu_lag(rec.t, data, {**arrays, "P_estimate": None}) is None  # no such path


def test_the_lag_left_on_the_path_solved_is_reported(tmp_path, long_recording, monkeypatch):
    """With --mag-lag 0 the lag is estimated once, on the path solved (here the IMU-only
    adjustment: no map) and reported, with a warning when significant; nothing removed.
    Without --mag-lag (auto, the default for IMU recordings) a significant estimate is
    removed (from the IMU-only adjustment first, then on the path solved) and the
    recording solved again; every step is recorded."""
    path = _late(long_recording, tmp_path, 0.15)
    found = [0.15, 0.02]  # what the estimates say, in turn (imu_lag stands in)
    calls = []

    def stand_in(t, data, arrays, key="estimate"):
        calls.append((key, data.Y.copy()))
        lag = found[min(len(calls), len(found)) - 1]
        return LagEstimate(lag, 500.0, abs(lag) >= 0.05, 3, 10.0, 0.05)

    monkeypatch.setattr(imurec, "imu_lag", stand_in)
    lines = []
    r = slam(path, overrides=NO_MAP, on_warning=lines.append, mag_lag=0.0)
    m = r.info["magnetometer_lag"]
    assert m["removed_seconds"] == 0.0 and m["path"] == "IMU-only adjustment"
    assert m["estimate"]["lag_seconds"] == 0.15 and len(m["steps"]) == 1
    assert [k for k, _ in calls] == ["imu_only"]
    assert any("--mag-lag 0.15 removes it" in line for line in lines)

    calls.clear()
    lines.clear()
    r = slam(path, overrides=NO_MAP, on_warning=lines.append)  # auto: the IMU default
    m = r.info["magnetometer_lag"]
    assert m["removed_seconds"] == 0.15 and m["estimate"]["lag_seconds"] == 0.02
    assert [s["path"] for s in m["steps"]] == ["IMU-only adjustment"] * 2
    assert m["steps"][0]["removed_seconds"] == 0.15 and "removed_seconds" not in m["steps"][1]
    (_, first), (_, second) = calls  # the magnetometer each estimate read
    rec = read_recording(path)
    np.testing.assert_array_equal(first, rec.Y)
    np.testing.assert_allclose(second, shift_magnetometer(rec.t, rec.Y, 0.15))
    assert any("shifted by 0.15 s" in line for line in lines)
    assert not any("removes it" in line for line in lines)


def test_a_lag_left_on_the_gp_slam_path_is_in_the_verdict(recording, monkeypatch):
    """With the map solved, the lag is estimated on GP-SLAM's path; a significant one left
    there makes the result untrusted (casmag.result.verdict), a clear path keeps it."""
    prob, _, path = recording
    settings = {"model": _true_noise_model(prob), "solver": _problem()["solver"]}
    for lag, trusted in ((0.15, False), (0.0, True)):
        found = LagEstimate(lag, 500.0, lag != 0.0, 3, 10.0, 0.05)
        monkeypatch.setattr(imurec, "imu_lag", lambda *a, found=found, **k: found)
        r = slam(path, settings, mag_lag=0.0)
        assert r.success and r.info["magnetometer_lag"]["path"] == "GP-SLAM"
        assert r.verdict["checks"]["magnetometer_lag"]["passed"] is trusted
        assert r.verdict["trusted"] is trusted, r.verdict["reasons"]


@pytest.mark.slow
def test_each_imu_session_gets_its_own_lag_estimate(tmp_path, long_recording):
    """``casmag slam A B`` with IMU recordings: each session's lag is estimated on its own
    keyframes of the stacked result, on the recording's own clock: with no map the same
    estimate as its recording solved alone."""
    late = _late(long_recording, tmp_path, 0.15)
    r = slam_sessions([long_recording, late], overrides=NO_MAP, mag_lag=0.0)
    m = r.info["magnetometer_lag"]
    assert m["path"] == "IMU-only adjustment" and m["auto"] is False
    assert [s["name"] for s in m["sessions"]] == [long_recording.stem, late.stem]
    for session, path in zip(m["sessions"], (long_recording, late), strict=True):
        alone = slam(path, overrides=NO_MAP, mag_lag=0.0).info["magnetometer_lag"]["estimate"]
        assert session["estimate"]["lag_seconds"] == pytest.approx(alone["lag_seconds"])
        assert session["estimate"]["windows"] == alone["windows"]


def test_imu_sessions_remove_each_ones_clear_lag_by_default(tmp_path, long_recording, monkeypatch):
    """Several IMU recordings, no --mag-lag: each one's lag is estimated on its own IMU-only
    adjustment and removed when significant before the sessions are stacked (a warning
    names the recording); the lag left on the path solved is reported per session. A lag
    in seconds belongs to one recording: refused in one line."""
    late = _late(long_recording, tmp_path, 0.15)
    found = [0.0, 0.15, 0.0, 0.01]  # each session alone, then each on the path solved
    calls = []

    def stand_in(t, data, arrays, key="estimate"):
        calls.append(data.Y.copy())
        lag = found[len(calls) - 1]
        return LagEstimate(lag, 500.0, abs(lag) >= 0.05, 3, 10.0, 0.05)

    monkeypatch.setattr(imurec, "imu_lag", stand_in)
    lines = []
    r = slam_sessions([long_recording, late], overrides=NO_MAP, on_warning=lines.append)
    m = r.info["magnetometer_lag"]
    assert m["auto"] is True and len(calls) == 4
    assert [s["removed_seconds"] for s in m["sessions"]] == [0.0, 0.15]
    assert [s["estimate"]["lag_seconds"] for s in m["sessions"]] == [0.0, 0.01]
    rec = read_recording(late)
    np.testing.assert_array_equal(calls[1], rec.Y)  # estimated on the recording as read
    np.testing.assert_allclose(calls[3], shift_magnetometer(rec.t, rec.Y, 0.15))  # solved shifted
    assert any(str(late) in line and "shifted by 0.15 s" in line for line in lines)
    # no map: the path solved is the IMU-only adjustment, whose lag the verdict leaves alone
    assert m["path"] == "IMU-only adjustment" and "magnetometer_lag" not in r.verdict["checks"]
    with pytest.raises(DataError, match="a lag in seconds belongs to one recording"):
        slam_sessions([long_recording, late], overrides=NO_MAP, mag_lag=0.15)


@pytest.mark.slow
def test_casmag_slam_draws_one_panel_per_imu_session(tmp_path, long_recording):
    """``casmag slam A B`` on IMU recordings writes its figures: sessions.png takes each
    session's keyframes (the IMU model's arrays are per keyframe)."""
    out = tmp_path / "out"
    res = _cli(["slam", long_recording, long_recording, "--out", out, "-q", "--set", NO_MAP[0]])
    assert res.exit_code == 0, res.output
    assert (out / "sessions.png").stat().st_size > 0 and (out / "trajectory.png").exists()
    saved = json.loads((out / "result.json").read_text())
    assert [s["keyframes"] for s in saved["info"]["sessions"]] == [161, 161]
