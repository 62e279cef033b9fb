"""How late the daemon's event loop runs, and why.

A ticker on the loop asks to wake every :data:`TICK` s; how much later than
asked it wakes is the loop's stall. Every stall over :data:`THRESHOLD` is
logged and counted as one of two kinds:

- **busy**: a callback on the loop held it that long, computing (it had the
  CPU for most of its time) or blocked in a system call of its own (a sleep,
  a file, a socket: the watcher reads which from ``/proc``). The stall names
  it: its task and coroutine, or its function, and where it was;
- **unscheduled**: the loop was ready and did not run: no callback ran long,
  or the long one waited on another thread (the GIL, held by the daemon's
  worker threads, whose wait is a futex) or for the CPU, which the OS gave
  to other processes (the cell's real-time motion and camera processes come
  first by design, SCHED_FIFO over the daemon's SCHED_OTHER).

Each callback's time is read where asyncio runs it (``Handle._run``, one
``perf_counter`` and one ``thread_time`` on each side: about a microsecond),
which is how the slow-callback report of asyncio's debug mode works too,
without the rest of debug mode's cost. A callback still running after the
threshold is sampled once by a watcher thread: where the loop's thread is in
it (the innermost frame and celld's frames around it) is the stall's
``where``, which a task's name alone would not tell. When the ticker itself
is late past the threshold, the watcher notes where the daemon's other
threads are (``others``): what had the GIL or the CPU while the loop waited.
"""

from __future__ import annotations

import asyncio
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from celld.log import get_logger

log = get_logger(__name__)

# The watch the callbacks report to (the last one installed; a daemon has one).
_ACTIVE: LoopWatch | None = None
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
    where: str = ""  # where the loop's thread was in it when the watcher looked, innermost first
    others: str = ""  # where the daemon's other threads were while the loop waited (an unscheduled stall)

    def as_dict(self) -> dict[str, Any]:
        return {
            "late_ms": round(self.late * 1e3, 1),
            "kind": self.kind,
            "callback": self.callback,
            "callback_ms": round(self.callback_s * 1e3, 1),
            "callback_cpu_ms": round(self.callback_cpu_s * 1e3, 1),
            "workers_cpu_ms": round(self.workers_cpu_s * 1e3, 1),
            "where": self.where,
            "others": self.others,
        }


def describe(callback: Callable[..., Any]) -> str:
    """A callback's name for a person: the task and its coroutine for a task's step, else the function."""
    owner = getattr(callback, "__self__", None)
    if isinstance(owner, asyncio.Task):
        coro = owner.get_coro()
        where = getattr(coro, "__qualname__", type(coro).__name__)
        return f"task {owner.get_name()} ({where})"
    return getattr(callback, "__qualname__", repr(callback))


_PACKAGE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_HERE = os.path.abspath(__file__)
# Frames of celld named in a sample's ``where``.
_FRAMES = 4


def where(frame: Any) -> str:
    """The innermost frame of a stack and celld's frames around it, innermost first: ``file:line function``."""
    parts: list[str] = []
    innermost = True
    while frame is not None and len(parts) < _FRAMES:
        path = frame.f_code.co_filename
        if path == _HERE:  # the watch's own wrapper
            frame = frame.f_back
            continue
        ours = path.startswith(_PACKAGE)
        if innermost or ours:
            name = os.path.relpath(path, os.path.dirname(_PACKAGE)) if ours else os.path.basename(path)
            parts.append(f"{name}:{frame.f_lineno} {frame.f_code.co_name}")
        innermost = False
        frame = frame.f_back
    return " < ".join(parts)


def classify(threshold: float, callback_s: float, callback_cpu_s: float, blocked: bool) -> str:
    """A stall's kind from its longest callback: its wall and CPU time (s), and whether the watcher saw its
    thread blocked in a system call other than a futex (a sleep, a file, a socket).

    A long callback that computed, or that blocked the loop in such a call, is busy. One that neither
    computed nor was seen so waited on another thread (the GIL, whose futex wait looks like a lock's) or
    for the CPU: unscheduled.
    """
    if callback_s <= threshold:
        return "unscheduled"
    return "busy" if callback_cpu_s >= 0.5 * callback_s or blocked else "unscheduled"


# The futex system call by machine: a thread that waits for the GIL (or a lock) waits in it.
_FUTEX = {"x86_64": "202", "aarch64": "98"}.get(os.uname().machine, "")


def syscall(native_id: int) -> str:
    """The system call a thread of this process is in (its number), ``running``, or "" when unreadable."""
    try:
        with open(f"/proc/self/task/{native_id}/syscall") as f:
            return f.read().split(maxsplit=1)[0]
    except (OSError, IndexError):
        return ""


def blocked_in(call: str) -> bool:
    """Whether a thread in system call ``call`` (:func:`syscall`) is blocked in it for itself: not running, not
    waiting on another thread (a futex: the GIL or a lock), and known."""
    return call not in ("", "running", _FUTEX)


