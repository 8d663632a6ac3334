import os
from pathlib import Path

import pytest

# `make test` runs one pytest-xdist worker per core. Each worker's BLAS and OpenMP pools
# would start one thread per core as well, and the workers' threads would then contend for
# the same cores: on 2 cores the tests of test_staged.py and test_tiledmap.py took 77 s
# that way and 58 s with one thread per worker. One thread per worker also makes the sums'
# order, and so the iterates, the same on machines with any number of cores. Set before
# numpy or casadi is loaded in the worker, and inherited by the commands the tests run; a
# run in one process (PYTEST_ARGS=-n0) keeps the libraries' defaults.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def root() -> Path:
    return ROOT
