"""A call run in a forked copy of this process, beside the caller: the first plan's second schedule move.

Why a fork and not a worker: the move's solve needs the NLP and solvers this process has built (a spawned worker
builds them again, ~0.2 s per slot layout after its machine's model), and two threads of one process solve at 1.2x,
not 2x (CasADi takes the GIL at every function evaluation; docs/benchmarks.md section 3). A fork shares them
copy-on-write and starts in a few ms. The child runs the call and nothing else: it ignores SIGINT (an interrupted
parent kills it), sends the pickled result through a pipe (its own result: nothing from a user is unpickled) and
leaves with ``os._exit`` (no atexit handlers; the parent's output buffers are flushed before the fork, so the child
writes none of them again); it dies with its parent (``prctl``, as the workers of :mod:`mpc.workers`). A fork the
system refuses (the process limit) is a failed call: the caller solves the move itself. The parent's other threads
are not in the child; one that held a lock the call needs would hang it, so the parent waits ``timeout`` at most,
then kills it and does the work itself (a child that crashes on a heap another thread was changing is a failed call
too). The MPC forks only while none of its own threads runs a solve (:meth:`MPCController.end_episode`).
"""

from __future__ import annotations

import logging
import math
import os
import pickle
import select
import signal
import sys
import time
import warnings
from collections.abc import Callable
from typing import Any

from mpc.workers import kill_with_parent

log = logging.getLogger(__name__)


def available() -> bool:
    """A forked call can run beside the caller here: Linux (fork is the platform's way, and CasADi's libraries are
    fork-safe there) with at least 2 CPUs for this process."""
    return sys.platform.startswith("linux") and hasattr(os, "fork") and len(os.sched_getaffinity(0)) >= 2


class ForkedCall:
    """``fn()`` started in a forked child; :meth:`result` waits for its return value, :meth:`cancel` kills it."""

    def __init__(self, fn: Callable[[], Any]) -> None:
        self._pid: int | None = None
        self._fd: int | None = None
        parent = os.getpid()
        read_fd, write_fd = os.pipe()
        for stream in (sys.stdout, sys.stderr):  # (the child must not write out the parent's buffered output again)
            try:
                stream.flush()
            except (AttributeError, OSError, ValueError):
                pass
        try:
            with warnings.catch_warnings():  # (Python 3.12+ warns of fork in a threaded process: see the module's note)
                warnings.simplefilter("ignore", DeprecationWarning)
                pid = os.fork()
        except OSError as exc:  # (EAGAIN at the process limit, ENOMEM: the call fails, the caller solves it itself)
            os.close(read_fd)
            os.close(write_fd)
            log.warning("no fork for a schedule-move solve (%s): solved here", exc)
            return
        if pid == 0:  # the child
            code = 1
            try:
                os.close(read_fd)
                kill_with_parent()  # (a parent killed with SIGKILL leaves no child solving on)
                if os.getppid() != parent:
                    os._exit(1)
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                data = pickle.dumps(fn(), protocol=pickle.HIGHEST_PROTOCOL)
                view = memoryview(data)
                while view:
                    view = view[os.write(write_fd, view):]
                code = 0
            except BaseException:  # (nothing to report to but the parent, which reads a failure from the empty pipe)
                pass
            finally:
                os._exit(code)
        os.close(write_fd)
        self._pid, self._fd = pid, read_fd

    def result(self, timeout: float) -> Any | None:
        """The call's return value, or None if the child failed, died or did not answer within ``timeout`` s
        (a finite number >= 0; it is killed then), or if its result was taken or the call cancelled before."""
        try:
            if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not 0.0 <= timeout < math.inf:
                raise ValueError(f"timeout must be a finite number of seconds >= 0, got {timeout!r}")
            return None if self._fd is None else self._read(timeout)
        finally:
            self.cancel()

    def _read(self, timeout: float) -> Any | None:
        chunks, deadline = [], time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._fd], [], [], left)[0]:
                log.warning("a forked schedule-move solve gave no answer in %.1f s: killed, solved here", timeout)
                return None
            chunk = os.read(self._fd, 1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
        status = _reap(self._pid)
        self._pid = None
        if not chunks or status not in (0, None):  # (None: reaped elsewhere, SIGCHLD ignored; a whole result counts)
            return None
        try:
            return pickle.loads(b"".join(chunks))
        except (pickle.UnpicklingError, EOFError, ValueError):  # (cut short: a child that died while writing)
            return None

    def cancel(self) -> None:
        """Kill the child if it still runs, and reap it (idempotent)."""
        if self._pid is not None:
            try:
                os.kill(self._pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            _reap(self._pid)
            self._pid = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _reap(pid: int) -> int | None:
    """The child's wait status once it has ended; None where it was reaped elsewhere (SIGCHLD ignored)."""
    try:
        return os.waitpid(pid, 0)[1]
    except ChildProcessError:
        return None
