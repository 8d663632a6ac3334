"""The shipped problem files, by kind, for the tests that load or run every one of them."""

from pathlib import Path

from casmag.problem.spec import document_kind, read_yaml

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS = ROOT / "problems"


def _kind(path: Path) -> str:
    """The file's kind as ``casmag solve`` reads it (tests/cli/test_cli_solve.py checks it
    against the folders)."""
    return document_kind(read_yaml(path))


ALL = sorted(PROBLEMS.rglob("*.yaml"))
# Translational problem files (casmag run): not the IMU problems (tests/solver/test_imu.py), not the
# real-data problems (tests/data/test_realdata.py) and not the table files, which list rows of
# overrides of a problem file (tests/experiments/test_sweep.py).
TRANSLATIONAL = [p for p in ALL if _kind(p) == "translational"]
