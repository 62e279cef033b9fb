"""Supervision both ways between the daemon and its child processes.

Down: the motion process (:mod:`celld.motion.supervisor`) and the tactile
camera process (:mod:`celld.daemon.devices`) are restarted when they die, each
after the delay :class:`Backoff` gives for its run of failures: quickly at
first, then less and less often, and from the start again once a process has
run long enough to count as stable.

Up: a child must never run on without its daemon. The daemon beats a
:class:`Heartbeat` in shared memory; each child watches it and its parent
with a :class:`ParentWatch` and, when the daemon is gone or hangs, stops what
it drives (the motion loop: a jerk-limited stop with the arc off) and exits.
:class:`ChildRecords` lets a daemon that was killed find the children and
shared-memory segments of its predecessor at the next start and clean them up.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import json
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from celld import fsutil
from celld.journal import utc_now
from celld.log import get_logger
from celld.shm import SeqlockSlot, unlink_segment

log = get_logger(__name__)


@dataclass(frozen=True)
class Backoff:
    """Delays between restarts, s: each failure in a row takes the next, up to the last."""

    delays: tuple[float, ...] = (0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
    # A process that ran this long (s) resets the sequence.
    stable_after: float = 10.0

    def delay(self, failures: int) -> float:
        """The wait before the restart that follows ``failures`` failures in a row (the first restart: 1)."""
        return self.delays[min(max(failures - 1, 0), len(self.delays) - 1)]

    def failures_after(self, failures: int, ran_for: float) -> int:
        """The count of failures in a row after a process that ran ``ran_for`` s ended."""
        return 0 if ran_for >= self.stable_after else failures + 1


# -- the other way round: a child watching its parent ---------------------------------

# The daemon's heartbeat: when it last beat (time.monotonic_ns) and its pid.
HEARTBEAT_DTYPE = np.dtype([("t_ns", np.int64), ("pid", np.int64)])
# PR_SET_PDEATHSIG of prctl(2): the signal a child gets when its parent ends.
_PR_SET_PDEATHSIG = 1
# PF_EXITING of the kernel's task flags (include/linux/sched.h): set as a thread starts to exit.
_PF_EXITING = 0x4
# SIGKILL in the pending-signals bitmap of /proc/<pid>/stat.
_SIGKILL_BIT = 1 << (signal.SIGKILL - 1)


def exiting(stat: bytes, stopped: bool = False) -> str:
    """Why the process of a ``/proc/<pid>/stat`` line is on its way out, or "" (proc(5)); with ``stopped``,
    also why it cannot run: stopped by a signal (SIGSTOP, SIGTSTP) or a debugger (state ``T`` or ``t``).

    A process killed with SIGKILL has the signal pending in its main thread
    at once, then the kernel's PF_EXITING flag while it frees its memory and
    closes its files, then it is a zombie. Only then does the kernel
    re-parent its children and send them the parent-death signal: for a
    large daemon that can take a tenth of a second or more, where a stop is
    due at once. The fields read: 3 (state), 9 (flags), 31 (pending
    signals). Raises ValueError on a line that is not one.
    """
    # The command name (field 2) may hold spaces and parentheses: split after its closing one.
    fields = stat[stat.rindex(b")") + 2 :].split()
    state, flags, pending = fields[0], int(fields[6]), int(fields[28])
    if state in (b"Z", b"X"):
        return "the daemon has exited"
    if flags & _PF_EXITING:
        return "the daemon is exiting"
    if pending & _SIGKILL_BIT:
        return "the daemon is being killed (SIGKILL)"
    if stopped and state == b"T":
        return "the daemon is stopped (SIGSTOP or SIGTSTP)"
    if stopped and state == b"t":
        return "the daemon is stopped by a debugger"
    return ""


class Heartbeat:
    """The daemon's heartbeat in shared memory, for its children to watch (:class:`ParentWatch`).

    The daemon calls :meth:`beat` from its event loop every few tens of
    milliseconds; a child that sees it older than its timeout takes the
    daemon for hung.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._slot = SeqlockSlot.create(name, HEARTBEAT_DTYPE)
        self._rec = np.zeros(1, HEARTBEAT_DTYPE)
        self._rec["pid"] = os.getpid()
        self.beat()

    def beat(self) -> None:
        self._rec["t_ns"] = time.monotonic_ns()
        self._slot.write(self._rec)

    def close(self) -> None:
        self._slot.close()
        self._slot.unlink()


