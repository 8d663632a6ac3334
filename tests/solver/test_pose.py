"""The pose-odometry model (casmag.model.pose), its solve (casmag.solver.pose), its filter
(casmag.solver.ekf.PoseNav) and ``casmag slam`` on a pose recording."""

from __future__ import annotations

import json
import math
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from click.testing import CliRunner

import casmag
from casmag import strapdown as sd
from casmag.cli.main import main
from casmag.data.posesim import simulate_pose
from casmag.data.recording import write_recording
from casmag.errors import DataError
from casmag.gp.reduced_rank import Domain, HilbertBasis
from casmag.model.pose import (
    nominal_parameters,
    pose_step_function,
)
from casmag.model.rrmap import field_and_jacobians
from casmag.problem.oriented import load_oriented_problem
from casmag.problem.spec import load_problem
from casmag.solver.ekf import FilterMap, PoseNav, run_filter
from casmag.solver.oriented import solve_oriented
from casmag.solver.pose import attitude_rms_deg

ROOT = Path(__file__).resolve().parents[2]


def _trajectory(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) positions of a loop walked about 1.5 times with a little height change and
    (n, 4) orientations facing along it with a roll/pitch wobble."""
    t = np.linspace(0.0, 2.0 * math.pi * 1.5, n)
    P = np.column_stack([1.2 * np.cos(t), 0.8 * np.sin(t), 0.05 * np.sin(3 * t)])
    P += 0.005 * rng.standard_normal(P.shape)
    yaw = t + math.pi / 2
    roll, pitch = 0.05 * np.sin(2 * t), 0.04 * np.cos(5 * t)
    return P, sd.quat_from_euler(roll, pitch, yaw)


def test_increments_and_dead_reckoning_are_inverse_with_biases_removed() -> None:
    rng = np.random.default_rng(3)
    P, Q = _trajectory(50, rng)
    U = sd.pose_increments(P, Q)
    dt = np.full(49, 0.5)
    b_p, b_w = np.array([0.01, -0.02, 0.003]), np.array([0.002, -0.001, 0.004])
    biased = U.copy()
    biased[:, :3] += b_p
    biased[:, 3:] = sd.quat_mul(U[:, 3:], sd.quat_exp(dt[:, None] * b_w))
    P2, Q2 = sd.dead_reckon_pose(biased, P[0], Q[0], b_p, b_w, dt)
    np.testing.assert_allclose(P2, P, atol=1e-12)
    assert np.max(sd.quat_angle(Q2, Q)) < 1e-12
    P3, _ = sd.dead_reckon_pose(biased, P[0], Q[0])  # the biases left in: a drift
    assert np.max(np.linalg.norm(P3 - P, axis=1)) > 0.1


def test_the_step_residual_is_zero_at_the_truth_and_whitened() -> None:
    """The NLP's odometry residual at the true poses and biases is zero; a displacement error
    of one sigma_p along an axis gives a residual of 1 on that axis."""
    rng = np.random.default_rng(4)
    P, Q = _trajectory(6, rng)
    U = sd.pose_increments(P, Q)
    b_p, b_w, h = np.array([0.01, 0.0, -0.01]), np.array([0.003, 0.001, -0.002]), 0.5
    step = pose_step_function()

    def f(*args: object) -> np.ndarray:
        out = step(*(ca.DM(np.reshape(np.asarray(a, float), (-1, 1))) for a in args))
        return out.full().ravel()

    nom = nominal_parameters(Q)
    for k in range(5):
        dq = sd.quat_mul(U[k, 3:], sd.quat_exp(h * b_w))
        rnom = nom["RNOM"][k]
        args = [P[k], P[k + 1], np.zeros(3), np.zeros(3), rnom, nom["QREL"][k],
                U[k, :3] + b_p, dq, b_p, b_w, h, 0.01, 0.002]  # fmt: skip
        np.testing.assert_allclose(f(*args), 0.0, atol=1e-12)
        moved = list(args)
        moved[1] = P[k + 1] + sd.rotate(Q[k], np.array([0.01, 0.0, 0.0]))
        np.testing.assert_allclose(f(*moved)[:3], [1.0, 0.0, 0.0], atol=1e-9)


def _small_problem(seed: int) -> tuple:
    """A 160-sample walk in 5 x 2 m at 2 Hz, dipole field, the peers' noise, a rate bias."""
    sets = ["simulation.trajectory.samples=160", "simulation.trajectory.area=[5.0, 2.0]"]
    prob = load_problem(ROOT / "problems" / "bench" / "peers.yaml", [f"seed={seed}", *sets])
    return simulate_pose(prob.spec.simulation, seed, bias_w=(0.0, 0.0, 0.002))


