"""The job manager: one job at a time, a bounded queue, cancel stops the robot first."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from celld.bus.requests import AcceptRequest, CalibrateJob, CancelRequest, HealthJob, ListRequest, MoveJob, StatusRequest
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
            fault = MotionError("link dropped: test")
            fault.add_note("the arm was left where it stopped")  # what the runner did after it
            raise fault

        async def stop() -> None:
            self.stops += 1

        def publish(job: str, kind: str, state: str, stage: str, **kw: Any) -> None:
            self.events.append({"job": job, "state": state, "stage": stage, **kw})

        self.manager = JobManager(
            self.journal,
            tmp_path,
            {"move": slow, "health": failing},
            publish,
            stop,
            cell="test",
            queue_depth=queue_depth,
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
    assert record.state == "failed" and record.reason == "link dropped: test; the arm was left where it stopped"
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
    with pytest.raises(JobError, match="only a succeeded calibrate or tool-calibrate job"):
        await h.manager.on_accept(AcceptRequest(job=job))
    await h.manager.close()


# -- the calibration quality gate at accept ------------------------------------------


def _calibration(verdict_ok: bool) -> dict[str, Any]:
    """A calibrate job's calibration with a real quality report: a wide or a narrow plane of poses."""
    import numpy as np

    from celld.calib.solve import solve_pairs
    from celld.se3 import apply, invert

    T = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
    rng = np.random.default_rng(3)
    width = 0.3 if verdict_ok else 0.02
    P_base = np.column_stack([rng.uniform(0.45, 0.75, 8), rng.uniform(-width / 2, width / 2, 8), np.full(8, 0.45)])
    P_cam = apply(invert(T), P_base) + rng.normal(0.0, 2e-4, (8, 3))
    result = solve_pairs([f"p{i}" for i in range(8)], P_base, P_cam)
    return {
        "T_base_cam": result.T_base_cam_stored.tolist(),
        "stored": result.stored,
        "method": result.method,
        "quality": result.quality.as_dict(),
    }


def _calibrating_harness(tmp_path: Path, verdict_ok: bool, auto_accept: bool = False) -> Harness:
    h = Harness(tmp_path)
    calibration = _calibration(verdict_ok)

    async def calibrate(ctx: JobContext) -> dict[str, Any]:
        return {"calibration": {"job": ctx.job_id, **calibration}}

    h.manager = JobManager(
        h.journal, tmp_path, {"calibrate": calibrate}, lambda *a, **k: None, h.manager.stop_robot, cell="test", auto_accept=auto_accept
    )
    return h


@run
async def test_accept_refuses_a_failed_quality_verdict_unless_forced(tmp_path: Path) -> None:
    from celld.bus import messages

    h = _calibrating_harness(tmp_path, verdict_ok=False)
    h.manager.start()
    job = (await h.manager.on_submit(CalibrateJob()))["job"]
    assert (await h.manager.wait(job, timeout=5)).state == "succeeded"
    with pytest.raises(JobError, match=r"failed its quality gate \(insufficient_rotation: rotation about X poorly fixed"):
        await h.manager.on_accept(AcceptRequest(job=job))
    assert (await h.manager.on_calibration(None))["calibration"] is None
    reply = await h.manager.on_accept(AcceptRequest(job=job, force=True))
    assert reply["calibration"]["forced"] is True and reply["calibration"]["quality"]["verdict"] == "insufficient_rotation"
    messages.check_message("accept-reply", {"ok": True, **reply})
    assert (await h.manager.on_calibration(None))["calibration"]["job"] == job
    await h.manager.close()


@run
async def test_accept_takes_a_passed_verdict_and_auto_accept_skips_a_failed_one(tmp_path: Path) -> None:
    from celld.bus import messages

    h = _calibrating_harness(tmp_path / "ok", verdict_ok=True)
    h.manager.start()
    job = (await h.manager.on_submit(CalibrateJob()))["job"]
    await h.manager.wait(job, timeout=5)
    reply = await h.manager.on_accept(AcceptRequest(job=job))
    assert "forced" not in reply["calibration"] and reply["calibration"]["quality"]["verdict"] == "ok"
    messages.check_message("accept-reply", {"ok": True, **reply})
    await h.manager.close()

    h = _calibrating_harness(tmp_path / "auto", verdict_ok=False, auto_accept=True)
    h.manager.start()
    job = (await h.manager.on_submit(CalibrateJob()))["job"]
    # The job itself succeeds; its calibration waits for an operator.
    assert (await h.manager.wait(job, timeout=5)).state == "succeeded"
    assert (await h.manager.on_calibration(None))["calibration"] is None
    await h.manager.close()
