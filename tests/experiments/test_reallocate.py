"""The real-field map-once-locate-later benchmark's plumbing (casmag.experiments.reallocate):
the child runs, their records and the table; the benchmark itself is `make
bench-localise-real`."""

import pytest

from casmag.experiments import reallocate


def _run(kind, errors, seconds=10.0, peak=1.0):
    return {"kind": kind, "seconds": seconds, "peak_gib": peak, "status": "Solve_Succeeded",
            "errors": errors}  # fmt: skip


def test_the_table_has_a_row_per_later_recording():
    e3 = {"seq3-drift1.5": {"rmse_before": 0.871, "rmse_after": 0.0104, "max_after": 0.0149}}
    e5 = {"seq5-drift1.5": {"rmse_before": 0.863, "rmse_after": 0.011, "max_after": 0.0178}}
    joint = {**e3, **e5, "seq1-drift0.5": {"rmse_before": 0.29, "rmse_after": 0.02}}
    runs = [
        _run("map", {}, 552.0, 5.3),
        _run("held3", e3, 52.0),
        _run("updated3", e3, 115.0, 3.3),
        _run("joint", joint, 492.0, 8.0),
        _run("joint3", e3, 547.0, 6.6),
    ]
    text = reallocate.table(runs)
    rows = [line for line in text.splitlines() if line.startswith("| seq")]
    assert rows[0] == (
        "| seq3-drift1.5 | 0.871 | 0.0104, 0.015 | 0.0104, 0.015 | 0.0104, 0.015 "
        "| 0.0104, 0.015 | 52 / 115 / 492 | 1.0 / 3.3 / 8.0 |"
    )
    # sequence 5 ran only in the joint solve here: the others are marked missing
    assert (
        rows[1]
        == "| seq5-drift1.5 | 0.863 | - | - | 0.0110, 0.018 | - | - / - / 492 | - / - / 8.0 |"
    )
    assert "The map (sequences 1, 2, 4): 552 s, 5.3 GiB peak, Solve_Succeeded." in text


def test_a_failed_run_is_recorded_with_its_exit_code_and_output(tmp_path):
    row = reallocate.solve("updated3", [tmp_path / "absent.csv"], tmp_path, [])
    assert row["exit_code"] == 2 and "status" not in row
    assert "absent.csv" in row["error"]
    assert row["seconds"] > 0 and row["peak_gib"] > 0


def test_a_session_and_a_single_run_give_their_errors():
    one = {"rmse_before": 0.8, "rmse_after": 0.01, "max_after": 0.02, "info": {}}
    assert reallocate._errors(one, ["seq3"]) == {
        "seq3": {"rmse_before": 0.8, "rmse_after": 0.01, "max_after": 0.02}
    }
    s = {"name": "seq5", "rmse_before": 0.9, "rmse_after": 0.02, "max_after": 0.03}
    both = {**one, "info": {"sessions": [s]}}
    assert reallocate._errors(both, ["seq5"])["seq5"]["rmse_after"] == 0.02


def test_without_the_shared_data_it_says_what_is_missing(tmp_path, monkeypatch):
    problem = tmp_path / "seq1-drift0.5.yaml"
    problem.write_text("name: seq1-drift0.5\nrecording:\n  sequence: ../nowhere/1\n")
    monkeypatch.setattr(reallocate, "PROBLEMS", tmp_path)
    why = reallocate.missing_data()
    assert why is not None and why.startswith(f"{problem}: recording.sequence:")
    assert "1-time.csv not found" in why
    with pytest.raises(SystemExit, match="reallocate: "):
        reallocate.main(["--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()
