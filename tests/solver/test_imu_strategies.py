"""The warm-start strategies of casmag.solver.staged run with the IMU model (ImuStaged)."""

import numpy as np
import pytest
from small_problems import imu_noise_free, tiny_imu

from casmag.errors import ProblemError
from casmag.problem.imu import (
    IMU_SOLVER_KEYS,
    load_imu_problem,
    load_planar_options,
    refuse_unused_solver_keys,
)
from casmag.problem.spec import load_problem
from casmag.solver.imu import IMU_NO_COVARIANCE, solve_imu


def test_auto_is_each_models_own_default():
    """``auto`` is the IMU model's default (also when its file gives a solver section
    without a strategy), and resolves to ``none`` for the translational model and to the
    solver defaults' growing prefixes (with the keys given) for the planar model."""
    assert load_imu_problem(tiny_imu()).spec.solver.warm_start.strategy == "auto"
    no_solver = {k: v for k, v in tiny_imu().items() if k != "solver"}
    assert load_imu_problem(no_solver).spec.solver.warm_start.strategy == "auto"
    given = load_imu_problem(tiny_imu(), ["solver.warm_start.strategy=none"])
    assert given.spec.solver.warm_start.strategy == "none"
    base = load_problem({"seed": 1}, ["solver.warm_start.strategy=auto"])
    assert base.spec.solver.warm_start.strategy == "none"
    planar = load_planar_options(
        None, ["solver.warm_start.strategy=auto", "solver.warm_start.growth=3"]
    ).solver.warm_start
    assert (planar.strategy, planar.first_samples, planar.growth) == ("growing", 150, 3.0)


@pytest.mark.parametrize(
    ("overrides", "key", "reason"),
    [
        (
            ["solver.warm_start.strategy=sliding", "model.gp.form=exact"],
            "solver.warm_start.strategy",
            "reduced-rank map",
        ),
        (
            ["solver.warm_start.strategy=sliding", "model.starts=3"],
            "model.starts",
            "IMU-only adjustment alone",
        ),
        (["model.starts=3"], "model.starts", "auto (the schedule ladder) runs once"),
        (["model.starts=2", "solver.warm_start.strategy=none"], "model.starts", "must be odd"),
    ],
)
def test_what_the_imu_model_cannot_run_is_refused_in_one_line(overrides, key, reason):
    with pytest.raises(ProblemError) as err:
        load_imu_problem(tiny_imu(), overrides)
    msg = str(err.value)
    assert key in msg and reason in msg and "\n" not in msg


def test_the_imu_command_takes_its_warm_start_keys_and_refuses_the_covariance():
    refuse_unused_solver_keys(
        ["solver.warm_start.strategy=growing", "solver.warm_start.first_samples=20"],
        "casmag imu",
        IMU_SOLVER_KEYS,
    )
    refuse_unused_solver_keys(["solver.warm_start.window=30"], "casmag imu", IMU_SOLVER_KEYS)
    with pytest.raises(ProblemError, match=r"solver\.uncertainty"):
        refuse_unused_solver_keys(["solver.uncertainty=false"], "casmag imu", IMU_SOLVER_KEYS)


def _noise_free_rectangle(strategy: str) -> dict:
    """The noise-free desk rectangle traced twice (constant biases, the weak zero-position
    update, 400 basis functions, given hyperparameters) with ``solver.warm_start.strategy``;
    growing prefixes from 10 keyframes, doubling."""
    data = imu_noise_free(tiny_imu(gp={"sigma_f": 0.3, "lengthscale": 0.2, "num_basis": 400}))
    data["simulation"]["scenario"]["loops"] = 2
    data["model"]["imu"]["bias"] = "constant"
    data["model"]["zero_position"] = {"sigma": 1.0}
    data["solver"]["warm_start"] = {"strategy": strategy, "first_samples": 10, "growth": 2.0}
    if strategy == "none":  # and three starts: the IMU-only adjustment and it turned +-10 deg
        data["model"]["starts"] = 3
    return data


@pytest.mark.parametrize("strategy", ["none", "growing", "coarse-to-fine", "sliding"])
def test_each_strategy_returns_the_truth_on_a_noise_free_rectangle(strategy):
    """Each strategy from the IMU-only adjustment ends at the truth (the noise-free
    optimum), the strategy's solves recorded in its one pass, the last the full problem at
    the assumed lengthscale, and the schedule ladder not run."""
    r = solve_imu(_noise_free_rectangle(strategy))
    assert r.success, r.status
    a = r.arrays
    assert np.abs(a["P_estimate"] - a["P_true"]).max() < 1e-3
    assert r.rmse_after < 0.05 * r.rmse_before
    assert r.info["warm_start"] == strategy
    assert r.uncertainty == {"error": IMU_NO_COVARIANCE}  # solver.uncertainty is on
    (record,) = r.details["schedules"]
    assert record["schedule"] == strategy and record["kept"]
    if strategy == "none":
        starts = record["starts"]
        assert len(starts) == 3 and starts[0]["bias"] == 0.0
        assert starts[1]["bias"] == pytest.approx(-starts[2]["bias"]) != 0.0
        kept = [s for s in starts if s["kept"]]
        assert len(kept) == 1 and kept[0]["cost"] == min(s["cost"] for s in starts)
        assert kept[0]["cost"] == pytest.approx(record["cost"])
    else:
        assert "starts" not in record
    (gp_slam,) = r.stages_named("gp_slam")
    solves = gp_slam["grow"]
    K = r.info["keyframes"]
    assert solves[-1]["keyframes"] == K and solves[-1]["lengthscale"] == 0.2
    assert solves[-1]["status"] == r.status
    kinds = [s["kind"] for s in solves]
    if strategy == "none":
        assert kinds == ["batch"]
    elif strategy == "growing":
        assert kinds == ["prefix"] * len(solves)
        assert [s["keyframes"] for s in solves[:2]] == [10, 20]
    elif strategy == "sliding":  # windows of auto length
        windows = solves[:-1]
        assert kinds == ["window"] * len(windows) + ["batch"] and len(windows) >= 3
        firsts = [s["first"] for s in windows]
        assert firsts[0] == 0 and firsts[-1] + windows[-1]["keyframes"] == K
        assert all(s["success"] for s in windows)
    else:
        ells = [s["lengthscale"] for s in solves]
        assert kinds == ["lengthscale", "lengthscale", "batch"]
        np.testing.assert_allclose(ells, [0.6, 0.6 / 3**0.5, 0.2])
