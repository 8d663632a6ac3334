"""``make bench-imu-recordings``: the IMU scenarios as recordings, solved by ``casmag slam``
with its defaults beside ``casmag imu`` on the problem file.

    python -m casmag.experiments.imurecbench problems/imu/*.yaml --seeds 3 \\
        --out results/bench/imu-recordings

For each scenario file and seed 1..SEEDS the simulated data are written as an IMU recording
(``recordings/<scenario>-<seed>.csv``: the increments, the magnetometer and the true pose)
and solved twice, one after the other in this process (``--set KEY=VALUE``: settings of
every problem file, e.g. another IMU or rate, which the simulation takes and the
recording's solve must find for itself):

- ``problem``: the problem file as ``casmag imu`` solves it, with the simulation's true
  noise and bias random walks;
- ``recording``: the recording as ``casmag slam REC`` solves it with no problem file: the
  noise estimated from the rest at the start, constant biases, the recording defaults
  (casmag.problem.imu.ImuRecordingSpec).

Each run is saved as ``runs/<scenario>-<seed>.json`` (resumable: a run saved with the same
package versions and source is not solved again); ``imu-recordings.json`` gathers them and
``imu-recordings.md`` is the table: position RMSE of the IMU-only adjustment and GP-SLAM
both ways, IPOPT's status, the iterations of the last solve, the wall time and the rest's
noise estimates against the simulation's values.
"""

from __future__ import annotations

import argparse
import json
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from casmag.data.imusim import simulate_imu
from casmag.data.recording import write_recording
from casmag.experiments.imubench import source_digest
from casmag.problem.imu import load_imu_problem
from casmag.result.outdir import write_text_atomic
from casmag.solver.imu import solve_imu
from casmag.solver.recslam import slam
from casmag.versions import versions


def _row(r: Any, seconds: float) -> dict[str, Any]:
    return {
        "status": r.status,
        "success": bool(r.success),
        "rmse_imu_only": r.rmse_before,
        "rmse_gp_slam": r.rmse_after,
        "iterations": r.iterations,
        "seconds": seconds,
        "map_decision": r.details.get("map_decision"),
        "flags": [f.get("name") for f in r.flags or []],
    }


def run_one(
    path: Path, seed: int, folder: Path, overrides: list[str] | None = None
) -> dict[str, Any]:
    """One scenario and seed, solved as a problem file and as a recording (module
    docstring); ``overrides``: ``key=value`` settings of the problem file (another IMU,
    rate or field; the recording's solve takes none of them)."""
    prob = load_imu_problem(path, [*(overrides or []), f"seed={seed}"])
    data = simulate_imu(prob)
    truth = data.truth
    rec = folder / f"{path.stem}-{seed}.csv"
    write_recording(
        rec, truth.t, data.Y, imu=np.hstack([data.dq, data.dv]), P_true=truth.P, q_true=truth.Q
    )
    out: dict[str, Any] = {"scenario": path.stem, "seed": seed}
    t0 = time.perf_counter()
    out["problem"] = _row(solve_imu(prob, data), time.perf_counter() - t0)
    t0 = time.perf_counter()
    r = slam(rec)
    out["recording"] = _row(r, time.perf_counter() - t0)
    sim = prob.spec.simulation
    rest = r.info["defaults"]["rest"]
    out["rest"] = rest
    out["rest_over_truth"] = {
        "gyro_noise_density": rest["gyro_noise_density"] / sim.imu.gyro_noise_density,
        "acc_noise_density": rest["acc_noise_density"] / sim.imu.acc_noise_density,
        "sigma_m": rest["sigma_m"] / sim.magnetometer.noise,
    }
    return out


def table(runs: list[dict[str, Any]], vers: dict[str, Any]) -> str:
    def f(v: Any, fmt: str = ".3g") -> str:
        return "-" if v is None else format(v, fmt)

    lines = [
        "| scenario | seed | IMU-only RMSE: imu, slam | casmag imu: GP-SLAM RMSE, status, it, s "
        "| casmag slam: GP-SLAM RMSE, status, it, s | rest / truth: gyro, acc, sigma_m |",
        "|---|---|---|---|---|---|",
    ]
    for run in runs:
        if "error" in run:
            lines.append(f"| {run['scenario']} | {run['seed']} | error: {run['error']} |||||")
            continue
        a, b, q = run["problem"], run["recording"], run["rest_over_truth"]
        lines.append(
            f"| {run['scenario']} | {run['seed']} "
            f"| {f(a['rmse_imu_only'])}, {f(b['rmse_imu_only'])} "
            f"| {f(a['rmse_gp_slam'])}, {a['status']}, {a['iterations']}, {f(a['seconds'], '.0f')} "
            f"| {f(b['rmse_gp_slam'])}, {b['status']}, {b['iterations']}, {f(b['seconds'], '.0f')} "
            f"| {f(q['gyro_noise_density'], '.2f')}, {f(q['acc_noise_density'], '.2f')}, "
            f"{f(q['sigma_m'], '.2f')} |"
        )
    names = ("casadi", "ipopt", "numpy", "scipy")
    lines += ["", "Versions: " + ", ".join(f"{k} {vers.get(k)}" for k in names if k in vers)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("problems", nargs="+", type=Path)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("results/bench/imu-recordings"))
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        help="KEY=VALUE for every problem file (e.g. simulation.imu.rate=200)",
    )
    args = ap.parse_args(argv)
    vers = versions()
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    (args.out / "recordings").mkdir(parents=True, exist_ok=True)
    runs = []
    for path in args.problems:
        for seed in range(1, args.seeds + 1):
            saved = args.out / "runs" / f"{path.stem}-{seed}.json"
            key = {"versions": vers, "source": source_digest(path), "overrides": args.overrides}
            if saved.exists():
                old = json.loads(saved.read_text(encoding="utf-8"))
                if {k: old.get(k) for k in key} == key:
                    runs.append(old)
                    continue
            try:
                run = run_one(path, seed, args.out / "recordings", args.overrides)
            except Exception as exc:  # a failed run is a row of the table, not the end
                traceback.print_exc()
                run = {"scenario": path.stem, "seed": seed, "error": f"{type(exc).__name__}: {exc}"}
            run.update(key)
            write_text_atomic(saved, json.dumps(run, indent=2))
            runs.append(run)
            print(f"{path.stem} seed {seed}: done", flush=True)
    write_text_atomic(
        args.out / "imu-recordings.json", json.dumps({"runs": runs, "versions": vers}, indent=2)
    )
    head = f"Problem files with {', '.join(args.overrides)}.\n\n" if args.overrides else ""
    write_text_atomic(args.out / "imu-recordings.md", head + table(runs, vers))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
