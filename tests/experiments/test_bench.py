"""The benchmark driver's outputs (casmag.experiments.bench), without the solves."""

import json

from click.testing import CliRunner

from casmag.experiments import bench


def test_area_writes_json_and_png(tmp_path, monkeypatch):
    """``bench area`` asks for every area and form in its own process (here a stand-in)
    and writes area.json (every run, a crashed one as failed) and area.png."""
    calls = []

    def spawn(args, timeout=None):
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


def test_a_run_past_its_time_bound_is_stopped_and_says_so():
    """A configuration still running at ``timeout`` is stopped (here: before the child has
    even imported casmag) and comes back as a failed row naming the bound."""
    row = bench._spawn(["50"], timeout=0.05)
    assert not row["success"]
    assert row["status"] == "stopped: still running after 0.05 s (--timeout)"
    assert row["wall_seconds"] == 0.05


def test_area_keeps_the_rows_it_finished(tmp_path, monkeypatch):
    """area.json is written again after every run: a benchmark stopped part-way keeps what
    it measured."""
    seen = []

    def spawn(args, timeout=None):
        if (tmp_path / "area.json").exists():
            seen.append(len(json.loads((tmp_path / "area.json").read_text())["runs"]))
        return {"args": args, "status": "crashed: stand-in", "success": False}

    monkeypatch.setattr(bench, "_spawn", spawn)
    out = CliRunner().invoke(
        bench.main, ["area", "--out", str(tmp_path), "--forms", "bumps", "--timeout", "5"]
    )
    assert out.exit_code == 0, out.output
    assert seen == list(range(1, len(bench.AREAS)))
    runs = json.loads((tmp_path / "area.json").read_text())["runs"]
    assert [r["form"] for r in runs] == ["bumps"] * len(bench.AREAS)


def _stand_in_row(args):
    form = args[args.index("--form") + 1]
    return {
        "form": form,
        "success": True,
        "status": "Solve_Succeeded",
        "iterations_total": 10,
        "wall_seconds": 1.0 + int(args[0]) / 1000,
        "seconds_per_iteration_last_stage": 0.1,
        "peak_rss_gib": 0.5,
        "rmse_before": 0.2,
        "rmse_after": 0.01,
    }


def test_scale_runs_the_room_box_and_the_building_tiles(tmp_path, monkeypatch):
    """``bench scale`` runs each N as one box in the 6 m room (the box's knots at 64,000) and
    as tiles over 50 m x 70 m in the dipole field; a call for one setting keeps the other's
    rows and the exact comparison's; an unknown setting is refused."""
    calls = []

    def spawn(args, timeout=None):
        calls.append(args)
        return _stand_in_row(args)

    monkeypatch.setattr(bench, "_spawn", spawn)
    run = CliRunner().invoke
    out = run(
        bench.main, ["scale", "--out", str(tmp_path), "--sizes", "1000,64000", "--exact-sizes", ""]
    )
    assert out.exit_code == 0, out.output
    room = [c for c in calls if c[c.index("--form") + 1] == "reduced_rank"]
    building = [c for c in calls if c[c.index("--form") + 1] == "tiled"]
    assert [c[0] for c in room] == [c[0] for c in building] == ["1000", "64000"]
    assert "--knot-every" not in room[0] and room[1][room[1].index("--knot-every") + 1] == "50"
    assert all("--knot-every" not in c for c in building)
    assert all("simulation.trajectory.area=[50.0, 70.0]" in c for c in building)
    assert all("simulation.field.method=dipoles" in c for c in building)
    assert not any("simulation.field.method=dipoles" in c for c in room)
    rows = json.loads((tmp_path / "scale.json").read_text())["runs"]
    assert sorted((r["set"], r["samples"]) for r in rows) == [
        ("building", 1000),
        ("building", 64000),
        ("room", 1000),
        ("room", 64000),
    ]
    assert (tmp_path / "scale.png").stat().st_size > 0

    calls.clear()
    out = run(
        bench.main,
        [
            "scale",
            "--out",
            str(tmp_path),
            "--sizes",
            "4000",
            "--exact-sizes",
            "",
            "--sets",
            "building",
        ],
    )
    assert out.exit_code == 0, out.output
    assert len(calls) == 1
    rows = json.loads((tmp_path / "scale.json").read_text())["runs"]
    assert sorted((r["set"], r["samples"]) for r in rows) == [
        ("building", 4000),
        ("room", 1000),
        ("room", 64000),
    ]

    out = run(bench.main, ["scale", "--out", str(tmp_path), "--sets", "hall"])
    assert out.exit_code != 0 and "hall" in out.output


