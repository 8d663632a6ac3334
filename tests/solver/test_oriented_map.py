"""The saved map of the models whose magnetometer turns with the body (planar, pose, IMU):
their NLPs solve for whitened weights, the saved map holds the map's own
(casmag.gp.savedmap); planar and pose recordings located against a saved map."""

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import casmag
from casmag import strapdown as sd
from casmag.cli.main import main
from casmag.gp.savedmap import MAP_FILE, load_map
from casmag.problem.oriented import load_oriented_problem
from casmag.result import Result

ROOT = Path(__file__).resolve().parents[2]
TINY = ["simulation.trajectory.samples=40"]


def _solved(name, overrides=()):
    problem = load_oriented_problem(ROOT / f"problems/{name}/walk.yaml", [*TINY, *overrides])
    result = casmag.solve(problem)
    assert result.success
    maker = result.map_maker  # saved_map() consumes it
    return result, maker, result.saved_map()


def _dense_precision(nlp, sol, basis, kernel, hyper):
    """The map's precision from the whole Hessian inverted densely (the marginal over the
    path, conditioned on what the solve held), turned from whitened weights into the map's."""
    x = {n: sol.x[n] for n in nlp.x_layout.entries}
    H = nlp.hessian(x, sol.params).toarray()
    free = np.ones(H.shape[0], dtype=bool)
    for name in sol.fixed:
        e = nlp.x_layout.entries[name]
        free[e.offset : e.offset + e.size] = False
    keep = np.flatnonzero(free)
    cov = np.linalg.inv(H[np.ix_(keep, keep)])
    z = np.concatenate([nlp.x_layout.entries[n].offset + np.arange(sol.x[n].size) for n in "Wc"])
    iz = np.searchsorted(keep, z)
    S = basis.prior_variances(kernel, hyper["sigma_f"], hyper["lengthscale"])
    d = np.concatenate([np.tile(np.sqrt(np.ravel(S)), sol.x["W"].shape[1]), np.ones(3)])
    return np.linalg.inv(d[:, None] * cov[np.ix_(iz, iz)] * d[None, :])


def _staged_dense_precision(maker):
    final = maker.final
    return _dense_precision(
        final.nlp, final.sol, final.structure.hilbert_basis(), maker.kernel, maker.hyper
    )


def _magnetometer_cost(saved, P, R, Y, sigma_m):
    """0.5 sum |(y_k - R_k^T m(p_k)) / sigma_m|^2 with the saved map's mean (c included)."""
    predicted = np.einsum("kji,kj->ki", R, saved.field(P))
    return 0.5 * float(np.sum(((Y - predicted) / sigma_m) ** 2))


