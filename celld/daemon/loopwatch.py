"""How late the daemon's event loop runs, and why.

A ticker on the loop asks to wake every :data:`TICK` s; how much later than
asked it wakes is the loop's stall. Every stall over :data:`THRESHOLD` is
logged and counted as one of two kinds:

- **busy**: a callback on the loop held it that long, computing (it had the
  CPU for most of its time) or blocked (it did not, and neither did the
  daemon's worker threads: a sleep, a file or a lock on the loop). The stall
  names it: its task and coroutine, or its function;
- **unscheduled**: the loop was ready and did not run: no callback ran long,
  or the long one spent its time waiting for the GIL while the daemon's
  worker threads had the CPU; or the OS ran other processes (the cell's
  real-time motion and camera processes come first by design, SCHED_FIFO
  over the daemon's SCHED_OTHER).

Each callback's time is read where asyncio runs it (``Handle._run``, one
``perf_counter`` and one ``thread_time`` on each side: about a microsecond),
which is how the slow-callback report of asyncio's debug mode works too,
without the rest of debug mode's cost.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from celld.log import get_logger

log = get_logger(__name__)

# The ticker's period, s.
TICK = 0.01
# A wake-up this much later than asked is a stall: logged and counted, s.
THRESHOLD = 0.05


@dataclass(frozen=True)
class Stall:
    """One stall of the loop: how late the ticker woke, of which kind, and what ran (s)."""

    late: float
    kind: str  # "busy" or "unscheduled"
    callback: str  # the longest callback in the gap ("" for none)
    callback_s: float  # its wall time
    callback_cpu_s: float  # the CPU it had
    workers_cpu_s: float  # the CPU the daemon's other threads had in the gap

    def as_dict(self) -> dict[str, Any]:
        return {
            "late_ms": round(self.late * 1e3, 1),
            "kind": self.kind,
            "callback": self.callback,
            "callback_ms": round(self.callback_s * 1e3, 1),
            "callback_cpu_ms": round(self.callback_cpu_s * 1e3, 1),
            "workers_cpu_ms": round(self.workers_cpu_s * 1e3, 1),
        }


def describe(callback: Callable[..., Any]) -> str:
    """A callback's name for a person: the task and its coroutine for a task's step, else the function."""
    owner = getattr(callback, "__self__", None)
    if isinstance(owner, asyncio.Task):
        coro = owner.get_coro()
        where = getattr(coro, "__qualname__", type(coro).__name__)
        return f"task {owner.get_name()} ({where})"
    return getattr(callback, "__qualname__", repr(callback))


def classify(threshold: float, callback_s: float, callback_cpu_s: float, workers_cpu_s: float) -> str:
    """A stall's kind from its longest callback (wall and CPU time) and the CPU the worker threads had, s."""
    if callback_s <= threshold:
        return "unscheduled"
    if callback_cpu_s >= 0.5 * callback_s:
        return "busy"  # it computed on the loop
    waited = callback_s - callback_cpu_s
    return "unscheduled" if workers_cpu_s >= 0.5 * waited else "busy"  # the GIL was the workers', or it blocked


class LoopWatch:
    """Stalls of one event loop (module docstring). :meth:`install` on the loop's thread, then run :meth:`run`."""

    def __init__(self, threshold: float = THRESHOLD, tick: float = TICK) -> None:
        self.threshold = threshold
        self.tick = tick
        self.counts = {"busy": 0, "unscheduled": 0}
        self.worst: dict[str, Stall | None] = {"busy": None, "unscheduled": None}
        self._longest: tuple[float, float, Callable[..., Any] | None] = (0.0, 0.0, None)
        self._installed = False

    # -- the callbacks' time -------------------------------------------------------

    def install(self) -> None:
        """Time every callback the loops of this process run (idempotent)."""
        if self._installed:
            return
        handle = asyncio.events.Handle
        run = handle._run
        watch = self

        def timed_run(h: asyncio.events.Handle) -> None:
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                run(h)
            finally:
                dt = time.perf_counter() - t0
                if dt > watch._longest[0]:
                    watch._longest = (dt, time.thread_time() - c0, getattr(h, "_callback", None))

        handle._run = timed_run  # type: ignore[method-assign,assignment]
        self._installed = True

    # -- the ticker ------------------------------------------------------------------

    async def run(self) -> None:
        """Tick until cancelled; log and count every stall over the threshold."""
        loop = asyncio.get_running_loop()
        loop_cpu, process_cpu = time.thread_time(), time.process_time()
        expected = loop.time() + self.tick
        while True:
            await asyncio.sleep(max(0.0, expected - loop.time()))
            now = loop.time()
            late = now - expected
            loop_now, process_now = time.thread_time(), time.process_time()
            if late > self.threshold:
                self._stall(late, (process_now - process_cpu) - (loop_now - loop_cpu))
            self._longest = (0.0, 0.0, None)
            loop_cpu, process_cpu = loop_now, process_now
            expected = now + self.tick

    def _stall(self, late: float, workers_cpu: float) -> None:
        dt, cpu, callback = self._longest
        kind = classify(self.threshold, dt, cpu, workers_cpu)
        stall = Stall(late, kind, describe(callback) if callback is not None else "", dt, cpu, workers_cpu)
        self.counts[kind] += 1
        worst = self.worst[kind]
        if worst is None or late > worst.late:
            self.worst[kind] = stall
        if kind == "busy":
            log.warning("event loop stall: a callback ran long", **stall.as_dict())
        else:
            log.warning("event loop stall: the loop was not scheduled", **stall.as_dict())

    def report(self) -> dict[str, Any]:
        """The counts and the worst stall of each kind since the start, for the status reply."""
        return {
            "threshold_ms": round(self.threshold * 1e3, 1),
            "busy": self.counts["busy"],
            "unscheduled": self.counts["unscheduled"],
            "worst_busy": None if self.worst["busy"] is None else self.worst["busy"].as_dict(),
            "worst_unscheduled": None if self.worst["unscheduled"] is None else self.worst["unscheduled"].as_dict(),
        }
