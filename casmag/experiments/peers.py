"""The MAP against the filter baseline over seeds (``make bench-peers``, ``make
bench-peers-pose``).

Each seed of a problem file (default problems/bench/peers.yaml: the filter publications'
setting) is simulated, with translational odometry or (``--motion pose``) as pose
odometry (casmag.data.posesim: heading along the path, a roll and pitch wobble, body-frame
increments with the publications' noise, 3 mm per step and 3 mrad per step, and a
displacement bias of 3 mm per step on each body axis), written as a recording, and solved by
``casmag slam``'s two methods on it, each with its defaults estimated from the data: the
MAP (``map``) and the EKF with the same map in its state (``ekf``, casmag.solver.ekf). Each
is timed whole. Writes OUT/peers.json (one row per seed, the versions, the summary) and
OUT/peers.md; the summary counts the seeds where the MAP's RMSE is at most half the
filter's and where it is worse than the filter's by more than 10 %::

    python -m casmag.experiments.peers [FILE] --seeds 20 --out results/bench/peers
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from casmag.data.posesim import simulate_pose
from casmag.data.recording import dataset_to_recording_arrays, write_recording
from casmag.data.simulate import simulate_problem
from casmag.problem.spec import load_problem
from casmag.result.outdir import write_text_atomic
from casmag.solver.recslam import slam
from casmag.versions import versions

DEFAULT_FILE = Path(__file__).resolve().parents[2] / "problems" / "bench" / "peers.yaml"
#: The issue's criteria: the MAP at most HALF the filter's RMSE, never WORSE x it.
HALF, WORSE = 0.5, 1.1


#: The pose-odometry bench's displacement bias [m per step] on each body axis and its
#: rotation noise [rad per step per axis] (the publications' setting).
POSE_BIAS, POSE_ROTATION_NOISE = (3e-3, 3e-3, 3e-3), 3e-3


def run_seed(
    path: Path,
    seed: int,
    rate_hz: float = 2.0,
    overrides: tuple[str, ...] = (),
    motion: str = "translational",
) -> dict[str, Any]:
    """One seed: simulate, write the recording (``rate_hz`` samples per second), solve it
    with both methods. ``overrides``: ``key=value`` settings of the problem file;
    ``motion``: ``translational`` or ``pose``."""
    prob = load_problem(path, [f"seed={seed}", *overrides])
    with tempfile.TemporaryDirectory(prefix="casmag-peers-") as tmp:
        rec = Path(tmp) / f"{prob.name}-{seed}.csv"
        if motion == "pose":
            sim = simulate_pose(
                prob.spec.simulation, seed, rate_hz, POSE_ROTATION_NOISE, bias_p=POSE_BIAS
            )
            write_recording(rec, **sim.recording_arrays())
            n = sim.t.shape[0]
        else:
            data = simulate_problem(prob)
            write_recording(rec, **dataset_to_recording_arrays(data, dt=1.0 / rate_hz))
            n = data.n_samples
        row: dict[str, Any] = {"seed": seed, "samples": n, "motion": motion}
        duration = (n - 1) / rate_hz
        for method in ("map", "ekf"):
            t0 = time.perf_counter()
            r = slam(rec, method=method)
            wall = time.perf_counter() - t0
            row["before"] = r.rmse_before
            row[method] = {
                "rmse": r.rmse_after,
                "max": r.max_after,
                "status": r.status,
                "trusted": r.trusted,
                "wall_seconds": wall,
                "real_time_factor": duration / wall,
            }
            if method == "ekf":
                row[method]["mean_nis"] = r.info.get("filter", {}).get("mean_nis")
            if motion == "pose":
                row[method]["attitude_rms_deg"] = r.details.get("attitude_rms_deg_after")
    return row


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians and the criteria's counts over the seeds where both methods gave an error."""
    both = [r for r in rows if r["map"]["rmse"] is not None and r["ekf"]["rmse"] is not None]
    ratios = [r["map"]["rmse"] / r["ekf"]["rmse"] for r in both]

    def med(method: str, key: str) -> float | None:
        vals = [r[method][key] for r in both if r[method][key] is not None]
        return statistics.median(vals) if vals else None

    return {
        "seeds": len(rows),
        "compared": len(both),
        "map_at_most_half_of_ekf": sum(q <= HALF for q in ratios),
        "map_worse_than_ekf_by_10pct": sum(q > WORSE for q in ratios),
        "median_ratio_map_over_ekf": statistics.median(ratios) if ratios else None,
        "median_before": statistics.median(r["before"] for r in both) if both else None,
        "median_rmse": {m: med(m, "rmse") for m in ("map", "ekf")},
        "median_wall_seconds": {m: med(m, "wall_seconds") for m in ("map", "ekf")},
        "trusted": {m: sum(bool(r[m]["trusted"]) for r in rows) for m in ("map", "ekf")},
    }