class BeatThread:
    """Beats a :class:`Heartbeat` every ``period`` s from a thread of its own, while ``alive()`` holds.

    A thread rather than the event loop: the loop may wait its turn on a
    loaded PC for a few hundred milliseconds, which is no hang, while a
    stopped or frozen daemon stops every thread at once. ``alive`` says
    whether the event loop still runs (its loop watch ticked within a
    bound), so a stuck loop stops the beat too, only later. The thread asks
    for SCHED_FIFO ``priority`` (below the camera's and the motion loop's)
    and runs at normal priority where that is refused.
    """

    def __init__(self, heartbeat: Heartbeat, alive: Callable[[], bool], period: float, priority: int = 30) -> None:
        self.heartbeat = heartbeat
        self.alive = alive
        self.period = period
        self.priority = priority
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="celld-heartbeat", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))  # this thread only
        while not self._stop.wait(self.period):
            if self.alive():
                self.heartbeat.beat()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)


# A child's exit note is <role> plus this, beside the daemon's records of its children.
EXIT_NOTE_SUFFIX = ".ended.json"


def write_exit_note(path: str | os.PathLike[str], role: str, reason: str) -> None:
    """A child's note of why it took its daemon for gone (and so stopped what it drove), for the next daemon;
    stamped in the journal's time, so it can be matched with the job that was running."""
    with contextlib.suppress(OSError):
        fsutil.write_json(Path(path), {"role": role, "pid": os.getpid(), "reason": reason, "at": utc_now()})


def exit_notes(run_dir: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The notes the previous daemon's children left (:func:`write_exit_note`), oldest first; each is removed."""
    notes: list[dict[str, Any]] = []
    for path in sorted(Path(run_dir).glob("*" + EXIT_NOTE_SUFFIX)):
        try:
            doc = json.loads(path.read_text())
            notes.append({"role": str(doc["role"]), "reason": str(doc["reason"]), "at": str(doc["at"])})
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("child_exit_note_unreadable", path=str(path), error=str(exc))
        path.unlink(missing_ok=True)
    return sorted(notes, key=lambda n: n["at"])


class ParentWatch:
    """A child process's view of the daemon that started it: is it still there?

    The daemon is gone when

    - it is being killed or exits: its ``/proc/<pid>/stat`` says so
      (:func:`exiting`), long before its children are re-parented;
    - this process was re-parented (the daemon died: ``getppid()`` changed);
    - a signal said so: the parent-death signal (``prctl(PR_SET_PDEATHSIG)``,
      delivered when the daemon's thread that started this process ends),
      SIGTERM or SIGHUP (systemd stopping the unit's control group);
    - its heartbeat (:class:`Heartbeat`) is older than ``timeout_ns``: the
      daemon hangs.

    :meth:`check` is cheap (three system calls and a seqlock read) and
    never raises; a real-time loop may call it every few cycles. The signal
    handlers only set a flag. Build it in the child, in its main thread,
    while the daemon is there (its ``/proc`` entry is opened then, so a
    recycled pid cannot stand in for it).
    """

    def __init__(self, parent_pid: int, heartbeat: str = "", timeout_ns: int = 3_000_000_000, signals: bool = True) -> None:
        self.parent_pid = parent_pid
        self.timeout_ns = timeout_ns
        self._slot = SeqlockSlot.attach(heartbeat, HEARTBEAT_DTYPE) if heartbeat else None
        self._rec = np.zeros(1, HEARTBEAT_DTYPE)
        self._signalled = ""
        try:
            self._stat: int | None = os.open(f"/proc/{parent_pid}/stat", os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            self._stat = None  # no such process (or no /proc): getppid() below says it is gone
        if signals:
            for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1):
                signal.signal(sig, self._on_signal)
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGUSR1), 0, 0, 0)

    def _on_signal(self, signum: int, frame: Any) -> None:
        self._signalled = "the daemon ended" if signum == signal.SIGUSR1 else f"{signal.Signals(signum).name} received"

    def check(self, now_ns: int | None = None, timeout_ns: int | None = None) -> str:
        """Why the daemon counts as gone, or "" while it is there; ``timeout_ns`` bounds the heartbeat's
        age instead of the watch's own (a loop that moves the robot asks for a shorter one)."""
        if self._signalled:
            return self._signalled
        if self._stat is not None:
            try:
                # A caller that moves the robot (it asks for a shorter timeout) takes a stopped daemon for hung
                # at once: it can cancel nothing, and no heartbeat can say so sooner.
                why = exiting(os.pread(self._stat, 1024, 0), stopped=timeout_ns is not None)
            except (OSError, ValueError, IndexError):  # reaped: ESRCH; getppid() below says so
                why = ""
            if why:
                return why
        if os.getppid() != self.parent_pid:
            return f"the daemon (pid {self.parent_pid}) is gone"
        if self._slot is not None and self._slot.read_into(self._rec):
            age = (time.monotonic_ns() if now_ns is None else now_ns) - int(self._rec["t_ns"][0])
            if age > (self.timeout_ns if timeout_ns is None else timeout_ns):
                return f"the daemon's heartbeat is {age / 1e6:.0f} ms old (it hangs)"
        return ""

    def close(self) -> None:
        if self._slot is not None:
            self._slot.close()
            self._slot = None
        if self._stat is not None:
            os.close(self._stat)
            self._stat = None


