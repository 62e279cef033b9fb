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
- Cancel keeps the canceller's reason in the record (and who cancelled, on
  a bus with users).
- Progress events go out through ``publish`` (the bus server); each job also
  gets its own rerun recording when a ``recording_factory`` is given.

Who may do what (:class:`celld.bus.security.Caller`, from the bus server): a
job's owner is the bus user who submitted it; an operator cancels only its own
jobs, a supervisor any; a user who may not see a job in full gets its record
redacted and its result refused. A submit with a ``request_id`` is
idempotent per owner: the same id and body give the original job back
(``replayed``), the same id with another body is refused.

Storage faults are job faults (:class:`celld.daemon.storage.StorageGuard`):

- a journal, result, dataset (any job file), calibration or recording write
  that fails fails the job with the reason (``storage: <what> <path>:
  <reason>``), and the cell goes into a storage fault that status shows;
- nothing is lost that can be kept: a job's end the journal could not take is
  kept in memory (status and list show it) and a result file that could not
  be written is kept too; both are owed writes, made in order once space
  returns;
- while the fault lasts, or while free space is under ``cell.min_free_mb``,
  submits are refused with the reason and the queue waits (a job whose start
  cannot be recorded goes back to the head of the queue); every
  ``storage_retry_s`` the owed writes and a probe are tried again, and the
  queue runs again once they succeed;
- the worker never dies of a job: anything a job raises ends that job.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from celld import __version__, fsutil
from celld.bus.messages import MAX_RESULT_BYTES, STORAGE
from celld.bus.requests import (
    AcceptRequest,
    CalibrationRequest,
    CancelRequest,
    Job,
    ListRequest,
    ResultRequest,
    RobotRequest,
    StatusRequest,
    job_to_message,
)
from celld.bus.security import OPEN, Caller
from celld.daemon import budget
from celld.daemon.storage import StorageGuard
from celld.daemon.store import CalibrationStore, failed_verification, last_verification, tool_store
from celld.errors import CelldError, DamagedStateError, JobError, JournalError, StorageError
from celld.journal import JobRecord, Journal, utc_now
from celld.log import get_logger
from celld.schemadoc import string, with_properties

if TYPE_CHECKING:
    from celld.recording.job import JobRecording

log = get_logger(__name__)

# Default: most jobs waiting behind the running one.
QUEUE_DEPTH = 4
# Default: how often owed writes are retried during a storage fault, s.
STORAGE_RETRY_S = 5.0
# Most files of one job listed in a result reply.
MAX_LISTED_FILES = 200


class ProgressSink(Protocol):
    def __call__(
        self,
        job: str,
        kind: str,
        state: str,
        stage: str,
        *,
        fraction: float | None = None,
        message: str = "",
        data: Mapping[str, Any] | None = None,
    ) -> Any: ...


@dataclass
class JobContext:
    """What a runner gets: its job, a way to report progress, its recording."""

    job_id: str
    job: Job
    state_dir: Path
    publish: ProgressSink
    recording: JobRecording | None = None
    started_ns: int = field(default_factory=time.monotonic_ns)

    def progress(self, stage: str, fraction: float | None = None, message: str = "", **data: Any) -> None:
        """Publish a progress event of this (running) job."""
        self.publish(self.job_id, self.job.kind, "running", stage, fraction=fraction, message=message, data=data)
        if self.recording is not None and message:
            self.recording.event_later(f"{stage}: {message}")

    def result_dir(self) -> Path:
        """A directory for this job's files (datasets, paths), created on demand."""
        d = self.state_dir / "jobs" / self.job_id
        d.mkdir(parents=True, exist_ok=True)
        return d


Runner = Callable[[JobContext], Awaitable[Mapping[str, Any]]]

# Job kinds whose result an accept makes current, and the key of their result that holds it.
ACCEPTED_KINDS = {"calibrate": "calibration", "tool-calibrate": "tool"}


