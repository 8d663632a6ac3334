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
``localise-tiled.md``. ``--motion imu`` does the same for IMU recordings of the
problems/imu scenarios (``--scenarios``; :func:`run_imu`, as recordings through
casmag.solver.imurec with its defaults) and writes ``localise-imu.json`` and
``localise-imu.md``. Runs one after the other in this process (timings are wall-clock
seconds of each call, the NLP builds included).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from casmag import strapdown as sd
from casmag.data.imusim import simulate_imu
from casmag.data.recording import Recording, read_recording, write_recording
from casmag.problem.imu import load_imu_problem, load_planar_options
from casmag.problem.oriented import load_oriented_problem
from casmag.problem.pose import load_pose_options
from casmag.result import Result
from casmag.result.outdir import write_text_atomic
from casmag.solver.imurec import slam_imu, slam_imu_sessions
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


#: The later IMU recording's biases (the scenario files': the gyroscope's [deg/s] and the
#: accelerometer's [m/s^2]); its noise is drawn from seed + LATER_IMU_SEED.
LATER_IMU = ["simulation.imu.gyro_bias=[-0.1, 0.06, -0.05]",
             "simulation.imu.acc_bias=[-0.015, 0.02, -0.025]"]  # fmt: skip
LATER_IMU_SEED = 1000


def _imu_recording(problem: Any, folder: Path, name: str) -> Recording:
    """A simulated IMU problem's data as a recording (written and read back as a user's)."""
    data = simulate_imu(problem)
    tr, path = data.truth, folder / f"{name}.csv"
    write_recording(path, tr.t, data.Y, imu=np.hstack([data.dq, data.dv]), P_true=tr.P,
                    q_true=tr.Q)  # fmt: skip
    return read_recording(path)


def run_imu(scenario: str, seed: int) -> dict[str, Any]:
    """One seed of one IMU scenario (problems/imu/SCENARIO.yaml): the recording of ``seed``
    mapped, and a later one of the same path and field (seed + :data:`LATER_IMU_SEED`, the
    biases :data:`LATER_IMU`) solved from scratch, located against the saved map (updated
    and held) and solved with the first as two sessions. Every solve is casmag.solver.imurec's
    with its defaults (noise from the rest, hyperparameters estimated, the lag searched),
    as ``casmag slam`` runs it."""
    yaml = ROOT / f"problems/imu/{scenario}.yaml"
    out: dict[str, Any] = {"motion": "imu", "scenario": scenario, "seed": seed}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        rec = _imu_recording(load_imu_problem(yaml, [f"seed={seed}"]), folder, scenario)
        later = _imu_recording(
            load_imu_problem(yaml, [f"seed={seed + LATER_IMU_SEED}", *LATER_IMU]), folder,
            f"{scenario}-later",
        )  # fmt: skip
        first, t = _timed(lambda: slam_imu(rec, mag_lag="auto"))
        out["keyframes"] = first.info["keyframes"]
        saved = first.saved_map()
        out["map_run"] = {**_row(first, t), "map": first.info["map"]}
        scratch, t = _timed(lambda: slam_imu(later, mag_lag="auto"))
        out["scratch"] = _row(scratch, t)
        if saved is not None:
            for key, hold in (("located", False), ("held", True)):
                loc, t = _timed(
                    lambda hold=hold: slam_imu(
                        later, mag_lag="auto", saved=saved, map_source="map", hold_map=hold
                    )
                )
                out[key] = {**_row(loc, t), "covered": loc.info["localisation"]["covered"]}
        joint, t = _timed(lambda: slam_imu_sessions([rec, later], mag_lag="auto"))
        row = next(r for r in joint.info["sessions"] if r["name"] == Path(later.path).stem)
    out["joint"] = {"status": joint.status, "rmse_after": row["rmse_after"], "seconds": t}
    return out


