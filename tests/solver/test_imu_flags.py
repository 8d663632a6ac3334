"""Truth-free flags of the IMU model's GP-SLAM estimate (casmag.solver.imu)."""

import numpy as np
import pytest

from casmag.solver.imu import SPREAD_LIMIT, path_spread


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
