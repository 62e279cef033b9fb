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
when its queryables are declared; SIGTERM or SIGINT stop it.
"""

from __future__ import annotations

import argparse
import asyncio
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
    max_queue : int
        Jobs that may wait behind the running one.
    """

    def __init__(self, name: str, journal: Journal, *, job_duration: float = 0.05, steps: int = 5, max_queue: int = MAX_QUEUE) -> None:
        self.name = name
        self.journal = journal
        self.job_duration = job_duration
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
        self._running = self.journal.start(record.id)
        self._task = asyncio.get_running_loop().create_task(self._run(self._running))

    async def _run(self, record: JobRecord) -> None:
        state, reason = "succeeded", ""
        try:
            for i in range(self.steps):
                self._progress(record, "running", "wait", fraction=i / self.steps, message=f"step {i + 1} of {self.steps}")
                await asyncio.sleep(self.job_duration / self.steps)
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
        record = self.journal.create(job.kind, job_to_message(job), job.ref)
        if self._running is None:
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


async def serve(cfg: config.Config, state_dir: Path, job_duration: float, ready: asyncio.Event | None = None) -> None:
    """Serve a dummy cell with ``cfg``'s bus until cancelled."""
    keys = CellKeys.of(cfg.bus.prefix, cfg.cell.name)
    with open_server(cfg.bus, keys) as server_session, Journal(state_dir / "jobs.sqlite3") as journal:
        cell = DummyCell(cfg.cell.name, journal, job_duration=job_duration)
        server = BusServer(server_session.session, keys, cell, state_rate_hz=cfg.bus.state_rate_hz)
        cell.attach(server)
        async with server:
            if ready is not None:
                ready.set()
            print(f"ready {cfg.cell.name}", flush=True)
            try:
                await asyncio.Event().wait()
            finally:
                await cell.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m celld.bus.dummy", description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="cell config whose [cell] and [bus] are used")
    parser.add_argument("--state-dir", required=True, help="directory of the job journal")
    parser.add_argument("--job-duration", type=float, default=0.05, help="seconds each job waits")
    args = parser.parse_args(argv)
    cfg = config.load(args.config)

    async def run() -> None:
        task = asyncio.current_task()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, task.cancel)  # type: ignore[union-attr]
        try:
            await serve(cfg, Path(args.state_dir), args.job_duration)
        except asyncio.CancelledError:
            pass

    asyncio.run(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
