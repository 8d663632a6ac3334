"""The report generator reads saved results only (hand-made files here)."""

import csv
import json
import statistics

import numpy as np
import pytest
from click.testing import CliRunner

from casmag.cli.main import main
from casmag.experiments.sweep import MANIFEST_FORMAT
from casmag.problem.paper import TABLES

PNG = b"\x89PNG\r\n\x1a\n"


def _invoke(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _write(path, name, success=True, after=0.003, seed=None, before=(0.066, 0.112), **extra):
    path.mkdir(parents=True)
    data = {
        "info": {"name": name, "seed": seed},
        "status": "Solve_Succeeded" if success else "Maximum_Iterations_Exceeded",
        "success": success,
        "iterations": 12,
        "rmse_before": before[0],
        "max_before": before[1],
        "rmse_after": after if success else None,
        "max_after": 2 * after if success else None,
        "cost_per_iteration": [10.0, 5.0, 1.0, 0.5],
        **extra,
    }
    (path / "result.json").write_text(json.dumps(data))
    return data


def _trajectory(path, n=20, offset=0.01):
    t = np.linspace(0, 4 * np.pi, n)
    x, y = 0.05 * t * np.cos(t) / 4, 0.05 * t * np.sin(t) / 4
    cols = np.column_stack([np.arange(n), x + offset, y + offset, x + 0.001, y, x, y])
    np.savetxt(
        path / "trajectory.csv",
        cols,
        delimiter=",",
        header="k,x_odo,y_odo,x_est,y_est,x_true,y_true",
        comments="",
    )


def _map_png(path):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(1, 1))
    fig.add_subplot().imshow(np.arange(16.0).reshape(4, 4))
    FigureCanvasAgg(fig)
    fig.savefig(path / "map.png")


def _sweep(root, rows, seeds, paper="table1", name="table1", variants=None):
    """A sweep folder: rows = {key: {seed: dict(after=..., success=..., before=...)}};
    variants = {key: (paper_key, label)} for rows that are not the paper's own."""
    variants = variants or {}

    def row(k):
        if k in variants:
            return {"key": k, "label": variants[k][1], "paper_key": variants[k][0]}
        return {"key": k, "label": TABLES[paper].row(k).label if paper else k, "paper_key": k}

    manifest = {
        "format": MANIFEST_FORMAT,
        "name": name,
        "title": None,
        "paper": paper,
        "source": "hand-made",
        "problem": "hand-made",
        "seeds": seeds,
        "rows": [row(k) for k in rows],
    }
    root.mkdir(parents=True)
    (root / "sweep.json").write_text(json.dumps(manifest))
    for key, runs in rows.items():
        for seed, kw in runs.items():
            run = root / key / f"seed-{seed:04d}"
            if kw == "error":
                run.mkdir(parents=True)
                (run / "error.json").write_text(json.dumps({"error": "RuntimeError: boom"}))
                continue
            _write(run, key, seed=seed, **kw)
            _trajectory(run)
    return root


def _cells(text, label):
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[0] == label:
            return cells
    raise AssertionError(f"no line {label!r} in\n{text}")


# --------------------------------------------------------------------------- loose results
def test_loose_results_layout(tmp_path):
    _write(tmp_path / "a", "sigma_f = 0.100")
    _write(tmp_path / "b", "sigma_f = 0.001", success=False)
    out = tmp_path / "t.md"
    res = _invoke(["report", tmp_path, "--out", out, "--no-figures"])
    assert res.exit_code == 0, res.output
    text = out.read_text()
    assert _cells(text, "Before SLAM")[:4] == ["Before SLAM", "0.0660", "n/a", "0.0660"]
    ok = _cells(text, "After SLAM, sigma_f = 0.100")
    assert ok[1] == "0.0030" and ok[4] == "0.0060" and ok[7] == "1/1" and ok[8] == "12.0"
    failed = _cells(text, "After SLAM, sigma_f = 0.001")
    assert failed[1] == "n/a" and failed[7] == "0/1 (Maximum_Iterations_Exceeded x1)"
    assert (tmp_path / "t.csv").is_file() and (tmp_path / "t.tex").is_file()
    assert not (tmp_path / "figures").exists()


