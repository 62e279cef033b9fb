"""The job manager: one motion job at a time, a bounded queue, the journal, cancel.

:class:`JobManager` answers the bus (it implements
:class:`celld.bus.server.CellHandlers`) and runs the jobs. Rules:

- One job runs at a time (every job kind moves the robot or needs the
  scanner). Up to ``queue_depth`` more wait, first in first out; a submit
  beyond that is refused, and the reply says so. A submit reply says whether
  the job runs now (``position`` 0) or where it waits.
- Every job is a journal row before it is acknowledged; every change of state
  is committed before it is published.
- A job runs as an asyncio task through the runner of its kind (a coroutine
  ``runner(ctx) -> result dict``). Its result is written atomically to
  ``<state_dir>/results/<job>.json`` and the journal points at it.
- Cancel: a queued job is dropped; a running job's task is cancelled, which
  the runner sees as :class:`asyncio.CancelledError` at its next await; the
  manager then calls ``stop_robot`` (a jerk-limited stop) before it records
  the job as cancelled. A runner never has to clean up the robot itself.
- Progress events go out through ``publish`` (the bus server); each job also
  gets its own rerun recording when a ``recording_factory`` is given.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from celld import __version__, fsutil
from celld.bus import schema
from celld.bus.schema import (
    AcceptRequest,
    CalibrationRequest,
    CancelRequest,
    Job,
    ListRequest,
    RobotRequest,
    StatusRequest,
)
from celld.errors import CelldError, JobError
from celld.journal import JobRecord, Journal
from celld.log import get_logger

log = get_logger(__name__)

# Default: most jobs waiting behind the running one.
QUEUE_DEPTH = 4


class ProgressSink(Protocol):
    def __call__(
        self, job: str, kind: str, state: str, stage: str, *, fraction: float | None = None,
        message: str = "", data: Mapping[str, Any] | None = None,
    ) -> Any: ...


@dataclass
class JobContext:
    """What a runner gets: its job, a way to report progress, its recording."""

    job_id: str
    job: Job
    state_dir: Path
    publish: ProgressSink
    recording: Any = None  # celld.recording.JobRecording, or None
    started_ns: int = field(default_factory=time.monotonic_ns)

    def progress(self, stage: str, fraction: float | None = None, message: str = "", **data: Any) -> None:
        """Publish a progress event of this (running) job."""
        self.publish(self.job_id, self.job.kind, "running", stage, fraction=fraction, message=message, data=data)
        if self.recording is not None and message:
            self.recording.log_event(f"{stage}: {message}")

    def result_dir(self) -> Path:
        """A directory for this job's files (datasets, paths), created on demand."""
        d = self.state_dir / "jobs" / self.job_id
        d.mkdir(parents=True, exist_ok=True)
        return d


Runner = Callable[[JobContext], Awaitable[Mapping[str, Any]]]


class CalibrationStore:
    """The current calibration, and the candidates finished calibrate jobs left.

    The current one is ``<state_dir>/calibration.json``; a candidate is
    ``<state_dir>/calibrations/<job>.json``. Both are written atomically.
    A candidate whose quality verdict (``quality.verdict``) is not ``ok`` is
    accepted only with ``force``, and is then marked ``forced``; a candidate
    without a verdict (written before the gate existed) is accepted as before.
    """

    def __init__(self, state_dir: Path) -> None:
        self.current_path = state_dir / "calibration.json"
        self.candidates = state_dir / "calibrations"
        self.candidates.mkdir(parents=True, exist_ok=True)

    def current(self) -> dict[str, Any] | None:
        import json

        if not self.current_path.exists():
            return None
        try:
            return json.loads(self.current_path.read_text())
        except (OSError, ValueError) as exc:
            log.error("current calibration unreadable; ignoring it", path=str(self.current_path), error=str(exc))
            return None

    def add_candidate(self, job_id: str, calibration: Mapping[str, Any]) -> Path:
        return fsutil.write_json(self.candidates / f"{job_id}.json", dict(calibration))

    def accept(self, job_id: str, force: bool = False) -> dict[str, Any]:
        import json

        path = self.candidates / f"{job_id}.json"
        if not path.exists():
            raise JobError("$.job", f"job {job_id} left no calibration to accept (not a finished calibrate job)")
        calibration = json.loads(path.read_text())
        quality = calibration.get("quality")
        verdict = quality.get("verdict") if isinstance(quality, dict) else None
        if verdict is not None and verdict != "ok":
            if not force:
                reasons = "; ".join(str(r) for r in quality.get("reasons", []))
                raise JobError(
                    "$.job",
                    f"the calibration of job {job_id} failed its quality gate ({verdict}: {reasons}); accept it with force to override",
                )
            calibration["forced"] = True
        calibration["accepted"] = _utc_now()
        fsutil.write_json(self.current_path, calibration)
        return calibration


