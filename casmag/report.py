"""Tables from saved results (never re-solves).

Reads ``result.json`` files and writes the paper's layout: a "Before SLAM" row and one
"After SLAM, <name>" row per result, with RMSE [m] and Max Error [m] (no alignment).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from casmag.errors import DataError


def find_results(paths: list[Path]) -> list[Path]:
    """result.json files: the paths themselves, or found recursively under folders."""
    found: list[Path] = []
    for p in paths:
        if p.is_file():
            found.append(p)
        elif p.is_dir():
            found.extend(sorted(p.rglob("result.json")))
        else:
            raise DataError(f"{p}: no such file or folder")
    if not found:
        raise DataError(f"{', '.join(map(str, paths))}: no result.json found")
    return found


def load_result(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: cannot read result ({exc})") from None
    for key in (
        "status",
        "success",
        "rmse_before",
        "max_before",
        "rmse_after",
        "max_after",
        "info",
    ):
        if key not in data:
            raise DataError(f"{path}: field {key!r} is missing")
    return data


def _m(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4f}"


def markdown_table(results: list[dict[str, Any]]) -> str:
    """The paper's layout. Before SLAM comes from the first result (all share the data when
    they differ only in the model); failed solves show their IPOPT status instead of numbers."""
    lines = [
        "|  | RMSE [m] | Max Error [m] | IPOPT iterations | status |",
        "|---|---|---|---|---|",
    ]
    first = results[0]
    lines.append(f"| Before SLAM | {_m(first['rmse_before'])} | {_m(first['max_before'])} |  |  |")
    for r in results:
        name = r["info"].get("name", "")
        if r["success"]:
            row = f"| After SLAM, {name} | {_m(r['rmse_after'])} | {_m(r['max_after'])} |"
        else:
            row = f"| After SLAM, {name} | failed | failed |"
        lines.append(f"{row} {r['iterations']} | {r['status']} |")
    lines.append("")
    lines.append("Position errors against truth, no alignment.")
    return "\n".join(lines) + "\n"
