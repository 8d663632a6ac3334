"""Sweeps: one problem (or a table of rows) solved over many seeds and parameter grids.

A sweep is planned from a problem file or a table file (``problems/paper/table*.yaml``: a
problem file plus rows of overrides, matched to the paper's published rows by key), the seeds
and an optional grid of ``key.path=v1,v2`` values. The problem file is translational, IMU,
planar or pose (``casmag.problem.spec.document_kind``): every run is one :func:`casmag.solve`
and is saved with its result's ``save`` under
``OUT/<row>/seed-<seed>/``; ``OUT/sweep.json`` records what the sweep is (kind, rows, labels,
overrides, seeds), which is all the report needs.

Runs execute in a local pool of processes (one per core, each single-threaded: the BLAS and
OpenMP thread counts are set to 1 before a worker imports numpy) or on a Dask distributed
cluster. A run whose ``result.json`` exists is skipped, so an interrupted sweep resumes; a run
that raised an error (not a solver failure, which is a result) leaves ``error.json`` and is
retried next time. Each worker process builds the NLP once per problem structure and reuses
it for every later run with the same structure (``casmag.model.translational.cached_nlp``).
The command, ``casmag sweep``, is casmag.cli.sweep.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import os
import re
import signal
import sys
import tempfile
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, ValidationError

from casmag import interrupt
from casmag.errors import CasmagError, DataError, ProblemError, one_line
from casmag.interrupt import Interrupted
from casmag.problem.imu import ImuProblem, load_imu_problem
from casmag.problem.oriented import OrientedProblem, load_oriented_problem
from casmag.problem.paper import TABLES
from casmag.problem.spec import (
    Problem,
    Strict,
    as_overrides,
    document_kind,
    load_problem,
    parse_override,
    read_yaml,
    validation_error,
)
from casmag.result import Result
from casmag.result.outdir import save_atomic
from casmag.solver.api import solve

MANIFEST = "sweep.json"
MANIFEST_FORMAT = "casmag-sweep/1"
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
CONNECT_TIMEOUT = "20s"  # to reach a Dask scheduler
_KEY = r"^[A-Za-z0-9][A-Za-z0-9_.=+-]*$"


# --------------------------------------------------------------------------- table files
class RowSpec(Strict):
    """One row of a table file: ``key`` (also its folder name, and for a paper table the
    paper's row it reproduces, unless ``paper_row`` names another), an optional ``label``
    (default: the paper's label, else the key) and ``set``, a mapping of ``key.path: value``
    overrides of the problem file. ``paper_row`` lets a variant of a paper row (a different
    model of the same experiment) be compared with that row's published numbers."""

    key: Annotated[str, Field(pattern=_KEY, max_length=80)]
    label: str | None = None
    paper_row: str | None = None
    set: dict[str, Any] = {}


class TableSpec(Strict):
    """A table file: ``problem`` (path relative to the table file), ``set`` (overrides for
    every row), ``rows``; ``paper`` names the paper's table the rows reproduce (their keys
    must be that table's row keys, casmag.problem.paper); ``name`` (default: the file stem) names
    the output; ``title`` defaults to the paper's caption."""

    name: Annotated[str, Field(pattern=_KEY, max_length=80)] | None = None
    title: str | None = None
    paper: str | None = None
    problem: str
    set: dict[str, Any] = {}
    rows: Annotated[list[RowSpec], Field(min_length=1)]


# --------------------------------------------------------------------------- plans
@dataclass(frozen=True)
class RowPlan:
    """A row of a sweep: its folder ``key``, ``label``, the paper row it reproduces (if any),
    the overrides applied to the problem file and a fingerprint of the resolved problem."""

    key: str
    label: str
    paper_key: str | None
    overrides: tuple[str, ...]
    fingerprint: str
    problem: dict[str, Any] = field(repr=False, hash=False, compare=False)


@dataclass(frozen=True)
class RunTask:
    """One solve: a validated problem (JSON-ready, seed and name set) and its folder."""

    sweep: str
    row: str
    seed: int
    problem: dict[str, Any]
    source: str
    out_dir: str
    figures: bool
    kind: str = "translational"  # "imu", "oriented": casmag.problem.spec.document_kind


@dataclass
class SweepPlan:
    """What a sweep solves: rows x seeds, written under ``out_dir``."""

    name: str
    title: str | None
    paper: str | None
    source: str
    problem_file: str
    rows: list[RowPlan]
    seeds: list[int]
    out_dir: Path
    kind: str = "translational"  # "imu", "oriented"

    def run_dir(self, row: str, seed: int) -> Path:
        return self.out_dir / row / f"seed-{seed:04d}"

    def tasks(self, figures: str = "first") -> Iterator[RunTask]:
        """Every (row, seed) run, seeds outermost so that early results cover every row."""
        for i, seed in enumerate(self.seeds):
            for row in self.rows:
                data = dict(row.problem, seed=seed)
                yield RunTask(
                    sweep=self.name,
                    row=row.key,
                    seed=seed,
                    problem=data,
                    source=f"{self.source}#{row.key}",
                    out_dir=str(self.run_dir(row.key, seed)),
                    figures=figures == "all" or (figures == "first" and i == 0),
                    kind=self.kind,
                )

    def manifest(self) -> dict[str, Any]:
        return {
            "format": MANIFEST_FORMAT,
            "name": self.name,
            "title": self.title,
            "paper": self.paper,
            "source": self.source,
            "problem": self.problem_file,
            "kind": self.kind,
            "seeds": self.seeds,
            "rows": [
                {
                    "key": r.key,
                    "label": r.label,
                    "paper_key": r.paper_key,
                    "set": list(r.overrides),
                    "fingerprint": r.fingerprint,
                }
                for r in self.rows
            ],
        }


def _fingerprint(problem: Problem | ImuProblem | OrientedProblem) -> str:
    """A hash of the problem's settings other than seed and names. Values left at their
    defaults are left out, so a new option with a default (a schema addition) does not
    make saved runs look as if they had been solved with different settings."""
    data = problem.spec.model_dump(mode="json", exclude_defaults=True)
    for key in ("seed", "name", "description"):
        data.pop(key, None)
    text = json.dumps(data, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def parse_grid(text: str) -> tuple[str, list[str]]:
    """``key.path=v1,v2,...`` as (key, [value texts]); commas inside [] or {} do not split."""
    key_path, _ = parse_override(text.split("=", 1)[0] + "=" if "=" in text else text, "--grid")
    raw = text.split("=", 1)[1]
    values, depth, cur = [], 0, ""
    for ch in raw:
        if ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        if ch == "," and depth == 0:
            values.append(cur.strip())
            cur = ""
        else:
            cur += ch
    values.append(cur.strip())
    key = ".".join(key_path)
    if depth != 0:
        raise ProblemError("--grid", key, "unbalanced brackets in values")
    if any(not v for v in values):
        raise ProblemError("--grid", key, "empty value (expected key.path=v1,v2,...)")
    if len(set(values)) != len(values):
        raise ProblemError("--grid", key, "lists a value twice")
    for v in values:
        parse_override(f"{key}={v}", "--grid")
    return key, values


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=+-]", "_", text)


#: How a sweep loads each kind of problem file it takes (casmag.problem.spec.document_kind).
LOADERS: dict[str, Callable[..., Any]] = {
    "translational": load_problem,
    "imu": load_imu_problem,
    "oriented": load_oriented_problem,
}


def _resolve(
    base: dict[str, Any], base_source: str, origins: list[tuple[str, str, str]], kind: str
) -> Problem | ImuProblem | OrientedProblem:
    """Validate the problem file with overrides given as (source, where, "key=value");
    an error in an overridden key names the override's source (table file row, --set, --grid)
    instead of the problem file."""
    try:
        return LOADERS[kind](base, [text for _, _, text in origins], source=base_source)
    except ProblemError as exc:
        for source, where, text in reversed(origins):
            key = text.split("=", 1)[0].strip()
            if exc.field and (exc.field == key or exc.field.startswith(key + ".")):
                at = f"{where}: {exc.field}" if where else exc.field
                raise ProblemError(source, at, exc.reason) from None
        raise


def load_sweep(
    path: str | Path,
    out_dir: str | Path,
    seeds: int = 20,
    first_seed: int | None = None,
    grid: str | Sequence[str] = (),
    overrides: str | Sequence[str] = (),
) -> SweepPlan:
    """Plan a sweep from a problem file or a table file (one with ``rows``).

    seeds: number of seeds per row, from ``first_seed`` (default: the problem's seed).
    grid: ``key.path=v1,v2`` strings; every combination is a row (times the table's rows).
    overrides: ``key.path=value`` for every run, applied before the grid.
    Raises ProblemError naming the file (or option), the field and the reason.
    """
    path = Path(path)
    grid, overrides = as_overrides(grid), as_overrides(overrides)
    data = read_yaml(path)
    src = str(path)
    grids = [parse_grid(g) for g in grid]
    if len({k for k, _ in grids}) != len(grids):
        raise ProblemError("--grid", "", "a key is given twice")
    if seeds < 1:
        raise ProblemError("--seeds", "", "must be at least 1")

    paper = None
    if "rows" in data:
        try:
            table = TableSpec.model_validate(data)
        except ValidationError as err:
            raise validation_error(src, err, TableSpec) from None
        keys = [r.key for r in table.rows]
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ProblemError(src, "rows", f"row key {dup[0]!r} is used twice")
        if table.paper is not None:
            if table.paper not in TABLES:
                raise ProblemError(
                    src, "paper", f"{table.paper!r} is not a paper table ({', '.join(TABLES)})"
                )
            paper = TABLES[table.paper]
            for i, r in enumerate(table.rows):
                ref = r.key if r.paper_row is None else r.paper_row
                if ref not in paper.keys:
                    raise ProblemError(
                        src,
                        f"rows.{i}.{'key' if r.paper_row is None else 'paper_row'}",
                        f"{ref!r} is not a row of the paper's Table {paper.number} "
                        f"({', '.join(paper.keys)})",
                    )
        elif any(r.paper_row is not None for r in table.rows):
            i = next(i for i, r in enumerate(table.rows) if r.paper_row is not None)
            raise ProblemError(src, f"rows.{i}.paper_row", "needs the table's 'paper'")
        problem_path = (path.parent / table.problem).resolve()
        try:
            shown = problem_path.relative_to(Path.cwd())
        except ValueError:
            shown = problem_path
        if not problem_path.is_file():
            raise ProblemError(src, "problem", f"no such file {table.problem!r}")
        base = read_yaml(problem_path)
        common = [(src, "set", t) for t in as_overrides(table.set)]
        rows = [
            (
                r.key,
                r.label or (paper.row(r.paper_row or r.key).label if paper else r.key),
                (r.paper_row or r.key) if paper else None,
                [*common, *[(src, f"rows.{i}.set", t) for t in as_overrides(r.set)]],
            )
            for i, r in enumerate(table.rows)
        ]
        name = table.name or path.stem
        title = table.title or (paper.caption if paper else None)
        base_source, problem_file = str(shown), str(shown)
    else:
        base = data
        rows = [(None, None, None, [])]
        # The problem's name when it gives one (its folder under --out with several files).
        given = data.get("name")
        name = _slug(given) if isinstance(given, str) and given.strip() else path.stem
        title, base_source, problem_file = None, src, src

    kind = document_kind(base)
    if kind not in LOADERS:
        raise ProblemError(
            problem_file,
            "",
            f"a {kind} problem file cannot be swept over seeds (a sweep takes "
            f"{' or '.join(LOADERS)} problem files)",
        )
    cli = [("--set", "", t) for t in overrides]
    plans: list[RowPlan] = []
    combos = list(itertools.product(*[[(k, v) for v in vals] for k, vals in grids]))
    for (key, label, paper_key, row_origins), combo in itertools.product(rows, combos):
        grid_origins = [("--grid", "", f"{k}={v}") for k, v in combo]
        problem = _resolve(base, base_source, [*row_origins, *cli, *grid_origins], kind)
        grid_key = "+".join(_slug(f"{k}={v}") for k, v in combo)
        full_key = "__".join(p for p in (key, grid_key) if p) or _slug(problem.name)
        grid_label = ", ".join(f"{k} = {v}" for k, v in combo)
        full_label = ", ".join(p for p in (label, grid_label) if p) or problem.name
        spec = problem.spec.model_dump(mode="json")
        spec["name"] = f"{name}: {full_label}"
        plans.append(
            RowPlan(
                key=full_key,
                label=full_label,
                paper_key=paper_key,
                overrides=tuple(t for _, _, t in [*row_origins, *cli, *grid_origins]),
                fingerprint=_fingerprint(problem),
                problem=spec,
            )
        )
    row_keys = [p.key for p in plans]
    if len(set(row_keys)) != len(row_keys):
        raise ProblemError("--grid", "", "two grid values give the same folder name")
    first = plans[0].problem["seed"] if first_seed is None else first_seed
    return SweepPlan(
        name=name,
        title=title,
        paper=None if paper is None else paper.id,
        source=src,
        problem_file=problem_file,
        rows=plans,
        seeds=list(range(first, first + seeds)),
        out_dir=Path(out_dir),
        kind=kind,
    )


# --------------------------------------------------------------------------- manifest
def _write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(json.dumps(data, indent=2) + "\n")
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def read_manifest(path: Path) -> dict[str, Any]:
    """A sweep.json, checked for the fields the report needs."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: cannot read sweep manifest ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
        raise DataError(f"{path}: format: expected {MANIFEST_FORMAT!r}")
    for key in ("name", "seeds", "rows"):
        if key not in data:
            raise DataError(f"{path}: {key}: required field is missing")
    for i, row in enumerate(data["rows"]):
        for key in ("key", "label"):
            if not isinstance(row, dict) or key not in row:
                raise DataError(f"{path}: rows.{i}.{key}: required field is missing")
    return data


def prepare(plan: SweepPlan, rerun: bool = False) -> list[int]:
    """Check an existing sweep folder against the plan and write the merged manifest.

    Returns the seeds the manifest now lists (earlier seeds are kept, so a shorter rerun
    does not hide results). A row whose settings changed since its runs were saved is an
    error unless ``rerun``.
    """
    path = plan.out_dir / MANIFEST
    seeds = list(plan.seeds)
    if path.exists() and not rerun:
        old = read_manifest(path)
        old_rows = {r["key"]: r for r in old["rows"]}
        for row in plan.rows:
            prev = old_rows.get(row.key)
            has_runs = (plan.out_dir / row.key).is_dir()
            if prev is not None and has_runs and prev.get("fingerprint") != row.fingerprint:
                raise ProblemError(
                    str(path),
                    f"rows.{row.key}",
                    "was solved with different settings; use another --out or --rerun",
                )
        seeds = sorted(set(seeds) | {int(s) for s in old["seeds"]})
    manifest = plan.manifest()
    manifest["seeds"] = seeds
    _write_json_atomic(path, manifest)
    return seeds


# --------------------------------------------------------------------------- running
class SweepAborted(CasmagError):
    """The pool or cluster stopped before every run was done (saved runs are kept)."""


@dataclass
class RunOutcome:
    """What a run reports back: IPOPT status (or ``error``), errors [m], wall-clock seconds."""

    task: RunTask
    status: str
    success: bool
    rmse_after: float | None
    seconds: float
    error: str | None = None
    traceback: str | None = None
    result: Result | None = field(default=None, repr=False)


# Workers with several threads (a Dask worker started with --nthreads > 1) share one NLP
# cache, whose IPOPT callbacks are not re-entrant: solves in one process run one at a time.
_SOLVE_LOCK = threading.Lock()


def run_task(task: RunTask, save: bool = True) -> RunOutcome:
    """Solve one run; save it into its folder (``save``) or return the Result to the caller.

    Any exception is returned as an outcome with ``status = "error"``: one broken run must not
    stop a sweep.
    """
    t0 = time.perf_counter()
    try:
        with _SOLVE_LOCK:
            problem = LOADERS[task.kind](task.problem, source=task.source)
            result = solve(problem)  # every kind (casmag.solver.api.solve)
        interrupt.check()  # a pool worker being stopped: not saved (casmag.interrupt)
        if save:
            result.save(task.out_dir, figures=task.figures)
    except Exception as exc:  # reported per run, never raised into the pool
        return RunOutcome(
            task,
            "error",
            False,
            None,
            time.perf_counter() - t0,
            error=one_line(f"{type(exc).__name__}: {exc}"),
            traceback=traceback.format_exc(),
        )
    return RunOutcome(
        task,
        result.status,
        result.success,
        result.rmse_after,
        time.perf_counter() - t0,
        result=None if save else result,
    )


def _run_unsaved(task: RunTask) -> RunOutcome:
    return run_task(task, save=False)


def _record(outcome: RunOutcome) -> None:
    """Save a returned Result, or write error.json for a run that raised."""
    out = Path(outcome.task.out_dir)
    if outcome.result is not None:
        outcome.result.save(out, figures=outcome.task.figures)
        outcome.result = None
    elif outcome.error is not None:
        record = {
            "seed": outcome.task.seed,
            "row": outcome.task.row,
            "error": outcome.error,
            "traceback": outcome.traceback,
        }
        # A run folder as any other (casmag.result.outdir's marker), so the retry may replace it.
        save_atomic(out, lambda d: (d / "error.json").write_text(json.dumps(record, indent=2)))


@contextlib.contextmanager
def single_threaded_environment() -> Iterator[None]:
    """Set OMP/OpenBLAS/MKL thread counts to 1 while worker processes are started (they
    read them when they import numpy), and restore the parent's values afterwards."""
    saved = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, "1"))
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def default_jobs() -> int:
    """The cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


#: Seconds between looks at a recorded Ctrl-C or SIGTERM while the pool's runs are awaited.
SIGNAL_POLL = 0.1

#: Seconds a worker has to stop after the sweep is interrupted (its solve stops at IPOPT's
#: next iteration, a save in progress completes or is undone) before it is killed.
STOP_GRACE = 5.0


def _worker_init() -> None:
    """In each pool worker: Ctrl-C (SIGINT, sent to the whole process group by a terminal)
    is left to the parent, which stops the workers with SIGTERM; SIGTERM is recorded
    (casmag.interrupt, deferred): IPOPT stops at its next iteration, the run is not saved,
    and :func:`_call` ends the worker."""
    interrupt.install(defer=True)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _call(fn: Callable[[Any], Any], item: Any) -> Any:
    """``fn(item)`` in a pool worker; an interrupted worker exits at once (it must not go
    on to a queued run)."""
    try:
        result = fn(item)
        interrupt.check()
        return result
    except Interrupted as exc:
        os._exit(exc.exit_code)


@contextlib.contextmanager
def _sigint_blocked() -> Iterator[None]:
    """Hold back SIGINT in this thread while worker processes are started, and ignore it
    there: a spawned worker inherits the ignored disposition (and then the blocked mask), so
    a Ctrl-C never interrupts its start-up with a traceback; blocked alone, a spawned
    worker started with an empty mask and Python's KeyboardInterrupt handler (measured on
    Python 3.11: a Ctrl-C while a worker unpickled its task printed a traceback). A Ctrl-C
    meanwhile stays pending here (Linux keeps a blocked signal even while ignored) and
    reaches this process's own handler, restored before the signal is unblocked."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _stop_pool(pool: Any) -> None:
    """Stop a process pool now: queued runs are cancelled, running ones are sent SIGTERM
    and killed after STOP_GRACE seconds. Further signals wait until it is done."""
    main = threading.current_thread() is threading.main_thread()
    stops = {signal.SIGINT, signal.SIGTERM}
    saved = signal.pthread_sigmask(signal.SIG_BLOCK, stops) if main else None
    try:
        procs = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            with contextlib.suppress(OSError, ValueError, AttributeError):
                p.terminate()
        deadline = time.monotonic() + STOP_GRACE
        for p in procs:
            with contextlib.suppress(OSError, ValueError, AttributeError, AssertionError):
                p.join(max(0.0, deadline - time.monotonic()))
        for p in procs:
            with contextlib.suppress(OSError, ValueError, AttributeError, AssertionError):
                if p.is_alive():
                    p.kill()
                    p.join(1.0)
    finally:
        if saved is not None:
            # Signals that arrived meanwhile are dropped: the sweep is stopping already.
            for sig in signal.sigpending() & stops:
                previous = signal.signal(sig, signal.SIG_IGN)
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {sig})
                signal.signal(sig, previous)
            signal.pthread_sigmask(signal.SIG_SETMASK, saved)


