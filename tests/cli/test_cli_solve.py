"""``casmag solve FILE``: one command for every kind of problem file, dispatched on the
file's keys (casmag.problem.spec.document_kind)."""

import json
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner
from problem_files import ALL, PROBLEMS

from casmag.cli.main import main
from casmag.errors import ProblemError
from casmag.experiments.realbench import load_real_problem
from casmag.experiments.sweep import TableSpec
from casmag.problem.imu import load_imu_problem
from casmag.problem.oriented import load_oriented_problem
from casmag.problem.spec import DOCUMENT_KINDS, document_kind, load_problem, read_yaml

# What each folder of problems/ holds (the tests' own list, independent of document_kind).
FOLDER_KIND = {
    "paper": None,
    "bench": "translational",
    "imu": "imu",
    "planar": "oriented",
    "pose": "oriented",
    "real": "recording",
}
LOADERS = {
    "translational": load_problem,
    "imu": load_imu_problem,
    "oriented": load_oriented_problem,
    "recording": load_real_problem,
    "table": lambda path: TableSpec.model_validate(read_yaml(path)),
}


def _invoke(args):
    return CliRunner().invoke(main, args)


@pytest.mark.parametrize("path", ALL, ids=lambda p: str(p.relative_to(PROBLEMS)))
def test_every_shipped_file_has_its_kind_and_loads_as_it(path):
    kind = document_kind(read_yaml(path))
    assert kind in DOCUMENT_KINDS
    folder = path.relative_to(PROBLEMS).parts[0]
    # problems/paper holds the base problem and the paper's table files; another folder
    # holds problems of its kind and table files of rows over one of them.
    expected = FOLDER_KIND[folder] or ("translational" if path.stem == "base" else "table")
    if FOLDER_KIND[folder] and "rows" in read_yaml(path):
        table = LOADERS["table"](path)
        assert document_kind(read_yaml(path.parent / table.problem)) == expected
        expected = "table"
    assert kind == expected
    LOADERS[kind](path)


def test_document_kind_reads_the_keys():
    assert document_kind({"rows": []}) == "table"
    assert document_kind({"recording": {}}) == "recording"
    assert document_kind({"sessions": []}) == "recording"
    assert document_kind({"simulation": {"scenario": {}}}) == "imu"
    assert document_kind({"simulation": {"imu": {}}}) == "imu"
    assert document_kind({"motion": {"kind": "pose"}, "simulation": {}}) == "oriented"
    assert document_kind({"simulation": {"trajectory": {}}}) == "translational"
    assert document_kind({"seed": 1}) == "translational"
    # motion.kind names the model in every kind of problem file
    assert document_kind({"motion": {"kind": "imu"}}) == "imu"
    assert document_kind({"motion": {"kind": "translational"}}) == "translational"
    assert document_kind({"motion": {"kind": "wheel"}}) == "oriented"  # named there


@pytest.mark.parametrize(
    ("path", "kind"),
    [("problems/paper/base.yaml", "translational"), ("problems/imu/rectangle.yaml", "imu")],
)
def test_motion_kind_is_taken_by_every_model(path, kind):
    """A translational or IMU file may name its motion model as planar and pose files do;
    the file loads to the same problem, and another model's kind is refused by its key."""
    from casmag.problem.imu import load_imu_problem

    load = load_imu_problem if kind == "imu" else load_problem
    data = read_yaml(Path(path))
    named = {**data, "motion": {"kind": kind}}
    assert document_kind(named) == kind
    assert load(named).spec == load(data).spec
    other = "translational" if kind == "imu" else "imu"
    with pytest.raises(ProblemError) as err:
        load({**data, "motion": {"kind": other}})
    assert err.value.field == "motion.kind"
    with pytest.raises(ProblemError, match="the motion model: translational, planar, pose or"):
        load_oriented_problem({"seed": 1, "motion": {"kind": "wheel"}})


def test_solve_a_translational_file_as_run(tmp_path):
    args = ["problems/paper/base.yaml", "--set", "seed=3", "-q", "--no-figures"]
    a, b = tmp_path / "solve", tmp_path / "run"
    assert _invoke(["solve", *args, "--out", str(a)]).exit_code == 0
    assert _invoke(["run", *args, "--out", str(b)]).exit_code == 0
    ra, rb = (json.loads((d / "result.json").read_text()) for d in (a, b))
    assert ra["status"] == rb["status"] == "Solve_Succeeded"
    assert ra["iterations"] == rb["iterations"]
    assert ra["rmse_after"] == rb["rmse_after"] < ra["rmse_before"]


def test_solve_an_imu_file_as_imu(tmp_path):
    problem = {
        "seed": 2,
        "simulation": {
            "scenario": {"kind": "rectangle", "size": [0.12, 0.08], "loops": 1, "static": 0.5}
        },
        "model": {"keyframe_rate": 5.0, "gp": {"form": "none"}},
        "solver": {"max_iter": 100, "tol": 1e-5},
    }
    path = tmp_path / "imu.yaml"
    path.write_text(yaml.safe_dump(problem))
    out = tmp_path / "out"
    res = _invoke(["solve", str(path), "--out", str(out), "-q", "--no-figures"])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["success"] is True and r["stages"][0]["status"] == "Solve_Succeeded"
    assert (out / "biases.md").is_file()