def test_stdout_without_out(tmp_path):
    _write(tmp_path / "a", "base")
    res = _invoke(["report", tmp_path / "a" / "result.json"])
    assert res.exit_code == 0
    assert "| After SLAM, base | 0.0030 |" in res.output
    assert list(tmp_path.iterdir()) == [tmp_path / "a"]


# --------------------------------------------------------------------------- sweeps
def test_sweep_statistics_paper_columns_and_failures(tmp_path):
    ok = {1: {"after": 0.002}, 2: {"after": 0.004}, 3: {"after": 0.006}}
    root = _sweep(
        tmp_path / "runs",
        {
            "sigma_f=0.100": ok,
            # A failed solve carrying a (bogus) error must not be averaged in.
            "sigma_f=1.000": {
                1: {"after": 0.001},
                2: {"success": False, "rmse_after": 0.5},
                3: "error",
            },
            "sigma_f=0.001": {1: {"after": 0.060}, 2: {"after": 0.070}},  # seed 3 never ran
        },
        seeds=[1, 2, 3],
    )
    # _write() ignores rmse_after for failures; write the bogus one by hand.
    failed = root / "sigma_f=1.000" / "seed-0002" / "result.json"
    data = json.loads(failed.read_text())
    data["rmse_after"], data["max_after"] = 0.5, 0.9
    failed.write_text(json.dumps(data))

    out = tmp_path / "paper" / "table1.md"
    res = _invoke(["report", root, "--out", out])
    assert res.exit_code == 0, res.output
    text = out.read_text()
    assert "### Table 1: Error in estimated trajectory for various sigma_f" in text
    before = _cells(text, "Before SLAM")
    assert before[1:6] == ["0.0660", "0.0000", "0.0660", "0.066", "1.00"]

    good = _cells(text, "After SLAM, sigma_f = 0.100")
    std = statistics.stdev([0.002, 0.004, 0.006])
    assert good[1:6] == ["0.0040", f"{std:.4f}", "0.0060", "0.003", "1.33"]
    assert good[6:11] == ["0.0080", f"{2 * std:.4f}", "0.0120", "0.005", "1.60"]
    assert good[11] == "3/3"
    assert good[13] == "<= 0.0030 (paper): no"

    mixed = _cells(text, "After SLAM, sigma_f = 1.000")
    assert mixed[1] == "0.0010" and mixed[3] == "0.0010"  # the failed run's 0.5 is left out
    assert mixed[11] == "1/3 (Maximum_Iterations_Exceeded x1, error x1)"
    assert mixed[13] == "<= 0.0040 (paper): no (not every seed solved)"

    # sigma_f = 0.001: the paper's GP-SLAM made it worse, so the target is 1.05 x before.
    worse = _cells(text, "After SLAM, sigma_f = 0.001")
    assert worse[11] == "2/3 (not run x1)"
    assert worse[13] == "<= 0.0693 (1.05 x before): no (not every seed solved)"

    rows = list(csv.DictReader((tmp_path / "paper" / "table1.csv").read_text().splitlines()))
    by_label = {r["label"]: r for r in rows}
    r = by_label["After SLAM, sigma_f = 0.100"]
    assert float(r["rmse_mean"]) == pytest.approx(0.004)
    assert float(r["rmse_std"]) == pytest.approx(std, rel=1e-5)
    assert float(r["rmse_ratio"]) == pytest.approx(0.004 / 0.003, rel=1e-5)
    assert r["target_met"] == "false" and r["runs_solved"] == "3"
    m = by_label["After SLAM, sigma_f = 1.000"]
    assert m["runs_failed"] == "1" and m["runs_error"] == "1"
    assert m["failed_statuses"] == "Maximum_Iterations_Exceeded:1"
    assert by_label["After SLAM, sigma_f = 0.001"]["runs_missing"] == "1"

    tex = (tmp_path / "paper" / "table1.tex").read_text()
    assert r"\begin{tabular}" in tex and r"After SLAM, $\sigma_f$ = 0.100" in tex
    assert r"0.0040 $\pm$ " in tex and tex.count(r" \\") == 5  # header + 4 lines

    figs = tmp_path / "paper" / "figures"
    for kind in ("trajectories", "rmse", "cost"):
        assert (figs / f"table1_{kind}.png").read_bytes()[:8] == PNG
        assert f"](figures/table1_{kind}.png)" in text
    assert not (figs / "table1_map.png").exists()  # no run saved a map.png
    assert [p.name for p in (tmp_path / "paper").iterdir() if p.name.startswith(".")] == []


