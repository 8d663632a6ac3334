"""Errors casmag raises for bad input and failed solves.

Every user-facing error renders as one line that names where the problem is (file, field or
column) and why, so the command line can print it as it is and exit non-zero.
"""

from __future__ import annotations


class CasmagError(Exception):
    """Base class of all errors casmag raises on purpose."""


class ProblemError(CasmagError):
    """A problem file or dictionary is invalid.

    source: the file path (or "<dict>"), field: dotted key path, reason: what is wrong.
    """

    def __init__(self, source: str, field: str, reason: str):
        self.source, self.field, self.reason = source, field, reason
        where = f"{source}: {field}" if field else source
        super().__init__(one_line(f"{where}: {reason}"))


def one_line(text: str) -> str:
    """Escape line breaks so a message always prints as one line."""
    return text.replace("\r", "\\r").replace("\n", "\\n")


class DataError(CasmagError):
    """Input data (a recording, a data file) is invalid: names the file, row or column."""


class SolverError(CasmagError):
    """IPOPT did not converge; carries IPOPT's return status and iteration count."""

    def __init__(self, status: str, iterations: int, message: str | None = None):
        self.status, self.iterations = status, iterations
        super().__init__(message or f"IPOPT failed: status {status} after {iterations} iterations")


class MemoryBudgetError(CasmagError):
    """A problem whose Hessian would not fit ``solver.memory_budget``, found while its NLP
    is built (casmag.memory): the solve is refused before it starts."""
