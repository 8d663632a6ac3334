"""The translational model's sliding windows (casmag.solver.staged.slide over
casmag.solver.translational.TranslationalStaged), the coarse-to-fine lengthscale schedule,
and their problem-file settings."""

import itertools
from pathlib import Path

import numpy as np
import pytest

import casmag
from casmag.data.simulate import simulate_problem
from casmag.errors import ProblemError
from casmag.model.builder import BUILDS, cached_slam
from casmag.result.metrics import rmse_and_max
from casmag.solver import staged, windowing
from casmag.solver.translational import TranslationalStaged

ROOT = Path(__file__).resolve().parents[2]
BASE = ROOT / "problems/paper/base.yaml"
AUTO_SPIRAL = 12
"""The automatic window on the Table 5 spiral (casmag.solver.staged.window_length)."""


def _spiral(bias=0.012, noise=1.0e-3, seed=2, *extra):
    """The paper's spiral with l = 0.4 m (Table 5) and a reduced-rank map; a 12 mm per-step
    bias drifts the dead reckoning by 3.4 lengthscales."""
    return casmag.load_problem(
        BASE,
        [
            f"seed={seed}",
            "simulation.field.lengthscale=0.4",
            f"simulation.odometry.bias=[{bias}, {bias}]",
            f"simulation.odometry.noise={noise}",
            "model.gp.form=reduced_rank",
            "solver.warm_start.window=10",
            "solver.warm_start.overlap=5",
            *extra,
        ],
    )


def test_window_starts_cover_every_sample():
    for n, w, o in [(81, 10, 5), (81, 20, 10), (100, 7, 1), (10, 20, 5), (50, 50, 10)]:
        starts = windowing.window_starts(n, w, o)
        assert starts[0] == 0 and starts[-1] + min(w, n) == n
        assert all(b - a <= w - o for a, b in itertools.pairwise(starts))
        assert all(b > a for a, b in itertools.pairwise(starts))
    assert windowing.window_starts(81, 10, 5) == [
        0,
        5,
        10,
        15,
        20,
        25,
        30,
        35,
        40,
        45,
        50,
        55,
        60,
        65,
        70,
        71,
    ]


@pytest.fixture(scope="module")
def drifting():
    """The drifting spiral (seed 2), and its windows alone run from an empty NLP cache
    with the number of window NLPs built meanwhile."""
    problem = _spiral()
    data = simulate_problem(problem)
    cached_slam.cache_clear()
    before = BUILDS["translational_window"]
    windows = staged.slide(TranslationalStaged(problem, data), problem.spec.solver.warm_start)
    return problem, data, windows, BUILDS["translational_window"] - before


def _iterations(windows):
    return sum(st.solved.sol.iterations for st in windows.stages)


def test_one_window_nlp_serves_every_window_and_the_map_is_counted_once(drifting):
    problem, data, windows, builds = drifting
    assert windows.completed, [st.status for st in windows.stages]
    assert len(windows.stages) == 16
    assert builds == 1
    # The carried prior is the GP prior plus every sample once, at its committed position.
    s = windows.stages[0].solved.structure
    J, _ = s.design(windows.states["P"], data.Y)
    prior = s.prior_precision(problem.assumed_sigma_f, problem.assumed_lengthscale, None)
    expected = prior + J.T @ J / problem.assumed_sigma_m**2
    Lam = windows.prior.Lam
    np.testing.assert_allclose(Lam, expected, rtol=1e-9, atol=1e-9 * expected.max())
    # The carried map predicts the field at the true positions (field sigma_f = 0.1).
    m = s.hilbert_basis().phi(data.P_true) @ windows.prior.mean
    assert np.sqrt(np.mean((m - data.M_true) ** 2)) < 0.01


def test_the_windows_alone_beat_dead_reckoning(drifting):
    _, data, windows, _ = drifting
    before, _ = rmse_and_max(data.dead_reckoning(), data.P_true)
    after, _ = rmse_and_max(windows.states["P"], data.P_true)
    assert before > 0.7  # 3.4 lengthscales of final drift
    assert after < 0.05 * before and after < 0.03, (before, after)
    # the total the windows estimated, the last window's increment included
    np.testing.assert_allclose(windows.states["bias"].ravel(), data.bias_true, rtol=0.1)
    assert _iterations(windows) < 200


