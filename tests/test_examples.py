"""The scripts in examples/ run as a user would run them (from the repository's root) and
print what they promise."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(name, *args):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "examples" / name), *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_translational_example_solves_saves_and_loads(tmp_path):
    out = _run("translational.py", tmp_path / "out")
    assert out.startswith("Solve_Succeeded: RMSE")
    assert (tmp_path / "out" / "arrays.npz").is_file()
    listing = _run("saved_result.py", tmp_path / "out")
    assert "GP-SLAM: Solve_Succeeded" in listing and "P_estimate: (81, 2)" in listing


@pytest.mark.slow
def test_imu_example_reports_every_stage(tmp_path):
    out = _run("imu.py", tmp_path / "out")
    assert out.startswith("Solve_Succeeded")
    assert all(f"{s} position RMSE" in out for s in ("strapdown", "imu_only", "gp_slam"))
    assert (tmp_path / "out" / "biases.md").is_file()


def test_recording_example_estimates_the_hyperparameters():
    out = _run("recording.py")
    assert "walk.csv: Solve_Succeeded" in out and "warnings: []" in out
    assert "estimated: ['sigma_f', 'lengthscale', 'sigma_m']" in out


@pytest.mark.slow
def test_planar_example_recovers_the_heading_rate_bias():
    out = _run("planar.py")
    assert out.startswith("Solve_Succeeded") and "heading-rate bias" in out


def test_filter_example_runs_a_motion_model_of_its_own():
    out = _run("filter.py")
    words = out.split()
    filt, dead = float(words[2]), float(words[6])
    scale = float(out.split("odometry scale ")[1].split()[0])
    assert filt < 0.5 * dead, out
    assert abs(scale - 0.93) < 0.05, out
