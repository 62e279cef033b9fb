"""Storage faults are job faults.

A write that fails (the journal, a result, a dataset, a recording) fails that
job with the reason; the worker and the queue live on; status says what
happened and how much space is left; new jobs are refused with the reason
while the fault lasts (or while free space is under the floor); once space
returns, the writes that were owed are made and the queue runs again.

Two ways to make a disk full: an injected error at each storage call (SQLite
``SQLITE_FULL`` at COMMIT, ``ENOSPC`` from the ``os`` calls of
:mod:`celld.fsutil` and of the recording writer), and, where the machine
allows a mount, a real 2 MB tmpfs as the state directory.
"""

from __future__ import annotations

import asyncio
import errno
import json
import os
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from celld import fsutil
from celld.bus.requests import CalibrateJob, HealthJob, MoveJob, StatusRequest, WeldJob
from celld.calib.dataset import SessionWriter
from celld.config import RecordingConfig
from celld.daemon.jobs import JobContext, JobManager
from celld.errors import JobError
from celld.journal import Journal
from celld.recording import job as recording_job
from celld.recording.job import JobRecording
from tests.conftest import fill_disk

MOVE = MoveJob(space="joint", target=(0.0, -1.57, 1.57, -1.57, -1.57, 0.0))
# How often the manager retries owed writes in these tests, s.
RETRY_S = 0.05


# -- injected faults ------------------------------------------------------------------


def sqlite_full() -> sqlite3.OperationalError:
    exc = sqlite3.OperationalError("database or disk is full")
    exc.sqlite_errorcode = sqlite3.SQLITE_FULL  # type: ignore[attr-defined]
    exc.sqlite_errorname = "SQLITE_FULL"  # type: ignore[attr-defined]
    return exc


class FullJournal:
    """Wraps a journal's SQLite connection: every COMMIT fails with SQLITE_FULL while ``full``."""

    def __init__(self, journal: Journal) -> None:
        self.db = journal._db
        self.full = False
        self.failures = 0
        journal._db = self  # type: ignore[assignment]

    def execute(self, sql: str, *args: Any) -> Any:
        if self.full and sql.strip().upper() == "COMMIT":
            self.failures += 1
            raise sqlite_full()
        return self.db.execute(sql, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.db, name)


class FullOs:
    """Stands in for the ``os`` module of one module: creating or writing a file under a
    matching path fails with ENOSPC while ``full``."""

    def __init__(self, match: Callable[[str], bool] = lambda path: True) -> None:
        self.full = False
        self.match = match
        self.failures = 0
        self._fds: dict[int, str] = {}

    def _fail(self, path: str) -> None:
        self.failures += 1
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), path)

    def open(self, path: Any, flags: int, mode: int = 0o777, **kw: Any) -> int:
        if self.full and self.match(str(path)) and flags & os.O_CREAT:
            self._fail(str(path))
        fd = os.open(path, flags, mode, **kw)
        self._fds[fd] = str(path)
        return fd

    def write(self, fd: int, data: Any) -> int:
        path = self._fds.get(fd, "")
        if self.full and self.match(path):
            self._fail(path)
        return os.write(fd, data)

    def __getattr__(self, name: str) -> Any:
        return getattr(os, name)


# -- the manager under test ---------------------------------------------------------------


