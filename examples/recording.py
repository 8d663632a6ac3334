"""GP-SLAM on a recording (CSV: t, dx, dy, mx, my, mz, optional truth), with casmag
slam's defaults: hyperparameters from the data, the field check, the plausibility checks.
Without an argument a small recording is simulated and written first.

    python examples/recording.py [RECORDING.csv]
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

import casmag
from casmag.data.recording import write_recording
from casmag.data.simulate import simulate_problem

if len(sys.argv) > 1:
    path = Path(sys.argv[1])
    result = casmag.slam(path, on_warning=print)
else:  # a simulated spiral walk, written as a recording at 10 Hz (removed afterwards)
    problem = casmag.load_problem("problems/paper/base.yaml", ["seed=3"])
    data = simulate_problem(problem)
    with tempfile.TemporaryDirectory(prefix="casmag-example-") as folder:
        path = Path(folder) / "walk.csv"
        t = 0.1 * np.arange(data.n_samples)  # s
        Y = 50.0 + 100.0 * data.Y  # the simulation's field units as microtesla-sized numbers
        write_recording(path, t, Y, dxy=data.U, P_true=data.P_true)
        result = casmag.slam(path, on_warning=print)
print(f"{path.name}: {result.status}, {result.iterations} iterations")
if result.rmse_before is not None and result.rmse_after is not None:
    print(f"RMSE {result.rmse_before:.4f} m -> {result.rmse_after:.4f} m")
print("estimated:", result.info["defaults"]["estimated"], result.hyperparameters)
print("warnings:", [w["check"] for w in result.warnings])
