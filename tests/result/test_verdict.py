"""One verdict for every motion model (casmag.result.verdict): the checks, their reasons,
exit code 3 and the figures' titles."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import planar_room_field

import casmag
from casmag.cli.main import main
from casmag.data.imusim import simulate_planar
from casmag.data.recording import write_recording
from casmag.result import plotting
from casmag.result.verdict import (
    MISFIT_LIMIT,
    NEES_LIMIT_FACTOR,
    STARTS_APART_LENGTHSCALES,
    STARTS_Z,
    WORSE_RATIO,
    revisit_fraction,
    verdict,
)
from casmag.solver.recslam import revisit_noise


def _result(**kw):
    base = dict(
        success=True,
        status="Solve_Succeeded",
        info={"n_samples": 100},
        cost_blocks={"magnetometer": {"before": 900.0, "after": 150.0}},
        rmse_before=0.2,
        rmse_after=0.02,
    )
    return SimpleNamespace(**{**base, **kw})


def test_a_good_estimate_passes_every_check():
    v = verdict(_result())
    assert v["trusted"] and v["reasons"] == []
    assert v["checks"]["magnetometer_misfit"]["value"] == pytest.approx(1.0)
    assert v["checks"]["against_truth"]["passed"] is True


def test_residuals_far_above_the_assumed_noise_are_not_trusted():
    v = verdict(_result(cost_blocks={"magnetometer": {"after": 150.0 * MISFIT_LIMIT}}))
    assert not v["trusted"] and v["checks"]["magnetometer_misfit"]["passed"] is False
    assert "assumed noise variance" in v["reasons"][0]


def test_worse_than_the_dead_reckoning_is_not_trusted_and_without_truth_not_checked():
    v = verdict(_result(rmse_after=0.2 * WORSE_RATIO * 1.01))
    assert not v["trusted"] and "worse than the dead reckoning" in v["reasons"][0]
    assert verdict(_result(rmse_after=0.2 * WORSE_RATIO))["trusted"]
    v = verdict(_result(rmse_before=None, rmse_after=None))
    assert v["trusted"] and "against_truth" not in v["checks"]


def test_one_session_worse_than_its_dead_reckoning_is_not_trusted():
    sessions = [
        {"name": "a", "rmse_before": 0.86, "rmse_after": 0.43},
        {"name": "b", "rmse_before": 0.87, "rmse_after": 1.44},
    ]
    # the whole run passes (0.86 -> 0.89 m) while session b ended worse than it started
    v = verdict(_result(rmse_before=0.86, rmse_after=0.89, info={"sessions": sessions}))
    assert not v["trusted"]
    assert v["reasons"] == [
        "session b worse than its dead reckoning against the truth: RMSE 0.87 -> 1.44 m "
        f"(more than {WORSE_RATIO:g} x)"
    ]
    assert [w["name"] for w in v["checks"]["against_truth"]["worse_sessions"]] == ["b"]
    sessions[1]["rmse_after"] = 0.87 * WORSE_RATIO
    assert verdict(_result(rmse_before=0.86, rmse_after=0.5, info={"sessions": sessions}))[
        "trusted"
    ]


def _started(other_cost, other_apart, tau=None, sessions=False):
    """A result of 100 samples (magnetometer block 150: its spread 150 sqrt(2 tau / 300))
    solved from two starts, the kept one at cost 400."""
    stages = [
        {"name": "start", "start": "dead reckoning", "cost": 400.0, "kept": True,
         "path_rms_from_kept": 0.0},
        {"name": "start", "start": "evidence bias", "cost": other_cost, "kept": False,
         "path_rms_from_kept": other_apart},
    ]  # fmt: skip
    if sessions:
        stages.append({"name": "start", "session": 1, "cost": 500.0, "kept": True})
    u = None if tau is None else {"inflation": {"tau": [[tau, tau, tau]]}}
    return _result(stages=stages, hyperparameters={"lengthscale": 0.3}, uncertainty=u)


def test_another_start_far_away_at_nearly_the_same_cost_is_not_trusted():
    sd = 150.0 * np.sqrt(2.0 / 300.0)  # tau 1
    far = 1.5 * STARTS_APART_LENGTHSCALES * 0.3
    v = verdict(_started(400.0 + 0.5 * STARTS_Z * sd, far))
    assert not v["trusted"] and v["checks"]["starts"]["passed"] is False
    assert "do not decide between the two" in v["reasons"][0]
    assert v["checks"]["starts"]["close"][0]["z"] == pytest.approx(0.5 * STARTS_Z)
    # decided by the cost, or the same estimate
    assert verdict(_started(400.0 + 1.5 * STARTS_Z * sd, far))["trusted"]
    assert verdict(_started(400.0 + 0.5 * STARTS_Z * sd, 0.5 * far))["trusted"]
    # correlated residuals widen the spread: tau 4 doubles it
    v = verdict(_started(400.0 + 1.5 * STARTS_Z * sd, far, tau=4.0))
    assert not v["trusted"] and v["checks"]["starts"]["tau_samples"] == 4.0
    # one start, a failed start, or several sessions: not made
    assert "starts" not in verdict(_result())["checks"]
    assert verdict(_started(None, far))["checks"]["starts"]["others"] == []
    assert "starts" not in verdict(_started(400.0, far, sessions=True))["checks"]


def test_a_failed_solve_and_a_models_own_flags_are_reasons():
    v = verdict(_result(success=False, status="Maximum_Iterations_Exceeded"))
    assert not v["trusted"] and "Maximum_Iterations_Exceeded" in v["reasons"][0]
    flag = {"name": "wrong_basin", "reason": "the truth costs less", "evidence": {}}
    v = verdict(_result(flags=[flag], motion="imu"))
    assert v["reasons"] == ["wrong_basin: the truth costs less"]
    assert "against_truth" not in v["checks"]  # the IMU model's flags judge it against the truth
    v = verdict(_result(flags=[flag]))  # the planar model's: the truth is checked too
    assert v["reasons"] == ["wrong_basin: the truth costs less"]
    assert v["checks"]["against_truth"]["passed"] is True


def _lag(lag_seconds, significant):
    return {"lag_seconds": lag_seconds, "gain": 800.0, "significant": significant}


def test_a_lag_left_on_the_estimated_path_is_not_trusted_one_on_the_dead_reckoning_is():
    """A significant lag estimated on the path solved (IMU: GP-SLAM) is a reason, per
    session when there are several; one estimated on the dead reckoning or the IMU-only
    adjustment stays a warning."""
    late = {"path": "GP-SLAM", "estimate": _lag(0.17, True), "removed_seconds": 0.0}
    v = verdict(_result(info={"n_samples": 100, "magnetometer_lag": late}))
    assert not v["trusted"] and v["checks"]["magnetometer_lag"]["passed"] is False
    assert v["reasons"] == [
        "the magnetometer lags the estimated path by 0.17 s (log-likelihood gain 800): it "
        "was read at the wrong places, an error the model does not hold (--mag-lag SECONDS "
        "removes a known lag)"
    ]
    clear = {**late, "estimate": _lag(0.02, False)}
    v = verdict(_result(info={"n_samples": 100, "magnetometer_lag": clear}))
    assert v["trusted"] and v["checks"]["magnetometer_lag"]["passed"] is True
    for path in ("IMU-only adjustment", None):  # None: translational (the dead reckoning)
        early = {**late, "path": path}
        v = verdict(_result(info={"n_samples": 100, "magnetometer_lag": early}))
        assert v["trusted"] and "magnetometer_lag" not in v["checks"]
    sessions = {
        "path": "GP-SLAM",
        "estimate": None,
        "sessions": [{"name": "a", "estimate": _lag(0.01, False)},
                     {"name": "b", "estimate": _lag(-0.12, True)}],
    }  # fmt: skip
    v = verdict(_result(info={"n_samples": 100, "magnetometer_lag": sessions}))
    assert not v["trusted"] and len(v["reasons"]) == 1
    assert v["reasons"][0].startswith(
        "the magnetometer lags the estimated path of session b by -0.12 s"
    )


def test_the_base_case_is_trusted_and_says_so_in_result_json(tmp_path):
    r = casmag.solve(casmag.load_problem("problems/paper/base.yaml", seed=1))
    assert r.trusted and set(r.verdict["checks"]) == {
        "solver",
        "magnetometer_misfit",
        "revisits",
        "flags",
        "against_truth",
        "covariance_against_truth",
    }
    assert r.verdict["checks"]["flags"] == {"passed": True, "names": []}  # one Result, any model
    assert r.verdict["checks"]["revisits"]["fraction"] > 0.5  # the paper's path loops
    r.save(tmp_path / "out", figures=False)
    saved = json.loads((tmp_path / "out" / "result.json").read_text())
    assert saved["verdict"] == r.verdict
    assert casmag.Result.load(tmp_path / "out").verdict == r.verdict


@pytest.fixture(scope="module")
def worse_recording(tmp_path_factory):
    """One loop without heading bias: the odometry is already good (RMSE 0.024 m) and the
    planar GP-SLAM makes it worse (0.066 m, seed 4)."""
    d = simulate_planar(4, planar_room_field(), size=(2.0, 1.5), loops=1, disp_noise=0.002)
    rec = tmp_path_factory.mktemp("rec") / "walk.csv"
    write_recording(rec, d.t, d.Y, planar=d.U, P_true=d.P, yaw_true=d.psi)
    return rec


def test_an_untrusted_result_exits_3_names_its_reason_and_its_figures_say_so(
    tmp_path, worse_recording
):
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["slam", str(worse_recording), "--out", str(out), "-q"])
    r = json.loads((out / "result.json").read_text())
    assert r["success"] and r["rmse_after"] > WORSE_RATIO * r["rmse_before"]
    assert res.exit_code == 3
    assert res.stderr.startswith(f"casmag: not trusted: {worse_recording}: worse than")
    assert r["verdict"]["trusted"] is False
    result = casmag.slam(worse_recording)
    fig = plotting.trajectory_figure(result, tmp_path / "t.png")
    title = fig.axes[0].get_title()
    assert "NOT TRUSTED: worse than the dead reckoning" in title
    assert fig.axes[0].title.get_color() == "tab:red"
    assert all(np.isfinite(result.arrays["P_estimate"]).ravel())


def test_the_report_counts_solved_runs_it_does_not_trust(tmp_path, worse_recording):
    out = tmp_path / "out"
    CliRunner().invoke(main, ["slam", str(worse_recording), "--out", str(out), "-q"])
    res = CliRunner().invoke(main, ["report", str(out)])
    assert res.exit_code == 0, res.output
    row = next(ln for ln in res.output.splitlines() if ln.startswith("| After SLAM"))
    assert "1/1 (not trusted x1)" in row


def _loop(turns: float, n: int = 400, radius: float = 1.0) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * np.pi * turns, n)
    return radius * np.column_stack([np.cos(a), np.sin(a)])


def test_revisits_are_counted_after_two_lengthscales_of_path():
    line = np.column_stack([np.linspace(0.0, 10.0, 200), np.zeros(200)])
    assert revisit_fraction(line, 0.3) == (0.0, 0)  # neighbours are not revisits
    share, pairs = revisit_fraction(_loop(2.0), 0.3)  # every sample comes back once
    assert share == pytest.approx(1.0) and pairs > 400
    share, _ = revisit_fraction(_loop(1.25), 0.3)  # the last quarter turn returns
    assert 0.3 < share < 0.6


def test_a_translational_path_that_never_returns_is_not_trusted():
    line = np.column_stack([np.linspace(0.0, 10.0, 100), np.zeros(100)])
    hyper = {"lengthscale": 0.3}
    v = verdict(_result(motion="translational", arrays={"P_estimate": line}, hyperparameters=hyper))
    assert not v["trusted"] and v["checks"]["revisits"]["fraction"] == 0.0
    assert "no loop closure" in v["reasons"][0]
    loop = _loop(2.0, 100)
    v = verdict(_result(motion="translational", arrays={"P_estimate": loop}, hyperparameters=hyper))
    assert v["trusted"] and v["checks"]["revisits"]["passed"]
    # The heading models' magnetometer is also a compass; the dead reckoning has no map.
    assert (
        "revisits"
        not in verdict(
            _result(motion="planar", arrays={"P_estimate": line}, hyperparameters=hyper)
        )["checks"]
    )
    v = verdict(
        _result(
            motion="translational",
            status="Odometry_Only",
            arrays={"P_estimate": line},
            hyperparameters=hyper,
        )
    )
    assert "revisits" not in v["checks"]


def test_revisit_noise_is_the_noise_that_does_not_repeat():
    """Two passes over a loop: a field that repeats cancels (the map's, at the same place);
    noise independent between the passes remains, its standard deviation per component."""
    rng = np.random.default_rng(4)
    P = _loop(2.0, 2000)
    field = np.column_stack([np.sin(3 * P[:, 0]), np.cos(2 * P[:, 1]), P[:, 0] * P[:, 1]])
    Y = field + 0.2 * rng.standard_normal(field.shape)
    noise, pairs = revisit_noise(P, Y, field, 0.3)
    assert pairs > 1000 and noise == pytest.approx(0.2, rel=0.1)
    assert np.isnan(revisit_noise(P[:500], Y[:500], field[:500], 0.3)[0])


@pytest.mark.parametrize("motion", ["translational", "planar", "pose"])
def test_an_untrusted_result_gives_no_covariance(motion):
    cov = np.tile(np.eye(2) * 1e-4, (3, 1, 1))
    summary = {"sigma_mean": 0.014, "nees_mean": 2345.8}
    flag = {"name": "wrong_basin", "reason": "a worse local optimum", "evidence": {}}

    def result(flags):  # judged as it is made (casmag.Result.judge)
        return casmag.Result(
            motion=motion, status="Solve_Succeeded", success=True, iterations=3,
            rmse_before=1.2, rmse_after=0.1, flags=flags, uncertainty=dict(summary), info={},
            build_seconds=0.1, solve_seconds=1.0, max_before=2.0, max_after=0.2,
            hyperparameters={}, cost_blocks={}, cost_per_iteration=[],
            arrays={"P_estimate": np.zeros((3, 2)), "P_cov": cov, "P_cov_uninflated": cov},
        )  # fmt: skip

    trusted = result([])
    assert trusted.uncertainty == summary and trusted.arrays["P_cov"] is cov
    wrong = result([flag])
    assert wrong.uncertainty["error"].startswith("withheld: the verdict does not trust")
    assert "wrong_basin" in wrong.uncertainty["error"]
    assert wrong.uncertainty["computed"] == summary
    assert wrong.arrays["P_cov"] is None and wrong.arrays["P_cov_uninflated"] is None
    # judged again after a flag is added (as the filter's localisation does)
    trusted.flags.append(flag)
    trusted.judge()
    assert not trusted.verdict["trusted"] and trusted.arrays["P_cov"] is None


def _with_nees(mean, interval=(0.4, 4.9), withheld=False):
    summary = {"sigma_mean": 0.016, "nees_mean": mean, "nees_interval_95": list(interval)}
    return _result(
        uncertainty={"error": "withheld: ...", "computed": summary} if withheld else summary
    )


def test_a_covariance_far_too_confident_against_the_truth_is_not_trusted():
    # real sequence 4 at 0.5 m of drift: RMSE no worse than the dead reckoning (0.288 ->
    # 0.291 m), every other check passed, and a mean NEES of 373 against an honest range
    # up to 4.87
    v = verdict(_with_nees(372.97, (0.40, 4.87)))
    check = v["checks"]["covariance_against_truth"]
    assert not v["trusted"] and check["passed"] is False
    assert check["limit"] == pytest.approx(NEES_LIMIT_FACTOR * 4.87)
    assert "far too confident" in v["reasons"][0] and "373" in v["reasons"][0]
    # at the limit it passes, above it not; an honest mean NEES passes
    assert verdict(_with_nees(NEES_LIMIT_FACTOR * 4.87, (0.40, 4.87)))["trusted"]
    assert not verdict(_with_nees(NEES_LIMIT_FACTOR * 4.87 * 1.01, (0.40, 4.87)))["trusted"]
    assert verdict(_with_nees(2.2))["checks"]["covariance_against_truth"]["passed"] is True
    # judged again after the covariance was withheld, the check reads the kept summary
    assert not verdict(_with_nees(372.97, withheld=True))["trusted"]
    # no truth (no NEES) or no honest range: the check is not made
    assert "covariance_against_truth" not in verdict(_with_nees(None))["checks"]
    assert (
        "covariance_against_truth" not in verdict(_result(uncertainty={"nees_mean": 9e9}))["checks"]
    )
