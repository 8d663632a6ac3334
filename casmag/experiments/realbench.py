"""Real-data problems and the real-data benchmark (``make bench-real``).

A real-data problem file names a recorded sequence and the conversion protocol
(casmag.data.realdata), plus optional ``model`` and ``solver`` sections that override the
defaults of ``casmag slam``::

    name: seq1-drift0.5
    description: ...
    recording:
      sequence: ../../../shared/data/magnetic-data/invensense/1  # relative to this file
      drift: 0.5          # final odometry drift [m]
      seed: 1
      # rate: 10, noise: 0.01, motion: translational (or planar, pose), field: recorded,
      # align: true
    model: {}
    solver: {}

A multi-session problem (casmag.solver.multisession) lists several recordings under ``sessions:``
(each a ``recording`` block) instead of one ``recording``; they are solved together with one
shared map and the table gets one row per session, named ``<name>: <sequence>``.

``python -m casmag.experiments.realbench FILES --out DIR [--method ekf]`` converts and solves
each file in its own process (``--method ekf``: with the filter baseline instead of the MAP,
single recordings only) and writes DIR/<name>/ (result.json with the protocol record in
``info.protocol``, trajectory.csv, figures) and DIR/table.md, DIR/table.json (rows of files
not run this time are kept from the previous table). Exit 1 when a solve failed (its row says so).
A single translational recording is also solved once more from its true trajectory
(:func:`truth_start`, ``info.truth_start``, the table's "from the truth" column): a
diagnostic of why a recording fails, never part of the estimate.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from casmag.data.realdata import Protocol, convert, load_sequence
from casmag.data.recording import read_recording, write_recording
from casmag.errors import CasmagError, DataError
from casmag.problem.spec import Strict, validate_spec
from casmag.result.evaluation import evaluate_result
from casmag.result.outdir import write_text_atomic
from casmag.solver.recslam import recording_problem, slam, slam_sessions
from casmag.solver.recslam import truth_start as solve_truth_start

DATA_HINT = "../shared/data/magnetic-data/invensense (see ../shared/data/README.md)"


class RecordingSpec(Strict):
    """How a recorded sequence becomes a recording (casmag.data.realdata.Protocol)."""

    sequence: str
    rate: float = Field(10.0, gt=0)
    drift: float = Field(0.5, ge=0)
    noise: float = Field(0.01, ge=0)
    seed: int = Field(0, ge=0)
    motion: Literal["translational", "planar", "pose"] = "translational"
    field: Literal["recorded", "constant"] = "recorded"
    constant_noise: float = Field(1.0, gt=0)
    align: bool = True


class RealProblemSpec(Strict):
    """A real-data problem file: name, description, recording, model, solver."""

    name: str
    description: str = ""
    recording: RecordingSpec | None = None
    sessions: list[RecordingSpec] = Field(default_factory=list)
    model: dict[str, Any] = Field(default_factory=dict)
    solver: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _one_source(self) -> RealProblemSpec:
        if (self.recording is None) == (not self.sessions):
            raise ValueError("give either recording or sessions (a list of recordings)")
        return self

    @property
    def recordings(self) -> list[RecordingSpec]:
        return [self.recording] if self.recording is not None else list(self.sessions)


def load_real_problem(path: str | Path) -> RealProblemSpec:
    """Read and validate a real-data problem file (one-line ProblemError on bad input)."""
    return validate_spec(RealProblemSpec, Path(path))[0]


def sequence_path(spec: RealProblemSpec, source: str | Path, index: int = 0) -> Path:
    """The sequence prefix of recording ``index``, relative paths taken from the problem
    file's folder."""
    p = Path(spec.recordings[index].sequence)
    return p if p.is_absolute() else (Path(source).resolve().parent / p)


def convert_problem(path: str | Path) -> tuple[RealProblemSpec, Any]:
    """Load a single-recording problem file and convert its sequence
    (casmag.data.realdata.Converted)."""
    spec = load_real_problem(path)
    if spec.recording is None:
        raise DataError(f"{path}: recording: missing (this file lists sessions)")
    return spec, _convert(spec, path, 0)


def convert_sessions(path: str | Path) -> tuple[RealProblemSpec, list[Any]]:
    """Load a problem file and convert every recording it names, in order."""
    spec = load_real_problem(path)
    return spec, [_convert(spec, path, i) for i in range(len(spec.recordings))]


