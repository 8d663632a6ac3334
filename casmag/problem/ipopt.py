"""IPOPT options checked against IPOPT itself before anything is built.

``solver.linear_solver`` and the options under ``solver.ipopt`` reach IPOPT only when a
problem's NLP is created, where an unknown option, a value of the wrong type or one out of
range stops the build, and a linear solver this casadi build does not ship makes every
solve fail with ``Invalid_Option``. :func:`option_error` creates IPOPT on a one-variable
problem with the option alone (cached per option and value) and words what IPOPT refused;
:func:`linear_solver_error` solves that problem once with the linear solver. IPOPT prints
its option documentation when it refuses a value; that text is captured, never shown.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import io
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator
from typing import Any

#: Linear solvers IPOPT may use here: MUMPS and SPRAL ship in the casadi wheel; the HSL
#: solvers (ma27, ma57, ma77, ma86, ma97) and Pardiso need libraries it does not ship
#: (measured on casadi 3.8: ma27 and ma57 fail every solve with Invalid_Option,
#: pardisomkl crashes the process). MUMPS stays the default: measured 2026-12-07 (casadi
#: 3.8.2, 2 cores, each run alone, three IPOPT iterations from the truth on 10,000 samples
#: of ``problems/bench/walk.yaml`` with the tiles in the dipole field; SPRAL with
#: OMP_CANCELLATION and OMP_PROC_BIND set, as it asks), over 6 x 6 m SPRAL's search
#: directions took 20.0 s against MUMPS's 3.6 s, and over 50 x 70 m (87,794 unknowns,
#: 26.7 million Hessian nonzeros) SPRAL stopped at the first with IPOPT's "Not enough
#: memory" where MUMPS took 47.8 s for all three and a peak of 4.84 GiB.
LINEAR_SOLVERS = ("mumps", "spral")

#: Options casmag does not pass on: an option file would bypass these checks.
REFUSED = {
    "option_file_name": "IPOPT option files are not read; give the options under solver.ipopt",
}

# One capture at a time: file descriptors 1 and 2 belong to the whole process.
_CAPTURE_LOCK = threading.Lock()

_TYPE_ERRORS = {
    'Assertion "is_int()" failed': "integer",
    'Assertion "is_double()" failed': "number",
    'Assertion "is_string()" failed': "string",
}


@contextlib.contextmanager
def _captured_output() -> Iterator[list[str]]:
    """Capture what is printed meanwhile: CasADi's Python module prints through
    ``sys.stdout``, IPOPT's own code to file descriptors 1 and 2; the list receives it."""
    libc = ctypes.CDLL(None)
    text: list[str] = []
    python = io.StringIO()
    with _CAPTURE_LOCK, tempfile.TemporaryFile() as sink:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        libc.fflush(None)
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            with contextlib.redirect_stdout(python), contextlib.redirect_stderr(python):
                yield text
        finally:
            libc.fflush(None)
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            text.append(python.getvalue() + sink.read().decode("utf-8", "replace"))


def _create(options: dict[str, Any], solve: bool = False) -> tuple[str | None, str, str | None]:
    """Create IPOPT on min (x - 1)^2 with ``options`` (IPOPT names, no prefix) and, with
    ``solve``, solve it once. Returns (CasADi's error or None, captured output, status)."""
    import casadi as ca

    x = ca.MX.sym("x")
    opts: dict[str, Any] = {"print_time": False, "ipopt.sb": "yes", "ipopt.print_level": 0}
    opts.update({f"ipopt.{k}": v for k, v in options.items()})
    error = status = None
    with _captured_output() as out:
        try:
            solver = ca.nlpsol("casmag_option_check", "ipopt", {"x": x, "f": (x - 1) ** 2}, opts)
            if solve:
                solver(x0=0.0)
                status = str(solver.stats().get("return_status"))
        except RuntimeError as exc:
            error = str(exc)
    return error, out[0] if out else "", status


def _invalid_setting(name: str, printed: str) -> str:
    """The reason IPOPT gave for an invalid value, from the documentation it printed: the
    valid range of a number or the valid settings of a string option."""
    lines = printed.splitlines()
    settings: list[str] = []
    in_settings = False
    for line in lines:
        if line.startswith("Valid Settings:"):
            in_settings = True
            continue
        if in_settings:
            if line.startswith("\t"):
                settings.append(line.strip().split(" ", 1)[0])
                continue
            in_settings = False
        # A number's range: "0 < (1e-08) <= +inf" (the default in parentheses).
        m = re.fullmatch(r"\s*(\S+\s*<=?)\s*\([^)]*\)\s*(<=?\s*\S+)\s*", line)
        if m:
            return f"out of range (IPOPT needs {m.group(1)} {name} {m.group(2)})"
    if settings:
        return f"not a valid setting (IPOPT accepts {', '.join(settings)})"
    return "not a valid setting for IPOPT"


@functools.lru_cache(maxsize=512)
def _option_error(name: str, value: Any, kind: type) -> str | None:
    if name in REFUSED:
        return REFUSED[name]
    if name == "linear_solver":
        return linear_solver_error(value)
    probe = os.devnull if name == "output_file" and isinstance(value, str) else value
    error, printed, _ = _create({name: probe})
    if error is not None:
        if "No such IPOPT option" in error:
            return "not an IPOPT option"
        for marker, wanted in _TYPE_ERRORS.items():
            if marker in error:
                return f"IPOPT expects {'an' if wanted == 'integer' else 'a'} {wanted}"
        if "Invalid options were detected" in error:
            return _invalid_setting(name, printed)
        return error.strip().splitlines()[-1]
    if kind is float:
        # CasADi truncates a number given for an integer option; ask IPOPT the type.
        error, _, _ = _create({name: "casmag-type-check"})
        if error is not None and 'Assertion "is_int()" failed' in error:
            return "IPOPT expects an integer"
    return None


def option_error(name: str, value: Any) -> str | None:
    """Why IPOPT refuses the option ``name: value`` (None when it accepts it)."""
    return _option_error(name, value, type(value))


@functools.lru_cache(maxsize=16)
def linear_solver_error(name: Any) -> str | None:
    """Why IPOPT cannot use the linear solver ``name`` here (None when it can)."""
    if name not in LINEAR_SOLVERS:
        return f"not a linear solver this casadi build ships (use {' or '.join(LINEAR_SOLVERS)})"
    if name == "mumps":  # IPOPT's default, always built in
        return None
    error, _, status = _create({"linear_solver": name}, solve=True)
    if error is not None or status != "Solve_Succeeded":
        return "not available in this casadi build (use mumps)"
    return None
