"""One cycle of the motion loop as a pure state machine: inputs in, what to send out.

:class:`MotionCore` holds the active controller, the twist limiter and the
safety monitors. The loop (:mod:`celld.motion.loop`) feeds it the robot state,
the latest tactile sample and setpoint, a newly taken command and a stop
request, and sends what it returns. No clock, socket or shared memory here, so
every behaviour can be tested by stepping it.

Modes::

    IDLE ──command──▶ ACTIVE ──done / fault / stop request──▶ STOPPING ──at rest──▶ IDLE
     ▲                  │ a new command takes over smoothly                        │
     └──────────────────┴──── the robot stops itself (protective stop, e-stop) ◀───┘

- IDLE: the robot is at rest and nothing but watchdog kicks is sent.
- ACTIVE: the controller's demand, shaped by the limiter, is sent as speedL.
- STOPPING: the limiter ramps the twist to zero (jerk-limited) and the last
  speedL sends exactly zero; the status then tells why the motion ended. The
  robot's speedl keeps that zero twist, so no speedStop is needed: ur-rtde
  treats speedStop as a non-real-time command that blocks until the
  controller reports it done, which has no place in a 2 ms cycle.

A joint move (:mod:`celld.motion.joint_move`) runs the same modes in joint
space: its own planner gives the joint speeds, sent as speedJ, and its own
stop brakes them to zero; the joint speeds sent are checked per joint, and
the workspace box with the measured TCP twist. It starts only from IDLE, and
no other command is taken while it runs (a stop request ends it).

The process output (the welding arc) is the servo law's to ask for and the
core's to grant: ``CycleOutput.process_on`` is True only while the mode is
ACTIVE with no fault, the controller is the servo slot, and the law's
telemetry says ``process_on``. It drops on the cycle a stop begins (a stop
request, a fault, the law's own DONE or fault), when the robot stops itself,
and whenever another command takes over. The loop switches the output.

With a welding power source (``CoreParams.source``) a servo whose plan asks
for the process runs with the weld's arc sequence (:mod:`celld.motion.arc`):
the law's wish starts it, its travel gate goes to the law each cycle
(``ServoInput.travel``: the torch comes to rest at the seam's start, holds
while the arc is not established, backs off before a re-strike), the law's
DONE waits at rest until the sequence has closed the seam, and a sequence
that failed (no arc, a source fault, a stuck wire) ends the servo with
``ARC``. Every stop aborts it: the arc off at once. No command starts while
the source says the wire is stuck, no weld while it is not ready or
faulted, and no motion while the torch's collision input is set (a stop of
the one running).

Every record carries the command id it serves and a status; the status of a
finished command stays until the next command, so a reader that comes late
still learns how it ended.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import IntEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from celld.config import MotionLimits
from celld.errors import InputError
from celld.motion.arc import ArcOutput, ArcPhase, ArcSequence, SourceSignals, params_of
from celld.motion.commands import Command, MoveJoints, MoveTo, StartServo, Stream
from celld.motion.controllers import (
    CartesianMove,
    ControlInput,
    Controller,
    Hold,
    MoveParams,
    ServoSlot,
    VelocityStream,
)
from celld.motion.joint_move import JointMove
from celld.motion.limits import CartesianLimits, JointMoveLimits, LimiterResult, TwistLimiter
from celld.motion.safety import (
    LIMITS,
    ROBOT_STOPPED,
    Fault,
    JointSequenceMonitor,
    SequenceMonitor,
    WorkspaceGuard,
    describe,
    inside,
    robot_faults,
    status_of,
)
from celld.motion.types import NO_TELEMETRY, ControlStatus, RobotState, ServoFactory, ServoTelemetry
from celld.tactile.sample import TactileSample

Array = NDArray[np.float64]

_ZERO6 = np.zeros(6)
_ZERO3 = np.zeros(3)
# Shortest time between two cycles the limiter and the monitors step over, s (two on one clock tick).
_MIN_SPACING = 1e-6
# What the power source is told while no weld has been sequenced.
_ARC_IDLE = ArcOutput(False, False, 0.0, 0.0, 0, ArcPhase.OFF)


class Mode(IntEnum):
    IDLE = 0
    ACTIVE = 1
    STOPPING = 2


class Action(IntEnum):
    """What the loop sends this cycle."""

    KICK = 0  # nothing but a watchdog kick
    SPEED = 1  # speedL(twist)
    SPEED_J = 2  # speedJ(joint speeds)


class SourceParams(NamedTuple):
    """What the core knows of the cell's welding power source (:mod:`celld.motion.arc`)."""

    has_process_active: bool = False
    has_heartbeat: bool = False
    heartbeat_timeout: float = 2.5  # s


