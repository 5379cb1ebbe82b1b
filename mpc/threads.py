"""The MPC's and the OCP's CasADi work from one thread at a time.

CasADi's functions and solvers are not thread-safe, and CasADi releases the GIL in its calls. Two ``MPCController``
driving cycles in two threads of one process (they share the machine's NLPs and solvers, :mod:`mpc.controller.solver`)
died of a segmentation fault (stop 65): in one solver's call ("Memory corruption detected for output grad_f_x"), and
in two ``nlpsol`` builds of the continuous reference at once. A solver's ``stats()`` are also its last call's,
whichever thread made it. So:

- :func:`casadi_turn`, one re-entrant lock per process: a controller's construction, ``reset`` and steps, and
  :func:`mpc.benchmark.ocp.solve_ocp`, hold it. Threads take turns (for parallel cycles use processes:
  :mod:`mpc.workers`, Ray).
- :func:`exclusive`, a lock per solver: each call with its ``stats()``. The real-time controller's worker thread
  solves (it builds nothing) beside its own controller's step, which holds the turn; where two share a solver, they
  take turns in it.
"""

from __future__ import annotations

import functools
import os
import threading
import weakref
from collections.abc import Callable
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

_TURN = threading.RLock()
_LOCKS: weakref.WeakKeyDictionary[Any, threading.Lock] = weakref.WeakKeyDictionary()
_GUARD = threading.Lock()


def casadi_turn() -> threading.RLock:
    """The process's lock for the MPC's and the OCP's CasADi work: ``with casadi_turn(): ...`` (re-entrant)."""
    return _TURN


def in_turn(fn: F) -> F:
    """``fn`` called within :func:`casadi_turn`."""

    @functools.wraps(fn)
    def turned(*args: Any, **kwargs: Any) -> Any:
        with casadi_turn():
            return fn(*args, **kwargs)

    return turned  # type: ignore[return-value]


def exclusive(solver: Any) -> threading.Lock:
    """The lock of ``solver`` (a CasADi Function): ``with exclusive(fn): out = fn(...); stats = fn.stats()``."""
    with _GUARD:
        lock = _LOCKS.get(solver)
        if lock is None:
            lock = _LOCKS[solver] = threading.Lock()
        return lock


def _fresh_locks() -> None:
    """A forked child (the first plan's forked move solves) is one thread: no lock its parent's threads held at the
    fork may stop it."""
    global _TURN, _LOCKS, _GUARD
    _TURN, _LOCKS, _GUARD = threading.RLock(), weakref.WeakKeyDictionary(), threading.Lock()


os.register_at_fork(after_in_child=_fresh_locks)
