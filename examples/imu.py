"""IMU GP-SLAM (the paper's tightly coupled model): a small problem as a dictionary (the
schema of problems/imu/README.md), simulated, solved in stages (IMU-only adjustment, then
GP-SLAM), with the errors of every stage and the verdict on the estimate.

    python examples/imu.py [OUT_DIR]
"""

import sys
import tempfile

from casmag.solver.imu import solve_imu

problem = {
    "seed": 11,
    "name": "desk rectangle",
    "simulation": {
        "scenario": {"kind": "rectangle", "size": [0.12, 0.08], "loops": 1, "static": 0.5},
        "field": {"dipoles": [{"position": [0.25, 0.0, -0.1], "moment": [2e-3, 1e-3, -3e-3]}]},
    },
    "model": {"keyframe_rate": 5.0, "gp": {"sigma_f": 0.3, "lengthscale": 0.2, "num_basis": 60}},
    "solver": {"max_iter": 100, "tol": 1e-5},
}
result = solve_imu(problem)
print(f"{result.status} (IMU-only stage: {result.stage('imu_only')['status']})")
for stage, e in result.details["errors"].items():
    if e["rmse"] is not None:
        print(f"  {stage} position RMSE {e['rmse']:.4f} m")
print(f"  trusted: {result.trusted}")  # casmag.result.verdict: solver, misfit, flags
for reason in result.verdict["reasons"]:  # e.g. wrong_basin, worse_than_imu_only
    print(f"  not trusted: {reason}")
out = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="casmag-example-")
result.save(out)  # result.json, biases.md, trajectory.csv, trajectory.png, cost.png
print(f"saved to {out}")
