"""IMU recordings located against a saved map (casmag.solver.imu.located_stages through
``casmag slam REC --map MAP``): the desk rectangle recorded twice over one dipole, with
other sensor noise, the first mapped, the second located, the map updated or held."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import tiny_imu

from casmag.cli.main import main
from casmag.data.imusim import simulate_imu
from casmag.data.recording import write_recording
from casmag.errors import DataError
from casmag.gp.savedmap import MAP_FILE, load_map
from casmag.problem.imu import load_imu_problem
from casmag.result import Result
from casmag.solver.imu import _truth_start_cost, solve_imu_stages
from casmag.solver.recslam import slam
from casmag.solver.staged import PriorMap

#: The mapping run's field model, given (the estimate takes a minute on this desk).
GIVEN = ["model.gp.sigma_f=0.3", "model.gp.lengthscale=0.2", "model.gp.num_basis=200"]


def _set(items):
    return [a for item in items for a in ("--set", item)]


def _desk(seed: int, **gp) -> dict:
    """The tiny desk rectangle traced twice, constant biases."""
    d = tiny_imu(imu={"bias": "constant"}, **({"gp": gp} if gp else {}))
    d["seed"] = seed
    d["simulation"]["scenario"]["loops"] = 2
    return d


@pytest.fixture(scope="module")
def desk(tmp_path_factory):
    """Two recordings of the tiny desk rectangle traced twice (seeds 11 and 12: other IMU and
    magnetometer noise, the same path and field), the first mapped by casmag slam into A."""
    folder = tmp_path_factory.mktemp("desk")
    for name, seed in (("first", 11), ("later", 12)):
        data = simulate_imu(load_imu_problem(_desk(seed)))
        tr = data.truth
        write_recording(folder / f"{name}.csv", tr.t, data.Y, imu=np.hstack([data.dq, data.dv]),
                        P_true=tr.P, q_true=tr.Q)  # fmt: skip
    res = CliRunner().invoke(
        main, ["slam", str(folder / "first.csv"), "--out", str(folder / "A"), "-q", *_set(GIVEN)]
    )
    assert res.exit_code == 0, res.output
    return folder


def _located(desk: Path, out: str, *args: str) -> Result:
    res = CliRunner().invoke(
        main,
        ["slam", str(desk / "later.csv"), "--map", str(desk / "A"), "--out", str(desk / out),
         "-q", *args],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return Result.load(desk / out)


def test_an_imu_recording_is_located_against_its_saved_map_and_updates_it(desk):
    saved = load_map(desk / "A")
    located = _located(desk, "B")
    assert located.success and located.motion == "imu"
    loc = located.info["localisation"]
    assert loc["map"] == str(desk / "A") and loc["covered"] > 0.9 and loc["updated"] is True
    # the map's own field model, none estimated; its posterior the prior of the update
    hyper = located.hyperparameters
    assert (hyper["sigma_f"], hyper["lengthscale"]) == (saved.sigma_f, saved.lengthscale)
    assert located.details["hyperparameters_source"] == "the saved map"
    assert "map_prior" in located.cost_blocks and "gp_prior" not in located.cost_blocks
    schedule = located.details["schedules"][0]
    assert schedule["solves"] == ["held, sigma_m x4", "held, sigma_m x1", "updated"]
    assert located.rmse_after < 0.25 * located.rmse_before
    # the updated map: the saved map's box and frame, knowing more along the new path
    updated = load_map(desk / "B")
    assert located.info["map"]["updated_from"] == str(desk / "A")
    assert updated.frame == saved.frame and updated.basis_key == saved.basis_key
    P = located.arrays["P_estimate"]
    assert updated.std(P).mean() < 0.9 * saved.std(P).mean()


def test_an_imu_recording_is_located_against_a_held_map(desk):
    """--hold-map: every solve holds the map at its saved mean, the last with sigma_m
    widened by the map's standard deviation along its start; no map written."""
    located = _located(desk, "H", "--hold-map")
    assert located.success and not (desk / "H" / MAP_FILE).exists()
    assert located.info["map"]["saved"] is False and "held" in located.info["map"]["reason"]
    loc = located.info["localisation"]
    assert loc["updated"] is False and loc["map_std_on_path"] > 0.0
    own = located.hyperparameters["sigma_m"]  # the recording's own, from its rest
    assert loc["sigma_m_used"] == pytest.approx(np.hypot(own, loc["map_std_on_path"]))
    assert "map_prior" not in located.cost_blocks
    assert located.details["schedules"][0]["solves"] == ["held, sigma_m x4", "held, sigma_m x1"]
    assert located.rmse_after < 0.25 * located.rmse_before


def test_a_map_that_cannot_locate_an_imu_recording_is_refused_in_one_line(desk, tmp_path):
    saved = load_map(desk / "A")
    flat = dataclasses.replace(saved, position_dim=2).save(tmp_path / "flat")
    with pytest.raises(DataError, match="a 2-D map cannot locate an IMU recording"):
        slam(desk / "later.csv", map_file=flat)
    for args, needle in (
        (["--set", "model.gp.form=exact"], "model.gp.form exact: an IMU recording is located"),
        (["--method", "ekf"], "an IMU recording is solved by the MAP estimate"),
    ):
        res = CliRunner().invoke(
            main,
            ["slam", str(desk / "later.csv"), "--map", str(desk / "A"), "--out",
             str(tmp_path / "o"), "-q", *args],
        )  # fmt: skip
        assert res.exit_code == 2 and needle in res.output
        assert len(res.output.strip().splitlines()) == 1
        assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("held", [False, True], ids=["updated", "held"])
def test_the_truth_start_of_a_located_recording_solves_the_same_problem(desk, held):
    """The wrong-basin check's solve from the truth (simulated data: true velocities and
    biases) is the located problem itself, the map updated or held as the estimate's last
    solve: from the truth it reaches the estimate's MAP cost (one optimum here), which
    the GP prior in place of the saved posterior would not."""
    saved = load_map(desk / "A")
    problem = load_imu_problem(
        _desk(12, sigma_f=saved.sigma_f, lengthscale=saved.lengthscale, kernel=saved.kernel)
    )
    data = simulate_imu(problem)
    res = solve_imu_stages(problem, data, prior_map=PriorMap.of(saved, held=held))
    assert res.slam.solution.success and res.prior_map is not None
    assert ("map_prior" in res.slam.solution.blocks_after) is not held
    cost, status = _truth_start_cost(problem, data, res.slam, res)
    assert status == "Solve_Succeeded"
    assert cost == pytest.approx(res.slam.solution.objective, abs=1.0)
