"""The project's log lines on a command line: every package logs to its module loggers (progress at INFO,
problems at WARNING); a command line or script shows them on stderr with :func:`cli_logging`. Used as a
library, nothing is printed unless the application configures logging."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

PACKAGES = ("wl", "mpc", "agents", "wl_env")  # the project's loggers


class _StderrHandler(logging.StreamHandler):
    """Plain lines (warnings with a ``warning:`` prefix) on whatever ``sys.stderr`` is when a record is
    emitted: tests and callers that swap the stream get neither repeated nor lost lines."""

    def __init__(self) -> None:
        super().__init__()
        self.setFormatter(logging.Formatter("%(message)s"))

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return f"warning: {text}" if record.levelno >= logging.WARNING else text

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


@contextmanager
def cli_logging(level: int = logging.INFO, names: tuple[str, ...] = PACKAGES) -> Iterator[None]:
    """Show the ``names`` loggers' messages from ``level`` up on stderr while the block runs."""
    handler = _StderrHandler()
    loggers = [logging.getLogger(name) for name in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.addHandler(handler)
        lg.setLevel(level)
    try:
        yield
    finally:
        for lg, previous in zip(loggers, levels, strict=True):
            lg.removeHandler(handler)
            lg.setLevel(previous)


def run_script(name: str, main: Callable[[], Any], loggers: tuple[str, ...] | None = None) -> None:
    """A script's entry point: ``main()`` with the script's own logger (``name``) on stderr; a
    ValueError (a bad option, named in its message) or an OSError (a missing or unreadable file, named in its
    message), as ``wl`` takes them, as one line ``name: error: ...`` and exit 2, Ctrl-C as exit 130 (the scripts
    write their outputs atomically at the end: nothing partial is left). ``loggers``: the loggers shown (default:
    the script's own)."""
    from mpc import interrupt  # (a signal module of its own: the flag that CasADi's solves check, as under `wl`)

    with cli_logging(names=loggers or (name,)), interrupt.handling():
        try:
            main()
        except SystemExit:
            raise
        except BaseException as exc:  # (Ctrl-C, or what it became inside a library: a SystemError, a RuntimeError, ...)
            if interrupt.caused_by_interrupt(exc):
                print(f"{name}: interrupted", file=sys.stderr)
                sys.exit(interrupt.exit_code())
            if isinstance(exc, (ValueError, OSError)):
                print(f"{name}: error: {' '.join(str(exc).split())}", file=sys.stderr)
                sys.exit(2)
            raise
