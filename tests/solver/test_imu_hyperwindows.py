"""Marginal-likelihood windows of the IMU pipeline (``model.gp.hyper_window``,
``hyper_windows``)."""

import numpy as np
import pytest
from small_problems import tiny_imu as _tiny

from casmag import strapdown as sd
from casmag.data.dipoles import Dipole, DipoleField, earth_field
from casmag.errors import ProblemError
from casmag.gp.hyper import estimate_hyperparameters
from casmag.model.imu import Keyframes
from casmag.problem.imu import HYPER_WINDOW, HYPER_WINDOWS, load_imu_problem
from casmag.solver.imu import ImuSolveStage, _hyperparameters, hyper_windows, short_windows


def test_default_windows_and_the_short_ones():
    model = load_imu_problem(_tiny()).spec.model  # 5 Hz keyframes
    assert hyper_windows(model, 246) == (HYPER_WINDOW, HYPER_WINDOWS) == (30, 16)
    assert short_windows(model, 246) == (10, 24)  # 2 s, all
    assert short_windows(model, 7) == (10, 1)  # shorter than a window: one window, all of it
    assert short_windows(load_imu_problem(_tiny(), ["model.keyframe_rate=20"]).spec.model, 246) == (
        40,
        6,
    )
    assert short_windows(load_imu_problem(_tiny(), ["model.keyframe_rate=1"]).spec.model, 246) == (
        3,
        82,
    )
    model = load_imu_problem(
        _tiny(), ["model.gp.hyper_window=10", "model.gp.hyper_windows=all"]
    ).spec.model
    assert hyper_windows(model, 246) == (10, 24)


@pytest.mark.parametrize(("key", "value"), [("hyper_window", "2"), ("hyper_windows", "some")])
def test_bad_windows_name_the_key(key, value):
    with pytest.raises(ProblemError) as err:
        load_imu_problem(_tiny(), [f"model.gp.{key}={value}"])
    assert f"model.gp.{key}" in str(err.value)


def test_hyperparameters_use_the_configured_windows():
    """The estimate on a previous stage's path is the marginal likelihood over the
    configured windows: 60 keyframes along a line past a dipole, windows of 10, all six."""
    rng = np.random.default_rng(3)
    K = 60
    P = np.column_stack([np.linspace(0.0, 0.6, K), 0.01 * rng.standard_normal(K), np.zeros(K)])
    dipole = Dipole(np.array([0.3, 0.15, -0.1]), np.array([2e-3, 0.0, 3e-3]))
    field = DipoleField(earth=earth_field(), dipoles=(dipole,))
    Q = sd.gibbs_quat(0.1 * rng.standard_normal((K, 3)))
    Y = sd.rotate(sd.quat_conj(Q), field(P)) + 0.004 * rng.standard_normal((K, 3))
    kf = Keyframes(idx=np.arange(K), DQ=None, DV=None, LINV=None, Y=Y)
    prev = ImuSolveStage(solution=None, nlp=None, P=P, V=None, Q=Q, b_w=None, b_a=None)
    problem = load_imu_problem(_tiny(gp={"hyper_window": 10, "hyper_windows": "all"}))
    hyper, _, est, windows = _hyperparameters(problem, kf, prev, "test")
    assert windows == (10, 6)
    direct = estimate_hyperparameters(P, sd.rotate(Q, Y), window=10, max_windows=6)
    assert est.n_windows == 6 and est.n_samples == K
    assert hyper["lengthscale"] == pytest.approx(direct.lengthscale)
    assert hyper["sigma_f"] == pytest.approx(direct.sigma_f)


def test_a_drifting_path_is_estimated_again_on_short_windows():
    """A path back and forth over 0.6 m (period 4 s, 24 s at 5 Hz) past a dipole, the
    previous estimate of it drifting away (quadratically, 0.16 m at the end): within a
    30-keyframe window the returns land elsewhere, so the drift is taken for noise (the
    estimate's sigma_m 7 times the assumed 0.004) and the estimate comes from 2-s windows
    (10 keyframes, no return within one) with drift_ratio 3; with null (the default) it
    does not."""
    rng = np.random.default_rng(4)
    K = 120
    t = np.arange(K) / 5.0
    P = np.column_stack(
        [0.3 * np.sin(2 * np.pi * t / 4.0), 0.002 * rng.standard_normal(K), np.zeros(K)]
    )
    dipole = Dipole(np.array([0.1, 0.15, -0.1]), np.array([2e-3, 0.0, 3e-3]))
    Y = DipoleField(earth=earth_field(), dipoles=(dipole,))(P)
    Y = Y + 0.004 * rng.standard_normal((K, 3))
    Q = np.tile([1.0, 0.0, 0.0, 0.0], (K, 1))
    drifted = P + 0.2 * (t[:, None] / t[-1]) ** 2 * np.array([[0.6, 0.8, 0.0]])
    kf = Keyframes(idx=np.arange(K), DQ=None, DV=None, LINV=None, Y=Y)
    prev = ImuSolveStage(solution=None, nlp=None, P=drifted, V=None, Q=Q, b_w=None, b_a=None)
    long_est = estimate_hyperparameters(drifted, Y, window=30, max_windows=16)
    assert long_est.sigma_m > 3 * 0.004  # the drift taken for noise
    problem = load_imu_problem(_tiny(gp={"drift_ratio": 3.0}))
    _, source, est, windows = _hyperparameters(problem, kf, prev, "test")
    assert windows == (10, 12) and est.n_windows == 12 and "10-keyframe windows" in source
    assert est.sigma_m < 0.6 * long_est.sigma_m
    problem = load_imu_problem(_tiny())  # drift_ratio null: the default
    _, _, est, windows = _hyperparameters(problem, kf, prev, "test")
    assert windows == (30, 16) and est.n_windows == 4
    assert est.sigma_m == pytest.approx(long_est.sigma_m)
