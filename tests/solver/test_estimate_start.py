"""Where the joint MAP starts estimated hyperparameters (model.estimate_start): the windowed
marginal likelihood at the dead reckoning, or the assumed values."""

from pathlib import Path

import numpy as np
import pytest

import casmag
from casmag.data.simulate import draw_field, simulate_problem
from casmag.errors import ProblemError
from casmag.experiments.sweep import _fingerprint
from casmag.gp.hyper import estimate_conditional, negative_log_marginal, select_windows
from casmag.model.translational import Structure, parameters_and_guess
from casmag.problem.spec import load_problem
from casmag.solver.translational import estimate_start

ROOT = Path(__file__).resolve().parents[2]
BASE = ROOT / "problems" / "paper" / "base.yaml"


def _problem(*overrides):
    return load_problem(BASE, ["seed=1", *overrides])


# --------------------------------------------------------------------------- the option
def test_option_defaults_to_both_and_validates():
    assert _problem().spec.model.estimate_start == "both"
    for ok in ("assumed", "marginal_likelihood", "both"):
        assert _problem(f"model.estimate_start={ok}").spec.model.estimate_start == ok
    for bad in ("model.estimate_start=ml", "model.estimate_start=1", "model.estimate_start=null"):
        with pytest.raises(ProblemError) as info:
            _problem(bad)
        assert info.value.field == "model.estimate_start"


def test_option_changes_neither_the_build_nor_the_default_fingerprint():
    est = ("model.estimate=[lengthscale]", "model.gp.lengthscale=0.005")
    ml, assumed = _problem(*est), _problem(*est, "model.estimate_start=assumed")
    data = simulate_problem(ml)
    assert Structure.of(ml, data) == Structure.of(assumed, data)  # one cached build
    explicit = _problem(*est, "model.estimate_start=both")
    assert _fingerprint(ml) == _fingerprint(explicit)  # saved sweeps stay resumable
    assert _fingerprint(ml) != _fingerprint(assumed)


# --------------------------------------------------------------------------- the estimate
def _spiral_data(seed=1, n=81):
    prob = _problem(f"seed={seed}", f"simulation.trajectory.samples={n}")
    return simulate_problem(prob)


def test_conditional_estimate_keeps_fixed_values_and_is_start_independent():
    """Only the free hyperparameter moves; from 0.005 and 0.15 m the search reaches the same
    maximum (one unbounded line search from 0.15 m overshot into the flat l -> 0 region)."""
    data = _spiral_data()
    X, Y = data.dead_reckoning(), data.Y
    fixed = {"sigma_f": 0.1, "sigma_m": 5e-4}
    a = estimate_conditional(X, Y, "se", {**fixed, "lengthscale": 0.005}, ["lengthscale"])
    b = estimate_conditional(X, Y, "se", {**fixed, "lengthscale": 0.15}, ["lengthscale"])
    assert a.converged and b.converged
    assert a.values["sigma_f"] == 0.1 and a.values["sigma_m"] == 5e-4
    assert a.values["lengthscale"] == pytest.approx(b.values["lengthscale"], rel=1e-3)
    wins = select_windows(X, Y, 150, 8)
    for ell in (0.005, 0.15, 0.8 * a.values["lengthscale"], 1.25 * a.values["lengthscale"]):
        f = negative_log_marginal(np.log([0.1, ell, 5e-4]), wins, "se", 0.0)
        assert a.neg_log_marginal <= f


def test_conditional_estimate_recovers_a_lengthscale_without_drift():
    rng = np.random.default_rng(4)
    t = np.arange(300) * 0.1
    X = np.column_stack([1.5 * np.sin(2 * np.pi * t / 23.0), 1.5 * np.sin(2 * np.pi * t / 17.0)])
    Y = draw_field(X, "se", 1.0, 0.3, rng) + 0.05 * rng.standard_normal((300, 3))
    est = estimate_conditional(
        X, Y, "se", {"sigma_f": 1.0, "lengthscale": 0.02, "sigma_m": 0.05}, ["lengthscale"]
    )
    assert est.values["lengthscale"] == pytest.approx(0.3, rel=0.2)


def test_conditional_estimate_rejects_bad_input():
    data = _spiral_data(n=20)
    X, Y = data.dead_reckoning(), data.Y
    values = {"sigma_f": 0.1, "lengthscale": 0.1, "sigma_m": 5e-4}
    for free in ([], ["noise"], ["sigma_f", "sigma_f"]):
        with pytest.raises(ValueError):
            estimate_conditional(X, Y, "se", values, free)


