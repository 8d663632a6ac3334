"""Map once, locate later, on the real field: robot sequences 1, 2 and 4 of
``../shared/data/magnetic-data/invensense`` (0.5 m of odometry drift) are mapped together,
and sequences 3 and 5 (1.5 m of drift) are located against that map, held
(``--hold-map``) and updated, beside the five sequences solved together as sessions (the
accuracy multi-session SLAM reaches) and, with ``--pairs``, the map's three sessions
solved with each later one.

    python -m casmag.experiments.reallocate --out results/bench/localise

Every recording is written by ``casmag convert problems/real/seqN-driftD.yaml`` (the real
problem files' odometry protocol and seeds) and every solve is one ``casmag slam`` run in a
child process, one after the other, with sigma_m = 2 uT as the real problem files give
it: wall seconds and the child's peak resident memory (``os.wait4``) are measured per run.
Writes ``localise-real.json`` (every run, after each) and ``localise-real.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from casmag.experiments.realbench import load_real_problem, sequence_path
from casmag.result.outdir import write_text_atomic

ROOT = Path(__file__).resolve().parents[2]
PROBLEMS = ROOT / "problems" / "real"

#: The sequences the map is made from, and the later ones located against it, with the
#: odometry drift [m] of each (the problem file ``seq{N}-drift{D}.yaml``).
MAPPED = ((1, 0.5), (2, 0.5), (4, 0.5))
LATER = ((3, 1.5), (5, 1.5))

#: The magnetometer noise of every solve [uT]: the real problem files' value.
SIGMA_M = ["--set", "model.magnetometer.sigma_m=2.0"]


def _name(seq: int, drift: float) -> str:
    return f"seq{seq}-drift{drift}"


def _problem(seq: int, drift: float) -> Path:
    return PROBLEMS / f"{_name(seq, drift)}.yaml"


def missing_data() -> str | None:
    """Why the benchmark cannot run here (a problem file or its sequence missing), or None."""
    for seq, drift in MAPPED + LATER:
        path = _problem(seq, drift)
        if not path.is_file():
            return f"{path}: not found"
        prefix = sequence_path(load_real_problem(path), path)
        data = prefix.with_name(f"{prefix.name}-time.csv")
        if not data.is_file():
            return f"{path}: recording.sequence: {data} not found (../shared beside the clone)"
    return None


def _child(args: list[str], log: Path) -> tuple[int, float, float]:
    """Run ``casmag ARGS`` with its output in ``log``: (exit code, wall seconds, peak
    resident memory of the child [GiB])."""
    t0 = time.perf_counter()
    with open(log, "w") as out:
        p = subprocess.Popen(
            [sys.executable, "-m", "casmag.cli.main", *args], stdout=out, stderr=subprocess.STDOUT
        )
        _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    return p.returncode, time.perf_counter() - t0, usage.ru_maxrss / 2**20


def _errors(result: dict[str, Any], names: list[str]) -> dict[str, Any]:
    """Each named recording's RMSE and max error after (a session's, or the run's own)."""
    sessions = {s["name"]: s for s in result.get("info", {}).get("sessions", [])}
    out = {}
    for name in names:
        s = sessions.get(name, result)
        out[name] = {k: s.get(k) for k in ("rmse_before", "rmse_after", "max_after")}
    return out


def solve(kind: str, recordings: list[Path], work: Path, extra: list[str]) -> dict[str, Any]:
    """One ``casmag slam`` run of ``recordings`` into ``work/kind``: its record."""
    out = work / kind
    code, seconds, peak = _child(
        ["slam", *map(str, recordings), "--out", str(out), "--quiet", *extra],
        work / f"{kind}.log",
    )
    row: dict[str, Any] = {"kind": kind, "exit_code": code, "seconds": seconds, "peak_gib": peak}
    if not (out / "result.json").is_file():
        row["error"] = (work / f"{kind}.log").read_text()[-2000:]
        return row
    result = json.loads((out / "result.json").read_text())
    u = result.get("uncertainty") or {}
    loc = result.get("info", {}).get("localisation") or {}
    row.update(
        status=result["status"],
        trusted=result.get("verdict", {}).get("trusted"),
        iterations=result["iterations"],
        errors=_errors(result, [p.stem for p in recordings]),
        nees_mean=u.get("nees_mean"),
        nees_interval_95=u.get("nees_interval_95"),
        covered=loc.get("covered"),
        updated=loc.get("updated"),
    )
    return row


