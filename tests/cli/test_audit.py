"""Bad input, interrupted sweeps and concurrent saves: every case asserts the exit code, the
one line on stderr (no traceback) and the state of the output folder (the previous result
intact, or nothing written)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from casmag.cli.main import main
from casmag.data.recording import write_recording
from casmag.problem.imu import STAGED_SOLVER_KEYS
from casmag.result.outdir import MARKER

ROOT = Path(__file__).resolve().parents[2]
BASE = ROOT / "problems/paper/base.yaml"
TINY = ["--set", "simulation.trajectory.samples=12"]


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file under folder (hidden ones too) with its contents."""
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def _one_line(res, *needles: str) -> str:
    """The single non-empty stderr line of a refused command, checked for the needles."""
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.output
    assert "Traceback" not in res.output
    assert lines[0].startswith("casmag: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def previous(tmp_path_factory) -> Path:
    """A finished tiny run, copied into each test's output folder as the previous result."""
    out = tmp_path_factory.mktemp("previous") / "out"
    res = _run(["run", BASE, "--out", out, "--no-figures", "-q", *TINY])
    assert res.exit_code == 0, res.output
    return out


def _with_previous(previous: Path, tmp_path: Path) -> tuple[Path, dict[str, bytes]]:
    import shutil

    out = tmp_path / "out"
    shutil.copytree(previous, out)
    return out, _tree(out)


def _recording(path: Path, n: int = 60, motion: str = "translation", Y=None, truth=True):
    """A small recording: a slow circle, a smooth field (or the given magnetometer)."""
    k = np.arange(n)
    t = 0.1 * k
    P = np.column_stack([np.cos(0.1 * k), np.sin(0.1 * k)])
    if Y is None:
        Y = np.column_stack([np.sin(2 * P[:, 0]), np.cos(3 * P[:, 1]), 0.5 + 0.1 * P[:, 0]])
    if motion == "translation":
        write_recording(path, t, Y, dxy=np.diff(P, axis=0), P_true=P if truth else None)
    else:
        planar = np.column_stack([np.full(n - 1, 0.1), np.zeros(n - 1), np.full(n - 1, 0.1)])
        write_recording(path, t, Y, planar=planar)
    return path


def _imu_problem(tmp_path: Path, **solver) -> Path:
    """A 4-second rectangle on a desk with one dipole (the tests' tiny IMU problem)."""
    data = {
        "seed": 11,
        "simulation": {
            "scenario": {"kind": "rectangle", "size": [0.12, 0.08], "loops": 1, "static": 0.5},
            "field": {"dipoles": [{"position": [0.25, 0.0, -0.1], "moment": [2e-3, 1e-3, -3e-3]}]},
        },
        "model": {
            "keyframe_rate": 5.0,
            "gp": {"sigma_f": 0.3, "lengthscale": 0.2, "num_basis": 40},
        },
        "solver": {"max_iter": 100, "tol": 1e-5, **solver},
    }
    path = tmp_path / "imu.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


# --------------------------------------------------------------------------- IPOPT options
@pytest.mark.parametrize(
    ("override", "needles"),
    [
        ("solver.ipopt.tol=-1", ["solver.ipopt.tol", "out of range", "0 < tol"]),
        ('solver.ipopt.max_iter="x"', ["solver.ipopt.max_iter", "expects an integer"]),
        ("solver.ipopt.max_iter=2.5", ["solver.ipopt.max_iter", "expects an integer"]),
        ("solver.ipopt.mu_strategy=bogus", ["solver.ipopt.mu_strategy", "monotone, adaptive"]),
        ("solver.ipopt.acceptable_tol=fast", ["solver.ipopt.acceptable_tol", "a number"]),
        ("solver.ipopt.no_such_option=1", ["solver.ipopt.no_such_option", "not an IPOPT option"]),
        ("solver.linear_solver=ma27", ["solver.linear_solver", "mumps or spral"]),
        ("solver.ipopt.linear_solver=pardisomkl", ["solver.ipopt.linear_solver", "mumps"]),
        ("solver.ipopt.option_file_name=ipopt.opt", ["solver.ipopt.option_file_name"]),
        # The key as written, not the union member pydantic tried (mu_init.float).
        ("solver.ipopt.mu_init=1e400", ["solver.ipopt.mu_init: ", "finite"]),
    ],
    ids=lambda v: v if isinstance(v, str) else None,
)
def test_a_bad_ipopt_option_is_refused_before_solving(previous, tmp_path, override, needles):
    out, before = _with_previous(previous, tmp_path)
    res = _run(["run", BASE, "--out", out, "--set", override, *TINY])
    assert res.exit_code == 2
    _one_line(res, str(BASE), *needles)
    assert _tree(out) == before


def test_a_bad_ipopt_option_in_an_imu_problem_file_is_refused(tmp_path):
    out = tmp_path / "out"
    problem = _imu_problem(tmp_path, ipopt={"mu_strategy": "bogus"})
    res = _run(["imu", problem, "--out", out])
    assert res.exit_code == 2
    _one_line(res, str(problem), "solver.ipopt.mu_strategy", "not a valid setting")
    assert not out.exists()


def test_valid_ipopt_options_and_yes_no_switches_solve(tmp_path):
    out = tmp_path / "out"
    res = _run(
        ["run", BASE, "--out", out, "-q", "--no-figures", *TINY,
         "--set", "solver.ipopt={acceptable_tol: 1.0e-4, warm_start_init_point: no}",
         "--set", "solver.linear_solver=spral"]
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert res.stderr == ""
    assert json.loads((out / "result.json").read_text())["success"] is True


# --------------------------------------------------------------------------- report
def _slam_result(folder: Path, name: str = "base") -> None:
    folder.mkdir(parents=True)
    data = {
        "info": {"name": name, "seed": 1},
        "status": "Solve_Succeeded",
        "success": True,
        "iterations": 12,
        "rmse_before": 0.066,
        "max_before": 0.112,
        "rmse_after": 0.003,
        "max_after": 0.006,
    }
    (folder / "result.json").write_text(json.dumps(data))


def _imu_result(folder: Path, name: str = "square_table", success: bool = True) -> None:
    """A result.json as ``casmag imu`` wrote it before the one Result (no rmse_before:
    errors per stage at the top level; casmag.result.upgrade_layout reads it)."""
    folder.mkdir(parents=True)
    data = {
        "info": {"name": name, "seed": 1},
        "status": "Solve_Succeeded" if success else "Maximum_Iterations_Exceeded",
        "success": success,
        "iterations": 10,
        "status_imu_only": "Solve_Succeeded",
        "iterations_imu_only": 15,
        "failed_stage": None if success else "gp_slam",
        "errors": {
            "strapdown": {"rmse": 91.2, "max": 239.7},
            "imu_only": {"rmse": 0.1516, "max": 0.1919},
            "gp_slam": {"rmse": 0.0163 if success else None, "max": 0.04 if success else None},
        },
        "flags": [],
    }
    (folder / "result.json").write_text(json.dumps(data))


def test_report_tabulates_imu_results_in_their_own_table(tmp_path):
    _imu_result(tmp_path / "runs" / "imu1")
    _imu_result(tmp_path / "runs" / "imu2", success=False)
    _slam_result(tmp_path / "runs" / "slam")
    out = tmp_path / "rep" / "table.md"
    res = _run(["report", tmp_path / "runs", "--out", out, "--no-figures"])
    assert res.exit_code == 0, res.output
    assert res.stderr == ""
    text = out.read_text()
    assert "### IMU results" in text and "IMU-only RMSE [m] mean" in text
    row = next(line for line in text.splitlines() if line.startswith("| square_table"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1:5] == ["0.1516", "0.1516", "0.0163", "0.0163"]
    assert cells[5].startswith("1/2 solved") and "Maximum_Iterations_Exceeded x1" in cells[5]
    assert cells[6] == "15.0 + 10.0"
    assert "After SLAM, base" in text  # the translational result is still reported
    assert sorted(p.name for p in out.parent.iterdir()) == ["table.csv", "table.md", "table.tex"]
    assert "imu,square_table,gp_slam" in (out.parent / "table.csv").read_text()


def test_report_gives_the_recovered_imu_biases_in_the_papers_table_6_layout(tmp_path):
    biases = {
        "gyro": {"truth": [0.05, -0.08, 0.12], "imu_only": [0.08, -0.08, 0.06],
                 "gp_slam": [0.05, -0.08, 0.11]},
        "acc": {"truth": [0.02, -0.015, 0.03], "imu_only": [0.0, 0.0, 0.03],
                "gp_slam": [0.02, -0.015, 0.03]},
    }  # fmt: skip
    for seed in (1, 2):
        folder = tmp_path / "runs" / f"s{seed}"
        folder.mkdir(parents=True)
        data = {
            "motion": "imu",
            "info": {"name": "table" if seed == 1 else "desk", "seed": seed},
            "status": "Solve_Succeeded",
            "success": True,
            "iterations": 10,
            "rmse_before": 0.1,
            "max_before": 0.2,
            "rmse_after": 0.01,
            "max_after": 0.02,
            "stages": [{"name": "imu_only", "status": "Solve_Succeeded", "iterations": 7}],
            "details": {
                "errors": {"imu_only": {"rmse": 0.1, "max": 0.2}, "gp_slam": {"rmse": 0.01}},
                "biases": biases,
                "map_decision": "map",
            },
        }
        (folder / "result.json").write_text(json.dumps(data))
    res = _run(["report", tmp_path / "runs"])
    assert res.exit_code == 0, res.output
    text = res.stdout
    assert "#### Recovered IMU biases" in text
    row = next(line for line in text.splitlines() if line.startswith("| table | 1 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    gyro_imu_only = np.sqrt(np.mean(np.subtract([0.08, -0.08, 0.06], [0.05, -0.08, 0.12]) ** 2))
    assert cells[2] == f"{gyro_imu_only:.4f}" and cells[3] == "0.0058"  # 0.01 / sqrt(3)
    assert cells[5] == "0.0000"
    assert "| Z | 0.1200 | 0.0600 | 0.1100 | 0.0300 | 0.0300 | 0.0300 |" in text
    assert "| 7.0 + 10.0 |" in text  # the IMU-only stage's iterations, from ``stages``


@pytest.mark.slow
def test_report_of_a_real_imu_result_folder(tmp_path):
    imu_out = tmp_path / "imu"
    res = _run(["imu", _imu_problem(tmp_path), "--out", imu_out, "-q", "--no-figures"])
    assert res.exit_code in (0, 1, 3), res.output  # a failed or flagged solve is a result too
    res = _run(["report", imu_out])
    assert res.exit_code == 0, res.output
    assert res.stderr == ""
    assert "### IMU results" in res.stdout and "| imu |" in res.stdout


@pytest.mark.parametrize("bad", ["{not json", "[1, 2]", '{"status": "x"}', "\udcff"])
def test_report_skips_an_unreadable_result_with_one_warning(tmp_path, bad):
    _slam_result(tmp_path / "runs" / "good")
    broken = tmp_path / "runs" / "broken" / "result.json"
    broken.parent.mkdir(parents=True)
    broken.write_bytes(bad.encode("utf-8", "surrogateescape"))
    out = tmp_path / "rep" / "table.md"
    res = _run(["report", tmp_path / "runs", "--out", out, "--no-figures"])
    assert res.exit_code == 0, res.output
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("casmag: warning: ")
    assert str(broken) in lines[0] and "skipped" in lines[0]
    assert "After SLAM, base" in out.read_text()


def test_report_skips_an_unreadable_sweep_manifest_and_reports_its_runs(tmp_path):
    sweep = tmp_path / "runs" / "sweep"
    _slam_result(sweep / "row" / "seed-0001", name="swept")
    (sweep / "sweep.json").write_text('{"format": "something else"}')
    _imu_result(tmp_path / "runs" / "imu")
    res = _run(["report", tmp_path / "runs"])
    assert res.exit_code == 0, res.output
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and str(sweep / "sweep.json") in lines[0] and "skipped" in lines[0]
    assert "After SLAM, swept" in res.stdout and "### IMU results" in res.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]  # nothing written


def test_report_with_no_readable_result_is_one_line_exit_2(tmp_path):
    for name in ("a", "b"):
        (tmp_path / "runs" / name).mkdir(parents=True)
        (tmp_path / "runs" / name / "result.json").write_text("{broken")
    out = tmp_path / "rep" / "table.md"
    res = _run(["report", tmp_path / "runs", "--out", out])
    assert res.exit_code == 2
    _one_line(res, "no result could be read (2 unreadable", "result.json")
    assert not out.parent.exists()


# --------------------------------------------------------------------------- duplicate keys
DUPLICATES = {
    "top": ("seed: 1\nname: a\nseed: 2\n", "seed", 3, 1),
    "nested": (
        "seed: 1\nsolver:\n  tol: 1.0e-6\n  max_iter: 5\n  tol: 1.0e-3\n",
        "solver.tol",
        5,
        3,
    ),
    "flow": ("seed: 1\nmodel: {gp: {jitter: 1.0e-6, jitter: 1.0e-5}}\n", "model.gp.jitter", 2, 2),
}


@pytest.mark.parametrize("case", list(DUPLICATES))
def test_a_key_given_twice_is_refused_naming_key_and_line(previous, tmp_path, case):
    text, key, line, first = DUPLICATES[case]
    problem = tmp_path / "dup.yaml"
    problem.write_text(text)
    out, before = _with_previous(previous, tmp_path)
    res = _run(["run", problem, "--out", out])
    assert res.exit_code == 2
    _one_line(res, f"{problem}: {key}: duplicate key on line {line} (first on line {first})")
    assert _tree(out) == before


def test_a_key_given_twice_in_an_imu_file_a_table_file_or_a_set_value(tmp_path):
    imu = _imu_problem(tmp_path)
    imu.write_text(imu.read_text() + "seed: 12\n")
    res = _run(["imu", imu, "--out", tmp_path / "o1"])
    assert res.exit_code == 2
    _one_line(res, f"{imu}: seed: duplicate key")
    table = tmp_path / "table.yaml"
    table.write_text(f"problem: {BASE}\nrows:\n  - key: a\n    set: {{seed: 1}}\n    key: b\n")
    res = _run(["sweep", table, "--out", tmp_path / "o2", "--seeds", 1])
    assert res.exit_code == 2
    _one_line(res, f"{table}: rows.0.key: duplicate key on line 5")
    res = _run(["run", BASE, "--out", tmp_path / "o3", "--set", "model.gp={jitter: 1, jitter: 2}"])
    assert res.exit_code == 2
    _one_line(res, "--set: model.gp: value gives the key 'jitter' twice")
    assert not any((tmp_path / f"o{i}").exists() for i in (1, 2, 3))


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("seed: 1\nx: " + "[" * 3000 + "]" * 3000 + "\n", "nested deeper than 64 levels"),
        (
            "seed: 1\na: &a [1,1,1,1,1,1,1,1,1,1]\n"
            + "".join(
                f"{b}: &{b} [{', '.join([f'*{a}'] * 10)}]\n"
                for a, b in zip("abcdefg", "bcdefgh", strict=True)
            ),
            "more than 100000 values (with aliases expanded)",
        ),
        ("seed: " + "9" * 5000 + "\n", "an integer has more digits than Python converts"),
        ("seed: 1\nx: &a [1, *a]\n", "an alias refers to a node that contains it"),
    ],
    ids=["deep", "alias-bomb", "huge-int", "recursive-alias"],
)
def test_yaml_the_parser_cannot_carry_is_one_line(previous, tmp_path, text, needle):
    problem = tmp_path / "p.yaml"
    problem.write_text(text)
    out, before = _with_previous(previous, tmp_path)
    res = _run(["run", problem, "--out", out])
    assert res.exit_code == 2
    _one_line(res, str(problem), needle)
    assert _tree(out) == before


# --------------------------------------------------------------------------- ignored --set keys
@pytest.mark.parametrize(
    ("override", "needle"),
    [
        ("simulation.trajectory.samples=5", "--set: simulation.trajectory.samples: simulation"),
        ("simulation.xxx=1", "--set: simulation.xxx: simulation has no meaning for a recording"),
        ("seed=3", "--set: seed: seed has no meaning for a recording"),
    ],
)
def test_slam_refuses_set_keys_a_recording_ignores(previous, tmp_path, override, needle):
    rec = _recording(tmp_path / "rec.csv")
    out, before = _with_previous(previous, tmp_path)
    res = _run(["slam", rec, "--out", out, "--set", override])
    assert res.exit_code == 2
    _one_line(res, needle)
    assert _tree(out) == before
    # Several sessions too.
    rec2 = _recording(tmp_path / "rec2.csv")
    res = _run(["slam", rec, rec2, "--out", out, "--set", override])
    assert res.exit_code == 2
    _one_line(res, needle)
    assert _tree(out) == before


@pytest.mark.parametrize(
    "override",
    [
        "solver.uncertainty_inflation=2.0",
        "solver.uncertainty=false",
        "solver.warm_start={}",
    ],
)
def test_imu_and_planar_refuse_solver_keys_they_ignore(tmp_path, override):
    key = override.split("=")[0]
    res = _run(["imu", _imu_problem(tmp_path), "--out", tmp_path / "o1", "--set", override])
    assert res.exit_code == 2
    _one_line(res, f"--set: {key}: casmag imu does not use")
    if key in STAGED_SOLVER_KEYS:
        return  # the planar model reads it (warm starts, the Laplace covariance)
    planar = _recording(tmp_path / "planar.csv", motion="planar")
    res = _run(["slam", planar, "--out", tmp_path / "o2", "--set", override])
    assert res.exit_code == 2
    _one_line(res, f"--set: {key}: casmag slam on a planar recording does not use")
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


@pytest.mark.parametrize("command", ["run", "sweep"])
def test_run_and_sweep_refuse_set_keys_the_problem_does_not_have(tmp_path, command):
    out = tmp_path / "out"
    extra = ["--seeds", 1] if command == "sweep" else []
    res = _run([command, BASE, "--out", out, *extra, "--set", "simulation.xxx=1"])
    assert res.exit_code == 2
    _one_line(res, "simulation.xxx: unknown key")
    assert not out.exists()


# --------------------------------------------------------------------------- recordings
@pytest.mark.parametrize(
    ("value", "needle"),
    [
        ("1_000", "not a number ('1_000')"),
        ("\u0661\u0662", "not a number"),
        ("\uff11", "not a number"),
        ("infinity", "value is infinite"),
        ("nan", "value is NaN"),
        ("0x10", "not a number ('0x10')"),
    ],
    ids=["underscore", "arabic-digits", "fullwidth-digit", "infinity", "nan", "hex"],
)
def test_a_recording_number_float_would_take_but_csv_does_not_is_refused(
    previous, tmp_path, value, needle
):
    rec = _recording(tmp_path / "rec.csv")
    lines = rec.read_text().splitlines()
    fields = lines[4].split(",")
    fields[3] = value  # column 'mx' of row 5
    lines[4] = ",".join(fields)
    rec.write_text("\n".join(lines) + "\n", encoding="utf-8")
    out, before = _with_previous(previous, tmp_path)
    res = _run(["slam", rec, "--out", out])
    assert res.exit_code == 2
    _one_line(res, f"{rec}: row 5, column 'mx': {needle}")
    assert _tree(out) == before


# --------------------------------------------------------------------------- sigma_m message
def test_the_sigma_m_message_is_one_line_naming_the_key(previous, tmp_path):
    out, before = _with_previous(previous, tmp_path)
    res = _run(["run", BASE, "--out", out, "--set", "model.estimate=[sigma_m]"])
    assert res.exit_code == 2
    line = _one_line(res, f"{BASE}: model.estimate: sigma_m cannot be estimated")
    assert "got {" not in line and "simulation" not in line and len(line) < 300
    assert _tree(out) == before


# --------------------------------------------------------------------------- extreme data
def test_a_constant_magnetometer_gives_odometry_only(tmp_path):
    rec = _recording(tmp_path / "rec.csv", Y=np.tile([0.3, -0.1, 0.5], (60, 1)))
    out = tmp_path / "out"
    res = _run(["slam", rec, "--out", out, "-q", "--no-figures"])
    assert res.exit_code == 0, res.output
    assert res.stderr == ""
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "Odometry_Only" and r["success"] is True
    assert "magnetometer is constant" in r["info"]["fallback"]
    assert r["rmse_after"] == r["rmse_before"]
    # Forced past the field check: one line, nothing replaced.
    before = _tree(out)
    res = _run(["slam", rec, "--out", out, "--no-field-check"])
    assert res.exit_code == 2
    _one_line(res, f"{rec}: mx, my, mz: the magnetometer is constant")
    assert _tree(out) == before


def test_a_constant_magnetometer_on_a_planar_recording_gives_odometry_only(tmp_path):
    rec = _recording(tmp_path / "planar.csv", motion="planar", Y=np.tile([0.3, 0, 0.5], (60, 1)))
    out = tmp_path / "out"
    res = _run(["slam", rec, "--out", out, "-q"])
    assert res.exit_code == 0, res.output
    assert res.stderr == ""
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "Odometry_Only" and r["iterations"] == 0
    assert "magnetometer is constant" in r["info"]["fallback"]
    assert {"result.json", "trajectory.csv", "trajectory.png", MARKER} <= set(_tree(out))


@pytest.mark.parametrize(
    ("value", "needle"),
    [
        ("1e300", "value 1e+300 is beyond what the numerics can carry (|value| <= 1e+100)"),
        ("1e90", "value 1e+90 is beyond what the numerics can carry: the column sums to 1e+90"),
    ],
)
def test_a_planar_step_the_numerics_cannot_carry_is_refused(previous, tmp_path, value, needle):
    rec = _recording(tmp_path / "planar.csv", motion="planar")
    lines = rec.read_text().splitlines()
    fields = lines[5].split(",")
    fields[1] = value  # column 'dfwd' of row 6
    lines[5] = ",".join(fields)
    rec.write_text("\n".join(lines) + "\n")
    out, before = _with_previous(previous, tmp_path)
    res = _run(["slam", rec, "--out", out])
    assert res.exit_code == 2
    _one_line(res, f"{rec}: row 6, column 'dfwd': {needle}")
    assert _tree(out) == before


def test_an_exact_field_beyond_memory_is_refused_at_validation(previous, tmp_path):
    out, before = _with_previous(previous, tmp_path)
    res = _run(["run", BASE, "--out", out, "--set", "simulation.trajectory.samples=1000000"])
    assert res.exit_code == 2
    line = _one_line(res, f"{BASE}: simulation.trajectory.samples: 1000000 samples with")
    assert "216.0 TB" in line and "more than this machine's" in line
    assert _tree(out) == before


# --------------------------------------------------------------------------- sweeps: signals
def _table(tmp_path: Path) -> Path:
    """A table of a tiny row (each run well under a second) and a big one (400 samples to
    a 1e-14 tolerance: minutes), two seeds each, so that runs finish while one runs on."""
    table = tmp_path / "table.yaml"
    table.write_text(
        textwrap.dedent(
            f"""\
            problem: {BASE}
            rows:
              - key: tiny
                set: {{simulation.trajectory.samples: 12}}
              - key: big
                set: {{simulation.trajectory.samples: 400, solver.tol: 1.0e-14,
                       solver.max_iter: 100000}}
            """
        )
    )
    return table


def _live_processes(pgid: int) -> list[int]:
    """Processes of a process group that are still running (not exited zombies, which an
    exited parent leaves until init reaps them)."""
    live = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            live.append(int(stat.parent.name))
    return live


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_sweep_stops_its_workers_at_once(tmp_path, sig, code):
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "casmag.cli.main",
        "sweep",
        str(_table(tmp_path)),
        "--out",
        str(out),
    ]
    cmd += ["--seeds", "2", "-j", "2", "--figures", "none", "-q"]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob("tiny/seed-*/result.json")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.1)
        saved = {p: p.read_bytes() for p in out.glob("tiny/seed-*/result.json")}
        t0 = time.monotonic()
        if sig == signal.SIGINT:
            os.killpg(proc.pid, sig)  # as a terminal's Ctrl-C: the whole process group
        else:
            proc.send_signal(sig)  # as kill: the sweep process alone
        _, err = proc.communicate(timeout=60)
        seconds = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == code, err
    assert err.splitlines() == [
        f"casmag: error: interrupted ({signal.Signals(sig).name}); saved runs are kept, "
        "rerun the same command to resume"
    ], err
    # The big run (minutes) was stopped, not finished: a worker has STOP_GRACE (5 s).
    assert seconds < 30
    gone = time.monotonic() + 5  # helper processes notice their parent's exit
    while _live_processes(proc.pid) and time.monotonic() < gone:
        time.sleep(0.1)
    assert _live_processes(proc.pid) == []  # every worker is gone
    for path, data in saved.items():
        assert path.read_bytes() == data
    assert not list(out.glob("big/seed-*/result.json"))
    hidden = [p for p in out.rglob(".*") if p.name != MARKER]
    assert hidden == []  # no half-written run folder left


