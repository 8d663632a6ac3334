"""The filter baseline (casmag.solver.ekf) against references written here in plain numpy."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import casmag
from casmag.cli.main import main
from casmag.data.recording import dataset_to_recording_arrays, write_recording
from casmag.data.simulate import simulate_problem
from casmag.gp.reduced_rank import Domain, HilbertBasis
from casmag.model.rrmap import field_and_jacobians
from casmag.solver.ekf import FilterMap, PlanarNav, TranslationalNav, run_filter

ROOT = Path(__file__).resolve().parents[2]


def _walk(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) a smooth loop of about 1 m radius with a little noise."""
    t = np.linspace(0.0, 2.0 * math.pi * 1.5, n)
    return np.column_stack([np.cos(t), 0.7 * np.sin(t)]) + 0.01 * rng.standard_normal((n, 2))


def test_known_positions_give_the_bayesian_linear_regression_posterior() -> None:
    """Positions known exactly (no odometry noise): the filter is a linear Kalman filter on
    the weights and the constant field, and its final mean is the batch posterior mean of
    Bayesian linear regression, computed here from the design matrix."""
    rng = np.random.default_rng(3)
    P = _walk(60, rng)
    basis = HilbertBasis(Domain(np.zeros(2), np.array([2.0, 2.0])), 40)
    fmap = FilterMap(basis, "se", sigma_f=0.5, lengthscale=0.4, sigma_m=0.05, sigma_lin=2.0)
    Y = rng.normal(size=(60, 3)) * 0.3 + np.array([1.0, -0.5, 0.2])
    nav = TranslationalNav(np.diff(P, axis=0), P[0], sigma=1e-12, anchor_sigma=1e-12)
    run = run_filter(nav, fmap, Y)

    Phi = basis.phi(P)  # (N, M)
    M = basis.num_basis
    A = np.zeros((3 * 60, 3 * M + 3))  # rows: sample-major, component-minor
    for j in range(3):
        A[j::3, j * M : (j + 1) * M] = Phi
        A[j::3, 3 * M + j] = 1.0
    prior = np.concatenate([fmap.prior_variances(), np.full(3, 2.0**2)])
    precision = A.T @ A / 0.05**2 + np.diag(1.0 / prior)
    mean = np.linalg.solve(precision, A.T @ Y.ravel() / 0.05**2)
    got = np.concatenate([run.weights, run.constant])
    np.testing.assert_allclose(got, mean, rtol=1e-6, atol=1e-8 * np.abs(mean).max())
    np.testing.assert_allclose(run.positions, P, atol=1e-9)


def _dense_reference(nav: PlanarNav, fmap: FilterMap, Y: np.ndarray) -> np.ndarray:
    """The same EKF written the plain way: full covariance, Jacobians by central
    differences of the prediction and of the measurement (field from basis.phi)."""
    M = fmap.basis.num_basis
    n = 4 + 3 * M + 3
    x = np.zeros(n)
    x0, P0 = nav.initial()
    x[:4] = x0
    P = np.zeros((n, n))
    P[:4, :4] = P0
    P[4:, 4:] = np.diag(np.concatenate([fmap.prior_variances(), np.full(3, fmap.sigma_lin**2)]))

    def h(x: np.ndarray) -> np.ndarray:
        W = x[4 : 4 + 3 * M].reshape(M, 3, order="F")
        m = fmap.basis.phi(x[None, :2])[0] @ W + x[4 + 3 * M :]
        c, s = math.cos(x[2]), math.sin(x[2])
        return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) @ m

    def jac(f, x: np.ndarray, rows: int) -> np.ndarray:
        J = np.zeros((rows, x.size))
        for i in range(x.size):
            e = np.zeros(x.size)
            e[i] = 1e-6
            J[:, i] = (f(x + e) - f(x - e)) / 2e-6
        return J

    out = np.empty((Y.shape[0], 4))
    for k in range(Y.shape[0]):
        if k > 0:
            xn, _, Q = nav.predict(x[:4], k - 1)
            F = jac(lambda z, k=k: nav.predict(z, k - 1)[0], x[:4], 4)
            Fb = np.eye(n)
            Fb[:4, :4] = F
            P = Fb @ P @ Fb.T
            P[:4, :4] += Q
            x[:4] = xn
        H = jac(h, x, 3)
        S = H @ P @ H.T + fmap.sigma_m**2 * np.eye(3)
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (Y[k] - h(x))
        P = P - K @ S @ K.T
        out[k] = x[:4]
    return out