def run(out: Path, pairs: bool, work: Path) -> list[dict[str, Any]]:
    """Convert, map, locate and solve jointly (module docstring); writes the JSON after
    every run and returns the records."""
    csv = {}
    for seq, drift in MAPPED + LATER:
        csv[seq] = work / f"{_name(seq, drift)}.csv"
        code, _, _ = _child(
            ["convert", str(_problem(seq, drift)), "--out", str(csv[seq])],
            work / f"convert{seq}.log",
        )
        if code != 0:
            raise SystemExit((work / f"convert{seq}.log").read_text().strip())
    mapped = [csv[s] for s, _ in MAPPED]
    plan = [("map", mapped, SIGMA_M)]
    for seq, _ in LATER:
        plan.append((f"held{seq}", [csv[seq]], ["--map", str(work / "map"), "--hold-map"]))
        plan.append((f"updated{seq}", [csv[seq]], ["--map", str(work / "map")]))
    plan.append(("joint", [*mapped, *(csv[s] for s, _ in LATER)], SIGMA_M))
    if pairs:
        plan += [(f"joint{s}", [*mapped, csv[s]], SIGMA_M) for s, _ in LATER]
    runs: list[dict[str, Any]] = []
    for kind, recs, extra in plan:
        runs.append(solve(kind, recs, work, extra))
        write_text_atomic(out / "localise-real.json", json.dumps(runs, indent=2) + "\n")
        r = runs[-1]
        said = ", ".join(
            f"{n} {e['rmse_after']:.4f} m" for n, e in r.get("errors", {}).items()
            if e.get("rmse_after") is not None
        )  # fmt: skip
        print(f"{kind}: {r.get('status', 'no result')}, {r['seconds']:.0f} s, {said}", flush=True)
    return runs


def _cell(row: dict[str, Any] | None, name: str) -> str:
    e = (row or {}).get("errors", {}).get(name)
    if not e or e.get("rmse_after") is None:
        return "-"
    return f"{e['rmse_after']:.4f}, {e['max_after']:.3f}"


def table(runs: list[dict[str, Any]]) -> str:
    """The markdown table: per later recording, its RMSE and max error after (m) held,
    updated, in the five-session solve and with the map's sessions; the wall seconds and
    peak memory of each run."""
    by = {r["kind"]: r for r in runs}
    lines = [
        "| recording | RMSE before [m] | held: after, max [m] | updated: after, max [m] "
        "| all sessions together: after, max [m] | the map's sessions and this one "
        "| seconds: held / updated / all together | peak GiB: held / updated / all together |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for seq, drift in LATER:
        name = _name(seq, drift)
        rows = [by.get(k) for k in (f"held{seq}", f"updated{seq}", "joint")]
        before = next(
            (r["errors"][name]["rmse_before"] for r in rows if r and name in r.get("errors", {})),
            None,
        )
        secs = " / ".join(f"{r['seconds']:.0f}" if r else "-" for r in rows)
        peaks = " / ".join(f"{r['peak_gib']:.1f}" if r else "-" for r in rows)
        lines.append(
            f"| {name} | {before if before is None else f'{before:.3f}'} "
            f"| {_cell(rows[0], name)} | {_cell(rows[1], name)} | {_cell(rows[2], name)} "
            f"| {_cell(by.get(f'joint{seq}'), name)} | {secs} | {peaks} |"
        )
    m = by.get("map")
    if m:
        lines.append(
            f"\nThe map (sequences {', '.join(str(s) for s, _ in MAPPED)}): "
            f"{m['seconds']:.0f} s, {m['peak_gib']:.1f} GiB peak, {m.get('status')}."
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "results/bench/localise")
    ap.add_argument(
        "--pairs", action="store_true",
        help="also solve the map's sessions with each later recording (two more joint runs)",
    )  # fmt: skip
    ap.add_argument(
        "--work", type=Path, help="keep the recordings and runs here (default: temporary)"
    )
    args = ap.parse_args(argv)
    why = missing_data()
    if why:
        raise SystemExit(f"reallocate: {why}")
    if args.work is not None:
        args.work.mkdir(parents=True, exist_ok=True)
        runs = run(args.out, args.pairs, args.work)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            runs = run(args.out, args.pairs, Path(tmp))
    write_text_atomic(args.out / "localise-real.md", table(runs))
    failed = [r["kind"] for r in runs if "status" not in r]
    if failed:
        raise SystemExit(f"reallocate: no result from {', '.join(failed)} (their logs: --work DIR)")


if __name__ == "__main__":
    main()