# --------------------------------------------------------------------------- the MAP's start
@pytest.mark.parametrize("method", ["marginal_likelihood", "both", "assumed"])
def test_initial_value_of_the_joint_map(method):
    prob = _problem(
        "model.gp.lengthscale=0.005",
        "model.estimate=[lengthscale]",
        f"model.estimate_start={method}",
    )
    data = simulate_problem(prob)
    s = Structure.of(prob, data)
    start = estimate_start(prob, data, s)
    assert start["method"] == method and start["assumed"] == {"lengthscale": 0.005}
    _, x0 = parameters_and_guess(prob, data, s, hyper_start=start["values"])
    if method == "assumed":
        assert start["values"] == {"lengthscale": 0.005}
        assert float(x0["log_lengthscale"]) == pytest.approx(np.log(0.005))
        return
    ml = estimate_conditional(
        data.dead_reckoning(),
        data.Y,
        "se",
        {"sigma_f": 0.1, "lengthscale": 0.005, "sigma_m": 5e-4},
        ["lengthscale"],
    )
    assert start["values"]["lengthscale"] == pytest.approx(ml.values["lengthscale"])
    assert float(x0["log_lengthscale"]) == pytest.approx(np.log(ml.values["lengthscale"]))
    assert not 0.004 < ml.values["lengthscale"] < 0.006  # it moved off the assumed value
    assert start["marginal_likelihood"]["converged"]


def test_no_start_record_without_estimated_field_hyperparameters():
    prob = _problem()
    data = simulate_problem(prob)
    assert estimate_start(prob, data, Structure.of(prob, data)) is None


def _small(method):
    return load_problem(
        {
            "seed": 3,
            "simulation": {"trajectory": {"samples": 30}},
            "model": {
                "gp": {"sigma_f": 0.3},
                "estimate": ["sigma_f"],
                "estimate_start": method,
            },
        }
    )


def test_start_is_recorded_in_the_result():
    """A small solve (30 samples): info["estimate_start"] and hyperparameters_initial hold
    the marginal-likelihood start, not the assumed value."""
    prob = _small("marginal_likelihood")
    r = casmag.solve(prob)
    assert r.success, r.status
    start = r.info["estimate_start"]
    assert start["method"] == "marginal_likelihood"
    assert start["assumed"] == {"sigma_f": 0.3}
    assert r.hyperparameters_initial["sigma_f"] == start["values"]["sigma_f"] != 0.3
    assert r.hyperparameters_initial["lengthscale"] == prob.assumed_lengthscale
    assert "solves" not in start
    assert "estimate_start" in r.to_dict()["info"]


def test_both_starts_keep_the_lower_cost():
    r = casmag.solve(_small("both"))
    assert r.success, r.status
    start = r.info["estimate_start"]
    solves = start["solves"]
    assert set(solves) == {"marginal_likelihood", "assumed"}
    assert solves["assumed"]["start"] == {"sigma_f": 0.3}
    chosen = start["chosen"]
    assert solves[chosen]["objective"] == min(v["objective"] for v in solves.values())
    assert r.iterations == solves[chosen]["iterations"]
    assert r.hyperparameters_initial["sigma_f"] == solves[chosen]["start"]["sigma_f"]
    total = sum(v["solve_seconds"] for v in solves.values())
    assert r.solve_seconds == pytest.approx(total)
    fixed = casmag.solve(load_problem({"seed": 3, "simulation": {"trajectory": {"samples": 12}}}))
    assert "estimate_start" not in fixed.info


def test_marginal_likelihood_start_escapes_the_local_optimum_of_a_small_lengthscale():
    """Base case cut to 20 samples, seed 6, l assumed 0.005 m (true 0.1 m): started there the
    joint MAP stops at l ~ 0.016 m (measured: cost -111.4, RMSE 0.45 m); started from the
    marginal likelihood (l ~ 0.02-0.03 m) it reaches l ~ 0.10 m (cost -236.2, RMSE 2.8 mm),
    and ``both`` keeps that one."""
    common = (
        "seed=6",
        "simulation.trajectory.samples=20",
        "model.gp.lengthscale=0.005",
        "model.estimate=[lengthscale]",
        "solver.uncertainty=false",
    )
    stuck = casmag.solve(_problem(*common, "model.estimate_start=assumed"))
    best = casmag.solve(_problem(*common, "model.estimate_start=both"))
    assert stuck.success and best.success
    assert stuck.hyperparameters["lengthscale"] < 0.05
    assert best.info["estimate_start"]["chosen"] == "marginal_likelihood"
    assert 0.08 < best.hyperparameters["lengthscale"] < 0.13
    assert best.rmse_after < 0.01 < stuck.rmse_after
    solves = best.info["estimate_start"]["solves"]
    assert solves["assumed"]["objective"] == pytest.approx(stuck.cost_per_iteration[-1])
    assert solves["marginal_likelihood"]["objective"] < solves["assumed"]["objective"] - 50
