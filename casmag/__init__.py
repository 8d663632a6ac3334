"""casmag: magnetic-field SLAM with a Gaussian-process field map, as one CasADi NLP solved
by IPOPT.

    import casmag
    problem = casmag.load_problem("problems/paper/base.yaml")
    result = casmag.solve(problem)
    print(result.status, result.rmse_before, result.rmse_after)
"""

from casmag.api import solve
from casmag.config import Problem, load_problem
from casmag.errors import CasmagError, DataError, ProblemError, SolverError
from casmag.result import Result
from casmag.versions import __version__

__all__ = [
    "CasmagError",
    "DataError",
    "Problem",
    "ProblemError",
    "Result",
    "SolverError",
    "__version__",
    "load_problem",
    "solve",
]
