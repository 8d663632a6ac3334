"""The benchmark driver's outputs (casmag.experiments.bench), without the solves."""

import json

from click.testing import CliRunner

from casmag.experiments import bench


def test_area_writes_json_and_png(tmp_path, monkeypatch):
    """``bench area`` asks for every area and form in its own process (here a stand-in)
    and writes area.json (every run, a crashed one as failed) and area.png."""
    calls = []

    def spawn(args):
        calls.append(args)
        form = args[args.index("--form") + 1]
        if "50.0, 70.0" in " ".join(args) and form == "reduced_rank":
            return {"args": args, "status": "crashed: MemoryError", "success": False}
        return {
            "form": form,
            "success": True,
            "status": "Solve_Succeeded",
            "iterations_total": 10,
            "wall_seconds": 1.0,
            "seconds_per_iteration_last_stage": 0.1,
            "peak_rss_gib": 0.5,
            "rmse_before": 0.2,
            "rmse_after": 0.01,
        }

    monkeypatch.setattr(bench, "_spawn", spawn)
    out = CliRunner().invoke(bench.main, ["area", "--out", str(tmp_path), "--samples", "50"])
    assert out.exit_code == 0, out.output
    assert len(calls) == 2 * len(bench.AREAS)
    assert all("simulation.field.method=dipoles" in c for c in calls)
    runs = json.loads((tmp_path / "area.json").read_text())["runs"]
    assert [r["area"] for r in runs[::2]] == [list(a) for a in bench.AREAS]
    assert sum(not r["success"] for r in runs) == 1
    assert (tmp_path / "area.png").stat().st_size > 0