# -- the children of a daemon that was killed ----------------------------------------

# How long a leftover child gets to stop its robot and exit after SIGTERM, s.
_REAP_GRACE = 3.0


def _start_ticks(pid: int) -> int | None:
    """The process's start time (clock ticks since boot, /proc/<pid>/stat field 22), None if it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # The command name (field 2) may hold spaces and parentheses: split after its closing one.
    return int(stat[stat.rindex(")") + 2 :].split()[19])


class ChildRecords:
    """The daemon's record of its children and their shared memory, one JSON file each in ``run_dir``.

    The daemon records a child when it starts it and forgets it when it ends.
    A daemon that was killed leaves its records behind; the next one calls
    :meth:`reap` before it starts its own children: each recorded process
    that still runs (the same pid and start time, so a reused pid is never
    hit) gets SIGTERM, on which it stops what it drives and exits, then
    SIGKILL if it has not gone within a few seconds; its recorded segments
    are unlinked.
    """

    def __init__(self, run_dir: str | os.PathLike[str]) -> None:
        self.dir = Path(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)

    def add(self, role: str, pid: int, segments: list[str] | tuple[str, ...] = ()) -> None:
        """Record child ``role`` (``motion``, ``tactile``) as process ``pid`` owning ``segments``."""
        doc = {"role": role, "pid": pid, "start_ticks": _start_ticks(pid), "daemon": os.getpid(), "segments": list(segments)}
        fsutil.write_json(self.dir / f"{role}.json", doc)

    def remove(self, role: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            (self.dir / f"{role}.json").unlink()

    def reap(self, grace: float = _REAP_GRACE) -> list[str]:
        """Stop the recorded children of a previous daemon and unlink their segments; what was done, one line each."""
        done: list[str] = []
        for path in sorted(self.dir.glob("*.json")):
            if path.name.endswith(EXIT_NOTE_SUFFIX):
                continue  # a child's exit note (write_exit_note), read after the reap
            try:
                doc = json.loads(path.read_text())
                pid, ticks = int(doc["pid"]), doc.get("start_ticks")
                segments = [str(s) for s in doc.get("segments", [])]
            except (OSError, ValueError, KeyError, TypeError) as exc:
                done.append(f"{path.name}: unreadable record ({exc}), removed")
                path.unlink(missing_ok=True)
                continue
            if pid != os.getpid() and ticks is not None and _start_ticks(pid) == ticks:
                done.append(self._stop(path.stem, pid, grace))
            for name in segments:
                if unlink_segment(name):
                    done.append(f"{path.stem}: removed shared memory {name}")
            path.unlink(missing_ok=True)
        for line in done:
            log.warning("leftover_of_a_previous_daemon", what=line)
        return done

    @staticmethod
    def _stop(role: str, pid: int, grace: float) -> str:
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            return f"{role} (pid {pid}) had already ended"
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline:
            if exited(pid):
                return f"{role} (pid {pid}) stopped on SIGTERM"
            time.sleep(0.02)
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
        return f"{role} (pid {pid}) did not stop within {grace:g} s: killed"


def exited(pid: int) -> bool:
    """Process ``pid`` has exited: reaped, or a zombie its parent has not reaped yet."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat[stat.rindex(")") + 2] == "Z"