class CoreParams(NamedTuple):
    """Everything the core needs to know about the cell (SI)."""

    limits: CartesianLimits
    period: float  # s
    workspace_min: tuple[float, float, float]
    workspace_max: tuple[float, float, float]
    state_stale: float  # s; older robot state stops the motion
    tactile_stale: float  # s; an older tactile sample stops the servo
    latency: float = 0.004  # s from a command to its effect in the measured state
    move: MoveParams = MoveParams()
    joint_limits: JointMoveLimits = JointMoveLimits.from_config(MotionLimits())
    # The cell's welding power source; None: the arc is the process output alone (the law's wish).
    source: SourceParams | None = None


class CycleInput(NamedTuple):
    """What the loop hands the core each cycle."""

    state: RobotState
    state_age: float  # s since the robot state last changed
    safety_bits: int  # UR safety_status_bits
    tactile: TactileSample | None
    tactile_age: float  # s, inf without a sample
    setpoint: Array  # (6,) streaming twist
    setpoint_age: float  # s, inf without a setpoint
    command: Command | None = None  # a command taken from the mailbox this cycle
    command_id: int = 0  # its mailbox sequence number
    command_error: str = ""  # why the command with command_id could not be decoded
    stop: bool = False  # the supervisor asked for a stop this cycle
    stop_reason: str = ""  # why, when not on request (the daemon hung or is gone)
    source: SourceSignals | None = None  # the power source's inputs, None without a source
    collision: bool = False  # the torch's collision input (a stop of any motion)


class CycleOutput(NamedTuple):
    """What to send, and what to record."""

    action: Action
    twist: Array  # (6,) the twist sent with SPEED, the joint speeds (rad/s) with SPEED_J, zero otherwise
    mode: Mode
    status: ControlStatus
    command_id: int  # the command this cycle serves (or last served)
    faults: Fault
    guarded: bool  # the limiter's viability guard acted
    event: str  # why a command ended badly or was refused ("" most cycles)
    event_id: int  # the command the event is about
    event_status: ControlStatus
    process_on: bool = False  # the process output (welding arc) should be on (module docstring)
    telemetry: ServoTelemetry = NO_TELEMETRY  # the servo law's, NO_TELEMETRY without a servo
    arc: ArcOutput | None = None  # what the power source is told this cycle, None without a source