def local_map(
    fn: Callable[[Any], Any], items: Sequence[Any], jobs: int, on_done: Callable[[Any], None]
) -> None:
    """Call ``fn`` on every item in a pool of ``jobs`` spawned, single-threaded processes and
    hand each return value to ``on_done`` as it arrives (in completion order). An exception
    or a signal (Ctrl-C, SIGTERM) in the caller stops the pool at once (:func:`_stop_pool`)
    and is raised; what ``on_done`` has been given is kept."""
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    if not items:
        return
    ctx = multiprocessing.get_context("spawn")
    pool = None
    try:
        # A signal is recorded and raised between waits, never inside concurrent.futures,
        # where it can leave a future's lock held and the exit hanging (casmag.interrupt).
        with interrupt.deferred():
            with single_threaded_environment(), _sigint_blocked():
                pool = ProcessPoolExecutor(
                    max_workers=min(jobs, len(items)), mp_context=ctx, initializer=_worker_init
                )
                # Spawned workers start during the first submits, inside this environment.
                pending = {pool.submit(_call, fn, item) for item in items}
            while pending and not interrupt.pending():
                done, pending = wait(pending, timeout=SIGNAL_POLL, return_when=FIRST_COMPLETED)
                for fut in done:
                    on_done(fut.result())
    except BrokenProcessPool as exc:
        _stop_pool(pool)
        raise SweepAborted(f"a worker process died ({exc}); saved runs are kept") from None
    except BaseException:
        if pool is not None:
            _stop_pool(pool)
        raise
    pool.shutdown(wait=True)


