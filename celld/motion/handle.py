"""The main process's handle on the robot: an asyncio-friendly client of the motion process.

::

    async with await MotionHandle.open(config) as motion:
        await motion.move_to(T_base_tcp)          # returns when arrived, raises why not
        motion.stream(twist)                      # call at any rate; stale setpoints mean zero
        motion.stop()                             # jerk-limited stop; queued commands are cancelled
        await motion.wait_idle()
        motion.state(), motion.health()

The handle owns a :class:`~celld.motion.supervisor.MotionSupervisor` and one
task that drains the state ring every 20 ms (it holds seconds of records, so
nothing is lost), keeps the latest state and loop timing statistics, resolves
the commands in flight and hands every record batch to listeners (the
recorder, the bus).

A command ends in its status: ``DONE`` returns; a stop request raises
:class:`~celld.errors.MotionError`; a protective stop, e-stop, workspace or
limit breach raises :class:`~celld.errors.SafetyStop`; a lost link, stale
state or a motion process that died raises :class:`~celld.errors.LinkLost`.
Each error carries the reason the loop gave.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import os
import time
from collections import deque
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

# For from_ur_pose in state() and move_to(): celld.se3 imports scipy's Rotation
# where it is used (a config loads without scipy), and a first import there
# (0.3 s and more on a loaded machine) would stall the caller's event loop.
import scipy.spatial.transform  # noqa: F401
from numpy.typing import ArrayLike

from celld.config import Config
from celld.config.power_source import PowerSourceConfig
from celld.errors import CelldError, InputError, LinkLost, MotionError, SafetyStop, StaleState
from celld.log import get_logger, settings
from celld.motion import commands as cmd
from celld.motion.channels import (
    SETPOINT_DTYPE,
    STATE_DTYPE,
    ChannelNames,
    Channels,
    decode_reason,
)
from celld.motion.controllers import MoveParams
from celld.motion.core import CoreParams, Mode, SourceParams
from celld.motion.limits import CartesianLimits, JointMoveLimits, check_twist
from celld.motion.loop import LoopParams
from celld.motion.process import MotionSpec, servo_laws_from
from celld.motion.supervisor import LinkState, MotionSupervisor, ProcessExit
from celld.motion.types import ControlStatus, RobotState, ServoPlan
from celld.realtime import RealtimeOptions
from celld.schemadoc import boolean, enum, integer, number, obj, string
from celld.se3 import from_ur_pose
from celld.supervision import EXIT_NOTE_SUFFIX, Backoff, ChildRecords

log = get_logger(__name__)

# The state ring holds this long of history at the loop rate (at least 2 s is required).
RING_SECONDS = 8.0
# How often the handle drains the ring, s.
DRAIN_PERIOD = 0.02
# The link counts as up while the loop's latest record is at most this many cycles old.
LINK_FRESH_CYCLES = 10
# Loop timing statistics cover this many recent cycles.
STATS_WINDOW = 30_000
_SAFETY = {ControlStatus.SAFETY, ControlStatus.WORKSPACE, ControlStatus.LIMIT}
_LINK = {ControlStatus.LINK_LOST, ControlStatus.STALE_STATE}


class Health(NamedTuple):
    """The robot link and the loop's timing, for the daemon's health check and the bus."""

    link: str  # LinkState value
    pid: int | None
    realtime: bool  # SCHED_FIFO granted to the loop
    cpu: int  # pinned CPU, -1 if none
    restarts: int
    last_exit: str  # reason the last motion process ended, "" if none has
    cycles: int  # records seen from the current and past processes
    lost_records: int  # ring records overwritten before the handle read them
    period_error_p50_ms: float  # |period - nominal| over the last window
    period_error_p99_ms: float
    period_error_p999_ms: float
    period_error_max_ms: float
    late_max_ms: float  # largest wake-up lateness in the window
    late_over_1ms: int  # cycles woken more than 1 ms late, in the window
    overruns: int  # cycles that ended after the next deadline (current process)
    tactile_torn: int  # torn tactile reads (current process)
    heartbeat_age_ms: float  # since the last record arrived


# The JSON shape of Health._asdict() in a health job's result (null where a figure is not finite: nothing measured yet).
HEALTH_SCHEMA = obj(
    "The robot link and the motion loop's timing.",
    {
        "link": enum([s.value for s in LinkState], "The link as the daemon sees it."),
        "pid": integer("The motion process.", null=True),
        "realtime": boolean("SCHED_FIFO granted to the loop."),
        "cpu": integer("The CPU it is pinned to, -1 if none.", lo=-1),
        "restarts": integer(lo=0),
        "last_exit": string("Why the last motion process ended, empty if none has."),
        "cycles": integer("Records seen from the current and past processes.", lo=0),
        "lost_records": integer("Records overwritten before the daemon read them.", lo=0),
        "period_error_p50_ms": number("|period - nominal| over the last window, median.", null=True),
        "period_error_p99_ms": number(null=True),
        "period_error_p999_ms": number(null=True),
        "period_error_max_ms": number(null=True),
        "late_max_ms": number("Largest wake-up lateness in the window.", null=True),
        "late_over_1ms": integer("Cycles woken more than 1 ms late, in the window.", lo=0),
        "overruns": integer("Cycles that ended after the next deadline (current process).", lo=0),
        "tactile_torn": integer("Torn tactile reads (current process).", lo=0),
        "heartbeat_age_ms": number("Since the last record arrived.", null=True),
    },
    Health._fields,
)


def error_for(status: ControlStatus, reason: str) -> CelldError:
    """The exception a command that ended with ``status`` raises."""
    text = reason or f"motion ended with status {status.name}"
    if status in _SAFETY:
        return SafetyStop(text)
    if status == ControlStatus.STALE_STATE:
        return StaleState(text)
    if status in _LINK:
        return LinkLost(text)
    return MotionError(text)


def spec_from_config(
    config: Config,
    names: ChannelNames,
    host: str | None = None,
    servo_laws: dict[str, str] | None = None,
    realtime: RealtimeOptions = RealtimeOptions(),
    move: MoveParams = MoveParams(),
    link_timeout: float = 0.1,
    watchdog_hz: float = 10.0,
    heartbeat: str = "",
) -> MotionSpec:
    """Build the motion process's spec from a validated config.

    ``link_timeout`` (s without fresh robot state before the link counts as
    lost) and ``watchdog_hz`` (the robot stops its program 1/watchdog_hz s
    after the last write) are the link's bounds. The process watches this
    one (its parent) and, with ``heartbeat``, that heartbeat slot
    (``motion.parent_timeout``), and stops the robot and ends without them.
    """
    robot, motion = config.robot, config.motion
    period = 1.0 / robot.frequency_hz
    limits = CartesianLimits.from_config(motion)
    joint_limits = JointMoveLimits.from_config(motion)
    return MotionSpec(
        host=host or robot.host,
        channels=names,
        core=CoreParams(
            limits=limits,
            period=period,
            workspace_min=robot.workspace_min,
            workspace_max=robot.workspace_max,
            state_stale=motion.state_stale_cycles * period,
            tactile_stale=motion.tactile_stale,
            move=move,
            joint_limits=joint_limits,
            source=source_params(config.power_source),
        ),
        loop=LoopParams(
            period_ns=int(round(period * 1e9)),
            # speedL's own ramp must never clip the limiter's profile.
            speed_accel=2.0 * max(limits.linear_accel, limits.angular_accel),
            joint_speed_accel=2.0 * joint_limits.accel,
            link_timeout_ns=int(link_timeout * 1e9),
            process_output=robot.arc_output,
            hang_timeout_ns=int(motion.hang_stop * 1e9) if heartbeat else 0,
        ),
        frequency_hz=robot.frequency_hz,
        watchdog_hz=watchdog_hz,
        realtime=realtime,
        servo_laws=servo_laws_from(servo_laws or {}),
        log_level=settings().level,  # the process logs as its daemon does
        log_json=settings().json,
        parent_pid=os.getpid(),
        heartbeat=heartbeat,
        parent_timeout_ns=int(motion.parent_timeout * 1e9),
        link_nice=motion.link_nice,
        source=config.power_source if config.power_source.enabled else None,
    )


def source_params(source: PowerSourceConfig) -> SourceParams | None:
    """What the motion core knows of the cell's power source (None: the cell has none)."""
    if not source.enabled:
        return None
    return SourceParams(
        has_process_active=source.signal("process_active") is not None,
        has_heartbeat=source.signal("heartbeat") is not None,
        heartbeat_timeout=source.heartbeat_timeout,
    )


