"""GP-SLAM on growing prefixes of the keyframes (``model.gp.grow``)."""

import numpy as np
import pytest
from small_problems import imu_noise_free as _noise_free
from small_problems import tiny_imu as _tiny

from casmag import strapdown as sd
from casmag.errors import ProblemError
from casmag.problem.imu import load_imu_problem
from casmag.solver import imu as imuslam
from casmag.solver.imu import ImuSolveStage, continue_start, grow_sizes, solve_imu


@pytest.mark.parametrize(
    ("value", "reason"),
    [
        ("[0.5, 0.25, 1.0]", "increasing"),
        ("[0.25, 0.5]", "last fraction must be 1"),
        ("[0.0, 1.0]", "(0, 1]"),
        ("[0.5, 1.5]", "(0, 1]"),
    ],
)
def test_bad_grow_fractions_name_the_key(value, reason):
    with pytest.raises(ProblemError) as err:
        load_imu_problem(_tiny(), [f"model.gp.grow={value}"])
    msg = str(err.value)
    assert "model.gp.grow" in msg and reason in msg


def test_grow_sizes():
    assert grow_sizes(246, [0.25, 0.5, 0.75, 1.0]) == [62, 123, 184, 246]
    assert grow_sizes(10, [0.01, 0.1, 0.15, 1.0]) == [2, 10]  # at least 2, strictly increasing
    assert grow_sizes(10, [1.0]) == [10]


def _stage(P, V, Q, bw, ba, **x):
    class Sol:
        pass

    sol = Sol()
    sol.x = {"BW": bw, "BA": ba, **x}
    return ImuSolveStage(solution=sol, nlp=None, P=P, V=V, Q=Q, b_w=bw, b_a=ba)


def test_continuation_joins_the_prefix_rigidly():
    """A prefix that is the reference moved by an offset and turned by a rotation: the
    continuation is the reference moved by the same offset (positions and velocities) and
    its orientations turned by the same rotation, the prefix kept, biases the prefix's last
    (random walk) or its constant, map weights carried over."""
    rng = np.random.default_rng(1)
    K, Kp = 12, 5
    P, V = rng.standard_normal((K, 3)), rng.standard_normal((K, 3))
    Q = sd.gibbs_quat(0.3 * rng.standard_normal((K, 3)))
    ref = _stage(P, V, Q, np.zeros((K, 3)), np.zeros((K, 3)))
    dp, dv = np.array([0.01, -0.02, 0.003]), np.array([1e-3, 0.0, -2e-3])
    turn = sd.gibbs_quat(np.array([[0.0, 0.01, 0.05]]))
    bw = rng.standard_normal((Kp, 3))
    W, c = rng.standard_normal((7, 1)), rng.standard_normal((3, 1))
    prefix = _stage(
        P[:Kp] + dp,
        V[:Kp] + dv,
        sd.quat_mul(np.repeat(turn, Kp, 0), Q[:Kp]),
        bw,
        np.ones((1, 3)),
        W=W,
        c=c,
    )
    out = continue_start({"zero_centre": np.zeros((1, 3))}, prefix, ref, K)
    np.testing.assert_allclose(out["P"], P + dp, atol=1e-12)
    np.testing.assert_allclose(out["V"], V + dv, atol=1e-12)
    ang = sd.quat_angle(out["Q"], sd.quat_mul(np.repeat(turn, K, 0), Q))
    assert np.max(ang) < 1e-7
    np.testing.assert_array_equal(out["BW"][:Kp], bw)
    np.testing.assert_array_equal(out["BW"][Kp:], np.repeat(bw[-1:], K - Kp, 0))
    assert out["BA"].shape == (1, 3)
    assert out["W"] is W and out["c"] is c


