"""``casmag slam`` on a planar recording (dfwd,dleft,dyaw): dispatched to the planar model
with a heading-rate bias; outputs, exit codes, one-line errors."""

import csv
import json

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import planar_room_field

from casmag.cli.main import main
from casmag.data.imusim import simulate_planar
from casmag.data.recording import write_recording

BIAS_DEG = 0.5  # heading-rate bias [deg/s]
MAX_ITER_2 = ["--set", "solver.max_iter=2"]


@pytest.fixture(scope="module")
def planar_recording(tmp_path_factory):
    """Three loops of a 2 m x 1.5 m rounded rectangle at 1 m/s (10 Hz, 186 samples) past
    four dipoles, heading-rate bias 0.5 deg/s, seeded (seeds 1-5 measured: RMSE after / before
    0.34, 0.17, 0.08, 0.09, 0.14; seed 1 ends in a worse local optimum)."""
    field = planar_room_field()
    d = simulate_planar(
        4, field, size=(2.0, 1.5), loops=3, heading_bias_deg=BIAS_DEG, disp_noise=0.002
    )
    path = tmp_path_factory.mktemp("rec") / "walk.csv"
    write_recording(path, d.t, d.Y, planar=d.U, P_true=d.P, yaw_true=d.psi)
    return path, d


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_slam_solves_a_planar_recording(tmp_path, planar_recording):
    path, d = planar_recording
    out = tmp_path / "out"
    res = _run(
        [
            "slam",
            path,
            "--out",
            out,
            "-q",
            "--set",
            "model.sigma_disp=0.002",
            "--set",
            f"model.sigma_dyaw={np.radians(0.05)}",
            "--set",
            "model.gp.num_basis=120",
        ]
    )
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["success"] is True and r["info"]["recording"] == str(path)
    assert r["info"]["name"] == "walk" and r["info"]["samples"] == d.t.size
    assert r["rmse_after"] <= 0.25 * r["rmse_before"]
    assert r["details"]["heading_rms_deg_after"] < r["details"]["heading_rms_deg_before"]
    assert np.degrees(r["odometry_bias"][0]) == pytest.approx(BIAS_DEG, rel=0.2)  # rad/s
    assert r["iterations"] <= 150
    with (out / "trajectory.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == d.t.size
    assert {"t", "x_odo", "psi_odo", "x_est", "y_est", "psi_est", "x_true", "psi_true"} <= set(
        rows[0]
    )
    np.testing.assert_allclose(float(rows[-1]["x_true"]), d.P[-1, 0], rtol=1e-8)
    for png in ("trajectory.png", "cost.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--set", "model.sigma_dsp=0.1"], "model.sigma_dsp: unknown key"),
        (["--set", "model.bias=drift"], "model.bias"),
        (["--set", "solver.max_iter=0"], "solver.max_iter"),
        (
            [
                "--set",
                "solver.warm_start.strategy=sliding",
                "--set",
                "model.gp.form=tiled",
                "--set",
                "model.gp.kernel=curl_free",
            ],
            "solver.warm_start.strategy: sliding windows need model.gp.form: reduced_rank",
        ),
        (["--set", "solver.warm_start.stage_max_iter=0"], "solver.warm_start.stage_max_iter"),
    ],
)
def test_slam_planar_bad_settings_exit_2(tmp_path, planar_recording, args, needle):
    path, _ = planar_recording
    out = tmp_path / "out"
    res = _run(["slam", path, "--out", out, "-q", *args])
    assert res.exit_code == 2
    assert needle in res.output and res.output.count("\n") == 1
    assert not out.exists()


def test_slam_planar_solver_failure_exit_1(tmp_path, planar_recording):
    path, _ = planar_recording
    out = tmp_path / "out"
    res = _run(["slam", path, "--out", out, "-q", "--set", "model.gp.num_basis=40", *MAX_ITER_2])
    assert res.exit_code == 1
    assert "Maximum_Iterations_Exceeded" in res.output
    assert json.loads((out / "result.json").read_text())["success"] is False


def test_slam_planar_mixed_motion_columns_is_bad_input(tmp_path, planar_recording):
    path, _ = planar_recording
    lines = path.read_text().splitlines()
    bad = tmp_path / "mixed.csv"
    bad.write_text("\n".join([lines[0] + ",dx,dy"] + [row + ",0,0" for row in lines[1:]]) + "\n")
    res = _run(["slam", bad, "--out", tmp_path / "out", "-q"])
    assert res.exit_code == 2
    assert "mixed motion inputs" in res.output and res.output.count("\n") == 1


def test_the_library_slam_takes_a_planar_recording(planar_recording):
    import casmag

    path, _ = planar_recording
    lines = []
    r = casmag.slam(
        path,
        model={"sigma_disp": 0.002, "sigma_dyaw": float(np.radians(0.05)), "num_basis": 120},
        on_warning=lines.append,
    )
    assert r.motion == "planar" and r.success and lines == []
    assert r.rmse_after <= 0.25 * r.rmse_before
    assert r.info["anchor"]["kind"] == "first true position"
    with pytest.raises(casmag.ProblemError) as err:
        casmag.slam(path, model={"gp": {"lengthscale": 0.3, "kernal": "se"}})
    assert "did you mean 'model.gp.kernel'" in str(err.value)