def worker_environment(_: Any = None) -> dict[str, str | None]:
    """The thread-count variables as a worker process sees them (for checks)."""
    return {k: os.environ.get(k) for k in THREAD_VARIABLES}


def _distributed(tasks: list[RunTask], address: str, on_done: Callable[[RunOutcome], None]) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:  # pragma: no cover - dask is a dependency
        raise CasmagError("--scheduler: needs dask[distributed]") from None
    try:
        client = Client(address, timeout=CONNECT_TIMEOUT, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise CasmagError(one_line(f"--scheduler {address}: cannot connect ({exc})")) from None
    token = uuid.uuid4().hex[:8]
    with client:
        futures = client.map(
            _run_unsaved,
            tasks,
            pure=False,
            # Readable keys, unique per call: a shared cluster may run other sweeps.
            key=[f"casmag-{t.sweep}-{t.row}-{t.seed}-{token}" for t in tasks],
        )
        try:
            for fut in as_completed(futures, loop=client.loop):
                on_done(fut.result())
        except Exception as exc:
            client.cancel(futures)
            msg = f"--scheduler {address}: {type(exc).__name__}: {exc}; saved runs are kept"
            raise SweepAborted(one_line(msg)) from None
        except BaseException:
            client.cancel(futures)
            raise


@dataclass
class SweepSummary:
    """Counts of a sweep: runs planned, skipped (already saved), solved, failed (IPOPT did
    not succeed; status counted), errors (raised), and the wall-clock seconds."""

    planned: int = 0
    skipped: int = 0
    solved: int = 0
    failed: int = 0
    errors: int = 0
    seconds: float = 0.0
    statuses: dict[str, int] = field(default_factory=dict)
    error_messages: list[str] = field(default_factory=list)


def run_sweeps(
    plans: Sequence[SweepPlan],
    jobs: int | None = None,
    scheduler: str | None = None,
    figures: str = "first",
    rerun: bool = False,
    progress: bool = True,
) -> SweepSummary:
    """Run every plan's missing runs (all of them with ``rerun``) in one pool or cluster.

    jobs: local worker processes (default: the cores available); scheduler: a Dask
    distributed scheduler address instead. figures: PNGs per run for the ``first`` seed of
    each row, ``all`` or ``none``.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    summary = SweepSummary()
    tasks: list[RunTask] = []
    for plan in plans:
        plan.seeds = prepare(plan, rerun)
        for task in plan.tasks(figures):
            summary.planned += 1
            if not rerun and (Path(task.out_dir) / "result.json").is_file():
                summary.skipped += 1
            else:
                tasks.append(task)
    if not tasks:
        summary.seconds = time.perf_counter() - t0
        return summary
    # Seeds outermost across files too (a stable sort keeps the file and row order within a
    # seed), so that an interrupted sweep of several tables has covered every row.
    tasks.sort(key=lambda t: t.seed)
    bar = tqdm(
        total=len(tasks),
        desc=", ".join(p.name for p in plans)[:40],
        unit="run",
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
    )

    def on_done(outcome: RunOutcome) -> None:
        _record(outcome)
        if outcome.error is not None:
            summary.errors += 1
            summary.error_messages.append(
                f"{outcome.task.out_dir}: {outcome.error}".replace("\n", " ")
            )
        elif outcome.success:
            summary.solved += 1
        else:
            summary.failed += 1
            summary.statuses[outcome.status] = summary.statuses.get(outcome.status, 0) + 1
        bar.set_postfix(failed=summary.failed, errors=summary.errors, refresh=False)
        bar.update(1)

    try:
        if scheduler:
            _distributed(tasks, scheduler, on_done)
        else:
            local_map(run_task, tasks, jobs or default_jobs(), on_done)
    finally:
        bar.close()
    summary.seconds = time.perf_counter() - t0
    return summary