def _sample() -> None:
    """Look every tick at the active watch: past its threshold, note once where a long callback's thread is, and
    where the other threads are while the ticker is late."""
    me = threading.get_ident()
    while True:
        watch = _ACTIVE
        time.sleep(TICK if watch is None else watch.tick)
        if watch is None:
            continue
        running = watch._running
        if running is not None and running[0] != watch._sampled[0] and time.perf_counter() - running[0] >= watch.threshold:
            call = syscall(running[2])
            watch._sampled = (running[0], where(sys._current_frames().get(running[1])), call)
        due, loop_thread = watch._due
        if due and due != watch._others[0] and time.monotonic() - due >= watch.threshold:
            names = {t.ident: t.name for t in threading.enumerate()}
            seen = [
                f"{names.get(ident, ident)}: {where(frame)}"
                for ident, frame in sys._current_frames().items()
                if ident not in (me, loop_thread) and _busy(frame)
            ]
            watch._others = (due, "; ".join(seen))


# Where an idle thread of the daemon waits (a worker pool's queue, a sleep, a lock): not what held the loop up.
_IDLE = frozenset({"wait", "_worker", "sleep", "select", "poll", "get", "acquire", "_wait_for_tstate_lock", "run_forever"})


def _busy(frame: Any) -> bool:
    """Whether a thread's innermost frame is doing work (not waiting for work)."""
    return frame is not None and frame.f_code.co_name not in _IDLE


class LoopWatch:
    """Stalls of one event loop (module docstring). :meth:`install` on the loop's thread, then run :meth:`run`."""

    def __init__(self, threshold: float = THRESHOLD, tick: float = TICK) -> None:
        self.threshold = threshold
        self.tick = tick
        self.counts = {"busy": 0, "unscheduled": 0}
        self.worst: dict[str, Stall | None] = {"busy": None, "unscheduled": None}
        self._longest: tuple[float, float, Callable[..., Any] | None, str, str] = (0.0, 0.0, None, "", "")
        # The callback running now: when it started (perf_counter) and on which thread (ident, native id);
        # where a sample found it, and in which system call.
        self._running: tuple[float, int, int] | None = None
        self._sampled: tuple[float, str, str] = (0.0, "", "")
        # When the ticker is due to wake (loop time) and the loop's thread; where the others were when it was late.
        self._due: tuple[float, int] = (0.0, 0)
        self._others: tuple[float, str] = (0.0, "")
        # When the ticker last ran (monotonic s, the loop's clock): the daemon's heartbeat beats while it is recent.
        self.last_tick = time.monotonic()

    # -- the callbacks' time -------------------------------------------------------

    def install(self) -> None:
        """Time every callback the loops of this process run, for this watch (the wrapper goes in once per process)."""
        global _ACTIVE
        _ACTIVE = self
        handle = asyncio.events.Handle
        if getattr(handle._run, "_celld_watched", False):
            return
        run = handle._run

        def timed_run(h: asyncio.events.Handle) -> None:
            watch = _ACTIVE
            if watch is None:
                run(h)
                return
            t0, c0 = time.perf_counter(), time.thread_time()
            watch._running = (t0, threading.get_ident(), threading.get_native_id())
            try:
                run(h)
            finally:
                watch._running = None
                dt = time.perf_counter() - t0
                if dt > watch._longest[0]:
                    _, seen, call = watch._sampled if watch._sampled[0] == t0 else (t0, "", "")
                    watch._longest = (dt, time.thread_time() - c0, getattr(h, "_callback", None), seen, call)

        timed_run._celld_watched = True  # type: ignore[attr-defined]
        handle._run = timed_run  # type: ignore[method-assign,assignment]
        threading.Thread(target=_sample, name="celld-loop-watch", daemon=True).start()

    # -- the ticker ------------------------------------------------------------------

    async def run(self) -> None:
        """Tick until cancelled; log and count every stall over the threshold."""
        loop = asyncio.get_running_loop()
        loop_cpu, process_cpu = time.thread_time(), time.process_time()
        expected = loop.time() + self.tick
        me = threading.get_ident()
        while True:
            self._due = (expected, me)
            await asyncio.sleep(max(0.0, expected - loop.time()))
            now = loop.time()
            self.last_tick = now
            late = now - expected
            loop_now, process_now = time.thread_time(), time.process_time()
            if late > self.threshold:
                at, others = self._others
                self._stall(late, (process_now - process_cpu) - (loop_now - loop_cpu), others if at == expected else "")
            self._longest = (0.0, 0.0, None, "", "")
            loop_cpu, process_cpu = loop_now, process_now
            expected = now + self.tick

    def _stall(self, late: float, workers_cpu: float, others: str) -> None:
        dt, cpu, callback, seen, call = self._longest
        kind = classify(self.threshold, dt, cpu, blocked_in(call))
        stall = Stall(late, kind, describe(callback) if callback is not None else "", dt, cpu, workers_cpu, seen, others)
        self.counts[kind] += 1
        worst = self.worst[kind]
        if worst is None or late > worst.late:
            self.worst[kind] = stall
        log.warning("event_loop_stall", **stall.as_dict())  # kind: busy (a callback ran long) or unscheduled

    def report(self) -> dict[str, Any]:
        """The counts and the worst stall of each kind since the start, for the status reply."""
        return {
            "threshold_ms": round(self.threshold * 1e3, 1),
            "busy": self.counts["busy"],
            "unscheduled": self.counts["unscheduled"],
            "worst_busy": None if self.worst["busy"] is None else self.worst["busy"].as_dict(),
            "worst_unscheduled": None if self.worst["unscheduled"] is None else self.worst["unscheduled"].as_dict(),
        }
