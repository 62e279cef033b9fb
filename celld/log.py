"""Logging set-up: structlog, one line of key=value (or JSON) per event.

Every module gets its logger with ``log = get_logger(__name__)`` and binds
context with ``log.bind(job=...)``, which returns a new logger. Nothing logs
from the 500 Hz loop. An event's name is snake_case (``job_failed``,
tests/test_log.py holds every call to it); what it is about goes in fields,
and a reader of the log reads those (:func:`read_events`), never the text.

The daemon's child processes log as it does: each starts with
:func:`configure` from the parent's :func:`settings` (the motion process
through its spec, the camera and scanner processes through
:func:`run_child`, the simulated robot through its ``--log-json``). With
JSON, an uncaught exception becomes an event whose ``exception`` field holds
the traceback, and the standard library's log records come as JSON too.
"""

from __future__ import annotations

import json as json_mod
import logging
import multiprocessing
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import structlog


@dataclass(frozen=True)
class LogSettings:
    """How a process logs: its level and whether as JSON lines; what a child is given to log as its parent."""

    level: str = "info"
    json: bool = False

    def argv(self) -> list[str]:
        """The options of a ``celld`` program for these settings."""
        return ["--log-level", self.level, *(["--log-json"] if self.json else [])]


_settings = LogSettings()


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
    global _settings
    numeric = logging.getLevelName(level.upper())
    if not isinstance(numeric, int):
        raise ValueError(f"unknown log level {level!r}: expected debug, info, warning or error")
    stamp: list[Any] = [structlog.processors.add_log_level, structlog.processors.TimeStamper(fmt="iso", utc=True)]
    renderer: Any = structlog.processors.JSONRenderer() if json else structlog.dev.ConsoleRenderer(colors=False)
    structlog.configure(
        processors=[structlog.contextvars.merge_contextvars, *stamp, structlog.processors.format_exc_info, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(numeric),
        logger_factory=structlog.PrintLoggerFactory(file=_CurrentStderr()),  # type: ignore[arg-type]
        cache_logger_on_first_use=False,
    )
    # The standard library's records (the libraries' own) in the same form as structlog's.
    handler = logging.StreamHandler(_CurrentStderr())
    handler.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            foreign_pre_chain=[structlog.stdlib.add_logger_name, *stamp],
            processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, structlog.processors.format_exc_info, renderer],
        )
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(numeric)
    if json:
        sys.excepthook = _log_uncaught
        threading.excepthook = _log_uncaught_in_thread
    else:
        sys.excepthook, threading.excepthook = sys.__excepthook__, threading.__excepthook__
    _settings = LogSettings(level, json)


def settings() -> LogSettings:
    """How this process logs (as :func:`configure` last set it): what its children are given."""
    return _settings


def _log_uncaught(kind: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
    if issubclass(kind, KeyboardInterrupt):
        sys.__excepthook__(kind, exc, tb)
        return
    structlog.get_logger(module=__name__).critical("uncaught_exception", exc_info=(kind, exc, tb))


def _log_uncaught_in_thread(args: threading.ExceptHookArgs) -> None:
    if args.exc_value is None or isinstance(args.exc_value, SystemExit):
        return
    name = args.thread.name if args.thread is not None else ""
    structlog.get_logger(module=__name__).critical(
        "uncaught_exception", thread=name, exc_info=(args.exc_type, args.exc_value, args.exc_traceback)
    )


def run_child(log: LogSettings, target: Callable[..., Any], *args: Any) -> None:
    """A child process's entry (a ``multiprocessing`` spawn target): log as ``log`` says, then run
    ``target(*args)``; an exception it lets out is logged (``child_process_failed``, the traceback a field)
    and ends the process with exit code 1, as multiprocessing's own report of it would."""
    configure(log.level, json=log.json)
    try:
        target(*args)
    except Exception:  # whatever ends the child is reported as a field  # noqa: BLE001
        structlog.get_logger(module=__name__).exception("child_process_failed", process=multiprocessing.current_process().name)
        raise SystemExit(1) from None


def read_events(text: str, event: str | None = None) -> Iterator[dict[str, Any]]:
    """The events of a JSON log (``--log-json``), oldest first, ``event``'s only when it is given.

    A line that is not a JSON object (a library's own print, a child's output before its logging is set up)
    is no event and is passed over."""
    for line in text.splitlines():
        if not line.startswith("{"):
            continue
        try:
            record = json_mod.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and (event is None or record.get("event") == event):
            yield record


def get_logger(name: str) -> Any:
    """Return a structlog logger bound to the module ``name``."""
    return structlog.get_logger(module=name)
