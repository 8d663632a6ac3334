"""Ctrl-C and SIGTERM as a clean stop.

The command line installs :func:`install`: a SIGINT or SIGTERM then raises
:class:`Interrupted` (a BaseException, so every ``finally`` and atomic writer cleans up),
except inside :func:`deferred`, where the signal is only recorded and raised as Interrupted
when the block ends. Two places need that:

- a call into IPOPT: an exception raised inside CasADi's callbacks would turn into a solver
  failure; the IPOPT iteration callback (casmag.nlp) stops IPOPT at its next iteration;
- waiting on a process pool (casmag.experiments.sweep): an exception raised at an arbitrary
  point inside ``concurrent.futures.wait`` can leave a future's lock held, and the pool's
  thread, which Python joins at exit, then waits on it for ever (measured: a Ctrl-C sent to
  a pool of 5000 short tasks hung the process on 4 of 10 tries).

Library users who do not call :func:`install` keep Python's own handling, except that in
the main thread a Ctrl-C inside :func:`deferred` is held back the same way and raised as
KeyboardInterrupt when the block ends.

Worker processes (casmag.experiments.sweep) install it with ``defer``: the handler then only records
the signal, as it does inside :func:`deferred`, since raising inside a CasADi callback
evaluated outside IPOPT would print a traceback and turn into an error; :func:`check` raises
Interrupted at the next safe point, and IPOPT stops at its next iteration.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class Interrupted(BaseException):
    """The run was stopped by a signal; ``exit_code`` is 128 + the signal number."""

    def __init__(self, signum: int):
        self.signum = signum
        self.exit_code = 128 + signum
        self.name = signal.Signals(signum).name
        super().__init__(f"interrupted by {self.name}")


_state: dict[str, Any] = {"depth": 0, "pending": None}


def _handler(signum: int, frame: Any) -> None:
    if _state["depth"] > 0:
        _state["pending"] = signum
        return
    raise Interrupted(signum)


def _record(signum: int, frame: Any) -> None:
    _state["pending"] = signum


def install(defer: bool = False) -> None:
    """Handle SIGINT and SIGTERM as described in the module docstring (``defer``: record
    them only, for :func:`check` and :func:`solving` to raise)."""
    handler = _record if defer else _handler
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def check() -> None:
    """Raise Interrupted for a signal recorded outside a solve (a no-op without one)."""
    signum = _state["pending"]
    if signum is not None and _state["depth"] == 0:
        _state["pending"] = None
        raise Interrupted(signum)


def pending() -> bool:
    """A signal arrived during the current solve."""
    return _state["pending"] is not None


@contextmanager
def deferred() -> Iterator[None]:
    """Signals are recorded while the block runs and raised when it ends (see the module
    docstring): as Interrupted, or as KeyboardInterrupt for a Ctrl-C that Python's own
    handler would have raised."""
    own = (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    )
    previous = signal.signal(signal.SIGINT, _record) if own else None
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
        if own:
            signal.signal(signal.SIGINT, previous)
        signum = _state["pending"]
        if _state["depth"] == 0 and signum is not None:
            _state["pending"] = None
            if own and signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise Interrupted(signum)
