"""Retention of calibration datasets: which saved sessions a cell keeps on disk.

Every calibrate job saves its session in ``<state_dir>/jobs/<job>/dataset/``
(:class:`~celld.calib.dataset.SessionWriter`), so that it can be solved again
offline. :func:`prune_sessions` deletes the old ones by the rules of the
config's ``[calibration]`` section:

- a dataset is kept if it is among the newest ``keep_last`` or younger than
  ``keep_days`` days; 0 turns a rule off, and with both off every dataset is
  kept;
- the datasets of the jobs in ``protect`` are never deleted (the daemon
  passes the current calibration's job, named in ``calibration.json``, and
  the running job);
- a dataset's age is that of its last write: the modification time of its
  ``poses.json`` (rewritten after each capture), else of the directory.

Only the ``dataset`` directory goes; the job's result, recording and
calibration candidate stay. Each deletion is logged with what and why; one
that fails is logged and skipped (pruning never fails a job).
"""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from celld.calib.dataset import POSES_FILE
from celld.errors import InputError
from celld.log import get_logger

log = get_logger(__name__)

# Name of a job's dataset directory under <state_dir>/jobs/<job>/.
DATASET_DIR = "dataset"
_DAY = 86_400.0  # s


@dataclass(frozen=True)
class Pruned:
    """A dataset that was deleted, and why."""

    job: str
    path: Path
    reason: str
    bytes: int


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def _last_write(dataset: Path) -> float:
    poses = dataset / POSES_FILE
    return (poses if poses.is_file() else dataset).stat().st_mtime


def prune_sessions(
    jobs_dir: str | Path,
    keep_last: int,
    keep_days: float,
    protect: Iterable[str | None] = (),
    now: float | None = None,
) -> list[Pruned]:
    """Delete the calibration datasets that the retention rules do not keep; return them.

    Parameters
    ----------
    jobs_dir : path
        ``<state_dir>/jobs``; every ``<job>/dataset`` directory in it is a candidate.
    keep_last : int
        Keep the newest this many datasets (0: no such rule).
    keep_days : float
        Keep every dataset written less than this many days ago (0: no such rule).
    protect : iterable of job ids
        Jobs whose datasets are never deleted (None entries are ignored).
    now : float or None
        Wall-clock time of the decision, s since the epoch (default: now).

    Raises
    ------
    InputError
        A negative or non-finite rule.
    """
    if isinstance(keep_last, bool) or not isinstance(keep_last, int) or keep_last < 0:
        raise InputError(f"keep_last: expected an integer >= 0, got {keep_last!r}")
    if not (math.isfinite(keep_days) and keep_days >= 0):
        raise InputError(f"keep_days: expected a number of days >= 0, got {keep_days!r}")
    jobs_dir = Path(jobs_dir)
    if (keep_last == 0 and keep_days == 0) or not jobs_dir.is_dir():
        return []
    now = time.time() if now is None else now
    protected = {p for p in protect if p is not None}
    datasets = []
    for job_dir in jobs_dir.iterdir():
        d = job_dir / DATASET_DIR
        try:
            if job_dir.is_dir() and d.is_dir() and not d.is_symlink():
                datasets.append((_last_write(d), job_dir.name, d))
        except OSError as exc:  # gone or unreadable since the listing: not a candidate
            log.error("calibration_dataset_not_prunable", path=str(d), error=str(exc))
    datasets.sort(key=lambda x: (x[0], x[1]), reverse=True)  # newest first
    pruned = []
    for rank, (written, job, d) in enumerate(datasets):
        age_days = (now - written) / _DAY
        if job in protected or (keep_last and rank < keep_last) or (keep_days and age_days < keep_days):
            continue
        rules = []
        if keep_last:
            rules.append(f"not among the newest {keep_last}")
        if keep_days:
            rules.append(f"written {age_days:.1f} days ago, over {keep_days:g}")
        reason = " and ".join(rules)
        try:
            size = _size(d)
            shutil.rmtree(d)
        except OSError as exc:
            log.error("calibration_dataset_not_pruned", job=job, path=str(d), error=str(exc))
            continue
        log.info("calibration_dataset_pruned", job=job, path=str(d), reason=reason, mb=round(size / 1e6, 1))
        pruned.append(Pruned(job, d, reason, size))
    return pruned