def _median(runs: list[dict[str, Any]], key: str, field: str) -> float | None:
    vals = [r[key][field] for r in runs if key in r and r[key].get(field) is not None]
    return float(np.median(vals)) if vals else None


def _f(v: Any, fmt: str = ".3f") -> str:
    return "-" if v is None else format(v, fmt)


def table(runs: list[dict[str, Any]], form: str = "auto") -> str:
    if runs and runs[0]["motion"] == "imu":
        return imu_table(runs)
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


def mm(v: float | None) -> float | None:
    """Metres in millimetres (None stays None: a failed run's RMSE)."""
    return None if v is None else 1e3 * v


def imu_table(runs: list[dict[str, Any]]) -> str:
    """The IMU rows (:func:`run_imu`): per scenario a row per seed (the mapping run's RMSE,
    the later recording's before any map and each way's after), then the medians and the
    runs that did not succeed. The IMU model gives no covariance, so no NEES."""
    lines = ["# Map once, locate later (IMU recordings)", ""]
    head = (
        "| scenario | seed | keyframes | map run [mm] | IMU-only [mm] | scratch [mm] (s) "
        "| located [mm] (s) | held [mm] (s) | joint [mm] (s) |"
    )
    for scenario in dict.fromkeys(r["scenario"] for r in runs):
        rows = [r for r in runs if r["scenario"] == scenario]
        lines += [f"## {scenario}", "", head, "|" + "---|" * 9]
        for r in rows:
            s, lo, h, j = r["scratch"], r.get("located", {}), r.get("held", {}), r["joint"]
            cells = [
                f"{_f(mm(x.get('rmse_after')), '.1f')} ({_f(x.get('seconds'), '.0f')})"
                for x in (s, lo, h, j)
            ]
            lines.append(
                f"| {scenario} | {r['seed']} | {r['keyframes']} | "
                f"{_f(mm(r['map_run']['rmse_after']), '.1f')} | "
                f"{_f(mm(s['rmse_before']), '.1f')} | " + " | ".join(cells) + " |"
            )
        keys = ("scratch", "located", "held", "joint")
        med = {k: _median(rows, k, "rmse_after") for k in keys}
        sec = {k: _median(rows, k, "seconds") for k in keys}
        lines += [
            "",
            "Medians: "
            + ", ".join(f"{k} {1e3 * med[k]:.1f} mm in {sec[k]:.0f} s" for k in med if med[k]),
            "",
            "Not successful: "
            + (
                ", ".join(
                    f"seed {r['seed']} {k} ({r[k]['status']})"
                    for r in rows
                    for k in keys
                    if k in r and r[k]["status"] != "Solve_Succeeded"
                )
                or "none"
            ),
            "",
        ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--motion", nargs="+", default=["planar", "pose"])
    ap.add_argument("--out", type=Path, default=ROOT / "results/bench/localise")
    ap.add_argument("--form", choices=["auto", "reduced_rank", "tiled"], default="auto")
    ap.add_argument("--scenarios", nargs="+", default=["rectangle", "spiral", "handwriting"])
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if "imu" in args.motion:
        if args.motion != ["imu"] or args.form != "auto":
            ap.error("--motion imu: alone, without --form (the IMU model maps one box)")
        imu_runs = []
        for scenario in args.scenarios:
            for seed in range(1, args.seeds + 1):
                imu_runs.append(run_imu(scenario, seed))
                text = json.dumps(imu_runs, indent=2) + "\n"
                write_text_atomic(args.out / "localise-imu.json", text)
                r = imu_runs[-1]
                said = [
                    f"{k} {_f(mm(r.get(k, {}).get('rmse_after')), '.1f')} "
                    f"({r.get(k, {}).get('status')})"
                    for k in ("scratch", "located", "held", "joint")
                ]
                print(f"imu {scenario} seed {seed}: {', '.join(said)} mm", flush=True)
        write_text_atomic(args.out / "localise-imu.md", imu_table(imu_runs))
        return
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