def test_sliding_start_reaches_the_basin_from_a_drifting_start(drifting):
    problem, data, _, _ = drifting
    slide = casmag.solve(problem.with_overrides(["solver.warm_start.strategy=sliding"]), data)
    assert slide.success, slide.status
    assert slide.rmse_before > 0.7 and slide.rmse_after < 0.01, slide.rmse_after
    stages = slide.stages
    assert [s["name"] for s in stages] == ["window"] * 16 + ["batch"]
    assert stages[-1]["iterations"] == slide.iterations
    assert sum(s["iterations"] for s in stages) < 200
    np.testing.assert_allclose(slide.odometry_bias, data.bias_true, atol=2e-4)


def test_a_window_that_leaves_the_map_box_ends_the_windows(drifting):
    problem, data, _, _ = drifting
    # A map box far from the path: the first window's positions lie outside it.
    model = TranslationalStaged(problem, data, window_box=data.dead_reckoning() + 50.0)
    windows = staged.slide(model, problem.spec.solver.warm_start)
    assert not windows.completed and windows.states is None  # the batch takes its own start
    assert [st.status for st in windows.stages] == [staged.LEFT_BOX]
    assert windows.stages[0].solved.sol.status == "Solve_Succeeded"  # IPOPT's own


def test_coarse_to_fine_schedule_and_solve():
    np.testing.assert_allclose(
        windowing.lengthscale_schedule(0.4, 3.0, 3), [1.2, 0.4 * 3**0.5, 0.4]
    )
    problem = _spiral(0.012, 1.0e-4, 1, "solver.warm_start.strategy=coarse-to-fine")
    data = simulate_problem(problem)
    res = casmag.solve(problem, data)
    assert res.success, res.status
    assert res.rmse_after < 0.01, res.rmse_after
    stages = res.stages
    assert [s["name"] for s in stages] == ["lengthscale", "lengthscale", "batch"]
    np.testing.assert_allclose([s["lengthscale"] for s in stages], [1.2, 0.4 * 3**0.5, 0.4])
    assert res.hyperparameters["lengthscale"] == pytest.approx(0.4)


def test_warm_start_settings_are_validated():
    ws = _spiral(0.003, 1e-4, 1, "solver.warm_start.strategy=sliding").spec.solver.warm_start
    assert (ws.window_samples, ws.overlap_samples) == (10, 5)
    timed = casmag.load_problem(
        BASE,
        [
            "solver.warm_start.unit=seconds",
            "solver.warm_start.sample_period=0.1",
            "solver.warm_start.window=2.0",
            "solver.warm_start.overlap=0.5",
        ],
    ).spec.solver.warm_start
    assert (timed.window_samples, timed.overlap_samples) == (20, 5)
    # Defaults: window and overlap auto, resolved against the data (staged.window_length).
    default = casmag.load_problem(BASE, []).spec.solver.warm_start
    assert (default.window, default.overlap, default.window_bias_prior) == (
        "auto",
        "auto",
        "laplace",
    )
    assert (default.window_samples, default.overlap_samples) == (None, None)
    half = casmag.load_problem(BASE, ["solver.warm_start.window=14"]).spec.solver.warm_start
    assert (half.window_samples, half.overlap_samples) == (14, 7)
    bad = {
        "solver.warm_start.overlap=0": "overlap",
        "solver.warm_start.window=20;solver.warm_start.overlap=20": "overlap",
        "solver.warm_start.window=auto;solver.warm_start.overlap=0.5": "whole numbers",
        "solver.warm_start.window_bias_prior=fixed": "window_bias_prior",
        "solver.warm_start.window=2": "at least 3 samples",
        "solver.warm_start.window=12.5": "whole numbers",
        "solver.warm_start.unit=seconds": "sample_period",
        "solver.warm_start.sample_period=0.1": "only used with unit: seconds",
        "solver.warm_start.strategy=windows": "strategy",
        "solver.warm_start.lengthscale_start=1.0": "lengthscale_start",
        "solver.warm_start.lengthscale_stages=1": "lengthscale_stages",
        "solver.warm_start.window_size=5": "unknown key",
    }
    for override, words in bad.items():
        with pytest.raises(ProblemError) as err:
            casmag.load_problem(BASE, override.split(";"))
        message = str(err.value)
        assert words in message and "\n" not in message, message
        assert "base.yaml" in message


