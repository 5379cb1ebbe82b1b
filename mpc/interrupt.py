"""Ctrl-C that stops a solve instead of failing one start of it.

CasADi looks for signals while IPOPT iterates. On SIGINT Python's handler raises KeyboardInterrupt
inside CasADi, which catches it and returns as an ordinary failed solve (status
``NonIpopt_Exception_Thrown``); the multi-start then took the interrupt for a start that did not
converge, went on with the next one and cached the result. Here the interrupt is kept in a
process-wide flag: the handler :func:`install` puts in place sets it before raising KeyboardInterrupt,
and :func:`check`, called after every solver call, raises KeyboardInterrupt again when the flag is set
or the solver reports an abort (also without the handler, for library use).

The command line installs the handler (:func:`handling`); so does every worker process of
:mod:`mpc.workers`.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

# IPOPT statuses of a solve that was stopped rather than finished: with no intermediate callback and
# no Python callbacks in these NLPs, only an interrupt produces them.
ABORT_STATUSES = frozenset({"User_Requested_Stop", "NonIpopt_Exception_Thrown"})

_flag = threading.Event()
_repeat = True
_signal = signal.SIGINT  # the signal that set the flag


def _handler(signum: int, frame: Any) -> None:
    global _signal
    first = not _flag.is_set()
    if first:
        _signal = signal.Signals(signum)
    _flag.set()
    if first or _repeat:
        raise KeyboardInterrupt


def exit_code() -> int:
    """The shell's code for the signal that stopped the work: 130 for Ctrl-C, 143 for SIGTERM."""
    return 128 + int(_signal)


def interrupted() -> bool:
    """True once SIGINT (or, under :func:`handling`, SIGTERM) arrived in this process (since the handler was
    installed)."""
    return _flag.is_set()


def caused_by_interrupt(exc: BaseException) -> bool:
    """``exc`` is what an interrupt became (the flag is set, or a KeyboardInterrupt lies in its chain): Ctrl-C that
    landed inside numpy's import became an ImportError, inside CasADi's DM.__array__ a SystemError."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return _flag.is_set()


def check(status: str | None = None) -> None:
    """Raise KeyboardInterrupt if this process was interrupted, or if ``status`` (a solver's return
    status) says the solve was aborted. Call it after every solver call."""
    if _flag.is_set():
        raise KeyboardInterrupt("interrupted")
    if status in ABORT_STATUSES:
        raise KeyboardInterrupt(f"the solver was interrupted (status {status})")


def install(repeat: bool = True) -> Any:
    """Put the flag-setting SIGINT handler in place (main thread only; elsewhere a no-op returning None)
    and clear the flag; returns the previous handler. ``repeat=False`` ignores further SIGINTs once the
    first one is being handled (worker processes, which get Ctrl-C from the terminal and again from
    their parent)."""
    global _repeat, _signal
    if threading.current_thread() is not threading.main_thread():
        return None
    _flag.clear()
    _signal = signal.SIGINT
    _repeat = repeat
    return signal.signal(signal.SIGINT, _handler)


@contextmanager
def handling() -> Iterator[None]:
    """The handler installed for the block, for SIGINT and SIGTERM (a scheduler's or ``timeout``'s stop
    cleans up as Ctrl-C does: it left a temporary folder of ``wl suite solve --check`` behind), the
    previous ones restored after it (the CLI's main, which tests also call in process)."""
    previous = install()
    previous_term = signal.signal(signal.SIGTERM, _handler) if previous is not None else None
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous_term is None else previous_term)  # (None: set from C)
            _flag.clear()


@contextmanager
def guarded() -> Iterator[None]:
    """The SIGINT handler for the block where none of this module's is in place (library use), in the main thread:
    an interrupt inside CasADi is raised as KeyboardInterrupt when the block ends, whatever CasADi made of it (the
    real-time iteration's ``sqpmethod`` raised a RuntimeError, which the solve took for a failed step). Without it, Ctrl-C during
    ``run_closed_loop`` in a script was lost: the cycle ran on, on a step that had stopped half-way, and its result
    was written."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is _handler:
        yield
        return
    previous = install()
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)  # (None: set from C)
        hit = _flag.is_set()
        _flag.clear()
        if hit:  # (in place of what CasADi made of it: a RuntimeError "... KeyboardInterrupt", a failed solve)
            raise KeyboardInterrupt("interrupted")  # noqa: B012


def _defer(signum: int, frame: Any) -> None:
    global _signal
    if _flag.is_set():  # a second one: raised now (a start that hangs must not be deaf to Ctrl-C)
        raise KeyboardInterrupt
    _signal = signal.Signals(signum)
    _flag.set()


@contextmanager
def deferred() -> Iterator[None]:
    """The first SIGINT (or SIGTERM where :func:`handling` raises on it) noted but not raised inside the block, and
    raised as KeyboardInterrupt when it ends; a second one is raised at once. For a call that an exception would
    leave half done, with nothing to clean up after it: Ctrl-C inside ``ray.init`` left the local instance's agents
    running, orphaned, which no ``ray.shutdown()`` could find. In the main thread only (elsewhere no signal
    arrives)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    held = {s: h for s, h in held.items() if h is _handler or h is signal.default_int_handler}
    was_set = _flag.is_set()
    for s in held:
        signal.signal(s, _defer)
    try:
        yield
    finally:
        for s, h in held.items():
            signal.signal(s, h)
        hit = _flag.is_set() and not was_set
        if hit and held.get(signal.SIGINT) is not _handler:  # (library use: Python's default handler keeps no flag)
            _flag.clear()
    if hit:
        raise KeyboardInterrupt("interrupted")
