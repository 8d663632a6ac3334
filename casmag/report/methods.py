"""Methods side by side on one recording: the dead reckoning, the filter baseline and the MAP.

``casmag slam REC --method both --out DIR`` solves the recording with the MAP (GP-SLAM) and
with the filter baseline (casmag.solver.ekf), each with the same map and settings, and
writes DIR/map/ and DIR/ekf/ (each a whole result folder) and, beside them,
``methods.md`` and ``methods.json`` (one row per method: RMSE and max error against the
truth when the recording has it, wall time, real-time factor, status, whether the verdict
trusts it) and ``methods.png`` (the truth, the dead reckoning and every estimate in one
plot). The wall time is each method's whole run (the problem's defaults estimated from the
data, the solve or filter, the evaluation), so the two are timed the same way; the
real-time factor is the recording's duration over it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from casmag.result.outdir import save_atomic

#: The methods of ``--method both``, in the order they are run and listed.
BOTH = ("map", "ekf")
LABELS = {"map": "GP-SLAM (MAP)", "ekf": "EKF"}
COLOURS = {"map": "tab:blue", "ekf": "tab:orange"}


def rows(results: dict[str, Any], walls: dict[str, float], duration: float | None) -> list[dict]:
    """One row for the dead reckoning, then one per method (``results``: method -> Result,
    ``walls``: method -> wall seconds; duration: the recording's length [s])."""
    first = next(iter(results.values()))
    out: list[dict[str, Any]] = [
        {
            "method": "dead reckoning",
            "rmse": first.rmse_before,
            "max": first.max_before,
            "wall_seconds": None,
            "real_time_factor": None,
            "status": "",
            "trusted": None,
        }
    ]
    for method, r in results.items():
        wall = walls[method]
        out.append(
            {
                "method": LABELS.get(method, method),
                "rmse": r.rmse_after,
                "max": r.max_after,
                "wall_seconds": wall,
                "real_time_factor": None if duration is None else duration / max(wall, 1e-9),
                "status": r.status,
                "trusted": r.trusted,
            }
        )
    return out


def _m(v: float | None, fmt: str = ".4f") -> str:
    return "-" if v is None else format(v, fmt)


def markdown(table: list[dict], source: str) -> str:
    """The rows as a markdown table with a title naming the recording."""
    lines = [
        f"### Methods on {source}",
        "",
        "| method | RMSE [m] | max error [m] | wall [s] | real-time factor | status | trusted |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in table:
        trusted = "" if r["trusted"] is None else ("yes" if r["trusted"] else "NO")
        lines.append(
            f"| {r['method']} | {_m(r['rmse'])} | {_m(r['max'])} | "
            f"{_m(r['wall_seconds'], '.1f')} | {_m(r['real_time_factor'], '.1f')} | "
            f"{r['status']} | {trusted} |"
        )
    lines += [
        "",
        "Errors against the truth, no alignment (none when the recording has no truth); wall "
        "time of each method's whole run; real-time factor: the recording's duration over it.",
        "",
    ]
    return "\n".join(lines)


def figure(results: dict[str, Any], path: Path) -> Figure:
    """The truth, the dead reckoning and each method's estimate (x-y), errors in the legend."""
    first = next(iter(results.values()))
    a = first.arrays
    fig = Figure(figsize=(6.4, 5.6))
    ax = fig.add_subplot()
    if a.get("P_true") is not None:
        ax.plot(*a["P_true"][:, :2].T, "-", color="black", lw=2.2, alpha=0.35, label="truth")
    before = "" if first.rmse_before is None else f", RMSE {first.rmse_before:.3f} m"
    ax.plot(*a["P_odometry"][:, :2].T, "--", color="tab:cyan", lw=1.2, label="odometry" + before)
    for method, r in results.items():
        if not r.success:
            continue
        err = "" if r.rmse_after is None else f", RMSE {r.rmse_after:.3f} m"
        mark = "" if r.trusted else " (NOT TRUSTED)"
        ax.plot(
            *r.arrays["P_estimate"][:, :2].T,
            "-",
            color=COLOURS.get(method),
            lw=1.3,
            label=f"{LABELS.get(method, method)}{err}{mark}",
        )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=7)
    ax.set_title(f"{first.info.get('name', '')}: methods side by side", fontsize=9)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120)
    return fig


def save_methods(
    out_dir: Path,
    results: dict[str, Any],
    walls: dict[str, float],
    duration: float | None,
    source: str,
    figures: bool = True,
) -> Path:
    """Write DIR/<method>/ (each result saved whole), methods.md, methods.json and
    methods.png into out_dir atomically (casmag.result.outdir.save_atomic)."""
    table = rows(results, walls, duration)

    def write(tmp: Path) -> None:
        for method, r in results.items():
            (tmp / method).mkdir()
            r.write_into(tmp / method, figures)
        (tmp / "methods.md").write_text(markdown(table, source))
        record = {"recording": source, "duration_seconds": duration, "rows": table}
        (tmp / "methods.json").write_text(json.dumps(record, indent=2) + "\n")
        if figures:
            figure(results, tmp / "methods.png")

    return save_atomic(out_dir, write)
