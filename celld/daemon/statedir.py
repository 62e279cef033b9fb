"""The state directory as a whole: its format version, and a backup of what a cell cannot measure again.

``<state_dir>/state-format.json`` names the layout of the directory
(:data:`STATE_FORMAT`). The daemon checks it first thing (after the journal's
lock, before it writes anything else, :func:`open_state`): a directory of a
newer format is refused with what to do, an older one is migrated step by
step (:data:`MIGRATIONS`, each step from format ``n`` to ``n + 1`` and the
marker rewritten after each), one without the marker is the layout from
before the marker (format 1, which needs no change) and gets it.

:func:`write_backup` packs what the cell has learnt into one ``.tar.gz``: the
current calibration, tool calibration, finger gain, verification and the
finger's reference rest, every accepted candidate, the job results and a
consistent copy of the job journal (SQLite's online backup, so a running
daemon need not stop); with ``datasets`` the calibration sessions too. The
recordings stay out: they are evidence, not state, and large. Restore: stop
the daemon, unpack into an empty ``cell.state_dir``, start it.
"""

from __future__ import annotations

import io
import json
import os
import sqlite3
import tarfile
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from celld import __version__, fsutil
from celld.errors import DamagedStateError, StateFormatError
from celld.log import get_logger

log = get_logger(__name__)

# The layout of a state directory this release writes and reads.
STATE_FORMAT = 1
MARKER = "state-format.json"
# From format n to n + 1, in place: none yet (format 1 is the first marked layout).
MIGRATIONS: dict[int, Callable[[Path], None]] = {}
# What a backup holds besides the journal: the sealed current state and the directories of what it came from.
BACKUP_FILES = (MARKER, "calibration.json", "tool.json", "finger.json", "verification.json", "tactile/rest.json")
BACKUP_DIRS = ("calibrations", "tool-calibrations", "results")
# With ``datasets``: the saved calibration sessions (large: the clouds).
DATASET_DIR = "jobs"
_MAX_MARKER_BYTES = 4096


def read_format(state_dir: Path) -> int | None:
    """The format the marker names; None without a marker. Raises DamagedStateError for a marker that is not one."""
    path = state_dir / MARKER
    try:
        with open(path, "rb") as f:
            raw = f.read(_MAX_MARKER_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise DamagedStateError("state format", str(path), f"unreadable: {exc.strerror or exc}") from exc
    if len(raw) > _MAX_MARKER_BYTES:
        raise DamagedStateError("state format", str(path), f"larger than {_MAX_MARKER_BYTES} bytes: not a marker")
    try:
        doc = json.loads(raw)
    except ValueError as exc:
        raise DamagedStateError("state format", str(path), f"not JSON: {exc}") from exc
    value = doc.get("format") if isinstance(doc, dict) else None
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise DamagedStateError("state format", str(path), f'expected {{"format": N}} with N a positive integer, got {raw[:80]!r}')
    return value


def _write_marker(state_dir: Path, fmt: int) -> None:
    fsutil.write_json(state_dir / MARKER, {"format": fmt, "written_by": f"celld {__version__}"})


def open_state(state_dir: Path, fresh: bool, migrations: dict[int, Callable[[Path], None]] | None = None) -> int:
    """Check (and migrate, or mark) ``state_dir`` for this release; return the format it had.

    ``fresh``: the directory held no journal before this daemon (a new cell), so an absent marker means this
    release's layout, not the layout from before the marker.

    Raises
    ------
    StateFormatError
        The directory is of a newer format than this release reads, or no migration leads from its format.
    DamagedStateError
        The marker is unreadable or malformed.
    """
    steps = MIGRATIONS if migrations is None else migrations
    found = read_format(state_dir)
    if found is None:
        if fresh:
            _write_marker(state_dir, STATE_FORMAT)  # a new cell: this release's layout from the start
            return STATE_FORMAT
        found = 1  # the layout from before the marker
        _write_marker(state_dir, found)
    if found > STATE_FORMAT:
        raise StateFormatError(
            f"{state_dir} holds state of format {found}, newer than celld {__version__} reads ({STATE_FORMAT}): "
            f"run the release that wrote it, or start this one on a state directory of its own "
            f"(a backup of the newer one, `celld backup`, keeps it)"
        )
    return _migrate(state_dir, found, steps) if found < STATE_FORMAT else found


def _migrate(state_dir: Path, found: int, steps: dict[int, Callable[[Path], None]]) -> int:
    fmt = found
    while fmt < STATE_FORMAT:
        step = steps.get(fmt)
        if step is None:
            raise StateFormatError(f"{state_dir} holds state of format {fmt}, and celld {__version__} has no migration from it")
        step(state_dir)
        fmt += 1
        _write_marker(state_dir, fmt)  # after each step: an interrupted migration resumes where it stopped
        log.info("state_migrated", state_dir=str(state_dir), to_format=fmt)
    return found


@dataclass(frozen=True)
class Backup:
    """What :func:`write_backup` wrote."""

    path: Path
    files: int
    bytes: int
    journal: bool

    def as_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "files": self.files, "bytes": self.bytes, "journal": self.journal}


def write_backup(state_dir: Path, out: Path, datasets: bool = False) -> Backup:
    """Pack ``state_dir``'s state (module docstring) into the ``.tar.gz`` at ``out``, written whole or not at all.

    Raises
    ------
    StateFormatError
        ``state_dir`` is not a cell's state directory (no journal, no marker).
    """
    journal = state_dir / "journal.db"
    if not (journal.exists() or (state_dir / MARKER).exists()):
        raise StateFormatError(f"{state_dir}: not a cell's state directory (no journal.db, no {MARKER})")
    names = [n for n in BACKUP_FILES if (state_dir / n).is_file()]
    for d in (*BACKUP_DIRS, *((DATASET_DIR,) if datasets else ())):
        root = state_dir / d
        if root.is_dir():
            names += sorted(str(p.relative_to(state_dir)) for p in root.rglob("*") if p.is_file() and not p.name.startswith("."))
    out.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    with fsutil.atomic_open(out) as f, tarfile.open(fileobj=f, mode="w:gz") as tar:
        for name in names:
            try:
                tar.add(state_dir / name, arcname=name, recursive=False)
            except FileNotFoundError:
                continue  # pruned while the backup ran
            count += 1
        has_journal = journal.exists()
        if has_journal:
            _add_bytes(tar, "journal.db", _journal_copy(journal))
            count += 1
    return Backup(out, count, out.stat().st_size, has_journal)


def _journal_copy(journal: Path) -> bytes:
    """A consistent copy of the journal's database (SQLite's online backup: a running daemon's writes wait)."""
    with tempfile.TemporaryDirectory(prefix="celld-backup-") as tmp:
        copy = Path(tmp) / "journal.db"
        src = sqlite3.connect(f"file:{journal}?mode=ro", uri=True)
        try:
            dst = sqlite3.connect(copy)
            try:
                src.backup(dst)
            finally:
                dst.close()
        finally:
            src.close()
        return copy.read_bytes()


def _add_bytes(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = len(data), int(time.time()), 0o600
    tar.addfile(info, io.BytesIO(data))


def default_backup_path(cell: str, directory: str | os.PathLike[str] = ".") -> Path:
    """``celld-backup-<cell>-<UTC time>.tar.gz`` in ``directory``."""
    return Path(directory) / f"celld-backup-{cell}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.tar.gz"