def test_the_bias_prior_is_a_parameter_and_accumulates(drifting):
    _, _, windows, builds = drifting
    assert builds == 1  # every window, with its own bias prior, re-solves one NLP
    entries = windows.stages[0].solved.nlp.p_layout.entries
    assert entries["bias_mean"].shape == (1, 2)
    assert entries["bias_precision"].shape == (2, 2)
    sigma = np.array([st.handed["bias"] for st in windows.stages])
    assert sigma.shape == (16, 2) and np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    # Each window's posterior contains the previous one's: the bias is known better at the
    # end than after the first window.
    assert np.all(sigma[-1] < 0.5 * sigma[0]), sigma


def test_auto_window_travels_the_documented_multiple_of_the_lengthscale():
    # The spiral steps 5 cm: l = 0.4 m is 8 steps, k = window_lengthscales of them plus one.
    problem = _spiral(0.003, 1.0e-4, 1, "solver.warm_start.window=auto")
    problem = problem.with_overrides(["solver.warm_start.overlap=auto"])
    k = problem.spec.solver.warm_start.window_lengthscales
    n = round(k * 0.4 / 0.05) + 1
    assert windowing.AUTO_WINDOW[0] <= n <= windowing.AUTO_WINDOW[1]
    assert _window(problem) == (n, n // 2) == (AUTO_SPIRAL, AUTO_SPIRAL // 2)
    # base.yaml: l = 0.1 m is 2 steps, below the floor of the clamp.
    assert _window(casmag.load_problem(BASE, []))[0] == windowing.AUTO_WINDOW[0]
    # A short recording: the window is the recording.
    assert _window(casmag.load_problem(BASE, ["simulation.trajectory.samples=7"])) == (7, 3)


def _window(problem):
    model = TranslationalStaged(problem, simulate_problem(problem))
    return staged.window_length(model, problem.spec.solver.warm_start)


def test_without_the_bias_prior_short_windows_run_away():
    """base.yaml (l = 0.1 m, bias 1 mm/step) with 10-sample windows: without the prior each
    window re-estimates the bias increment from its own samples and the total wanders off;
    with it the estimate settles. The first 40 samples (8 windows) show it."""
    problem = casmag.load_problem(
        BASE,
        [
            "model.gp.form=reduced_rank",
            "solver.warm_start.window=10",
            "solver.warm_start.overlap=5",
        ],
    )
    data = simulate_problem(problem).prefix(40)
    err = {}
    for prior in ("none", "laplace"):
        p = problem.with_overrides([f"solver.warm_start.window_bias_prior={prior}"])
        windows = staged.slide(TranslationalStaged(p, data), p.spec.solver.warm_start)
        assert windows.completed
        err[prior] = np.abs(windows.states["bias"].ravel() - data.bias_true).max()
    assert err["none"] > 1.0e-3 and err["laplace"] < 2.5e-4, err


@pytest.mark.parametrize(
    ("statuses", "solved"),
    [
        (["Solve_Succeeded"] * 3, 3),
        (["Maximum_Iterations_Exceeded", "Solve_Succeeded", "Solve_Succeeded"], 3),
        (["Solve_Succeeded", "Restoration_Failed", "Solve_Succeeded"], 2),
        (["Solve_Succeeded", "Solve_Succeeded", "Maximum_Iterations_Exceeded"], 3),
    ],
)
def test_grow_goes_on_past_an_early_iteration_limit_and_stops_at_any_other_failure(
    statuses, solved
):
    """casmag.solver.windowing.grow, the loop every motion model's growing prefixes run: each stage
    gets the previous one's state; an earlier stage at the iteration limit still starts the
    next, any other failure ends the growth."""
    from types import SimpleNamespace

    from casmag.solver.windowing import grow

    seen = []

    def stage(k, prev, last):
        seen.append((k, prev, last))
        status = statuses[len(seen) - 1]
        return SimpleNamespace(status=status, success=status == "Solve_Succeeded"), k

    out = grow([10, 20, 40], stage)
    assert [k for k, _, _ in out] == [10, 20, 40][:solved]
    assert seen == [(10, None, False), (20, 10, False), (40, 20, True)][:solved]


def test_lowest_cost_keeps_the_cheapest_successful_start():
    """casmag.nlp.lowest_cost, the choice among starts of every model: a failed solve is
    never kept however low its cost; none succeeded gives None; costs may be given."""
    from types import SimpleNamespace

    from casmag.nlp import lowest_cost

    def sol(ok, f):
        return SimpleNamespace(success=ok, objective=f)

    assert lowest_cost([sol(True, 3.0), sol(False, 1.0), sol(True, 2.0)]) == 2
    assert lowest_cost([sol(False, 1.0), sol(False, 0.5)]) is None
    assert lowest_cost([sol(True, 3.0), sol(True, 2.0)], costs=[1.0, 5.0]) == 0
    assert lowest_cost([sol(True, 2.0), sol(True, 2.0)]) == 0  # ties: the first


@pytest.mark.parametrize(("kernel", "constant_field"), [("se", False), ("curl_free", True)])
def test_the_window_map_prior_enters_the_hessian_as_its_precision(kernel, constant_field):
    """The carried prior 0.5 (z - mu)^T Lambda (z - mu) enters the Hessian as the parameter
    Lambda placed at the map's unknowns (NLPBuilder.quadratic; a shared SE precision once
    per field column): with the magnetometer's weight made negligible the map block of the
    Hessian is Lambda itself, so a wrong offset or column order fails here."""
    from casmag.model.rrmap import make_basis
    from casmag.model.translational import WindowStructure
    from casmag.problem.spec import SolverSpec

    Q = np.cumsum(np.full((6, 2), 0.1), axis=0)
    hb = make_basis(kernel, Q, 0.5, 12, None)  # a curl-free map's box is 3-D
    s = WindowStructure(
        n=6,
        dim=2,
        kernel=kernel,
        basis=(tuple(hb.domain.center), tuple(hb.domain.half_width), hb.num_basis),
        knot_every=1,
        constant_field=constant_field,
        estimate_bias=True,
        solver=SolverSpec().model_dump_json(),
    )
    assert s.shared_prior == (kernel == "se")
    nlp = s.nlp()
    rng = np.random.default_rng(3)
    n_r, n_c = s.prior_shape
    A = rng.normal(size=(n_r, n_r))
    Lam = A @ A.T + n_r * np.eye(n_r)
    params = {
        "Q": Q,
        "Y": rng.normal(size=(6, 3)),
        "anchor": Q[:1],
        "sigma_o": 0.01,
        "sigma_anchor": 0.001,
        "sigma_m": 1.0e8,
        "bias_mean": np.zeros((1, 2)),
        "bias_precision": np.eye(2),
        "map_mean": rng.normal(size=(n_r, n_c)),
        "map_precision": Lam,
        "sigma_f": 1.0,
        "lengthscale": 0.5,
        "sigma_lin": 1.0,
    }
    entries = nlp.x_layout.entries
    x = {name: rng.normal(size=e.shape) for name, e in entries.items()}
    H = nlp.hessian(x, params).toarray()
    first = entries["W"].offset
    size = entries["W"].size + (entries["c"].size if constant_field else 0)
    block = H[first : first + size, first : first + size]
    expected = np.kron(np.eye(n_c), Lam)
    np.testing.assert_allclose(block, expected, rtol=1e-9, atol=1e-9)
