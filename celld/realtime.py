"""Real-time set-up of celld's processes: SCHED_FIFO, CPU pinning, locked memory, timer slack.

The motion loop, the tactile camera process and the simulated controller each
ask for what they need with :class:`RealtimeOptions` and get a
:class:`RealtimeReport` of what the OS granted; a refusal is reported, never
raised (the process then runs best effort and says so once in its log).
Granting needs root, CAP_SYS_NICE or systemd's ``LimitRTPRIO`` (and
``LimitMEMLOCK`` for locked memory): see ``systemd/celld.service``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple

_MCL_CURRENT = 1
_MCL_FUTURE = 2
_PR_SET_TIMERSLACK = 29


@dataclass(frozen=True)
class RealtimeOptions:
    """What a process asks for.

    Attributes
    ----------
    priority : int
        SCHED_FIFO priority, 1..99; 0: stay best effort.
    cpu : int or None
        CPU to pin the calling thread to; negative: counted from the last
        CPU the process may use (-1 the last, -2 the one before; the first
        when there are fewer); None: any CPU.
    lock_memory : bool
        mlockall, so the process never waits on a page fault.
    nice : int
        Niceness when the process runs best effort (negative: ahead of other
        best-effort work; needs CAP_SYS_NICE).
    timer_slack_ns : int
        Timer slack: sleeps end this close to their deadline (the kernel's
        default is 50 us).
    enabled : bool
        False: ask for nothing.
    """

    priority: int = 80
    cpu: int | None = -1
    lock_memory: bool = True
    nice: int = 0
    timer_slack_ns: int = 1
    enabled: bool = True


class RealtimeReport(NamedTuple):
    """What the OS granted."""

    fifo: bool
    cpu: int  # -1 when not pinned
    memory_locked: bool
    refused: str  # what the OS refused, "" when everything asked for was granted


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def make_realtime(opts: RealtimeOptions) -> RealtimeReport:
    """Apply ``opts`` to the calling thread (affinity, policy) and process (memory); report what was granted."""
    if not opts.enabled:
        return RealtimeReport(False, -1, False, "real time disabled by the options")
    refused: list[str] = []
    cpu = -1
    fifo = False
    locked = False
    libc = _libc()
    libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(opts.timer_slack_ns), 0, 0, 0)
    if opts.cpu is not None:
        allowed = sorted(os.sched_getaffinity(0))
        want = allowed[max(opts.cpu, -len(allowed))] if opts.cpu < 0 else opts.cpu
        try:
            os.sched_setaffinity(0, {want})
            cpu = want
        except (OSError, ValueError) as exc:
            refused.append(f"CPU affinity {want}: {getattr(exc, 'strerror', None) or exc}")
    if opts.priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(opts.priority))
            fifo = True
        except OSError as exc:
            refused.append(f"SCHED_FIFO {opts.priority}: {exc.strerror or exc} (needs root, CAP_SYS_NICE or LimitRTPRIO)")
    if not fifo and opts.nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, opts.nice)
        except OSError as exc:
            refused.append(f"nice {opts.nice}: {exc.strerror or exc}")
    if opts.lock_memory:
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
            locked = True
        else:
            refused.append(f"mlockall: {os.strerror(ctypes.get_errno())} (needs LimitMEMLOCK)")
    return RealtimeReport(fifo, cpu, locked, "; ".join(refused))


def thread_ids() -> set[int]:
    """The ids of the calling process's threads (Linux: /proc/self/task)."""
    try:
        return {int(name) for name in os.listdir("/proc/self/task")}
    except OSError:
        return set()


def schedule_threads(tids: Iterable[int], priority: int, nice: int = 0) -> str:
    """Put the threads ``tids`` of this process at SCHED_FIFO ``priority``, or (``priority`` 0) back to best
    effort at ``nice``; what the OS refused, "" for nothing.

    For threads a library starts and does not raise itself (ur-rtde raises its
    receive threads only on a PREEMPT_RT kernel). Their CPU affinity is left
    as it is. A thread that has ended meanwhile is skipped.
    """
    policy = os.SCHED_FIFO if priority > 0 else os.SCHED_OTHER
    asked = f"SCHED_FIFO {priority}" if priority > 0 else f"best effort at nice {nice}"
    refused: list[str] = []
    for tid in sorted(tids):
        try:
            os.sched_setscheduler(tid, policy, os.sched_param(priority))
            if priority == 0:
                os.setpriority(os.PRIO_PROCESS, tid, nice)  # Linux: a thread id sets that thread's niceness
        except ProcessLookupError:
            continue
        except OSError as exc:
            refused.append(f"{asked} for thread {tid}: {exc.strerror or exc}")
    return "; ".join(refused)
