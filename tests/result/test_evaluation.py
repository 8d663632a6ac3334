"""Errors after an optional alignment to the truth (casmag.result.evaluation): the closed-form rigid
alignment against a numpy reference, its optimality, and ``--align`` through every motion
model's command, result.json and ``casmag report``."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import planar_room_field

import casmag
from casmag.cli.main import main
from casmag.data.imusim import simulate_planar
from casmag.data.recording import write_recording
from casmag.errors import DataError
from casmag.result.evaluation import evaluate, rigid_alignment


def _rotation(d, rng):
    if d == 2:
        a = rng.uniform(-np.pi, np.pi)
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@pytest.mark.parametrize("d", [2, 3])
def test_se_alignment_undoes_a_rigid_motion(d):
    rng = np.random.default_rng(7)
    truth = np.cumsum(rng.normal(size=(200, d)), axis=0)
    R0, t0 = _rotation(d, rng), rng.normal(size=d)
    moved = truth @ R0.T + t0  # the truth in another frame
    R, t = rigid_alignment(moved, truth, "se")
    np.testing.assert_allclose(R, R0.T, atol=1e-10)
    np.testing.assert_allclose(moved @ R.T + t, truth, atol=1e-9)
    e = evaluate({"P_estimate": moved, "P_true": truth}, "se")
    assert e["after"]["rmse"] < 1e-9
    assert e["after"]["max"] < 1e-9


@pytest.mark.parametrize("d", [2, 3])
def test_se_is_the_best_rigid_alignment_and_start_matches_the_first_position(d):
    rng = np.random.default_rng(11)
    truth = np.cumsum(rng.normal(size=(150, d)), axis=0)
    est = truth + np.cumsum(rng.normal(scale=0.05, size=(150, d)), axis=0) + 0.3
    arrays = {"P_estimate": est, "P_true": truth}
    rmse = {a: evaluate(arrays, a)["after"]["rmse"] for a in ("none", "start", "se")}
    assert rmse["se"] < rmse["start"] and rmse["se"] < rmse["none"]
    R, t = rigid_alignment(est, truth, "start")
    np.testing.assert_allclose(est[0] @ R.T + t, truth[0])
    # A random rotation about the optimum never does better.
    Rs, ts = rigid_alignment(est, truth, "se")
    for _ in range(20):
        Rp = _rotation(d, rng) if d == 3 else _rotation(2, rng)
        Rq = Rs @ (np.eye(d) + 1e-2 * (Rp - Rp.T))
        u, _, vt = np.linalg.svd(Rq)
        Rq = u @ vt
        worse = np.sqrt(np.mean(np.sum((est @ Rq.T + ts - truth) ** 2, axis=1)))
        assert worse >= rmse["se"] - 1e-12


def test_se_alignment_never_reflects():
    truth = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 2.0]])
    mirrored = truth * np.array([1.0, -1.0])
    R, _ = rigid_alignment(mirrored, truth, "se")
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_unknown_alignment_is_refused():
    with pytest.raises(DataError, match="align: expected one of none, start, se"):
        evaluate({"P_estimate": np.zeros((3, 2)), "P_true": np.zeros((3, 2))}, "sim3")


def _invoke(args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def base_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    for seed in (1, 2):
        res = _invoke(
            ["solve", "problems/paper/base.yaml", "--set", f"seed={seed}", "--out",
             root / f"s{seed}", "--align", "se", "-q", "--no-figures"]
        )  # fmt: skip
        assert res.exit_code == 0, res.output
    return root


def test_solve_records_the_anchor_and_the_alignment(base_runs):
    r = json.loads((base_runs / "s1" / "result.json").read_text())
    e = r["evaluation"]
    assert e["align"] == "se" and e["before_trajectory"] == "P_odometry"
    assert e["anchor"]["kind"] == "first true position"
    # se is the best rigid alignment, the anchored frame one of them.
    assert e["after"]["rmse"] <= r["rmse_after"] and e["before"]["rmse"] <= r["rmse_before"]
    assert e["after"]["rmse"] < e["before"]["rmse"]
    loaded = casmag.Result.load(base_runs / "s1")
    assert loaded.evaluation == e
    assert casmag.evaluate(loaded, "none")["after"]["rmse"] == pytest.approx(r["rmse_after"])


def test_report_measures_again_after_the_alignment(base_runs):
    plain = _invoke(["report", base_runs])
    aligned = _invoke(["report", base_runs, "--align", "se"])
    assert plain.exit_code == 0 and aligned.exit_code == 0, aligned.output
    assert "no alignment" in plain.output and "after alignment 'se'" in aligned.output
    after = [json.loads((base_runs / s / "result.json").read_text()) for s in ("s1", "s2")]
    mean_se = np.mean([a["evaluation"]["after"]["rmse"] for a in after])
    row = next(ln for ln in aligned.output.splitlines() if ln.startswith("| After SLAM"))
    assert f"| {mean_se:.4f} |" in row


def test_report_align_without_saved_arrays_names_the_file(tmp_path, base_runs):
    src = json.loads((base_runs / "s1" / "result.json").read_text())
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "result.json").write_text(json.dumps(src))
    res = _invoke(["report", tmp_path / "r" / "result.json", "--align", "start"])
    assert res.exit_code == 2
    assert "result.json: no arrays.npz beside it to align" in res.output
    assert res.output.count("\n") == 1


def test_imu_results_are_aligned_against_the_imu_only_adjustment(tmp_path):
    out = tmp_path / "imu"
    res = _invoke(
        ["imu", "problems/imu/rectangle.yaml", "--set", "simulation.scenario.loops=1", "--set",
         "model.gp.form=none", "--out", out, "--align", "start", "-q", "--no-figures"]
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    e = r["evaluation"]
    assert e["align"] == "start" and e["before_trajectory"] == "P_imu_only"
    assert e["anchor"]["kind"].startswith("initial state")
    assert (out / "arrays.npz").is_file()
    rep = _invoke(["report", out, "--align", "start"])
    assert rep.exit_code == 0, rep.output
    assert "after alignment 'start'" in rep.output


def test_planar_results_carry_the_anchor(tmp_path):
    d = simulate_planar(4, planar_room_field(), size=(2.0, 1.5), loops=1, disp_noise=0.002)
    rec = tmp_path / "walk.csv"
    write_recording(rec, d.t, d.Y, planar=d.U, P_true=d.P, yaw_true=d.psi)
    out = tmp_path / "out"
    res = _invoke(["slam", rec, "--out", out, "--align", "se", "-q", "--no-figures"])
    r = json.loads((out / "result.json").read_text())
    assert res.exit_code == (0 if r["verdict"]["trusted"] else 3), res.output
    assert r["evaluation"]["align"] == "se"
    assert r["evaluation"]["anchor"]["kind"] == "first true position"
    assert r["evaluation"]["before"]["rmse"] <= r["rmse_before"] + 1e-12


def test_the_anchor_is_an_option_and_the_report_states_it(tmp_path, monkeypatch):
    """``--anchor origin``: the estimate in the odometry's frame, evaluated after alignment;
    the truth-start check is not run (the true states are in another frame)."""
    import casmag.solver.planar

    checks = []
    monkeypatch.setattr(casmag.solver.planar, "truth_check", lambda *a: checks.append(a))
    d = simulate_planar(4, planar_room_field(), size=(2.0, 1.5), loops=2, disp_noise=0.002)
    rec = tmp_path / "walk.csv"
    write_recording(rec, d.t, d.Y, planar=d.U, P_true=d.P, yaw_true=d.psi)
    out = tmp_path / "origin"
    res = _invoke(
        ["slam", rec, "--out", out, "--anchor", "origin", "--align", "se", "-q", "--no-figures"]
    )
    assert checks == []
    r = json.loads((out / "result.json").read_text())
    assert res.exit_code == (0 if r["verdict"]["trusted"] else 3), res.output
    e = r["evaluation"]
    assert e["anchor"]["kind"] == "origin" and e["anchor"]["position"] == [0.0, 0.0]
    # the frame is the odometry's: without alignment the error holds the frame's offset
    assert r["max_before"] >= np.linalg.norm(d.P[0]) - 1e-9  # the first sample: |p_0|
    assert e["before"]["rmse"] < 0.2 * r["rmse_before"]
    rep = _invoke(["report", out, "--align", "se"])
    assert "anchored at the origin, after alignment 'se'" in rep.output
    sessions = _invoke(["slam", rec, rec, "--out", tmp_path / "two", "--anchor", "origin"])
    assert sessions.exit_code == 2 and "several sessions" in sessions.output


def test_the_rigid_fit_is_given_whatever_the_alignment():
    """``evaluation["rigid"]`` is the se fit's errors beside the alignment asked for: a path
    right in shape but turned about its start has a large RMSE and a rigid one near zero."""
    rng = np.random.default_rng(3)
    truth = np.cumsum(rng.normal(scale=0.1, size=(300, 2)), axis=0)
    a = np.radians(8.0)
    turned = truth @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]).T
    odometry = truth + np.cumsum(rng.normal(scale=0.02, size=(300, 2)), axis=0)
    arrays = {"P_estimate": turned, "P_true": truth, "P_odometry": odometry}
    for align in ("none", "start", "se"):
        e = evaluate(arrays, align)
        assert e["rigid"] == evaluate(arrays, "se")["rigid"]
        assert e["rigid"]["after"]["rmse"] < 1e-9
        assert e["rigid"]["after"]["rotation_deg"] == pytest.approx(8.0)
        assert e["rigid"]["before"] == evaluate(arrays, "se")["before"]
    assert evaluate(arrays, "none")["after"]["rmse"] > 0.01
    assert evaluate({"P_estimate": None, "P_true": truth}, "none")["rigid"]["after"]["rmse"] is None
