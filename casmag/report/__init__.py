"""Tables and figures from saved results (never re-solves).

Reads what ``casmag run`` and ``casmag sweep`` saved: ``result.json`` and ``trajectory.csv``
per run, ``map.png`` where figures were saved, and a sweep's ``sweep.json`` (its rows,
labels and seeds, and which of the paper's tables it reproduces). Writes the paper's layout:
a "Before SLAM" row and one "After SLAM, <setting>" row per setting, with RMSE [m] and
Max Error [m] (no alignment) as mean, sample standard deviation and worst case over the
seeds, the paper's own numbers beside them and the ratio ours/paper; as markdown, CSV and
LaTeX, with figures in the paper's style.

Runs whose IPOPT solve failed are counted per row (with their statuses) and left out of the
statistics, never averaged in; runs that raised an error or were never run are counted too.

Results of ``casmag imu`` (position errors of the IMU-only adjustment and of GP-SLAM, no
odometry-only "before") get a table of their own, one row per problem name. A result.json
that cannot be read is skipped with a warning naming it; only when none can be read is
that an error.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
import statistics
import tempfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from casmag.errors import DataError
from casmag.experiments.sweep import read_manifest
from casmag.problem.paper import TABLES, PaperRow, PaperTable
from casmag.result import ARRAYS_FILE, bias_table, upgrade_layout
from casmag.result.evaluation import evaluate
from casmag.result.outdir import record_written

# Where the paper's GP-SLAM made the trajectory worse, ours must stay within this factor of
# the odometry-only RMSE.
NEVER_WORSE = 1.05
_REQUIRED = ("status", "success", "rmse_before", "max_before", "rmse_after", "max_after", "info")


# --------------------------------------------------------------------------- reading
def _visible(root: Path, name: str) -> list[Path]:
    """Files ``name`` under root, not inside hidden folders (an interrupted save's
    ``.NAME.tmp-*``, casmag.result.outdir)."""
    return sorted(
        f
        for f in root.rglob(name)
        if not any(part.startswith(".") for part in f.relative_to(root).parts[:-1])
    )


def find_results(paths: list[Path]) -> list[Path]:
    """result.json files: the paths themselves, or found recursively under folders."""
    found: list[Path] = []
    for p in paths:
        if p.is_file():
            found.append(p)
        elif p.is_dir():
            found.extend(_visible(p, "result.json"))
        else:
            raise DataError(f"{p}: no such file or folder")
    if not found:
        raise DataError(f"{', '.join(map(str, paths))}: no result.json found")
    return found


def load_result(path: Path, data: Any = None) -> dict[str, Any]:
    """A result.json (read from path unless given parsed) in today's layout
    (casmag.result.upgrade_layout), checked for the fields the tables need."""
    if data is None:
        data = _read_json(path)
    if not isinstance(data, dict):
        raise DataError(f"{path}: a result must be a JSON object")
    data = upgrade_layout(data)
    for key in _REQUIRED:
        if key not in data:
            raise DataError(f"{path}: field {key!r} is missing")
    for key in ("rmse_before", "max_before", "rmse_after", "max_after"):
        value = data[key]
        if value is not None and (not isinstance(value, (int, float)) or isinstance(value, bool)):
            raise DataError(f"{path}: field {key!r}: expected a number or null, got {value!r}")
    if data["success"] and data["rmse_after"] is None:
        raise DataError(f"{path}: field 'rmse_after': null in a successful result")
    if not isinstance(data["info"], dict):
        raise DataError(f"{path}: field 'info': expected an object")
    return data


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: cannot read result ({exc})") from None


def is_imu_result(data: Any) -> bool:
    """A result.json of the IMU model (``motion`` imu, or the layout before the one
    Result: errors per stage at the top level)."""
    return isinstance(data, dict) and upgrade_layout(data).get("motion") == "imu"


_IMU_REQUIRED = ("status", "success", "info", "details")


def load_imu_result(path: Path, data: dict[str, Any]) -> dict[str, Any]:
    """An IMU result.json (already parsed), in today's layout, checked for the fields its
    table needs (``details.errors`` per estimate)."""
    data = upgrade_layout(data)
    for key in _IMU_REQUIRED:
        if key not in data:
            raise DataError(f"{path}: field {key!r} is missing")
    if not isinstance(data["info"], dict):
        raise DataError(f"{path}: field 'info': expected an object")
    for stage in ("imu_only", "gp_slam"):
        errors = (data["details"].get("errors") or {}).get(stage)
        if not isinstance(errors, dict):
            raise DataError(f"{path}: field 'details.errors.{stage}': expected an object")
        for key in ("rmse", "max"):
            value = errors.get(key)
            if value is not None and (
                not isinstance(value, (int, float)) or isinstance(value, bool)
            ):
                raise DataError(
                    f"{path}: field 'details.errors.{stage}.{key}': expected a number or null, "
                    f"got {value!r}"
                )
    return data


def read_result(path: Path) -> tuple[str, dict[str, Any]]:
    """("slam", data) or ("imu", data) for a result.json; DataError naming the file when
    it cannot be read or lacks what its table needs."""
    data = _read_json(path)
    if is_imu_result(data):
        return "imu", load_imu_result(path, data)
    return "slam", load_result(path, data)


@dataclass
class Run:
    """One saved run: its folder, seed, result.json contents, or the error it raised."""

    path: Path
    seed: int | None
    data: dict[str, Any] | None = None
    error: str | None = None

    @property
    def solved(self) -> bool:
        return self.data is not None and bool(self.data["success"])

    @property
    def failed(self) -> bool:
        return self.data is not None and not self.data["success"]


@dataclass
class Row:
    """A setting: its runs over seeds, and the paper's row it reproduces (if any)."""

    key: str
    label: str
    runs: list[Run]
    expected: int
    paper: PaperRow | None = None


