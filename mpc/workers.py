"""Jobs in spawned worker processes that stop on Ctrl-C within about a second and die with their parent.

:func:`run_in_workers` runs each job ``"module:function", args`` in its own process and returns the
results by name. A worker

- starts with SIGINT ignored and installs :mod:`mpc.interrupt`'s handler before it imports the job's
  module (args are plain data, so nothing heavy is imported before that): Ctrl-C in the terminal, or a
  SIGINT its parent forwards, ends its solve and it reports KeyboardInterrupt;
- dies with its parent: ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` on Linux, and a watchdog thread that exits
  once ``os.getppid()`` is no longer the parent (any POSIX system), so ``kill -9`` of the parent leaves no
  orphan solving on.

When the parent is interrupted, or a job fails, the other workers get SIGINT, then SIGTERM after
``grace`` seconds (0.5: a worker inside a long CasADi call, e.g. building an NLP, sees the signal only
when it returns) and SIGKILL after one more. Their finished work is already on disk (atomically), so a
rerun resumes there; what they were solving is dropped.
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import sys
import threading
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from typing import Any

from mpc import interrupt

WATCHDOG_PERIOD = 0.5  # s between the watchdog's looks at the parent
WORKERS_PER_CPU = 4  # local worker processes at most, per CPU: each builds its own NLPs; past the cores they only queue


def max_local_workers() -> int:
    """The most local worker processes a job may start (WORKERS_PER_CPU per CPU of this machine)."""
    return WORKERS_PER_CPU * (os.cpu_count() or 1)


def check_workers(workers: Any, name: str = "workers") -> int:
    """``workers`` if it is an integer in [1, :func:`max_local_workers`], else ValueError naming ``name`` and the
    range (`wl suite solve --workers 100000000` started 100 CasADi processes on 2 cores, one per piece of work)."""
    from wl_env.params import plain, shown

    most = max_local_workers()
    workers = plain(workers)  # (a numpy integer as the int it holds)
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= most:
        # (shown: 10**5000 was repr()'s "Exceeds the limit (4300 digits)", naming no option)
        raise ValueError(f"{name} must be an integer in [1, {most}] ({WORKERS_PER_CPU} per CPU), got {shown(workers)}")
    return workers


@contextmanager
def ray_session(address: str) -> Iterator[Any]:
    """The ``ray`` module, connected to the cluster at ``address`` (``"local"``: a Ray instance started on this
    machine) for the block, and disconnected after it if this call connected it."""
    try:
        import ray
    except ImportError:
        raise RuntimeError("--ray needs Ray: pip install -e \".[ray]\"") from None
    started = not ray.is_initialized()
    if started:
        check_ray_address(address)
        check_reachable(address)
        # (Ctrl-C inside the start of a local instance left its agents running, orphaned; a start of 3-6 s)
        hold = interrupt.deferred() if address == "local" else nullcontext()
        try:
            with hold:
                ray.init(address=None if address == "local" else address, include_dashboard=False,
                         logging_level=logging.WARNING, log_to_driver=False)
        except KeyboardInterrupt:  # (arrived during the start: raised once it is done, and undone here)
            ray.shutdown()
            raise
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


RAY_ADDRESS_FORMS = "local, auto or [ray://]HOST:PORT with PORT in [1, 65535] (or nothing: a local Ray instance)"


def check_ray_address(address: Any, option: str = "--ray") -> str:
    """``address`` if :func:`is_ray_address`, else ValueError naming ``option``: Ray's own error ("Invalid
    address format") names neither, comes after the work's setup, and ``ray://`` without a port waits a minute."""
    if not is_ray_address(address):
        from wl_env.params import shown

        raise ValueError(f"{option} must be {RAY_ADDRESS_FORMS}, got {shown(address)}")
    return address


def is_ray_address(address: Any) -> bool:
    """``local``, ``auto``, ``HOST:PORT`` or ``ray://HOST:PORT`` (PORT in [1, 65535]); another ``scheme://`` is
    left to Ray."""
    if not isinstance(address, str):
        return False
    scheme, sep, _ = address.partition("://")
    return address in ("local", "auto") or bool(sep and scheme.isidentifier() and scheme != "ray") or _host_port(
        address.removeprefix("ray://"))


