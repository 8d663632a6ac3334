"""The report generator reads saved results only (hand-made files here)."""

import json

from click.testing import CliRunner

from casmag.cli import main


def _write(path, name, success=True, after=0.003):
    path.mkdir(parents=True)
    data = {
        "info": {"name": name},
        "status": "Solve_Succeeded" if success else "Maximum_Iterations_Exceeded",
        "success": success,
        "iterations": 12,
        "rmse_before": 0.066,
        "max_before": 0.112,
        "rmse_after": after if success else None,
        "max_after": 0.005 if success else None,
    }
    (path / "result.json").write_text(json.dumps(data))


def test_report_layout(tmp_path):
    _write(tmp_path / "a", "sigma_f = 0.100")
    _write(tmp_path / "b", "sigma_f = 0.001", success=False)
    out = tmp_path / "t.md"
    res = CliRunner().invoke(main, ["report", str(tmp_path), "--out", str(out)])
    assert res.exit_code == 0, res.output
    text = out.read_text()
    assert "| Before SLAM | 0.0660 | 0.1120 |" in text
    assert "| After SLAM, sigma_f = 0.100 | 0.0030 | 0.0050 | 12 | Solve_Succeeded |" in text
    assert (
        "| After SLAM, sigma_f = 0.001 | failed | failed | 12 | Maximum_Iterations_Exceeded |"
        in text
    )


def test_report_bad_inputs(tmp_path):
    res = CliRunner().invoke(main, ["report", str(tmp_path / "missing")])
    assert res.exit_code == 2 and "no such file" in res.output
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "result.json").write_text("{not json")
    res = CliRunner().invoke(main, ["report", str(tmp_path / "x")])
    assert res.exit_code == 2 and "cannot read result" in res.output
    (tmp_path / "x" / "result.json").write_text(json.dumps({"status": "x"}))
    res = CliRunner().invoke(main, ["report", str(tmp_path / "x")])
    assert res.exit_code == 2 and "missing" in res.output
