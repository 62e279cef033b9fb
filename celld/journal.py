"""The job journal: one SQLite database (WAL) in the state directory, one row per job.

Every job the cell takes is a row, and every change of its state is its own
committed transaction (``synchronous=FULL``: on disk when the call returns),
so after a crash, a ``kill -9`` or a power cut the journal says what the cell
was doing. States and the transitions allowed between them::

    queued ──> running ──> succeeded | failed | cancelled | interrupted
       └─────────────────> failed | cancelled | interrupted

When a journal is opened, jobs that a previous process left ``running`` (or
``queued``: the queue lived in that process) become ``interrupted`` with a
reason; :attr:`Journal.recovered` lists them. One process at a time may hold
a journal (an exclusive lock on ``<file>.lock``); a second one is refused
instead of marking the first one's running job interrupted.

Each row also keeps who submitted the job (``owner``, the bus user; empty on
an open bus) and the client's ``request_id``, unique per owner, so a replayed
submit finds the job it already made (:meth:`Journal.find_request`).

A damaged database (SQLite finds a page it cannot read, or the integrity
check at start fails) is not a write to retry: every call then raises
:class:`~celld.errors.JournalDamagedError` with the reason and the way out
(:data:`WAY_OUT`), and :attr:`Journal.damage` says why. ``keep_damaged``
opens a journal that is damaged already in that state, holding its lock, so
a daemon can serve its status and refuse jobs with the reason instead of
failing to start.

A change that cannot be committed (the disk is full, an I/O error, a
read-only file system) raises :class:`~celld.errors.JournalWriteError`
(a :class:`~celld.errors.StorageError` and a JournalError) naming the
database and SQLite's reason; the transaction is rolled back and the journal
stays usable, so the same change can be made again once there is room.

Times are UTC wall clock, ISO 8601 with milliseconds (``2025-03-01T12:00:00.123Z``).
Job ids are ``<UTC yyyymmdd-HHMMSS>-<6 hex>``: sortable, and one zenoh key chunk.
Calls are thread-safe; each is a few milliseconds of blocking I/O (an fsync),
so the asyncio daemon may call them directly for job transitions (rare) or
through ``asyncio.to_thread``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import secrets
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from celld.errors import JournalDamagedError, JournalError, JournalWriteError

# States, and which states each may move to.
STATES = ("queued", "running", "succeeded", "failed", "cancelled", "interrupted")
TERMINAL = frozenset({"succeeded", "failed", "cancelled", "interrupted"})
_NEXT: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "failed", "cancelled", "interrupted"}),
    "running": frozenset({"succeeded", "failed", "cancelled", "interrupted"}),
}
# Version of the table layout, kept in PRAGMA user_version (2: owner and request_id).
_SCHEMA_VERSION = 2
# How long a statement waits for a lock held by a reader, ms.
_BUSY_TIMEOUT_MS = 5000
# Reasons written when a journal is opened after its process died.
INTERRUPTED_RUNNING = "interrupted: the daemon stopped while the job was running"
_REASON_QUEUED = "interrupted: the daemon stopped before the job started"
# What an operator does about a damaged journal.
WAY_OUT = "stop celld and run `celld journal set-aside` (it keeps the damaged journal beside the new one it starts)"
# SQLite's names for a damaged database file.
_DAMAGE = frozenset({"SQLITE_CORRUPT", "SQLITE_NOTADB"})

_CREATE = f"""
CREATE TABLE IF NOT EXISTS jobs (
    seq     INTEGER PRIMARY KEY AUTOINCREMENT,
    id      TEXT NOT NULL UNIQUE,
    kind    TEXT NOT NULL,
    params  TEXT NOT NULL,
    ref     TEXT NOT NULL DEFAULT '',
    state   TEXT NOT NULL CHECK (state IN ({", ".join(repr(s) for s in STATES)})),
    reason  TEXT NOT NULL DEFAULT '',
    created TEXT NOT NULL,
    started TEXT,
    ended   TEXT,
    result  TEXT,
    owner   TEXT NOT NULL DEFAULT '',
    request_id TEXT
);
CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state);
"""
# Layout 1 -> 2: who submitted the job, and the client's request id.
_MIGRATE_1_2 = """
ALTER TABLE jobs ADD COLUMN owner TEXT NOT NULL DEFAULT '';
ALTER TABLE jobs ADD COLUMN request_id TEXT
"""
# A request id names one job per owner (NULLs are distinct in a UNIQUE index).
_INDEX_REQUESTS = "CREATE UNIQUE INDEX IF NOT EXISTS jobs_by_request ON jobs (owner, request_id)"
_COLUMNS = "id, kind, params, ref, state, reason, created, started, ended, result, owner, request_id"


def utc_now() -> str:
    """The wall clock in the journal's format."""
    return _utc(datetime.now(UTC))


