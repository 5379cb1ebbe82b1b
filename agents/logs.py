"""Logging of the agents package: its modules log to ``agents.*`` loggers (progress at INFO, problems at
WARNING); a command line shows them on stderr with :func:`cli_logging`. Used as a library, nothing is
printed unless the application configures logging."""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager


class _Format(logging.Formatter):
    """Progress lines as they are, warnings with a ``warning:`` prefix (as the CLI printed them before)."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return f"warning: {text}" if record.levelno >= logging.WARNING else text


@contextmanager
def cli_logging(level: int = logging.INFO) -> Iterator[None]:
    """Show the ``agents`` loggers' messages from ``level`` up on stderr while the block runs.

    The handler is bound to the ``sys.stderr`` of this call and removed afterwards, so that calls in one
    process (tests, scripts) neither repeat lines nor write to a stream that was replaced.
    """
    logger = logging.getLogger("agents")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Format("%(message)s"))
    previous = logger.level
    logger.addHandler(handler)
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(previous)