def _host_port(text: str) -> bool:
    host, sep, port = text.rpartition(":")
    return bool(sep and host.strip("[]").strip() and port.isascii() and port.isdigit() and 1 <= int(port) <= 65535)


RAY_CONNECT_TIMEOUT = 5.0  # s: Ray itself retries an unreachable head for minutes, deaf to Ctrl-C


def check_reachable(address: str) -> None:
    """ConnectionError naming ``address`` if it is ``host:port`` (or ``ray://host:port``) and nothing answers
    there within RAY_CONNECT_TIMEOUT; other forms (``local``, ``auto``) are left to Ray."""
    import socket

    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=RAY_CONNECT_TIMEOUT).close()
    except OSError as exc:
        raise ConnectionError(f"--ray {address}: no Ray head answers there ({exc.strerror or exc}); start one with "
                              f"`ray start --head`, or give --ray without an address for a local instance") from None


class WorkerTraceback(Exception):
    """The traceback of an exception raised in a worker (set as that exception's cause)."""


def run_in_workers(jobs: dict[str, tuple[str, tuple]], log_level: int = logging.WARNING,
                   grace: float = 0.5) -> dict[str, Any]:
    """``{name: module:function(*args)}`` with each job in a spawned process; a job's exception (and
    KeyboardInterrupt) is raised here once the other workers are stopped."""
    check_jobs(jobs, log_level, grace)
    ctx = multiprocessing.get_context("spawn")  # not fork: the parent may hold threads (torch, BLAS) a fork inherits locked
    procs: dict[str, Any] = {}
    conns: dict[Any, str] = {}
    results: dict[str, Any] = {}
    try:
        # multiprocessing's resource tracker, started now rather than at the first start below: once it has started
        # it unblocks SIGINT, inside _sigint_held (a Ctrl-C then was lost while SIGINT was ignored there, and the first
        # worker started with SIGINT unblocked)
        if os.name == "posix":
            from multiprocessing import resource_tracker

            resource_tracker.ensure_running()
        for name, (target, args) in jobs.items():
            recv, send = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_child, args=(send, os.getpid(), log_level, target, args),
                            name=f"wl-worker-{name}", daemon=True)
            procs[name] = p  # (before its start: a Ctrl-C held meanwhile is raised as the start ends, and stops it too)
            with _sigint_held():
                p.start()
            send.close()  # the worker holds the only write end: its death reads as EOF here
            conns[recv] = name
        interrupt.check()  # (a Ctrl-C that an import or a start swallowed: waiting for the workers would outlast it)
        while conns:
            for conn in multiprocessing.connection.wait(list(conns)):
                name = conns.pop(conn)
                try:
                    kind, value, tb = conn.recv()
                except EOFError:
                    procs[name].join(1.0)
                    raise RuntimeError(f"the worker process for {name} died (exit code {procs[name].exitcode})") from None
                finally:
                    conn.close()
                if kind != "ok":
                    if tb:
                        value.__cause__ = WorkerTraceback(tb)
                    raise value
                results[name] = value
        return results
    finally:
        _stop(list(procs.values()), graceful=len(results) == len(jobs), grace=grace)


MAX_GRACE = 60.0  # s a stopped worker gets before SIGTERM


def check_jobs(jobs: Any, log_level: Any = logging.WARNING, grace: Any = 0.5) -> None:
    """:func:`run_in_workers`' arguments, each refused by name before a worker starts: a log level logging does not
    know killed each worker at its start ("the worker process died", its traceback on stderr), a ``grace`` of inf was
    an OverflowError while the other workers were being stopped (left running), NaN or -1 no grace at all, jobs that
    are no mapping or name no ``module:function`` failed inside the workers."""
    from wl_env.params import is_integer, is_real_number, plain, shown

    if not isinstance(jobs, dict):
        raise ValueError(f"jobs must be a dict {{name: ('module:function', args)}}, got {type(jobs).__name__}")
    for name, job in jobs.items():
        if not (isinstance(job, (tuple, list)) and len(job) == 2 and isinstance(job[0], str) and job[0].count(":") == 1
                and all(job[0].split(":")) and isinstance(job[1], (tuple, list))):
            raise ValueError(f"job {shown(name)} must be ('module:function', args), got {shown(job)}")
    level = plain(log_level)
    if not ((is_integer(level) and level >= 0) or (isinstance(level, str) and isinstance(logging.getLevelName(level), int))):
        raise ValueError(f"log_level must be a logging level (an integer >= 0, e.g. logging.INFO, or its name), "
                         f"got {shown(log_level)}")
    if not (is_real_number(grace) and 0.0 <= grace <= MAX_GRACE):
        raise ValueError(f"grace must lie in [0, {MAX_GRACE:g}] s, got {shown(grace)}")