def _convert(spec: RealProblemSpec, path: str | Path, index: int) -> Any:

    prefix = sequence_path(spec, path, index)
    where = "recording" if spec.recording is not None else f"sessions[{index}]"
    if not prefix.with_name(f"{prefix.name}-time.csv").is_file():
        raise DataError(
            f"{path}: {where}.sequence: {prefix}-time.csv not found (expected {DATA_HINT})"
        )
    r = spec.recordings[index]
    protocol = Protocol(
        rate=r.rate,
        drift=r.drift,
        noise=r.noise,
        seed=r.seed,
        motion=r.motion,
        field=r.field,
        constant_noise=r.constant_noise,
        align=r.align,
    )
    return convert(load_sequence(prefix), protocol)


def solve_problem(
    path: str | Path,
    out_dir: str | Path,
    progress: Any = None,
    align: str = "none",
    method: str = "map",
) -> list[dict[str, Any]]:
    """Convert and solve one real-data problem (one recording with ``casmag slam``'s
    defaults, or several sessions with one shared map, casmag.solver.multisession); saves DIR and
    returns its table rows (one per session). ``align``: the result's ``evaluation``
    (casmag.result.evaluation); ``method``: ``map`` or the filter baseline ``ekf``
    (casmag.solver.recslam.slam; one recording at a time)."""
    if method != "map" and load_real_problem(path).recording is None:
        raise DataError(f"{path}: the filter runs one recording at a time, not sessions")
    spec, convs = convert_sessions(path)
    overrides_file = {"model": spec.model, "solver": spec.solver, "name": spec.name}
    with tempfile.TemporaryDirectory(prefix="casmag-real-") as tmp:
        recs = []
        for conv in convs:
            seq = Path(conv.record["sequence"]).name
            stem = spec.name if spec.recording is not None else seq
            rec = Path(tmp) / f"{'seq' + stem if stem.isdigit() else stem}.csv"
            write_recording(rec, **conv.arrays)
            recs.append(rec)
        prob = Path(tmp) / "problem.yaml"
        prob.write_text(json.dumps(overrides_file))
        t0 = time.perf_counter()
        if spec.recording is not None:
            result = slam(recs[0], prob, progress=progress, method=method)
        else:
            result = slam_sessions(recs, prob, progress=progress, name=spec.name)
        wall = time.perf_counter() - t0
        if (
            spec.recording is not None
            and method == "map"
            and result.success
            and not result.info.get("fallback")
        ):
            truth = truth_start(recs[0], prob, result)
            if truth is not None:
                result.info["truth_start"] = truth
    records = [c.record for c in convs]
    result.info["recording"] = str(path)
    result.info["protocol"] = records[0] if spec.recording is not None else records
    result.info["wall_seconds"] = wall
    result.evaluation = evaluate_result(result, align)
    result.save(out_dir)
    if spec.recording is not None:
        return [row(spec, records[0], result, wall)]
    return session_table_rows(spec, records, result, wall)


def truth_start(recording: Path, problem: Path | None, result: Any) -> dict[str, Any] | None:
    """The truth-start diagnostic of a translational recording's result
    (casmag.solver.recslam.truth_start: ``casmag slam``'s problem, one batch, from the true
    trajectory), the one ``slam`` made itself when it flagged the estimate, else made here.
    None for other recordings or without truth."""
    if result.info.get("truth_start") is not None:
        return result.info["truth_start"]
    rec = read_recording(recording)
    if rec.motion != "translation":
        return None
    data = rec.to_dataset()
    if data.P_true is None:
        return None
    prob, _ = recording_problem(data, rec.t, recording.stem, problem, ())
    made = solve_truth_start(prob, data, result)
    return None if made is None else made[0]