def _noise_free_rectangle_data(grow, grow_anneal=False, form="reduced_rank", **more):
    """The noise-free rectangle of test_imu (traced twice, constant biases, 400 basis
    functions or the exact GP, sigma_m x4 then x1) with model.gp.grow (and ``more``
    model.gp settings)."""
    gp = {"sigma_f": 0.3, "lengthscale": 0.2, "grow": grow, "grow_anneal": grow_anneal, **more}
    gp.update({"num_basis": 400} if form == "reduced_rank" else {"form": form})
    data = _noise_free(_tiny(gp=gp))
    data["simulation"]["scenario"]["loops"] = 2
    data["model"]["imu"]["bias"] = "constant"
    data["model"]["zero_position"] = {"sigma": 1.0}
    return data


def _noise_free_rectangle(grow, grow_anneal=False, form="reduced_rank", **more):
    return solve_imu(load_imu_problem(_noise_free_rectangle_data(grow, grow_anneal, form, **more)))


@pytest.mark.parametrize(
    ("grow_anneal", "form"),
    [(False, "reduced_rank"), (True, "reduced_rank"), (True, "exact")],
    ids=["first-pass", "anneal-per-prefix", "exact-gp"],
)
def test_noise_free_gp_slam_grown_from_a_prefix_returns_the_truth(grow_anneal, form):
    """Grown from 3/4 of the keyframes: the same truth as the batch passes (0.30 mm with
    the reduced-rank map, 0.74 mm with the exact GP; measured the same here), each solve
    recorded and the total counted. (From half, one loop with no revisit, the prefix stops
    at the iteration limit: measured.)"""
    r = _noise_free_rectangle([0.75, 1.0], grow_anneal, form)
    assert r.success, r.status
    a = r.arrays
    assert np.abs(a["P_estimate"] - a["P_true"]).max() < 1e-3
    true, est = (
        np.array(r.details["biases"]["gyro"]["truth"]),
        np.array(r.details["biases"]["gyro"]["gp_slam"]),
    )
    # The exact GP's z gyroscope bias: 0.129 against 0.12 deg/s, as in the batch pass.
    np.testing.assert_allclose(est, true, rtol=0.05 if form == "reduced_rank" else 0.1)
    first = r.stages_named("gp_slam")[0]
    K = r.info["keyframes"]
    sizes = [round(0.75 * K), K]
    if grow_anneal:  # one pass: sigma_m x4, x1 on each prefix
        assert len(r.stages_named("gp_slam")) == 1
        assert [(g["keyframes"], g["sigma_m_factor"]) for g in first["grow"]] == [
            (k, f) for k in sizes for f in (4.0, 1.0)
        ]
    else:
        assert [g["keyframes"] for g in first["grow"]] == sizes
        assert "grow" not in r.stages_named("gp_slam")[1]
    assert first["iterations"] == first["grow"][-1]["iterations"]
    assert first["iterations_total"] == sum(g["iterations"] for g in first["grow"])


def test_prefix_at_the_iteration_limit_starts_the_next():
    """The same rectangle grown from half the keyframes (one loop, no revisit): that prefix
    stops at the iteration limit (measured), recorded with its status, and still starts
    the full problem, which returns the truth."""
    r = _noise_free_rectangle([0.5, 1.0])
    assert r.success, r.status
    first = r.stages_named("gp_slam")[0]  # grown (sigma_m x4), then the x1 pass
    K = r.info["keyframes"]
    assert [g["keyframes"] for g in first["grow"]] == [round(K / 2), K]
    assert first["grow"][0]["status"] == "Maximum_Iterations_Exceeded"
    assert first["grow"][0]["success"] is False
    assert np.abs(r.arrays["P_estimate"] - r.arrays["P_true"]).max() < 1e-3


def _failing_first_solve(monkeypatch):
    """The first GP-SLAM solve reports an IPOPT failure other than the iteration limit."""
    real, calls = imuslam._slam_solve, []

    def fake(*args, **kwargs):
        st, s2 = real(*args, **kwargs)
        calls.append(st)
        if len(calls) == 1:
            st.solution.status, st.solution.success = "Restoration_Failed", False
        return st, s2

    monkeypatch.setattr(imuslam, "_slam_solve", fake)


