"""A scanner served from a process of its own: the capture's work off the daemon's GIL, the cloud back through shared memory.

Some scanners do their work in Python or in libraries that hold the GIL
while they run: the simulated scanner ray casts a whole scene (a
full-resolution PhoXi M capture holds the GIL for up to 0.65 s at a time),
and a driver may decode in Python. In a thread of the daemon that work keeps
its event loop from running. :class:`ScannerProcess` builds the scanner in a
child process instead (``build``, a picklable callable) and asks it for each
capture over a pipe; the child writes the organized cloud into a shared
array the daemon owns, so the cloud is not pickled, and the daemon copies it
out. The child runs at a lower priority (``nice``) than the daemon, below the
cell's real-time processes. It exits when the daemon closes it or dies (its
end of the pipe closes).

It is a :class:`~celld.scanner.base.Scanner` like any other: errors of the
capture come back as the same :class:`~celld.errors.DeviceError` or
:class:`~celld.errors.InputError` with the child's message; a child that dies
is a DeviceError that says so.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import uuid
from collections.abc import Callable
from typing import Any

import numpy as np

from celld.errors import CelldError, DeviceError, InputError
from celld.log import get_logger, run_child, settings
from celld.scanner.base import OrganizedCloud, Scanner
from celld.shm import SharedArray

log = get_logger(__name__)

# How much lower than the daemon the scanner's process runs (nice increment).
NICE = 5
# Longest the child may take to build its scanner, and to capture, s.
START_TIMEOUT = 120.0
CAPTURE_TIMEOUT = 120.0
# Longest a close waits for the child to end before it is killed, s.
CLOSE_TIMEOUT = 5.0
# Errors the child sends back by name, raised again as themselves.
_ERRORS: dict[str, type[CelldError]] = {"DeviceError": DeviceError, "InputError": InputError}


def _serve(build: Callable[[], Scanner], conn: Any, nice: int) -> None:
    """The child: build the scanner, then answer ``capture``, ``health`` and ``close`` until closed or orphaned."""
    if nice:
        os.nice(nice)
    try:
        scanner = build()
        info = scanner.info()
        conn.send(("ready", info))
    except CelldError as exc:
        conn.send(("error", type(exc).__name__, str(exc)))
        return
    shared: SharedArray | None = None
    try:
        while True:
            try:
                request = conn.recv()
            except (EOFError, OSError):
                return  # the daemon is gone
            what = request[0]
            if what == "close":
                return
            if what == "segment":
                shared = SharedArray.attach(request[1], tuple(request[2]), np.float32)
                conn.send(("ok",))
            elif what == "health":
                conn.send(("health", scanner.health()))
            elif what == "capture":
                try:
                    cloud = scanner.capture()
                except CelldError as exc:
                    conn.send(("error", type(exc).__name__, str(exc)))
                    continue
                if shared is None or cloud.points.shape != shared.shape:
                    shape = None if shared is None else shared.shape
                    conn.send(("error", "DeviceError", f"scanner process: a {cloud.points.shape} cloud does not fit the shared {shape}"))
                    continue
                np.copyto(shared.array, cloud.points)
                conn.send(("cloud", cloud.stamp_ns))
    finally:
        scanner.close()
        if shared is not None:
            shared.close()


class ScannerProcess:
    """The scanner ``build`` makes, in a child process (module docstring). Blocks until it is ready.

    Raises
    ------
    DeviceError
        The child could not build the scanner (its reason), or did not answer in time.
    """

    def __init__(self, build: Callable[[], Scanner], name: str = "scanner", nice: int = NICE) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._lock = threading.Lock()
        self._shared: SharedArray | None = None
        self._proc = ctx.Process(target=run_child, args=(settings(), _serve, build, child, nice), name=f"celld-{name}", daemon=True)
        self._proc.start()
        child.close()
        try:
            reply = self._ask(None, START_TIMEOUT, "start")
        except DeviceError:
            self._end()
            raise
        self._info: dict[str, Any] = reply[1]
        shape = (int(self._info["height_px"]), int(self._info["width_px"]), 3)
        self._shared = SharedArray.create(f"celld-{name}-{uuid.uuid4().hex[:8]}", shape, np.float32)
        self._ask(("segment", self._shared.name, shape), START_TIMEOUT, "start")

    def _ask(self, request: tuple[Any, ...] | None, timeout: float, what: str) -> tuple[Any, ...]:
        """Send ``request`` (None: only wait) and return the child's answer; its error raised as such."""
        try:
            if request is not None:
                self._conn.send(request)
            if not self._conn.poll(timeout):
                raise DeviceError(f"scanner process: no answer to {what} within {timeout:g} s")
            reply: tuple[Any, ...] = self._conn.recv()
        except (EOFError, OSError, BrokenPipeError) as exc:
            code = self._proc.exitcode
            raise DeviceError(f"scanner process: it ended ({'exit code ' + str(code) if code is not None else exc}) at {what}") from exc
        if reply[0] == "error":
            raise _ERRORS.get(reply[1], DeviceError)(reply[2])
        return reply

    def capture(self) -> OrganizedCloud:
        with self._lock:
            shared = self._shared
            if shared is None:
                raise DeviceError("scanner process: capture after close")
            reply = self._ask(("capture",), CAPTURE_TIMEOUT, "capture")
            return OrganizedCloud(shared.array.copy(), int(reply[1]))

    def info(self) -> dict[str, Any]:
        return dict(self._info)

    def health(self) -> dict[str, Any]:
        with self._lock:
            if self._shared is None:
                return {"ok": False, "captures": 0, "failures": 0, "last_capture_ns": 0, "last_error": "closed"}
            return dict(self._ask(("health",), CAPTURE_TIMEOUT, "health")[1])

    def close(self) -> None:
        with self._lock:
            if self._shared is None:
                return
            try:
                self._conn.send(("close",))
            except (OSError, BrokenPipeError):
                pass
            self._end()

    def _end(self) -> None:
        self._proc.join(CLOSE_TIMEOUT)
        if self._proc.is_alive():
            log.warning("scanner_process_killed", pid=self._proc.pid)
            self._proc.kill()
            self._proc.join(CLOSE_TIMEOUT)
        self._conn.close()
        if self._shared is not None:
            self._shared.close()
            self._shared.unlink()
            self._shared = None
