"""The job manager: one job at a time, a bounded queue, cancel stops the robot first."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from celld.bus.schema import CancelRequest, HealthJob, ListRequest, MoveJob, StatusRequest, AcceptRequest
from celld.daemon.jobs import JobContext, JobManager
from celld.errors import JobError, MotionError
from celld.journal import Journal


class Harness:
    def __init__(self, tmp_path: Path, queue_depth: int = 2) -> None:
        self.events: list[dict[str, Any]] = []
        self.stops = 0
        self.gate = asyncio.Event()
        self.journal = Journal(tmp_path / "journal.db")

        async def slow(ctx: JobContext) -> dict[str, Any]:
            ctx.progress("moving", 0.5, "half way")
            await self.gate.wait()
            return {"done": ctx.job_id}

        async def failing(ctx: JobContext) -> dict[str, Any]:
            raise MotionError("link dropped: test")

        async def stop() -> None:
            self.stops += 1

        def publish(job: str, kind: str, state: str, stage: str, **kw: Any) -> None:
            self.events.append({"job": job, "state": state, "stage": stage, **kw})

        self.manager = JobManager(
            self.journal, tmp_path, {"move": slow, "health": failing}, publish, stop,
            cell="test", queue_depth=queue_depth,
        )


def run(coro_fn):
    """Run an async test body on a fresh event loop."""

    def wrapper(tmp_path: Path) -> None:
        asyncio.run(asyncio.wait_for(coro_fn(tmp_path), 30))

    wrapper.__name__ = coro_fn.__name__
    return wrapper


MOVE = MoveJob(space="joint", target=(0.0, -1.57, 1.57, -1.57, -1.57, 0.0))


@run
async def test_one_job_runs_others_queue_and_the_full_queue_refuses(tmp_path: Path) -> None:
    h = Harness(tmp_path, queue_depth=1)
    h.manager.start()
    first = await h.manager.on_submit(MOVE)
    second = await h.manager.on_submit(MOVE)
    assert (first["state"], first["position"]) == ("running", 0)
    assert (second["state"], second["position"]) == ("queued", 1)
    with pytest.raises(JobError, match="queue is full"):
        await h.manager.on_submit(MOVE)
    await asyncio.sleep(0.05)
    status = await h.manager.on_status(StatusRequest())
    assert status["running"] == first["job"] and status["queued"] == [second["job"]]
    h.gate.set()
    for job in (first["job"], second["job"]):
        record = await h.manager.wait(job, timeout=5)
        assert record is not None and record.state == "succeeded"
        result = json.loads(Path(record.result).read_text())
        assert result == {"done": job}
    await h.manager.close()


@run
async def test_cancel_running_stops_the_robot_and_ends_cancelled(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.manager.start()
    job = (await h.manager.on_submit(MOVE))["job"]
    await asyncio.sleep(0.05)
    reply = await h.manager.on_cancel(CancelRequest(job=job, reason="operator"))
    assert reply == {"job": job, "state": "cancelled"}
    assert h.stops == 1
    assert h.journal.get(job).state == "cancelled"
    with pytest.raises(JobError, match="already ended"):
        await h.manager.on_cancel(CancelRequest(job=job))
    await h.manager.close()


@run
async def test_cancel_queued_job_never_runs_it(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.manager.start()
    first = (await h.manager.on_submit(MOVE))["job"]
    second = (await h.manager.on_submit(MOVE))["job"]
    await h.manager.on_cancel(CancelRequest(job=second))
    h.gate.set()
    await h.manager.wait(first, timeout=5)
    assert h.journal.get(second).state == "cancelled" and h.journal.get(second).started is None
    assert h.stops == 0
    await h.manager.close()


@run
async def test_a_failing_job_records_its_reason_and_stops_the_robot(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.manager.start()
    job = (await h.manager.on_submit(HealthJob()))["job"]
    record = await h.manager.wait(job, timeout=5)
    assert record.state == "failed" and "link dropped" in record.reason
    assert h.stops == 1
    assert h.events[-1]["state"] == "failed"
    listed = await h.manager.on_list(ListRequest(limit=10))
    assert listed["jobs"][0]["id"] == job
    await h.manager.close()


@run
async def test_unknown_jobs_and_bad_accepts_are_refused(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    with pytest.raises(JobError, match="no such job"):
        await h.manager.on_status(StatusRequest(job="20260101-000000-abcdef"))
    with pytest.raises(JobError, match="no such job"):
        await h.manager.on_accept(AcceptRequest(job="20260101-000000-abcdef"))
    h.manager.start()
    job = (await h.manager.on_submit(HealthJob()))["job"]
    await h.manager.wait(job, timeout=5)
    with pytest.raises(JobError, match="only a succeeded calibrate job"):
        await h.manager.on_accept(AcceptRequest(job=job))
    await h.manager.close()