def test_target_met_when_every_seed_beats_the_paper(tmp_path):
    root = _sweep(
        tmp_path / "runs",
        {"sigma_f=0.100": {1: {"after": 0.001}, 2: {"after": 0.003}}},
        seeds=[1, 2],
    )
    _map_png(root / "sigma_f=0.100" / "seed-0001")
    res = _invoke(["report", root, "--out", tmp_path / "t.md"])
    assert res.exit_code == 0, res.output
    assert _cells((tmp_path / "t.md").read_text(), "After SLAM, sigma_f = 0.100")[13] == (
        "<= 0.0030 (paper): yes"
    )
    assert (tmp_path / "figures" / "table1_map.png").read_bytes()[:8] == PNG


def test_rows_with_their_own_odometry_get_their_own_before_line(tmp_path):
    root = _sweep(
        tmp_path / "runs",
        {
            "noise=0.5mm": {1: {"after": 0.004, "before": (0.19, 0.33)}},
            "noise=5.0mm": {1: {"after": 0.010, "before": (0.21, 0.35)}},
        },
        seeds=[1],
        paper="table5",
        name="table5",
    )
    res = _invoke(["report", root])
    assert res.exit_code == 0, res.output
    labels = [c.split("|")[1].strip() for c in res.output.splitlines() if c.startswith("| ")]
    assert labels[1:] == [
        "Before SLAM, Odometry noise = 0.5mm",
        "After SLAM, Odometry noise = 0.5mm",
        "Before SLAM, Odometry noise = 5.0mm",
        "After SLAM, Odometry noise = 5.0mm",
    ]
    assert _cells(res.output, "Before SLAM, Odometry noise = 5.0mm")[4] == "0.201"
    # 5.0 mm: the paper improved (0.201 -> 0.154), so the paper's value is the target.
    assert _cells(res.output, "After SLAM, Odometry noise = 5.0mm")[13] == (
        "<= 0.1540 (paper): yes"
    )


def test_several_sweeps_one_report(tmp_path):
    _sweep(tmp_path / "runs" / "table1", {"sigma_f=0.100": {1: {}}}, seeds=[1])
    _sweep(
        tmp_path / "runs" / "table3", {"l=0.4": {1: {}}}, seeds=[1], paper="table3", name="table3"
    )
    res = _invoke(["report", tmp_path / "runs", "--out", tmp_path / "all.md", "--no-figures"])
    assert res.exit_code == 0, res.output
    text = (tmp_path / "all.md").read_text()
    assert text.index("### Table 1:") < text.index("### Table 3:")
    assert "After SLAM, l = 0.4m" in text


