"""casmag.experiments.truthstart: the two-start comparison of a table's runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from casmag.experiments.truthstart import main, markdown, solve_both, summarise
from casmag.problem.spec import read_yaml

ROOT = Path(__file__).resolve().parents[2]


def _run(seed: int, a: float, b: float, ok: bool = True) -> dict:
    def one(cost: float, rmse: float) -> dict:
        return {"cost": cost, "rmse": rmse, "iterations": 5, "status": "x", "success": ok}

    return {"seed": seed, "dead_reckoning": one(a, 0.01), "truth": one(b, 0.001)}


def test_summary_counts_same_lower_and_higher_optima() -> None:
    runs = [
        _run(1, 10.0, 10.0 + 1e-9),
        _run(2, 10.0, 9.0),
        _run(3, 10.0, 11.0),
        _run(4, 1, 1, False),
    ]
    s = summarise(runs)
    assert (s["runs"], s["both_solved"]) == (4, 3)
    assert (s["same_optimum"], s["truth_start_lower_cost"], s["truth_start_higher_cost"]) == (
        1,
        1,
        1,
    )
    assert s["rmse_dead_reckoning_start"] == pytest.approx(0.01)
    assert s["rmse_truth_start"] == pytest.approx(0.001)
    text = markdown([{"table": "t", "row": "r", **s}])
    assert "| t | r | 4 | 1 | 1 | 1 | 0.0100 | 0.0010 |" in text


def test_true_model_reaches_the_same_optimum_from_both_starts() -> None:
    problem = read_yaml(ROOT / "problems/paper/base.yaml")
    problem["seed"] = 3
    out = solve_both(problem)
    dr, truth = out["dead_reckoning"], out["truth"]
    assert dr["success"] and truth["success"]
    assert dr["cost"] == pytest.approx(truth["cost"], rel=1e-6)
    assert dr["rmse"] < 0.2 * out["rmse_before"]


def test_bad_table_file_is_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "t.yaml"
    bad.write_text("problem: missing.yaml\nrows: []\n")
    assert main([str(bad), "--out", str(tmp_path / "o"), "--seeds", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err
    assert not (tmp_path / "o" / "truth_start.json").exists()
