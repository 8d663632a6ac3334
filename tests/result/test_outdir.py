"""Output folders and interrupts: no user file is ever lost, every failure says what it is.

Each case asserts the exit code, the one-line message and the state of the output folder."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from casmag.cli.main import main
from casmag.interrupt import Interrupted
from casmag.result.outdir import MARKER, OutputError, check_output_dir, save_atomic

ROOT = Path(__file__).resolve().parents[2]
BASE = ROOT / "problems/paper/base.yaml"
TINY = ["--set", "simulation.trajectory.samples=12"]


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _tree(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.mark.parametrize(
    "out", [".", "..", "", "HOME", "/"], ids=["dot", "dotdot", "empty", "home", "root"]
)
def test_dangerous_output_paths_are_refused_before_anything_runs(tmp_path, monkeypatch, out):
    work = tmp_path / "work"
    work.mkdir()
    (work / "keep.txt").write_text("mine")
    (tmp_path / "sibling.txt").write_text("mine too")
    monkeypatch.chdir(work)
    monkeypatch.setenv("HOME", str(tmp_path))
    before = _tree(tmp_path)
    res = _run(["run", BASE, "--out", str(tmp_path) if out == "HOME" else out, *TINY])
    assert res.exit_code == 2, res.output
    assert res.output.count("\n") == 1 and res.output.startswith("casmag: error: --out")
    assert _tree(tmp_path) == before


def test_a_folder_with_other_files_is_refused_and_kept(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    res = _run(["run", BASE, "--out", out, *TINY])
    assert res.exit_code == 2
    assert "holds files casmag did not write (notes.txt)" in res.output
    assert _tree(out) == ["notes.txt"]


def test_a_result_folder_is_replaced_but_not_with_a_users_file_added(tmp_path):
    out = tmp_path / "out"
    assert _run(["run", BASE, "--out", out, *TINY]).exit_code == 0
    assert (out / MARKER).is_file()
    first = (out / "result.json").read_text()
    res = _run(["run", BASE, "--out", out, *TINY, "--set", "seed=2"])
    assert res.exit_code == 0, res.output
    assert (out / "result.json").read_text() != first
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # nothing left beside it
    (out / "mine.txt").write_text("mine")
    res = _run(["run", BASE, "--out", out, *TINY])
    assert res.exit_code == 2 and "mine.txt" in res.output
    assert (out / "mine.txt").read_text() == "mine"


def test_a_report_written_into_a_result_folder_belongs_to_it(tmp_path):
    out = tmp_path / "out"
    assert _run(["run", BASE, "--out", out, *TINY]).exit_code == 0
    assert _run(["report", out, "--out", out / "table.md", "--no-figures"]).exit_code == 0
    assert _run(["run", BASE, "--out", out, *TINY]).exit_code == 0


@pytest.mark.parametrize("where", ["under-a-file", "unwritable"])
def test_an_output_that_cannot_be_written_is_refused_before_the_solve(tmp_path, where):
    if where == "under-a-file":
        (tmp_path / "file").write_text("x")
        out = tmp_path / "file" / "out"
    else:
        if os.geteuid() == 0:
            pytest.skip("root writes into read-only folders")
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        out = ro / "out"
    t0 = time.perf_counter()
    res = _run(["run", BASE, "--out", out])
    assert res.exit_code == 2 and res.output.count("\n") == 1, res.output
    assert time.perf_counter() - t0 < 5  # refused before building or solving


def test_an_interrupted_save_keeps_the_previous_result_and_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    save_atomic(out, lambda d: (d / "result.json").write_text("old"))

    def interrupted(d):
        (d / "result.json").write_text("half")
        raise Interrupted(signal.SIGTERM)

    with pytest.raises(Interrupted):
        save_atomic(out, interrupted)
    assert (out / "result.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_leftovers_of_a_killed_save_are_cleaned_and_a_set_aside_result_restored(tmp_path):
    out = tmp_path / "out"
    save_atomic(out, lambda d: (d / "result.json").write_text("old"))
    # A kill between the two renames: the previous result set aside, a complete new one
    # not yet moved in; and a half-written one from an earlier kill.
    os.replace(out, tmp_path / ".out.old-1-2")
    half = tmp_path / ".out.tmp-abc"
    half.mkdir()
    (half / MARKER).write_text("x\n")
    check_output_dir(out)
    save_atomic(out, lambda d: (d / "result.json").write_text("new"))
    assert (out / "result.json").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_output_error_is_one_line():
    with pytest.raises(OutputError) as exc:
        check_output_dir("")
    assert "\n" not in str(exc.value)


def _spawn(out, *extra):
    # A problem that iterates long enough to be interrupted inside IPOPT.
    cmd = [sys.executable, "-m", "casmag.cli.main", "run", str(BASE), "--out", str(out)]
    cmd += ["--set", "simulation.trajectory.samples=400", "--set", "solver.tol=1e-14"]
    cmd += ["--set", "solver.max_iter=100000", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_ipopt_exits_cleanly_and_keeps_the_previous_output(tmp_path, sig, code):
    out = tmp_path / "out"
    assert _run(["run", BASE, "--out", out, *TINY]).exit_code == 0
    before = (out / "result.json").read_text()
    proc = _spawn(out)
    # Wait for IPOPT's first iteration lines, then signal.
    seen = ""
    while "iter" not in seen:
        line = proc.stderr.readline()
        assert line, proc.stdout.read()
        seen += line
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    last = [x for x in err.splitlines() if not x.startswith("  iter")]
    assert last == [
        f"casmag: error: interrupted ({signal.Signals(sig).name}); no output was replaced"
    ]
    assert (out / "result.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize(
    ("override", "needle"),
    [
        ("model.gp.sigma_f=.inf", "model.gp.sigma_f: Input should be a finite number"),
        ("model.gp.sigma_f=.nan", "model.gp.sigma_f: Input should be a finite number"),
        ("model.gp.sigma_f=1e300", "a value is too large for the numerics"),
    ],
    ids=["inf", "nan", "1e300"],
)
def test_values_the_numerics_cannot_carry_are_one_line_exit_2(tmp_path, override, needle):
    out = tmp_path / "out"
    res = _run(["run", BASE, "--out", out, *TINY, "--set", override, "-q"])
    assert res.exit_code == 2, res.output
    assert res.output.count("\n") == 1 and needle in res.output
    assert not out.exists()


def test_a_problem_file_that_is_not_utf8_is_one_line_exit_2(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"seed: 1\n\xff\xfe name: x\n")
    res = _run(["run", bad, "--out", tmp_path / "out"])
    assert res.exit_code == 2 and res.output.count("\n") == 1
    assert "not UTF-8 text" in res.output and str(bad) in res.output


@pytest.mark.parametrize("seed", ["-1", "4294967296"])
def test_a_seed_numpy_cannot_take_is_refused_at_validation(tmp_path, seed):
    res = _run(["run", BASE, "--out", tmp_path / "out", "--set", f"seed={seed}"])
    assert res.exit_code == 2 and res.output.count("\n") == 1
    assert ": seed: Input should be" in res.output
