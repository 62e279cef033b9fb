"""A cell without devices that answers the bus like the daemon: for bus tests and the bus benchmark.

:class:`DummyCell` implements :class:`~celld.bus.server.CellHandlers` with the
real job journal and the daemon's queueing rules (one job at a time, a bounded
queue, refusal beyond it, cancel of queued and running jobs), but its jobs
only wait: each publishes ``steps`` progress events over ``job_duration``
seconds and succeeds. A succeeded calibrate job has the identity as its
"result", so ``accept`` and ``calibration`` can be exercised over the bus; it
is not a calibration and nothing else may use it as one.

``python -m celld.bus.dummy --config FILE --state-dir DIR`` serves one such
cell with the bus settings of FILE and prints ``ready <cell>`` on stdout
when its queryables are declared; SIGTERM or SIGINT stop it. With
``--state-hz`` it also feeds made-up robot and tactile samples at that rate
into the server's (decimating) state publications, as the daemon feeds the
real ones, so a load test carries the publication traffic too.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import signal
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any, Mapping

from celld import __version__, config
from celld.bus.keys import CellKeys
from celld.bus.schema import (
    AcceptRequest,
    CalibrationRequest,
    CancelRequest,
    Job,
    ListRequest,
    StatusRequest,
    job_to_message,
)
from celld.bus.server import BusServer
from celld.bus.session import open_server
from celld.errors import JobError
from celld.journal import Journal, JobRecord, utc_now
from celld.log import configure

# Default: jobs that wait at most this many, and are refused beyond.
MAX_QUEUE = 8
_IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


class DummyCell:
    """Jobs that wait, behind the daemon's bus interface (see the module docstring).

    Parameters
    ----------
    name : str
        The cell's name.
    journal : Journal
        Where jobs are recorded.
    job_duration : float
        How long each job takes, s.
    steps : int
        Progress events per job before the final one.
    progress_hz : float, optional
        Instead of ``steps``: progress events per second of the job's duration.
    durations : mapping, optional
        Per-kind durations (``{"weld": 40.0}``) overriding ``job_duration``.
    max_queue : int
        Jobs that may wait behind the running one.
    """

    def __init__(
        self,
        name: str,
        journal: Journal,
        *,
        job_duration: float = 0.05,
        steps: int = 5,
        max_queue: int = MAX_QUEUE,
        durations: Mapping[str, float] | None = None,
        progress_hz: float | None = None,
    ) -> None:
        self.name = name
        self.progress_hz = progress_hz
        self.journal = journal
        self.job_duration = job_duration
        self.durations = dict(durations or {})
        self.steps = max(1, steps)
        self.max_queue = max_queue
        self.server: BusServer | None = None
        self._queue: deque[JobRecord] = deque()
        self._running: JobRecord | None = None
        self._task: asyncio.Task[None] | None = None
        self._calibration: dict[str, Any] | None = None
        self._started = time.monotonic()

    def attach(self, server: BusServer) -> None:
        """Publish progress through ``server``."""
        self.server = server

    def _progress(self, record: JobRecord, state: str, stage: str, fraction: float | None = None, message: str = "") -> None:
        if self.server is not None:
            self.server.publish_progress(record.id, record.kind, state, stage, fraction=fraction, message=message)

    # -- job running ----------------------------------------------------------------

    def _start(self, record: JobRecord) -> None:
        self._running = record if record.state == "running" else self.journal.start(record.id)
        self._task = asyncio.get_running_loop().create_task(self._run(self._running))

    async def _run(self, record: JobRecord) -> None:
        state, reason = "succeeded", ""
        duration = self.durations.get(record.kind, self.job_duration)
        steps = self.steps if self.progress_hz is None else max(1, round(duration * self.progress_hz))
        try:
            for i in range(steps):
                self._progress(record, "running", "wait", fraction=i / steps, message=f"step {i + 1} of {steps}")
                await asyncio.sleep(duration / steps)
        except asyncio.CancelledError:
            state, reason = "cancelled", "cancelled by request"
        final = self.journal.finish(record.id, state, reason)
        self._progress(final, state, "done", fraction=1.0 if state == "succeeded" else None, message=reason)
        self._running, self._task = None, None
        if self._queue:
            self._start(self._queue.popleft())

    async def close(self) -> None:
        """Cancel the running job and mark queued ones cancelled."""
        while self._queue:
            self.journal.finish(self._queue.popleft().id, "cancelled", "the cell stopped")
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    # -- handlers -------------------------------------------------------------------

    async def on_submit(self, job: Job) -> Mapping[str, Any]:
        if self._running is not None and len(self._queue) >= self.max_queue:
            raise JobError("$", f"refused: a job is running and {len(self._queue)} wait (the queue holds {self.max_queue})")
        idle = self._running is None
        record = self.journal.create(job.kind, job_to_message(job), job.ref, start=idle)
        if idle:
            self._start(record)
            return {"job": record.id, "state": "running", "position": 0}
        self._queue.append(record)
        return {"job": record.id, "state": "queued", "position": len(self._queue)}

    async def on_status(self, req: StatusRequest) -> Mapping[str, Any]:
        if req.job is not None:
            record = self.journal.get(req.job)
            if record is None:
                raise JobError("$.job", f"no job {req.job} in the journal")
            return {"record": record.to_message()}
        return {
            "cell": self.name,
            "state": "running" if self._running else "idle",
            "running": self._running.id if self._running else None,
            "queued": [r.id for r in self._queue],
            "robot_link": "unknown",
            "calibration": self._calibration["job"] if self._calibration else None,
            "uptime_s": time.monotonic() - self._started,
            "version": __version__,
            "message": "dummy cell: jobs only wait",
        }

    async def on_cancel(self, req: CancelRequest) -> Mapping[str, Any]:
        if self._running is not None and self._running.id == req.job and self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            return {"job": req.job, "state": "cancelled"}
        for record in self._queue:
            if record.id == req.job:
                self._queue.remove(record)
                self.journal.finish(record.id, "cancelled", req.reason or "cancelled by request")
                self._progress(record, "cancelled", "done")
                return {"job": req.job, "state": "cancelled"}
        found = self.journal.get(req.job)
        if found is None:
            raise JobError("$.job", f"no job {req.job} in the journal")
        raise JobError("$.job", f"job {req.job} is {found.state}; only queued or running jobs can be cancelled")

    async def on_list(self, req: ListRequest) -> Mapping[str, Any]:
        return {"jobs": [r.to_message() for r in self.journal.jobs(req.limit, req.state, req.kind)]}

    async def on_accept(self, req: AcceptRequest) -> Mapping[str, Any]:
        record = self.journal.get(req.job)
        if record is None:
            raise JobError("$.job", f"no job {req.job} in the journal")
        if record.kind != "calibrate" or record.state != "succeeded":
            raise JobError("$.job", f"expected a succeeded calibrate job, got a {record.state} {record.kind} job")
        self._calibration = {"job": record.id, "T_base_cam": _IDENTITY, "accepted": utc_now()}
        return {"job": record.id, "calibration": self._calibration}

    async def on_calibration(self, req: CalibrationRequest) -> Mapping[str, Any]:
        return {"calibration": self._calibration}

    async def feed_state(self, rate_hz: float) -> None:
        """Offer made-up robot and tactile samples at ``rate_hz`` to the server until cancelled."""
        period = 1.0 / rate_hz
        next_t = time.monotonic()
        while True:
            if self.server is not None:
                now_ns = time.monotonic_ns()
                phase = now_ns * 1e-9
                q = [math.sin(phase + i) for i in range(6)]
                self.server.publish_robot_state(
                    {"t_ns": now_ns, "link": "up", "q": q, "qd": [0.0] * 6, "tcp_pose": [0.5, 0.0, 0.4, 0.0, math.pi, 0.0], "tcp_speed": [0.0] * 6},
                    now_ns,
                )
                self.server.publish_tactile_state({"t_ns": now_ns, "valid": True, "contact": True, "delta": [0.0, 0.0015, 0.0]}, now_ns)
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))


async def serve(
    cfg: config.Config,
    state_dir: Path,
    job_duration: float,
    steps: int = 5,
    state_hz: float = 0.0,
    durations: Mapping[str, float] | None = None,
    progress_hz: float | None = None,
) -> None:
    """Serve a dummy cell with ``cfg``'s bus until cancelled."""
    keys = CellKeys.of(cfg.bus.prefix, cfg.cell.name)
    with open_server(cfg.bus, keys) as server_session, Journal(state_dir / "jobs.sqlite3") as journal:
        cell = DummyCell(
            cfg.cell.name, journal, job_duration=job_duration, steps=steps, durations=durations, progress_hz=progress_hz
        )
        server = BusServer(server_session.session, keys, cell, state_rate_hz=cfg.bus.state_rate_hz)
        cell.attach(server)
        async with server:
            feed = asyncio.create_task(cell.feed_state(state_hz)) if state_hz > 0 else None
            print(f"ready {cfg.cell.name}", flush=True)
            try:
                await asyncio.Event().wait()
            finally:
                if feed is not None:
                    feed.cancel()
                await cell.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m celld.bus.dummy", description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="cell config whose [cell] and [bus] are used")
    parser.add_argument("--state-dir", required=True, help="directory of the job journal")
    parser.add_argument("--job-duration", type=float, default=0.05, help="seconds each job waits")
    parser.add_argument("--weld-duration", type=float, help="seconds a weld job waits (default: --job-duration)")
    parser.add_argument("--steps", type=int, default=5, help="progress events per job")
    parser.add_argument("--progress-hz", type=float, help="progress events per second of a job (instead of --steps)")
    parser.add_argument("--state-hz", type=float, default=0.0, help="rate of made-up state samples offered (0: none)")
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))
    args = parser.parse_args(argv)
    configure(args.log_level)  # logs on stderr: stdout carries the ready line
    cfg = config.load(args.config)

    async def run() -> None:
        task = asyncio.current_task()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, task.cancel)  # type: ignore[union-attr]
        try:
            durations = {} if args.weld_duration is None else {"weld": args.weld_duration}
            await serve(cfg, Path(args.state_dir), args.job_duration, args.steps, args.state_hz, durations, args.progress_hz)
        except asyncio.CancelledError:
            pass

    asyncio.run(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