def test_planar_filter_matches_a_dense_numpy_ekf() -> None:
    """Heading, heading-rate bias, a body-frame magnetometer: the filter (upper triangle,
    analytic Jacobians) and the dense reference agree to the finite differences' accuracy."""
    rng = np.random.default_rng(11)
    n = 40
    dt = np.full(n - 1, 0.1)
    U = np.column_stack(
        [0.05 + 0.01 * rng.random(n - 1), 0.005 * rng.standard_normal(n - 1), np.full(n - 1, 0.08)]
    )
    basis = HilbertBasis(Domain(np.array([0.5, 0.5]), np.array([1.5, 1.5])), 12)
    fmap = FilterMap(basis, "se", sigma_f=0.3, lengthscale=0.5, sigma_m=0.02, sigma_lin=1.0)
    Y = rng.normal(size=(n, 3)) * 0.2 + np.array([0.4, 0.1, -0.6])
    nav = PlanarNav(U, dt, np.array([0.0, 0.0, 0.3]), 0.01, 0.005, 1e-3, 0.01, 0.02, 1e-3)
    run = run_filter(nav, fmap, Y)
    ref = _dense_reference(nav, fmap, Y)
    np.testing.assert_allclose(run.states, ref, atol=1e-6)
    assert 0.0 < run.mean_nis < np.inf


@pytest.mark.parametrize("kernel", ["se", "curl_free"])
def test_filter_locates_against_a_known_map_and_finds_the_bias(kernel: str) -> None:
    """A loop walked three times through a field drawn from the map's prior, odometry with
    a constant bias (0.48 m of drift): with the map given (its weights as the prior mean,
    prior variances near zero) the filter tracks the path to a few millimetres, its
    innovations have the assumed size (mean NIS near 3) and it recovers the bias in
    casmag's convention (p_{k+1} = p_k + u_k - b)."""
    rng = np.random.default_rng(5)
    n = 240
    t = np.linspace(0.0, 2.0 * math.pi * 3, n)
    dim = 3 if kernel == "curl_free" else 2
    P = np.zeros((n, dim))
    P[:, 0], P[:, 1] = 1.2 * np.cos(t), 0.8 * np.sin(t)
    half = np.array([2.5, 2.2, 1.0][:dim])
    basis = HilbertBasis(Domain(np.zeros(dim), half), 150 if kernel == "se" else 300)
    sigma_m = 0.05
    prior = FilterMap(basis, kernel, sigma_f=1.0, lengthscale=0.4, sigma_m=sigma_m, sigma_lin=2.0)
    w = rng.standard_normal(prior.n_w) * np.sqrt(prior.prior_variances())
    c = np.array([0.5, -0.3, 0.8])
    f, _, _ = field_and_jacobians(basis, kernel, P, w)
    Y = f + c + sigma_m * rng.standard_normal((n, 3))
    bias = np.array([0.002, -0.0015, 0.0005][:dim])
    U = np.diff(P, axis=0) + bias + 0.001 * rng.standard_normal((n - 1, dim))

    class KnownMap(FilterMap):
        def prior_variances(self) -> np.ndarray:
            return np.full(self.n_w, 1e-14)

    fmap = KnownMap(basis, kernel, 1.0, 0.4, sigma_m, 1e-7, weights_mean=w, constant_mean=c)
    nav = TranslationalNav(U, P[0], sigma=0.001, anchor_sigma=1e-3, bias_sigma=0.005)
    run = run_filter(nav, fmap, Y)
    dead = np.vstack([P[0], P[0] + np.cumsum(U, axis=0)])
    err_dead = np.sqrt(np.mean(np.sum((dead - P) ** 2, axis=1)))
    err = np.sqrt(np.mean(np.sum((run.positions - P) ** 2, axis=1)))
    assert err_dead > 0.3
    assert err < 0.01, (err, err_dead)
    assert 2.0 < run.mean_nis < 4.5
    np.testing.assert_allclose(run.states[-1, dim:], bias, atol=2e-4)


def _walk_recording(tmp_path: Path, samples: int, *extra: str) -> Path:
    """A simulated looping walk in a 3 m x 3 m room at 10 Hz, written as a recording."""
    prob = casmag.load_problem(
        ROOT / "problems/bench/walk.yaml",
        [
            "seed=3",
            f"simulation.trajectory.samples={samples}",
            "simulation.trajectory.area=[3.0, 3.0]",
            *extra,
        ],
    )
    rec = tmp_path / "walk.csv"
    write_recording(rec, **dataset_to_recording_arrays(simulate_problem(prob), dt=0.1))
    return rec


