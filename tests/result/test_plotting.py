"""The figures say what happened: read through the matplotlib objects (titles, labels,
artists), not pixels."""

from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.collections import QuadMesh

import casmag
from casmag.result import plotting


def _labels(ax):
    return [t.get_text() for t in ax.get_legend().get_texts()]


@pytest.fixture(scope="module")
def solved():
    return casmag.solve(casmag.load_problem("problems/paper/base.yaml", ["seed=3"]))


@pytest.fixture(scope="module")
def failed():
    problem = casmag.load_problem("problems/paper/base.yaml", ["seed=3", "solver.max_iter=2"])
    return casmag.solve(problem)


def test_trajectory_of_a_solved_run_names_status_marks_start_and_draws_the_error_panel(
    solved, tmp_path
):
    assert solved.success
    fig = plotting.trajectory_figure(solved, tmp_path / "t.png")
    ax, ax_err = fig.axes[:2]
    assert "Solve_Succeeded" in ax.get_title() and "RMSE" in ax.get_title()
    labels = _labels(ax)
    for label in ("odometry only", "truth", "GP-SLAM", "start", "end", "3-sigma (Laplace)"):
        assert label in labels
    err_labels = _labels(ax_err)
    assert "3-sigma radius (Laplace)" in err_labels and "position error" in err_labels
    radius = ax_err.get_lines()[0].get_ydata()
    cov = solved.arrays["P_cov"]
    assert np.allclose(radius, 3 * np.sqrt(np.trace(cov, axis1=1, axis2=2)))
    assert (tmp_path / "t.png").stat().st_size > 0


def test_trajectory_of_a_failed_run_shows_no_estimate(failed, tmp_path):
    assert not failed.success
    fig = plotting.trajectory_figure(failed, tmp_path / "t.png")
    ax = fig.axes[0]
    assert failed.status in ax.get_title() and "IPOPT failed" in ax.get_title()
    assert ax.title.get_color() == "tab:red"
    labels = _labels(ax)
    assert "GP-SLAM" not in labels and "last iterate (failed)" in labels
    assert not ax.patches  # no covariance ellipses around a failed iterate


def test_ellipses_are_labelled_by_the_covariance_drawn(solved, tmp_path):
    inflated = SimpleNamespace(**{**vars(solved)})
    inflated.uncertainty = {**(solved.uncertainty or {}), "inflation": {"active": True}}
    fig = plotting.trajectory_figure(inflated, tmp_path / "t.png")
    assert "3-sigma (Laplace, inflated for correlated residuals)" in _labels(fig.axes[0])


def test_cost_figure_shows_every_stage_with_integer_ticks_and_the_failure(failed, tmp_path):
    stages = [
        {
            "stage": name,
            "status": "Solve_Succeeded",
            "iterations": n,
            "objective": list(np.geomspace(100.0, 1.0, n + 1)),
            "inf_pr": [0.0] * (n + 1),
            "inf_du": list(np.geomspace(10.0, 1e-7, n + 1)),
        }
        for name, n in (("IMU only", 4), ("GP-SLAM 1/2", 6), ("GP-SLAM 2/2", 3))
    ]
    run = SimpleNamespace(
        info={"name": "three"},
        status="Solve_Succeeded",
        success=True,
        iterations=3,
        cost_per_iteration=[],
        convergence=stages,
    )
    fig = plotting.cost_figure(run, tmp_path / "c.png")
    ax, ax_kkt = fig.axes
    labels = _labels(ax)
    assert len(labels) == 3 and labels[1] == "GP-SLAM 1/2: Solve_Succeeded, 6 it"
    assert ax.get_yscale() == "log" and ax_kkt.get_yscale() == "log"
    # the stages one after another: 5 + 7 + 4 points, separated by two dashed lines
    xs = [line.get_xdata() for line in ax.get_lines() if len(line.get_xdata()) > 2]
    assert [int(x[0]) for x in xs] == [0, 5, 12] and int(xs[-1][-1]) == 15
    assert sum(1 for line in ax.get_lines() if line.get_linestyle() == "--") == 2
    ticks = ax_kkt.xaxis.get_major_locator().tick_values(0, 15)
    assert np.allclose(ticks, np.round(ticks))
    fig = plotting.cost_figure(failed, tmp_path / "f.png")
    title = fig.axes[0].get_title()
    assert title.startswith("FAILED") and failed.status in title
    assert failed.convergence[0]["inf_du"], "the dual infeasibility is recorded"


def test_map_is_masked_where_no_sample_informs_it_and_shows_its_std(solved, tmp_path):
    std, prior = solved.arrays["map_std"], solved.arrays["map_prior_std"]
    assert std.shape == solved.arrays["map_field"].shape and np.all(std <= prior + 1e-12)
    fig = plotting.map_figure(solved, tmp_path / "m.png")
    ax_map, ax_std = fig.axes[:2]  # then their colorbars
    mean = next(c for c in ax_map.collections if isinstance(c, QuadMesh)).get_array()
    ratio = std.mean(axis=-1) / prior.mean(axis=-1)
    assert np.ma.is_masked(mean)
    assert np.array_equal(np.ma.getmaskarray(mean).ravel(), (ratio > plotting.MAP_MASK).ravel())
    # near the path the data pin the map down: far below the prior std there
    k = np.unravel_index(np.argmin(ratio), ratio.shape)
    assert ratio[k] < 0.2
    assert "posterior std" in ax_std.get_title()


def _map_checks(result, tmp_path):
    a = result.arrays
    std, prior = a["map_std"], a["map_prior_std"]
    assert std.shape == a["map_field"].shape == (*a["map_x"].shape, 3)
    assert np.all(std <= prior + 1e-12)
    ratio = std.mean(axis=-1) / prior.mean(axis=-1)
    assert ratio.min() < 0.2 and ratio.max() > plotting.MAP_MASK  # path and far away
    fig = plotting.map_figure(result, tmp_path / "m.png")
    assert result.status in fig.axes[0].get_title()
    return fig


def test_planar_results_draw_their_map_with_its_std(tmp_path):
    from small_problems import planar_room_field

    from casmag.data.imusim import simulate_planar
    from casmag.solver.planar import solve_planar

    d = simulate_planar(4, planar_room_field(), size=(2.0, 1.5), loops=1, disp_noise=0.002)
    r = solve_planar(d.U[:, 0], d.U[:, 1], d.U[:, 2], d.Y, t=d.t, truth={"P": d.P, "psi": d.psi})
    assert r.success
    _map_checks(r, tmp_path)
    r.save(tmp_path / "out")
    assert (tmp_path / "out" / "map.png").is_file()


@pytest.mark.slow
def test_imu_results_draw_their_map_at_the_path_height(tmp_path):
    from casmag.problem.imu import load_imu_problem
    from casmag.solver.imu import solve_imu

    problem = load_imu_problem("problems/imu/spiral.yaml", ["simulation.scenario.turns=1"])
    r = solve_imu(problem)
    assert r.success and r.details["map_decision"] == "map"
    fig = _map_checks(r, tmp_path)
    z = float(r.arrays["map_z"])
    assert z == pytest.approx(float(np.median(r.arrays["P_estimate"][:, 2])))
    assert f"z = {z:.3g} m" in fig.axes[0].get_title()