def test_pose_filter_locates_against_a_known_map_and_finds_the_rate_bias() -> None:
    """The error-state filter with the map given (its weights as the prior mean, variances
    near zero): tracks a 6-DoF loop whose dead reckoning drifts by decimetres to under
    2 cm, innovations of the assumed size (mean NIS near 3), rate bias recovered."""
    rng = np.random.default_rng(6)
    n = 300
    P, Q = _trajectory(n, rng)
    basis = HilbertBasis(Domain(np.zeros(3), np.array([2.5, 2.2, 1.0])), 300)
    sigma_m = 0.05
    prior = FilterMap(basis, "curl_free", 1.0, 0.4, sigma_m, 2.0)
    w = rng.standard_normal(prior.n_w) * np.sqrt(prior.prior_variances())
    c = np.array([0.5, -0.3, 0.8])
    f, _, _ = field_and_jacobians(basis, "curl_free", P, w)
    Y = sd.rotate(sd.quat_conj(Q), f + c) + sigma_m * rng.standard_normal((n, 3))
    dt = np.full(n - 1, 0.5)
    b_w = np.array([0.001, -0.002, 0.003])
    U = sd.pose_increments(P, Q)
    U[:, :3] += 0.002 * rng.standard_normal((n - 1, 3))
    U[:, 3:] = sd.quat_mul(
        U[:, 3:], sd.quat_exp(dt[:, None] * b_w + 0.001 * rng.standard_normal((n - 1, 3)))
    )

    class KnownMap(FilterMap):
        def prior_variances(self) -> np.ndarray:
            return np.full(self.n_w, 1e-14)

    fmap = KnownMap(basis, "curl_free", 1.0, 0.4, sigma_m, 1e-7, weights_mean=w, constant_mean=c)
    nav = PoseNav(U, dt, P[0], Q[0], 0.002, 0.001, 1e-3, 1e-3, 0.01)
    run = run_filter(nav, fmap, Y)
    P_dr, Q_dr = sd.dead_reckon_pose(U, P[0], Q[0])
    err_dead = float(np.sqrt(np.mean(np.sum((P_dr - P) ** 2, axis=1))))
    err = float(np.sqrt(np.mean(np.sum((run.positions - P) ** 2, axis=1))))
    assert err_dead > 0.2
    assert err < 0.02, (err, err_dead)
    assert 2.0 < run.mean_nis < 4.5
    np.testing.assert_allclose(run.states[-1, 6:9], b_w, atol=5e-4)
    att_dead = attitude_rms_deg(Q_dr, Q)
    assert attitude_rms_deg(nav.orientations(run.states), Q) < 0.25 * att_dead, att_dead


def _recording(tmp_path: Path, seed: int = 2) -> Path:
    r = _small_problem(seed)
    path = tmp_path / "walk.csv"
    write_recording(path, **r.recording_arrays())
    return path


@pytest.mark.slow
def test_slam_on_a_pose_recording_map_ekf_and_both(tmp_path: Path) -> None:
    """``casmag slam`` reads the pose columns and solves the pose model from the dead
    reckoning (hyperparameters estimated): a fifth of the dead reckoning's position error,
    the attitude corrected, the heading-rate bias recovered, every prefix in few iterations;
    the filter and both methods side by side; result.json says which."""
    rec = _recording(tmp_path)
    out = tmp_path / "out"
    args = ["slam", str(rec), "--out", str(out), "--method", "both", "--quiet"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    res = json.loads((out / "map" / "result.json").read_text())
    res_ekf = json.loads((out / "ekf" / "result.json").read_text())
    assert res["motion"] == "pose" and res_ekf["motion"] == "pose"
    assert res["status"] == "Solve_Succeeded"
    assert res["rmse_before"] > 0.15
    assert res["rmse_after"] < 0.2 * res["rmse_before"], (res["rmse_after"], res["rmse_before"])
    d = res["details"]
    assert d["attitude_rms_deg_after"] < 0.5 * d["attitude_rms_deg_before"]
    assert abs(d["bias_w"][2] - 0.002) < 5e-4, d["bias_w"]
    assert d["bias_p"] == [0.0, 0.0, 0.0]  # not estimated by default
    assert res["info"]["map"]["dim"] == 2 and res["info"]["map"]["height_prior_m"] == 0.2
    assert all(s["iterations"] <= 30 for s in res["stages"]), res["stages"]
    assert res_ekf["status"] == "Filter_Completed" and res_ekf["info"]["method"] == "ekf"
    assert res_ekf["rmse_after"] < res_ekf["rmse_before"]
    header = (out / "map" / "trajectory.csv").read_text().splitlines()[0].split(",")
    assert {"qw_est", "qz_true", "z_est"} <= set(header)
    tum = np.loadtxt(out / "map" / "trajectory.tum")
    assert tum.shape == (160, 8) and np.allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0)
    assert (out / "methods.md").exists() and (out / "map" / "trajectory.png").exists()


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--set", "model.map_dim=4"], "model.map_dim"),
        (["--set", "model.sigma_p=-1"], "model.sigma_p"),
        (["--refit-noise"], "this one is pose"),
    ],
)
def test_slam_on_a_pose_recording_bad_settings_exit_2(
    tmp_path: Path, extra: list[str], needle: str
) -> None:
    rec = _recording(tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["slam", str(rec), "--out", str(out), *extra])
    assert r.exit_code == 2, r.output
    assert needle in r.output
    assert not out.exists()


