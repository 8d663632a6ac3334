"""Marginal-likelihood windows of the IMU pipeline (``model.gp.hyper_window``,
``hyper_windows``)."""

import numpy as np
import pytest
from test_imu import _tiny

from casmag import strapdown as sd
from casmag.dipoles import Dipole, DipoleField, earth_field
from casmag.errors import ProblemError
from casmag.hyper import estimate_hyperparameters
from casmag.imuconfig import load_imu_problem
from casmag.imuslam import (
    HYPER_WINDOW,
    HYPER_WINDOWS,
    ImuSolveStage,
    Keyframes,
    _hyperparameters,
    hyper_windows,
)


def test_default_windows_are_unchanged_and_all_covers_the_path():
    gp = load_imu_problem(_tiny()).spec.model.gp
    assert hyper_windows(gp, 246) == (HYPER_WINDOW, HYPER_WINDOWS) == (30, 16)
    gp = load_imu_problem(
        _tiny(), ["model.gp.hyper_window=10", "model.gp.hyper_windows=all"]
    ).spec.model.gp
    assert hyper_windows(gp, 246) == (10, 24)
    assert hyper_windows(gp, 7) == (10, 1)  # shorter than a window: one window, all of it


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
    hyper, _, est = _hyperparameters(problem, kf, prev, "test")
    direct = estimate_hyperparameters(P, sd.rotate(Q, Y), window=10, max_windows=6)
    assert est.n_windows == 6 and est.n_samples == K
    assert hyper["lengthscale"] == pytest.approx(direct.lengthscale)
    assert hyper["sigma_f"] == pytest.approx(direct.sigma_f)
