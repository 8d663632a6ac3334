"""The dipole-walk recording: a translational walk in a physical field, read back as a
recording with its truth and the drift it was asked for."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from casmag.data.recording import read_recording
from casmag.experiments.dipolewalk import dipole_walk


def test_dipole_walk_recording_reads_back_with_its_drift(tmp_path):
    out = tmp_path / "walk.csv"
    subprocess.run(
        [sys.executable, "-m", "casmag.experiments.dipolewalk", str(out), "--samples", "3000",
         "--area", "4", "--seed", "2", "--drift", "0.4"],
        check=True, capture_output=True,
    )  # fmt: skip
    rec = read_recording(out)
    data = rec.to_dataset()
    assert data.n_samples == 3000 and data.P_true is not None
    assert np.all(np.abs(data.P_true) <= 2.0 + 0.05)  # inside the 4 m square
    err = data.dead_reckoning() - data.P_true
    rmse = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    assert 0.3 < rmse < 0.6, rmse  # 0.4 m of bias drift plus the 2 mm random walk
    field = np.linalg.norm(data.Y, axis=1)
    assert 30.0 < np.median(field) < 80.0  # microtesla, Earth's field plus the dipoles
    assert np.std(data.Y, axis=0).min() > 0.5  # the dipoles vary the field along the path
    again = dipole_walk(3000, 4.0, 2, 0.4)
    np.testing.assert_allclose(data.Y, again["Y"], rtol=1e-15)  # seeded