def test_report_never_solves(tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the report must not solve")

    monkeypatch.setattr("casmag.solver.api.solve", refuse)
    monkeypatch.setattr("casmag.solve", refuse)
    root = _sweep(tmp_path / "runs", {"sigma_f=0.100": {1: {}}}, seeds=[1])
    assert _invoke(["report", root, "--out", tmp_path / "t.md"]).exit_code == 0


def test_paper_numbers():
    improved = {(t, r.key) for t, tab in TABLES.items() for r in tab.rows if r.improved}
    worse = {(t, r.key) for t, tab in TABLES.items() for r in tab.rows} - improved
    assert worse == {
        ("table1", "sigma_f=0.001"),
        ("table2", "sigma_f=0.001"),
        ("table2", "sigma_f=0.010"),
        ("table4", "l=0.400"),
    }
    assert TABLES["table5"].row("noise=5.0mm").rmse_before == 0.201
    assert [len(t.rows) for t in TABLES.values()] == [4, 4, 2, 4, 3]


# --------------------------------------------------------------------------- bad input
def test_report_bad_inputs(tmp_path):
    res = _invoke(["report", tmp_path / "missing"])
    assert res.exit_code == 2 and "no such file" in res.output
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "result.json").write_text("{not json")
    res = _invoke(["report", tmp_path / "x"])
    assert res.exit_code == 2 and "cannot read result" in res.output
    (tmp_path / "x" / "result.json").write_text(json.dumps({"status": "x"}))
    res = _invoke(["report", tmp_path / "x"])
    assert res.exit_code == 2 and "missing" in res.output
    _write(tmp_path / "y", "y", rmse_after="big")
    res = _invoke(["report", tmp_path / "y"])
    assert res.exit_code == 2 and "y/result.json: field 'rmse_after': expected a number" in (
        res.output
    )
    (tmp_path / "z").mkdir()
    (tmp_path / "z" / "sweep.json").write_text(json.dumps({"format": "other"}))
    res = _invoke(["report", tmp_path / "z"])
    assert res.exit_code == 2 and "z/sweep.json: format" in res.output
    empty = tmp_path / "empty"
    empty.mkdir()
    res = _invoke(["report", empty])
    assert res.exit_code == 2 and "no result.json found" in res.output


def test_bad_input_writes_nothing(tmp_path):
    root = _sweep(tmp_path / "runs", {"sigma_f=0.100": {1: {}, 2: {}}}, seeds=[1, 2])
    out = tmp_path / "rep" / "t.md"
    res = _invoke(["report", root, "--out", tmp_path / "rep" / "t.txt"])
    assert res.exit_code == 2 and "--out must end in .md" in res.output
    # A broken trajectory of the figure's run stops the report before anything is written.
    for seed in (1, 2):
        (root / "sigma_f=0.100" / f"seed-{seed:04d}" / "trajectory.csv").write_text(
            "k,x_odo\n1,a\n"
        )
    res = _invoke(["report", root, "--out", out])
    assert res.exit_code == 2 and "trajectory.csv: cannot read trajectory" in res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1
    assert not out.exists() and not (out.parent / "figures").exists()
    assert list(out.parent.iterdir()) == []


def test_variant_rows_compare_with_their_paper_row(tmp_path):
    """An "estimated" row shares its paper row's published numbers and target: the paper's
    RMSE where the paper improved on odometry, 1.05 x ours before where it made it worse."""
    fixed = {1: {"after": 0.005}, 2: {"after": 0.007}}
    est = {1: {"after": 0.001}, 2: {"after": 0.002}}
    root = _sweep(
        tmp_path / "runs",
        {
            "sigma_f=1.000": fixed,
            "sigma_f=1.000_estimated": est,
            "sigma_f=0.001_estimated": {1: {"after": 0.072}, 2: {"after": 0.070}},
        },
        seeds=[1, 2],
        paper="table2",
        name="table2",
        variants={
            "sigma_f=1.000_estimated": ("sigma_f=1.000", "sigma_f = 1.000, estimated"),
            "sigma_f=0.001_estimated": ("sigma_f=0.001", "sigma_f = 0.001, estimated"),
        },
    )
    out = tmp_path / "t.md"
    res = _invoke(["report", root, "--out", out, "--no-figures"])
    assert res.exit_code == 0, res.output
    text = out.read_text()
    a = _cells(text, "After SLAM, sigma_f = 1.000")
    b = _cells(text, "After SLAM, sigma_f = 1.000, estimated")
    c = _cells(text, "After SLAM, sigma_f = 0.001, estimated")
    assert a[1] == "0.0060" and a[4] == "0.004" and a[5] == "1.50"
    assert a[-1] == "<= 0.0040 (paper): no"
    assert b[1] == "0.0015" and b[4] == "0.004" and b[5] == "0.38"
    assert b[-1] == "<= 0.0040 (paper): yes"
    assert c[4] == "0.206"  # the paper's (worse than odometry) row
    assert c[-1] == "<= 0.0693 (1.05 x before): no"  # 0.071 > 1.05 x 0.066
