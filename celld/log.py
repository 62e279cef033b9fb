"""Logging set-up: structlog, one line of key=value (or JSON) per event.

Every module gets its logger with ``log = get_logger(__name__)`` and binds
context with ``log.bind(job=...)``, which returns a new logger. Nothing logs
from the 500 Hz loop.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

import structlog

_configured = False


class _CurrentStderr:
    """Writes to whatever ``sys.stderr`` is at the time of the write.

    A logger bound to the stderr object of its configuration time breaks when
    that object is replaced and closed (a test runner's capture, a daemon that
    redirects its output).
    """

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


def configure(level: str = "info", json: bool = False) -> None:
    """Configure structlog and the standard library root logger once.

    Parameters
    ----------
    level : str
        ``debug``, ``info``, ``warning`` or ``error``.
    json : bool
        One JSON object per line (for journald and log shippers) instead of
        human-readable key=value lines.
    """
    global _configured
    numeric = logging.getLevelName(level.upper())
    if not isinstance(numeric, int):
        raise ValueError(f"unknown log level {level!r}: expected debug, info, warning or error")
    logging.basicConfig(stream=sys.stderr, level=numeric, format="%(message)s")
    renderer: Any = structlog.processors.JSONRenderer() if json else structlog.dev.ConsoleRenderer(colors=False)
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            structlog.processors.format_exc_info,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(numeric),
        logger_factory=structlog.PrintLoggerFactory(file=_CurrentStderr()),  # type: ignore[arg-type]
        cache_logger_on_first_use=False,
    )
    _configured = True


def get_logger(name: str) -> Any:
    """Return a structlog logger bound to the module ``name``."""
    return structlog.get_logger(module=name)
