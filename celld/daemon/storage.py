"""The state directory's health: free space, the disk-space floor, the last storage error, owed writes.

:class:`StorageGuard` is what the job manager asks before it takes or starts a
job, and what it tells when a write fails. Rules:

- Free space is read with ``statvfs`` and cached for :data:`FREE_CACHE_S`
  (status may be asked a thousand times a second).
- Below the floor (``cell.min_free_mb``) new jobs are refused and queued jobs
  wait: the floor is there to stop work *before* the disk is full.
- A failed write (:meth:`StorageGuard.failed`) puts the guard in fault: the
  reason is kept as the last error (it stays visible after recovery, with its
  time), new jobs are refused and the queue is held.
- A damaged store (the journal's database, :attr:`Journal.damage`) is a
  fault no retry clears: it is reported first, with its way out, until an
  operator deals with it and the daemon starts again.
- A write that must still happen (a job's end in the journal, a result file)
  is *owed* (:meth:`StorageGuard.owe`): :meth:`StorageGuard.retry`, called
  periodically while in fault, makes owed writes in order, then writes a small
  probe file; once all succeed and free space is above the floor, the fault
  clears.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from celld import fsutil
from celld.daemon.budget import MIB, BudgetReport
from celld.errors import CelldError, StorageError
from celld.journal import utc_now
from celld.log import get_logger

log = get_logger(__name__)

# How long a free-space reading is reused, s.
FREE_CACHE_S = 0.5
# Bytes in a MiB: the floor and the figures are in MiB.
# The file written to find out whether the state directory takes writes again.
PROBE_NAME = ".storage-probe"


@dataclass(frozen=True)
class StorageFault:
    """One failed write: which store, which file, why, when (UTC wall clock)."""

    what: str
    path: str
    reason: str
    at: str

    def to_message(self) -> dict[str, Any]:
        return {"what": self.what, "path": self.path, "reason": self.reason, "at": self.at}

    def __str__(self) -> str:
        return f"storage: {self.what} {self.path}: {self.reason}" if self.path else f"storage: {self.what}: {self.reason}"


@dataclass
class OwedWrite:
    """A write that failed and is made again by :meth:`StorageGuard.retry`."""

    label: str
    write: Callable[[], Any]
    job: str = ""


class StorageGuard:
    """Free space, the floor, faults and owed writes of one state directory (see the module docstring).

    Parameters
    ----------
    state_dir : Path
    min_free_mb : float
        The floor, MiB; 0 turns it off.
    free_bytes : callable, optional
        Replaces the ``statvfs`` reading (tests).
    clock : callable
        Monotonic seconds, for the cache.
    damage : callable, optional
        Why a store is damaged ("" when none is): the journal's :attr:`~celld.journal.Journal.damage`.
    """

    def __init__(
        self,
        state_dir: Path,
        min_free_mb: float = 0.0,
        *,
        free_bytes: Callable[[], int | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        damage: Callable[[], str] | None = None,
        budget_mb: float = 0.0,
    ) -> None:
        if min_free_mb < 0:
            raise ValueError(f"min_free_mb: expected >= 0, got {min_free_mb}")
        self.state_dir = Path(state_dir)
        self.min_free_mb = float(min_free_mb)
        self._read_free = free_bytes or self._statvfs
        self._clock = clock
        self._damage = damage or (lambda: "")
        self._free: tuple[float, int | None] | None = None
        self.fault: StorageFault | None = None  # active: set on failure, cleared by retry
        self.last_error: StorageFault | None = None  # the most recent, kept after recovery
        self.owed: deque[OwedWrite] = deque()
        self.failures = 0
        # The storage budget (celld.daemon.budget; 0: none), its last enforcement and what it pruned since the start.
        self.budget_mb = float(budget_mb)
        self.budget: BudgetReport | None = None
        self.pruned = 0
        self.pruned_bytes = 0

    def budget_enforced(self, report: BudgetReport) -> None:
        """Keep an enforcement's report for the status."""
        self.budget = report
        self.pruned += len(report.pruned)
        self.pruned_bytes += sum(a.bytes for a in report.pruned)

    def _statvfs(self) -> int | None:
        try:
            return fsutil.free_bytes(self.state_dir)
        except OSError:
            return None

    # -- figures ------------------------------------------------------------------------

    def free(self, fresh: bool = False) -> int | None:
        """Free bytes on the state directory's file system (None if it cannot be read)."""
        now = self._clock()
        if fresh or self._free is None or now - self._free[0] > FREE_CACHE_S:
            self._free = (now, self._read_free())
        return self._free[1]

    def below_floor(self, fresh: bool = False) -> bool:
        free = self.free(fresh)
        return free is not None and free < self.min_free_mb * MIB

    @property
    def ok(self) -> bool:
        """No damage, no fault and free space above the floor."""
        return not self._damage() and self.fault is None and not self.below_floor()

    def problem(self) -> str:
        """Why new work is refused now, or ""."""
        damage = self._damage()
        if damage:
            return f"storage: {damage}"
        if self.fault is not None:
            owed = f"; {len(self.owed)} write(s) owed" if self.owed else ""
            return f"{self.fault}{owed} (retried until it succeeds)"
        if self.below_floor():
            free = self.free()
            return (
                f"only {(free or 0) / MIB:.1f} MB free in {self.state_dir}, under the floor of {self.min_free_mb:g} MB (cell.min_free_mb)"
            )
        return ""

    def to_message(self) -> dict[str, Any]:
        """The ``storage`` object of the status reply and of a health job's result."""
        free = self.free()
        return {
            "ok": self.ok,
            "free_mb": None if free is None else round(free / MIB, 3),
            "floor_mb": self.min_free_mb,
            "fault": f"storage: {self._damage()}" if self._damage() else str(self.fault) if self.fault else "",
            "last_error": self.last_error.to_message() if self.last_error else None,
            "pending_writes": len(self.owed),
            "budget_mb": self.budget_mb,
            "used_mb": None if self.budget is None else round(self.budget.used_after / MIB, 3),
            "over_budget": bool(self.budget is not None and self.budget.over),
            "pruned": self.pruned,
            "pruned_mb": round(self.pruned_bytes / MIB, 3),
        }

    # -- faults ---------------------------------------------------------------------------

    def failed(self, exc: BaseException, what: str = "", path: str = "") -> StorageFault:
        """Record a failed write (a StorageError, or an OSError of store ``what``); returns the fault."""
        err = fsutil.storage_error(what or "state directory", exc, path or None)
        fault = StorageFault(err.what, err.path, err.reason, utc_now())
        self.fault = self.last_error = fault
        self.failures += 1
        self._free = None
        log.error("storage_write_failed", what=fault.what, path=fault.path, reason=fault.reason)
        return fault

    def owe(self, label: str, write: Callable[[], Any], job: str = "") -> None:
        """Queue a write to be made again by :meth:`retry`, after those already owed."""
        self.owed.append(OwedWrite(label, write, job))

    def owes(self, job: str) -> bool:
        return any(w.job == job for w in self.owed)

    def retry(self) -> bool:
        """Make owed writes in order, then probe; clear the fault when all succeed. Returns :attr:`ok`.

        A write that fails again stays first in line and the rest wait; one
        that is no longer possible (a CelldError that is not a StorageError,
        e.g. the job's row is gone) is dropped with a log line.
        """
        while self.owed:
            owed = self.owed[0]
            try:
                owed.write()
            except StorageError as exc:
                self.failed(exc)
                return False
            except OSError as exc:
                self.failed(exc, owed.label)
                return False
            except CelldError as exc:
                log.error("owed_write_dropped", write=owed.label, job=owed.job, error=str(exc))
            self.owed.popleft()
            log.info("owed_write_made", write=owed.label, job=owed.job)
        if self.fault is not None:
            try:
                fsutil.write_text(self.state_dir / PROBE_NAME, utc_now() + "\n")
            except OSError as exc:
                self.failed(exc, "probe")
                return False
            if self.below_floor(fresh=True):
                return False
            log.info("storage_writable_again", free_mb=round((self.free() or 0) / MIB, 1))
            self.fault = None
        return self.ok