@contextmanager
def _sigint_held() -> Iterator[None]:
    """SIGINT blocked while a worker is spawned, so it starts with SIGINT blocked (a mask exec keeps) until its
    handler is in place; here a Ctrl-C meanwhile is noted and raised once the start is done
    (:func:`mpc.interrupt.deferred`). It was ignored meanwhile (SIG_IGN): the mask blocks it in this thread only, and
    the kernel gave a Ctrl-C to another thread (numpy's BLAS threads), where the disposition dropped it: the sweep ran
    on, the parent waiting for the workers' whole fronts (1 run in ~150 at 0.6-0.8 s)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    with interrupt.deferred():
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if hasattr(signal, "pthread_sigmask") else None
        try:
            yield
        finally:
            if mask is not None:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _stop(procs: list[Any], graceful: bool, grace: float) -> None:
    """Join workers that are done; interrupt, then terminate and kill those that are not."""
    if graceful:
        for p in procs:
            p.join(10.0)
    alive = [p for p in procs if p.is_alive()]
    for p in alive:
        try:
            os.kill(p.pid, signal.SIGINT)
        except (ProcessLookupError, AttributeError):  # gone, or no os.kill signals (Windows)
            pass
    deadline = time.monotonic() + grace
    for p in alive:
        p.join(max(0.0, deadline - time.monotonic()))
    for p in alive:
        if p.is_alive():
            p.terminate()
            p.join(1.0)
        if p.is_alive():
            p.kill()
            p.join()


# ---------------------------------------------------------------------------------------------- worker side
def _child(conn: Any, parent_pid: int, log_level: int, target: str, args: tuple) -> None:
    interrupt.install(repeat=False)  # before anything heavy is imported
    _die_with_parent(parent_pid)
    logging.basicConfig(level=log_level, format="%(message)s", stream=sys.stderr)
    try:
        if hasattr(signal, "pthread_sigmask"):  # (in the try: a Ctrl-C held since the spawn is raised here, and reported
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # as any; it was a traceback of its own)
        module, _, name = target.partition(":")
        message = ("ok", getattr(importlib.import_module(module), name)(*args), None)
    except BaseException as exc:  # noqa: BLE001 - everything goes back to the parent, KeyboardInterrupt too
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a forwarded Ctrl-C must not cut the report short
        message = ("error", _portable(exc), None if isinstance(exc, KeyboardInterrupt) else traceback.format_exc())
    try:
        conn.send(message)
    except (OSError, pickle.PicklingError, TypeError, AttributeError):  # parent gone, or a result that does not pickle
        if message[0] == "ok":
            conn.send(("error", RuntimeError(f"the result of {target} cannot be sent back"), traceback.format_exc()))
    finally:
        conn.close()
        # Reported: end now. The interpreter's teardown with CasADi loaded takes ~0.2 s, which an
        # interrupted parent would wait for; everything this process wrote is on disk (atomically).
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0 if message[0] == "ok" else 1)


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - any failure to round-trip
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def kill_with_parent() -> None:
    """This process gets SIGKILL when its parent dies (Linux's ``prctl(PR_SET_PDEATHSIG)``; elsewhere nothing)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            PR_SET_PDEATHSIG = 1
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass


def _die_with_parent(parent_pid: int) -> None:
    kill_with_parent()  # (where it cannot be armed, the watchdog below still ends it)
    if os.getppid() != parent_pid:  # the parent died before the death signal was armed
        os._exit(1)
    threading.Thread(target=_watchdog, args=(parent_pid,), name="wl-parent-watchdog", daemon=True).start()


def _watchdog(parent_pid: int) -> None:
    while True:
        time.sleep(WATCHDOG_PERIOD)
        if os.getppid() != parent_pid:  # re-parented: the parent is gone
            os._exit(1)
