"""The versions a result depends on: casmag, Python, CasADi, the IPOPT inside CasADi's wheel,
numpy, scipy and numpy's BLAS, plus the processor architecture.

Every ``result.json`` carries them under ``info.versions``; :func:`line` is the one-line form
``make test-latest`` prints before the tests.
"""

from __future__ import annotations

import platform
import re
from functools import lru_cache
from pathlib import Path
from typing import Any

import casadi
import numpy
import scipy

__version__ = "0.1.0"


def _ipopt_version() -> str:
    """IPOPT's version from the shared library CasADi's wheel ships (libipopt.so.X.Y.Z)."""
    here = Path(casadi.__file__).parent
    found = sorted(
        m.group(1)
        for f in here.glob("*ipopt*")
        if (m := re.search(r"ipopt[^/]*?\.(\d+\.\d+\.\d+)", f.name)) and "sipopt" not in f.name
    )
    return found[-1] if found else "unknown"


def _blas() -> str:
    try:
        from threadpoolctl import threadpool_info

        for lib in threadpool_info():
            if lib.get("user_api") == "blas" and "numpy" in str(lib.get("filepath", "")):
                return f"{lib.get('internal_api')} {lib.get('version')}"
    except Exception:  # pragma: no cover - informational only
        pass
    return "unknown"


@lru_cache(maxsize=1)
def versions() -> dict[str, Any]:
    """{name: version} of what a solve depends on."""
    return {
        "casmag": __version__,
        "python": platform.python_version(),
        "casadi": casadi.__version__,
        "ipopt": _ipopt_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "blas": _blas(),
        "machine": platform.machine(),
    }


def line() -> str:
    """``name=version`` pairs on one line."""
    return " ".join(f"{k}={v}" for k, v in versions().items())