def test_solve_refuses_a_table_file_naming_sweep(tmp_path):
    out = tmp_path / "out"
    res = _invoke(["solve", "problems/paper/table1.yaml", "--out", str(out)])
    assert res.exit_code == 2
    assert "casmag sweep problems/paper/table1.yaml" in res.output
    assert res.output.count("\n") == 1 and not out.exists()


def test_solve_refuses_set_on_a_real_data_file(tmp_path):
    out = tmp_path / "out"
    res = _invoke(
        ["solve", "problems/real/seq1-drift0.5.yaml", "--out", str(out), "--set", "seed=2"]
    )
    assert res.exit_code == 2
    assert "--set" in res.output and res.output.count("\n") == 1 and not out.exists()


def test_solve_a_file_that_is_not_yaml_exit_2(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("seed: [1,\n")
    res = _invoke(["solve", str(path), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and str(path) in res.output and res.output.count("\n") == 1


@pytest.mark.parametrize(
    ("command", "path", "names"),
    [
        ("run", "problems/paper/table1.yaml", "casmag sweep problems/paper/table1.yaml"),
        ("run", "problems/imu/spiral.yaml", "casmag imu problems/imu/spiral.yaml"),
        ("run", "problems/real/seq1-drift0.5.yaml", "casmag solve problems/real/"),
        ("imu", "problems/paper/base.yaml", "casmag run problems/paper/base.yaml"),
    ],
)
def test_run_and_imu_name_the_command_for_another_kind(tmp_path, command, path, names):
    out = tmp_path / "out"
    res = _invoke([command, path, "--out", str(out)])
    assert res.exit_code == 2
    assert names in res.output and res.output.count("\n") == 1 and not out.exists()


# Each IMU scenario at tiny size (one loop, one turn, one letter; the IMU-only adjustment):
# casmag solve runs every shipped IMU file end to end.
IMU_TINY = {
    "rectangle": ["simulation.scenario.loops=1"],
    "spiral": ["simulation.scenario.turns=1"],
    "handwriting": ["simulation.scenario.passes=1", "simulation.scenario.word=a"],
}


@pytest.mark.parametrize("path", sorted((PROBLEMS / "imu").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_imu_file_is_solved_at_tiny_size(tmp_path, path):
    kind = read_yaml(path)["simulation"]["scenario"]["kind"]
    sets = [*IMU_TINY[kind], "model.gp.form=none"]
    out = tmp_path / "out"
    args = ["solve", str(path), "--out", str(out), "-q", "--no-figures"]
    res = _invoke([*args, *(x for s in sets for x in ("--set", s))])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["stages"][0]["status"] == "Solve_Succeeded"
    assert r["details"]["errors"]["imu_only"]["rmse"] < r["details"]["errors"]["strapdown"]["rmse"]


@pytest.mark.slow
def test_an_imu_map_lengthscale_longer_than_the_path_is_named(tmp_path):
    out = tmp_path / "out"
    sets = [
        "simulation.scenario.loops=1",
        "model.gp.lengthscale=30",
        "model.gp.sigma_f=0.1",
        "solver.max_iter=3",
    ]
    args = ["imu", "problems/imu/rectangle.yaml", "--out", str(out), "-q"]
    res = _invoke([*args, *(x for s in sets for x in ("--set", s))])
    assert res.exit_code == 1  # three iterations: the solve fails, and says so
    assert "model.gp.lengthscale: 30 m is longer than the path's extent" in res.stderr
    r = json.loads((out / "result.json").read_text())
    assert [w["check"] for w in r["warnings"]] == ["lengthscale"]


@pytest.mark.parametrize(
    "path",
    [PROBLEMS / "planar" / "walk.yaml", PROBLEMS / "pose" / "walk.yaml"],  # the drift tables: sweep
    ids=lambda p: f"{p.parent.name}/{p.stem}",
)
def test_every_planar_and_pose_file_is_solved_at_tiny_size(tmp_path, path):
    out = tmp_path / "out"
    args = ["solve", str(path), "--out", str(out), "-q", "--no-figures"]
    # the Laplace covariance is on by default, and solver.uncertainty turns it off
    off = path.parent.name == "pose"
    sets = ["simulation.trajectory.samples=60", f"solver.uncertainty={str(not off).lower()}"]
    res = _invoke([*args, *(x for s in sets for x in ("--set", s))])
    assert res.exit_code == 0, res.output
    r = json.loads((out / "result.json").read_text())
    assert r["motion"] == path.parent.name and r["status"] == "Solve_Succeeded"
    assert r["info"]["samples"] == 60 and r["info"]["seed"] == read_yaml(path)["seed"]
    assert r["rmse_after"] < r["rmse_before"]
    assert r["odometry_bias_true"] is not None and r["info"]["recording"] is None
    assert (r["uncertainty"] is None) == off
    assert off or r["uncertainty"]["nees_expected"] == 2.0