# --------------------------------------------------------------------------- concurrent saves
SAVER = """
import json, random, sys, time
from casmag.result.outdir import save_atomic
from casmag.errors import CasmagError

def write(folder):
    (folder / "result.json").write_text(json.dumps({"writer": sys.argv[2]}))
    time.sleep(random.random() * 0.005)
    (folder / "trajectory.csv").write_text("k\\n" * 2000)

for _ in range(int(sys.argv[3])):
    try:
        save_atomic(sys.argv[1], write)
    except CasmagError as exc:
        print(f"casmag: error: {exc}", file=sys.stderr)
        sys.exit(2)
"""


def test_concurrent_saves_into_one_folder_take_turns(tmp_path):
    out = tmp_path / "out"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", SAVER, str(out), str(i), "150"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(3)
    ]
    results = [p.communicate(timeout=120) for p in procs]
    for p, (_, err) in zip(procs, results, strict=True):
        assert p.returncode == 0, err
        assert err == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it
    assert sorted(_tree(out)) == [MARKER, "result.json", "trajectory.csv"]
    assert json.loads((out / "result.json").read_text())["writer"] in {"0", "1", "2"}
    assert (out / MARKER).read_text().splitlines()[1:] == ["result.json", "trajectory.csv"]


def test_two_runs_into_one_output_folder_leave_one_complete_result(tmp_path):
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "casmag.cli.main",
        "run",
        str(BASE),
        "--out",
        str(out),
        "-q",
        *TINY,
    ]
    procs = [
        subprocess.Popen(
            [*cmd, "--set", f"seed={seed}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for seed in (1, 2)
    ]
    results = [p.communicate(timeout=180) for p in procs]
    for p, (_, err) in zip(procs, results, strict=True):
        assert p.returncode in (0, 2), err
        assert "Traceback" not in err and len(err.splitlines()) <= 1
    assert any(p.returncode == 0 for p in procs)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    names = (out / MARKER).read_text().splitlines()[1:]
    assert sorted(_tree(out)) == sorted([MARKER, *names])
    assert json.loads((out / "result.json").read_text())["info"]["seed"] in (1, 2)


# --------------------------------------------------------------------------- usage errors
@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["sweep", BASE, "--out", "sw", "--seeds", "0"], ["'--seeds'", "casmag sweep --help"]),
        (["run"], ["Missing argument 'PROBLEM'", "casmag run --help"]),
        (["run", BASE, "--bogus"], ["No such option '--bogus'", "casmag run --help"]),
        (["nosuchcommand"], ["No such command 'nosuchcommand'", "casmag --help"]),
    ],
    ids=["out-of-range", "missing-argument", "unknown-option", "unknown-command"],
)
def test_a_usage_error_is_one_line_naming_the_option_and_the_help(tmp_path, args, needles):
    cmd = [sys.executable, "-m", "casmag.cli.main", *map(str, args)]
    res = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("casmag: error: "), res.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["run", "sweep"])
def test_a_set_key_given_twice_is_refused(previous, tmp_path, command):
    out, before = _with_previous(previous, tmp_path)
    res = _run([command, BASE, "--out", out, "--set", "seed=1", "--set", "seed=2"])
    assert res.exit_code == 2
    _one_line(res, "'--set'", "seed is given twice")
    assert _tree(out) == before