def test_a_stopped_run_keeps_what_its_progress_lines_said():
    """The progress lines a run prints per IPOPT iteration (iteration 0 of each stage not
    counted) give a stopped run's iterations, seconds and seconds per iteration; a line cut
    off by the stop is passed over; no lines, no figures."""
    lines = [
        bench.PROGRESS
        + json.dumps(
            {
                "iterations": n,
                "stage_iteration": k,
                "stage_seconds": s,
                "wall_seconds": w,
                "cost": c,
            }
        )
        for n, k, s, w, c in [
            (0, 0, 1.0, 1.0, 9.0),
            (1, 1, 3.0, 3.0, 8.0),
            (2, 1, 6.0, 9.0, 7.0),
            (3, 2, 10.0, 13.0, 6.0),
        ]
    ]
    text = "\n".join(["solving ...", *lines, bench.PROGRESS + '{"iterations": 4, "sta'])
    got = bench.progress_so_far(text.encode())
    assert got == {
        "iterations_done": 3,
        "solve_seconds_done": 13.0,
        "stage_iterations_done": 2,
        "seconds_per_iteration_last_stage": 5.0,
        "cost_last": 6.0,
        "peak_rss_gib": 0.0,
    }
    assert bench.progress_so_far(b"Traceback ...") == {}
    assert bench.progress_so_far(None) == {}


def test_area_runs_the_areas_asked_for_and_keeps_the_others(tmp_path, monkeypatch):
    """``--areas`` runs only those areas; the rows of the others already in area.json stay,
    the rows run again are replaced; a malformed area is refused naming the option."""
    monkeypatch.setattr(bench, "_spawn", lambda args, timeout=None: _stand_in_row(args))
    run = CliRunner().invoke
    assert run(bench.main, ["area", "--out", str(tmp_path), "--samples", "50"]).exit_code == 0
    out = run(
        bench.main,
        ["area", "--out", str(tmp_path), "--samples", "70", "--areas", "20x20", "--forms", "bumps"],
    )
    assert out.exit_code == 0, out.output
    runs = json.loads((tmp_path / "area.json").read_text())["runs"]
    assert len(runs) == 2 * len(bench.AREAS)
    walls = {(tuple(r["area"]), r["form"]): r["wall_seconds"] for r in runs}
    assert walls[(20.0, 20.0), "bumps"] == 1.07
    assert walls[(20.0, 20.0), "reduced_rank"] == walls[(6.0, 6.0), "bumps"] == 1.05
    bad = run(bench.main, ["area", "--out", str(tmp_path), "--areas", "20by20"])
    assert bad.exit_code != 0 and "--areas" in bad.output


