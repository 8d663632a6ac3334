"""Box or tiles for a recording whose problem does not choose (casmag.model.mapchoice), and
the choice as ``casmag slam``'s problems make it (casmag.solver.recslam.recording_problem,
the planar and pose options)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import casmag
from casmag.data.simulate import Dataset
from casmag.gp.reduced_rank import MAX_NUM_BASIS
from casmag.model.mapchoice import (
    BOX_FLOPS_LIMIT,
    box_cost,
    box_needed,
    choose_map,
    resolve_options,
)
from casmag.model.rrmap import make_basis
from casmag.problem.imu import PlanarOptions, load_planar_options
from casmag.problem.oriented import load_oriented_problem
from casmag.problem.pose import load_pose_options
from casmag.solver.oriented import solve_oriented
from casmag.solver.recslam import recording_problem

ROOT = Path(__file__).resolve().parents[2]


def loop(width: float, height: float, n: int) -> np.ndarray:
    """n positions around a width x height rectangle's ellipse (m)."""
    a = np.linspace(0.0, 2.0 * np.pi, n)
    return np.column_stack([0.5 * width * np.cos(a), 0.5 * height * np.sin(a)])


@pytest.mark.parametrize(("kernel", "size", "ell"), [("se", 4.0, 0.3), ("curl_free", 3.0, 0.5)])
def test_the_box_cost_counts_the_basis_the_solve_would_build(kernel, size, ell):
    X = loop(size, size, 200)
    cost = box_cost(kernel, X, ell, 60)
    built = make_basis(kernel, X, ell, None, None).num_basis
    assert cost.functions == built < MAX_NUM_BASIS
    per = 3 if kernel == "se" else 1
    assert cost.weights == per * built + 3
    assert cost.flops == pytest.approx(cost.weights**3 / 3 + 60 * cost.weights**2)


def test_a_room_keeps_the_box():
    choice = choose_map("se", loop(3.0, 2.0, 300), 0.4, 3 * 300)
    assert (choice.form, choice.kernel) == ("reduced_rank", "se")
    assert choice.reason.startswith("one box of")
    assert choice.box.flops < BOX_FLOPS_LIMIT
    assert choice.to_dict()["box"]["functions_needed"] == choice.box.functions


def test_a_box_that_would_be_capped_takes_the_tiles():
    # 30 x 30 m at l = 0.3 m: far more than MAX_NUM_BASIS functions.
    choice = choose_map("se", loop(30.0, 30.0, 500), 0.3, 100)
    assert (choice.form, choice.kernel) == ("tiled", "curl_free")
    assert choice.box.capped and "basis functions" in choice.reason
    assert choice.to_dict()["box"]["functions_needed"] > MAX_NUM_BASIS


