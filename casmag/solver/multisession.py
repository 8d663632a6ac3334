"""Multi-session GP-SLAM: several recordings of the same field, one map.

A single walk that never returns to where it has been (a lawnmower sweep, a corridor) gives
a magnetic map nothing to close the loop on: the drift along the path is unobservable, and
single-session GP-SLAM can only keep the odometry. Recordings of the same building made at
other times cross that path. casmag stacks them into one MAP problem: every session keeps
its own trajectory (knot corrections), its own odometry bias and its own anchor (its known
first position, in the common frame), and all of them share one reduced-rank field map.
Each session's odometry is integrated only within the session (casmag.data.simulate.Dataset with
``starts``; casmag.model.knots keeps one chain per session).

Solving all sessions at once from their dead reckoning can end in a poor local optimum: on a
synthetic pair (a spiral with loops and a straight line across it,
tests/solver/test_multisession.py) the hybrid Hessian stopped at a cost of 20,985 against
134 at the truth. So sessions are added one at a time (:func:`solve_sessions`): the session
whose dead reckoning revisits itself most comes first (:func:`session_order`, computable
without truth), and every later stage starts from the previous stage's trajectories plus the
new session's dead reckoning. On that pair this reached the truth's optimum in 6 iterations
for the last stage. Long sessions (more than 2 x FIRST_PREFIX samples) are also tried from
growing prefixes, and the start with the lower MAP cost is kept (:func:`starts`): on the
real field neither start is right every time, and the cost told them apart in every case
measured (README, Measured: real field).

These steps are casmag.solver.staged.solve_sessions, written once for every motion model;
here it runs on the translational model (casmag.solver.translational.TranslationalStaged),
and the session order and the per-session rows of a result are shared
(casmag.solver.sessions).

``casmag slam REC1.csv REC2.csv ... --out DIR`` runs it with the single-recording defaults
(casmag.solver.recslam.recording_problem on the stacked data) and reports every session's errors in
``result.json`` under ``info.sessions``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from casmag.data.simulate import Dataset
from casmag.problem.spec import Problem, WarmStartSpec
from casmag.result import Result
from casmag.solver.api import solve
from casmag.solver.biasscan import BiasScan, drift_grid, evidence_start, field_sigma
from casmag.solver.sessions import revisit_order, session_errors
from casmag.solver.staged import SessionsRun, StagedRun, StartBias, solve_starts
from casmag.solver.staged import Stage as StagedStage
from casmag.solver.staged import solve_sessions as staged_sessions
from casmag.solver.translational import TranslationalStaged, stage_record


def stack(sessions: Sequence[Dataset]) -> Dataset:
    """One data set holding every session (``starts``, one anchor row and bias row each).
    Truth is kept only when every session has it."""
    if len(sessions) < 1:
        raise ValueError("need at least one session")
    dims = {d.dim for d in sessions}
    if len(dims) != 1:
        raise ValueError(f"sessions of different dimension: {sorted(dims)}")
    if len(sessions) == 1:
        return sessions[0]
    dim = dims.pop()
    starts = tuple(int(i) for i in np.cumsum([0] + [d.n_samples for d in sessions[:-1]]))
    gap = np.zeros((1, dim))  # the step between two sessions: not odometry, ignored
    U = np.vstack([u for d in sessions for u in (d.U, gap)][:-1])
    truth = all(d.P_true is not None for d in sessions)
    field = all(d.M_true is not None for d in sessions)
    biases = all(d.bias_true is not None for d in sessions)
    return Dataset(
        U=U,
        Y=np.vstack([d.Y for d in sessions]),
        anchor=np.vstack([np.ravel(d.anchor) for d in sessions]),
        P_true=np.vstack([d.P_true for d in sessions]) if truth else None,
        M_true=np.vstack([d.M_true for d in sessions]) if field else None,
        bias_true=np.vstack([np.ravel(d.bias_true) for d in sessions]) if biases else None,
        starts=starts,
    )


def session_order(sessions: Sequence[Dataset], lengthscale: float) -> list[int]:
    """Sessions by decreasing revisit fraction of their dead reckoning
    (casmag.solver.sessions.revisit_order)."""
    return revisit_order([d.dead_reckoning() for d in sessions], lengthscale)


def solve_sessions(
    problem: Problem,
    sessions: Sequence[Dataset],
    progress: Callable[[int, float, float, float], None] | None = None,
    order: Sequence[int] | None = None,
) -> tuple[Result, Dataset, list[int]]:
    """Solve sessions with one shared map, adding them one at a time in ``order`` (default
    :func:`session_order`) by casmag.solver.staged.solve_sessions on the translational
    model: the first session from :func:`starts`, each later one from its dead reckoning
    and from its growing prefixes (FIRST_PREFIX, x ``growth``, ... samples), the lower MAP
    cost kept. The final solve starts from the kept positions. Returns the final result,
    the stacked data in that order and the order; the first records of ``result.stages``
    (name ``start``, with ``session``, ``start``, ``cost`` and ``kept``) are every solve
    before it."""
    order = (
        list(order) if order is not None else session_order(sessions, problem.assumed_lengthscale)
    )
    ordered = [sessions[i] for i in order]
    data = stack(ordered)
    if len(ordered) == 1:
        result = solve(problem, data, progress)
        result.info["session_order"] = order
        return result, data, order
    model = TranslationalStaged(problem, data)
    strategies, _ = starts(problem, ordered[0].n_samples)
    run = staged_sessions(model, _growing(problem), [0.0] * len(strategies), strategies)
    stages = _records(model, run)
    final = run.final
    P0 = model.states(final)["P"] if final.sol.success else data.dead_reckoning()
    batch = problem.with_overrides(["solver.warm_start.strategy=none"])
    result = solve(batch, data, progress, initial_positions=P0)
    result.info["session_order"] = order
    result.stages = stages + result.stages
    result.iterations += sum(st["iterations"] for st in stages)
    result.solve_seconds += sum(st["solve_seconds"] for st in stages)
    return result, data, order


FIRST_PREFIX = 400
"""First prefix [samples] of the growing start tried for the first session."""


def starts(problem: Problem, n: int) -> tuple[list[WarmStartSpec], list[str]]:
    """The starts of a translational solve of n samples and their names: the batch from
    the dead reckoning, and (above 2 x FIRST_PREFIX samples) growing prefixes from
    FIRST_PREFIX samples."""
    batch = problem.spec.solver.warm_start.model_copy(update={"strategy": "none"})
    if n <= 2 * FIRST_PREFIX:
        return [batch], ["dead reckoning"]
    return [batch, _growing(problem)], ["dead reckoning", "growing prefixes"]


def _growing(problem: Problem) -> WarmStartSpec:
    """Growing prefixes from FIRST_PREFIX samples (a start's, and each added session's)."""
    ws = problem.spec.solver.warm_start
    return ws.model_copy(update={"strategy": "growing", "first_samples": FIRST_PREFIX})


def _record(model: TranslationalStaged, st: StagedStage, name: str, **more: Any) -> dict:
    """A ``start`` record: the solve's (casmag.solver.translational.stage_record), its
    start's ``name`` and its MAP ``cost`` (None when it failed)."""
    so = st.solved.sol
    cost = so.objective if so.success else None
    return {**stage_record(model, st), "name": "start", "start": name, "cost": cost, **more}


