"""Is a table row's error the model's or the optimiser's? Solve every (row, seed) of a table
file twice: from the dead reckoning (as the sweep does) and from the true trajectory, and
compare the MAP costs and errors.

When both starts end at the same cost, the error is that of the row's MAP estimate itself
(for a row with wrong fixed hyperparameters: of the misspecified model), and no optimiser can
do better on that model. When the truth start ends at a lower cost, the sweep's solve missed
the global optimum. When it ends at a higher cost (a local optimum next to the truth), the
model prefers a trajectory farther from the truth than the truth itself.

    python -m casmag.experiments.truthstart problems/paper/table2.yaml problems/paper/table4.yaml \
        --seeds 20 --out results/paper/truth_start

writes ``truth_start.json`` (every run) and ``truth_start.md`` (per row) into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from casmag.data.simulate import simulate_problem
from casmag.errors import CasmagError
from casmag.experiments.sweep import default_jobs, load_sweep, local_map
from casmag.problem.spec import load_problem
from casmag.result.metrics import rmse_and_max
from casmag.solver.translational import solve_translational

#: Relative cost difference under which two solves count as the same optimum.
SAME_COST = 1e-6


def solve_both(problem: dict[str, Any]) -> dict[str, Any]:
    """The two solves of one run: MAP cost, RMSE, iterations and status from each start."""
    prob = load_problem(problem)
    data = simulate_problem(prob)
    out: dict[str, Any] = {
        "seed": prob.spec.seed,
        "rmse_before": rmse_and_max(data.dead_reckoning(), data.P_true)[0],
    }
    for name, init in (("dead_reckoning", None), ("truth", data.P_true)):
        t0 = time.perf_counter()
        sol, *_ = solve_translational(prob, data, initial_positions=init)
        out[name] = {
            "cost": sol.objective,
            "rmse": rmse_and_max(sol.x["P"], data.P_true)[0],
            "iterations": sol.iterations,
            "status": sol.status,
            "success": sol.success,
            "seconds": time.perf_counter() - t0,
        }
    return out


def _task(item: tuple[str, str, dict[str, Any]]) -> tuple[str, str, dict[str, Any]]:
    table, row, problem = item
    return table, row, solve_both(problem)


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-row counts: same optimum, truth start lower, truth start higher; mean RMSEs."""
    ok = [r for r in runs if r["dead_reckoning"]["success"] and r["truth"]["success"]]
    same = lower = higher = 0
    for r in ok:
        a, b = r["dead_reckoning"]["cost"], r["truth"]["cost"]
        tol = SAME_COST * max(1.0, abs(a), abs(b))
        if abs(a - b) <= tol:
            same += 1
        elif b < a:
            lower += 1
        else:
            higher += 1
    mean = lambda key: float(np.mean([r[key]["rmse"] for r in ok])) if ok else None  # noqa: E731
    return {
        "runs": len(runs),
        "both_solved": len(ok),
        "same_optimum": same,
        "truth_start_lower_cost": lower,
        "truth_start_higher_cost": higher,
        "rmse_dead_reckoning_start": mean("dead_reckoning"),
        "rmse_truth_start": mean("truth"),
    }


def markdown(rows: list[dict[str, Any]]) -> str:
    head = (
        "| table | row | runs | same optimum | truth start lower cost | truth start higher "
        "cost | RMSE after, dead-reckoning start [m] | RMSE after, truth start [m] |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    fmt = lambda v: "-" if v is None else f"{v:.4f}"  # noqa: E731
    lines = [
        f"| {r['table']} | {r['row']} | {r['runs']} | {r['same_optimum']} | "
        f"{r['truth_start_lower_cost']} | {r['truth_start_higher_cost']} | "
        f"{fmt(r['rmse_dead_reckoning_start'])} | {fmt(r['rmse_truth_start'])} |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:

    ap = argparse.ArgumentParser(
        prog="python -m casmag.experiments.truthstart", description=__doc__
    )
    ap.add_argument("tables", nargs="+", type=Path, help="table files (problems/paper/*.yaml)")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--rows", default=None, help="comma-separated row keys (default: all)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("-j", "--jobs", type=int, default=default_jobs())
    args = ap.parse_args(argv)
    items: list[tuple[str, str, dict[str, Any]]] = []
    keys = None if args.rows is None else set(args.rows.split(","))
    try:
        for path in args.tables:
            plan = load_sweep(path, args.out / "unused", seeds=args.seeds)
            for task in plan.tasks(figures="none"):
                if keys is None or task.row in keys:
                    items.append((plan.name, task.row, task.problem))
    except CasmagError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    results: dict[tuple[str, str], list[dict[str, Any]]] = {}
    t0 = time.perf_counter()

    def done(out: tuple[str, str, dict[str, Any]]) -> None:
        table, row, run = out
        results.setdefault((table, row), []).append(run)
        n = sum(len(v) for v in results.values())
        print(f"\r{n}/{len(items)} runs", end="", file=sys.stderr, flush=True)

    local_map(_task, items, args.jobs, done)
    print(file=sys.stderr)
    order = list(dict.fromkeys((t, r) for t, r, _ in items))
    rows = [{"table": t, "row": r, **summarise(results[(t, r)])} for t, r in order]
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {
        "seconds": time.perf_counter() - t0,
        "jobs": args.jobs,
        "same_cost_tolerance": SAME_COST,
        "rows": rows,
        "runs": {f"{t}/{r}": sorted(v, key=lambda x: x["seed"]) for (t, r), v in results.items()},
    }
    _write_atomic(args.out / "truth_start.json", json.dumps(doc, indent=2) + "\n")
    _write_atomic(args.out / "truth_start.md", markdown(rows))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
