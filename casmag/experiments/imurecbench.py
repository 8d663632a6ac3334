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
package versions and source is not solved again); ``imu-recordings.json`` gathers them
(with the runs saved by earlier calls for other scenarios or seeds) and
``imu-recordings.md`` is the table: position RMSE of the IMU-only adjustment and GP-SLAM
both ways, IPOPT's status, the iterations of the last solve, the wall time and the rest's
noise estimates against the simulation's values.

With ``--lag SECONDS`` (``make bench-imu-lag``) the recording's magnetometer is written
that late (row k reads the field of time t_k - lag) and solved by ``casmag slam REC`` twice
instead: as it is (``--mag-lag 0``: the lag estimated on the path solved and reported) and
with ``--mag-lag auto`` (the default: the estimated lag removed); each row has the
estimate, what was removed, GP-SLAM's RMSE and the wall time
(``runs/<scenario>-<seed>-lag<SECONDS>.json``).

With ``--mag-every K`` (``make bench-imu-mag-rate``) the recording is written twice: as
simulated, and with the magnetometer on every K-th row only (the other rows' mx, my, mz
empty: a magnetometer K times slower than the IMU, which casmag.data.recording
interpolates to the IMU's rows); both solved by ``casmag slam REC`` with its defaults
(``runs/<scenario>-<seed>-every<K>.json``).
"""

from __future__ import annotations

import argparse
import json
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from casmag.data.clock import shift_magnetometer
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


def _lag_row(r: Any, seconds: float) -> dict[str, Any]:
    m = r.info["magnetometer_lag"]
    est = m.get("estimate") or {}
    return {
        **_row(r, seconds),
        "lag_estimate": est.get("lag_seconds"),
        "lag_gain": est.get("gain"),
        "lag_significant": est.get("significant"),
        "lag_removed": m.get("removed_seconds"),
        "lag_steps": m.get("steps"),
    }


def run_lag(
    path: Path, seed: int, folder: Path, lag: float, overrides: list[str] | None = None
) -> dict[str, Any]:
    """One scenario and seed with the magnetometer written ``lag`` seconds late, solved as a
    recording with and without ``--mag-lag auto`` (module docstring)."""
    prob = load_imu_problem(path, [*(overrides or []), f"seed={seed}"])
    data = simulate_imu(prob)
    tr = data.truth
    Y = shift_magnetometer(tr.t, data.Y, -lag)  # row k: the field of time t_k - lag
    rec = folder / f"{path.stem}-{seed}-lag{lag:g}.csv"
    write_recording(rec, tr.t, Y, imu=np.hstack([data.dq, data.dv]), P_true=tr.P, q_true=tr.Q)
    out: dict[str, Any] = {"scenario": path.stem, "seed": seed, "lag": lag}
    for key, mag_lag in (("as_is", 0.0), ("auto", "auto")):
        t0 = time.perf_counter()
        r = slam(rec, mag_lag=mag_lag)
        out[key] = _lag_row(r, time.perf_counter() - t0)
    return out


def run_mag_rate(
    path: Path, seed: int, folder: Path, every: int, overrides: list[str] | None = None
) -> dict[str, Any]:
    """One scenario and seed written with the magnetometer on every row and on every
    ``every``-th row only, both solved as recordings (module docstring)."""
    prob = load_imu_problem(path, [*(overrides or []), f"seed={seed}"])
    data = simulate_imu(prob)
    tr = data.truth
    slow = np.full_like(data.Y, np.nan)
    slow[::every] = data.Y[::every]
    out: dict[str, Any] = {"scenario": path.stem, "seed": seed, "every": every}
    for key, Y in (("every_row", data.Y), ("slow", slow)):
        rec = (
            folder / f"{path.stem}-{seed}-{'every1' if key == 'every_row' else f'every{every}'}.csv"
        )
        write_recording(rec, tr.t, Y, imu=np.hstack([data.dq, data.dv]), P_true=tr.P, q_true=tr.Q)
        t0 = time.perf_counter()
        r = slam(rec)
        out[key] = {
            **_row(r, time.perf_counter() - t0),
            "sigma_m_rest": r.info["defaults"]["rest"]["sigma_m"],
        }
    out["sigma_m_true"] = prob.spec.simulation.magnetometer.noise
    return out


def mag_rate_table(runs: list[dict[str, Any]], vers: dict[str, Any]) -> str:
    def row(run: dict[str, Any]) -> str:
        a, b, true = run["every_row"], run["slow"], run["sigma_m_true"]
        return (
            f"| {run['scenario']} | {run['seed']} | {run['every']} rows "
            f"| {cell(a['rmse_imu_only'])} "
            f"| {cell(a['rmse_gp_slam'])}, {a['status']}, {cell(a['seconds'], '.0f')}, "
            f"{cell(a['sigma_m_rest'] / true, '.2f')} "
            f"| {cell(b['rmse_gp_slam'])}, {b['status']}, {cell(b['seconds'], '.0f')}, "
            f"{cell(b['sigma_m_rest'] / true, '.2f')} |"
        )

    head = (
        "| scenario | seed | magnetometer every | IMU-only RMSE | every row: GP-SLAM RMSE, "
        "status, s, sigma_m / true | slower: GP-SLAM RMSE, status, s, sigma_m / true |"
    )
    return _table(head, runs, vers, row, "every")


def cell(v: Any, fmt: str = ".3g") -> str:
    """A table cell: ``v`` formatted, ``-`` for None."""
    return "-" if v is None else format(v, fmt)


def _with_versions(lines: list[str], vers: dict[str, Any]) -> str:
    """The table's lines and the package versions under them."""
    names = ("casadi", "ipopt", "numpy", "scipy")
    lines += ["", "Versions: " + ", ".join(f"{k} {vers.get(k)}" for k in names if k in vers)]
    return "\n".join(lines) + "\n"


def _table(
    head: str,
    runs: list[dict[str, Any]],
    vers: dict[str, Any],
    row: Callable[[dict[str, Any]], str],
    third: str | None = None,
) -> str:
    """A markdown table: the header ``head``, one ``row(run)`` per run, a run that failed
    as its scenario, seed (and its ``third`` key) and error; the versions under it."""
    columns = head.count("|") - 1
    lines = [head, "|" + "---|" * columns]
    for run in runs:
        if "error" not in run:
            lines.append(row(run))
            continue
        cells = [run["scenario"], run["seed"], *([run.get(third)] if third else [])]
        cells.append(f"error: {run['error']}")
        lines.append("| " + " | ".join(map(str, cells)) + " |" + "|" * (columns - len(cells)))
    return _with_versions(lines, vers)


def lag_table(runs: list[dict[str, Any]], vers: dict[str, Any]) -> str:
    def row(run: dict[str, Any]) -> str:
        a, b = run["as_is"], run["auto"]
        return (
            f"| {run['scenario']} | {run['seed']} | {run['lag']:g} "
            f"| {cell(a['lag_estimate'], '+.2f')}, {cell(a['rmse_gp_slam'])}, {a['status']}, "
            f"{cell(a['seconds'], '.0f')} "
            f"| {cell(b['lag_removed'], '+.2f')}, {cell(b['lag_estimate'], '+.2f')}, "
            f"{cell(b['rmse_gp_slam'])}, {b['status']}, {cell(b['seconds'], '.0f')} |"
        )

    head = (
        "| scenario | seed | lag put in [s] | as it is: estimate [s], GP-SLAM RMSE, status, s "
        "| --mag-lag auto: removed [s], left [s], GP-SLAM RMSE, status, s |"
    )
    return _table(head, runs, vers, row, "lag")


def table(runs: list[dict[str, Any]], vers: dict[str, Any]) -> str:
    def row(run: dict[str, Any]) -> str:
        a, b, q = run["problem"], run["recording"], run["rest_over_truth"]
        return (
            f"| {run['scenario']} | {run['seed']} "
            f"| {cell(a['rmse_imu_only'])}, {cell(b['rmse_imu_only'])} "
            f"| {cell(a['rmse_gp_slam'])}, {a['status']}, {a['iterations']}, "
            f"{cell(a['seconds'], '.0f')} "
            f"| {cell(b['rmse_gp_slam'])}, {b['status']}, {b['iterations']}, "
            f"{cell(b['seconds'], '.0f')} "
            f"| {cell(q['gyro_noise_density'], '.2f')}, {cell(q['acc_noise_density'], '.2f')}, "
            f"{cell(q['sigma_m'], '.2f')} |"
        )

    head = (
        "| scenario | seed | IMU-only RMSE: imu, slam | casmag imu: GP-SLAM RMSE, status, it, s "
        "| casmag slam: GP-SLAM RMSE, status, it, s | rest / truth: gyro, acc, sigma_m |"
    )
    return _table(head, runs, vers, row)


def _earlier_runs(folder: Path, suffix: str, runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The runs saved in ``folder`` by earlier calls in the same mode (file names ending in
    ``suffix``: ``-lag<S>``, ``-every<K>``, or neither) whose scenario and seed this call did
    not run: the tables keep their rows, as ``make bench-real``'s do."""
    done = {(r["scenario"], r["seed"]) for r in runs}
    out = []
    for f in sorted(folder.glob(f"*{suffix}.json")):
        if not suffix and ("-lag" in f.stem or "-every" in f.stem):
            continue
        run = json.loads(f.read_text(encoding="utf-8"))
        if (run.get("scenario"), run.get("seed")) not in done:
            out.append(run)
    return out


def _order(run: dict[str, Any]) -> tuple[str, int]:
    return run["scenario"], run["seed"]


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
    ap.add_argument(
        "--lag",
        type=float,
        default=None,
        help="write the magnetometer this many seconds late and solve the recording with "
        "and without --mag-lag auto",
    )
    ap.add_argument(
        "--mag-every",
        type=int,
        default=None,
        help="also write the magnetometer on every K-th row only and solve both recordings",
    )
    args = ap.parse_args(argv)
    if args.lag is not None and args.mag_every is not None:
        ap.error("--lag and --mag-every: one at a time")
    vers = versions()
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    (args.out / "recordings").mkdir(parents=True, exist_ok=True)
    suffix = "" if args.lag is None else f"-lag{args.lag:g}"
    if args.mag_every is not None:
        suffix = f"-every{args.mag_every}"
    runs = []
    for path in args.problems:
        for seed in range(1, args.seeds + 1):
            stem = f"{path.stem}-{seed}{suffix}"
            saved = args.out / "runs" / f"{stem}.json"
            key = {"versions": vers, "source": source_digest(path), "overrides": args.overrides}
            if saved.exists():
                old = json.loads(saved.read_text(encoding="utf-8"))
                if {k: old.get(k) for k in key} == key:
                    runs.append(old)
                    continue
            try:
                folder = args.out / "recordings"
                if args.mag_every is not None:
                    run = run_mag_rate(path, seed, folder, args.mag_every, args.overrides)
                elif args.lag is None:
                    run = run_one(path, seed, folder, args.overrides)
                else:
                    run = run_lag(path, seed, folder, args.lag, args.overrides)
            except Exception as exc:  # a failed run is a row of the table, not the end
                traceback.print_exc()
                run = {"scenario": path.stem, "seed": seed, "lag": args.lag}
                run["error"] = f"{type(exc).__name__}: {exc}"
            run.update(key)
            write_text_atomic(saved, json.dumps(run, indent=2))
            runs.append(run)
            print(f"{path.stem} seed {seed}: done", flush=True)
    runs = sorted([*runs, *_earlier_runs(args.out / "runs", suffix, runs)], key=_order)
    name = "imu-recordings" if args.lag is None else f"imu-lag{args.lag:g}"
    if args.mag_every is not None:
        name = f"imu-mag-every{args.mag_every}"
    write_text_atomic(
        args.out / f"{name}.json", json.dumps({"runs": runs, "versions": vers}, indent=2)
    )
    head = f"Problem files with {', '.join(args.overrides)}.\n\n" if args.overrides else ""
    if args.mag_every is not None:
        body = mag_rate_table(runs, vers)
    else:
        body = table(runs, vers) if args.lag is None else lag_table(runs, vers)
    write_text_atomic(args.out / f"{name}.md", head + body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
