"""Truth-free flags of the IMU model's GP-SLAM estimate (casmag.solver.imu)."""

import numpy as np
import pytest

from casmag.solver.imu import GROW_MISFIT, SPREAD_LIMIT, path_spread, schedule_needed


def test_a_path_spread_beyond_the_limit_is_flagged_and_a_drift_correction_is_not():
    """A GP-SLAM path scaled about its centroid by more than SPREAD_LIMIT against the
    IMU-only path is flagged ``path_spread`` with the ratio; a shifted, slightly rotated and
    slightly scaled path (what a drift correction does) is not."""
    rng = np.random.default_rng(7)
    imu_only = np.cumsum(rng.normal(scale=0.01, size=(50, 3)), axis=0)
    c, s = np.cos(0.2), np.sin(0.2)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    corrected = 0.9 * (imu_only - imu_only.mean(0)) @ R.T + [0.05, -0.02, 0.0]
    assert path_spread(corrected, imu_only) is None
    spread = imu_only.mean(0) + 4.0 * (imu_only - imu_only.mean(0))
    flag = path_spread(spread, imu_only)
    assert flag["name"] == "path_spread"
    assert flag["evidence"]["ratio"] == pytest.approx(4.0)
    assert flag["evidence"]["limit"] == SPREAD_LIMIT
    assert "\n" not in flag["reason"]


def test_a_later_schedule_runs_only_after_a_failed_or_badly_fitting_one():
    """The ladder's rule (casmag.solver.imu.schedule_needed): coarse-to-fine after a failure
    or a misfit above refit_misfit; the grown schedule and the one from the IMU-only
    adjustment without closures only after a failure or a misfit above GROW_MISFIT."""
    assert schedule_needed("coarse_to_fine", True, 0.6, 0.55)
    assert not schedule_needed("coarse_to_fine", True, 0.5, 0.55)
    for name in ("grown", "without_closures"):
        assert not schedule_needed(name, True, 0.9 * GROW_MISFIT, 0.55)
        assert schedule_needed(name, True, 1.1 * GROW_MISFIT, 0.55)
        assert schedule_needed(name, False, 0.1, 0.55)
