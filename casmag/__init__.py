"""casmag: magnetic-field SLAM with a Gaussian-process field map, as one CasADi NLP solved
by IPOPT.

    import casmag
    problem = casmag.load_problem("problems/paper/base.yaml", seed=7)
    # settings as keyword sections: model={"gp": {"sigma_f": 0.2}}, solver={...}
    result = casmag.solve(problem)
    print(result.status, result.rmse_before, result.rmse_after)
    result.save("out")                      # result.json, arrays.npz, trajectory.csv, PNGs
    again = casmag.load_result("out")       # any result folder (translational, planar, IMU)
    casmag.evaluate(result, "se")           # errors after a rigid alignment to the truth

    result = casmag.slam("walk.csv")        # a recording, casmag slam's defaults
                                            # (translational or planar)
"""

import os

# MUMPS (in casadi's wheel) writes a closing line to Fortran's standard output when a
# casadi Linsol ends it (casmag.linalg); gfortran buffers that unit when it is not a
# terminal and writes the buffer out when the process exits, past casmag.linalg's
# redirection. Unbuffered, the line goes where the redirection sends it. Read once, when
# casadi first loads a plugin linked to gfortran (IPOPT, MUMPS), which is after this.
os.environ.setdefault("GFORTRAN_UNBUFFERED_PRECONNECTED", "y")

from casmag.errors import CasmagError, DataError, ProblemError, SolverError
from casmag.problem.spec import Problem, ProblemSpec, load_problem
from casmag.result import Result
from casmag.result.evaluation import evaluate_result as evaluate
from casmag.solver.api import load_result, solve
from casmag.solver.recslam import slam, slam_sessions
from casmag.versions import __version__

__all__ = [
    "CasmagError",
    "DataError",
    "Problem",
    "ProblemError",
    "ProblemSpec",
    "Result",
    "SolverError",
    "__version__",
    "evaluate",
    "load_problem",
    "load_result",
    "slam",
    "slam_sessions",
    "solve",
]