def test_slam_method_ekf_on_a_recording(tmp_path: Path) -> None:
    """``casmag slam REC --method ekf``: the filter with casmag slam's map and hyperparameters,
    saved as every result is (status Filter_Completed, the filter's figures in info)."""
    rec = _walk_recording(tmp_path, 400, "simulation.odometry.bias=[6.0e-4, -3.0e-4]")
    out = tmp_path / "out"
    r = CliRunner().invoke(
        main, ["slam", str(rec), "--method", "ekf", "--out", str(out), "--quiet"]
    )
    assert r.exit_code in (0, 3), r.output
    res = json.loads((out / "result.json").read_text())
    assert res["status"] == "Filter_Completed" and res["success"]
    assert res["info"]["method"] == "ekf"
    assert res["info"]["filter"]["state_size"] == 2 + 2 + 3 * res["info"]["num_basis"] + 3
    assert np.isfinite(res["rmse_after"]) and res["rmse_before"] > 0
    assert (out / "trajectory.csv").is_file() and (out / "trajectory.png").is_file()
    assert res["uncertainty"]["nees_mean"] is not None
    assert res["info"]["filter"]["real_time_factor"] > 0
    # the covariance reported is the filter's scaled by its residuals' long-run inflation
    scale = res["uncertainty"]["inflation"]["scale"]
    assert scale >= 1.0
    plain = res["uncertainty"]["uninflated"]["sigma_mean"]
    assert res["uncertainty"]["sigma_mean"] == pytest.approx(np.sqrt(scale) * plain)


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--map", "nowhere.npz"], "nowhere.npz: no such map file"),
        (["--refit-noise"], "--refit"),
        (["--refit-noise", "--method", "both"], "--refit-noise"),
    ],
)
def test_slam_method_ekf_bad_options_exit_2(tmp_path: Path, extra: list[str], needle: str) -> None:
    rec = tmp_path / "r.csv"
    rec.write_text("t,dx,dy,mx,my,mz\n0,0,0,1,2,3\n0.1,0.1,0,1,2,3\n")
    r = CliRunner().invoke(
        main, ["slam", str(rec), "--method", "ekf", "--out", str(tmp_path / "o"), *extra]
    )
    assert r.exit_code == 2, r.output
    assert needle in r.output


def test_slam_method_both_writes_the_methods_side_by_side(tmp_path: Path) -> None:
    """--method both: the MAP and the filter in one run, each a whole result folder, with the
    table (dead reckoning, MAP, EKF) and the overlay figure; casmag report lists the filter
    under its own row."""
    rec = _walk_recording(tmp_path, 300)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["slam", str(rec), "--method", "both", "--out", str(out)])
    assert r.exit_code in (0, 3), r.output
    assert "| EKF |" in r.output and "| GP-SLAM (MAP) |" in r.output
    for name in ("map/result.json", "ekf/result.json", "methods.md", "methods.png"):
        assert (out / name).is_file(), name
    table = json.loads((out / "methods.json").read_text())
    assert [row["method"] for row in table["rows"]] == ["dead reckoning", "GP-SLAM (MAP)", "EKF"]
    assert table["duration_seconds"] == pytest.approx(29.9)
    assert all(row["real_time_factor"] > 0 for row in table["rows"][1:])
    mapped = json.loads((out / "map" / "result.json").read_text())
    assert table["rows"][1]["rmse"] == mapped["rmse_after"]
    report = CliRunner().invoke(main, ["report", str(out)])
    assert report.exit_code == 0, report.output
    assert "walk (ekf)" in report.output


def test_slam_method_ekf_refuses_a_map_it_cannot_carry(tmp_path: Path) -> None:
    """The filter carries the box map only: the tiled form is refused in one line, exit 2,
    nothing written."""
    rec = _walk_recording(tmp_path, 200)
    out = tmp_path / "o"
    args = ["slam", str(rec), "--method", "ekf", "--set", "model.gp.form=tiled"]
    args += ["--set", "model.gp.kernel=curl_free", "--out", str(out)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2, r.output
    assert "model.gp.form" in r.output and "reduced_rank" in r.output
    assert not out.exists()


def test_slam_method_ekf_without_truth_and_several_recordings(tmp_path: Path) -> None:
    """Without truth the filter's errors are null, never made up; several recordings (one
    map for sessions) are the MAP's alone: one line, exit 2."""
    rec = _walk_recording(tmp_path, 200)
    lines = rec.read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, h in enumerate(header) if not h.endswith("_true")]
    bare = tmp_path / "bare.csv"
    bare.write_text("\n".join(",".join(row.split(",")[i] for i in keep) for row in lines) + "\n")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["slam", str(bare), "--method", "ekf", "--out", str(out), "-q"])
    assert r.exit_code in (0, 3), r.output
    res = json.loads((out / "result.json").read_text())
    assert res["success"] and res["rmse_after"] is None and res["rmse_before"] is None
    r = CliRunner().invoke(
        main, ["slam", str(rec), str(bare), "--method", "both", "--out", str(tmp_path / "o2")]
    )
    assert r.exit_code == 2 and "one recording at a time" in r.output
    assert not (tmp_path / "o2").exists()