def test_a_costly_box_takes_the_tiles():
    # The handheld library recording's size: 15 x 15 m, l 0.53 m, SE, a pose per sample.
    X, n = loop(15.0, 15.0, 1586), 1586
    choice = choose_map("se", X, 0.53, 3 * n)
    assert not choice.box.capped
    assert choice.box.flops > BOX_FLOPS_LIMIT
    assert choice.tiled and "flops" in choice.reason
    # The same box with the translational model's knots (one per 10 samples) stays.
    assert choose_map("se", X, 0.53, 2 * (n // 10 + 2)).form == "tiled"  # still 7,000 weights
    assert choose_map("se", loop(5.0, 4.0, n), 0.27, 2 * (n // 10 + 2)).form == "reduced_rank"


def test_a_box_over_the_memory_budget_takes_the_tiles():
    X = loop(3.0, 2.0, 300)
    choice = choose_map("se", X, 0.4, 900, memory_budget=1e-4)
    assert choice.tiled and "memory budget" in choice.reason


def test_a_reason_for_the_box_keeps_it_and_is_said():
    X = loop(30.0, 30.0, 500)
    choice = choose_map("se", X, 0.3, 100, box_only=box_needed(2, "map", False))
    assert (choice.form, choice.kernel) == ("reduced_rank", "se")
    assert "several sessions" in choice.reason
    assert "saved map" in box_needed(1, "map", True)
    assert "filter" in box_needed(1, "ekf", False)
    assert box_needed(1, "map", False) is None


def test_planar_and_pose_options_default_to_the_choice_and_keep_what_is_given():
    assert load_planar_options().form == "auto"
    assert load_pose_options().form == "auto"
    assert load_planar_options(None, ["model.gp.kernel=se"]).form == "reduced_rank"
    assert load_planar_options(None, ["model.gp.num_basis=200"]).form == "reduced_rank"
    assert load_planar_options(None, ["model.gp.kernel=curl_free"]).form == "auto"
    assert load_planar_options(None, ["model.gp.form=tiled", "model.gp.kernel=curl_free"]).form == (
        "tiled"
    )
    sliding = load_planar_options(None, ["solver.warm_start.strategy=sliding"])
    assert sliding.form == "reduced_rank"
    # The library API's own default stays the box.
    assert PlanarOptions().form == "reduced_rank"
    # A simulated planar or pose problem file leaves the choice to the data as a recording.
    for motion in ("planar", "pose"):
        assert load_oriented_problem(ROOT / f"problems/{motion}/walk.yaml").options.form == "auto"
    set_kernel = ["model.gp.kernel=se"]
    assert load_oriented_problem(ROOT / "problems/planar/walk.yaml", set_kernel).options.form == (
        "reduced_rank"
    )


def test_resolving_planar_options():
    wide = loop(30.0, 30.0, 500)
    options, choice = resolve_options(PlanarOptions(form="auto"), wide, 0.3, 1500, None)
    assert (options.form, options.kernel) == ("tiled", "curl_free") and choice.tiled
    options, choice = resolve_options(
        PlanarOptions(form="auto", lengthscale=0.3), wide, 0.3, 1500, None
    )
    assert options.form == "reduced_rank" and "lengthscale given" in choice.reason
    same, none = resolve_options(PlanarOptions(), wide, 0.3, 1500, None)
    assert none is None and same.form == "reduced_rank"


def wide_dataset(seed: int, side: float = 30.0, n: int = 400) -> Dataset:
    """A translational recording's dataset over side x side m with a smooth field."""
    rng = np.random.default_rng(seed)
    P = loop(side, side, n)
    Y = np.column_stack(
        [np.sin(P[:, 0] / 2.0), np.cos(P[:, 1] / 2.0), 0.3 * np.sin((P[:, 0] + P[:, 1]) / 3.0)]
    )
    Y = 40.0 + Y + 0.05 * rng.standard_normal(Y.shape)
    U = np.diff(P, axis=0)
    return Dataset(U=U, Y=Y, anchor=P[0], P_true=P)


def test_a_wide_translational_recording_gets_the_tiles_with_a_constant_field():
    data = wide_dataset(1)
    times = np.arange(data.n_samples) * 0.1
    given = [
        "model.gp.kernel=curl_free",
        "model.gp.lengthscale=0.3",
        "model.gp.sigma_f=1.0",
        "model.magnetometer.sigma_m=0.1",
    ]
    prob, how = recording_problem(data, times, "wide", None, given)
    gp = prob.spec.model.gp
    assert (gp.form, gp.kernel) == ("tiled", "curl_free")
    assert gp.sigma_lin is not None  # the tiles carry the constant field too
    assert how["map_choice"]["form"] == "tiled"
    # A form or an SE kernel given keeps what was given.
    prob, how = recording_problem(data, times, "wide", None, [*given, "model.gp.form=reduced_rank"])
    assert prob.spec.model.gp.form == "reduced_rank" and "map_choice" not in how
    se = [g for g in given if "kernel" not in g] + ["model.gp.kernel=se"]
    prob, how = recording_problem(data, times, "wide", None, se)
    assert prob.spec.model.gp.form == "reduced_rank"
    assert "model.gp.kernel se given" in how["map_choice"]["reason"]
    prob, how = recording_problem(data, times, "wide", None, given, box_only="a saved map")
    assert prob.spec.model.gp.form == "reduced_rank"
    # The tiles asked for without a kernel take the curl-free one; with the SE kernel given
    # the problem is refused.
    tiled = [g for g in given if "kernel" not in g] + ["model.gp.form=tiled"]
    prob, how = recording_problem(data, times, "wide", None, tiled)
    assert (prob.spec.model.gp.form, prob.spec.model.gp.kernel) == ("tiled", "curl_free")
    with pytest.raises(casmag.ProblemError, match=r"tiled needs model\.gp\.kernel: curl_free"):
        recording_problem(data, times, "wide", None, [*tiled, "model.gp.kernel=se"])


def test_a_small_translational_recording_keeps_the_box_by_default():
    data = wide_dataset(2, side=3.0, n=300)
    prob, how = recording_problem(data, np.arange(300) * 0.1, "room")
    gp = prob.spec.model.gp
    assert (gp.form, gp.kernel) == ("reduced_rank", "se")
    assert how["map_choice"]["reason"].startswith("one box of")


@pytest.mark.slow
@pytest.mark.parametrize("motion", ["planar", "pose"])
def test_a_wide_walk_is_solved_on_the_tiles_it_chose(motion):
    problem = load_oriented_problem(
        ROOT / f"problems/{motion}/walk.yaml",
        [
            "simulation.trajectory.samples=40",
            "simulation.trajectory.area=[30.0, 30.0]",
            "model.gp.kernel=curl_free",
            "model.gp.lengthscale=0.4",
            "solver.ipopt.max_iter=3",
        ],
    )
    result = solve_oriented(problem)
    choice = result.info["map_choice"]
    assert choice["form"] == "tiled" and choice["box"]["functions_needed"] > MAX_NUM_BASIS
    assert result.info["map"]["form"] == "tiled" and result.info["kernel"] == "curl_free"
    assert result.iterations is not None


def test_the_translational_box_keeps_a_costlier_factor():
    """Between BOX_FLOPS_LIMIT and TRANSLATIONAL_BOX_FLOPS_LIMIT the translational model
    keeps its box, whose factor it solves faster than the tiles; the planar and pose limit
    takes the tiles there."""
    from casmag.model.mapchoice import TRANSLATIONAL_BOX_FLOPS_LIMIT

    # A 16,000-sample walk's size: 6 x 6 m at l = 0.315 m, SE, a knot per 10 samples.
    X, knots = loop(6.0, 6.0, 2000), 2 * (16_000 // 10 + 2)
    tiles = choose_map("se", X, 0.315, knots)
    box = choose_map("se", X, 0.315, knots, flops_limit=TRANSLATIONAL_BOX_FLOPS_LIMIT)
    assert BOX_FLOPS_LIMIT < box.box.flops < TRANSLATIONAL_BOX_FLOPS_LIMIT
    assert tiles.tiled and "limit 5e+10" in tiles.reason
    assert (box.form, box.kernel) == ("reduced_rank", "se")