def with_manager_fields(kind: str, result: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON shape of a ``kind`` job's result as the manager writes it: its runner's (``result``) with what
    :meth:`JobManager._run` adds: the job's recording, and a health job's the state directory's storage."""
    out = with_properties(result, {"recording": string("Path of the job's rerun recording on the cell PC.")})
    if kind == "health":
        out = with_properties(out, {"storage": STORAGE}, ("storage",))
    return out


@dataclass(frozen=True)
class _Ending:
    """A job's end the journal has not taken yet (a storage fault); status shows it meanwhile."""

    state: str
    reason: str
    result: str | None
    ended: str


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
    loop_report : callable() -> dict, optional
        The event loop's stalls for the status reply (:meth:`celld.daemon.loopwatch.LoopWatch.report`).
    auto_accept : bool
        Make a calibrate (or tool-calibrate) job's result current when it succeeds (and its verdict is ok).
    min_free_mb : float
        The disk-space floor of the state directory, MiB (``cell.min_free_mb``); 0: none.
    storage_retry_s : float
        How often owed writes are retried during a storage fault, s.
    storage_budget_mb, result_retention_days : float
        The state directory's budget (0: none) and how long results are kept whatever it says
        (``cell.storage_budget_mb``, ``cell.result_retention_days``; :mod:`celld.daemon.budget`), enforced
        after every job.
    free_bytes : callable, optional
        Replaces the free-space reading (tests).
    unready : callable(kind, dry_run) -> str, optional
        Why a job of that kind cannot run now for want of a device ("" when it
        can: :meth:`celld.daemon.devices.CellDevices.unready`); such a submit is
        refused at once with it, not queued to fail.
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
        loop_report: Callable[[], dict[str, Any]] | None = None,
        min_free_mb: float = 0.0,
        storage_retry_s: float = STORAGE_RETRY_S,
        free_bytes: Callable[[], int | None] | None = None,
        unready: Callable[[str, bool], str] | None = None,
        storage_budget_mb: float = 0.0,
        result_retention_days: float = 30.0,
    ) -> None:
        if storage_retry_s <= 0:
            raise ValueError(f"storage_retry_s: expected > 0, got {storage_retry_s}")
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
        self.loop_report = loop_report
        self.unready = unready
        self.storage = StorageGuard(
            self.state_dir, min_free_mb, free_bytes=free_bytes, damage=journal.damage_report, budget_mb=storage_budget_mb
        )
        self.result_retention_days = result_retention_days
        self.storage_retry_s = storage_retry_s
        self.calibrations = CalibrationStore(self.state_dir)
        self.tools = tool_store(self.state_dir)
        self.results_dir = self.state_dir / "results"
        self.results_dir.mkdir(parents=True, exist_ok=True)
        fsutil.remove_stale_temporaries(self.state_dir)
        self._queue: deque[tuple[str, Job]] = deque()
        self._running: tuple[str, Job, asyncio.Task[None]] | None = None
        self._wake = asyncio.Event()
        self._worker: asyncio.Task[None] | None = None
        self._watcher: asyncio.Task[None] | None = None
        self._closing = False
        self._fault = ""
        self._t0 = time.monotonic()
        self._endings: dict[str, _Ending] = {}
        self._cancel_reasons: dict[str, str] = {}
        self._recording: JobRecording | None = None  # the running job's recording, for status
        self.finished: dict[str, asyncio.Event] = {}

    # -- life cycle ---------------------------------------------------------------

    def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._worker = loop.create_task(self._work(), name="celld-jobs")
        self._watcher = loop.create_task(self._watch_storage(), name="celld-storage")

    async def close(self) -> None:
        """Cancel queued and running jobs (the robot stops first), then stop the worker."""
        self._closing = True
        while self._queue:
            job_id, job = self._queue.popleft()
            self._end(job_id, job, "cancelled", "the daemon is shutting down")
        if self._running is not None:
            self._cancel_reasons.setdefault(self._running[0], "the daemon is shutting down")
            self._running[2].cancel()
            await asyncio.gather(self._running[2], return_exceptions=True)
        for task in (self._worker, self._watcher):
            if task is not None:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
        if self.storage.owed:
            self.storage.retry()  # a last try; what is still owed is lost with this process
            if self.storage.owed:
                log.error("writes_still_owed_at_shutdown", owed=[w.label for w in self.storage.owed])

    def set_fault(self, message: str) -> None:
        """Mark the cell faulty (e.g. the robot link is down); "" clears it."""
        self._fault = message

    # -- records --------------------------------------------------------------------

    def _record(self, job_id: str) -> JobRecord | None:
        """The journal's record of ``job_id``, with its end if the journal still owes it."""
        record = self.journal.get(job_id)
        return None if record is None else self._with_ending(record)

    def _known(self, job_id: str) -> JobRecord:
        """:meth:`_record`, refused with the reason when there is no such job."""
        record = self._record(job_id)
        if record is None:
            raise JobError("$.job", f"no such job {job_id!r}")
        return record

    def _with_ending(self, record: JobRecord) -> JobRecord:
        """``record`` with the end the journal still owes, if any."""
        ending = self._endings.get(record.id)
        if ending is None:
            return record
        return dataclasses.replace(
            record, state=ending.state, reason=ending.reason, ended=ending.ended, result=ending.result or record.result
        )

    def _position(self, job_id: str) -> int:
        for i, (queued, _) in enumerate(self._queue):
            if queued == job_id:
                return i + 1 if self._running is not None else i
        return 0

    # -- CellHandlers ---------------------------------------------------------------

    async def on_submit(self, job: Job, caller: Caller = OPEN) -> Mapping[str, Any]:
        if not caller.may("submit"):
            raise JobError("$", f"refused: {caller} may not submit jobs")
        if self._closing:
            raise JobError("$", "refused: the daemon is shutting down")
        if job.kind not in self.runners:
            raise JobError("$.kind", f"this cell cannot run {job.kind!r} jobs (it runs {', '.join(sorted(self.runners))})")
        params = job_to_message(job)
        params.pop("request_id", None)  # kept in its own column; the body is the rest
        request_id = job.request_id or None
        if request_id is not None:
            prior = self.journal.find_request(caller.user, request_id)
            if prior is not None:
                if prior.params != params:
                    raise JobError(
                        "$.request_id",
                        f"request id {request_id!r} was used for job {prior.id} with a different body; a new job needs a new request id",
                    )
                prior = self._with_ending(prior)
                log.info("submit_replayed", job=prior.id, request_id=request_id, user=caller.user)
                return {"job": prior.id, "state": prior.state, "position": self._position(prior.id), "replayed": True}
        problem = self.storage.problem()
        if problem:
            raise JobError("$", f"refused: {problem}")
        if self._waiting() >= self.queue_depth:
            raise JobError("$", f"refused: a job is running and the queue is full ({self.queue_depth})")
        missing = self.unready(job.kind, bool(getattr(job, "dry_run", False))) if self.unready is not None else ""
        if missing:
            raise JobError("$", f"refused: {missing}")
        try:
            record = self.journal.create(job.kind, params, ref=job.ref, owner=caller.user, request_id=request_id)
        except StorageError as exc:
            fault = self.storage.failed(exc)
            self._wake.set()
            raise JobError("$", f"refused: {fault}; the job was not taken") from exc
        self.finished[record.id] = asyncio.Event()
        self._queue.append((record.id, job))
        position = self._waiting()
        self.publish(record.id, job.kind, "queued", "queued", fraction=0.0, message=f"position {position}")
        self._wake.set()
        log.info("job_accepted", job=record.id, kind=job.kind, position=position, user=caller.user)
        return {"job": record.id, "state": "running" if position == 0 else "queued", "position": position}

    def _waiting(self) -> int:
        """Jobs waiting behind the one that runs (or is about to run)."""
        return len(self._queue) if self._running is not None else max(0, len(self._queue) - 1)

    async def on_status(self, req: StatusRequest, caller: Caller = OPEN) -> Mapping[str, Any]:
        if req.job is not None:
            record = self._record(req.job)
            if record is None:
                raise JobError("$.job", f"no such job {req.job!r}")
            return {"record": record.to_message(caller.may_see(record.owner))}
        # What refuses welds besides a fault, said here as each refusal says it: the stored calibrations
        # damaged, the current calibration's verification failed.
        said = [self.tools.damage()]
        try:
            current = self.calibrations.current()
        except DamagedStateError as exc:
            current = None
            said.append(str(exc))
        if current is not None:
            said.append(failed_verification(last_verification(self.state_dir), current))
        self._note_recording_trouble()
        storage_problem = self.storage.problem()
        message = "; ".join(m for m in (self._fault, storage_problem, *said) if m)
        if self._fault or storage_problem:
            state = "fault"
            if storage_problem and self._queue:
                message += f"; {len(self._queue)} queued job(s) wait for it"
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
            "message": message,
            "storage": self.storage.to_message(),
        }
        if self.robot_report is not None:
            reply["robot"] = self.robot_report()
        if self.loop_report is not None:
            reply["loop"] = self.loop_report()
        return reply

    def _note_recording_trouble(self) -> None:
        """A recording that cannot write shows in status while its job still runs."""
        rec = self._recording
        error = getattr(rec, "write_error", None)
        if error is not None and self.storage.fault is None:
            self.storage.failed(error, "recording", str(getattr(rec, "path", "") or ""))

    async def on_cancel(self, req: CancelRequest, caller: Caller = OPEN) -> Mapping[str, Any]:
        record = self._known(req.job)
        if not caller.may_cancel(record.owner):
            raise JobError("$.job", f"job {req.job} is another user's; {caller} may cancel only its own jobs (a supervisor may cancel any)")
        reason = req.reason or "cancelled by request"
        if caller.user:
            reason += f" (by {caller.user})"
        for i, (job_id, job) in enumerate(self._queue):
            if job_id == req.job:
                del self._queue[i]
                self._end(job_id, job, "cancelled", reason)
                log.info("job_cancelled", job=job_id, user=caller.user, reason=reason)
                return {"job": job_id, "state": "cancelled"}
        if self._running is not None and self._running[0] == req.job:
            task = self._running[2]
            self._cancel_reasons[req.job] = reason
            task.cancel(reason)
            await asyncio.gather(task, return_exceptions=True)
            log.info("job_cancelled", job=req.job, user=caller.user, reason=reason)
            after = self._record(req.job)
            return {"job": req.job, "state": after.state if after else "cancelled"}
        raise JobError("$.job", f"job {req.job} has already ended ({record.state})")

    async def on_list(self, req: ListRequest, caller: Caller = OPEN) -> Mapping[str, Any]:
        records = (self._with_ending(r) for r in self.journal.jobs(req.limit, req.state, req.kind))
        return {"jobs": [r.to_message(caller.may_see(r.owner)) for r in records]}

    async def on_accept(self, req: AcceptRequest, caller: Caller = OPEN) -> Mapping[str, Any]:
        if not caller.may("accept"):
            raise JobError("$", f"refused: {caller} may not accept calibrations")
        record = self._known(req.job)
        if record.kind not in ACCEPTED_KINDS or record.state != "succeeded":
            raise JobError(
                "$.job",
                f"job {req.job} is a {record.state} {record.kind} job; only a succeeded calibrate or tool-calibrate job can be accepted",
            )
        if self._running is not None:
            raise JobError("$", f"refused: job {self._running[0]} is running; accept a calibration between jobs")
        store = self.tools if record.kind == "tool-calibrate" else self.calibrations
        try:
            calibration = store.accept(req.job, force=req.force)
        except OSError as exc:
            fault = self.storage.failed(exc, "calibration")
            raise JobError("$", f"refused: {fault}") from exc
        log.info("calibration_accepted", job=req.job, kind=record.kind, user=caller.user, forced=bool(calibration.get("forced")))
        return {"job": req.job, "kind": record.kind, ACCEPTED_KINDS[record.kind]: calibration}

    async def on_calibration(self, req: CalibrationRequest, caller: Caller = OPEN) -> Mapping[str, Any]:
        return {"calibration": self.calibrations.current(), "tool": self.tools.current()}

    async def on_robot(self, req: RobotRequest, caller: Caller = OPEN) -> Mapping[str, Any]:
        if self.robot_action is None:
            raise JobError("$", "this cell has no robot dashboard to send commands to")
        if self._running is not None:
            raise JobError("$.action", f"refused: job {self._running[0]} is running; {req.action} is for a robot at rest, between jobs")
        log.warning("operator_robot_command", action=req.action, user=caller.user)
        return await self.robot_action(req.action)

    async def on_result(self, req: ResultRequest, caller: Caller = OPEN) -> Mapping[str, Any]:
        record = self._known(req.job)
        if not caller.may_see(record.owner):
            raise JobError("$.job", f"{caller} may not read the results of other users' jobs (bus.users job_details)")
        if not record.terminal:
            raise JobError("$.job", f"job {req.job} is {record.state}; its result comes when it ends")
        return await asyncio.to_thread(self._result_reply, record)

    def _result_reply(self, record: JobRecord) -> dict[str, Any]:
        reply: dict[str, Any] = {
            "job": record.id,
            "kind": record.kind,
            "state": record.state,
            "reason": record.reason,
            "result": None,
            "too_large": False,
            "path": record.result,
            "files": self._files(record.id),
        }
        if record.result:
            path = Path(record.result)
            try:
                size = path.stat().st_size
                reply["bytes"] = size
                if size > MAX_RESULT_BYTES:
                    reply["too_large"] = True
                else:
                    reply["result"] = json.loads(path.read_bytes())
            except (OSError, ValueError) as exc:
                raise JobError("$.job", f"the result of job {record.id} cannot be read on the cell: {exc}") from exc
        return reply

    def _files(self, job_id: str) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        places = [self.state_dir / "jobs" / job_id, self.state_dir / "recordings" / f"{job_id}.rrd"]
        for place in places:
            found = [place] if place.is_file() else sorted(p for p in place.rglob("*") if p.is_file()) if place.is_dir() else []
            for p in found[: MAX_LISTED_FILES - len(out)]:
                try:
                    out.append({"path": str(p.relative_to(self.state_dir)), "bytes": p.stat().st_size})
                except OSError:
                    continue
        return out

    # -- running ----------------------------------------------------------------------

    async def wait(self, job_id: str, timeout: float | None = None) -> JobRecord | None:
        """Wait until ``job_id`` has ended (tests and the demo); returns its record."""
        event = self.finished.get(job_id)
        if event is not None:
            await asyncio.wait_for(event.wait(), timeout)
        return self._record(job_id)

    async def _watch_storage(self) -> None:
        """While storage is not ok, retry the owed writes and the probe every ``storage_retry_s``."""
        while True:
            await asyncio.sleep(self.storage_retry_s)
            if self.storage.fault is None and not self.storage.owed and not (self._queue and self.storage.below_floor()):
                continue
            try:
                if self.storage.retry():
                    self._wake.set()
            except Exception:  # the watcher must outlive anything a retry raises
                log.exception("storage_retry_failed")

    async def _work(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._queue and not self._closing:
                if not self.storage.ok:
                    # Held, not lost: the watcher wakes the worker once storage is back.
                    break
                job_id, job = self._queue.popleft()
                try:
                    await self._run_one(job_id, job)
                except asyncio.CancelledError:
                    raise
                except Exception:  # a bug around one job must not end the worker
                    log.exception("job_handling_failed", job=job_id)

    async def _run_one(self, job_id: str, job: Job) -> None:
        try:
            self.journal.start(job_id)
        except StorageError as exc:
            # It has not started: it waits at the head of the queue until its start can be recorded.
            self.storage.failed(exc)
            self._queue.appendleft((job_id, job))
            return
        task = asyncio.get_running_loop().create_task(self._run(job_id, job), name=f"job-{job_id}")
        self._running = (job_id, job, task)
        try:
            await asyncio.shield(task)
        except asyncio.CancelledError:
            if not task.done():
                raise
        except Exception:  # noqa: BLE001 (logged below as the task's exception; the job still gets its end)
            pass
        finally:
            self._running = None
            self._recording = None
        error = task.exception() if task.done() and not task.cancelled() else None
        if error is not None:
            log.error("job_task_failed", job=job_id, error=repr(error))
        record = self._record(job_id)
        if record is not None and not record.terminal:
            # Cancelled before its first step, or ended by a bug before its end was recorded.
            if error is not None:
                self._end(job_id, job, "failed", f"internal error: {type(error).__name__}: {error}")
            else:
                self._end(job_id, job, "cancelled", self._cancel_reasons.pop(job_id, "cancelled before it started"))

    async def _run(self, job_id: str, job: Job) -> None:
        recording = None
        if self.recording_factory is not None:
            try:
                # Off the event loop: opening a recording pays rerun's set-up (tens of ms).
                recording = await asyncio.to_thread(self.recording_factory, job_id, job.kind)
            except StorageError as exc:
                fault = self.storage.failed(exc)
                self._end(job_id, job, "failed", f"{fault}; the job did not start")
                return
            except CelldError as exc:
                log.error("job_recording_not_opened", job=job_id, error=str(exc))
        self._recording = recording
        ctx = JobContext(job_id, job, self.state_dir, self.publish, recording)
        self.publish(job_id, job.kind, "running", "start", fraction=0.0)
        state, reason, result_path = "failed", "", None
        try:
            result = dict(await self.runners[job.kind](ctx))
            if recording is not None and recording.path is not None:
                result.setdefault("recording", str(recording.path))
            if job.kind == "health":
                result.setdefault("storage", self.storage.to_message())
            result_path, reason = await self._save_result(job_id, job, result)
            state = "failed" if reason else "succeeded"
        except asyncio.CancelledError:
            state, reason = "cancelled", self._cancel_reasons.pop(job_id, "cancelled by request")
            await self._stop_robot_safely(job_id)
        except StorageError as exc:
            state, reason = "failed", str(self.storage.failed(exc))
            await self._stop_robot_safely(job_id)
            log.warning("job_failed", job=job_id, error=reason)
        except CelldError as exc:
            state, reason = "failed", "; ".join([str(exc), *getattr(exc, "__notes__", ())])  # notes: what followed it
            await self._stop_robot_safely(job_id)
            log.warning("job_failed", job=job_id, error=reason)
        except Exception as exc:  # a bug: the job fails, the daemon stays up
            if fsutil.is_storage_error(exc, self.state_dir):
                state, reason = "failed", str(self.storage.failed(exc, "job files"))
                log.warning("job_failed", job=job_id, error=reason)
            else:
                state, reason = "failed", f"internal error: {type(exc).__name__}: {exc}"
                log.exception("job_internal_error", job=job_id)
            await self._stop_robot_safely(job_id)
        finally:
            if recording is not None:
                try:
                    # Off the event loop: a close flushes, merges and fsyncs the file (seconds for a
                    # calibration's clouds), and the daemon's heartbeat must go on meanwhile.
                    await asyncio.to_thread(recording.close)
                except StorageError as exc:
                    fault = self.storage.failed(exc)
                    if state == "succeeded":
                        state, reason = "failed", f"{fault} (the job itself succeeded; its recording is incomplete)"
                    else:
                        reason = f"{reason}; and {fault}" if reason else str(fault)
                except CelldError as exc:
                    log.error("job_recording_not_closed_cleanly", job=job_id, error=str(exc))
                except Exception as exc:  # a bug in the recording's close must not leave the job without an end
                    log.exception("job_recording_close_error", job=job_id)
                    note = f"its recording was not closed: internal error: {type(exc).__name__}: {exc}"
                    reason = f"{reason}; {note}" if reason else note
        self._end(job_id, job, state, reason, result_path)
        await self._enforce_budget()

    async def _enforce_budget(self) -> None:
        """Prune the state directory to its budget (:mod:`celld.daemon.budget`), off the event loop; never fails."""
        if self.storage.budget_mb <= 0:
            return
        try:
            protect: list[str | None] = [r.id for r in self.journal.active()]
            protect += [(self.calibrations.current() or {}).get("job"), (self.tools.current() or {}).get("job")]
        except (DamagedStateError, JournalError) as exc:  # which jobs to keep is unknown: keep everything
            log.warning("storage_not_pruned", reason=str(exc))
            return
        try:
            report = await asyncio.to_thread(budget.enforce, self.state_dir, self.storage.budget_mb, protect, self.result_retention_days)
        except Exception:  # pruning never fails a job nor the daemon
            log.exception("storage_not_pruned")
            return
        self.storage.budget_enforced(report)

    async def _save_result(self, job_id: str, job: Job, result: dict[str, Any]) -> tuple[str | None, str]:
        """Write the result (and a calibration candidate); returns (path, "") or (None, the storage reason).

        The file is encoded and written in a worker thread (a weld's paths and a calibration's report
        take tens of milliseconds to encode and sync). A result the disk could not take is kept and
        owed: written, and the journal pointed at it, once there is room.
        """
        path = self.results_dir / f"{job_id}.json"
        try:
            written = str(await asyncio.to_thread(fsutil.write_json, path, result))
        except OSError as exc:
            fault = self.storage.failed(exc, "result", str(path))

            def write_later() -> None:
                self.journal.set_result(job_id, str(fsutil.write_json(path, result)))
                ending = self._endings.get(job_id)
                if ending is not None:
                    self._endings[job_id] = dataclasses.replace(ending, result=str(path))

            self.storage.owe(f"result {path.name}", write_later, job=job_id)
            return None, f"{fault} (the result is kept and written once there is room)"
        key = ACCEPTED_KINDS.get(job.kind)
        if key is not None and key in result:
            store = self.tools if job.kind == "tool-calibrate" else self.calibrations
            try:
                store.add_candidate(job_id, result[key])
                if self.auto_accept:
                    store.accept(job_id)
            except JobError as exc:  # a failed quality verdict waits for an operator
                log.warning("calibration_not_accepted_automatically", job=job_id, reason=str(exc))
            except OSError as exc:
                return written, str(self.storage.failed(exc, "calibration"))
        return written, ""

    async def _stop_robot_safely(self, job_id: str) -> None:
        try:
            await asyncio.shield(self.stop_robot())
        except Exception as exc:  # the job's end must still be recorded  # noqa: BLE001
            log.error("stop_after_job_failed", job=job_id, error=str(exc))

    def _end(self, job_id: str, job: Job, state: str, reason: str, result: str | None = None) -> None:
        """Record, then publish, a job's end; an end the journal cannot take is kept and owed."""
        if self.storage.owes(job_id):
            self._owe_end(job_id, state, reason, result)  # after the result owed before it
        else:
            try:
                self.journal.finish(job_id, state, reason, result)
            except StorageError as exc:
                fault = self.storage.failed(exc)
                if not reason.startswith("storage:"):
                    was = f"{state}: {reason}" if reason else state
                    state, reason = "failed", f"{fault} (recording the end of the job, which {was})"
                self._owe_end(job_id, state, reason, result)
            except JournalError as exc:  # not a storage fault: an impossible transition
                log.error("job_end_not_recorded", job=job_id, state=state, error=str(exc))
        self.publish(job_id, job.kind, state, "end", fraction=1.0 if state == "succeeded" else None, message=reason)
        event = self.finished.get(job_id)
        if event is not None:
            event.set()
        log.info("job_ended", job=job_id, kind=job.kind, state=state, reason=reason)

    def _owe_end(self, job_id: str, state: str, reason: str, result: str | None) -> None:
        self._endings[job_id] = _Ending(state, reason, result, utc_now())

        def write_end() -> None:
            ending = self._endings.get(job_id)
            if ending is None:
                return
            try:
                self.journal.finish(job_id, ending.state, ending.reason, ending.result)
            except StorageError:
                raise
            except JournalError as exc:
                log.error("owed_job_end_dropped", job=job_id, error=str(exc))
            self._endings.pop(job_id, None)

        self.storage.owe(f"journal: end of job {job_id}", write_end, job=job_id)
