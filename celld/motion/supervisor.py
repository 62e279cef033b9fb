"""Supervision of the motion process from the main (asyncio) process.

The supervisor owns the shared-memory channels (they outlive any one motion
process), starts the motion process with the ``spawn`` start method, and
watches it every 20 ms:

- ``CONNECTING`` for longer than the connect timeout: the ur-rtde constructor
  is stuck (it holds the GIL, so the process cannot give up by itself): kill;
- ``RUNNING`` but the state ring has not advanced for the hang timeout: the
  loop is stuck (e.g. in a ur-rtde call that waits for the controller): kill;
- the process exited: read its reason from the status slot, tell the
  listeners (the handle fails the commands in flight), and start a new one
  after a back-off delay that grows with each failure and resets once a
  process has run for a while.

A kill is SIGKILL: nothing is sent after it, and the RTDE watchdog stops the
robot's program. A stop request goes through the control slot; commands
posted before it are cancelled by the loop, never run.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from celld.log import get_logger
from celld.motion.channels import CONTROL_DTYPE, STATUS_DTYPE, Channels, Phase, decode_reason
from celld.motion.process import EXIT_CODES, MotionSpec, main
from celld.motion.types import ControlStatus
from celld.supervision import Backoff, ChildRecords

log = get_logger(__name__)

# How often the supervisor looks at the process, s.
_WATCH_PERIOD = 0.02
# How long a process whose loop has ended may take to close its link and exit, s.
_EXIT_TIMEOUT = 5.0
_CODE_STATUS = {code: status for status, code in EXIT_CODES.items()}


class LinkState(StrEnum):
    """The robot link as the main process sees it."""

    STARTING = "starting"  # the process is starting or connecting
    RUNNING = "running"  # the loop runs
    RESTARTING = "restarting"  # waiting out the back-off before the next start
    STOPPED = "stopped"  # shut down


@dataclass(frozen=True)
class ProcessExit:
    """How a motion process ended."""

    pid: int
    exitcode: int | None  # negative: killed by that signal
    status: ControlStatus
    reason: str
    ran_for: float  # s in RUNNING


@dataclass
class _Proc:
    process: multiprocessing.process.BaseProcess
    started: float
    running_since: float | None = None
    exiting_since: float | None = None
    last_head: int = -1
    last_progress: float = field(default_factory=time.monotonic)
    killed_for: str = ""


class MotionSupervisor:
    """Starts, watches and restarts the motion process.

    Parameters
    ----------
    spec : MotionSpec
        What each motion process runs (the channels must be created first).
    channels : Channels
        The created channels (this side owns them).
    connect_timeout : float
        s a process may spend starting and connecting.
    hang_timeout : float
        s the state ring may stand still while the loop should run.
    backoff : Backoff
    records : ChildRecords, optional
        Where the daemon records its children, so that a successor can clean
        up after a killed daemon.
    """

    def __init__(
        self,
        spec: MotionSpec,
        channels: Channels,
        connect_timeout: float = 10.0,
        hang_timeout: float = 0.5,
        backoff: Backoff = Backoff(),
        records: ChildRecords | None = None,
    ) -> None:
        self.spec = spec
        self.records = records
        # When the supervision last made progress (monotonic s): the systemd watchdog asks.
        self.last_tick = time.monotonic()
        self.ch = channels
        self.connect_timeout = connect_timeout
        self.hang_timeout = hang_timeout
        self.backoff = backoff
        self.state = LinkState.STOPPED
        self.restarts = 0
        self.last_exit: ProcessExit | None = None
        self._ran_since_exit = False  # a process reached RUNNING after last_exit: that end is history
        self._failures = 0
        self._retry = False
        self._proc: _Proc | None = None
        self._task: asyncio.Task[None] | None = None
        self._closing = False
        self._exit_listeners: list[Callable[[ProcessExit], None]] = []
        self._running = asyncio.Event()
        self._ctx = multiprocessing.get_context("spawn")
        self._ctl = np.zeros(1, CONTROL_DTYPE)
        self._status = np.zeros(1, STATUS_DTYPE)

    # -- public ------------------------------------------------------------------

    @property
    def pid(self) -> int | None:
        return self._proc.process.pid if self._proc else None

    def running(self) -> bool:
        """The supervision task runs (started and not finished)."""
        return self._task is not None and not self._task.done()

    def on_exit(self, callback: Callable[[ProcessExit], None]) -> None:
        """Call ``callback(exit)`` in the event loop whenever a motion process ends."""
        self._exit_listeners.append(callback)

    def start(self) -> None:
        """Start supervising (and the first process); returns at once."""
        if self._task is None:
            self._closing = False
            self._task = asyncio.get_running_loop().create_task(self._watch(), name="celld-motion-supervisor")

    async def wait_running(self, timeout: float) -> bool:
        """Wait until a loop runs; False on timeout."""
        try:
            await asyncio.wait_for(self._running.wait(), timeout)
            return True
        except TimeoutError:
            return False

    def status(self) -> np.void:
        """The motion process's last status record (phase, pid, real time, reason)."""
        self.ch.status.read_into(self._status)
        return self._status[0].copy()

    def retry_now(self) -> None:
        """Restart now if waiting to restart, with the back-off reset (the operator cleared a fault)."""
        self._failures = 0
        self._retry = True

    def request_stop(self) -> None:
        """Ask the loop for a jerk-limited stop; commands posted so far are cancelled."""
        self._write_control(stop=True, shutdown=False)

    async def close(self, timeout: float = 3.0) -> None:
        """Stop the robot, end the process (killing it after ``timeout``) and stop supervising."""
        self._closing = True
        proc = self._proc
        if proc is not None and proc.process.is_alive():
            self._write_control(stop=True, shutdown=True)
            deadline = time.monotonic() + timeout
            while proc.process.is_alive() and time.monotonic() < deadline:
                await asyncio.sleep(_WATCH_PERIOD)
            if proc.process.is_alive():
                proc.killed_for = f"did not shut down within {timeout} s"
                self._kill(proc)
        if self._task is not None:
            await self._task
            self._task = None
        self.state = LinkState.STOPPED

    # -- internals ---------------------------------------------------------------

    def _write_control(self, stop: bool, shutdown: bool) -> None:
        self.ch.control.read_into(self._ctl)
        c = self._ctl
        if stop:
            c["stop_epoch"] = int(c["stop_epoch"][0]) + 1
            c["stop_posted"] = self.ch.commands.posted
        c["shutdown"] = shutdown
        self.ch.control.write(c)

    def _spawn(self) -> _Proc:
        # A new process starts without a pending shutdown.
        self._write_control(stop=False, shutdown=False)
        process = self._ctx.Process(target=main, args=(self.spec,), name="celld-motion", daemon=True)
        process.start()
        if self.records is not None and process.pid is not None:
            n = self.spec.channels
            self.records.add(self.spec.role, process.pid, [n.state, n.events, n.commands, n.setpoint, n.control, n.status])
        log.info("motion_process_started", pid=process.pid, host=self.spec.host)
        return _Proc(process, time.monotonic())

    def _kill(self, proc: _Proc) -> None:
        try:
            os.kill(proc.process.pid, signal.SIGKILL)  # type: ignore[arg-type]
        except ProcessLookupError:
            pass

    def outage_cause(self) -> str:
        """Why the link is down now, as the motion process that ended last said: "" when a process has run
        since it ended (the link dropped again and its process has not ended yet, or the link is up)."""
        return "" if self.last_exit is None or self._ran_since_exit else self.last_exit.reason

    def _check(self, proc: _Proc) -> None:
        """Kill a process that is stuck connecting or whose loop stands still."""
        now = time.monotonic()
        st = self.status()
        phase = Phase(int(st["phase"])) if int(st["pid"]) == proc.process.pid else Phase.STARTING
        if phase == Phase.RUNNING:
            if proc.running_since is None:
                proc.running_since = now
                proc.last_progress = now
                self.state = LinkState.RUNNING
                self._running.set()
                self._ran_since_exit = True
            head = self.ch.state.head
            if head != proc.last_head:
                proc.last_head = head
                proc.last_progress = now
            elif now - proc.last_progress > self.hang_timeout and not proc.killed_for and not self._closing:
                proc.killed_for = (
                    f"the motion loop stood still for {(now - proc.last_progress) * 1e3:.0f} ms "
                    "(most likely blocked in a ur-rtde call that waits for the controller)"
                )
                log.error("killing_the_motion_process", pid=proc.process.pid, reason=proc.killed_for)
                self._kill(proc)
        elif phase == Phase.EXITED:
            if proc.exiting_since is None:
                proc.exiting_since = now
            elif now - proc.exiting_since > _EXIT_TIMEOUT and not proc.killed_for:
                proc.killed_for = f"did not exit within {_EXIT_TIMEOUT} s after its loop ended"
                self._kill(proc)
        elif phase in (Phase.STARTING, Phase.CONNECTING, Phase.NONE):
            if now - proc.started > self.connect_timeout and not proc.killed_for:
                proc.killed_for = f"connecting to the robot took longer than {self.connect_timeout} s"
                log.error("killing_the_motion_process", pid=proc.process.pid, reason=proc.killed_for)
                self._kill(proc)

    def _exit_of(self, proc: _Proc) -> ProcessExit:
        code = proc.process.exitcode
        st = self.status()
        own = int(st["pid"]) == proc.process.pid and int(st["phase"]) == int(Phase.EXITED)
        ran = time.monotonic() - proc.running_since if proc.running_since else 0.0
        if own and (code in _CODE_STATUS or proc.exiting_since is not None):
            return ProcessExit(
                proc.process.pid,  # type: ignore[arg-type]
                code,
                ControlStatus(int(st["exit_status"])),
                decode_reason(st["reason"]),
                ran,
            )
        if proc.killed_for:
            reason = f"motion process killed: {proc.killed_for}"
        elif code is not None and code < 0:
            reason = f"motion process died of signal {signal.Signals(-code).name}"
        else:
            reason = f"motion process ended with exit code {code}"
        return ProcessExit(proc.process.pid, code, ControlStatus.LINK_LOST, reason, ran)  # type: ignore[arg-type]

    async def _watch(self) -> None:
        while not self._closing:
            self.state = LinkState.STARTING
            self._running.clear()
            proc = self._proc = self._spawn()
            while proc.process.is_alive():
                self._check(proc)
                self.last_tick = time.monotonic()
                await asyncio.sleep(_WATCH_PERIOD)
            proc.process.join()
            if self.records is not None:
                self.records.remove(self.spec.role)
            end = self._exit_of(proc)
            self.last_exit = end
            self._ran_since_exit = False
            self._running.clear()
            log_fn = log.info if end.status == ControlStatus.OK else log.warning
            log_fn("motion process ended", pid=end.pid, exitcode=end.exitcode, status=end.status.name, reason=end.reason)
            for callback in list(self._exit_listeners):
                callback(end)
            if self._closing:
                break
            self._failures = self.backoff.failures_after(self._failures, end.ran_for)
            delay = self.backoff.delay(self._failures)
            self.state = LinkState.RESTARTING
            self.restarts += 1
            restart_at = time.monotonic() + delay
            self._retry = False
            while time.monotonic() < restart_at and not self._closing and not self._retry:
                self.last_tick = time.monotonic()
                await asyncio.sleep(min(_WATCH_PERIOD, max(restart_at - time.monotonic(), 0.0)))
        self._proc = None
        self.state = LinkState.STOPPED
