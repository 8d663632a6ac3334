"""Memory: what the machine gives this process, what the process holds, and the budget a
solve may use (``solver.memory_budget``).

A solve's peak memory beyond what the process holds when IPOPT starts is dominated by the
Hessian: the numpy map blocks' values, CasADi's and IPOPT's copies and MUMPS's factor all
grow with its non-zeros. Measured on this project's 2-core machine (casadi 3.8.2, IPOPT
3.14.19, MUMPS; the walk of ``make bench-scale`` in a 6 x 6 m room, one knot per second, 4
IPOPT iterations; resident memory when the solve starts -> peak):

| map | samples | Hessian non-zeros | GiB | bytes per non-zero |
|---|---|---|---|---|
| box, 861 functions | 2,000 | 2,153,446 | 0.29 -> 0.61 | 149 |
| box, 4,000 functions | 2,000 | 28,831,807 | 1.24 -> 4.46 | 111 |
| box, 1,124 functions | 8,000 | 7,305,901 | 0.47 -> 1.78 | 180 |
| tiled (curl-free) | 2,000 | 5,661,079 | 0.44 -> 1.14 | 124 |

:data:`HESSIAN_NONZERO_BYTES` is above the largest, so the estimate errs on the side of
refusing. IPOPT's ``mumps_mem_percent`` did not change the peak (100 against the default
1000: 4.45 against 4.44 GiB). The same estimate is taken twice: while the NLP is built, as
soon as a map's Hessian pattern is known and before CasADi copies it (:func:`check_pattern`,
raising MemoryBudgetError; the 4,000-function box's build alone peaked at 3.08 GiB), and
when a solve starts (casmag.nlp), for the Hessians CasADi forms itself.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from casmag.errors import MemoryBudgetError

GIB = 2**30
#: Default budget: this fraction of the memory the machine gives the process.
BUDGET_FRACTION = 0.8
#: Peak bytes per non-zero of the (upper-triangular) Hessian IPOPT factorises.
HESSIAN_NONZERO_BYTES = 200
#: What to change when a solve does not fit its budget.
REMEDY = (
    "raise it, or make the problem smaller (fewer knots or keyframes, fewer basis functions, "
    "the tiled map)"
)


def _cgroup_limit() -> int | None:
    """The memory limit of this process's control group (v2, then v1), if any."""
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 2**60:
            return int(text)
    return None


def machine_bytes() -> int:
    """The memory this process may use: the physical memory, or its control group's limit
    when lower."""
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    limit = _cgroup_limit()
    return min(physical, limit) if limit is not None else physical


def rss_bytes() -> int:
    """The process's resident memory now (Linux: /proc/self/statm; elsewhere its peak so
    far, from getrusage)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        import resource
        import sys

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak if sys.platform == "darwin" else peak * 1024


def budget_bytes(gib: float | None) -> int:
    """A budget in bytes: ``gib`` GiB, or (None) :data:`BUDGET_FRACTION` of
    :func:`machine_bytes`."""
    if gib is None:
        return int(BUDGET_FRACTION * machine_bytes())
    return int(gib * GIB)


def solve_estimate(hessian_nonzeros: int) -> int:
    """The peak resident memory a solve is expected to reach, in bytes: what the process
    holds now plus :data:`HESSIAN_NONZERO_BYTES` per Hessian non-zero."""
    return rss_bytes() + HESSIAN_NONZERO_BYTES * int(hessian_nonzeros)


def over_budget_message(estimate: int | None, budget: int, nonzeros: int) -> str:
    """The one line a refused or stopped solve reports."""
    what = (
        f"needs about {estimate / GIB:.3g} GiB"
        if estimate is not None
        else f"passed {rss_bytes() / GIB:.3g} GiB while solving"
    )
    return (
        f"the solve {what} (Hessian with {nonzeros:,} non-zeros) against a memory budget "
        f"of {budget / GIB:.3g} GiB (solver.memory_budget): {REMEDY}"
    )


#: The budget of the NLP being built (set by casmag.model.builder.build_slam).
_BUILD_BUDGET: ContextVar[int | None] = ContextVar("casmag_build_budget", default=None)


@contextmanager
def build_budget(budget: int) -> Iterator[None]:
    """Within this block, a Hessian pattern (:func:`check_pattern`) is held against
    ``budget`` bytes."""
    token = _BUILD_BUDGET.set(budget)
    try:
        yield
    finally:
        _BUILD_BUDGET.reset(token)


def check_pattern(nonzeros: int) -> None:
    """Raise MemoryBudgetError when a Hessian of ``nonzeros`` non-zeros, whose pattern is
    about to be built, would take the solve past the budget of the NLP being built (the
    same estimate as the solve's own check, taken before the pattern's CasADi copies)."""
    budget = _BUILD_BUDGET.get()
    if budget is None:
        return
    estimate = solve_estimate(nonzeros)
    if estimate > budget:
        raise MemoryBudgetError(over_budget_message(estimate, budget, nonzeros))
