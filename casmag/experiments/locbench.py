"""Map once, locate later, for the models whose magnetometer turns with the body: a planar
or pose walk (problems/planar/walk.yaml, problems/pose/walk.yaml) is mapped, and a later
recording of the same path and field, with another odometry bias and noise and new
magnetometer noise, is (a) solved from scratch, (b) located against the saved map (which
it updates: casmag slam REC --map MAP), (c) located against the map held (``--hold-map``),
(d) solved together with the first as two sessions of one map, the accuracy a joint solve
reaches.

    python -m casmag.experiments.locbench --seeds 5 --out results/bench/localise

writes ``localise.json`` (every run) and ``localise.md`` (per model: the medians, and a row
per seed) into --out; ``--form tiled`` maps and locates on the tiled map
(``model.gp.form=tiled`` in every run) and writes ``localise-tiled.json`` and
``localise-tiled.md``. Runs one after the other in this process (timings are wall-clock
seconds of each call, the NLP builds included).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from casmag import strapdown as sd
from casmag.data.recording import Recording
from casmag.problem.imu import load_planar_options
from casmag.problem.oriented import load_oriented_problem
from casmag.problem.pose import load_pose_options
from casmag.result import Result
from casmag.result.outdir import write_text_atomic
from casmag.solver.oriented import simulate_oriented, slam_oriented
from casmag.solver.planar import solve_planar_sessions
from casmag.solver.pose import solve_pose_sessions

ROOT = Path(__file__).resolve().parents[2]

#: The later recording's odometry errors: displacement bias per step [m] (body frame),
#: heading-rate bias [rad/s], noise per step [m] and [rad], magnetometer noise added [uT].
LATER = {"bias_p": (-0.002, 0.003), "bias_w": -3e-3, "noise_p": 3e-3, "noise_w": 2e-3, "mag": 0.05}


def later_recording(rec: Recording, seed: int) -> Recording:
    """The same path and field as ``rec``: its odometry with :data:`LATER`'s errors added
    (so the biases are the sum of both), its magnetometer with fresh noise added (seeded
    by ``seed``)."""
    rng = np.random.default_rng([seed, 99])
    h = np.diff(rec.t)
    U = np.array(rec.increments, dtype=float)
    k = U.shape[0]
    if rec.motion == "planar":
        U[:, :2] += LATER["bias_p"] + LATER["noise_p"] * rng.standard_normal((k, 2))
        U[:, 2] += LATER["bias_w"] * h + LATER["noise_w"] * rng.standard_normal(k)
    else:  # pose: dp in the body frame, dq turned by the rate bias about the body z axis
        U[:, :2] += LATER["bias_p"]
        U[:, :3] += LATER["noise_p"] * rng.standard_normal((k, 3))
        rate = np.zeros((k, 3))
        rate[:, 2] = LATER["bias_w"] * h + LATER["noise_w"] * rng.standard_normal(k)
        U[:, 3:] = sd.quat_mul(U[:, 3:], sd.quat_exp(rate))
    Y = rec.Y + LATER["mag"] * rng.standard_normal(rec.Y.shape)
    return dataclasses.replace(rec, increments=U, Y=Y, path=f"{Path(rec.path).stem}-later")


def _timed(call: Any) -> tuple[Any, float]:
    t0 = time.perf_counter()
    out = call()
    return out, time.perf_counter() - t0


def _row(result: Result, seconds: float) -> dict[str, Any]:
    u = result.uncertainty or {}
    return {
        "status": result.status,
        "rmse_before": result.rmse_before,
        "rmse_after": result.rmse_after,
        "iterations": result.iterations,
        "seconds": seconds,
        "nees_mean": u.get("nees_mean"),
        "flags": [f["name"] for f in result.flags],
    }


def run(motion: str, seed: int, form: str = "auto") -> dict[str, Any]:
    """One seed of one model: the map run, and the later recording three ways; ``form``:
    ``model.gp.form`` of every run (``auto``: the problem file's)."""
    sets = [f"seed={seed}", *([] if form == "auto" else [f"model.gp.form={form}"])]
    problem = load_oriented_problem(ROOT / f"problems/{motion}/walk.yaml", sets)
    rec, _ = simulate_oriented(problem)
    later = later_recording(rec, seed)
    first, t_first = _timed(lambda: slam_oriented(rec, problem.sections))
    saved = first.saved_map()
    out: dict[str, Any] = {
        "motion": motion, "seed": seed, "samples": int(rec.t.size), "form": form,
    }  # fmt: skip
    out["map_run"] = {**_row(first, t_first), "map": first.info["map"]}
    scratch, t = _timed(lambda: slam_oriented(later, problem.sections))
    out["scratch"] = _row(scratch, t)
    if saved is not None:
        loc, t = _timed(
            lambda: slam_oriented(later, problem.sections, saved=saved, map_source="map")
        )
        out["located"] = {**_row(loc, t), "covered": loc.info["localisation"]["covered"]}
        P = loc.arrays["P_estimate"][:, : saved.dim]
        updated = loc.saved_map()
        if updated is not None:
            out["located"]["map_std_ratio"] = float(updated.std(P).mean() / saved.std(P).mean())
        held, t = _timed(
            lambda: slam_oriented(
                later, problem.sections, saved=saved, map_source="map", hold_map=True
            )
        )
        out["held"] = {**_row(held, t), "covered": held.info["localisation"]["covered"]}
    load = load_planar_options if motion == "planar" else load_pose_options
    sessions = solve_planar_sessions if motion == "planar" else solve_pose_sessions
    joint, t = _timed(lambda: sessions([rec, later], load(problem.sections, sets[1:])))
    row = next(s for s in joint.info["sessions"] if s["name"] == later.path)
    out["joint"] = {"status": joint.status, "rmse_after": row["rmse_after"], "seconds": t}
    return out


def _median(runs: list[dict[str, Any]], key: str, field: str) -> float | None:
    vals = [r[key][field] for r in runs if key in r and r[key].get(field) is not None]
    return float(np.median(vals)) if vals else None


def _f(v: Any, fmt: str = ".3f") -> str:
    return "-" if v is None else format(v, fmt)


def table(runs: list[dict[str, Any]], form: str = "auto") -> str:
    title = "# Map once, locate later (planar and pose walks)"
    lines = [title if form == "auto" else f"{title}, model.gp.form {form}", ""]
    head = (
        "| model | seed | RMSE before [m] | scratch [m] (s) | located [m] (s) | held [m] (s) "
        "| joint [m] (s) | located NEES | held NEES | map std on path, updated / saved |"
    )
    for motion in sorted({r["motion"] for r in runs}):
        rows = [r for r in runs if r["motion"] == motion]
        lines += [f"## {motion}", "", head, "|" + "---|" * 10]
        for r in rows:
            s, lo, h, j = r["scratch"], r.get("located", {}), r.get("held", {}), r["joint"]
            lines.append(
                f"| {motion} | {r['seed']} | {_f(s['rmse_before'])} | {_f(s['rmse_after'])} "
                f"({_f(s['seconds'], '.1f')}) | {_f(lo.get('rmse_after'))} "
                f"({_f(lo.get('seconds'), '.1f')}) | {_f(h.get('rmse_after'))} "
                f"({_f(h.get('seconds'), '.1f')}) | {_f(j['rmse_after'])} "
                f"({_f(j['seconds'], '.1f')}) | {_f(lo.get('nees_mean'), '.2f')} "
                f"| {_f(h.get('nees_mean'), '.2f')} | {_f(lo.get('map_std_ratio'), '.2f')} |"
            )
        keys = ("scratch", "located", "held", "joint")
        med = {k: _median(rows, k, "rmse_after") for k in keys}
        sec = {k: _median(rows, k, "seconds") for k in keys}
        lines += [
            "",
            "Medians: " + ", ".join(f"{k} {med[k]:.3f} m in {sec[k]:.1f} s" for k in med if med[k]),
            "",
        ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--motion", nargs="+", default=["planar", "pose"])
    ap.add_argument("--out", type=Path, default=ROOT / "results/bench/localise")
    ap.add_argument("--form", choices=["auto", "reduced_rank", "tiled"], default="auto")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "localise" if args.form == "auto" else f"localise-{args.form}"
    runs = []
    for motion in args.motion:
        for seed in range(1, args.seeds + 1):
            runs.append(run(motion, seed, args.form))
            r = runs[-1]
            nan = float("nan")
            print(
                f"{motion} seed {seed}: scratch {r['scratch']['rmse_after']:.3f}, located "
                f"{r.get('located', {}).get('rmse_after', nan):.3f}, held "
                f"{r.get('held', {}).get('rmse_after', nan):.3f}, joint "
                f"{r['joint']['rmse_after']:.3f} m",
                flush=True,
            )
            write_text_atomic(args.out / f"{stem}.json", json.dumps(runs, indent=2) + "\n")
    write_text_atomic(args.out / f"{stem}.md", table(runs, args.form))


if __name__ == "__main__":
    main()