@pytest.mark.parametrize("motion", ["pose", "planar"])
def test_a_constant_magnetometer_gives_the_dead_reckoning(tmp_path: Path, motion: str) -> None:
    """A magnetometer that never changes (a straight walk, the sensor's axes fixed)
    carries no position information: the result is the dead reckoning (status
    Odometry_Only, the reason given), not a search that fails on the field's spread."""
    n = 50
    t = 0.5 * np.arange(n)
    P = np.column_stack([np.linspace(0.0, 5.0, n), np.zeros(n), np.zeros(n)])
    yaw = np.zeros(n)
    Q = sd.quat_from_euler(yaw, yaw, yaw)
    Y = np.tile([20.0, 0.0, -40.0], (n, 1))
    path = tmp_path / "constant.csv"
    if motion == "pose":
        write_recording(path, t, Y, pose=sd.pose_increments(P, Q), P_true=P, q_true=Q)
    else:
        U = sd.pose_increments(P, Q)
        planar = np.column_stack([U[:, 0], U[:, 1], np.diff(yaw)])
        write_recording(path, t, Y, planar=planar, P_true=P[:, :2], yaw_true=yaw)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["slam", str(path), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    res = json.loads((out / "result.json").read_text())
    assert res["motion"] == motion and res["status"] == "Odometry_Only"
    assert res["info"]["fallback"].startswith("homogeneous field")
    assert res["rmse_after"] == res["rmse_before"] < 1e-9


@pytest.mark.slow
def test_a_pose_walk_with_the_tiled_map() -> None:
    """problems/pose/walk.yaml (80 samples, seed 2) with ``model.gp.form: tiled``: the
    pose model reads the tiles through its 3-D rotation as the planar model does, and
    locates as the box does (measured 2026-11-28: 0.0444 m in 8 iterations, the box's
    0.0566 m in 7, dead reckoning 0.191 m; 120 samples: 0.0382 against 0.0384 m); the
    Laplace covariance is computed and honest (mean NEES 1.00, expected 2)."""
    problem = load_oriented_problem(
        ROOT / "problems/pose/walk.yaml",
        ["seed=2", "simulation.trajectory.samples=80", "model.gp.form=tiled"],
    )
    r = casmag.solve(problem)
    assert r.status == "Solve_Succeeded" and r.iterations <= 30
    assert r.info["map"]["form"] == "tiled" and r.info["map"]["tiles"] >= 4
    assert r.info["map"]["dim"] == 2
    assert r.rmse_after < 0.35 * r.rmse_before, (r.rmse_after, r.rmse_before)
    assert r.flags == []
    assert r.arrays["map_field"].shape[-1] == 3
    assert 0.3 < r.uncertainty["nees_mean"] < 5.0
    saved = r.saved_map()  # the tiles saved with their grid, read at planar positions
    assert r.info["map"]["saved"] and saved.form == "tiled" and saved.dim == 2
    P = r.arrays["P_estimate"][:, :2]
    assert np.all(saved.std(P) < 0.5 * saved.prior_std(P))


@pytest.mark.parametrize(
    ("sets", "method", "needle"),
    [
        (["model.gp.kernel=se"], "map", "form tiled needs kernel: curl_free"),
        (["solver.warm_start.strategy=sliding"], "map", "sliding windows need"),
        ([], "ekf", "the filter baseline needs the box map"),
    ],
)
def test_the_tiled_pose_map_refuses_what_it_cannot_do(sets, method, needle) -> None:
    file = ROOT / "problems/pose/walk.yaml"
    sets = ["simulation.trajectory.samples=40", "model.gp.form=tiled", *sets]
    with pytest.raises((casmag.ProblemError, DataError), match=needle):
        solve_oriented(load_oriented_problem(file, sets), method=method)