def test_failed_prefix_is_reported_with_its_status(monkeypatch):
    """A prefix that fails (other than at the iteration limit) stops the pipeline: that is
    the result, with IPOPT's status."""
    _failing_first_solve(monkeypatch)
    r = _noise_free_rectangle([0.5, 1.0], coarse_to_fine=None, fallback_grow=None)
    assert r.stage("imu_only")["status"] == "Solve_Succeeded"
    assert not r.success and r.status == "Restoration_Failed"
    assert r.details["failed_stage"] == "gp_slam" and r.details["errors"]["gp_slam"]["rmse"] is None
    assert r.details["biases"]["gyro"]["gp_slam"] is None
    (only,) = r.stages_named("gp_slam")
    assert only["status"] == "Restoration_Failed"
    assert [g["keyframes"] for g in only["grow"]] == [round(r.info["keyframes"] / 2)]
    assert only["grow"][0]["success"] is False


@pytest.mark.slow
def test_a_failed_schedule_is_recorded_and_the_coarse_to_fine_one_kept(monkeypatch):
    """The same failure with the coarse-to-fine schedule on (the default): it runs, reaches
    the truth, and is the result; the failed anneal schedule is recorded with its status."""
    _failing_first_solve(monkeypatch)
    r = _noise_free_rectangle([0.5, 1.0])
    assert r.success, r.status
    anneal, c2f = r.details["schedules"]
    assert anneal["status"] == "Restoration_Failed" and not anneal["kept"]
    assert c2f["success"] and c2f["kept"] and len(r.stages_named("gp_slam")) == 3
    assert np.abs(r.arrays["P_estimate"] - r.arrays["P_true"]).max() < 1e-3


def test_the_grown_schedule_follows_two_failed_ones(monkeypatch):
    """The anneal and coarse-to-fine schedules both fail in their first solve: the grown
    schedule (the anneal factors on each prefix, here 3/4 and all) runs from the IMU-only
    adjustment, reaches the truth and is the result; every schedule is recorded."""
    real, calls = imuslam._slam_solve, []

    def fake(*args, **kwargs):
        st, s2 = real(*args, **kwargs)
        calls.append(st)
        if len(calls) <= 2:  # anneal's first pass, then coarse-to-fine's first pass
            st.solution.status, st.solution.success = "Restoration_Failed", False
        return st, s2

    monkeypatch.setattr(imuslam, "_slam_solve", fake)
    r = _noise_free_rectangle(None, fallback_grow=[0.75, 1.0])
    assert r.success, r.status
    assert [s["schedule"] for s in r.details["schedules"]] == ["anneal", "coarse_to_fine", "grown"]
    assert [s["kept"] for s in r.details["schedules"]] == [False, False, True]
    assert [s["status"] for s in r.details["schedules"][:2]] == ["Restoration_Failed"] * 2
    assert len(r.details["schedules"][2]["iterations"]) == 4  # two prefixes, sigma_m x4 then x1
    assert np.abs(r.arrays["P_estimate"] - r.arrays["P_true"]).max() < 1e-3


def test_command_names_the_failed_prefix(tmp_path, monkeypatch):
    import json

    import yaml
    from click.testing import CliRunner

    from casmag.cli.main import imu as imu_command

    _failing_first_solve(monkeypatch)
    path = tmp_path / "p.yaml"
    path.write_text(
        yaml.safe_dump(
            _noise_free_rectangle_data([0.5, 1.0], coarse_to_fine=None, fallback_grow=None)
        )
    )
    out = tmp_path / "out"
    res = CliRunner().invoke(imu_command, [str(path), "--out", str(out), "-q"])
    assert res.exit_code == 1
    assert "GP-SLAM (prefix of 24 of 47 keyframes)" in res.output
    assert "Restoration_Failed" in res.output
    r = json.loads((out / "result.json").read_text())
    assert r["success"] is False and r["stages"][1]["grow"][0]["keyframes"] == 24
