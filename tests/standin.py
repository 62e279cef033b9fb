"""A stand-in cell without devices that answers the bus as the daemon does: for bus tests and the bus benchmark.

:class:`DummyCell` is the daemon's own :class:`~celld.daemon.jobs.JobManager`
(the real journal, queueing, cancelling, results and calibration store)
with runners that only wait: each job publishes ``steps`` progress events
over ``job_duration`` seconds and succeeds, and there is no robot to stop. A
succeeded calibrate job leaves the identity as its calibration, so
``accept`` and ``calibration`` can be exercised over the bus; it is not a
calibration and nothing else may use it as one.

``python -m tests.standin --config FILE --state-dir DIR`` (from the repository) serves one such
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
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from celld import config
from celld.bus.keys import CellKeys
from celld.bus.messages import JOB_KINDS
from celld.bus.requests import Job
from celld.bus.security import OPEN, Caller
from celld.bus.server import BusServer
from celld.bus.session import callers, open_server
from celld.daemon.jobs import JobContext, JobManager
from celld.journal import Journal
from celld.log import configure

# Default: jobs that wait at most this many, and are refused beyond.
MAX_QUEUE = 8
_IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


async def _no_robot() -> None:
    """The dummy cell has no robot to stop."""


class DummyCell(JobManager):
    """Jobs that wait, behind the daemon's job manager (see the module docstring).

    Parameters
    ----------
    name : str
        The cell's name.
    journal : Journal
        Where jobs are recorded; results and calibrations go beside it.
    job_duration : float
        How long each job takes, s.
    steps : int
        Progress events per job between its start and end events.
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
        self.progress_hz = progress_hz
        self.job_duration = job_duration
        self.durations = dict(durations or {})
        self.steps = max(1, steps)
        self.server: BusServer | None = None
        super().__init__(
            journal,
            journal.path.parent,
            {kind: self._wait for kind in JOB_KINDS},
            self._publish,
            _no_robot,
            cell=name,
            queue_depth=max_queue,
        )

    def attach(self, server: BusServer) -> None:
        """Publish progress through ``server``."""
        self.server = server

    def _publish(self, job: str, kind: str, state: str, stage: str, **kw: Any) -> None:
        if self.server is not None:
            self.server.publish_progress(job, kind, state, stage, **kw)

    async def on_submit(self, job: Job, caller: Caller = OPEN) -> Mapping[str, Any]:
        if self._worker is None:
            self.start()  # on the server's loop, at the first job
        return await super().on_submit(job, caller)

    async def _wait(self, ctx: JobContext) -> Mapping[str, Any]:
        duration = self.durations.get(ctx.job.kind, self.job_duration)
        steps = self.steps if self.progress_hz is None else max(1, round(duration * self.progress_hz))
        for i in range(steps):
            ctx.progress("wait", i / steps, f"step {i + 1} of {steps}")
            await asyncio.sleep(duration / steps)
        if ctx.job.kind == "calibrate":
            return {"calibration": {"job": ctx.job_id, "T_base_cam": _IDENTITY, "method": "none: a dummy cell's identity"}}
        return {"waited_s": duration}

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
                    {
                        "t_ns": now_ns,
                        "link": "up",
                        "q": q,
                        "qd": [0.0] * 6,
                        "tcp_pose": [0.5, 0.0, 0.4, 0.0, math.pi, 0.0],
                        "tcp_speed": [0.0] * 6,
                    },
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
    max_queue: int = MAX_QUEUE,
) -> None:
    """Serve a dummy cell with ``cfg``'s bus until cancelled."""
    keys = CellKeys.of(cfg.bus.prefix, cfg.cell.name)
    with open_server(cfg.bus, keys) as server_session, Journal(state_dir / "jobs.sqlite3") as journal:
        cell = DummyCell(
            cfg.cell.name,
            journal,
            job_duration=job_duration,
            steps=steps,
            durations=durations,
            progress_hz=progress_hz,
            max_queue=max_queue,
        )
        server = BusServer(server_session.session, keys, cell, state_rate_hz=cfg.bus.state_rate_hz, callers=callers(cfg.bus))
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
    parser = argparse.ArgumentParser(prog="python -m tests.standin", description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="cell config whose [cell] and [bus] are used")
    parser.add_argument("--state-dir", required=True, help="directory of the job journal")
    parser.add_argument("--job-duration", type=float, default=0.05, help="seconds each job waits")
    parser.add_argument("--weld-duration", type=float, help="seconds a weld job waits (default: --job-duration)")
    parser.add_argument("--steps", type=int, default=5, help="progress events per job")
    parser.add_argument("--progress-hz", type=float, help="progress events per second of a job (instead of --steps)")
    parser.add_argument("--state-hz", type=float, default=0.0, help="rate of made-up state samples offered (0: none)")
    parser.add_argument("--max-queue", type=int, default=MAX_QUEUE, help="jobs that may wait behind the running one")
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
            await serve(
                cfg, Path(args.state_dir), args.job_duration, args.steps, args.state_hz, durations, args.progress_hz, args.max_queue
            )
        except asyncio.CancelledError:
            pass

    asyncio.run(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
