"""Read a saved result folder back (result.json and arrays.npz): its statistics, its
convergence record and its arrays, e.g. to plot or evaluate with other tools.

    python examples/saved_result.py RESULT_DIR
"""

import sys

import numpy as np

import casmag

result = casmag.Result.load(sys.argv[1])
print(f"{result.info.get('name')}: {result.status}, success {result.success}")
print(f"  trusted: {result.trusted} {result.verdict['reasons']}")
print(f"  after an SE alignment: {casmag.evaluate(result, 'se')['after']['rmse']} m")
for stage in result.convergence:  # every IPOPT solve of the run
    print(f"  {stage['stage']}: {stage['status']}, {stage['iterations']} iterations")
for key, value in sorted(result.arrays.items()):
    print(f"  {key}: {np.shape(value)}")
if result.arrays.get("P_true") is not None:
    err = np.linalg.norm(result.arrays["P_estimate"] - result.arrays["P_true"], axis=1)
    print(f"  position error: RMSE {np.sqrt(np.mean(err**2)):.4f} m, max {err.max():.4f} m")
