"""The IMU recordings benchmark's tables (casmag.experiments.imurecbench): rows kept from
earlier calls, failed runs as rows."""

import json

from casmag.experiments.imurecbench import _earlier_runs, lag_table


def _run(scenario, seed, lag):
    row = {"status": "Solve_Succeeded", "rmse_gp_slam": 0.004, "seconds": 20.0}
    row |= {"lag_estimate": 0.01, "lag_removed": 0.0}
    return {"scenario": scenario, "seed": seed, "lag": lag, "as_is": row, "auto": row}


def test_a_table_keeps_the_rows_of_earlier_calls_in_its_own_mode(tmp_path):
    """Runs saved by an earlier call for other scenarios or seeds stay in the table; runs
    of another mode (another lag, the plain recordings) and the ones run now are not read
    again."""
    saved = {
        "rectangle-1-lag0.2": _run("rectangle", 1, 0.2),
        "spiral-1-lag0.2": _run("spiral", 1, 0.2),
        "spiral-1-lag0": _run("spiral", 1, 0.0),
        "spiral-1": {"scenario": "spiral", "seed": 1},
    }
    for stem, run in saved.items():
        (tmp_path / f"{stem}.json").write_text(json.dumps(run))
    now = [_run("spiral", 1, 0.2)]
    earlier = _earlier_runs(tmp_path, "-lag0.2", now)
    assert [(r["scenario"], r["seed"], r["lag"]) for r in earlier] == [("rectangle", 1, 0.2)]
    plain = _earlier_runs(tmp_path, "", [])
    assert [(r["scenario"], r["seed"]) for r in plain] == [("spiral", 1)]


def test_a_failed_run_is_a_row_with_its_error():
    failed = {"scenario": "handwriting", "seed": 2, "lag": 0.2, "error": "DataError: bad"}
    text = lag_table([_run("rectangle", 1, 0.2), failed], {"casadi": "3.8.2"})
    lines = text.splitlines()
    assert lines[2].startswith("| rectangle | 1 | 0.2 | +0.01, 0.004, Solve_Succeeded, 20 |")
    assert lines[3] == "| handwriting | 2 | 0.2 | error: DataError: bad ||"
    assert lines[-1] == "Versions: casadi 3.8.2"
