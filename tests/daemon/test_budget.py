"""The storage budget: the oldest artefacts go until the state directory fits, never a protected job's."""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path
from typing import Any

from celld.bus.checker import validate
from celld.bus.messages import STORAGE
from celld.bus.requests import MoveJob, StatusRequest
from celld.daemon.budget import DATASET, JOB_FILES, MIB, RECORDING, RESULT, Artefact, artefacts, enforce, plan_pruning
from celld.daemon.jobs import JobContext, JobManager
from celld.journal import Journal

NOW = 1_800_000_000.0
DAY = 86_400.0


def _a(kind: str, job: str, mb: float, days_ago: float) -> Artefact:
    return Artefact(kind, job, Path(f"/x/{job}/{kind}"), int(mb * MIB), NOW - days_ago * DAY)


def test_the_oldest_go_first_until_it_fits_and_protected_jobs_and_young_results_stay() -> None:
    items = [
        _a(RECORDING, "j1", 40, 50),
        _a(DATASET, "cal", 60, 60),  # the current calibration's: oldest, but protected
        _a(RESULT, "j1", 1, 50),
        _a(RECORDING, "j2", 40, 20),
        _a(RESULT, "j3", 1, 5),  # younger than the results' 30 days
        _a(RECORDING, "j3", 40, 5),
    ]
    plan = plan_pruning(items, used_bytes=200 * MIB, budget_bytes=120 * MIB, protect=["cal", None], keep_results_days=30, now=NOW)
    assert [(a.kind, a.job) for a in plan] == [(RECORDING, "j1"), (RESULT, "j1"), (RECORDING, "j2")]
    # Within the budget, or no budget: nothing goes.
    assert plan_pruning(items, 100 * MIB, 110 * MIB, now=NOW) == []
    assert plan_pruning(items, 200 * MIB, 0, now=NOW) == []
    # Over it with nothing that may go: nothing goes either (the report says it is over).
    assert plan_pruning(items, 200 * MIB, 10 * MIB, protect=["cal", "j1", "j2", "j3"], now=NOW) == []


def _file(path: Path, mb: float, days_ago: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\0" * int(mb * MIB))
    os.utime(path, (NOW - days_ago * DAY, NOW - days_ago * DAY))


def _state(root: Path) -> Path:
    state = root / "state"
    _file(state / "journal.db", 0.1, 0)
    _file(state / "calibration.json", 0.01, 70)
    _file(state / "recordings" / "old.rrd", 3, 40)
    _file(state / "recordings" / "mid.rrd", 3, 20)
    _file(state / "recordings" / "now.rrd.part", 3, 0)  # being written
    _file(state / "results" / "old.json", 0.2, 40)
    _file(state / "results" / "mid.json", 0.2, 20)
    _file(state / "jobs" / "old" / "paths.json", 1, 40)
    _file(state / "jobs" / "cal" / "dataset" / "p000.png", 4, 70)  # the current calibration's
    _file(state / "jobs" / "cal" / "dataset" / "poses.json", 0.01, 70)
    return state


def test_enforce_deletes_the_oldest_and_reports_what_it_freed(tmp_path: Path) -> None:
    state = _state(tmp_path)
    assert {(a.kind, a.job) for a in artefacts(state)} == {
        (RECORDING, "old"),
        (RECORDING, "mid"),
        (RESULT, "old"),
        (RESULT, "mid"),
        (JOB_FILES, "old"),
        (DATASET, "cal"),
    }
    report = enforce(state, budget_mb=10.4, protect=["cal"], keep_results_days=30, now=NOW)
    assert {a.job for a in report.pruned} == {"old"} and len(report.pruned) == 3
    assert not (state / "recordings" / "old.rrd").exists() and not (state / "jobs" / "old").exists()
    assert (state / "recordings" / "mid.rrd").exists() and (state / "jobs" / "cal" / "dataset" / "p000.png").exists()
    assert (state / "recordings" / "now.rrd.part").exists() and (state / "journal.db").exists()
    assert report.used_before - report.used_after == sum(a.bytes for a in report.pruned)
    assert report.used_after <= 10.4 * MIB and not report.over
    # A budget nothing more can meet: what may go goes, the rest stays, and the report says it is over.
    tight = enforce(state, budget_mb=1.0, protect=["cal"], keep_results_days=30, now=NOW)
    assert {(a.kind, a.job) for a in tight.pruned} == {(RECORDING, "mid")} and tight.over
    assert (state / "results" / "mid.json").exists(), "a result younger than the retention stays"


def test_the_job_manager_enforces_the_budget_after_each_job_and_status_says_so(tmp_path: Path) -> None:
    async def body() -> dict[str, Any]:
        journal = Journal(tmp_path / "journal.db")
        _file(tmp_path / "recordings" / "ancient.rrd", 2, 400)

        async def move(ctx: JobContext) -> dict[str, Any]:
            return {"done": ctx.job_id}

        async def stop() -> None:
            pass

        manager = JobManager(
            journal, tmp_path, {"move": move}, lambda *a, **k: None, stop, cell="t", storage_budget_mb=1.0, result_retention_days=30
        )
        manager.start()
        job = (await manager.on_submit(MoveJob(space="joint", target=(0.0, -1.57, 1.57, -1.57, -1.57, 0.0))))["job"]
        record = await manager.wait(job, timeout=5)
        assert record is not None and record.state == "succeeded"
        for _ in range(100):  # the enforcement follows the job's end
            if manager.storage.budget is not None:
                break
            await asyncio.sleep(0.02)
        status = await manager.on_status(StatusRequest())
        await manager.close()
        return status["storage"]

    storage = asyncio.run(asyncio.wait_for(body(), 30))
    validate(STORAGE, storage)
    assert storage["budget_mb"] == 1.0 and storage["pruned"] == 1 and storage["pruned_mb"] == 2.0
    assert storage["used_mb"] is not None and storage["used_mb"] < 1.0 and not storage["over_budget"]
    assert not (tmp_path / "recordings" / "ancient.rrd").exists()
    assert json.loads(next((tmp_path / "results").glob("*.json")).read_text())["done"]