class Harness:
    """A job manager whose runners wait on a gate or write what real runners write."""

    def __init__(self, state_dir: Path, *, recording: bool = False, **options: Any) -> None:
        self.state_dir = state_dir
        self.gate = asyncio.Event()
        self.events: list[dict[str, Any]] = []
        self.journal = Journal(state_dir / "journal.db")
        self.result_size = 0

        async def move(ctx: JobContext) -> dict[str, Any]:
            await self.gate.wait()
            return {"done": ctx.job_id}

        async def health(ctx: JobContext) -> dict[str, Any]:
            return {"checks": {"all": "ok"}}

        async def weld(ctx: JobContext) -> dict[str, Any]:
            # A weld's figures and a path: results of a few hundred kB are real.
            path = np.linspace(0.0, 1.0, max(1, self.result_size // 20)).tolist()
            if ctx.recording is not None:
                ctx.recording.log_cloud_base("scan", np.random.default_rng(0).random((20_000, 3)))
            return {"figures": {"n": len(path)}, "path": path}

        async def calibrate(ctx: JobContext) -> dict[str, Any]:
            # The calibrate runner saves its dataset as it captures, through the same writer.
            writer = SessionWriter(ctx.result_dir() / "dataset", flange="iso-50", scanner="phoxi-m")
            writer.set_verification(np.eye(4), np.random.default_rng(0).random((100, 3)))
            return {"calibration": {"job": ctx.job_id, "T_base_cam": np.eye(4).tolist()}}

        def publish(job: str, kind: str, state: str, stage: str, **kw: Any) -> None:
            self.events.append({"job": job, "state": state, "stage": stage, **kw})

        async def stop() -> None:
            pass

        factory = None
        if recording:

            def factory(job_id: str, kind: str) -> JobRecording:
                return JobRecording.for_job(state_dir, job_id, "other", RecordingConfig())

        options.setdefault("storage_retry_s", RETRY_S)
        self.manager = JobManager(
            self.journal,
            state_dir,
            {"move": move, "health": health, "weld": weld, "calibrate": calibrate},
            publish,
            stop,
            cell="test",
            queue_depth=8,
            recording_factory=factory,
            **options,
        )
        self.manager.start()

    async def status(self, job: str | None = None) -> dict[str, Any]:
        reply = dict(await self.manager.on_status(StatusRequest(job=job)))
        return reply["record"] if job else reply

    async def until(self, condition: Callable[[], bool], timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, "condition not met in time"
            await asyncio.sleep(0.01)

    async def until_state(self, job: str, *states: str, timeout: float = 10.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            record = await self.status(job)
            if record["state"] in states:
                return record
            assert time.monotonic() < deadline, f"job {job} is {record['state']}, expected {states}"
            await asyncio.sleep(0.01)

    async def close(self) -> None:
        await self.manager.close()
        self.journal.close()


def run(coro_fn):
    """Run an async test body on a fresh event loop, with a hard timeout."""

    def wrapper(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        asyncio.run(asyncio.wait_for(coro_fn(tmp_path, monkeypatch), 60))

    wrapper.__name__ = coro_fn.__name__
    return wrapper


# -- the journal ------------------------------------------------------------------------------


@run
async def test_a_journal_write_that_fails_at_a_jobs_end_fails_it_and_the_queue_lives_on(tmp_path: Path, monkeypatch) -> None:
    h = Harness(tmp_path)
    db = FullJournal(h.journal)
    first = (await h.manager.on_submit(MOVE))["job"]
    later = [(await h.manager.on_submit(HealthJob()))["job"] for _ in range(4)]
    await h.until_state(first, "running")
    db.full = True  # the disk fills while the weld runs
    h.gate.set()
    await h.until(lambda: db.failures > 0)
    await asyncio.sleep(5 * RETRY_S)  # retries fail too while the disk stays full

    # The job that could not be recorded failed, with the reason; the cell says so.
    record = await h.status(first)
    assert record["state"] == "failed"
    assert "journal" in record["reason"] and "database or disk is full" in record["reason"]
    status = await h.status()
    assert status["state"] == "fault" and "database or disk is full" in status["message"]
    assert status["storage"]["last_error"]["what"] == "journal"
    assert status["storage"]["ok"] is False
    assert status["queued"] == later, "the queue is held, not lost"
    with pytest.raises(JobError) as refused:  # new work is refused with the reason, not an internal error
        await h.manager.on_submit(HealthJob())
    assert refused.value.field == "$" and "storage" in refused.value.reason

    db.full = False  # space freed: the owed write is made, the held jobs run
    for job in later:
        assert (await h.until_state(job, "succeeded", "failed"))["state"] == "succeeded"
    row = h.journal.get(first)
    assert row is not None and row.state == "failed" and "database or disk is full" in row.reason
    for _ in range(250):  # the last job's end is in the journal; the worker lets it go a moment later
        status = await h.status()
        if status["state"] != "running":
            break
        await asyncio.sleep(0.02)
    assert status["state"] == "idle" and status["storage"]["ok"] is True and status["storage"]["pending_writes"] == 0
    assert status["storage"]["last_error"]["what"] == "journal", "the last error stays visible after recovery"
    assert (await h.manager.on_submit(HealthJob()))["state"] in ("running", "queued")
    await h.close()


@run
async def test_a_submit_the_journal_cannot_record_is_refused_with_the_reason(tmp_path: Path, monkeypatch) -> None:
    h = Harness(tmp_path)
    db = FullJournal(h.journal)
    db.full = True
    with pytest.raises(JobError) as refused:
        await h.manager.on_submit(HealthJob())
    assert "storage" in refused.value.reason and "database or disk is full" in refused.value.reason
    assert (await h.status())["storage"]["last_error"]["what"] == "journal"
    db.full = False
    await h.until(lambda: h.manager.storage.ok)
    job = (await h.manager.on_submit(HealthJob()))["job"]
    assert (await h.until_state(job, "succeeded"))["state"] == "succeeded"
    await h.close()


@run
async def test_a_job_whose_start_cannot_be_recorded_waits_and_runs_once_space_returns(tmp_path: Path, monkeypatch) -> None:
    h = Harness(tmp_path)
    first = (await h.manager.on_submit(MOVE))["job"]
    second = (await h.manager.on_submit(HealthJob()))["job"]
    await h.until_state(first, "running")
    db = FullJournal(h.journal)
    db.full = True
    h.gate.set()  # the first ends (its end cannot be written), the second cannot start
    await h.until(lambda: db.failures >= 2)
    assert (await h.status(second))["state"] == "queued"
    db.full = False
    assert (await h.until_state(second, "succeeded"))["state"] == "succeeded"
    await h.close()


# -- results, datasets, recordings --------------------------------------------------------------


@run
async def test_a_result_that_cannot_be_written_fails_the_job_and_is_written_once_space_returns(tmp_path: Path, monkeypatch) -> None:
    h = Harness(tmp_path)
    disk = FullOs(lambda p: "/results/" in p)
    monkeypatch.setattr(fsutil, "os", disk)
    disk.full = True
    job = (await h.manager.on_submit(WeldJob()))["job"]
    later = (await h.manager.on_submit(HealthJob()))["job"]
    record = await h.until_state(job, "failed")
    assert "result" in record["reason"] and "No space left on device" in record["reason"]
    assert "internal error" not in record["reason"]
    status = await h.status()
    assert status["state"] == "fault" and status["storage"]["last_error"]["what"] == "result"
    disk.full = False
    assert (await h.until_state(later, "succeeded"))["state"] == "succeeded"
    await h.until(lambda: (tmp_path / "results" / f"{job}.json").exists())
    assert json.loads((tmp_path / "results" / f"{job}.json").read_text())["figures"] == {"n": 1}
    assert h.journal.get(job).result == str(tmp_path / "results" / f"{job}.json")
    await h.close()


@run
async def test_a_dataset_that_cannot_be_written_fails_the_job_with_its_path(tmp_path: Path, monkeypatch) -> None:
    h = Harness(tmp_path)
    disk = FullOs(lambda p: "/dataset/" in p)
    monkeypatch.setattr(fsutil, "os", disk)
    disk.full = True
    job = (await h.manager.on_submit(CalibrateJob()))["job"]
    record = await h.until_state(job, "failed")
    assert "dataset" in record["reason"] and "No space left on device" in record["reason"]
    assert "internal error" not in record["reason"]
    assert (await h.status())["storage"]["last_error"]["what"] == "job files"
    disk.full = False
    await h.until(lambda: h.manager.storage.ok)
    job = (await h.manager.on_submit(CalibrateJob()))["job"]
    assert (await h.until_state(job, "succeeded"))["state"] == "succeeded"
    await h.close()


@run
async def test_a_recording_that_cannot_be_written_fails_the_job(tmp_path: Path, monkeypatch) -> None:
    h = Harness(tmp_path, recording=True)
    disk = FullOs(lambda p: p.endswith(".rrd.part"))
    monkeypatch.setattr(recording_job, "os", disk, raising=False)
    disk.full = True
    job = (await h.manager.on_submit(WeldJob()))["job"]
    record = await h.until_state(job, "failed", "succeeded", timeout=30)
    assert record["state"] == "failed"
    assert "recording" in record["reason"] and "No space left on device" in record["reason"]
    assert (await h.status())["storage"]["last_error"]["what"] == "recording"
    disk.full = False
    await h.until(lambda: h.manager.storage.ok)
    job = (await h.manager.on_submit(WeldJob()))["job"]
    assert (await h.until_state(job, "succeeded", "failed", timeout=30))["state"] == "succeeded"
    await h.close()


# -- the floor ------------------------------------------------------------------------------------


@run
async def test_the_free_space_floor_refuses_new_jobs_before_the_disk_is_full(tmp_path: Path, monkeypatch) -> None:
    free = {"bytes": 50 * 2**20}
    h = Harness(tmp_path, min_free_mb=100.0, free_bytes=lambda: free["bytes"])
    with pytest.raises(JobError) as refused:
        await h.manager.on_submit(HealthJob())
    assert "50" in refused.value.reason and "100" in refused.value.reason and "cell.min_free_mb" in refused.value.reason
    status = await h.status()
    assert status["storage"]["ok"] is False and status["storage"]["free_mb"] == pytest.approx(50.0)
    assert status["storage"]["floor_mb"] == pytest.approx(100.0)
    assert h.journal.jobs() == []
    free["bytes"] = 200 * 2**20
    await asyncio.sleep(0.6)  # the free-space figure is cached for a fraction of a second
    job = (await h.manager.on_submit(HealthJob()))["job"]
    assert (await h.until_state(job, "succeeded"))["state"] == "succeeded"
    await h.close()


@run
async def test_a_health_job_reports_the_storage(tmp_path: Path, monkeypatch) -> None:
    h = Harness(tmp_path, min_free_mb=10.0)
    job = (await h.manager.on_submit(HealthJob()))["job"]
    await h.until_state(job, "succeeded")
    result = json.loads((tmp_path / "results" / f"{job}.json").read_text())
    assert result["storage"]["ok"] is True and result["storage"]["free_mb"] > 10.0
    await h.close()


# -- a real full disk -------------------------------------------------------------------------------


def test_a_full_disk_fails_the_job_refuses_new_ones_and_recovers(tmp_path: Path, small_disk) -> None:
    state = small_disk(2 * 2**20)

    async def body() -> None:
        h = Harness(state, min_free_mb=0.1)
        h.result_size = 400_000  # a 400 kB result
        filler = fill_disk(state, leave=200_000)
        job = (await h.manager.on_submit(WeldJob()))["job"]
        record = await h.until_state(job, "failed")
        assert "No space left on device" in record["reason"] or "disk is full" in record["reason"]
        status = await h.status()
        assert status["state"] == "fault"
        assert status["storage"]["free_mb"] < 0.25 and status["storage"]["last_error"] is not None
        with pytest.raises(JobError) as refused:
            await h.manager.on_submit(HealthJob())
        assert "storage" in refused.value.reason or "cell.min_free_mb" in refused.value.reason
        os.unlink(filler)
        await h.until(lambda: h.manager.storage.ok, timeout=10)
        job = (await h.manager.on_submit(WeldJob()))["job"]
        assert (await h.until_state(job, "succeeded", "failed"))["state"] == "succeeded"
        await h.close()

    asyncio.run(asyncio.wait_for(body(), 60))


@run
async def test_a_recording_whose_close_raises_a_bug_still_ends_the_job_and_the_queue_lives_on(tmp_path: Path, monkeypatch) -> None:
    """Not a storage fault: a bug in the recording's close (it once joined a feed thread not yet started) fails
    the job with the reason and the next job runs; no job waits forever for its end."""
    h = Harness(tmp_path, recording=True)
    real_close = recording_job.JobRecording.close

    def broken_close(self) -> None:
        real_close(self)
        raise RuntimeError("cannot join thread before it is started")

    monkeypatch.setattr(recording_job.JobRecording, "close", broken_close)
    job = (await h.manager.on_submit(WeldJob()))["job"]
    record = await h.until_state(job, "failed", "succeeded", timeout=30)
    assert record["state"] == "succeeded" and "recording was not closed: internal error: RuntimeError" in record["reason"], record
    monkeypatch.setattr(recording_job.JobRecording, "close", real_close)
    job = (await h.manager.on_submit(WeldJob()))["job"]
    assert (await h.until_state(job, "succeeded", "failed", timeout=30))["state"] == "succeeded"
    await h.close()