def _utc_now() -> str:
    from celld.journal import utc_now

    return utc_now()


class JobManager:
    """Runs the cell's jobs one at a time; answers the bus.

    Parameters
    ----------
    journal : Journal
    state_dir : Path
    runners : mapping of job kind to Runner
    publish : ProgressSink
        Usually :meth:`celld.bus.server.BusServer.publish_progress`.
    stop_robot : coroutine function
        A jerk-limited stop that returns once the robot stands still.
    cell : str
    queue_depth : int
    recording_factory : callable(job_id, kind) -> JobRecording, optional
    link_state : callable() -> "up" | "down" | "unknown"
    robot_report : callable() -> dict, optional
        The robot's condition for the status reply (CellDevices.robot_report).
    robot_action : coroutine function(action) -> dict, optional
        Sends an operator's recovery command (CellDevices.robot_action);
        refused while a job runs.
    auto_accept : bool
        Make a calibrate job's result current when it succeeds.
    """

    def __init__(
        self,
        journal: Journal,
        state_dir: Path,
        runners: Mapping[str, Runner],
        publish: ProgressSink,
        stop_robot: Callable[[], Awaitable[None]],
        *,
        cell: str,
        queue_depth: int = QUEUE_DEPTH,
        recording_factory: Callable[[str, str], Any] | None = None,
        link_state: Callable[[], str] = lambda: "unknown",
        auto_accept: bool = False,
        robot_report: Callable[[], dict[str, Any]] | None = None,
        robot_action: Callable[[str], Awaitable[dict[str, Any]]] | None = None,
    ) -> None:
        self.journal = journal
        self.state_dir = Path(state_dir)
        self.runners = dict(runners)
        self.publish = publish
        self.stop_robot = stop_robot
        self.cell = cell
        self.queue_depth = queue_depth
        self.recording_factory = recording_factory
        self.link_state = link_state
        self.auto_accept = auto_accept
        self.robot_report = robot_report
        self.robot_action = robot_action
        self.calibrations = CalibrationStore(self.state_dir)
        self.results_dir = self.state_dir / "results"
        self.results_dir.mkdir(parents=True, exist_ok=True)
        fsutil.remove_stale_temporaries(self.state_dir)
        self._queue: deque[tuple[str, Job]] = deque()
        self._running: tuple[str, Job, asyncio.Task[None]] | None = None
        self._wake = asyncio.Event()
        self._worker: asyncio.Task[None] | None = None
        self._closing = False
        self._fault = ""
        self._t0 = time.monotonic()
        self.finished: dict[str, asyncio.Event] = {}

    # -- life cycle ---------------------------------------------------------------

    def start(self) -> None:
        self._worker = asyncio.get_running_loop().create_task(self._work(), name="celld-jobs")

    async def close(self) -> None:
        """Cancel queued and running jobs (the robot stops first), then stop the worker."""
        self._closing = True
        while self._queue:
            job_id, job = self._queue.popleft()
            self._end(job_id, job, "cancelled", "the daemon is shutting down")
        if self._running is not None:
            self._running[2].cancel()
            await asyncio.gather(self._running[2], return_exceptions=True)
        if self._worker is not None:
            self._worker.cancel()
            await asyncio.gather(self._worker, return_exceptions=True)

    def set_fault(self, message: str) -> None:
        """Mark the cell faulty (e.g. the robot link is down); "" clears it."""
        self._fault = message

    # -- CellHandlers ---------------------------------------------------------------

    async def on_submit(self, job: Job) -> Mapping[str, Any]:
        if self._closing:
            raise JobError("$", "refused: the daemon is shutting down")
        if job.kind not in self.runners:
            raise JobError("$.kind", f"this cell cannot run {job.kind!r} jobs (it runs {', '.join(sorted(self.runners))})")
        if self._waiting() >= self.queue_depth:
            raise JobError("$", f"refused: a job is running and the queue is full ({self.queue_depth})")
        params = schema.job_to_message(job)
        record = self.journal.create(job.kind, params, ref=getattr(job, "ref", ""))
        self.finished[record.id] = asyncio.Event()
        self._queue.append((record.id, job))
        position = self._waiting()
        self.publish(record.id, job.kind, "queued", "queued", fraction=0.0, message=f"position {position}")
        self._wake.set()
        log.info("job accepted", job=record.id, kind=job.kind, position=position)
        return {"job": record.id, "state": "running" if position == 0 else "queued", "position": position}

    def _waiting(self) -> int:
        """Jobs waiting behind the one that runs (or is about to run)."""
        return len(self._queue) if self._running is not None else max(0, len(self._queue) - 1)

    async def on_status(self, req: StatusRequest) -> Mapping[str, Any]:
        if req.job is not None:
            record = self.journal.get(req.job)
            if record is None:
                raise JobError("$.job", f"no such job {req.job!r}")
            return {"record": record.to_message()}
        current = self.calibrations.current()
        if self._fault:
            state = "fault"
        elif self._closing:
            state = "stopping"
        else:
            state = "running" if self._running is not None else "idle"
        reply = {
            "cell": self.cell,
            "state": state,
            "running": self._running[0] if self._running else None,
            "queued": [j for j, _ in self._queue],
            "robot_link": self.link_state(),
            "calibration": current.get("job") if current else None,
            "uptime_s": time.monotonic() - self._t0,
            "version": __version__,
            "message": self._fault,
        }
        if self.robot_report is not None:
            reply["robot"] = self.robot_report()
        return reply

    async def on_cancel(self, req: CancelRequest) -> Mapping[str, Any]:
        reason = req.reason or "cancelled by request"
        for i, (job_id, job) in enumerate(self._queue):
            if job_id == req.job:
                del self._queue[i]
                self._end(job_id, job, "cancelled", reason)
                return {"job": job_id, "state": "cancelled"}
        if self._running is not None and self._running[0] == req.job:
            task = self._running[2]
            task.cancel(reason)
            await asyncio.gather(task, return_exceptions=True)
            record = self.journal.get(req.job)
            return {"job": req.job, "state": record.state if record else "cancelled"}
        record = self.journal.get(req.job)
        if record is None:
            raise JobError("$.job", f"no such job {req.job!r}")
        raise JobError("$.job", f"job {req.job} has already ended ({record.state})")

    async def on_list(self, req: ListRequest) -> Mapping[str, Any]:
        return {"jobs": [r.to_message() for r in self.journal.jobs(req.limit, req.state, req.kind)]}

    async def on_accept(self, req: AcceptRequest) -> Mapping[str, Any]:
        record = self.journal.get(req.job)
        if record is None:
            raise JobError("$.job", f"no such job {req.job!r}")
        if record.kind != "calibrate" or record.state != "succeeded":
            raise JobError("$.job", f"job {req.job} is a {record.state} {record.kind} job; only a succeeded calibrate job can be accepted")
        if self._running is not None:
            raise JobError("$", f"refused: job {self._running[0]} is running; accept a calibration between jobs")
        calibration = self.calibrations.accept(req.job, force=req.force)
        log.info("calibration accepted", job=req.job, forced=bool(calibration.get("forced")))
        return {"job": req.job, "calibration": calibration}

    async def on_calibration(self, req: CalibrationRequest) -> Mapping[str, Any]:
        return {"calibration": self.calibrations.current()}

    async def on_robot(self, req: RobotRequest) -> Mapping[str, Any]:
        if self.robot_action is None:
            raise JobError("$", "this cell has no robot dashboard to send commands to")
        if self._running is not None:
            raise JobError("$.action", f"refused: job {self._running[0]} is running; {req.action} is for a robot at rest, between jobs")
        log.warning("operator robot command", action=req.action)
        return await self.robot_action(req.action)

    # -- running ----------------------------------------------------------------------

    async def wait(self, job_id: str, timeout: float | None = None) -> JobRecord | None:
        """Wait until ``job_id`` has ended (tests and the demo); returns its record."""
        event = self.finished.get(job_id)
        if event is not None:
            await asyncio.wait_for(event.wait(), timeout)
        return self.journal.get(job_id)

    async def _work(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._queue and not self._closing:
                job_id, job = self._queue.popleft()
                task = asyncio.get_running_loop().create_task(self._run(job_id, job), name=f"job-{job_id}")
                self._running = (job_id, job, task)
                try:
                    await asyncio.shield(task)
                except asyncio.CancelledError:
                    if not task.done():
                        raise
                finally:
                    self._running = None
                record = self.journal.get(job_id)
                if record is not None and not record.terminal:
                    # Cancelled before its first step: it never ran.
                    self._end(job_id, job, "cancelled", "cancelled before it started")

    async def _run(self, job_id: str, job: Job) -> None:
        self.journal.start(job_id)
        recording = None
        if self.recording_factory is not None:
            try:
                recording = self.recording_factory(job_id, job.kind)
            except CelldError as exc:
                log.error("job recording not opened; the job runs without one", job=job_id, error=str(exc))
        ctx = JobContext(job_id, job, self.state_dir, self.publish, recording)
        self.publish(job_id, job.kind, "running", "start", fraction=0.0)
        state, reason, result_path = "failed", "", None
        try:
            result = dict(await self.runners[job.kind](ctx))
            if recording is not None and recording.path is not None:
                result.setdefault("recording", str(recording.path))
            result_path = str(fsutil.write_json(self.results_dir / f"{job_id}.json", result))
            if job.kind == "calibrate" and "calibration" in result:
                self.calibrations.add_candidate(job_id, result["calibration"])
                if self.auto_accept:
                    try:
                        self.calibrations.accept(job_id)
                    except JobError as exc:  # a failed quality verdict waits for an operator
                        log.warning("calibration not accepted automatically", job=job_id, reason=str(exc))
            state = "succeeded"
        except asyncio.CancelledError:
            state, reason = "cancelled", "cancelled by request"
            await self._stop_robot_safely(job_id)
        except CelldError as exc:
            state, reason = "failed", str(exc)
            await self._stop_robot_safely(job_id)
            log.warning("job failed", job=job_id, error=reason)
        except Exception as exc:  # a bug: the job fails, the daemon stays up
            state, reason = "failed", f"internal error: {type(exc).__name__}: {exc}"
            await self._stop_robot_safely(job_id)
            log.exception("job failed with an internal error", job=job_id)
        finally:
            if recording is not None:
                try:
                    recording.close()
                except CelldError as exc:
                    log.error("job recording not closed cleanly", job=job_id, error=str(exc))
        self._end(job_id, job, state, reason, result_path)

    async def _stop_robot_safely(self, job_id: str) -> None:
        try:
            await asyncio.shield(self.stop_robot())
        except Exception as exc:  # the job's end must still be recorded  # noqa: BLE001
            log.error("stop after the job failed", job=job_id, error=str(exc))

    def _end(self, job_id: str, job: Job, state: str, reason: str, result: str | None = None) -> None:
        self.journal.finish(job_id, state, reason, result)
        self.publish(job_id, job.kind, state, "end", fraction=1.0 if state == "succeeded" else None, message=reason)
        event = self.finished.get(job_id)
        if event is not None:
            event.set()
        log.info("job ended", job=job_id, kind=job.kind, state=state, reason=reason)