class _Pending(NamedTuple):
    future: asyncio.Future[ControlStatus]
    reason: list[str]


class MotionHandle:
    """See the module docstring. Create with :meth:`open`."""

    def __init__(
        self,
        supervisor: MotionSupervisor,
        channels: Channels,
        limits: CartesianLimits,
        workspace: tuple[tuple[float, ...], tuple[float, ...]],
    ) -> None:
        self.supervisor = supervisor
        self.ch = channels
        self.limits = limits
        self.workspace = workspace
        self._seq = 0
        self._event_seq = 0
        self._lost = 0
        self._cycles = 0
        self._last_record: np.void | None = None
        self._last_record_t = 0.0
        self._fresh_ns = LINK_FRESH_CYCLES * supervisor.spec.loop.period_ns
        self._periods: deque[np.ndarray] = deque()
        self._period_count = 0
        self._pending: dict[int, _Pending] = {}
        self._reasons: dict[int, tuple[ControlStatus, str]] = {}
        # Reasons of the loop's events about no command (the latest 32), e.g. a failed arc write.
        self.loop_events: deque[str] = deque(maxlen=32)
        self.loop_event_count = 0  # all of them so far
        self._listeners: list[Callable[[np.ndarray], None]] = []
        self._stream_id = 0
        self._stream_timeout = 0.1
        self._sp = np.zeros(1, SETPOINT_DTYPE)
        self._task: asyncio.Task[None] | None = None
        self._period_ns = supervisor.spec.loop.period_ns
        supervisor.on_exit(self._on_exit)

    # -- life cycle ------------------------------------------------------------

    @classmethod
    async def open(
        cls,
        config: Config,
        *,
        host: str | None = None,
        servo_laws: dict[str, str] | None = None,
        tactile_slot: str | None = None,
        realtime: RealtimeOptions = RealtimeOptions(),
        move: MoveParams = MoveParams(),
        connect_timeout: float | None = None,
        hang_timeout: float = 0.5,
        link_timeout: float = 0.1,
        watchdog_hz: float = 10.0,
        backoff: Backoff = Backoff(),
        wait: bool = True,
        heartbeat: str = "",
        records: ChildRecords | None = None,
        role: str = "motion",
    ) -> MotionHandle:
        """Create the channels, start the motion process and (by default) wait for its loop.

        ``tactile_slot`` names the tactile process's seqlock slot; without it
        the handle creates one (tests write samples into it). ``heartbeat``
        names the daemon's heartbeat slot the process watches, ``records``
        where the daemon records its children, ``role`` its name there (where
        it also leaves its exit note). Raises LinkLost when the loop does not
        run within the connect timeout.
        """
        capacity = int(math.ceil(RING_SECONDS * config.robot.frequency_hz))
        names = ChannelNames.unique(capacity, tactile_slot)
        channels = Channels.create(names, create_tactile=tactile_slot is None)
        try:
            spec = spec_from_config(config, names, host, servo_laws, realtime, move, link_timeout, watchdog_hz, heartbeat=heartbeat)
            note = str(records.dir / (role + EXIT_NOTE_SUFFIX)) if records is not None else ""
            spec = dataclasses.replace(spec, role=role, exit_note=note)
            timeout = connect_timeout if connect_timeout is not None else config.robot.connect_timeout
            sup = MotionSupervisor(spec, channels, timeout, hang_timeout, backoff, records)
            handle = cls(sup, channels, spec.core.limits, (spec.core.workspace_min, spec.core.workspace_max))
            sup.start()
            handle._task = asyncio.get_running_loop().create_task(handle._drain_forever(), name="celld-motion-drain")
        except BaseException:
            channels.close()
            channels.unlink()
            raise
        if wait and not await handle.wait_ready(timeout + 5.0):
            reason = sup.last_exit.reason if sup.last_exit else "no reply"
            await handle.close()
            raise LinkLost(f"robot {spec.host}: the motion loop did not start: {reason}")
        return handle

    async def wait_ready(self, timeout: float) -> bool:
        """Wait until the loop runs and its first state has been read; False on timeout."""
        deadline = time.monotonic() + timeout
        if not await self.supervisor.wait_running(timeout):
            return False
        seen = self._cycles
        while self._cycles == seen or self.supervisor.state != LinkState.RUNNING:
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(DRAIN_PERIOD)
        return True

    async def close(self) -> None:
        """Stop the robot, end the motion process and release the channels."""
        await self.supervisor.close()
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None
        self._drain()
        self._fail_all(MotionError("the motion handle was closed"))
        self.ch.close()
        self.ch.unlink()

    async def __aenter__(self) -> MotionHandle:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- commands ----------------------------------------------------------------

    def _require_link(self) -> None:
        if self.supervisor.state != LinkState.RUNNING:
            last = self.supervisor.last_exit
            why = f": {last.reason}" if last else ""
            raise LinkLost(f"the robot link is {self.supervisor.state.value}{why}")

    def _post(self, command: cmd.Command) -> int:
        self._require_link()
        cid = self.ch.commands.post(cmd.encode(command))
        return cid

    def _track(self, cid: int) -> asyncio.Future[ControlStatus]:
        fut: asyncio.Future[ControlStatus] = asyncio.get_running_loop().create_future()
        self._pending[cid] = _Pending(fut, [""])
        return fut

    async def _arrive(self, command: cmd.Command, what: str, timeout: float | None) -> RobotState:
        """Post a move, wait for it to end, and return the state on arrival or raise why it did not."""
        cid = self._post(command)
        fut = self._track(cid)
        try:
            status = await asyncio.wait_for(asyncio.shield(fut), timeout)
        except TimeoutError:
            self.stop()
            raise MotionError(f"{what} did not arrive within {timeout} s; the robot was stopped") from None
        if status != ControlStatus.DONE:
            raise error_for(status, self._pending_reason(cid))
        state = self.state()
        if state is None:  # cannot happen: a DONE record was read
            raise MotionError(f"{what} arrived but no robot state was read")
        return state

    async def move_to(
        self,
        target: ArrayLike,
        speed_scale: float = 1.0,
        tolerance: float = 5e-5,
        angle_tolerance: float = 5e-4,
        timeout: float | None = None,
    ) -> RobotState:
        """Move the TCP straight to ``target`` and return the state on arrival.

        Parameters
        ----------
        target : array, shape (4, 4) or (6,)
            ``T_base_tcp``, or a UR pose ``[x, y, z, rx, ry, rz]`` (m, rad).
        speed_scale : float
            0 < speed_scale <= 1, applied to every configured limit.
        tolerance, angle_tolerance : float
            Arrival tolerances, m and rad.
        timeout : float, optional
            s to wait before stopping the robot and raising MotionError.

        Raises
        ------
        InputError
            The target is malformed or outside the workspace box.
        SafetyStop, LinkLost, MotionError
            The move did not arrive; the message says why.
        """
        arr = np.asarray(target, dtype=np.float64)
        T = from_ur_pose(arr) if arr.shape == (6,) else arr
        command = cmd.move_to(T, speed_scale, tolerance, angle_tolerance)
        lo, hi = self.workspace
        p = command.T_base_tcp[:3, 3]
        if not all(lo[i] <= p[i] <= hi[i] for i in range(3)):
            raise InputError(f"move_to target {np.round(p, 4).tolist()} m lies outside the workspace box {list(lo)} .. {list(hi)}")
        return await self._arrive(command, "move_to", timeout)

    async def move_joints(
        self,
        q_goal: ArrayLike,
        speed_scale: float = 1.0,
        tolerance: float = 5e-5,
        timeout: float | None = None,
        rest_timeout: float = 5.0,
    ) -> RobotState:
        """Move the joints straight in joint space to ``q_goal`` (rad) and return the state on arrival.

        A joint move starts from rest: this waits up to ``rest_timeout`` s for
        the loop to hold still first. The caller checks the path and the
        goal's TCP against the cell (:class:`celld.daemon.planning.MotionPlanner`);
        ``speed_scale`` scales every joint limit.

        Raises
        ------
        InputError
            ``q_goal`` is not 6 finite joint positions within +-2 pi.
        SafetyStop, LinkLost, MotionError
            The move did not arrive; the message says why.
        """
        command = cmd.move_joints(q_goal, speed_scale, tolerance)
        await self.wait_idle(rest_timeout)
        return await self._arrive(command, "move_joints", timeout)

    def stream(self, twist: ArrayLike, timeout: float = 0.1) -> None:
        """Set the streamed twist (6,) (base frame, m/s and rad/s); starts streaming if needed.

        The loop follows the latest setpoint through the limiter; a setpoint
        older than ``timeout`` s counts as zero, so a caller that stops
        calling brings the robot to rest. :meth:`stop` ends streaming; the
        next call starts it again.

        Raises
        ------
        InputError
            ``twist`` is not 6 finite numbers.
        LinkLost
            The robot link is not running (the reason of the last exit is given).
        """
        t = check_twist(twist)
        self._sp["t_ns"] = time.monotonic_ns()
        self._sp["twist"] = t
        self.ch.setpoint.write(self._sp)
        if self._stream_ended() or timeout != self._stream_timeout:
            self._stream_id = self._post(cmd.stream(timeout))
            self._stream_timeout = timeout

    def _stream_ended(self) -> bool:
        """True unless our stream command is queued or being served."""
        sid = self._stream_id
        if sid == 0 or sid in self._reasons:
            return True
        rec = self._last_record
        if rec is None or int(rec["command_id"]) < sid:
            return False  # posted, not yet taken up
        return not (int(rec["command_id"]) == sid and int(rec["mode"]) == int(Mode.ACTIVE))

    async def start_servo(self, plan: ServoPlan) -> int:
        """Start the servo law ``plan.name`` with ``plan``; return its command id for :meth:`wait`."""
        cid = self._post(cmd.start_servo(plan))
        self._track(cid)
        return cid

    async def wait(self, command_id: int, timeout: float | None = None) -> ControlStatus:
        """Wait until command ``command_id`` ends; return DONE or raise why it did not."""
        pending = self._pending.get(command_id)
        if pending is None:
            raise InputError(f"no command {command_id} is being tracked")
        status = await asyncio.wait_for(asyncio.shield(pending.future), timeout)
        if status != ControlStatus.DONE:
            raise error_for(status, self._pending_reason(command_id))
        return status

    def stop(self) -> None:
        """Request a jerk-limited stop now; commands posted before it never run."""
        self.supervisor.request_stop()

    async def wait_idle(self, timeout: float = 5.0) -> None:
        """Wait until the loop holds still (after a stop or the end of a motion)."""
        deadline = time.monotonic() + timeout
        seen = self._cycles
        while True:
            rec = self._last_record
            if rec is not None and self._cycles > seen and int(rec["mode"]) == int(Mode.IDLE):
                return
            if time.monotonic() > deadline:
                raise MotionError(f"the robot did not come to rest within {timeout} s")
            await asyncio.sleep(DRAIN_PERIOD)

    # -- state ---------------------------------------------------------------------

    def add_listener(self, callback: Callable[[np.ndarray], None]) -> None:
        """Call ``callback(records)`` with every batch of :data:`STATE_DTYPE` records read."""
        self._listeners.append(callback)

    def remove_listener(self, callback: Callable[[np.ndarray], None]) -> None:
        """Stop calling ``callback`` (no error if it was not added)."""
        if callback in self._listeners:
            self._listeners.remove(callback)

    def last_record(self) -> np.void | None:
        """The latest state record (:data:`~celld.motion.channels.STATE_DTYPE`), a copy."""
        return None if self._last_record is None else self._last_record.copy()

    def state(self) -> RobotState | None:
        """The latest robot state read by the loop, or None before the first."""
        rec = self._last_record
        if rec is None:
            return None
        return RobotState(
            int(rec["t_ns"]), np.array(rec["q"]), np.array(rec["qd"]), from_ur_pose(rec["tcp_pose"]), np.array(rec["tcp_speed"])
        )

    def process_running(self) -> bool:
        """True while the motion process runs its loop (the supervisor's view: not starting, restarting or
        stopped), fresh records or not."""
        return self.supervisor.state == LinkState.RUNNING

    def link_running(self) -> bool:
        """True while the motion loop runs: its process is up and its latest record is fresh (cheap).

        Read from the state ring itself, not from what the drain task last
        collected, so it follows the loop within :data:`LINK_FRESH_CYCLES`
        cycles even while the event loop is busy.
        """
        if self.supervisor.state != LinkState.RUNNING:
            return False
        last = self.ch.state.latest(1)
        if len(last) == 0:
            return False
        return time.monotonic_ns() - int(last["t_ns"][0]) <= self._fresh_ns

    def heartbeat_age(self) -> float:
        """Seconds since the last state record arrived (inf before the first); cheap."""
        return time.monotonic() - self._last_record_t if self._last_record_t else math.inf

    def health(self) -> Health:
        """Link state and loop timing over the last :data:`STATS_WINDOW` cycles."""
        sup = self.supervisor
        st = sup.status()
        rec = self._last_record
        periods = np.concatenate(list(self._periods)) if self._periods else np.zeros(0, STATE_DTYPE)
        err = np.abs(periods["period_ns"].astype(np.float64) - self._period_ns) * 1e-6
        err = err[periods["period_ns"] > 0]
        late = periods["late_ns"].astype(np.float64) * 1e-6

        def pct(q: float) -> float:
            return float(np.percentile(err, q)) if len(err) else math.nan

        return Health(
            link=sup.state.value,
            pid=sup.pid,
            realtime=bool(st["realtime"]),
            cpu=int(st["cpu"]),
            restarts=sup.restarts,
            last_exit=sup.last_exit.reason if sup.last_exit else "",
            cycles=self._cycles,
            lost_records=self._lost,
            period_error_p50_ms=pct(50),
            period_error_p99_ms=pct(99),
            period_error_p999_ms=pct(99.9),
            period_error_max_ms=float(err.max()) if len(err) else math.nan,
            late_max_ms=float(late.max()) if len(late) else math.nan,
            late_over_1ms=int(np.count_nonzero(late > 1.0)),
            overruns=int(rec["overruns"]) if rec is not None else 0,
            tactile_torn=int(rec["tactile_torn"]) if rec is not None else 0,
            heartbeat_age_ms=self.heartbeat_age() * 1e3,
        )

    # -- draining ------------------------------------------------------------------

    def _pending_reason(self, cid: int) -> str:
        got = self._reasons.get(cid)
        return got[1] if got else ""

    async def _drain_forever(self) -> None:
        while True:
            self._drain()
            await asyncio.sleep(DRAIN_PERIOD)

    def _drain(self) -> None:
        records, self._seq, lost = self.ch.state.read_since(self._seq)
        self._lost += lost
        # Events after the state: an event is written before the record that ends its command.
        events, self._event_seq, _ = self.ch.events.read_since(self._event_seq)
        for e in events:
            cid = int(e["command_id"])
            if cid == 0:
                # About no command: the loop's own trouble (e.g. the arc output could not be switched).
                log.error("motion_loop_event", status=ControlStatus(int(e["status"])).name, reason=decode_reason(e["reason"]))
                self.loop_events.append(decode_reason(e["reason"]))
                self.loop_event_count += 1
                continue
            self._reasons[cid] = (ControlStatus(int(e["status"])), decode_reason(e["reason"]))
        if len(records):
            self._cycles += len(records)
            self._last_record = records[-1].copy()
            self._last_record_t = time.monotonic()
            self._periods.append(records[["period_ns", "late_ns"]].copy())
            self._period_count += len(records)
            while self._period_count - len(self._periods[0]) >= STATS_WINDOW:
                self._period_count -= len(self._periods.popleft())
            for callback in self._listeners:
                callback(records)
        self._resolve(records)

    def _resolve(self, records: np.ndarray) -> None:
        if not self._pending:
            return
        ids = records["command_id"].astype(np.int64) if len(records) else np.zeros(0, np.int64)
        for cid, pending in list(self._pending.items()):
            if pending.future.done():
                del self._pending[cid]
                continue
            status: ControlStatus | None = None
            mine = ids == cid
            if np.any(mine & (records["mode"] == int(Mode.IDLE))):
                status = ControlStatus(int(records["status"][mine & (records["mode"] == int(Mode.IDLE))][0]))
            elif np.any(ids > cid):
                if cid not in self._reasons:
                    self._reasons[cid] = (ControlStatus.STOPPED, f"superseded by command {int(ids[ids > cid][0])}")
                status = self._reasons[cid][0]
            elif cid in self._reasons and not np.any(mine) and self._reasons[cid][0] != ControlStatus.DONE:
                # Refused or cancelled before it ever ran.
                status = self._reasons[cid][0]
            if status is not None:
                pending.future.set_result(status)
                del self._pending[cid]

    def _fail_all(self, exc: CelldError) -> None:
        for pending in self._pending.values():
            if not pending.future.done():
                pending.future.set_exception(exc)
        self._pending.clear()

    def _on_exit(self, end: ProcessExit) -> None:
        self._drain()
        self._stream_id = 0
        exc = error_for(end.status if end.status != ControlStatus.OK else ControlStatus.LINK_LOST, end.reason)
        self._fail_all(exc)