def start_records(model: TranslationalStaged, run: StagedRun, names: list[str]) -> list[dict]:
    """One ``start`` record of each start of a run (its last solve: ``start``, ``cost``,
    ``kept``, ``path_rms_from_kept``: casmag.solver.staged.paths_apart)."""
    apart = run.apart or [None] * len(run.runs)
    return [
        _record(model, stages[-1], name, kept=i == run.kept, path_rms_from_kept=apart[i])
        for i, (name, stages) in enumerate(zip(names, run.runs, strict=True))
    ]


def _records(model: TranslationalStaged, run: SessionsRun) -> list[dict[str, Any]]:
    """The ``start`` records of a sessions run: the first session's starts, then every
    solve of each session added (``session``, ``start``, ``kept`` on the kept one's last)."""
    _, names = starts(model.problem, model.sessions(model.n)[0][1])
    out = [{**r, "session": 0} for r in start_records(model, run.first, names)]
    for j, (tried, kept) in enumerate(zip(run.added, run.kept, strict=True)):
        for i, (name, stages) in enumerate(tried):
            for k, st in enumerate(stages):
                last = k == len(stages) - 1
                out.append(_record(model, st, name, session=j + 1, kept=i == kept and last))
    return out


def solve_recording_starts(
    problem: Problem, data: Dataset
) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """One recording from :func:`starts` and from the odometry bias of :func:`drift_start`
    (``evidence bias``, when it chose one), keeping the lowest MAP cost
    (casmag.solver.staged.solve_starts). Returns the kept positions (the dead reckoning
    when every start failed) and a ``start`` record of each start (``start``, ``cost``,
    ``kept``; the evidence bias's with its ``scan``). No start is right every time on the
    real field: on sequence 5 at 0.5 m drift the batch reached 0.012 m at cost 661 and
    growing 0.418 m at cost 1,552; at 1.5 m drift the batch stopped at 0.944 m (cost
    1,116) and growing reached 0.011 m; on sequence 3 at 1.5 m the batch and growing ended
    at costs 501 and 510, the evidence bias at 288 and 0.018 m."""
    model = TranslationalStaged(problem, data)
    strategies, names = starts(problem, data.n_samples)
    biases: list[StartBias] = [0.0] * len(strategies)
    scan = drift_start(problem, model)
    if scan is not None:
        strategies.append(strategies[0])
        names.append(EVIDENCE_START)
        biases.append(scan.bias)
    run = solve_starts(model, strategies[0], biases, strategies=strategies)
    records = start_records(model, run, names)
    if scan is not None:
        records[-1]["scan"] = scan.to_dict()
    final = run.final
    if not final.sol.success:
        for r in records:
            r["kept"] = False
        return data.dead_reckoning(), records
    return model.states(final)["P"], records


