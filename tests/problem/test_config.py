"""Problem loading and validation (casmag.problem.spec): defaults, strictness, one-line errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from problem_files import TRANSLATIONAL

from casmag import Problem, load_problem
from casmag.errors import ProblemError

REPO_ROOT = Path(__file__).resolve().parents[2]
PROBLEM_FILES = TRANSLATIONAL


def _write(tmp_path: Path, name: str, data) -> Path:
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def _error(problem, overrides=()) -> ProblemError:
    with pytest.raises(ProblemError) as info:
        load_problem(problem, overrides)
    err = info.value
    assert "\n" not in str(err)
    return err


# --------------------------------------------------------------------------- seed
def test_minimal_dict_loads_with_defaults():
    problem = load_problem({"seed": 1})
    assert isinstance(problem, Problem)
    assert problem.spec.seed == 1
    assert problem.source == "<dict>"
    assert problem.name == "problem"
    assert problem.spec.simulation.trajectory.samples == 81
    assert problem.spec.simulation.field.kernel == "se"
    assert problem.spec.model.estimate == []
    assert problem.spec.solver.max_iter == 200


def test_seed_missing():
    err = _error({})
    assert err.field == "seed"
    assert "missing" in err.reason


def test_seed_as_string_is_rejected():
    err = _error({"seed": "7"})
    assert err.field == "seed"


def test_seed_as_bool_is_rejected():
    err = _error({"seed": True})
    assert err.field == "seed"


def test_seed_as_float_is_rejected():
    err = _error({"seed": 1.0})
    assert err.field == "seed"


# --------------------------------------------------------------------------- unknown keys
def test_unknown_top_level_key_in_file(tmp_path):
    path = _write(tmp_path, "typo.yaml", {"seed": 1, "simulaton": {}})
    err = _error(path)
    assert err.field == "simulaton"
    assert err.source == str(path)
    msg = str(err)
    assert "simulaton" in msg
    assert "unknown key" in msg
    assert "typo.yaml" in msg


def test_unknown_nested_key_in_file(tmp_path):
    path = _write(tmp_path, "nested.yaml", {"seed": 1, "model": {"gp": {"lenghtscale": 0.2}}})
    err = _error(path)
    assert err.field == "model.gp.lenghtscale"
    msg = str(err)
    assert "model.gp.lenghtscale" in msg
    assert "unknown key" in msg
    assert "nested.yaml" in msg


def test_unknown_key_in_dict_names_dict_source():
    err = _error({"seed": 1, "solver": {"maxiter": 3}})
    assert err.source == "<dict>"
    assert err.field == "solver.maxiter"
    assert "unknown key" in str(err)


# --------------------------------------------------------------------------- bad values
@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"model": {"gp": {"lengthscale": -0.1}}}, "model.gp.lengthscale"),
        ({"simulation": {"field": {"lengthscale": -0.1}}}, "simulation.field.lengthscale"),
        ({"simulation": {"field": {"sigma_f": 0.0}}}, "simulation.field.sigma_f"),
        ({"simulation": {"trajectory": {"samples": 1}}}, "simulation.trajectory.samples"),
        ({"simulation": {"field": {"kernel": "rbf"}}}, "simulation.field.kernel"),
        ({"model": {"gp": {"kernel": "rbf"}}}, "model.gp.kernel"),
        ({"simulation": {"odometry": {"bias": [1e-3, 1e-3, 1e-3]}}}, "simulation.odometry.bias"),
        ({"simulation": {"odometry": {"bias": [1e-3]}}}, "simulation.odometry.bias"),
        ({"simulation": {"magnetometer": {"noise": -1.0}}}, "simulation.magnetometer.noise"),
        ({"model": {"estimate": ["sigma_q"]}}, "model.estimate.0"),
        ({"solver": {"hessian": "bfgs"}}, "solver.hessian"),
        ({"solver": {"max_iter": 0}}, "solver.max_iter"),
    ],
)
def test_bad_value_names_field(data, field):
    err = _error({"seed": 1, **data})
    assert err.field == field
    assert field in str(err)


def test_estimate_twice_is_rejected():
    err = _error({"seed": 1, "model": {"estimate": ["sigma_f", "lengthscale", "sigma_f"]}})
    assert err.field.startswith("model")
    assert "estimate" in str(err)


def test_estimate_twice_names_estimate_field():
    err = _error({"seed": 1, "model": {"estimate": ["sigma_f", "sigma_f"]}})
    assert err.field == "model.estimate"


# --------------------------------------------------------------------------- file errors
def test_invalid_yaml_names_file(tmp_path):
    path = _write(tmp_path, "broken.yaml", "seed: 1\nmodel: [gp\n")
    err = _error(path)
    assert err.source == str(path)
    assert "broken.yaml" in str(err)
    assert "invalid YAML" in str(err)


def test_top_level_list_is_rejected(tmp_path):
    path = _write(tmp_path, "list.yaml", "- seed\n- 1\n")
    err = _error(path)
    assert "list.yaml" in str(err)
    assert "mapping" in err.reason


def test_empty_file_is_rejected(tmp_path):
    path = _write(tmp_path, "empty.yaml", "")
    err = _error(path)
    assert "empty.yaml" in str(err)


def test_missing_file(tmp_path):
    path = tmp_path / "does_not_exist.yaml"
    err = _error(path)
    assert "does_not_exist.yaml" in str(err)


def test_file_loads_and_is_named_after_file(tmp_path):
    path = _write(tmp_path, "mine.yaml", {"seed": 3})
    problem = load_problem(str(path))
    assert problem.spec.seed == 3
    assert problem.source == str(path)
    assert problem.name == "mine"


# --------------------------------------------------------------------------- overrides
def test_override_seed_is_int():
    problem = load_problem({"seed": 1}, ["seed=7"])
    assert problem.spec.seed == 7
    assert type(problem.spec.seed) is int


def test_override_sigma_f():
    problem = load_problem({"seed": 1}, ["model.gp.sigma_f=1.5"])
    assert problem.spec.model.gp.sigma_f == 1.5
    assert problem.assumed_sigma_f == 1.5


def test_override_samples():
    problem = load_problem({"seed": 1}, ["simulation.trajectory.samples=12"])
    assert problem.spec.simulation.trajectory.samples == 12


def test_overrides_apply_to_file(tmp_path):
    path = _write(tmp_path, "base.yaml", {"seed": 1, "model": {"gp": {"sigma_f": 0.2}}})
    problem = load_problem(path, ["seed=5", "model.gp.sigma_f=0.3"])
    assert problem.spec.seed == 5
    assert problem.spec.model.gp.sigma_f == 0.3


def test_overrides_apply_to_problem():
    base = load_problem({"seed": 1})
    assert load_problem(base) is base
    changed = load_problem(base, ["seed=9", "model.estimate=[sigma_f]"])
    assert changed.spec.seed == 9
    assert changed.spec.model.estimate == ["sigma_f"]
    assert base.spec.seed == 1


def test_override_does_not_mutate_input():
    data = {"seed": 1, "model": {"gp": {"sigma_f": 0.2}}}
    load_problem(data, ["model.gp.sigma_f=0.4"])
    assert data == {"seed": 1, "model": {"gp": {"sigma_f": 0.2}}}


def test_override_unknown_key():
    err = _error({"seed": 1}, ["nonsense.key=1"])
    assert "unknown key" in str(err)
    assert "nonsense" in err.field


def test_override_unknown_nested_key():
    err = _error({"seed": 1}, ["model.gp.lenghtscale=0.2"])
    assert err.field == "model.gp.lenghtscale"
    assert "unknown key" in str(err)


def test_override_bad_value_is_validated():
    err = _error({"seed": 1}, ["model.gp.lengthscale=-1"])
    assert err.field == "model.gp.lengthscale"


@pytest.mark.parametrize("text", ["seed", "=3", "a..b=1", "seed=[1"])
def test_malformed_override(text):
    _error({"seed": 1}, [text])


def test_override_without_equals_names_it():
    err = _error({"seed": 1}, ["seed"])
    assert "key.path=value" in str(err)


def test_override_through_a_value():
    err = _error({"seed": 1}, ["seed.x=1"])
    assert err.field == "seed"


def test_override_exponent_without_dot():
    problem = load_problem({"seed": 1}, ["model.gp.sigma_f=1e-3"])
    assert problem.spec.model.gp.sigma_f == pytest.approx(1e-3)


# --------------------------------------------------------------------------- resolved defaults
def test_assumed_values_default_to_truth():
    problem = load_problem(
        {
            "seed": 1,
            "simulation": {
                "field": {"kernel": "curl_free", "sigma_f": 0.3, "lengthscale": 0.4},
                "magnetometer": {"noise": 0.01},
                "odometry": {"noise": 0.002},
            },
        }
    )
    assert problem.assumed_kernel == "curl_free"
    assert problem.assumed_sigma_f == 0.3
    assert problem.assumed_lengthscale == 0.4
    assert problem.assumed_sigma_m == 0.01
    assert problem.assumed_sigma_odometry == 0.002


def test_assumed_values_use_model_when_given():
    problem = load_problem(
        {
            "seed": 1,
            "model": {
                "gp": {"kernel": "div_free", "sigma_f": 0.5, "lengthscale": 0.6},
                "magnetometer": {"sigma_m": 0.07},
                "odometry": {"sigma": 0.08},
            },
        }
    )
    assert problem.assumed_kernel == "div_free"
    assert problem.assumed_sigma_f == 0.5
    assert problem.assumed_lengthscale == 0.6
    assert problem.assumed_sigma_m == 0.07
    assert problem.assumed_sigma_odometry == 0.08


def test_zero_magnetometer_noise_needs_sigma_m():
    err = _error({"seed": 1, "simulation": {"magnetometer": {"noise": 0.0}}})
    assert err.field == "model.magnetometer.sigma_m"
    assert "model.magnetometer.sigma_m" in str(err)
    # stating sigma_m explicitly makes it valid
    problem = load_problem(
        {
            "seed": 1,
            "simulation": {"magnetometer": {"noise": 0.0}},
            "model": {"magnetometer": {"sigma_m": 0.01}},
        }
    )
    assert problem.assumed_sigma_m == 0.01


def test_zero_odometry_noise_needs_model_sigma():
    err = _error({"seed": 1, "simulation": {"odometry": {"noise": 0.0}}})
    assert err.field == "model.odometry.sigma"


# --------------------------------------------------------------------------- one-line errors
ONE_LINE_CASES = [
    ({}, ()),
    ({"seed": "a\nb"}, ()),
    ({"seed": 1, "simulation": {"field": {"kernel": "multi\nline"}}}, ()),
    ({"seed": 1, "model": {"estimate": ["sigma_f", "sigma_f"]}}, ()),
    pytest.param(
        {"seed": 1, "weird\nkey": 1},
        (),
        id="newline-in-key",
    ),
    ({"seed": 1}, ("seed",)),
    ({"seed": 1}, ("seed={",)),
    ({"seed": 1}, ("seed='a\nb'",)),
    ({"seed": 1}, ("nonsense.key=1",)),
]


@pytest.mark.parametrize(("data", "overrides"), ONE_LINE_CASES)
def test_error_is_one_line(data, overrides):
    _error(data, overrides)  # asserts no newline in str()


@pytest.mark.parametrize(
    "text",
    [
        "seed: 1\nmodel: [gp\n",
        "seed: 1\n  bad: indent\n",
        "seed: 'unterminated\n",
        "seed: 1\n\tmodel: {}\n",
        "- 1\n- 2\n",
        "just a string\n",
        "",
    ],
)
def test_file_error_is_one_line(tmp_path, text):
    _error(_write(tmp_path, "p.yaml", text))


# --------------------------------------------------------------------------- shipped problems
def test_problem_files_exist():
    assert PROBLEM_FILES, f"no problem files under {REPO_ROOT / 'problems'}"


@pytest.mark.parametrize(
    "path", PROBLEM_FILES, ids=[str(p.relative_to(REPO_ROOT)) for p in PROBLEM_FILES]
)
def test_shipped_problem_loads(path):
    problem = load_problem(path)
    assert problem.source == str(path)


# --------------------------------------------------------------------------- one override string
def test_one_override_string_is_one_override(tmp_path):
    base = REPO_ROOT / "problems/paper/base.yaml"
    assert load_problem(base, overrides="seed=3").spec.seed == 3
    problem = load_problem({"seed": 1}, "simulation.trajectory.samples=12")
    assert problem.spec.simulation.trajectory.samples == 12
    assert load_problem(problem, "seed=5").spec.seed == 5
    assert problem.with_overrides("seed=4").spec.seed == 4
    assert load_problem(base, None).spec.seed == 1


def test_one_override_string_in_the_other_entry_points(tmp_path):
    from casmag.experiments.sweep import load_sweep
    from casmag.problem.imu import load_imu_problem
    from casmag.solver.recslam import slam

    imu = yaml.safe_load((REPO_ROOT / "problems/imu/rectangle.yaml").read_text())
    assert load_imu_problem(imu, "seed=5").spec.seed == 5
    plan = load_sweep(
        REPO_ROOT / "problems/paper/base.yaml",
        tmp_path / "out",
        seeds=1,
        overrides="simulation.trajectory.samples=12",
        grid="model.gp.jitter=1.0e-6,1.0e-5",
    )
    assert [row.problem["simulation"]["trajectory"]["samples"] for row in plan.rows] == [12, 12]
    assert len(plan.rows) == 2
    with pytest.raises(ProblemError) as info:
        slam(tmp_path / "never-read.csv", overrides="seed=3")
    assert info.value.field == "seed" and "no meaning for a recording" in info.value.reason


@pytest.mark.parametrize("bad", [3, b"seed=3", ["seed=3", 4], {3: "seed"}], ids=repr)
def test_overrides_that_are_not_strings_are_a_type_error(bad):
    with pytest.raises(TypeError, match=r"overrides must be|override keys must be"):
        load_problem({"seed": 1}, bad)


def test_overrides_as_a_mapping_equal_the_strings():
    given = {"seed": 3, "model.gp.sigma_f": 0.25, "model.estimate": ["lengthscale"]}
    a = load_problem(REPO_ROOT / "problems/paper/base.yaml", given)
    b = load_problem(
        REPO_ROOT / "problems/paper/base.yaml",
        ["seed=3", "model.gp.sigma_f=0.25", "model.estimate=[lengthscale]"],
    )
    assert a.spec == b.spec and a.spec.seed == 3 and a.spec.model.gp.sigma_f == 0.25
    with pytest.raises(ProblemError) as info:
        load_problem(REPO_ROOT / "problems/paper/base.yaml", {"model.gp.sigma_f": -1})
    assert info.value.field == "model.gp.sigma_f"


# --------------------------------------------------------------------------- key suggestions
@pytest.mark.parametrize(
    ("override", "key", "hint"),
    [
        ("model.gp.lenghtscale=0.3", "model.gp.lenghtscale", "model.gp.lengthscale"),
        ("modle.gp.sigma_f=1", "modle", "model"),
        ("model.lengthscale=0.3", "model.lengthscale", "model.gp.lengthscale"),
    ],
)
def test_an_unknown_key_gets_the_key_it_most_likely_means(override, key, hint):
    with pytest.raises(ProblemError) as err:
        load_problem("problems/paper/base.yaml", [override])
    assert err.value.field == key
    assert err.value.reason == f"unknown key (did you mean '{hint}'?)"


def test_an_unknown_key_with_no_likely_meaning_gets_no_guess():
    with pytest.raises(ProblemError) as err:
        load_problem("problems/paper/base.yaml", ["model.foo=1"])
    assert err.value.reason == "unknown key"


@pytest.mark.parametrize("model", ["planar", "pose"])
def test_every_model_spells_its_field_keys_in_gp_and_magnetometer(model):
    """The planar and pose models take model.gp.* and model.magnetometer.sigma_m as the
    translational and IMU models do; their earlier top-level spelling (model.sigma_f) still
    loads to the same options, a key given both ways is refused, and a misspelt one gets
    the key in its section."""
    from casmag.problem.imu import load_planar_options
    from casmag.problem.pose import load_pose_options

    load = load_planar_options if model == "planar" else load_pose_options
    nested = load(
        {"model": {"gp": {"lengthscale": 0.3, "num_basis": 90}, "magnetometer": {"sigma_m": 2}}}
    )
    flat = load(None, ["model.lengthscale=0.3", "model.num_basis=90", "model.sigma_m=2"])
    assert nested == flat
    assert (nested.lengthscale, nested.num_basis, nested.sigma_m) == (0.3, 90, 2.0)
    with pytest.raises(ProblemError) as err:
        load(None, ["model.sigma_f=1", "model.gp.sigma_f=2"])
    assert (err.value.field, err.value.reason) == (
        "model",
        "gp.sigma_f is given twice, also as sigma_f (the earlier spelling); keep gp.sigma_f",
    )
    with pytest.raises(ProblemError) as err:
        load(None, ["model.lenghtscale=0.3"])
    assert err.value.reason == "unknown key (did you mean 'model.gp.lengthscale'?)"


# --------------------------------------------------------------------------- typed and keyword
def test_settings_as_keyword_sections_equal_the_dotted_overrides():
    by_keyword = load_problem(
        "problems/paper/base.yaml", seed=7, model={"gp": {"form": "reduced_rank", "sigma_f": 0.2}}
    )
    dotted = load_problem(
        "problems/paper/base.yaml",
        {"seed": 7, "model.gp.form": "reduced_rank", "model.gp.sigma_f": 0.2},
    )
    assert by_keyword.spec == dotted.spec
    assert by_keyword.spec.seed == 7 and by_keyword.spec.model.gp.sigma_f == 0.2


def test_a_keyword_section_with_an_unknown_key_is_refused_naming_it():
    err = _error_kw(model={"gp": {"lenghtscale": 0.3}})
    assert err.field == "model.gp.lenghtscale"
    assert "did you mean 'model.gp.lengthscale'" in err.reason


def _error_kw(**sections):
    with pytest.raises(ProblemError) as info:
        load_problem("problems/paper/base.yaml", **sections)
    return info.value


def test_a_problem_built_from_typed_specs():
    from casmag import ProblemSpec
    from casmag.problem.spec import GPSpec, ModelSpec

    spec = ProblemSpec(seed=4, model=ModelSpec(gp=GPSpec(form="reduced_rank", sigma_f=0.2)))
    problem = load_problem(spec, seed=5)
    assert problem.spec.seed == 5 and problem.spec.model.gp.form == "reduced_rank"
    assert problem.source == "<spec>" and load_problem(spec).spec == spec


@pytest.mark.parametrize(
    ("key", "name"), [("model.gp.sigma_f", "sigma_f"), ("model.gp.lengthscale", "lengthscale")]
)
def test_estimate_as_a_value_lists_the_hyperparameter(key, name):
    """``model.gp.lengthscale: estimate`` (the IMU and recording models' spelling) is the
    same problem as ``model.estimate: [lengthscale]`` with a null value; a start value given
    in the list form stays the start."""
    as_value = load_problem("problems/paper/base.yaml", [f"{key}=estimate"])
    as_list = load_problem("problems/paper/base.yaml", [f"model.estimate=[{name}]"])
    assert as_value.spec == as_list.spec
    assert as_value.spec.model.estimate == [name]
    both = load_problem(
        "problems/paper/base.yaml", [f"{key}=estimate", "model.estimate=[sigma_f, lengthscale]"]
    )
    assert sorted(both.spec.model.estimate) == ["lengthscale", "sigma_f"]


def test_estimate_as_a_value_keeps_the_refusals():
    with pytest.raises(ProblemError, match=r"model\.estimate: sigma_m cannot be estimated"):
        load_problem("problems/paper/base.yaml", ["model.magnetometer.sigma_m=estimate"])
    with pytest.raises(ProblemError, match="cannot be estimated with the reduced-rank"):
        load_problem(
            "problems/paper/base.yaml",
            ["model.gp.form=reduced_rank", "model.gp.lengthscale=estimate"],
        )
    with pytest.raises(ProblemError, match=r"model\.gp\.sigma_f"):
        load_problem("problems/paper/base.yaml", ["model.gp.sigma_f=guess"])


@pytest.mark.parametrize("model", ["planar", "pose"])
def test_null_hyperparameters_of_a_recording_model_say_why(model):
    """A recording has no truth: null (a simulation's true value) is refused naming the key
    and what to give instead."""
    from casmag.problem.imu import load_planar_options
    from casmag.problem.pose import load_pose_options

    load = load_planar_options if model == "planar" else load_pose_options
    for key in ("model.sigma_f", "model.gp.sigma_f"):
        with pytest.raises(ProblemError, match=r"model\.gp\.sigma_f: null means a simulation's"):
            load(None, [f"{key}=null"])
    assert load(None, ["model.gp.sigma_f=estimate"]).sigma_f == "estimate"


@pytest.mark.parametrize("key", ["sigma_f", "lengthscale"])
def test_null_gp_hyperparameters_of_an_imu_problem_say_why(key):
    """null is a simulation's true value; the IMU simulation's field has no GP
    hyperparameters, so null is refused with the reason and what to give instead."""
    from casmag.problem.imu import load_imu_problem

    with pytest.raises(ProblemError) as err:
        load_imu_problem(REPO_ROOT / "problems/imu/rectangle.yaml", [f"model.gp.{key}=null"])
    assert err.value.field == f"model.gp.{key}"
    assert "has no GP hyperparameters: give a number or estimate" in err.value.reason
