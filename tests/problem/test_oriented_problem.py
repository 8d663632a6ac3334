"""Planar and pose problem files (casmag.problem.oriented): the motion section picks the
model's schema; null hyperparameters are the simulation's; bad input is one line naming
the key."""

import pytest

from casmag.errors import ProblemError
from casmag.problem.oriented import OrientedProblem, load_oriented_problem
from casmag.problem.spec import document_kind

SIM = {
    "trajectory": {"kind": "walk", "samples": 40, "step": 0.5, "area": [6.0, 3.0]},
    "field": {"kernel": "curl_free", "sigma_f": 1.0, "lengthscale": 1.2, "method": "dipoles"},
    "magnetometer": {"noise": 0.05},
}


def _doc(kind, **extra):
    return {"seed": 1, "motion": {"kind": kind}, "simulation": SIM, **extra}


@pytest.mark.parametrize("kind", ["planar", "pose"])
def test_the_motion_kind_picks_the_model(kind):
    p = load_oriented_problem(_doc(kind))
    assert isinstance(p, OrientedProblem) and p.motion == kind
    assert document_kind(_doc(kind)) == "oriented"
    # each model's own defaults: planar se, pose curl_free; hyperparameters estimated
    assert p.options.kernel == ("se" if kind == "planar" else "curl_free")
    assert p.options.lengthscale == "estimate"
    assert p.options.solver.warm_start.strategy == "growing"


@pytest.mark.parametrize("kind", ["planar", "pose"])
@pytest.mark.parametrize(
    "model",
    [
        {"magnetometer": {"sigma_m": None}, "gp": {"sigma_f": None, "lengthscale": None}},
        {"sigma_m": None, "sigma_f": None, "lengthscale": None},  # the earlier spelling
    ],
)
def test_null_is_the_simulations_value_with_its_kernel(kind, model):
    o = load_oriented_problem(_doc(kind, model=model)).options
    assert (o.sigma_m, o.sigma_f, o.lengthscale, o.kernel) == (0.05, 1.0, 1.2, "curl_free")


def test_null_with_another_kernel_is_refused():
    doc = _doc("planar", model={"gp": {"kernel": "se", "lengthscale": None}})
    with pytest.raises(ProblemError, match=r"model.gp.lengthscale: null is the simulation's"):
        load_oriented_problem(doc)


@pytest.mark.parametrize(
    ("doc", "overrides", "where"),
    [
        ({"seed": 1, "motion": {"kind": "wheel"}}, (), "motion.kind"),
        ({"seed": 1, "motion": "pose"}, (), "motion"),
        (_doc("pose", motion={"kind": "pose", "heading_bias": 0.1}), (), "motion.heading_bias"),
        (_doc("planar"), ("model.sigma_p=0.1",), "model.sigma_p"),
        (
            _doc("planar", model={"form": "tiled", "kernel": "curl_free"}),
            ("solver.warm_start.strategy=sliding",),
            "solver.warm_start.strategy",
        ),
        (_doc("pose"), ("solver.warm_start.window=2",), "solver.warm_start"),
        (_doc("planar", simulation={"trajectory": {"samples": 2}}), (), "simulation"),
    ],
)
def test_bad_input_names_the_key(doc, overrides, where):
    with pytest.raises(ProblemError) as err:
        load_oriented_problem(doc, overrides)
    assert err.value.field.startswith(where)
    assert "\n" not in str(err.value)


def test_overrides_apply_to_a_loaded_problem():
    p = load_oriented_problem(_doc("pose"))
    q = load_oriented_problem(p, ["seed=4", "motion.rate=5.0"])
    assert (q.spec.seed, q.spec.motion.rate) == (4, 5.0) and p.spec.seed == 1
