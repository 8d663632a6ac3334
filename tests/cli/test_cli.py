"""The command line: outputs, exit codes, one-line errors, no half-written output."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from casmag.cli.main import main

ROOT = Path(__file__).resolve().parents[2]
BASE = ROOT / "problems/paper/base.yaml"
TINY = ["--set", "simulation.trajectory.samples=12"]


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_run_writes_result_csv_and_figures(tmp_path):
    out = tmp_path / "out"
    res = _run(["run", BASE, "--out", out, *TINY, "--set", "seed=7"])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    for key in (
        "status",
        "success",
        "iterations",
        "solve_seconds",
        "rmse_before",
        "max_before",
        "rmse_after",
        "max_after",
        "hyperparameters",
    ):
        assert key in r
    assert r["success"] is True and r["info"]["seed"] == 7
    assert set(r["hyperparameters"]) == {"sigma_f", "lengthscale", "sigma_m"}
    with (out / "trajectory.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 12
    assert {"x_odo", "y_odo", "x_est", "y_est", "x_true", "y_true"} <= set(rows[0])
    for png in ("trajectory.png", "cost.png", "map.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary folders left


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--set", "model.gp.lenghtscale=0.1"], "model.gp.lenghtscale: unknown key"),
        (["--set", "simulation.field.lengthscale=-1"], "simulation.field.lengthscale"),
        (["--set", "seed=seven"], "seed"),
        (["--set", "novalue"], "override must look like"),
    ],
)
def test_bad_input_one_line_exit_2_no_output(tmp_path, args, needle):
    out = tmp_path / "out"
    res = _run(["run", BASE, "--out", out, *args])
    assert res.exit_code == 2
    err = res.stderr if hasattr(res, "stderr") else res.output
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0], err
    assert not out.exists()


def test_bad_file_names_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("seed: 1\nsimulation:\n  trajectory:\n    samplez: 3\n")
    res = _run(["run", bad, "--out", tmp_path / "o"])
    assert res.exit_code == 2
    assert "bad.yaml: simulation.trajectory.samplez: unknown key" in res.output


def test_existing_output_survives_bad_input(tmp_path):
    out = tmp_path / "out"
    assert _run(["run", BASE, "--out", out, *TINY]).exit_code == 0
    before = (out / "result.json").read_text()
    assert _run(["run", BASE, "--out", out, "--set", "seed=x"]).exit_code == 2
    assert (out / "result.json").read_text() == before


def test_solver_failure_exit_1_with_status(tmp_path):
    out = tmp_path / "out"
    res = _run(["run", BASE, "--out", out, *TINY, "--set", "solver.max_iter=1"])
    assert res.exit_code == 1
    assert "Maximum_Iterations_Exceeded" in res.output
    r = json.loads((out / "result.json").read_text())
    assert r["success"] is False and r["rmse_after"] is None


def test_console_script_version():
    exe = Path(sys.executable).with_name("casmag")
    out = subprocess.run([str(exe), "--version"], capture_output=True, text=True, check=True)
    assert "0.1.0" in out.stdout


def test_progress_lines_unless_quiet(tmp_path):
    res = _run(["run", BASE, "--out", tmp_path / "a", *TINY])
    assert res.exit_code == 0
    lines = [line for line in res.stderr.splitlines() if line.strip().startswith("iter")]
    r = json.loads((tmp_path / "a" / "result.json").read_text())
    assert len(lines) == r["iterations"] + 1
    quiet = _run(["run", BASE, "--out", tmp_path / "b", *TINY, "--quiet"])
    assert quiet.exit_code == 0 and quiet.output == ""
