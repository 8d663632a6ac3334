"""The odometry bias chosen by the field's evidence (casmag.solver.biasscan)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import casmag
from casmag import strapdown as sd
from casmag.data.simulate import simulate_problem
from casmag.gp.reduced_rank import Domain, HilbertBasis
from casmag.model.planar import dead_reckon_planar
from casmag.problem.oriented import load_oriented_problem
from casmag.solver.biasscan import (
    drift_grid,
    evidence_score,
    heading_grid,
    scan_bias,
)
from casmag.solver.multisession import EVIDENCE_START, solve_recording_starts
from casmag.solver.oriented import simulate_oriented
from casmag.solver.translational import TranslationalStaged

ROOT = Path(__file__).resolve().parents[2]


def _drifting_walk(seed: int = 2):
    """A 600-sample looping walk in a 3 m x 3 m room whose odometry drifts 1.0 and -0.7 m."""
    return casmag.load_problem(
        ROOT / "problems/bench/walk.yaml",
        [
            f"seed={seed}",
            "simulation.trajectory.samples=600",
            "simulation.trajectory.area=[3.0, 3.0]",
            "simulation.odometry.bias=[1.5e-3, -1.0e-3]",
        ],
    )


def _rmse(P, T):
    return float(np.sqrt(np.mean(np.sum((P - T) ** 2, axis=1))))


def test_evidence_score_is_the_marginal_likelihood_of_the_reduced_rank_map():
    rng = np.random.default_rng(4)
    P = rng.uniform(-1.0, 1.0, (40, 2))
    Y = rng.standard_normal((40, 3))
    Yc = Y - Y.mean(axis=0)
    basis = HilbertBasis(Domain.around(P, 1.0), 30)
    v = np.asarray(basis.prior_variances("se", 1.3, 0.5), dtype=float)
    Phi = basis.phi(P)
    K = Phi @ np.diag(v) @ Phi.T + 0.2**2 * np.eye(40)
    _, logdet = np.linalg.slogdet(K)
    dense = sum(
        0.5 * y @ np.linalg.solve(K, y) + 0.5 * logdet + 20.0 * np.log(2.0 * np.pi) for y in Yc.T
    )
    assert evidence_score(basis, v, P, Yc, 0.2) == pytest.approx(dense, rel=1e-10)


def _translational_path(DR, Y):
    k = np.arange(len(DR), dtype=float)[:, None]
    return lambda b: (DR - k * b, Y)


def test_scan_finds_the_drift_the_dead_reckoning_carries():
    data = simulate_problem(_drifting_walk())
    DR, T = data.dead_reckoning(), data.P_true
    grid = drift_grid(DR, 0.35)
    scan = scan_bias(grid, _translational_path(DR, data.Y), 1.0, 0.35, 0.1)  # the walk's
    k = np.arange(len(DR))[:, None]
    assert not scan.at_edge
    # The end drift it removes is within two grid spacings of the true one (0.9, -0.6 m).
    end = (len(DR) - 1) * (scan.bias - np.ravel(data.bias_true))
    assert np.all(np.abs(end) <= 2 * scan.spacing), (end, scan.spacing)
    assert _rmse(DR - k * scan.bias, T) < 0.25 * _rmse(DR, T)
    assert scan.score < scan.score_zero


def test_the_grids_hold_no_bias_at_their_centre_and_reach_the_set_drift():
    P = np.column_stack([np.linspace(0.0, 30.0, 301), np.zeros(301)])  # a 30 m path
    drift = drift_grid(P, 0.3)
    assert drift.shape == (drift.shape[0], drift.shape[0]) and drift.shape[0] % 2 == 1
    assert not np.any(drift.biases[len(drift.biases) // 2])
    assert drift.reach == pytest.approx(0.08 * 30.0)
    corner = drift.biases[-1] * 300  # the end drift of the outermost candidate
    assert corner == pytest.approx([drift.reach, drift.reach])
    turn = heading_grid(P[:51], 60.0, 0.3)
    assert turn.shape[0] % 2 == 1 and turn.biases[len(turn.biases) // 2] == 0.0
    # The outermost heading rates turn the heading by +-pi over the 60 s, in steps that
    # move the far end (5 m out) by half the scan lengthscale (0.3 m) at most.
    assert turn.biases[-1] * 60.0 == pytest.approx(np.pi)
    assert turn.biases[0] * 60.0 == pytest.approx(-np.pi)
    assert turn.spacing <= 0.3 + 1e-12


def test_no_scan_where_its_map_would_be_too_large():
    rng = np.random.default_rng(1)
    DR = np.cumsum(rng.normal(0.0, 1.0, (300, 2)), axis=0) * 3.0  # hundreds of metres
    Y = rng.standard_normal((300, 3))
    assert scan_bias(drift_grid(DR, 0.3), _translational_path(DR, Y), 1.0, 0.3, 0.1) is None


def test_a_translational_start_removes_a_per_step_bias():
    data = simulate_problem(_drifting_walk())
    model = TranslationalStaged(_drifting_walk(), data)
    b = np.array([1.0e-3, -5.0e-4])
    start = model.start(data.n_samples, b)
    np.testing.assert_allclose(start["P"], data.debiased(b).dead_reckoning())
    np.testing.assert_allclose(start["bias"], b[None, :])
    with pytest.raises(ValueError, match="no heading"):
        model.start(data.n_samples, 0.1)


def test_the_evidence_bias_is_one_more_start_of_a_recording_kept_by_its_cost():
    problem = _drifting_walk()
    data = simulate_problem(problem)
    P0, records = solve_recording_starts(problem, data)
    assert [r["start"] for r in records] == ["dead reckoning", EVIDENCE_START]
    scan = records[-1]["scan"]
    assert scan["score"] < scan["score_zero"] and len(scan["bias"]) == 2
    costs = [r["cost"] for r in records]
    kept = [r for r in records if r["kept"]]
    assert len(kept) == 1 and kept[0]["cost"] == min(c for c in costs if c is not None)
    assert _rmse(P0, data.P_true) < 0.25 * _rmse(data.dead_reckoning(), data.P_true)


def test_the_heading_scan_finds_a_planar_walk_s_heading_rate_bias():
    problem = load_oriented_problem(
        ROOT / "problems/planar/walk.yaml", ["seed=3", "motion.heading_bias=0.01"]
    )
    rec, _ = simulate_oriented(problem)
    t = rec.t - rec.t[0]
    dt = np.diff(rec.t)
    p0, psi0 = rec.P_true[0], float(rec.yaw_true[0])

    def path_of(b):
        P, psi = dead_reckon_planar(rec.increments, p0, psi0, b * dt)
        zero = np.zeros_like(psi)
        return P, sd.rotate(sd.quat_from_euler(zero, zero, psi), rec.Y)

    grid = heading_grid(path_of(0.0)[0], float(t[-1]), 1.0)  # the walk's field: l 1 m
    scan = scan_bias(grid, path_of, 1.0, 1.0, 0.05)
    assert not scan.at_edge
    step = grid.biases[1] - grid.biases[0]
    assert abs(scan.bias - 0.01) <= 2 * step, (scan.bias, step)
    DR = path_of(0.0)[0]
    assert _rmse(path_of(scan.bias)[0], rec.P_true) < 0.25 * _rmse(DR, rec.P_true)
