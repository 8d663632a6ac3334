"""Magnetic loop closures (casmag.solver.closures): pairs at the same place found by the
field's signature along a drifting path."""

import numpy as np
from problem_files import PROBLEMS

from casmag.data.dipoles import Dipole, DipoleField, earth_field
from casmag.data.imusim import handwriting_path, simulate_imu
from casmag.problem.imu import load_imu_problem
from casmag.solver.closures import magnetic_closures
from casmag.solver.imu import closure_start, solve_imu_stages, structure_base

ELL = 0.1  # the map's lengthscale [m], that of the dipoles' field 0.25-0.4 m away


def _resample(points, step):
    """Points every ``step`` metres along the polyline."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    t = np.arange(0.0, s[-1], step)
    return np.stack([np.interp(t, s, points[:, k]) for k in range(3)], axis=1)


def _field(with_dipoles=True):
    dipoles = (
        (
            Dipole(np.array([0.12, 0.24, 0.0]), np.array([1.2e-3, -1.8e-3, 6.0e-4])),
            Dipole(np.array([0.10, 0.0, -0.22]), np.array([6.0e-4, 9.0e-4, -3.6e-3])),
            Dipole(np.array([-0.15, -0.15, 0.0]), np.array([4.0e-4, 2.0e-4, 2.0e-4])),
        )
        if with_dipoles
        else ()
    )
    return DipoleField(earth_field(), dipoles)


def _drifting(truth, rng, drift=0.15):
    """The truth with a smooth drift growing to ``drift`` metres (a bent quadratic in time)
    and a small heading error: what an IMU-only adjustment looks like."""
    t = np.linspace(0.0, 1.0, truth.shape[0])[:, None]
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    return truth + drift * t**2 * direction + 0.02 * np.sin(3 * t) * rng.normal(size=3)


def test_a_word_written_twice_closes_where_the_pen_returns():
    """Every accepted pair is within a third of a lengthscale in truth although the
    drifting path puts the passes up to 0.15 m apart, and most of the second pass closes."""
    rng = np.random.default_rng(3)
    truth = _resample(handwriting_path("mag", 0.12, 2, 0.01), 0.01)
    F = _field()(truth) + rng.normal(scale=0.002, size=truth.shape)
    P = _drifting(truth, rng)
    found = magnetic_closures(P, F, ELL)
    assert len(found) > 0.3 * truth.shape[0] / 2
    i, j = found.pairs.T
    assert np.all(j > i)
    assert np.max(np.linalg.norm(truth[i] - truth[j], axis=1)) < ELL / 3
    assert np.median(np.linalg.norm(P[i] - P[j], axis=1)) > ELL / 3  # the drift was real
    assert found.info["pairs"] == len(found)


def test_no_closures_in_a_field_without_variation_or_on_a_path_that_never_returns():
    rng = np.random.default_rng(4)
    truth = _resample(handwriting_path("mag", 0.12, 2, 0.01), 0.01)
    F = _field(with_dipoles=False)(truth) + rng.normal(scale=0.002, size=truth.shape)
    assert len(magnetic_closures(_drifting(truth, rng), F, ELL)) == 0
    line = _resample(np.array([[-0.3, -0.1, 0.0], [0.4, 0.2, 0.0]]), 0.005)
    F = _field()(line) + rng.normal(scale=0.002, size=line.shape)
    assert len(magnetic_closures(line, F, ELL)) == 0


def test_a_device_at_rest_or_a_short_path_gives_no_closures_and_says_why():
    P = np.zeros((200, 3))
    F = np.tile(earth_field(), (200, 1))
    found = magnetic_closures(P, F, ELL)
    assert len(found) == 0 and found.info["skipped"] == "no motion"
    short = _resample(np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]), 0.005)
    found = magnetic_closures(short, _field()(short), ELL)
    assert len(found) == 0 and "skipped" in found.info


def test_closures_bring_a_drifted_imu_path_back_to_its_first_pass():
    """The handwriting scenario (a word written twice, IMU-only path about 0.14 m from the
    truth against a lengthscale of 0.1 m): the closures found on the IMU-only adjustment
    are all kept (none beyond CLOSURE_OUTLIER sigma), close to within millimetres, and
    their adjustment is at least twice as near the truth: the start GP-SLAM needs."""
    problem = load_imu_problem(PROBLEMS / "imu" / "handwriting.yaml", ["seed=5"])
    data = simulate_imu(problem)
    alone = load_imu_problem(problem, ["model.gp.form=none"])
    res = solve_imu_stages(alone, data)
    kf, st1 = res.keyframes, res.imu_only
    hyper = {"sigma_f": 0.2, "lengthscale": ELL, "sigma_m": 0.002}
    base = structure_base(problem, data, kf.idx.size)
    stage, record = closure_start(problem, data, kf, base, st1, hyper, None)
    assert record["used"] and record["pairs_used"] == record["pairs"] > 50
    assert record["solves"][-1]["gap_after_median"] < 0.1 * record["gap_before_median"]
    assert record["solves"][-1]["iterations"] <= 20
    truth = data.truth.P[kf.idx]

    def rmse(P):
        return np.sqrt(np.mean(np.sum((P - truth) ** 2, axis=1)))

    assert rmse(stage.P) < 0.5 * rmse(st1.P)