def test_growing_prefixes_on_a_planar_recording(tmp_path):
    """solver.warm_start.strategy=growing (casmag.solver.windowing.grow, as for translational
    recordings): prefixes of 50, 100 and all 186 samples, each from the previous one
    continued by the odometry with its bias removed; the last is the full problem. Measured
    on this walk at 2 deg/s (seeds 1-5, RMSE after / before): batch 0.048, 0.060, 0.045,
    0.052, 0.034; growing 0.083, 0.046, 0.025, 0.052, 0.034."""
    field = planar_room_field()
    d = simulate_planar(3, field, size=(2.0, 1.5), loops=3, heading_bias_deg=2.0, disp_noise=0.002)
    path = tmp_path / "walk.csv"
    write_recording(path, d.t, d.Y, planar=d.U, P_true=d.P, yaw_true=d.psi)
    out = tmp_path / "out"
    sets = [
        "model.sigma_disp=0.002",
        f"model.sigma_dyaw={np.radians(0.05)}",
        "model.gp.num_basis=120",
        "solver.warm_start.strategy=growing",
        "solver.warm_start.first_samples=50",
        "solver.warm_start.growth=2",
        "solver.warm_start.evidence=false",  # the growing strategy's stages alone
    ]
    res = _run(["slam", path, "--out", out, "-q", *[a for k in sets for a in ("--set", k)]])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["info"]["warm_start"] == "growing"
    stages = r["stages"]
    assert {st["name"] for st in stages} == {"prefix"}
    assert [st["samples"] for st in stages] == [50, 100, d.t.size]
    assert [st["kept"] for st in stages] == [False, False, True]
    assert all(st["iterations"] <= 25 for st in stages[:-1])  # stage_max_iter
    assert r["success"] and r["rmse_after"] <= 0.1 * r["rmse_before"]
    # The magnetometer noise is estimated from the data (simulated: 0.01).
    assert r["hyperparameters"]["sigma_m"] == pytest.approx(0.01, rel=0.2)
    assert r["info"]["sigma_lin"]["source"] == "data"


@pytest.mark.parametrize(("loops", "seed", "flagged"), [(3, 1, True), (2, 2, False)])
def test_a_worse_local_optimum_is_flagged_by_the_solve_from_the_truth(loops, seed, flagged):
    """With truth, an estimate above TRUTH_START_RATIO of the dead reckoning's error is
    solved again from the truth. Three loops, seed 1 (RMSE ratio 0.34): from the truth the
    MAP cost is 257.7 against 266.2 (RMSE 0.016 m): ``wrong_basin``, not trusted. Two loops,
    seed 2 (ratio 0.54): the truth start finds no lower cost, so the model's optimum itself
    is that far (one revisit is a weak loop closure) and no flag is raised. Both without
    the start of the field's evidence, which on three loops, seed 1, reaches the truth's
    basin (checked last)."""
    from casmag.problem.imu import load_planar_options
    from casmag.solver.planar import solve_planar
    from casmag.solver.staged import TRUTH_START_RATIO

    d = simulate_planar(
        seed, planar_room_field(), size=(2.0, 1.5), loops=loops, heading_bias_deg=BIAS_DEG,
        disp_noise=0.002,
    )  # fmt: skip
    sets = ["model.sigma_disp=0.002", f"model.sigma_dyaw={np.radians(0.05)}"]
    sets = [*sets, "model.gp.num_basis=120"]
    opts = load_planar_options(None, [*sets, "solver.warm_start.evidence=false"])
    r = solve_planar(*d.U.T, d.Y, opts, truth={"P": d.P, "psi": d.psi}, t=d.t)
    assert r.success and r.rmse_after > TRUTH_START_RATIO * r.rmse_before
    assert [f["name"] for f in r.flags] == (["wrong_basin"] if flagged else [])
    assert r.trusted is not flagged
    if flagged:
        ev = r.flags[0]["evidence"]
        assert ev["map_cost_from_truth"] < ev["map_cost"] - 1.0
        assert ev["rmse_from_truth"] < r.rmse_after
        assert r.verdict["reasons"][0].startswith("wrong_basin: RMSE 0.34 of the dead")
        # The defaults add the heading-rate start of the field's evidence: the truth's basin.
        r = solve_planar(
            *d.U.T, d.Y, load_planar_options(None, sets), truth={"P": d.P, "psi": d.psi}, t=d.t
        )
        assert r.info["bias_scan"] is not None and r.flags == [] and r.trusted
        assert r.rmse_after < TRUTH_START_RATIO * r.rmse_before


def test_slam_method_ekf_on_a_planar_recording(tmp_path, planar_recording):
    """The filter baseline with the planar model: heading and heading-rate bias in the
    state, the same map box and settings as the MAP; a planar result with headings."""
    path, d = planar_recording
    out = tmp_path / "out"
    res = _run(
        [
            "slam", path, "--method", "ekf", "--out", out, "-q",
            "--set", "model.sigma_disp=0.002",
            "--set", f"model.sigma_dyaw={np.radians(0.05)}",
            "--set", "model.gp.num_basis=120",
        ]
    )  # fmt: skip
    assert res.exit_code in (0, 3), res.output
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "Filter_Completed" and r["motion"] == "planar"
    assert r["info"]["filter"]["state_size"] == 4 + 3 * 120 + 3
    assert r["details"]["heading_rms_deg_after"] is not None
    with open(out / "trajectory.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == d.t.size
