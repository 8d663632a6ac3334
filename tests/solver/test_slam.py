"""`casmag slam` on recordings: defaults from the data, the staged (growing) solve, knots."""

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import casmag
from casmag.cli.main import main
from casmag.data.recording import dataset_to_recording_arrays, read_recording, write_recording
from casmag.data.simulate import simulate_problem
from casmag.model.knots import Knots
from casmag.solver.recslam import recording_problem, truth_check, truth_start
from casmag.solver.windowing import continued, stage_lengths

ROOT = Path(__file__).resolve().parents[2]


def _walk(samples=900, seed=3):
    """A looping walk in a 3 m x 3 m room at 10 Hz with a drifting odometry."""
    return casmag.load_problem(
        ROOT / "problems/bench/walk.yaml",
        [
            f"seed={seed}",
            f"simulation.trajectory.samples={samples}",
            "simulation.trajectory.area=[3.0, 3.0]",
            "simulation.odometry.bias=[6.0e-4, -3.0e-4]",
        ],
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    data = simulate_problem(_walk())
    path = tmp_path_factory.mktemp("rec") / "walk.csv"
    write_recording(path, **dataset_to_recording_arrays(data, dt=0.1))
    return path, data


@pytest.mark.slow
def test_slam_on_a_recording_with_truth(recording, tmp_path):
    path, _ = recording
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["slam", str(path), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    res = json.loads((out / "result.json").read_text())
    assert res["success"]
    for name in ("trajectory.csv", "trajectory.png", "map.png", "cost.png"):
        assert (out / name).is_file()
    assert res["rmse_after"] <= 0.25 * res["rmse_before"], (res["rmse_before"], res["rmse_after"])
    info = res["info"]
    assert info["gp_form"] == "reduced_rank"
    assert info["knot_every"] == 10  # one knot per second at 10 Hz
    # Hyperparameters from the marginal likelihood, not the simulation's values.
    est = info["defaults"]["marginal_likelihood"]
    assert est["lengthscale"] == pytest.approx(res["hyperparameters"]["lengthscale"])
    assert 0.2 < est["lengthscale"] < 0.6  # truth 0.35 m, seen through drifted positions


def test_slam_without_truth_reports_null_errors(recording, tmp_path):
    _, data = recording
    arrays = dataset_to_recording_arrays(data.prefix(300), dt=0.1)
    arrays.pop("P_true")
    path = tmp_path / "no_truth.csv"
    write_recording(path, **arrays)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["slam", str(path), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    res = json.loads((out / "result.json").read_text())
    assert res["success"] and res["rmse_before"] is None and res["rmse_after"] is None


def test_slam_bad_recording_is_one_line_exit_2(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("t,dx,dy,mx,my,mz\n0,,,1,2,3\n1,0.1,0.1,1,2\n")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["slam", str(path), "--out", str(out)])
    assert r.exit_code == 2
    assert len(r.output.strip().splitlines()) == 1 and "bad.csv" in r.output
    assert not out.exists()


def test_slam_refuses_a_simulation_section(recording, tmp_path):
    path, _ = recording
    prob = tmp_path / "p.yaml"
    prob.write_text("simulation: {}\n")
    r = CliRunner().invoke(
        main, ["slam", str(path), "--out", str(tmp_path / "o"), "--problem", str(prob)]
    )
    assert r.exit_code == 2 and "simulation" in r.output


@pytest.mark.slow
def test_growing_warm_start_recovers_drift_a_batch_does_not():
    """Strong drift: the batch from dead reckoning stalls far from the truth; growing
    prefixes (bias removed stage by stage) reach it."""
    prob = _walk(samples=1600, seed=5).with_overrides(
        ["simulation.odometry.bias=[1.5e-3, -1.0e-3]"]
    )
    data = simulate_problem(prob)
    batch = casmag.solve(prob.with_overrides(["solver.warm_start.strategy=none"]), data)
    grown = casmag.solve(
        prob.with_overrides(
            ["solver.warm_start.strategy=growing", "solver.warm_start.first_samples=400"]
        ),
        data,
    )
    assert grown.success, grown.status
    assert [s["samples"] for s in grown.stages_named("prefix")] == [400, 1600]
    assert grown.info["warm_start"] == "growing" and len(grown.stages) == 2
    assert grown.rmse_after <= 0.1 * grown.rmse_before
    assert grown.rmse_after < 0.5 * (batch.rmse_after if batch.success else np.inf)


def test_stage_lengths_and_continuation():
    assert stage_lengths(64000, 4000, 4.0) == [4000, 16000, 64000]
    assert stage_lengths(20000, 4000, 4.0) == [4000, 20000]
    assert stage_lengths(4100, 4000, 4.0) == [4100]
    prev = np.array([[0.0, 0.0], [1.0, 1.0]])
    dr = np.array([[0.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    np.testing.assert_allclose(continued(prev, dr), [[0, 0], [1, 1], [2, 1]])


def test_knots_interpolate_and_collapse_the_odometry():
    k = Knots(11, 4)
    np.testing.assert_array_equal(k.samples, [0, 4, 8, 10])
    np.testing.assert_array_equal(k.steps, [4, 4, 2])
    A = k.matrix.toarray()
    np.testing.assert_allclose(A.sum(axis=1), 1.0)
    np.testing.assert_allclose(A[6], [0, 0.5, 0.5, 0])
    # fit() recovers corrections that are piecewise linear between knots
    rng = np.random.default_rng(0)
    C = rng.standard_normal((4, 2))
    Q = rng.standard_normal((11, 2))
    np.testing.assert_allclose(k.fit(Q, k.positions(Q, C)), C, atol=1e-9)


def test_estimate_in_a_recordings_problem_means_from_the_data(tmp_path):
    """``estimate`` as a hyperparameter's value (the planar and pose models' spelling), in
    the problem file or as --set, is what null means for a recording: estimated from the
    data by the marginal likelihood, not listed for the joint MAP (which the reduced-rank
    map refuses)."""
    from casmag.solver.recslam import recording_problem

    data = simulate_problem(_walk(samples=200))
    times = np.arange(data.n_samples) * 0.1
    problem = tmp_path / "p.yaml"
    problem.write_text("model:\n  gp:\n    sigma_f: estimate\n    lengthscale: 0.4\n")
    prob, how = recording_problem(
        data, times, "walk", problem, ["model.magnetometer.sigma_m=estimate"]
    )
    assert sorted(how["estimated"]) == ["sigma_f", "sigma_m"]
    assert prob.spec.model.estimate == []
    est = how["marginal_likelihood"]
    assert prob.spec.model.gp.sigma_f == est["sigma_f"]
    assert prob.spec.model.magnetometer.sigma_m == est["sigma_m"]
    assert prob.spec.model.gp.lengthscale == 0.4


def test_a_worse_optimum_than_the_truths_is_flagged_wrong_basin(tmp_path):
    """With truth (evaluation), an estimate above 1/4 of the dead reckoning's RMSE is solved
    again from the true positions (as the planar and pose models are): a MAP cost lower
    there flags ``wrong_basin`` and the verdict withholds trust. The walk's own estimate is
    right (the solve from the truth ends at its cost); its RMSE and cost are then made to
    look like a worse optimum's, and like a better one's."""
    data = simulate_problem(_walk(samples=300))
    path = tmp_path / "walk.csv"
    write_recording(path, **dataset_to_recording_arrays(data, dt=0.1))
    result = casmag.slam(path)
    assert result.success and result.rmse_after <= 0.25 * result.rmse_before
    assert "truth_start" not in result.info and result.verdict["trusted"]
    rec = read_recording(path)
    prob, _ = recording_problem(rec.to_dataset(), rec.t, "walk", None, ())
    dataset = rec.to_dataset()
    start, _ = truth_start(prob, dataset, result)
    assert start["success"] and abs(start["cost_above_result"]) < 1.0
    for shift, flagged in ((1000.0, True), (-1000.0, False)):
        r = copy.deepcopy(result)
        r.rmse_after = 0.5 * r.rmse_before
        r.cost_blocks["magnetometer"]["after"] += shift
        truth_check(prob, dataset, r)
        assert r.info["truth_start"]["cost_above_result"] == pytest.approx(-shift, abs=1.0)
        names = [f["name"] for f in r.flags or []]
        assert ("wrong_basin" in names) is flagged
        assert r.verdict["trusted"] is not flagged