def utc_at(t_ns: int) -> str:
    """The wall-clock time, in the journal's format, of ``t_ns`` on this machine's monotonic clock
    (``time.monotonic_ns``, which every process of the cell stamps its samples with)."""
    ago_ns = time.monotonic_ns() - t_ns
    return _utc(datetime.now(UTC) - timedelta(microseconds=ago_ns / 1e3))


def _utc(t: datetime) -> str:
    return t.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def new_job_id() -> str:
    """A fresh job id: ``<UTC yyyymmdd-HHMMSS>-<6 hex>``."""
    return f"{datetime.now(UTC):%Y%m%d-%H%M%S}-{secrets.token_hex(3)}"


@dataclass(frozen=True)
class JobRecord:
    """One job as the journal keeps it. ``params_json`` is the job message as submitted."""

    id: str
    kind: str
    params_json: str
    ref: str
    state: str
    reason: str
    created: str
    started: str | None
    ended: str | None
    result: str | None
    owner: str = ""
    request_id: str | None = None

    @property
    def params(self) -> dict[str, Any]:
        value: dict[str, Any] = json.loads(self.params_json)
        return value

    @property
    def terminal(self) -> bool:
        return self.state in TERMINAL

    def to_message(self, details: bool = True) -> dict[str, Any]:
        """The record as the bus sends it (the ``job-reply`` record).

        Without ``details`` the parameters, the client's reference and request
        id, the owner and the result's path are left out and ``redacted`` is
        true: what a user who may not see other users' jobs gets.
        """
        message: dict[str, Any] = {
            "id": self.id,
            "kind": self.kind,
            "state": self.state,
            "reason": self.reason,
            "created": self.created,
            "started": self.started,
            "ended": self.ended,
        }
        if not details:
            message["redacted"] = True
            return message
        message.update(ref=self.ref, params=self.params, result=self.result, owner=self.owner, request_id=self.request_id)
        return message