def session_table_rows(
    spec: RealProblemSpec, records: list[dict[str, Any]], result: Any, wall: float
) -> list[dict[str, Any]]:
    """One table row per session of a multi-session result; ``records`` are the protocol
    records in the problem file's order (``result.info["session_order"]`` maps the solve
    order back to it)."""
    order = result.info.get("session_order") or list(range(len(records)))
    rows = []
    for i, sess in zip(order, result.info["sessions"], strict=True):
        r = row(spec, records[i], result, wall, spec.recordings[i])
        u = sess.get("uncertainty") or {}
        after = sess.get("rmse_after")
        r.update(
            name=f"{spec.name}: {sess['name']}",
            samples=sess["n_samples"],
            rmse_before=sess.get("rmse_before"),
            max_before=sess.get("max_before"),
            rmse_after=after,
            max_after=sess.get("max_after"),
            ratio=None
            if after is None or not sess.get("rmse_before")
            else after / sess["rmse_before"],
            nees_mean=u.get("nees_mean"),
            nees_expected=u.get("nees_expected"),
            nees_interval_95=u.get("nees_interval_95"),
            sigma_mean=u.get("sigma_mean"),
            inside_95=u.get("inside_95"),
            nees_mean_uninflated=(sess.get("uncertainty_uninflated") or {}).get("nees_mean"),
            inside_95_uninflated=(sess.get("uncertainty_uninflated") or {}).get("inside_95"),
            sessions=len(records),
        )
        rows.append(r)
    return rows


def row(
    spec: RealProblemSpec,
    record: dict[str, Any],
    result: Any,
    wall: float,
    recording: RecordingSpec | None = None,
) -> dict[str, Any]:
    rec = recording or spec.recording
    u = result.uncertainty or {}
    withheld = "computed" in u  # not trusted: the covariance is not given, its figures kept
    u = u.get("computed", u)
    hyp = result.info.get("defaults", {}).get("marginal_likelihood", {})
    return {
        "name": spec.name,
        "sequence": record["sequence"],
        "motion": rec.motion,
        "field": rec.field,
        "drift_target": rec.drift,
        "samples": record["samples"],
        "clock_shift_s": record.get("clock", {}).get("shift_seconds"),
        "status": result.status,
        "success": result.success,
        "iterations": result.iterations,
        "wall_seconds": wall,
        "rmse_before": result.rmse_before,
        "max_before": result.max_before,
        "rmse_after": result.rmse_after,
        "max_after": result.max_after,
        "ratio": None
        if result.rmse_after is None or not result.rmse_before
        else result.rmse_after / result.rmse_before,
        "sigma_f": result.hyperparameters.get("sigma_f"),
        "lengthscale": result.hyperparameters.get("lengthscale"),
        "sigma_m": result.hyperparameters.get("sigma_m"),
        "ml_converged": hyp.get("converged"),
        "fallback": result.info.get("fallback"),
        "nees_mean": u.get("nees_mean"),
        "nees_expected": u.get("nees_expected"),
        "nees_interval_95": u.get("nees_interval_95"),
        "sigma_mean": u.get("sigma_mean"),
        "inside_95": u.get("inside_95"),
        "covariance_withheld": withheld,
        "nees_mean_uninflated": (u.get("uninflated") or {}).get("nees_mean"),
        "inside_95_uninflated": (u.get("uninflated") or {}).get("inside_95"),
        "inflation_factor_mean": (u.get("inflation") or {}).get("factor_mean"),
        "truth_start": result.info.get("truth_start"),
        "trusted": (result.verdict or {}).get("trusted"),
        "verdict_reasons": list((result.verdict or {}).get("reasons") or []),
        "starts": [
            {k: st.get(k) for k in ("start", "cost", "kept", "iterations", "solve_seconds")}
            for st in result.stages_named("start")
        ],
    }


def _fmt(v: Any, spec: str = ".3f") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def _plain(r: dict[str, Any]) -> str:
    """The plain Laplace covariance's mean NEES and inside-95 % fraction (before the
    inflation for correlated residuals, casmag.solver.uncertainty)."""
    if r.get("nees_mean_uninflated") is None:
        return "-"
    return f"{r['nees_mean_uninflated']:.2f}, {_fmt(r.get('inside_95_uninflated'), '.2f')}"


def _truth(r: dict[str, Any]) -> str:
    """The truth-start diagnostic (:func:`truth_start`): its RMSE and cost above ours."""
    t = r.get("truth_start")
    if not t:
        return "-"
    if not t.get("success"):
        return t["status"]
    return f"{t['rmse']:.3f}, {t['cost_above_result']:+.1f}"


def _verdict(r: dict[str, Any]) -> str:
    """The verdict (casmag.result.verdict): trusted, or not and the checks that failed."""
    if r.get("trusted") is None:
        return "-"
    if r["trusted"]:
        return "yes"
    names = sorted({reason.split(":")[0] for reason in r.get("verdict_reasons") or []})
    return "no (" + "; ".join(names) + ")" if names else "no"