def test_a_planar_run_saves_its_map_in_the_maps_own_weights(tmp_path):
    result, maker, saved = _solved("planar")
    record = result.info["map"]
    assert record["saved"] is True and record["form"] == "reduced_rank"
    assert saved.dim == 2 and saved.kernel == result.info["kernel"]
    assert "heading" in saved.frame
    P, psi = result.arrays["P_estimate"], result.arrays["psi_estimate"]
    # the mean: the saved map predicts the magnetometer as the solve did (its cost block)
    R = sd.quat_to_rotmat(sd.quat_from_euler(0.0 * psi, 0.0 * psi, psi))
    Y = maker.final.sol.params["Y"]
    cost = _magnetometer_cost(saved, P, R, Y, result.hyperparameters["sigma_m"])
    assert cost == pytest.approx(result.cost_blocks["magnetometer"]["after"], rel=1e-8)
    # the precision: the Schur complement equals the dense marginal, unwhitened
    dense = _staged_dense_precision(maker)
    np.testing.assert_allclose(saved.precision, dense, atol=1e-7 * np.abs(dense).max())
    # where the walk went the map knows much more than its prior
    assert np.all(saved.std(P) < 0.5 * saved.prior_std(P))
    # written with the result, read back by Result.load and drawn by casmag map
    result.save(tmp_path / "run", figures=False)
    again = load_map(tmp_path / "run" / MAP_FILE)
    np.testing.assert_array_equal(again.mean, saved.mean)
    assert again.dim == 2
    assert Result.load(tmp_path / "run").field_map is not None
    res = CliRunner().invoke(main, ["map", str(tmp_path / "run"), "--out", str(tmp_path / "m")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "m" / "map.png").is_file()


def test_a_pose_run_with_a_planar_curl_free_map_is_read_at_planar_positions():
    result, maker, saved = _solved("pose")
    assert result.info["map"]["dim"] == 2 and result.info["map"]["saved"] is True
    # the potential's box is 3-D, the map is read at (x, y): z = 0
    assert saved.kernel == "curl_free" and len(saved.center) == 3 and saved.dim == 2
    P = result.arrays["P_estimate"][:, :2]
    R = sd.quat_to_rotmat(result.arrays["Q_estimate"])
    Y = maker.final.sol.params["Y"]
    cost = _magnetometer_cost(saved, P, R, Y, result.hyperparameters["sigma_m"])
    assert cost == pytest.approx(result.cost_blocks["magnetometer"]["after"], rel=1e-8)
    # the displacement bias is held (not estimated by default): conditioned on, not marginal
    assert maker.final.sol.fixed
    dense = _staged_dense_precision(maker)
    np.testing.assert_allclose(saved.precision, dense, atol=1e-7 * np.abs(dense).max())
    assert saved.inside(P).all()


# --------------------------------------------------------------------------- localisation
@pytest.fixture(scope="module")
def walks(tmp_path_factory):
    """The planar walk (120 samples) as a mapping recording, and a later recording of the
    same path and field with another odometry bias and noise and new magnetometer noise
    (seeded), both written as CSV; the first mapped by casmag slam into A."""
    from casmag.data.recording import write_recording
    from casmag.solver.oriented import simulate_oriented

    problem = load_oriented_problem(
        ROOT / "problems/planar/walk.yaml", ["simulation.trajectory.samples=120"]
    )
    rec, _ = simulate_oriented(problem)
    rng = np.random.default_rng(31)
    P, psi = rec.P_true, rec.yaw_true
    d = np.diff(P, axis=0)
    c, s = np.cos(psi[:-1]), np.sin(psi[:-1])
    body = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    U = np.column_stack(
        [
            body + [-0.004, 0.006] + 0.003 * rng.standard_normal((d.shape[0], 2)),
            np.diff(psi) - 6e-3 * np.diff(rec.t) + 2e-3 * rng.standard_normal(d.shape[0]),
        ]
    )
    Y = rec.Y + 0.05 * rng.standard_normal(rec.Y.shape)
    folder = tmp_path_factory.mktemp("walks")
    for name, inc, mag in (("first", rec.increments, rec.Y), ("later", U, Y)):
        write_recording(folder / f"{name}.csv", rec.t, mag, planar=inc, P_true=P, yaw_true=psi)
    res = CliRunner().invoke(
        main, ["slam", str(folder / "first.csv"), "--out", str(folder / "A"), "-q"]
    )
    assert res.exit_code == 0, res.output
    return folder


@pytest.mark.slow
def test_a_planar_recording_is_located_against_a_planar_map_and_updates_it(walks):
    runner = CliRunner()
    saved = load_map(walks / "A")
    B = walks / "B"
    res = runner.invoke(main, ["slam", str(walks / "later.csv"), "--map", str(walks / "A"),
                               "--out", str(B), "-q"])  # fmt: skip
    assert res.exit_code == 0, res.output
    located = Result.load(B)
    assert located.success and located.motion == "planar"
    loc = located.info["localisation"]
    assert loc["map"] == str(walks / "A") and loc["covered"] > 0.9
    assert located.info["map"]["saved"] is True
    assert located.info["map"]["updated_from"] == str(walks / "A")
    # the map's own hyperparameters, none estimated; its posterior was the prior
    assert located.hyperparameters == pytest.approx(saved.hyperparameters())
    assert "map_prior" in located.cost_blocks and "gp_prior" not in located.cost_blocks
    assert located.rmse_after < 0.25 * located.rmse_before
    # the updated map is in the saved map's frame and knows more along the new path
    updated = load_map(B)
    assert updated.frame == saved.frame and updated.basis_key == saved.basis_key
    P = located.arrays["P_estimate"]
    assert updated.std(P).mean() < 0.9 * saved.std(P).mean()
    assert located.uncertainty and "nees_mean" in located.uncertainty


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--method", "ekf"], "--method ekf locates translational recordings"),
        (["--set", "model.gp.form=tiled"], "which is one box (reduced_rank)"),
    ],
)
def test_a_planar_recording_refuses_what_only_translational_localisation_has(
    walks, tmp_path, args, needle
):
    res = CliRunner().invoke(
        main,
        ["slam", str(walks / "later.csv"), "--map", str(walks / "A"), "--out", str(tmp_path / "o"),
         "-q", *args],
    )  # fmt: skip
    assert res.exit_code == 2
    assert needle in res.output and len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "map_name", ["A", pytest.param("T", marks=pytest.mark.slow)], ids=["box", "tiles"]
)
def test_a_planar_recording_is_located_against_a_held_map(walks, map_name, request):
    """--hold-map: the map held at its mean in every solve, the whole recording's with
    sigma_m widened by the map's standard deviation along the path; no map written."""
    if map_name == "T":
        request.getfixturevalue("tiled_map")
    saved = load_map(walks / map_name)
    out = walks / f"H{map_name}"
    res = CliRunner().invoke(
        main,
        ["slam", str(walks / "later.csv"), "--map", str(walks / map_name), "--hold-map",
         "--out", str(out), "-q"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    located = Result.load(out)
    assert located.success and not (out / MAP_FILE).exists()
    assert located.info["map"]["saved"] is False and "held" in located.info["map"]["reason"]
    loc = located.info["localisation"]
    assert loc["updated"] is False and loc["covered"] > 0.9
    assert loc["sigma_m_used"] == pytest.approx(np.hypot(saved.sigma_m, loc["map_std_on_path"]))
    assert loc["map_std_on_path"] > 0.0
    assert "map_prior" not in located.cost_blocks
    assert located.rmse_after < 0.25 * located.rmse_before


@pytest.fixture(scope="module")
def tiled_map(walks):
    """The mapping recording of ``walks`` mapped by casmag slam on the tiled map into T."""
    res = CliRunner().invoke(
        main,
        ["slam", str(walks / "first.csv"), "--out", str(walks / "T"), "-q",
         "--set", "model.gp.form=tiled"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    saved = load_map(walks / "T")
    assert saved.tiles is not None
    return walks / "T"


def test_a_saved_tiled_map_is_the_prior_of_the_whitened_tiles(tiled_map):
    """PriorMap in the NLP's units (whitened weights V, W = sqrt(S) V tile by tile): the
    same quadratic form as the saved posterior, and a held map the saved mean."""
    from casmag.solver.staged import PriorMap

    saved = load_map(tiled_map)
    prior = PriorMap.of(saved)
    assert prior.tiled and prior.grid == saved.tiles and prior.basis is None
    tiles = saved.tiled_basis()
    sqrt_s = np.sqrt(np.ravel(tiles.prior_variances(saved.sigma_f, saved.lengthscale)))
    d = np.concatenate([np.tile(sqrt_s, tiles.num_tiles), np.ones(3)])
    rng = np.random.default_rng(4)
    z = saved.mean + rng.standard_normal(saved.size) * 0.1
    r, rv = z - saved.mean, z / d - prior.mean
    assert rv @ prior.precision @ rv == pytest.approx(r @ saved.precision @ r, rel=1e-9)
    held = prior._held()
    W = sqrt_s[:, None] * held["W"]
    np.testing.assert_allclose(W, saved.unknowns()["W"], rtol=1e-12)
    np.testing.assert_allclose(held["c"], saved.unknowns()["c"], rtol=1e-12)


@pytest.mark.slow
def test_a_planar_recording_is_located_against_a_tiled_map_and_updates_it(walks, tiled_map):
    from casmag.data.recording import read_recording

    saved = load_map(tiled_map)
    B = walks / "BT"
    res = CliRunner().invoke(
        main, ["slam", str(walks / "later.csv"), "--map", str(tiled_map), "--out", str(B), "-q"]
    )
    assert res.exit_code == 0, res.output
    located = Result.load(B)
    assert located.success and located.info["map"]["form"] == "tiled"
    assert located.info["localisation"]["covered"] > 0.9
    assert located.hyperparameters == pytest.approx(saved.hyperparameters())
    assert "map_prior" in located.cost_blocks and "gp_prior" not in located.cost_blocks
    assert located.rmse_after < 0.3 * located.rmse_before
    # the updated map: the saved tiles and frame, knowing more along the new path, and
    # predicting the magnetometer as the solve did
    updated = load_map(B)
    assert updated.tiles == saved.tiles and updated.frame == saved.frame
    P, psi = located.arrays["P_estimate"], located.arrays["psi_estimate"]
    assert updated.std(P).mean() < 0.9 * saved.std(P).mean()
    R = sd.quat_to_rotmat(sd.quat_from_euler(0.0 * psi, 0.0 * psi, psi))
    Y = read_recording(walks / "later.csv").Y
    cost = _magnetometer_cost(updated, P, R, Y, located.hyperparameters["sigma_m"])
    assert cost == pytest.approx(located.cost_blocks["magnetometer"]["after"], rel=1e-6)
    assert located.uncertainty and "nees_mean" in located.uncertainty


def test_a_three_d_map_cannot_locate_a_planar_recording(walks):
    from dataclasses import replace

    from casmag.data.recording import read_recording
    from casmag.errors import DataError
    from casmag.solver.oriented import slam_oriented

    saved = load_map(walks / "A")
    box3 = replace(
        saved, center=(*saved.center, 0.0), half_width=(*saved.half_width, 1.0), position_dim=3
    )
    with pytest.raises(DataError, match="a 3-D map cannot locate a planar recording"):
        slam_oriented(read_recording(walks / "later.csv"), saved=box3, map_source="box3")


def _pose_later(rec):
    """A later recording of ``rec``'s path and field: another displacement and rotation-rate
    bias, odometry and magnetometer noise (seeded)."""
    from dataclasses import replace

    rng = np.random.default_rng(5)
    U = rec.increments.copy()
    h = np.diff(rec.t).reshape(-1, 1)
    U[:, :3] += [0.004, -0.003, 0.0] + 0.003 * rng.standard_normal((U.shape[0], 3))
    U[:, 3:] = sd.quat_mul(U[:, 3:], sd.quat_exp(h * np.array([0.0, 0.0, -4e-3])))
    return replace(rec, increments=U, Y=rec.Y + 0.05 * rng.standard_normal(rec.Y.shape))


@pytest.mark.slow
@pytest.mark.parametrize(
    ("form", "ratio"),
    # the tiles' lattice on 80 samples is coarser than the box: 0.24 of the drift measured
    [("reduced_rank", 0.25), ("tiled", 0.3)],
)
def test_a_pose_recording_is_located_against_a_pose_map_and_updates_it(form, ratio):
    from casmag.solver.oriented import simulate_oriented, slam_oriented

    problem = load_oriented_problem(
        ROOT / "problems/pose/walk.yaml",
        ["simulation.trajectory.samples=80", f"model.gp.form={form}"],
    )
    rec, _ = simulate_oriented(problem)
    saved = slam_oriented(rec, problem.sections).saved_map()
    assert saved is not None and saved.form == form
    located = slam_oriented(_pose_later(rec), problem.sections, saved=saved, map_source="first")
    assert located.success and located.info["localisation"]["covered"] > 0.9
    assert located.info["map"]["dim"] == saved.dim and located.info["map"]["updated_from"]
    assert located.info["map"]["form"] == form
    assert "map_prior" in located.cost_blocks and "gp_prior" not in located.cost_blocks
    assert located.rmse_after < ratio * located.rmse_before
    updated = located.saved_map()
    assert updated.frame == saved.frame and updated.dim == saved.dim
    assert updated.tiles == saved.tiles and updated.form == form
    P = located.arrays["P_estimate"][:, : saved.dim]
    assert updated.std(P).mean() < 0.9 * saved.std(P).mean()


def test_an_imu_run_saves_its_map_in_the_maps_own_weights():
    from small_problems import imu_noise_free, tiny_imu

    from casmag.problem.imu import load_imu_problem
    from casmag.solver.imu import solve_imu

    # the noise-free rectangle traced twice past a dipole (casmag's IMU tests' quick case)
    data = imu_noise_free(tiny_imu(gp={"sigma_f": 0.3, "lengthscale": 0.2, "num_basis": 400}))
    data["simulation"]["scenario"]["loops"] = 2
    data["model"]["imu"]["bias"] = "constant"
    data["model"]["zero_position"] = {"sigma": 1.0}
    result = solve_imu(load_imu_problem(data))
    assert result.success and result.details["map_decision"] == "map"
    stage = result.map_maker.args[0]
    saved = result.saved_map()
    assert result.info["map"]["saved"] is True and saved.dim == 3
    sol = stage.solution
    cost = _magnetometer_cost(saved, stage.P, sd.quat_to_rotmat(stage.Q), sol.params["Y"],
                              stage.sigma_m)  # fmt: skip
    assert cost == pytest.approx(sol.cost_blocks()["magnetometer"]["after"], rel=1e-6)
    fm = stage.field_model
    dense = _dense_precision(stage.nlp, sol, saved.basis(), fm["kernel"], fm["hyper"])
    np.testing.assert_allclose(saved.precision, dense, atol=1e-7 * np.abs(dense).max())