class MotionCore:
    """The motion loop's per-cycle logic (module docstring).

    Parameters
    ----------
    params : CoreParams
    servo_factories : mapping of str to ServoFactory
        The servo laws this process can run, by plan name.
    """

    def __init__(self, params: CoreParams, servo_factories: Mapping[str, ServoFactory] | None = None) -> None:
        self.params = params
        self.factories = dict(servo_factories or {})
        self.limiter = TwistLimiter(params.limits, params.period)
        self.monitor = SequenceMonitor(params.limits, params.period)
        self.joint_monitor = JointSequenceMonitor(params.joint_limits, params.period)
        # The breach is found after this cycle's twist went out: one more period of travel.
        self.workspace = WorkspaceGuard(params.workspace_min, params.workspace_max, params.limits, params.latency + params.period)
        self._last_ns = -1  # the last cycle's state stamp; -1 before the first
        self._dt = params.period  # s since the cycle before this one
        self.mode = Mode.IDLE
        self.controller: Controller | JointMove = Hold()
        self.command_id = 0
        self.status = ControlStatus.HOLD
        self._stop_status = ControlStatus.STOPPED
        self._stop_reason = ""
        self._event = ""
        self._event_id = 0
        self._event_status = ControlStatus.OK
        # The power source's sequence of the latest weld (kept after it ends: its gas may still post-flow).
        self.arc: ArcSequence | None = None
        self._arc_servo: ServoSlot | None = None  # the servo whose weld ``arc`` sequences
        self._law_done = False  # that servo's law reported DONE last cycle
        self._t = 0.0  # this cycle's state stamp, s
        self._sig: SourceSignals | None = None
        self._last_telemetry = NO_TELEMETRY  # the telemetry of the last cycle's output (the law's wish then)

    # -- transitions ----------------------------------------------------------

    def _refuse(self, command_id: int, status: ControlStatus, reason: str) -> None:
        self._event, self._event_id, self._event_status = reason, command_id, status

    def _begin_stop(self, status: ControlStatus, reason: str) -> None:
        if self.mode != Mode.ACTIVE:
            return
        if self.arc is not None and self.arc.active:
            self.arc.abort(self._t, reason)
        self.mode = Mode.STOPPING
        self._stop_status = status
        self._stop_reason = reason
        if isinstance(self.controller, JointMove):
            self.controller.begin_stop()

    def _refusal(self, cmd: Command) -> tuple[ControlStatus, str] | None:
        """Why ``cmd`` cannot start here, or None."""
        p = self.params
        if isinstance(self.controller, JointMove):
            return ControlStatus.BAD_COMMAND, (
                f"a joint move (command {self.command_id}) is running: it takes no other command; stop it first"
            )
        if isinstance(cmd, MoveJoints) and self.mode != Mode.IDLE:
            return ControlStatus.BAD_COMMAND, (
                f"a joint move starts from rest: command {self.command_id} is still {self.mode.name.lower()}"
            )
        if isinstance(cmd, MoveTo) and not inside(cmd.T_base_tcp[:3, 3], p.workspace_min, p.workspace_max):
            return ControlStatus.WORKSPACE, (
                f"move_to target {np.round(cmd.T_base_tcp[:3, 3], 4).tolist()} m lies outside the workspace "
                f"box {list(p.workspace_min)} .. {list(p.workspace_max)}"
            )
        if isinstance(cmd, StartServo) and cmd.plan.name not in self.factories:
            known = ", ".join(sorted(self.factories)) or "none"
            return ControlStatus.BAD_COMMAND, f"no servo law registered as {cmd.plan.name!r}; known: {known}"
        sig = self._sig
        if sig is not None:
            if sig.wire_stuck:
                return ControlStatus.ARC, "the wire is stuck in the pool (the source's wire_stuck input): no motion until it is cut"
            if isinstance(cmd, StartServo) and cmd.plan.params.get("process"):
                if sig.fault:
                    return ControlStatus.ARC, "the power source reports a fault: no weld starts until it is cleared"
                if not sig.ready:
                    return ControlStatus.ARC, "the power source is not ready: no weld starts"
        return None

    def _build(self, cmd: Command) -> Controller | JointMove:
        p = self.params
        if isinstance(cmd, MoveTo):
            return CartesianMove(cmd.T_base_tcp, p.limits, p.period, cmd.speed_scale, cmd.tolerance, cmd.angle_tolerance, p.move)
        if isinstance(cmd, MoveJoints):
            return JointMove(cmd.q_goal, p.joint_limits, p.period, cmd.speed_scale, cmd.tolerance)
        if isinstance(cmd, Stream):
            return VelocityStream(cmd.timeout)
        if isinstance(cmd, StartServo):
            slot = ServoSlot(self.factories[cmd.plan.name](cmd.plan), cmd.plan.name)
            if p.source is not None and cmd.plan.params.get("process"):
                try:
                    arc_params = params_of(cmd.plan.params)._replace(heartbeat_timeout=p.source.heartbeat_timeout)
                except ValueError as exc:
                    raise InputError(f"the weld's arc sequence: {exc}") from exc
                self.arc = ArcSequence(arc_params, p.source.has_process_active, p.source.has_heartbeat)
                self._arc_servo = slot
                self._law_done = False
                self._last_telemetry = NO_TELEMETRY  # not the wish of the law it takes over from
            return slot
        raise InputError(f"unknown command {type(cmd).__name__}")

    def _accept(self, inp: CycleInput, faults: Fault) -> None:
        cid = inp.command_id
        if inp.command_error:
            self._refuse(cid, ControlStatus.BAD_COMMAND, inp.command_error)
            return
        if faults & Fault.STALE_STATE:
            self._refuse(cid, ControlStatus.STALE_STATE, "robot state is stale: no motion can start")
            return
        if faults & Fault.COLLISION:
            self._refuse(cid, ControlStatus.COLLISION, "the torch's collision input is set: no motion until the torch is reseated")
            return
        refusal = self._refusal(inp.command)  # type: ignore[arg-type]
        if refusal is not None:
            self._refuse(cid, *refusal)
            return
        try:
            ctrl = self._build(inp.command)  # type: ignore[arg-type]
        except InputError as exc:  # a servo factory refused its plan
            self._refuse(cid, ControlStatus.BAD_COMMAND, str(exc))
            return
        except Exception as exc:  # a servo factory must not take the loop down  # noqa: BLE001
            self._refuse(cid, ControlStatus.BAD_COMMAND, f"building the controller failed: {exc!r}")
            return
        if self.mode == Mode.IDLE:
            self.limiter.reset()
            self.monitor.reset()
            self.joint_monitor.reset()
        if isinstance(ctrl, JointMove):
            ctrl.start(inp.state, self.limiter.twist, self.limiter.accel, since=self._dt)
        else:
            ctrl.start(inp.state, self.limiter.twist, self.limiter.accel)
        self.controller = ctrl
        self.command_id = cid
        self.mode = Mode.ACTIVE
        self.status = ControlStatus.OK

    # -- the cycle ------------------------------------------------------------

    def step(self, inp: CycleInput) -> CycleOutput:
        """Advance one cycle."""
        self._event = ""
        p = self.params
        # The time since the last cycle's command went out: the robot held it that long. The limiter
        # and the monitors work over it, so a late cycle does not leave what is sent behind the clock.
        stamp = inp.state.stamp_ns
        # (A stamp that does not advance measures nothing: one period then.)
        dt = (stamp - self._last_ns) * 1e-9 if 0 <= self._last_ns < stamp else p.period
        dt = max(dt, _MIN_SPACING)
        self._last_ns = stamp
        self._dt = dt
        self._t = stamp * 1e-9
        self._sig = inp.source
        faults = robot_faults(inp.safety_bits)
        if inp.state_age > p.state_stale:
            faults |= Fault.STALE_STATE
        if inp.collision:
            faults |= Fault.COLLISION

        if faults & ROBOT_STOPPED:
            # The robot has stopped by itself; nothing we send would move it.
            if self.mode != Mode.IDLE:
                self._refuse(self.command_id, ControlStatus.SAFETY, f"the robot stopped itself: {describe(faults)}")
                self.status = ControlStatus.SAFETY
            if self.arc is not None and self.arc.active:
                self.arc.abort(self._t, f"the robot stopped itself: {describe(faults)}")
            self.mode = Mode.IDLE
            self.controller = Hold()
            self.limiter.reset()
            self.monitor.reset()
            self.joint_monitor.reset()
            if inp.command is not None or inp.command_error:
                self._refuse(inp.command_id, ControlStatus.SAFETY, f"refused: the robot reports {describe(faults)}")
            return self._output(Action.KICK, _ZERO6, faults, False)

        if inp.stop:
            self._begin_stop(ControlStatus.STOPPED, inp.stop_reason or "stopped on request")
        if inp.command is not None or inp.command_error:
            self._accept(inp, faults)
        if isinstance(self.controller, JointMove):
            return self._step_joint(self.controller, inp, faults)

        twist: Array = _ZERO6
        guarded = False
        welding = self.arc is not None and self.controller is self._arc_servo and self.mode == Mode.ACTIVE
        travel = self._step_arc(inp, welding)
        if self.mode == Mode.ACTIVE:
            cinp = ControlInput(inp.state, inp.tactile, inp.tactile_age, inp.setpoint, inp.setpoint_age, travel)
            demand, status = self.controller.step(cinp)
            if isinstance(self.controller, ServoSlot) and inp.tactile_age > p.tactile_stale:
                faults |= Fault.STALE_TACTILE
            if welding and self.arc is not None:
                # The seam's end is the sequence's to close (crater, burn-back, post-flow, the wire's check):
                # the arm holds at rest until it has, then the servo ends as the sequence says.
                self._law_done = status == ControlStatus.DONE
                if self._law_done and self.arc.active:
                    status = ControlStatus.OK
                elif self.arc.phase == ArcPhase.DONE and status < ControlStatus.WORKSPACE:
                    status = ControlStatus.DONE
                elif self.arc.phase in (ArcPhase.FAILED, ArcPhase.STUCK) and status < ControlStatus.WORKSPACE:
                    status = ControlStatus.ARC
                    self.controller.reason = self.arc.reason
            if status == ControlStatus.DONE or status >= ControlStatus.WORKSPACE:
                self._begin_stop(status, self.controller.reason)
            elif faults:
                self._begin_stop(status_of(faults), describe(faults))
            else:
                twist, result = self.limiter.step(demand.twist, demand.accel, dt)
                guarded = result == LimiterResult.GUARDED
                if result == LimiterResult.ERROR:
                    faults |= Fault.SPEED
                    self._begin_stop(ControlStatus.LIMIT, "the twist limiter failed")
                self.status = status
        if self.mode == Mode.STOPPING:
            twist, result = self.limiter.step(_ZERO6, None, dt)
            guarded = result == LimiterResult.GUARDED
            self.status = self._stop_status
            if self.limiter.at_rest():
                return self._finish(faults)

        if self.mode == Mode.IDLE:
            return self._output(Action.KICK, _ZERO6, faults, False)
        faults |= self.monitor.check(twist, dt)
        a = self.limiter.accel
        if self.workspace(inp.state.T_base_tcp[:3, 3], twist[:3], a[:3]):
            faults |= Fault.WORKSPACE
        if faults & (Fault.WORKSPACE | Fault.SPEED | Fault.ACCEL | Fault.JERK):
            # The twist is sent (the limiter's state already holds it); the stop starts next cycle.
            self._begin_stop(status_of(faults), describe(faults))
        return self._output(Action.SPEED, twist, faults, guarded)

    def _step_arc(self, inp: CycleInput, welding: bool) -> int | None:
        """Step the weld's arc sequence with the law's wish of the last cycle and the source's signals now; the
        travel gate for the law this cycle (None: not welding)."""
        arc = self.arc
        sig = inp.source
        if arc is None or sig is None:
            return None
        v = inp.state.v_tcp
        speed = float(np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))
        want = welding and self._last_telemetry.process_on
        out = arc.step(self._t, want, welding and self._law_done, speed, self._dt, sig)
        return out.travel if welding else None

    def _step_joint(self, ctrl: JointMove, inp: CycleInput, faults: Fault) -> CycleOutput:
        """The cycle of a joint move (module docstring)."""
        qd: Array = _ZERO6
        if self.mode == Mode.ACTIVE:
            if faults:
                # Brake from what was sent last cycle, not from one more planned step.
                self._begin_stop(status_of(faults), describe(faults))
            else:
                qd, status = ctrl.step(inp.state)
                if status == ControlStatus.DONE or status >= ControlStatus.WORKSPACE:
                    self._begin_stop(status, ctrl.reason)
                else:
                    self.status = status
        if self.mode == Mode.STOPPING:
            qd, at_rest = ctrl.stop_step(inp.state.stamp_ns)
            self.status = self._stop_status
            if at_rest:
                return self._finish(faults, Action.SPEED_J)
        faults |= self.joint_monitor.check(qd, self._dt)
        # The TCP's twist in a joint move is the robot's own; the stop is in joint space.
        if self.workspace(inp.state.T_base_tcp[:3, 3], inp.state.v_tcp[:3], _ZERO3):
            faults |= Fault.WORKSPACE
        if faults & (Fault.WORKSPACE | LIMITS):
            self._begin_stop(status_of(faults), describe(faults))
        return self._output(Action.SPEED_J, qd, faults, False)

    def _finish(self, faults: Fault, action: Action = Action.SPEED) -> CycleOutput:
        self.mode = Mode.IDLE
        self.controller = Hold()
        self.status = self._stop_status
        self.monitor.reset()
        self.joint_monitor.reset()
        if self._stop_status != ControlStatus.DONE:
            self._refuse(self.command_id, self._stop_status, self._stop_reason)
        return self._output(action, _ZERO6, faults, False)

    def _output(self, action: Action, twist: Array, faults: Fault, guarded: bool) -> CycleOutput:
        ctrl = self.controller
        telemetry = ctrl.telemetry() if isinstance(ctrl, ServoSlot) else NO_TELEMETRY
        self._last_telemetry = telemetry
        arc: ArcOutput | None = None
        if self.params.source is not None:
            arc = self.arc.output(self._t) if self.arc is not None else _ARC_IDLE
            process_on = arc.arc_start
        else:
            process_on = self.mode == Mode.ACTIVE and not faults and telemetry.process_on
        return CycleOutput(
            action,
            twist,
            self.mode,
            self.status,
            self.command_id,
            faults,
            guarded,
            self._event,
            self._event_id,
            self._event_status,
            process_on,
            telemetry,
            arc,
        )