class Journal:
    """The job journal of one cell (see the module docstring).

    Parameters
    ----------
    path : str or Path
        The database file; its directory is created if needed.
    clock : callable
        Wall-clock source, for tests.
    keep_damaged : bool
        Open a damaged journal in its damaged state (:attr:`damage` set, the
        lock held, every call refused) instead of raising.

    Raises
    ------
    JournalDamagedError
        The file is damaged (and ``keep_damaged`` is false).
    JournalError
        The file is not a journal, is newer than this code, or another process holds it.
    """

    def __init__(self, path: str | os.PathLike[str], clock: Callable[[], str] = utc_now, *, keep_damaged: bool = False) -> None:
        self.path = Path(path)
        self._clock = clock
        self._lock = threading.Lock()
        self.damage = ""
        self.recovered: tuple[JobRecord, ...] = ()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock_fd = self._take_lock()
        self._db: sqlite3.Connection | None = None
        try:
            self._db = self._connect()
            self._setup()
            self.recovered = self._recover()
        except JournalDamagedError:
            if not keep_damaged:
                self.close()
                raise
        except sqlite3.DatabaseError as exc:
            self.close()
            if _damaged(exc):
                raise self.mark_damaged(str(exc)) from exc
            raise JournalError(f"{self.path}: not a usable job journal: {exc}") from exc
        except BaseException:
            self.close()
            raise

    def _take_lock(self) -> int:
        lock_path = self.path.with_name(self.path.name + ".lock")
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise JournalError(f"{self.path}: the journal is held by another process (pid {holder})") from exc
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return fd

    def _release_lock(self) -> None:
        if self._lock_fd >= 0:
            os.close(self._lock_fd)  # closing the descriptor drops the flock
            self._lock_fd = -1

    def mark_damaged(self, why: str) -> JournalDamagedError:
        """Refuse every call from now on, saying ``why``; returns the error the calls raise."""
        self.damage = self.damage or why
        return JournalDamagedError(self.damage_report())

    def damage_report(self) -> str:
        """What an operator reads about the damage, with the way out; "" when the journal is intact."""
        return f"the job journal {self.path} is damaged: {self.damage}; {WAY_OUT}" if self.damage else ""

    def set_aside(self) -> Path:
        """Move this journal's files aside and start an empty journal in their place; returns where they went.

        ``journal.db`` (with its ``-wal`` and ``-shm``) becomes
        ``journal-set-aside-<UTC time>.db``, kept for whoever wants to read
        or repair it; the lock is held throughout, so no daemon starts on
        either file meanwhile. For one process alone (the command line).
        """
        if self._lock_fd < 0:
            raise JournalError(f"{self.path}: the journal is closed")
        if self._db is not None:
            self._db.close()
            self._db = None
        aside = self.path.with_name(f"{self.path.stem}-set-aside-{datetime.now(UTC):%Y%m%dT%H%M%SZ}{self.path.suffix}")
        for suffix in ("", "-wal", "-shm"):
            source = Path(f"{self.path}{suffix}")
            if source.exists():
                os.replace(source, Path(f"{aside}{suffix}"))
        self.damage = ""
        self._db = self._connect()
        self._setup()
        self.recovered = ()
        return aside

    def _connect(self) -> sqlite3.Connection:
        return sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=_BUSY_TIMEOUT_MS / 1e3)

    @contextlib.contextmanager
    def _damage_seen(self) -> Iterator[None]:
        """SQLite's word that the file is damaged, inside the block, marks the journal damaged and raises it."""
        try:
            yield
        except sqlite3.DatabaseError as exc:
            if _damaged(exc):
                raise self.mark_damaged(str(exc)) from exc
            raise

    def _open_db(self) -> sqlite3.Connection:
        """The database, for a call made under the thread lock; refused when closed or damaged."""
        if self._lock_fd < 0 or self._db is None:
            raise JournalError(f"{self.path}: the journal is closed")
        if self.damage:
            raise self.mark_damaged(self.damage)
        return self._db

    def _setup(self) -> None:
        db = self._open_db()
        db.execute(f"PRAGMA busy_timeout = {_BUSY_TIMEOUT_MS}")
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise JournalError(f"{self.path}: SQLite refused WAL mode (got {mode})")
        db.execute("PRAGMA synchronous = FULL")
        version = db.execute("PRAGMA user_version").fetchone()[0]
        if version > _SCHEMA_VERSION:
            raise JournalError(f"{self.path}: journal layout {version} is newer than this celld ({_SCHEMA_VERSION})")
        with self._transaction():
            exists = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'jobs'").fetchone()
            script = _MIGRATE_1_2 if exists and version == 1 else ("" if exists else _CREATE)
            for statement in script.strip().split(";"):
                if statement.strip():
                    db.execute(statement)
            db.execute(_INDEX_REQUESTS)
            db.execute(f"PRAGMA user_version = {_SCHEMA_VERSION}")

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """One committed transaction, under the thread lock.

        SQLite's operational errors (disk full, I/O error, read-only) become
        :class:`JournalWriteError`; the transaction is rolled back, if SQLite
        has not done so itself, so the next change starts clean.
        """
        with self._lock:
            db = self._open_db()
            try:
                with self._damage_seen():
                    db.execute("BEGIN IMMEDIATE")
                    try:
                        yield db
                        db.execute("COMMIT")
                    except BaseException:
                        if db.in_transaction:
                            with contextlib.suppress(sqlite3.Error):
                                db.execute("ROLLBACK")
                        raise
            except sqlite3.OperationalError as exc:
                name = getattr(exc, "sqlite_errorname", None)
                raise JournalWriteError("journal", str(self.path), f"{exc}" + (f" ({name})" if name else "")) from exc

    def _recover(self) -> tuple[JobRecord, ...]:
        now = self._clock()
        with self._transaction() as db:
            ids = [r[0] for r in db.execute("SELECT id FROM jobs WHERE state IN ('running', 'queued') ORDER BY seq")]
            db.execute("UPDATE jobs SET state = 'interrupted', reason = ?, ended = ? WHERE state = 'running'", (INTERRUPTED_RUNNING, now))
            db.execute("UPDATE jobs SET state = 'interrupted', reason = ?, ended = ? WHERE state = 'queued'", (_REASON_QUEUED, now))
        return tuple(r for r in (self.get(i) for i in ids) if r is not None)

    def close(self) -> None:
        """Close the database and drop the lock (idempotent)."""
        with self._lock:
            if self._lock_fd < 0:
                return
            if self._db is not None:
                self._db.close()
                self._db = None
            self._release_lock()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- changes ------------------------------------------------------------------------

    def create(
        self,
        kind: str,
        params: Mapping[str, Any],
        ref: str = "",
        start: bool = False,
        *,
        owner: str = "",
        request_id: str | None = None,
    ) -> JobRecord:
        """Record a new job as ``queued``, or as ``running`` with ``start``; returns its record.

        ``start=True`` records a job that runs at once in one transaction (one
        fsync instead of two); the record gets a fresh id either way.
        ``owner`` is the bus user who submitted it; ``request_id`` the
        client's id of the request, unique per owner.

        Raises
        ------
        JournalError
            ``params`` is not JSON-serialisable (NaN, infinities, objects), or
            ``owner`` already has a job with ``request_id``.
        JournalWriteError
            The change could not be committed (disk full, I/O error).
        """
        try:
            params_json = json.dumps(dict(params), allow_nan=False, separators=(",", ":"))
        except (TypeError, ValueError) as exc:
            raise JournalError(f"job parameters are not JSON: {exc}") from exc
        now = self._clock()
        state, started = ("running", now) if start else ("queued", None)
        for _ in range(8):
            job_id = new_job_id()
            try:
                with self._transaction() as db:
                    db.execute(
                        "INSERT INTO jobs (id, kind, params, ref, state, created, started, owner, request_id) "
                        "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        (job_id, kind, params_json, ref, state, now, started, owner, request_id),
                    )
            except sqlite3.IntegrityError as exc:
                if request_id is not None and self.find_request(owner, request_id) is not None:
                    raise JournalError(f"request id {request_id!r} of {owner or 'the open bus'} names a job already") from exc
                continue  # the same id in the same second: draw again
            return self._get_required(job_id)
        raise JournalError("could not draw a unique job id")

    def start(self, job_id: str) -> JobRecord:
        """``queued`` -> ``running``; stamps ``started``."""
        return self._move(job_id, "running", "", None)

    def finish(self, job_id: str, state: str, reason: str = "", result: str | None = None) -> JobRecord:
        """Move a job to a terminal ``state`` with a ``reason`` and an optional result path; stamps ``ended``."""
        if state not in TERMINAL:
            raise JournalError(f"expected a terminal state ({', '.join(sorted(TERMINAL))}), got {state!r}")
        return self._move(job_id, state, reason, result)

    def explain_interruption(self, job_id: str, why: str) -> JobRecord:
        """Say why a job the previous process left running was interrupted (what its children saw end it:
        the daemon hung, or died), after the generic reason :attr:`recovered` jobs get (and before any note)."""
        n = len(INTERRUPTED_RUNNING)
        with self._transaction() as db:
            done = db.execute(
                "UPDATE jobs SET reason = ? || ': ' || ? || substr(reason, ?) WHERE id = ? AND state = 'interrupted' AND substr(reason, 1, ?) = ?",
                (INTERRUPTED_RUNNING, why, n + 1, job_id, n, INTERRUPTED_RUNNING),
            ).rowcount
            if done != 1:
                raise JournalError(f"no job {job_id!r} interrupted while running in the journal")
        return self._get_required(job_id)

    def note(self, job_id: str, text: str) -> JobRecord:
        """Add ``text`` to the reason of a job that ended (what was found after its end, e.g. its recording cut short)."""
        terminal = ", ".join(repr(s) for s in sorted(TERMINAL))
        with self._transaction() as db:
            done = db.execute(
                f"UPDATE jobs SET reason = CASE WHEN reason = '' THEN ? ELSE reason || '; ' || ? END WHERE id = ? AND state IN ({terminal})",
                (text, text, job_id),
            ).rowcount
            if done != 1:
                raise JournalError(f"no ended job {job_id!r} in the journal")
        return self._get_required(job_id)

    def set_result(self, job_id: str, result: str) -> JobRecord:
        """Record the path of a job's result written after the job ended (a write retried once space returned)."""
        with self._transaction() as db:
            if db.execute("UPDATE jobs SET result = ? WHERE id = ?", (result, job_id)).rowcount != 1:
                raise JournalError(f"no job {job_id!r} in the journal")
        return self._get_required(job_id)

    def _move(self, job_id: str, state: str, reason: str, result: str | None) -> JobRecord:
        allowed_from = sorted(s for s, nxt in _NEXT.items() if state in nxt)
        now = self._clock()
        stamp = "started" if state == "running" else "ended"
        marks = ", ".join("?" for _ in allowed_from)
        with self._transaction() as db:
            cur = db.execute(
                f"UPDATE jobs SET state = ?, reason = ?, {stamp} = ?, result = COALESCE(?, result) WHERE id = ? AND state IN ({marks})",
                (state, reason, now, result, job_id, *allowed_from),
            )
            if cur.rowcount != 1:
                row = db.execute("SELECT state FROM jobs WHERE id = ?", (job_id,)).fetchone()
                if row is None:
                    raise JournalError(f"no job {job_id!r} in the journal")
                raise JournalError(f"job {job_id} is {row[0]}; it cannot become {state}")
        return self._get_required(job_id)

    # -- queries --------------------------------------------------------------------

    def _rows(self, sql: str, args: tuple[Any, ...] = ()) -> list[JobRecord]:
        with self._lock, self._damage_seen():
            return [JobRecord(*row) for row in self._open_db().execute(sql, args)]

    def get(self, job_id: str) -> JobRecord | None:
        rows = self._rows(f"SELECT {_COLUMNS} FROM jobs WHERE id = ?", (job_id,))
        return rows[0] if rows else None

    def find_request(self, owner: str, request_id: str) -> JobRecord | None:
        """The job ``owner`` submitted with ``request_id``, if any."""
        rows = self._rows(f"SELECT {_COLUMNS} FROM jobs WHERE owner = ? AND request_id = ?", (owner, request_id))
        return rows[0] if rows else None

    def _get_required(self, job_id: str) -> JobRecord:
        record = self.get(job_id)
        if record is None:
            raise JournalError(f"no job {job_id!r} in the journal")
        return record

    def jobs(self, limit: int = 50, state: str | None = None, kind: str | None = None) -> list[JobRecord]:
        """Jobs, newest first, optionally of one state and one kind."""
        where, args = [], []
        if state is not None:
            where.append("state = ?")
            args.append(state)
        if kind is not None:
            where.append("kind = ?")
            args.append(kind)
        clause = f"WHERE {' AND '.join(where)}" if where else ""
        return self._rows(f"SELECT {_COLUMNS} FROM jobs {clause} ORDER BY seq DESC LIMIT ?", (*args, int(limit)))

    def active(self) -> list[JobRecord]:
        """Queued and running jobs, oldest first."""
        return self._rows(f"SELECT {_COLUMNS} FROM jobs WHERE state IN ('queued', 'running') ORDER BY seq")

    def check(self) -> list[str]:
        """Problems found in the journal; empty when it is intact.

        Runs SQLite's ``integrity_check`` and checks what the journal promises:
        at most one running job, times stamped where the state says so. A
        journal already found damaged reports that damage.
        """
        with self._lock:
            if self._lock_fd < 0 or self._db is None:
                raise JournalError(f"{self.path}: the journal is closed")
            if self.damage:
                return [self.damage]
            db = self._db
            try:
                return self._problems(db)
            except sqlite3.DatabaseError as exc:
                if not _damaged(exc):
                    raise
                return [str(exc)]

    @staticmethod
    def _problems(db: sqlite3.Connection) -> list[str]:
        """SQLite's integrity check and the journal's own promises (see :meth:`check`)."""
        problems = [r[0] for r in db.execute("PRAGMA integrity_check") if r[0] != "ok"]
        running = db.execute("SELECT count(*) FROM jobs WHERE state = 'running'").fetchone()[0]
        if running > 1:
            problems.append(f"{running} jobs are running; at most one may be")
        for job_id, state in db.execute("SELECT id, state FROM jobs WHERE state = 'running' AND started IS NULL"):
            problems.append(f"job {job_id} is {state} but has no start time")
        terminal = ", ".join(repr(s) for s in sorted(TERMINAL))
        for (job_id,) in db.execute(f"SELECT id FROM jobs WHERE state IN ({terminal}) AND ended IS NULL"):
            problems.append(f"job {job_id} ended but has no end time")
        return problems


def _damaged(exc: sqlite3.DatabaseError) -> bool:
    """Whether SQLite's error says the file is damaged (not full, locked or read-only)."""
    return getattr(exc, "sqlite_errorname", "") in _DAMAGE or type(exc) is sqlite3.DatabaseError