def test_area_runs_each_tile_basis_as_a_map_of_its_own(tmp_path, monkeypatch):
    """The tiled map's bases are rows of their own: ``hilbert`` and ``bumps`` each ask the
    child for the tiled form with their basis; rows an earlier file calls ``tiled`` (the
    Hilbert tiles, before the bases were told apart) are kept as ``hilbert``; an unknown
    map is refused naming the option."""
    calls = []

    def spawn(args, timeout=None):
        calls.append(args)
        return _stand_in_row(args)

    monkeypatch.setattr(bench, "_spawn", spawn)
    earlier = {"area": [50.0, 70.0], "form": "tiled", "success": False, "status": "stopped"}
    (tmp_path / "area.json").write_text(json.dumps({"runs": [earlier]}))
    run = CliRunner().invoke
    out = run(
        bench.main,
        ["area", "--out", str(tmp_path), "--samples", "50", "--areas", "6x6",
         "--forms", "bumps,hilbert"],
    )  # fmt: skip
    assert out.exit_code == 0, out.output
    assert [c[c.index("--form") + 1] for c in calls] == ["tiled", "tiled"]
    assert ["model.gp.tile_basis=bumps" in c for c in calls] == [True, False]
    assert ["model.gp.tile_basis=hilbert" in c for c in calls] == [False, True]
    runs = json.loads((tmp_path / "area.json").read_text())["runs"]
    assert sorted((tuple(r["area"]), r["form"]) for r in runs) == [
        ((6.0, 6.0), "bumps"),
        ((6.0, 6.0), "hilbert"),
        ((50.0, 70.0), "hilbert"),
    ]
    bad = run(bench.main, ["area", "--out", str(tmp_path), "--forms", "tiled"])
    assert bad.exit_code != 0 and "--forms" in bad.output and "tiled" in bad.output


def test_area_runs_each_start_as_a_row_of_its_own(tmp_path, monkeypatch):
    """``--starts`` asks the child for each start (``--start truth``: one batch from the
    true positions); rows carry their start, rows of an earlier file without one are kept as
    started from the dead reckoning and not replaced by a truth row; an unknown start is
    refused naming the option."""
    calls = []

    def spawn(args, timeout=None):
        calls.append(args)
        return _stand_in_row(args)

    monkeypatch.setattr(bench, "_spawn", spawn)
    earlier = {**_stand_in_row(["50", "--form", "bumps"]), "area": [6.0, 6.0], "form": "bumps",
               "wall_seconds": 9.0}  # fmt: skip
    (tmp_path / "area.json").write_text(json.dumps({"runs": [earlier]}))
    run = CliRunner().invoke
    out = run(
        bench.main,
        ["area", "--out", str(tmp_path), "--samples", "50", "--areas", "6x6",
         "--forms", "bumps", "--starts", "truth"],
    )  # fmt: skip
    assert out.exit_code == 0, out.output
    assert [c[c.index("--start") + 1] for c in calls] == ["truth"]
    runs = json.loads((tmp_path / "area.json").read_text())["runs"]
    assert sorted((r["form"], r["start"], r["wall_seconds"]) for r in runs) == [
        ("bumps", "dead-reckoning", 9.0),
        ("bumps", "truth", 1.05),
    ]
    assert (tmp_path / "area.png").stat().st_size > 0
    bad = run(bench.main, ["area", "--out", str(tmp_path), "--starts", "oracle"])
    assert bad.exit_code != 0 and "--starts" in bad.output and "oracle" in bad.output


def test_one_solves_from_the_truth_when_asked(monkeypatch):
    """``bench one --start truth`` hands the true positions to the solve as its start (one
    batch); the default start hands none."""
    import casmag

    seen = []
    real = casmag.solve

    def solve(problem, data, progress=None, initial_positions=None):
        seen.append(None if initial_positions is None else initial_positions.copy())
        return real(problem, data, progress, initial_positions)

    monkeypatch.setattr(casmag, "solve", solve)
    sets = ["simulation.trajectory.area=[3.0, 3.0]", "solver.warm_start.strategy=none",
            "solver.uncertainty=false"]  # fmt: skip
    row = bench.run_one(120, "reduced_rank", None, extra=tuple(sets), start="truth")
    assert row["start"] == "truth" and row["success"]
    assert seen[0] is not None and seen[0].shape == (120, 2)
    row = bench.run_one(120, "reduced_rank", None, extra=tuple(sets))
    assert row["start"] == "dead-reckoning" and seen[1] is None
