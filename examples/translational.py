"""Translational GP-SLAM built in Python: a problem as a dictionary (the schema of
problems/README.md), simulated from its seed, solved, saved and read back.

    python examples/translational.py [OUT_DIR]
"""

import sys
import tempfile

import casmag

problem = casmag.load_problem(
    {
        "seed": 7,
        "name": "spiral",
        "simulation": {
            "trajectory": {"kind": "spiral", "samples": 81, "step": 0.05},
            "field": {"kernel": "se", "sigma_f": 0.1, "lengthscale": 0.1},
        },
    },
    ["model.magnetometer.sigma_m=0.0005"],  # overrides: the command line's --set strings
)
result = casmag.solve(problem)
print(f"{result.status}: RMSE {result.rmse_before:.4f} m -> {result.rmse_after:.4f} m")
print(f"{result.iterations} IPOPT iterations; hyperparameters {result.hyperparameters}")

out = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="casmag-example-")
result.save(out)  # result.json, arrays.npz, trajectory.csv, trajectory.png, cost.png, map.png
again = casmag.Result.load(out)
print(f"saved to {out}; P_estimate {again.arrays['P_estimate'].shape}")
assert again.rmse_after == result.rmse_after