def markdown(rows: list[dict[str, Any]]) -> str:
    head = (
        "| problem | motion | field | N | clock shift [s] | RMSE before [m] | max before [m] "
        "| RMSE after [m] | max after [m] | after/before | iterations | wall [s] "
        "| sigma_f | l [m] | sigma_m | mean NEES (expected; 95 % range if honest) | inside 95 % "
        "| plain Laplace: mean NEES, inside 95 % | from the truth: RMSE [m], cost - ours "
        "| trusted | status |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        nees = "-"
        if r.get("nees_mean") is not None:
            span = r.get("nees_interval_95")
            rng = "" if span is None else f"; {span[0]:.2f}-{span[1]:.2f}"
            nees = f"{r['nees_mean']:.2f} ({r['nees_expected']:.0f}{rng})"
            if r.get("covariance_withheld"):
                nees += ", withheld: not trusted"
        lines.append(
            "| "
            + " | ".join(
                [
                    r["name"],
                    r["motion"],
                    r["field"],
                    _fmt(r["samples"]),
                    _fmt(r["clock_shift_s"], ".2f"),
                    _fmt(r["rmse_before"]),
                    _fmt(r["max_before"]),
                    _fmt(r["rmse_after"]),
                    _fmt(r["max_after"]),
                    _fmt(r["ratio"], ".2f"),
                    _fmt(r["iterations"]),
                    _fmt(r["wall_seconds"], ".0f"),
                    _fmt(r["sigma_f"], ".2f"),
                    _fmt(r["lengthscale"], ".2f"),
                    _fmt(r["sigma_m"], ".2f"),
                    nees,
                    _fmt(r["inside_95"], ".2f"),
                    _plain(r),
                    _truth(r),
                    _verdict(r),
                    r["status"] + (f" ({r['fallback']})" if r.get("fallback") else ""),
                ]
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def _worker(args: tuple[str, str, str]) -> list[dict[str, Any]]:
    from threadpoolctl import threadpool_limits

    path, out, method = args
    with threadpool_limits(1):
        try:
            return solve_problem(path, out, method=method)
        except CasmagError as exc:
            return [{"name": Path(path).stem, "error": str(exc)}]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m casmag.experiments.realbench", description=__doc__)
    ap.add_argument("files", nargs="+")
    ap.add_argument("--out", required=True)
    ap.add_argument("-j", "--jobs", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument(
        "--method",
        choices=("map", "ekf"),
        default="map",
        help="map: casmag slam's MAP (default); ekf: the filter baseline (one recording each)",
    )
    a = ap.parse_args(argv)
    out = Path(a.out)
    specs = []
    for f in a.files:
        try:
            specs.append((f, load_real_problem(f).name))
        except CasmagError as exc:
            print(f"casmag: error: {exc}", file=sys.stderr)
            return 2
    jobs = [(f, str(out / name), a.method) for f, name in specs]
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    rows: list[dict[str, Any]] = []
    with ProcessPoolExecutor(a.jobs, mp_context=mp.get_context("spawn")) as pool:
        for r in (r for rs in pool.map(_worker, jobs) for r in rs):
            rows.append(r)
            msg = r.get("error") or (
                f"{r['name']}: {r['status']}, RMSE {r['rmse_before']:.3f} -> "
                f"{_fmt(r['rmse_after'])} m, {r['iterations']} it, {r['wall_seconds']:.0f} s"
            )
            print(msg, flush=True)
    failed = [r for r in rows if "error" in r]
    # Rows of problems not run this time are kept from an earlier table (re-running a few
    # files updates their rows only).
    previous = out / "table.json"
    merged = (
        {r["name"]: r for r in json.loads(previous.read_text())["rows"]}
        if previous.is_file()
        else {}
    )
    merged.update({r["name"]: r for r in rows})
    table = [merged[k] for k in sorted(merged)]
    write_text_atomic(previous, json.dumps({"rows": table}, indent=2) + "\n")
    write_text_atomic(out / "table.md", markdown([r for r in table if "error" not in r]))
    return 1 if failed or any(not r["success"] for r in rows if "error" not in r) else 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