@dataclass
class Table:
    """A group of rows: one sweep (``name`` from its manifest) or loose results; ``kind``
    ``imu`` for results of ``casmag imu`` (their own layout, :func:`imu_markdown_table`)."""

    name: str
    title: str | None
    rows: list[Row]
    paper: PaperTable | None = None
    source: str | None = None
    seeds: list[int] = field(default_factory=list)
    kind: str = "slam"
    align: str = "none"

    @property
    def frame(self) -> str:
        """How the errors were measured: the anchor that fixed the runs' frame (when their
        result.json records it), then "no alignment" or after which alignment."""
        kinds = sorted(
            {
                str(((r.data.get("info") or {}).get("anchor") or {}).get("kind"))
                for row in self.rows
                for r in row.runs
                if r.data is not None and (r.data.get("info") or {}).get("anchor")
            }
        )
        anchored = f"anchored at the {' / '.join(kinds)}, " if kinds else ""
        how = "no alignment" if self.align == "none" else f"after alignment {self.align!r}"
        return anchored + how


def _read_manifest(path: Path) -> dict[str, Any]:

    return read_manifest(path)


def realigned(path: Path, kind: str, data: dict[str, Any], align: str) -> dict[str, Any]:
    """The result data of ``path`` (a result.json) with its error fields measured again
    after ``align`` (casmag.result.evaluation) from the arrays.npz beside it; unchanged for
    ``none``. DataError naming the file when it has no saved arrays."""
    if align == "none":
        return data
    npz = path.parent / ARRAYS_FILE
    if not npz.is_file():
        raise DataError(f"{path}: no {ARRAYS_FILE} beside it to align (saved without arrays)")
    with np.load(npz, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    if not data["success"]:
        arrays.pop("P_estimate", None)
    e = evaluate(arrays, align, data["info"].get("anchor"))
    out = {**data, "evaluation": e}
    b, a = _pair(e["before"]), _pair(e["after"])
    if kind == "imu":
        errors = data["details"]["errors"]
        out["details"] = {
            **data["details"],
            "errors": {
                **errors,
                "imu_only": {**errors["imu_only"], **b},
                "gp_slam": {**errors["gp_slam"], **a},
            },
        }
    out.update(rmse_before=b["rmse"], max_before=b["max"], rmse_after=a["rmse"], max_after=a["max"])
    return out


def _pair(errors: dict[str, Any]) -> dict[str, Any]:
    return {"rmse": errors["rmse"], "max": errors["max"]}


def _sweep_table(
    manifest_path: Path, skip: Callable[[DataError], None] | None = None, align: str = "none"
) -> Table:
    m = _read_manifest(manifest_path)
    folder = manifest_path.parent
    paper = TABLES.get(m.get("paper") or "")
    if m.get("paper") and paper is None:
        raise DataError(f"{manifest_path}: paper: {m['paper']!r} is not a paper table")
    kind = "imu" if m.get("kind") == "imu" else "slam"  # sweeps before "kind": translational
    load = (lambda p: read_result(p)[1]) if kind == "imu" else load_result
    rows = []
    for r in m["rows"]:
        runs = []
        row_dir = folder / r["key"]
        for run_dir in sorted(row_dir.glob("seed-*")) if row_dir.is_dir() else []:
            try:
                seed = int(run_dir.name.split("-", 1)[1])
            except ValueError:
                continue
            if (run_dir / "result.json").is_file():
                try:
                    data = realigned(
                        run_dir / "result.json", kind, load(run_dir / "result.json"), align
                    )
                except DataError as exc:
                    if skip is None:
                        raise
                    skip(exc)
                    runs.append(Run(run_dir, seed, error="unreadable result.json"))
                    continue
                runs.append(Run(run_dir, seed, data=data))
            elif (run_dir / "error.json").is_file():
                try:
                    err = json.loads((run_dir / "error.json").read_text()).get("error", "error")
                except (OSError, json.JSONDecodeError, AttributeError):
                    err = "error (unreadable error.json)"
                runs.append(Run(run_dir, seed, error=str(err)))
        paper_row = None
        if paper is not None and r.get("paper_key"):
            try:
                paper_row = paper.row(r["paper_key"])
            except KeyError:
                raise DataError(
                    f"{manifest_path}: rows.{r['key']}.paper_key: not a row of the paper's "
                    f"Table {paper.number}"
                ) from None
        expected = len(set(m["seeds"]) | {run.seed for run in runs})
        rows.append(Row(r["key"], r["label"], runs, expected, paper_row))
    return Table(
        name=m["name"],
        title=m.get("title"),
        rows=rows,
        paper=paper,
        source=m.get("source"),
        seeds=[int(s) for s in m["seeds"]],
        kind=kind,
        align=align,
    )


def collect(
    paths: list[Path], warn: Callable[[str], None] | None = None, align: str = "none"
) -> list[Table]:
    """Tables from paths: one per sweep folder (``sweep.json``) found, one table of the
    remaining results and one of ``casmag imu`` results, one row per problem name (its
    seeds aggregated). ``align``: errors measured again after this alignment
    (:func:`realigned`).

    A result.json or sweep.json that cannot be read is skipped: with ``warn``, each is
    passed to it (one line naming the file) once the others have been read; without, the
    first raises DataError. When no result at all can be read, DataError (the file's own
    line when it is the only one)."""
    tables: list[Table] = []
    loose: list[Path] = []
    skipped: list[str] = []

    def skip(exc: DataError) -> None:
        if warn is None:
            raise exc
        skipped.append(str(exc))

    for p in paths:
        if p.is_file():
            loose.append(p)
        elif p.is_dir():
            manifests = []
            for m in _visible(p, "sweep.json"):
                try:
                    tables.append(_sweep_table(m, skip, align))
                    manifests.append(m)
                except DataError as exc:  # its runs are reported as loose results
                    skip(exc)
            sweep_dirs = [m.parent for m in manifests]
            loose.extend(
                f for f in _visible(p, "result.json") if not any(d in f.parents for d in sweep_dirs)
            )
        else:
            raise DataError(f"{p}: no such file or folder")
    by_kind: dict[str, dict[str, list[Run]]] = {"slam": {}, "imu": {}}
    for f in loose:
        try:
            kind, data = read_result(f)
            data = realigned(f, kind, data, align)
        except DataError as exc:
            skip(exc)
            continue
        name = str(data["info"].get("name", f.parent.name))
        method = data["info"].get("method")
        if method not in (None, "map"):  # a filter's row beside the MAP's of the same name
            name = f"{name} ({method})"
        seed = data["info"].get("seed")
        by_kind[kind].setdefault(name, []).append(Run(f.parent, seed, data=data))
    for kind, table_name, title in (("slam", "results", None), ("imu", "imu", "IMU results")):
        if by_kind[kind]:
            rows = [Row(n, n, runs, len(runs)) for n, runs in by_kind[kind].items()]
            tables.append(Table(table_name, title, rows, kind=kind, align=align))
    where = ", ".join(map(str, paths))
    if skipped and not any(r.data is not None for t in tables for row in t.rows for r in row.runs):
        if len(skipped) == 1:
            raise DataError(skipped[0])
        raise DataError(
            f"{where}: no result could be read ({len(skipped)} unreadable; first: {skipped[0]})"
        )
    if not tables or not any(r.runs for t in tables for r in t.rows):
        raise DataError(f"{where}: no result.json found")
    for message in skipped:
        assert warn is not None
        warn(f"{message}; skipped")
    return tables


# --------------------------------------------------------------------------- statistics
@dataclass(frozen=True)
class Stats:
    """Mean, sample standard deviation (None for one value) and worst (largest) of n values."""

    n: int
    mean: float | None
    std: float | None
    worst: float | None

    @classmethod
    def of(cls, values: list[float]) -> Stats:
        if not values:
            return cls(0, None, None, None)
        std = statistics.stdev(values) if len(values) > 1 else None
        return cls(len(values), statistics.fmean(values), std, max(values))


@dataclass(frozen=True)
class RowSummary:
    """Everything a table row shows, from a Row's runs."""

    row: Row
    rmse_before: Stats
    max_before: Stats
    rmse_after: Stats
    max_after: Stats
    solved: int
    failed: Counter
    errors: int
    missing: int
    iterations: float | None
    untrusted: int = 0

    @classmethod
    def of(cls, row: Row) -> RowSummary:
        with_data = [r.data for r in row.runs if r.data is not None]
        solved = [r.data for r in row.runs if r.solved]

        def values(runs: list[dict[str, Any]], key: str) -> list[float]:
            return [float(d[key]) for d in runs if d.get(key) is not None]

        iters = [float(d["iterations"]) for d in with_data if d.get("iterations") is not None]
        return cls(
            row=row,
            rmse_before=Stats.of(values(with_data, "rmse_before")),
            max_before=Stats.of(values(with_data, "max_before")),
            rmse_after=Stats.of(values(solved, "rmse_after")),
            max_after=Stats.of(values(solved, "max_after")),
            solved=len(solved),
            failed=Counter(str(r.data["status"]) for r in row.runs if r.failed),
            errors=sum(r.error is not None for r in row.runs),
            missing=max(row.expected - len(row.runs), 0),
            iterations=statistics.fmean(iters) if iters else None,
            untrusted=sum(not (d.get("verdict") or {}).get("trusted", True) for d in solved),
        )

    @property
    def complete(self) -> bool:
        """Every expected seed solved successfully."""
        return self.solved == self.row.expected and self.solved > 0

    def runs_text(self) -> str:
        text = f"{self.solved}/{self.row.expected}"
        notes = [f"{s} x{n}" for s, n in sorted(self.failed.items())]
        if self.untrusted:
            notes.append(f"not trusted x{self.untrusted}")
        if self.errors:
            notes.append(f"error x{self.errors}")
        if self.missing:
            notes.append(f"not run x{self.missing}")
        return text + (f" ({', '.join(notes)})" if notes else "")

    def target(self) -> tuple[float, str] | None:
        """The value our mean RMSE after must not exceed, and how it was set: the paper's
        RMSE where its GP-SLAM improved on odometry, else 1.05 x our mean RMSE before."""
        paper = self.row.paper
        if paper is None:
            return None
        if paper.improved:
            return paper.rmse_after, "paper"
        if self.rmse_before.mean is None:
            return None
        return NEVER_WORSE * self.rmse_before.mean, f"{NEVER_WORSE:g} x before"

    def target_met(self) -> bool | None:
        t = self.target()
        if t is None:
            return None
        return self.complete and self.rmse_after.mean is not None and self.rmse_after.mean <= t[0]


def _shared_before(summaries: list[RowSummary]) -> bool:
    """Whether every row has the same odometry-only errors seed by seed (the settings
    differ only in the field or the model), so one "Before SLAM" row serves them all."""
    seen: dict[int | None, tuple[float, float]] = {}
    for s in summaries:
        for run in s.row.runs:
            if run.data is None or run.data["rmse_before"] is None:
                continue
            value = (float(run.data["rmse_before"]), float(run.data["max_before"]))
            prev = seen.setdefault(run.seed, value)
            if any(
                not math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
                for a, b in zip(prev, value, strict=True)
            ):
                return False
    return (
        bool(seen)
        and len({s.row.paper.rmse_before if s.row.paper else None for s in summaries}) == 1
    )


# --------------------------------------------------------------------------- table lines
@dataclass(frozen=True)
class Line:
    """One printed row: label, kind ("before" or "after"), our statistics, the paper's."""

    label: str
    kind: str
    summary: RowSummary
    rmse: Stats
    max: Stats
    paper_rmse: float | None
    paper_max: float | None


def table_lines(table: Table) -> list[Line]:
    """The paper's layout: one shared "Before SLAM" line when every row has the same
    odometry, else a "Before SLAM" line ahead of each "After SLAM" line (Table 5)."""
    summaries = [RowSummary.of(r) for r in table.rows]
    lines: list[Line] = []
    shared = _shared_before(summaries)
    if shared:
        s = max(summaries, key=lambda x: x.rmse_before.n)
        p = s.row.paper
        lines.append(
            Line(
                "Before SLAM",
                "before",
                s,
                s.rmse_before,
                s.max_before,
                p.rmse_before if p else None,
                p.max_before if p else None,
            )
        )
    for s in summaries:
        p = s.row.paper
        if not shared:
            lines.append(
                Line(
                    f"Before SLAM, {s.row.label}",
                    "before",
                    s,
                    s.rmse_before,
                    s.max_before,
                    p.rmse_before if p else None,
                    p.max_before if p else None,
                )
            )
        lines.append(
            Line(
                f"After SLAM, {s.row.label}",
                "after",
                s,
                s.rmse_after,
                s.max_after,
                p.rmse_after if p else None,
                p.max_after if p else None,
            )
        )
    return lines


# --------------------------------------------------------------------------- IMU results
@dataclass(frozen=True)
class ImuSummary:
    """A row of ``casmag imu`` results: position RMSE and max error [m] of the IMU-only
    adjustment (every run that has them) and of GP-SLAM (solved runs only), IPOPT
    statuses, flagged runs and mean iterations of each stage."""

    row: Row
    imu_only: Stats
    imu_only_max: Stats
    gp_slam: Stats
    gp_slam_max: Stats
    solved: int
    statuses: Counter
    flagged: int
    iterations_imu_only: float | None
    iterations: float | None

    @classmethod
    def of(cls, row: Row) -> ImuSummary:
        runs = [r.data for r in row.runs if r.data is not None]
        solved = [d for d in runs if d["success"]]

        def values(ds: list[dict[str, Any]], stage: str, key: str) -> list[float]:
            out = []
            for d in ds:
                v = d["details"]["errors"][stage].get(key)
                if v is not None:
                    out.append(float(v))
            return out

        def mean(key: str) -> float | None:
            v = [float(d[key]) for d in runs if isinstance(d.get(key), (int, float))]
            return statistics.fmean(v) if v else None

        def imu_only_iterations(d: dict[str, Any]) -> Any:
            return next((s for s in d.get("stages", []) if s.get("name") == "imu_only"), {}).get(
                "iterations"
            )

        its = [imu_only_iterations(d) for d in runs]
        its = [float(v) for v in its if isinstance(v, (int, float))]

        return cls(
            row=row,
            imu_only=Stats.of(values(runs, "imu_only", "rmse")),
            imu_only_max=Stats.of(values(runs, "imu_only", "max")),
            gp_slam=Stats.of(values(solved, "gp_slam", "rmse")),
            gp_slam_max=Stats.of(values(solved, "gp_slam", "max")),
            solved=len(solved),
            statuses=Counter(str(d["status"]) for d in runs),
            flagged=sum(bool(d.get("flags")) for d in runs),
            iterations_imu_only=statistics.fmean(its) if its else None,
            iterations=mean("iterations"),
        )

    def status_text(self) -> str:
        text = f"{self.solved}/{len(self.row.runs)} solved"
        notes = [f"{s} x{n}" for s, n in sorted(self.statuses.items())]
        if self.flagged:
            notes.append(f"flagged x{self.flagged}")
        return text + (f" ({', '.join(notes)})" if notes else "")

    def iterations_text(self) -> str:
        return f"{_m(self.iterations_imu_only, 1)} + {_m(self.iterations, 1)}"


def imu_markdown_table(table: Table) -> str:
    """``casmag imu`` results in markdown: IMU-only and GP-SLAM position RMSE [m] (mean and
    worst over the runs of a problem name), the runs' IPOPT statuses and iterations."""
    head = [
        "",
        "IMU-only RMSE [m] mean",
        "worst",
        "GP-SLAM RMSE [m] mean",
        "worst",
        "status",
        "iterations (IMU only + GP-SLAM)",
    ]
    out = [f"### {_heading(table)}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in table.rows:
        s = ImuSummary.of(row)
        cells = [
            row.label,
            _m(s.imu_only.mean),
            _m(s.imu_only.worst),
            _m(s.gp_slam.mean),
            _m(s.gp_slam.worst),
            s.status_text(),
            s.iterations_text(),
        ]
        out.append("| " + " | ".join(cells) + " |")
    out += [
        "",
        f"Position errors in metres against the truth, {table.frame}, of the IMU-only "
        "adjustment "
        "and of GP-SLAM (`casmag imu`); GP-SLAM statistics over the solved runs only; "
        "'iterations' are the mean IPOPT iteration counts of the two stages.",
        "",
    ]
    return "\n".join(out) + imu_bias_tables(table)


def imu_bias_tables(table: Table) -> str:
    """The recovered IMU biases in markdown: per problem name, the error of the IMU-only
    adjustment's and GP-SLAM's mean biases against the truth's (RMS over the three axes,
    mean over the solved runs); and for a name with one run, its true and recovered biases
    per axis (the paper's Table 6 layout, as biases.md). Empty when no run has biases."""
    head = [
        "",
        "runs",
        "gyro IMU only [deg/s]",
        "gyro GP-SLAM",
        "acc IMU only [m/s^2]",
        "acc GP-SLAM",
    ]
    rows, single = [], []
    for row in table.rows:
        runs = [r.data for r in row.runs if r.data is not None and r.data["success"]]
        runs = [d for d in runs if (d.get("details") or {}).get("biases")]
        if not runs:
            continue
        cells = [row.label, str(len(runs))]
        for which in ("gyro", "acc"):
            for est in ("imu_only", "gp_slam"):
                errs = [_bias_error(d["details"]["biases"][which], est) for d in runs]
                errs = [e for e in errs if e is not None]
                cells.append(_m(statistics.fmean(errs) if errs else None, 4))
        rows.append("| " + " | ".join(cells) + " |")
        if len(runs) == 1:
            single.append((row.label, runs[0]))
    if not rows:
        return ""
    out = [
        "#### Recovered IMU biases",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
        *rows,
        "",
        "Error of the run's mean bias against the true mean bias, RMS over the three axes, "
        "mean over the solved runs.",
        "",
    ]
    for label, d in single:
        out += [f"{label}:", "", bias_table(d["details"], d.get("stages") or []).rstrip(), ""]
    return "\n".join(out)


def _bias_error(b: dict[str, Any], est: str) -> float | None:
    """RMS over the axes of an estimate's mean bias minus the truth's (None when either is
    unknown)."""
    if b.get("truth") is None or b.get(est) is None:
        return None
    return float(np.sqrt(np.mean(np.subtract(b[est], b["truth"]) ** 2)))


def imu_latex_table(table: Table) -> str:
    """``casmag imu`` results as a LaTeX ``table`` (the columns of imu_markdown_table)."""
    out = [
        r"\begin{table}[htbp]",
        r"\centering",
        r"\begin{tabular}{lrrrrl}",
        r"\hline",
        r" & IMU-only RMSE [m] & worst & GP-SLAM RMSE [m] & worst & solved \\",
        r"\hline",
    ]
    for row in table.rows:
        s = ImuSummary.of(row)
        cells = [
            _latex_label(row.label),
            _m(s.imu_only.mean),
            _m(s.imu_only.worst),
            _m(s.gp_slam.mean),
            _m(s.gp_slam.worst),
            _latex_label(s.status_text()),
        ]
        out.append(" & ".join(cells) + r" \\")
    caption = _latex_label(_heading(table)) + f": position errors against truth, {table.frame}."
    out += [r"\hline", r"\end{tabular}", rf"\caption{{{caption}}}", rf"\label{{tab:{table.name}}}"]
    out += [r"\end{table}", ""]
    return "\n".join(out)


def _imu_csv_rows(table: Table) -> list[list[Any]]:
    rows = []
    for row in table.rows:
        s = ImuSummary.of(row)
        failed = {k: n for k, n in s.statuses.items() if k != "Solve_Succeeded"}
        for line, rmse, worst, iters in (
            ("imu_only", s.imu_only, s.imu_only_max, s.iterations_imu_only),
            ("gp_slam", s.gp_slam, s.gp_slam_max, s.iterations),
        ):
            rows.append(
                [
                    table.name,
                    row.key,
                    line,
                    row.label,
                    len(row.runs),
                    s.solved,
                    len(row.runs) - s.solved,
                    0,
                    0,
                    ";".join(f"{k}:{n}" for k, n in sorted(failed.items())),
                    _num(rmse.mean),
                    _num(rmse.std),
                    _num(rmse.worst),
                    _num(worst.mean),
                    _num(worst.std),
                    _num(worst.worst),
                    "",
                    "",
                    "",
                    "",
                    _num(iters),
                    "",
                    "",
                ]
            )
    return rows


def _m(value: float | None, digits: int = 4) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _ratio(ours: float | None, paper: float | None) -> str:
    if ours is None or paper is None or paper == 0:
        return "n/a"
    return f"{ours / paper:.2f}"


def _target_text(line: Line) -> str:
    if line.kind != "after":
        return ""
    t = line.summary.target()
    if t is None:
        return ""
    met = line.summary.target_met()
    verdict = "yes" if met else "no"
    if not line.summary.complete:
        verdict = "no (not every seed solved)"
    return f"<= {t[0]:.4f} ({t[1]}): {verdict}"


def _heading(table: Table) -> str:
    if table.paper is not None:
        return f"Table {table.paper.number}: {table.title or table.paper.caption}"
    return table.title or table.name


def markdown_table(table: Table, figures: dict[str, str] | None = None) -> str:
    """One table in markdown; with ``figures`` ({kind: relative path}) links to them."""
    if table.kind == "imu":
        return imu_markdown_table(table)
    has_paper = table.paper is not None
    lines = table_lines(table)
    out = [f"### {_heading(table)}", ""]
    if has_paper:
        out.append(f"Varies: {table.paper.varies}. Source: `{table.source}`.")
        out.append("")
    if has_paper:
        head = [
            "",
            "RMSE [m] mean",
            "std",
            "worst",
            "paper",
            "ours/paper",
            "Max Error [m] mean",
            "std",
            "worst",
            "paper",
            "ours/paper",
            "solved",
            "iterations",
            "target: mean RMSE",
        ]
    else:
        head = [
            "",
            "RMSE [m] mean",
            "std",
            "worst",
            "Max Error [m] mean",
            "std",
            "worst",
            "solved",
            "iterations",
        ]
    out.append("| " + " | ".join(head) + " |")
    out.append("|" + "---|" * len(head))
    for ln in lines:
        s = ln.summary
        runs = s.runs_text() if ln.kind == "after" else ""
        iters = _m(s.iterations, 1) if ln.kind == "after" else ""
        cells = [ln.label, _m(ln.rmse.mean), _m(ln.rmse.std), _m(ln.rmse.worst)]
        if has_paper:
            cells += [_m(ln.paper_rmse, 3), _ratio(ln.rmse.mean, ln.paper_rmse)]
        cells += [_m(ln.max.mean), _m(ln.max.std), _m(ln.max.worst)]
        if has_paper:
            cells += [_m(ln.paper_max, 3), _ratio(ln.max.mean, ln.paper_max)]
        cells += [runs, iters]
        if has_paper:
            cells.append(_target_text(ln))
        out.append("| " + " | ".join(cells) + " |")
    out.append("")
    seeds = _seed_text(table)
    note = (
        f"Position errors in metres against the truth, {table.frame}; mean, sample standard "
        f"deviation and worst case over the solved seeds{seeds}. Runs whose IPOPT solve failed "
        "are counted under 'solved' with their status and left out of the statistics (solved "
        "runs whose verdict does not trust them are counted as 'not trusted', "
        "casmag.result.verdict); "
        "'iterations' is the mean IPOPT iteration count."
    )
    if has_paper:
        note += (
            " The paper reports one run per row. Target: our mean RMSE after at or below the "
            "paper's where its GP-SLAM improved on odometry, else at most "
            f"{NEVER_WORSE:g} x our mean RMSE before; a row with unsolved seeds does not meet it."
        )
    out.append(note)
    out += consistency_lines(table)
    if figures:
        out.append("")
        for kind, rel in figures.items():
            out.append(f"![{table.name} {kind}]({rel})")
    out.append("")
    return "\n".join(out)


#: The orientation error each motion model's result reports (``details``), and its name.
ORIENTATION_ERRORS = {
    "heading_rms_deg_after": "heading",
    "attitude_rms_deg_after": "attitude",
}


def _yaw_rate_bias(d: dict[str, Any]) -> tuple[float, float] | None:
    """(estimated, true) heading- or yaw-rate bias [rad/s] of a planar or pose result on
    simulated data (casmag.solver.oriented), None otherwise."""
    details, true = d.get("details") or {}, d.get("odometry_bias_true")
    if d.get("motion") == "planar" and d.get("odometry_bias") and true:
        return float(d["odometry_bias"][-1]), float(true[0])
    if d.get("motion") == "pose" and details.get("bias_w") and details.get("bias_w_true"):
        return float(details["bias_w"][2]), float(details["bias_w_true"][2])
    return None


def consistency_lines(table: Table) -> list[str]:
    """A second markdown table for the rows whose solved runs report them: the Laplace
    covariance's consistency (median over the seeds of each run's mean NEES against the
    expected value, and the seeds whose mean NEES is above the range an honest covariance
    gives it, ``uncertainty.nees_interval_95``; covariances withheld or not computed are
    counted), the orientation error after (mean) and, for the simulated planar and pose
    problems, the heading- or yaw-rate bias estimated against the truth. Empty when no row
    has any of these."""
    rows = []
    for row in table.rows:
        solved = [r.data for r in row.runs if r.solved and r.data is not None]
        u = [d.get("uncertainty") or {} for d in solved]
        nees = [x for x in u if x.get("nees_mean") is not None]
        not_given = sum(1 for x in u if "error" in x)
        above = sum(
            1 for x in nees if x["nees_mean"] > (x.get("nees_interval_95") or [np.inf] * 2)[1]
        )
        orient = [
            (name, float(d["details"][key]))
            for d in solved
            for key, name in ORIENTATION_ERRORS.items()
            if (d.get("details") or {}).get(key) is not None
        ]
        biases = [b for b in (_yaw_rate_bias(d) for d in solved) if b is not None]
        if not (nees or not_given or orient or biases):
            continue
        cells = [row.label]
        if nees:
            med = statistics.median(x["nees_mean"] for x in nees)
            expected = nees[0]["nees_expected"]
            cells += [f"{med:.2f} ({expected:g})", f"{above}/{len(nees)}"]
        else:
            cells += ["-", "-"]
        cells.append(str(not_given) if not_given else "")
        if orient:
            cells.append(f"{orient[0][0]} {statistics.fmean(v for _, v in orient):.2f}")
        else:
            cells.append("-")
        if biases:
            err = [abs(e - t) for e, t in biases]
            cells.append(f"{1e3 * biases[0][1]:.3g}: {1e3 * max(err):.3g}")
        else:
            cells.append("-")
        rows.append("| " + " | ".join(cells) + " |")
    if not rows:
        return []
    head = [
        "",
        "mean NEES, median over seeds (expected)",
        "seeds above the honest range",
        "covariance not given",
        "orientation RMS after [deg], mean",
        "rate bias true: worst error [mrad/s]",
    ]
    return [
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
        *rows,
        "",
        "The Laplace covariance of the solved runs (casmag.solver.uncertainty): each run's "
        "mean NEES against the truth, the number of runs above the 95 % range an honest "
        "covariance gives it (uncertainty.nees_interval_95), and the runs whose covariance was "
        "withheld (the verdict did not trust them) or not computed; the heading (planar) or "
        "attitude (pose) error after; the heading- or yaw-rate bias of the simulated planar "
        "and pose problems, its true value and the largest error of its estimate.",
    ]


def _seed_text(table: Table) -> str:
    seeds = sorted(table.seeds)
    if not seeds:
        return ""
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 1:
        return f" ({len(seeds)} seeds per row, {seeds[0]}-{seeds[-1]})"
    return f" (seeds {', '.join(map(str, seeds))})"


def markdown(tables: list[Table], figures: dict[str, dict[str, str]] | None = None) -> str:
    figures = figures or {}
    return "\n".join(markdown_table(t, figures.get(t.name)) for t in tables)


CSV_COLUMNS = (
    "table",
    "row",
    "line",
    "label",
    "runs_expected",
    "runs_solved",
    "runs_failed",
    "runs_error",
    "runs_missing",
    "failed_statuses",
    "rmse_mean",
    "rmse_std",
    "rmse_worst",
    "max_mean",
    "max_std",
    "max_worst",
    "paper_rmse",
    "paper_max",
    "rmse_ratio",
    "max_ratio",
    "iterations_mean",
    "target_rmse",
    "target_met",
)


def _num(value: float | None) -> str:
    return "" if value is None else f"{value:.6g}"


def csv_text(tables: list[Table]) -> str:
    """Every printed line of every table, machine-readable (metres, full precision)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for t in tables:
        if t.kind == "imu":
            w.writerows(_imu_csv_rows(t))
            continue
        for ln in table_lines(t):
            s = ln.summary
            target = s.target() if ln.kind == "after" else None
            met = s.target_met() if ln.kind == "after" else None
            w.writerow(
                [
                    t.name,
                    "" if ln.label == "Before SLAM" else s.row.key,
                    ln.kind,
                    ln.label,
                    s.row.expected,
                    s.solved,
                    sum(s.failed.values()),
                    s.errors,
                    s.missing,
                    ";".join(f"{k}:{n}" for k, n in sorted(s.failed.items())),
                    _num(ln.rmse.mean),
                    _num(ln.rmse.std),
                    _num(ln.rmse.worst),
                    _num(ln.max.mean),
                    _num(ln.max.std),
                    _num(ln.max.worst),
                    _num(ln.paper_rmse),
                    _num(ln.paper_max),
                    _num(
                        None
                        if not ln.paper_rmse or ln.rmse.mean is None
                        else ln.rmse.mean / ln.paper_rmse
                    ),
                    _num(
                        None
                        if not ln.paper_max or ln.max.mean is None
                        else ln.max.mean / ln.paper_max
                    ),
                    _num(s.iterations) if ln.kind == "after" else "",
                    _num(target[0]) if target else "",
                    "" if met is None else str(met).lower(),
                ]
            )
    return buf.getvalue()


_LATEX_ESCAPES = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "#": r"\#",
    "_": r"\_",
    "$": r"\$",
    "{": r"\{",
    "}": r"\}",
    "~": r"\~{}",
    "^": r"\^{}",
}


def _latex_label(text: str) -> str:
    out = "".join(_LATEX_ESCAPES.get(c, c) for c in text)
    out = out.replace(r"sigma\_f", r"$\sigma_f$").replace("<=", r"$\le$")
    if out.startswith(("l = ", "l=")):
        out = "$l$" + out[1:]
    return out.replace(", l = ", ", $l$ = ")


def latex_table(table: Table) -> str:
    """One table as a LaTeX ``table`` (plain tabular, no extra packages): mean +- std and
    worst per error, the paper's value and the ratio ours/paper."""
    if table.kind == "imu":
        return imu_latex_table(table)
    has_paper = table.paper is not None
    cols = "l" + ("rrrr" if has_paper else "rr") * 2 + "r"
    head = [r"RMSE [m]", "worst"] + (["paper", "ratio"] if has_paper else [])
    head += ["Max Error [m]", "worst"] + (["paper", "ratio"] if has_paper else []) + ["solved"]
    out = [
        r"\begin{table}[htbp]",
        r"\centering",
        rf"\begin{{tabular}}{{{cols}}}",
        r"\hline",
        " & " + " & ".join(head) + r" \\",
        r"\hline",
    ]

    def pm(st: Stats) -> str:
        if st.mean is None:
            return "n/a"
        return f"{st.mean:.4f}" + ("" if st.std is None else rf" $\pm$ {st.std:.4f}")

    for ln in table_lines(table):
        cells = [_latex_label(ln.label), pm(ln.rmse), _m(ln.rmse.worst)]
        if has_paper:
            cells += [_m(ln.paper_rmse, 3), _ratio(ln.rmse.mean, ln.paper_rmse)]
        cells += [pm(ln.max), _m(ln.max.worst)]
        if has_paper:
            cells += [_m(ln.paper_max, 3), _ratio(ln.max.mean, ln.paper_max)]
        cells.append(_latex_label(ln.summary.runs_text()) if ln.kind == "after" else "")
        out.append(" & ".join(cells) + r" \\")
    caption = _latex_label(_heading(table)) + (
        ". Mean $\\pm$ sample standard deviation and worst case over the solved seeds"
        + _latex_label(_seed_text(table))
        + f"; position errors against truth, {table.frame}."
    )
    out += [r"\hline", r"\end{tabular}", rf"\caption{{{caption}}}", rf"\label{{tab:{table.name}}}"]
    out += [r"\end{table}", ""]
    return "\n".join(out)


def latex(tables: list[Table]) -> str:
    return "\n".join(latex_table(t) for t in tables)


# --------------------------------------------------------------------------- figures
def representative(row: Row) -> Run | None:
    """The run a figure shows for a row: the solved seed with the median RMSE after (the
    lower of the two middle ones), else the first run with a trajectory."""
    solved = sorted((r for r in row.runs if r.solved), key=lambda r: r.data["rmse_after"])
    if solved:
        return solved[(len(solved) - 1) // 2]
    for r in sorted(row.runs, key=lambda r: (r.seed is None, r.seed)):
        if (r.path / "trajectory.csv").is_file():
            return r
    return None


def read_trajectory(path: Path) -> dict[str, Any]:
    """trajectory.csv as columns (numpy arrays) by name."""
    import numpy as np

    try:
        with path.open() as fh:
            header = fh.readline().strip().split(",")
        values = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: cannot read trajectory ({exc})") from None
    if values.shape[1] != len(header):
        raise DataError(f"{path}: {values.shape[1]} values per row for {len(header)} columns")
    cols = dict(zip(header, values.T, strict=True))
    for name in ("x_odo", "y_odo", "x_est", "y_est"):
        if name not in cols:
            raise DataError(f"{path}: column {name!r} is missing")
    return cols


def _short(table: Table) -> str:
    return f"Table {table.paper.number}" if table.paper is not None else table.name


def _tex(text: str) -> str:
    """A label for matplotlib: sigma_f as mathtext."""
    return text.replace("sigma_f", r"$\sigma_f$")


def _grid_shape(n: int) -> tuple[int, int]:
    ncols = 1 if n == 1 else 2 if n <= 4 else 3
    return math.ceil(n / ncols), ncols


def _panel_title(row: Row, run: Run) -> str:
    title = f"{_tex(row.label)} (seed {run.seed})"
    if run.solved:
        d = run.data
        trusted = (d.get("verdict") or {}).get("trusted", True)
        return (
            title
            + f"\n{d['status']}{'' if trusted else ', NOT TRUSTED'}: "
            + f"RMSE {d['rmse_before']:.3f} -> {d['rmse_after']:.4f} m"
        )
    if run.data is not None:
        return title + f"\nfailed: {run.data['status']}"
    return title + "\nerror"


def trajectories_figure(table: Table, path: Path) -> bool:
    """Per row, odometry only (cyan dashed), GP-SLAM (blue solid) and truth (red triangles)
    of the representative seed, as the paper's Figures 1-4. False if nothing to draw."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    panels = [(row, representative(row)) for row in table.rows]
    panels = [(row, run) for row, run in panels if run is not None]
    panels = [(row, run) for row, run in panels if (run.path / "trajectory.csv").is_file()]
    if not panels:
        return False
    nrows, ncols = _grid_shape(len(panels))
    fig = Figure(figsize=(4.2 * ncols, 4.0 * nrows))
    for i, (row, run) in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        c = read_trajectory(run.path / "trajectory.csv")
        ax.plot(c["x_odo"], c["y_odo"], "--", color="c", lw=1.2, label="odometry only")
        ax.plot(c["x_est"], c["y_est"], "-", color="b", lw=1.2, label="GP-SLAM")
        if "x_true" in c:
            ax.plot(c["x_true"], c["y_true"], "^", color="r", ms=3, mfc="none", label="truth")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(_panel_title(row, run), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("x [m]", fontsize=8)
        ax.set_ylabel("y [m]", fontsize=8)
        if i == 0:
            ax.legend(fontsize=7, loc="best")
    fig.suptitle(_tex(_heading(table)), fontsize=9)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return True


def cost_figure(table: Table, path: Path) -> bool:
    """Objective per IPOPT iteration of each row's representative seed (the paper's Figure
    7; every solve of the run one after another when the run recorded them), its final
    status in the legend. False if no run recorded its cost."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(6.4, 4.0))
    ax = fig.add_subplot()
    drawn, positive = False, True
    for row in table.rows:
        run = representative(row)
        data = (run.data or {}) if run else {}
        stages = data.get("convergence") or []
        cost = [v for st in stages for v in st.get("objective", [])] or data.get(
            "cost_per_iteration"
        )
        if not cost:
            continue
        cost = [float(c) for c in cost if c is not None]
        positive = positive and all(c > 0 for c in cost)
        label = f"{_tex(row.label)} ({data.get('status', '?')})"
        ax.plot(cost, "o-", ms=2.5, lw=1, label=label)
        drawn = True
    if not drawn:
        return False
    ax.set_yscale("log" if positive else "symlog")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("IPOPT iteration (every solve of the run)")
    ax.set_ylabel("objective")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    ax.set_title(f"{_short(table)}: cost per IPOPT iteration (median seed of each row)", fontsize=9)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return True


def rmse_figure(table: Table, path: Path) -> bool:
    """RMSE after of every solved seed per row (dots) and their mean (blue bar), the paper's
    value (red cross) and our mean RMSE before (grey bar): the spread behind the table."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    summaries = [RowSummary.of(r) for r in table.rows]
    if not any(s.solved for s in summaries):
        return False
    fig = Figure(figsize=(max(4.0, 1.3 * len(summaries) + 1.5), 4.0))
    ax = fig.add_subplot()
    for i, s in enumerate(summaries):
        ys = [float(r.data["rmse_after"]) for r in s.row.runs if r.solved]
        xs = [i + 0.15 * ((k % 5) - 2) / 2 for k in range(len(ys))]
        ax.plot(xs, ys, "o", color="b", ms=3, alpha=0.7, label="ours, per seed" if i == 0 else None)
        if s.rmse_after.mean is not None:
            ax.hlines(
                s.rmse_after.mean,
                i - 0.25,
                i + 0.25,
                color="b",
                lw=1.5,
                label="ours, after (mean)" if i == 0 else None,
            )
        if s.rmse_before.mean is not None:
            ax.hlines(
                s.rmse_before.mean,
                i - 0.3,
                i + 0.3,
                color="0.5",
                lw=2,
                label="ours, before (mean)" if i == 0 else None,
            )
        if s.row.paper is not None:
            ax.plot(
                [i],
                [s.row.paper.rmse_after],
                "x",
                color="r",
                ms=8,
                mew=2,
                label="paper, after" if i == 0 else None,
            )
    ax.set_yscale("log")
    ax.set_xticks(
        range(len(summaries)), [_tex(s.row.label) for s in summaries], fontsize=7, rotation=15
    )
    ax.set_ylabel("RMSE after [m]")
    ax.grid(alpha=0.3, which="both", axis="y")
    ax.legend(fontsize=7)
    ax.set_title(f"{_short(table)}: RMSE after SLAM per seed", fontsize=9)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return True


def map_figure(table: Table, path: Path) -> bool:
    """The saved field-map images (``map.png``, estimated field magnitude with the estimated
    path) of the first seed of each row that has one, side by side."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.image import imread

    panels = []
    for row in table.rows:
        runs = sorted(
            (r for r in row.runs if (r.path / "map.png").is_file()),
            key=lambda r: (r.seed is None, r.seed),
        )
        if runs:
            panels.append((row, runs[0]))
    if not panels:
        return False
    nrows, ncols = _grid_shape(len(panels))
    fig = Figure(figsize=(4.4 * ncols, 3.9 * nrows))
    for i, (row, run) in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        try:
            ax.imshow(imread(run.path / "map.png"))
        except (OSError, ValueError, SyntaxError) as exc:
            raise DataError(f"{run.path / 'map.png'}: cannot read image ({exc})") from None
        ax.set_axis_off()
        ax.set_title(f"{_tex(row.label)} (seed {run.seed})", fontsize=8)
    fig.suptitle(f"{_short(table)}: estimated field magnitude (first seed of each row)", fontsize=9)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return True


FIGURES = {
    "trajectories": trajectories_figure,
    "rmse": rmse_figure,
    "cost": cost_figure,
    "map": map_figure,
}


# --------------------------------------------------------------------------- writing
def write_report(tables: list[Table], out_file: Path, figures: bool = True) -> list[Path]:
    """Write ``out_file`` (markdown) and, beside it, the same stem as .csv and .tex, and the
    figures in ``figures/`` next to it (``<table>_<kind>.png``). Everything is written to
    temporary files first and renamed into place only once all of it is complete."""
    if out_file.suffix != ".md":
        raise DataError(f"{out_file}: --out must end in .md (.csv and .tex are written beside it)")
    out_dir = out_file.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_file.stem}.", dir=out_dir))
    try:
        fig_dir = out_dir / "figures"
        links: dict[str, dict[str, str]] = {}
        staged: list[tuple[Path, Path]] = []
        if figures:
            for t in tables:
                if t.kind != "slam":  # IMU results: their own figures are in their folders
                    continue
                for kind, draw in FIGURES.items():
                    name = f"{t.name}_{kind}.png"
                    if draw(t, tmp / name):
                        staged.append((tmp / name, fig_dir / name))
                        rel = os.path.relpath(fig_dir / name, out_dir)
                        links.setdefault(t.name, {})[kind] = rel
        texts = {
            ".md": markdown(tables, links),
            ".csv": csv_text(tables),
            ".tex": latex(tables),
        }
        for suffix, text in texts.items():
            (tmp / f"table{suffix}").write_text(text)
            staged.append((tmp / f"table{suffix}", out_file.with_suffix(suffix)))
        if staged and figures:
            fig_dir.mkdir(exist_ok=True)
        for src, dst in staged:
            os.replace(src, dst)
        # Into a result folder: what the report added belongs to casmag too (casmag.result.outdir).
        record_written(out_dir, [out_file.with_suffix(s).name for s in texts] + ["figures"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [dst for _, dst in staged]
