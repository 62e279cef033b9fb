"""The state directory's storage budget: what a cell prunes, oldest first, to stay under ``cell.storage_budget_mb``.

After every job the daemon measures the whole state directory and, while it
is over the budget, deletes the oldest artefact that may go:

- a job's recording (``recordings/<job>.rrd``), its calibration dataset
  (``jobs/<job>/dataset/``), its other files (``jobs/<job>/``: a weld's
  paths, a tool calibration's poses) and its result (``results/<job>.json``);
- never an artefact of a protected job: the running ones, the current
  calibration's and the current tool calibration's (their datasets are what
  `celld calib solve` can solve again);
- never a result younger than ``cell.result_retention_days``, and never the
  journal, the current state files or a recording being written (``.part``).

Age is the last write (modification time). Each deletion is logged with what
it freed; one that fails is logged and skipped (pruning never fails a job).
What is left over the budget once nothing more may go is said in the
report, and the status shows it. The dataset rules of ``[calibration]``
(:mod:`celld.daemon.retention`) still apply first.

:func:`plan_pruning` is the decision alone (pure); :func:`enforce` measures,
decides and deletes.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from celld.log import get_logger

log = get_logger(__name__)

MIB = 2**20  # the state directory's figures are in MiB (celld.daemon.storage too)
_DAY = 86_400.0  # s
# Artefact kinds, in the words of the log and the status.
RECORDING, DATASET, JOB_FILES, RESULT = "recording", "dataset", "job files", "result"


@dataclass(frozen=True)
class Artefact:
    """One thing the budget may delete."""

    kind: str
    job: str
    path: Path
    bytes: int
    written: float  # s since the epoch, its last write


@dataclass(frozen=True)
class BudgetReport:
    """One enforcement: the budget, what the directory held before and after, what went."""

    budget_bytes: int
    used_before: int
    used_after: int
    pruned: tuple[Artefact, ...] = ()

    @property
    def over(self) -> bool:
        return self.budget_bytes > 0 and self.used_after > self.budget_bytes


def plan_pruning(
    artefacts: Iterable[Artefact],
    used_bytes: int,
    budget_bytes: int,
    protect: Iterable[str | None] = (),
    keep_results_days: float = 0.0,
    now: float | None = None,
) -> list[Artefact]:
    """The artefacts to delete, oldest first, until ``used_bytes`` is within ``budget_bytes`` (0: no budget)."""
    if budget_bytes <= 0 or used_bytes <= budget_bytes:
        return []
    now = time.time() if now is None else now
    protected = {p for p in protect if p}
    out: list[Artefact] = []
    for a in sorted(artefacts, key=lambda a: (a.written, a.job, a.kind)):
        if used_bytes <= budget_bytes:
            break
        if a.job in protected or (a.kind == RESULT and (now - a.written) < keep_results_days * _DAY):
            continue
        out.append(a)
        used_bytes -= a.bytes
    return out


def _tree(path: Path) -> tuple[int, float]:
    """The bytes of every file under ``path`` and the newest write among them (one walk)."""
    total, newest = 0, path.lstat().st_mtime
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                st = os.lstat(os.path.join(root, name))
            except OSError:
                continue  # gone since the listing
            total += st.st_size
            newest = max(newest, st.st_mtime)
    return total, newest


def artefacts(state_dir: Path) -> list[Artefact]:
    """Every artefact of ``state_dir`` the budget may consider (module docstring), with its size and age."""
    out: list[Artefact] = []

    def add(kind: str, job: str, path: Path, tree: bool) -> None:
        try:
            if tree:
                size, written = _tree(path)
            else:
                st = path.lstat()
                size, written = st.st_size, st.st_mtime
        except OSError:
            return
        out.append(Artefact(kind, job, path, size, written))

    for path in _entries(state_dir / "recordings"):
        if path.is_file() and path.suffix == ".rrd":  # not a .rrd.part: being written, or merged at the next start
            add(RECORDING, path.name[: -len(".rrd")], path, tree=False)
    for path in _entries(state_dir / "results"):
        if path.is_file() and path.suffix == ".json":
            add(RESULT, path.stem, path, tree=False)
    for job_dir in _entries(state_dir / "jobs"):
        if not job_dir.is_dir() or job_dir.is_symlink():
            continue
        for part in _entries(job_dir):
            if part.name == "dataset" and part.is_dir() and not part.is_symlink():
                add(DATASET, job_dir.name, part, tree=True)
            elif part.is_file():
                add(JOB_FILES, job_dir.name, part, tree=False)
    return out


def _entries(directory: Path) -> list[Path]:
    try:
        return sorted(directory.iterdir())
    except OSError:
        return []


def enforce(
    state_dir: Path,
    budget_mb: float,
    protect: Iterable[str | None] = (),
    keep_results_days: float = 0.0,
    now: float | None = None,
) -> BudgetReport:
    """Measure ``state_dir``, delete what :func:`plan_pruning` says, and report (blocking: run it off the loop)."""
    budget = int(budget_mb * MIB)
    used = _tree(state_dir)[0]
    if budget <= 0 or used <= budget:
        return BudgetReport(budget, used, used)
    plan = plan_pruning(artefacts(state_dir), used, budget, protect, keep_results_days, now)
    pruned: list[Artefact] = []
    for a in plan:
        try:
            if a.path.is_dir():
                shutil.rmtree(a.path)
            else:
                a.path.unlink()
        except OSError as exc:
            log.error("storage_artefact_not_pruned", kind=a.kind, job=a.job, path=str(a.path), error=str(exc))
            continue
        log.info("storage_artefact_pruned", kind=a.kind, job=a.job, path=str(a.path), mb=round(a.bytes / MIB, 3))
        pruned.append(a)
        _drop_empty_job_dir(a.path, state_dir)
    after = _tree(state_dir)[0]
    report = BudgetReport(budget, used, after, tuple(pruned))
    if report.over:
        log.warning("storage_over_budget", used_mb=round(after / MIB, 1), budget_mb=budget_mb, why="nothing more may be pruned")
    return report


def _drop_empty_job_dir(path: Path, state_dir: Path) -> None:
    parent = path.parent
    if parent.parent == state_dir / "jobs":
        try:
            parent.rmdir()  # only when empty
        except OSError:
            pass