#: The name of the start from the bias the field's evidence chose (:func:`drift_start`).
EVIDENCE_START = "evidence bias"


def drift_start(problem: Problem, model: TranslationalStaged) -> BiasScan | None:
    """The per-step odometry bias the field's evidence chooses (casmag.solver.biasscan,
    over its drift_grid) for one more start of a single recording, or None: when
    ``solver.warm_start.evidence`` is false, when the bias is not estimated or has a prior
    (a start with a bias removed would then solve another problem), for several sessions,
    and as casmag.solver.biasscan.evidence_start says."""
    m, data = problem.spec.model, model.data
    if not problem.spec.solver.warm_start.evidence:
        return None
    if data.n_sessions > 1 or not m.odometry.estimate_bias or m.odometry.bias_prior_sigma:
        return None
    h = problem.assumed_hyperparameters
    ell = h["lengthscale"]
    sigma = field_sigma(problem.assumed_kernel, h["sigma_f"], ell)
    grid = drift_grid(data.dead_reckoning(), ell)
    return evidence_start(model, grid, sigma, ell, h["sigma_m"], data.dim)


def split(data: Dataset, array: np.ndarray | None) -> list[np.ndarray | None]:
    """The per-session pieces of an (N, ...) array of the stacked data."""
    if array is None:
        return [None] * data.n_sessions
    return [array[i:j] for i, j in data.session_bounds]


def session_rows(data: Dataset, result: Result, names: Sequence[str]) -> list[dict[str, Any]]:
    """Per-session errors of a stacked solve (casmag.solver.sessions.session_errors), each
    session's odometry bias one row of ``result.odometry_bias``."""
    bias = result.odometry_bias
    bias_true = data.bias_true
    return session_errors(
        data.session_bounds,
        result,
        names,
        data.P_true,
        None if bias is None else list(np.reshape(bias, (data.n_sessions, -1))),
        None if bias_true is None else list(np.reshape(bias_true, (data.n_sessions, -1))),
    )