def markdown(rows: list[dict[str, Any]], s: dict[str, Any], source: str) -> str:
    lines = [
        f"### The MAP and the filter baseline on {source}",
        "",
        "| seed | RMSE before [m] | MAP RMSE [m] | EKF RMSE [m] | MAP / EKF | MAP wall [s] | "
        "EKF wall [s] | EKF mean NIS | trusted (MAP, EKF) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def f(v: Any, fmt: str = ".4f") -> str:
        return "-" if v is None else format(v, fmt)

    for r in rows:
        m, e = r["map"], r["ekf"]
        ratio = None if m["rmse"] is None or e["rmse"] is None else m["rmse"] / e["rmse"]
        lines.append(
            f"| {r['seed']} | {f(r['before'])} | {f(m['rmse'])} | {f(e['rmse'])} | "
            f"{f(ratio, '.2f')} | {f(m['wall_seconds'], '.1f')} | {f(e['wall_seconds'], '.1f')} "
            f"| {f(e.get('mean_nis'), '.2f')} | {'yes' if m['trusted'] else 'NO'}, "
            f"{'yes' if e['trusted'] else 'NO'} |"
        )
    lines += [
        "",
        f"{s['compared']} seeds: the MAP's RMSE is at most half the filter's on "
        f"{s['map_at_most_half_of_ekf']}, worse than the filter's by more than 10 % on "
        f"{s['map_worse_than_ekf_by_10pct']}; median MAP / EKF "
        f"{f(s['median_ratio_map_over_ekf'], '.2f')}; median wall "
        f"{f(s['median_wall_seconds']['map'], '.1f')} s (MAP) and "
        f"{f(s['median_wall_seconds']['ekf'], '.1f')} s (EKF).",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m casmag.experiments.peers")
    ap.add_argument("file", nargs="?", type=Path, default=DEFAULT_FILE)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--out", type=Path, default=Path("results/bench/peers"))
    ap.add_argument("--motion", choices=("translational", "pose"), default="translational")
    args = ap.parse_args(argv)
    rows = []
    for seed in range(1, args.seeds + 1):
        rows.append(run_seed(args.file, seed, motion=args.motion))
        r = rows[-1]
        print(
            f"seed {seed}: before {r['before']:.3f} m, MAP {r['map']['rmse']}, "
            f"EKF {r['ekf']['rmse']}",
            flush=True,
        )
    s = summary(rows)
    source = f"{args.file} ({args.motion} odometry)"
    record = {
        "file": str(args.file), "motion": args.motion, "rows": rows, "summary": s,
        "versions": versions(),
    }  # fmt: skip
    write_text_atomic(args.out / "peers.json", json.dumps(record, indent=2) + "\n")
    write_text_atomic(args.out / "peers.md", markdown(rows, s, source))
    print(markdown(rows, s, source))
    return 0


if __name__ == "__main__":
    sys.exit(main())
