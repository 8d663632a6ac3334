"""casmag.solver.staged: the warm-start strategies written once over the staged motion
models (planar, pose): their bookkeeping on a stand-in model, each strategy with each
model at tiny size, and which test solves each pair of motion model and strategy."""

from __future__ import annotations

import ast
import itertools
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from small_problems import planar_room_field

from casmag.data.imusim import simulate_planar
from casmag.data.posesim import simulate_pose
from casmag.problem.imu import STAGED_STRATEGIES, load_planar_options
from casmag.problem.pose import load_pose_options
from casmag.problem.spec import SolverSpec, WarmStartSpec, load_problem
from casmag.result import MOTIONS
from casmag.solver.planar import solve_planar
from casmag.solver.pose import solve_pose
from casmag.solver.staged import (
    Solved,
    StagedModel,
    heading_bias_starts,
    solve_sessions,
    solve_starts,
    solve_strategy,
)
from casmag.solver.windowing import lengthscale_schedule, stage_lengths

ROOT = Path(__file__).resolve().parents[2]


class StandIn(StagedModel):
    """A model whose 'solve' records its call and returns a cost from ``cost(k, bias,
    lengthscale)``; ``fail`` lists (k, lengthscale) solves that end with an IPOPT error."""

    def __init__(self, n: int, cost: Any, fail: tuple = ()) -> None:
        self.n, self.lengthscale, self.solver = n, 0.5, SolverSpec(max_iter=80)
        self.cost, self.fail, self.calls = cost, fail, []

    def start(self, k: int, bias: float = 0.0) -> dict[str, np.ndarray]:
        return {"k": np.array(k), "bias": np.array(bias), "from": np.array(-1)}

    def states(self, solved: Solved) -> dict[str, np.ndarray]:
        x = solved.sol.x  # a one-sample path at (bias, 0)
        return {**x, "P": np.array([[float(x["bias"]), 0.0]])}

    def extend(self, states: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        return {"k": np.array(k), "bias": states["bias"], "from": states["k"]}

    def solve(self, k: int, start: dict, solver: SolverSpec, lengthscale: float) -> Solved:
        self.calls.append((k, int(start["from"]), solver.max_iter, lengthscale))
        failed = (k, lengthscale) in self.fail
        sol = SimpleNamespace(
            x={"k": np.array(k), "bias": start["bias"]},
            objective=self.cost(k, float(start["bias"]), lengthscale),
            success=not failed,
            status="Restoration_Failed" if failed else "Solve_Succeeded",
            iterations=3,
            solve_seconds=0.01,
            rounds=1,
        )
        return Solved(sol, None, None, lengthscale)  # type: ignore[arg-type]


def _ws(strategy: str, **kw: Any) -> WarmStartSpec:
    return WarmStartSpec(strategy=strategy, stage_max_iter=7, **kw)


def test_each_strategy_chains_its_stages_and_ends_with_the_full_problem() -> None:
    """growing: prefixes of stage_lengths, each from the previous one, the last with the
    full settings; coarse-to-fine: the full problem over the lengthscale schedule, each
    stage from the previous; none: one batch from the dead reckoning."""
    m = StandIn(1000, lambda k, b, ell: 1.0)
    stages = solve_strategy(m, _ws("growing", first_samples=100, growth=3.0))
    sizes = stage_lengths(1000, 100, 3.0)
    assert [s.samples for s in stages] == sizes == [100, 300, 1000]
    assert m.calls == [(100, -1, 7, 0.5), (300, 100, 7, 0.5), (1000, 300, 80, 0.5)]
    m.calls.clear()
    stages = solve_strategy(m, _ws("coarse-to-fine", lengthscale_start=4.0, lengthscale_stages=3))
    assert [s.kind for s in stages] == ["lengthscale", "lengthscale", "batch"]
    np.testing.assert_allclose([s.lengthscale for s in stages], [2.0, 1.0, 0.5])
    assert [c[:3] for c in m.calls] == [(1000, -1, 7), (1000, 1000, 7), (1000, 1000, 80)]
    assert lengthscale_schedule(0.5, 4.0, 3) == [s.lengthscale for s in stages]
    m.calls.clear()
    assert [s.kind for s in solve_strategy(m, _ws("none"))] == ["batch"]
    assert m.calls == [(1000, -1, 80, 0.5)]
    with pytest.raises(NotImplementedError, match="no sliding windows"):
        solve_strategy(m, _ws("sliding"))


def test_a_failed_stage_ends_the_strategy_and_its_start_is_not_kept() -> None:
    """Starts: every start runs the strategy; the lowest cost among those whose last stage
    is the full problem and succeeded is kept, and the records mark it. A start whose
    coarse stage fails stops there (no later stage is solved) and is not kept, though its
    cost is the lowest."""
    ws = _ws("coarse-to-fine", lengthscale_start=2.0, lengthscale_stages=2)
    biases = heading_bias_starts(3, 10.0, 100.0)
    d = np.radians(10.0) / 100.0
    np.testing.assert_allclose(biases, [0.0, d, -d])
    cost = {0.0: 5.0, d: 3.0, -d: 1.0}
    m = StandIn(50, lambda k, b, ell: cost[b])
    run = solve_starts(m, ws, biases)
    assert run.kept == 2 and run.final.sol.objective == 1.0
    records = run.records()
    assert [r["name"] for r in records] == ["lengthscale", "batch"] * 3
    assert [r["kept"] for r in records] == [False] * 5 + [True]
    assert [r["bias"] for r in records][::2] == biases
    # each start's last solve: how far its path lies from the kept one's
    np.testing.assert_allclose(run.apart, [d, 2 * d, 0.0])
    assert [r.get("path_rms_from_kept") for r in records][1::2] == run.apart
    assert all("path_rms_from_kept" not in r for r in records[::2])

    class FailsOne(StandIn):
        def solve(self, k: int, start: dict, solver: SolverSpec, lengthscale: float) -> Solved:
            out = super().solve(k, start, solver, lengthscale)
            if float(start["bias"]) == -d and lengthscale == 1.0:
                out.sol.success, out.sol.status = False, "Restoration_Failed"
            return out

    # -d's coarse stage fails: its run stops there, and the next lowest cost is kept
    m = FailsOne(50, lambda k, b, ell: cost[b])
    run = solve_starts(m, ws, biases)
    assert [len(r) for r in run.runs] == [2, 2, 1]
    assert run.kept == 1 and run.final.sol.objective == 3.0
    assert run.apart[2] is None  # its last solve failed
    assert [r["name"] for r in run.records()][-1] == "start"  # one solve: named as a start
    # none succeeded: the first start is kept (the dead reckoning's), and says so
    m = StandIn(50, lambda k, b, ell: 1.0, fail=((50, 0.5),))
    run = solve_starts(m, _ws("none"), [0.0, 0.1])
    assert run.kept == 0 and not run.final.sol.success


def _planar(strategy: str):
    d = simulate_planar(
        1, planar_room_field(), size=(2.0, 1.5), loops=2, heading_bias_deg=0.5, disp_noise=0.002
    )
    sets = [
        "model.sigma_disp=0.002",
        f"model.sigma_dyaw={np.radians(0.05)}",
        "model.gp.num_basis=120",
        f"solver.warm_start.strategy={strategy}",
        "solver.warm_start.first_samples=40",
        "solver.warm_start.stage_max_iter=10",
    ]
    r = solve_planar(
        *d.U.T, d.Y, load_planar_options(None, sets), truth={"P": d.P, "psi": d.psi}, t=d.t
    )
    return r, d.P.shape[0]


def _pose(strategy: str, *more: str):
    sets = ["simulation.trajectory.samples=100", "simulation.trajectory.area=[4.0, 2.0]"]
    prob = load_problem(ROOT / "problems" / "bench" / "peers.yaml", ["seed=2", *sets])
    rec = simulate_pose(prob.spec.simulation, 2, bias_w=(0.0, 0.0, 0.002))
    # the windows' map: a smaller basis, so that the dense map block of each window's
    # KKT system stays small at this size
    basis = ["model.gp.num_basis=250"] if strategy == "sliding" else []
    opts = load_pose_options(
        None,
        [
            f"solver.warm_start.strategy={strategy}",
            "solver.warm_start.first_samples=40",
            "solver.warm_start.stage_max_iter=10",
            *basis,
            *more,
        ],
    )
    r = solve_pose(rec.U, rec.Y, opts, truth={"P": rec.P_true, "q": rec.q_true}, t=rec.t)
    return r, rec.P_true.shape[0]


#: The (model, strategy) pairs solved here, by test_every_strategy_solves_every_staged_model.
PAIRS = [
    ("planar", "coarse-to-fine"),
    ("planar", "sliding"),
    ("pose", "growing"),
    ("pose", "coarse-to-fine"),
    ("pose", "sliding"),
]

#: Every warm-start strategy a motion model can run: the four of solver.warm_start, several
#: starts kept by the lowest MAP cost, and several sessions of one field (one map).
STRATEGIES = (*STAGED_STRATEGIES, "starts", "sessions")

#: The tests that solve each (motion model, strategy) pair at tiny size: (file under
#: tests/, test function, the pairs it solves).
SOLVED_BY = [
    (
        "solver/test_slam.py",
        "test_growing_warm_start_recovers_drift_a_batch_does_not",
        [("translational", "none"), ("translational", "growing")],
    ),
    (
        "solver/test_windowing.py",
        "test_coarse_to_fine_schedule_and_solve",
        [("translational", "coarse-to-fine")],
    ),
    (
        "solver/test_windowing.py",
        "test_sliding_start_reaches_the_basin_from_a_drifting_start",
        [("translational", "sliding")],
    ),
    (
        "data/test_realdata.py",
        "test_slam_keeps_the_lowest_cost_of_its_starts",
        [("translational", "starts")],
    ),
    (
        "solver/test_multisession.py",
        "test_cli_solves_several_recordings",
        [("translational", "sessions")],
    ),
    (
        "solver/test_imu.py",
        "test_planar_starts_keep_the_lowest_cost",
        [("planar", "none"), ("planar", "starts")],
    ),
    (
        "cli/test_planar_cli.py",
        "test_growing_prefixes_on_a_planar_recording",
        [("planar", "growing")],
    ),
    (
        "solver/test_oriented_sessions.py",
        "test_slam_solves_planar_sessions_and_refuses_mixed_kinds",
        [("planar", "sessions")],
    ),
    (
        "solver/test_pose.py",
        "test_slam_on_a_pose_recording_map_ekf_and_both",
        [("pose", "none")],
    ),
    (
        "solver/test_staged.py",
        "test_pose_starts_are_turned_dead_reckonings_and_the_lowest_cost_is_kept",
        [("pose", "starts")],
    ),
    (
        "solver/test_oriented_sessions.py",
        "test_pose_sessions_share_one_map",
        [("pose", "sessions")],
    ),
    (
        "solver/test_imu_strategies.py",
        "test_each_strategy_returns_the_truth_on_a_noise_free_rectangle",
        [("imu", s) for s in (*STAGED_STRATEGIES, "starts")],
    ),
    (
        "solver/test_imu_sessions.py",
        "test_two_recordings_of_the_rectangle_share_one_map",
        [("imu", "sessions")],
    ),
    ("solver/test_staged.py", "test_every_strategy_solves_every_staged_model", PAIRS),
]


def test_every_pair_is_solved_somewhere() -> None:
    """Every motion model with every warm-start strategy is solved by a named test, and
    every test named exists (a renamed or removed test fails here, not silently)."""
    solved = {pair for _, _, pairs in SOLVED_BY for pair in pairs}
    assert solved == {(m, s) for m in MOTIONS for s in STRATEGIES}
    for path, name, _ in SOLVED_BY:
        tree = ast.parse((ROOT / "tests" / path).read_text())
        defined = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
        assert name in defined, f"{path}::{name}"


@pytest.mark.slow
def test_pose_starts_are_turned_dead_reckonings_and_the_lowest_cost_is_kept() -> None:
    """model.starts = 3 for the pose model: the dead reckoning and the dead reckoning turned
    about the vertical by +-10 deg over the recording (casmag.strapdown.turn_heading), each
    solved, the lowest MAP cost kept."""
    r, n = _pose("none", "model.starts=3", "solver.warm_start.evidence=false")
    assert r.success, r.status
    starts = r.stages_named("start")
    assert len(starts) == 3 and starts[0]["bias"] == 0.0
    assert starts[1]["bias"] == pytest.approx(-starts[2]["bias"])
    t = r.arrays["t"]
    assert len(t) == n and starts[1]["bias"] == pytest.approx(np.radians(10.0) / (t[-1] - t[0]))
    kept = [s for s in starts if s["kept"]]
    assert len(kept) == 1 and kept[0]["cost"] == min(s["cost"] for s in starts)
    assert r.rmse_after < 0.5 * r.rmse_before


class Sessions(StandIn):
    """Two sessions, samples [0, 100) and [100, 300); a solve's cost depends on where its
    start came from (``cost_from``: the sample count of the state it was continued from),
    and solves of (k, from) in ``fail`` end with an IPOPT error."""

    session_starts = (0, 100)

    def __init__(self, cost_from: dict[int, float], fail: tuple = ()) -> None:
        super().__init__(300, lambda k, b, ell: 1.0)
        self.cost_from, self.fail_from = cost_from, fail

    def solve(self, k: int, start: dict, solver: SolverSpec, lengthscale: float) -> Solved:
        out = super().solve(k, start, solver, lengthscale)
        origin = int(start["from"])
        out.sol.objective = self.cost_from.get(origin, 1.0)
        if (k, origin) in self.fail_from:
            out.sol.success, out.sol.status = False, "Restoration_Failed"
        return out


def test_sessions_are_added_one_at_a_time_from_two_starts_kept_by_cost() -> None:
    """The first session alone runs the strategy (one batch of its 100 samples); the second
    (200 samples > 2 x first_samples) is solved from the first session's estimate continued
    (its dead reckoning) and in growing prefixes of 20, 40, 80 samples beside it, those
    before the last capped at stage_max_iter; the lower cost of the full solves is kept."""
    ws = _ws("none", first_samples=20, growth=2.0)
    m = Sessions({100: 20.0, 180: 10.0})  # the growing start's full solve costs less
    run = solve_sessions(m, ws, [0.0])
    assert m.calls == [
        (100, -1, 80, 0.5),  # the first session
        (300, 100, 80, 0.5),  # the second's dead reckoning beside it
        (120, 100, 7, 0.5), (140, 120, 7, 0.5), (180, 140, 7, 0.5), (300, 180, 80, 0.5),
    ]  # fmt: skip
    assert run.kept == [1] and run.final.sol.objective == 10.0
    records = run.records()
    assert [(r["session"], r.get("start"), r["samples"]) for r in records] == [
        (0, None, 100), (1, "dead reckoning", 300), (1, "growing prefixes", 120),
        (1, "growing prefixes", 140), (1, "growing prefixes", 180),
        (1, "growing prefixes", 300),
    ]  # fmt: skip
    assert [r["kept"] for r in records] == [False] * 5 + [True]
    # A failed full solve is never kept, however low its cost.
    m = Sessions({100: 20.0, 180: 10.0}, fail=((300, 180),))
    run = solve_sessions(m, ws, [0.0])
    assert run.kept == [0] and run.final.sol.objective == 20.0
    assert [r["kept"] for r in run.records()] == [False, True, False, False, False, False]
    with pytest.raises(ValueError, match="one session at a time"):
        solve_sessions(m, _ws("sliding"), [0.0])


@pytest.mark.parametrize(("model", "strategy"), PAIRS)
def test_every_strategy_solves_every_staged_model(model: str, strategy: str) -> None:
    """A strategy of solver.warm_start with a staged model at tiny size: the stages the
    strategy prescribes, the last the full problem at the assumed lengthscale, kept, and the
    position error at most half the dead reckoning's."""
    r, n = (_planar if model == "planar" else _pose)(strategy)
    assert r.success, r.status
    stages = r.stages
    ell = r.hyperparameters["lengthscale"]
    if strategy == "growing":
        assert [s["samples"] for s in stages] == stage_lengths(n, 40, 2.0)
        assert {s["name"] for s in stages} == {"prefix"}
    elif strategy == "coarse-to-fine":
        assert [s["name"] for s in stages] == ["lengthscale", "lengthscale", "batch"]
        np.testing.assert_allclose([s["lengthscale"] for s in stages], [3 * ell, 3**0.5 * ell, ell])
        assert all(s["iterations"] <= 10 for s in stages[:-1])  # stage_max_iter
    elif strategy == "sliding":
        windows = stages[:-1]
        assert [s["name"] for s in stages] == ["window"] * len(windows) + ["batch"]
        firsts = [s["first"] for s in windows]
        k = windows[0]["samples"]
        assert firsts[0] == 0 and firsts[-1] + k == n and len(windows) > 2
        # consecutive windows overlap, and every sample is in one
        assert all(0 < b - a < k for a, b in itertools.pairwise(firsts))
        assert all(s["iterations"] <= 50 for s in windows)  # window_max_iter
    else:
        assert [s["name"] for s in stages] == ["start"]
    assert stages[-1]["samples"] == n and stages[-1]["lengthscale"] == ell
    assert [s["kept"] for s in stages] == [False] * (len(stages) - 1) + [True]
    assert r.info["warm_start"] == (strategy if len(stages) > 1 else "none")
    assert r.rmse_after < 0.5 * r.rmse_before, (r.rmse_after, r.rmse_before)


def test_a_tiled_stage_is_solved_on_around_where_its_samples_went():
    """solve_rehomed stops a tiled solve whose Hessian dropped border products (samples
    beyond their home tiles), lays the pattern around the samples' new places in a new,
    uncached NLP, solves on from where it stopped, and merges the rounds; a solve whose
    samples stay home is one round of the cached NLP."""
    import dataclasses as dc

    from casmag.model.tiledmap import home_points, tile_grid
    from casmag.nlp import STALLED, Solution
    from casmag.solver.staged import solve_rehomed

    @dc.dataclass(frozen=True)
    class Structure:
        grid: Any
        home: tuple[int, ...]
        tiled: bool = True

    P0 = np.column_stack([np.linspace(0.0, 3.0, 20), np.zeros(20)])
    P1 = P0 + np.array([1.5, 0.5])
    grid = tile_grid(np.vstack([P0, P1]), 0.3)

    def solution(status, P, iterations):
        return Solution(
            x={"P": P}, lam_x=np.zeros(0), status=status, success=status != STALLED,
            iterations=iterations, solve_seconds=1.0, objective=1.0,
            cost_per_iteration=[1.0] * iterations, inf_pr_per_iteration=[0.0] * iterations,
            blocks_before={"b": float(iterations)}, blocks_after={},
        )  # fmt: skip

    built = []

    class FakeNLP:
        def __init__(self, s, moves):
            self.s, self.moves = s, moves
            self.keep = (None, SimpleNamespace(dropped=[]))

        def solve(self, params, x0, stop_when=None, **kw):
            if self.moves:  # the samples go to P1; the next evaluation drops terms
                self.keep[1].dropped = [0, 7]
                assert stop_when is not None and stop_when()
                return solution(STALLED, P1, 3)
            self.keep[1].dropped = [0]
            return solution("Solve_Succeeded", P1, 5)

    def nlp_of(s, cache=True):
        built.append((s.home, cache))
        return FakeNLP(s, moves=len(built) == 1)

    s0 = Structure(grid, home_points(grid, P0))
    sol, nlp, s = solve_rehomed(s0, nlp_of, {}, {"P": P0}, 2)
    assert built == [(s0.home, True), (home_points(grid, P1), False)]
    assert s.home == home_points(grid, P1) != s0.home and nlp.s is s
    assert sol.status == "Solve_Succeeded" and sol.iterations == 8 and sol.rounds == 2
    assert sol.blocks_before == {"b": 3.0}
    built.clear()
    built.append("first done")  # nlp_of's next NLP does not move
    sol, _, s = solve_rehomed(s0, nlp_of, {}, {"P": P0}, 2)
    assert built[1:] == [(s0.home, True)] and sol.rounds == 1 and s is s0


class Turning(StandIn):
    """A stand-in whose states carry the turn applied to them and whose stage problem's
    MAP cost is ``cost_of(turn)``."""

    turns = True

    def __init__(self, cost_of: Any) -> None:
        super().__init__(300, lambda k, b, ell: 1.0)
        self.cost_of, self.evaluated = cost_of, []

    def turned(self, states: dict, k: int, turn: float) -> dict:
        return {**states, "turn": np.array(float(states.get("turn", 0.0)) + turn)}

    def stage_problem(self, k, start, solver, lengthscale, structure=None, coarse=False):
        turn = float(start.get("turn", 0.0))
        self.evaluated.append(turn)
        return SimpleNamespace(
            structure=structure, nlp_of=lambda s, cache=True: None,
            cost=lambda nlp: self.cost_of(turn),
        )  # fmt: skip


@pytest.mark.parametrize("best_deg", [-5.3, 0.0, 2.6, 40.0])
def test_the_turn_search_brackets_and_narrows_the_lowest_cost(best_deg: float) -> None:
    """casmag.solver.staged.best_turn on a cost with its minimum at ``best_deg``: trials of
    +-1 deg, doubled downhill until the cost rises, then golden-section steps; the start
    kept when neither first trial lowers the cost, and no turn beyond TURN_MAX_DEG."""
    from casmag.solver.staged import TURN_MAX_DEG, best_turn

    model = Turning(lambda turn: (np.degrees(turn) - best_deg) ** 2)
    start = {"k": np.array(300), "bias": np.array(0.0), "from": np.array(40)}
    out, rec = best_turn(model, 300, start, model.solver, 0.5)
    assert rec is not None and rec["evaluations"] == len(set(model.evaluated))
    assert rec["cost_after"] <= rec["cost_before"]
    if best_deg == 0.0:
        assert rec["turn_deg"] == 0.0 and rec["evaluations"] == 3 and "turn" not in out
        return
    found = float(np.degrees(out["turn"]))
    assert found == pytest.approx(rec["turn_deg"])
    if abs(best_deg) > TURN_MAX_DEG:
        assert found == pytest.approx(TURN_MAX_DEG)
    else:
        assert abs(found - best_deg) < 0.6, (found, best_deg)


def test_a_model_without_a_heading_or_with_sessions_is_not_turned() -> None:
    """No search on the translational stand-in (``turns`` False) or across sessions."""
    from casmag.solver.staged import best_turn

    start = {"k": np.array(300), "bias": np.array(0.0), "from": np.array(40)}
    assert best_turn(StandIn(300, lambda k, b, ell: 1.0), 300, start, SolverSpec(), 0.5) == (
        start, None,
    )  # fmt: skip
    two = Turning(lambda turn: turn**2)
    two.session_starts = (0, 100)
    assert best_turn(two, 300, start, two.solver, 0.5) == (start, None)


@pytest.mark.parametrize("motion", ["planar", "pose"])
def test_a_continued_start_is_turned_to_its_lowest_cost(monkeypatch, motion: str) -> None:
    """Growing prefixes on the planar and pose models: every prefix after the first starts
    from the previous estimate turned about the vertical by the search's angle
    (casmag.solver.staged.best_turn, recorded as the stage's ``turn``), which never raises
    the start's MAP cost. The turns compose (a turn by a then b is one by a + b, the first
    pose kept, the last heading turned by the angle; planar: the odometry's cost as it
    was), and the search finds a turn put on the chosen start again."""
    import casmag.solver.staged as staged

    calls: list[tuple] = []
    original = staged.best_turn

    def recording(model, k, start, solver, ell):
        out = original(model, k, start, solver, ell)
        calls.append((model, k, solver, ell, out[0]))
        return out

    monkeypatch.setattr(staged, "best_turn", recording)
    r, n = _planar("growing") if motion == "planar" else _pose("growing")
    assert r.success, r.status
    prefixes = r.stages_named("prefix")
    assert len(prefixes) >= 2 and "turn" not in prefixes[0]
    for st in prefixes[1:]:
        assert st["turn"]["cost_after"] <= st["turn"]["cost_before"]
        assert st["turn"]["evaluations"] >= 3
    assert r.rmse_after < 0.5 * r.rmse_before

    model, k, solver, ell, chosen = calls[-1]
    assert k == n
    a, b = np.radians(3.0), np.radians(-1.0)
    twice, once = model.turned(model.turned(chosen, k, a), k, b), model.turned(chosen, k, a + b)
    for name in once:
        np.testing.assert_allclose(twice[name], once[name], atol=1e-9)
    np.testing.assert_allclose(once["P"][0], chosen["P"][0], atol=1e-12)
    if motion == "planar":
        assert once["psi"][-1] - chosen["psi"][-1] == pytest.approx(a + b)
        problem = model.stage_problem(k, chosen, solver, ell)
        nlp = problem.nlp_of(problem.structure, cache=False)
        p = nlp.p_layout.pack(problem.params)

        def odometry(start: dict) -> float:
            x0 = model.stage_problem(k, start, solver, ell, problem.structure).x0
            return nlp.evaluate_blocks(nlp.x_layout.pack(x0), p)["odometry"]

        assert odometry(once) == pytest.approx(odometry(chosen), rel=1e-9)
    off = model.turned(chosen, k, np.radians(-6.0))
    _, rec = original(model, k, off, solver, ell)
    assert rec["cost_after"] < rec["cost_before"]
    assert abs(rec["turn_deg"] - 6.0) < 1.0, rec
