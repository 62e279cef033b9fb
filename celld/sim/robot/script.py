"""Programs sent to the script ports, and the interpreter of ur-rtde's control script.

URScript is not interpreted in general. An upload is recognised as ur-rtde's
control script (``rtde_control``) by its main loop, and its register protocol
is then executed here, command by command, as the script's ``process_cmd`` does
it (ur-rtde 1.6.5):

- the command id is in ``input_int_register_0`` (+ the register offset),
  arguments in the input double registers and int registers 1-7;
- real-time ids (speeds, servos, some getters) are processed on every cycle
  and answered with ready (``output_int_register_0`` = 1);
- any other id is processed once and answered with done (= 2); the client then
  writes 0 and the script answers ready again. A synchronous move or stop
  blocks the loop until the arm has finished it;
- query results go to ``output_int_register_1`` and the output double
  registers 0-5, async progress to ``output_int_register_2``.

Any other program is a :class:`CustomProgram`: its ``write_output_integer_register``
lines are applied (that is how ur-rtde's ``sendCustomScriptFunction`` reports
completion) and it ends; other statements are not simulated.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from celld.robot import kinematics as kin
from celld.sim.robot import geometry as g
from celld.sim.robot import model as m

if TYPE_CHECKING:
    from celld.sim.robot.controller import Controller

# A complete top-level program: "def name():" or "sec name():" up to an unindented "end".
_PROGRAM = re.compile(rb"^(def|sec)[ \t]+(\w+)[ \t]*\([ \t]*\)[ \t]*:[ \t]*\r?\n(.*?)^end[ \t]*(?:\r?\n|$)", re.M | re.S)
# ur-rtde writes the register offsets on the line after these comments.
_INT_OFFSET = re.compile(rb"reg_offset_int\s*=\s*#[^\n]*\n\s*(\d+)")
_FLOAT_OFFSET = re.compile(rb"reg_offset_float\s*=\s*#[^\n]*\n\s*(\d+)")
# The main loop of ur-rtde's control script.
_CONTROL_LOOP = re.compile(rb"def rtde_cmd\(\):.*keep_running = process_cmd\(cmd\)", re.S)
_WRITE_INT_REGISTER = re.compile(rb"write_output_integer_register\(\s*(\d+)\s*(?:\+\s*(\d+)\s*)?,\s*(-?\d+)\s*\)")

# Command ids processed on every cycle (the script's "realtime commands").
REALTIME_COMMANDS = frozenset((24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71))
CMD_STOP_SCRIPT = 255
# Handshake values of output_int_register_0.
READY = 1
DONE = 2
# Step time the script reports (get_steptime), s.
STEP_TIME = 0.002
# Deceleration of force_mode_stop's stopl and stop_jog's stopl, as in the script.
FORCE_STOP_DECEL = 10.0
JOG_STOP_DECEL = 1.2


class ScriptError(Exception):
    """A runtime error of the running program (the controller stops it)."""


@dataclass(frozen=True)
class Program:
    """One program received on a script port."""

    name: str
    body: bytes
    is_control_script: bool
    int_offset: int
    float_offset: int


def find_programs(buffer: bytes) -> tuple[list[Program], bytes]:
    """The complete programs in ``buffer`` and the bytes after the last one."""
    programs: list[Program] = []
    end = 0
    for match in _PROGRAM.finditer(buffer):
        body = match.group(0)
        int_off = _INT_OFFSET.search(body)
        float_off = _FLOAT_OFFSET.search(body)
        programs.append(
            Program(
                name=match.group(2).decode("ascii"),
                body=body,
                is_control_script=bool(_CONTROL_LOOP.search(body)),
                int_offset=int(int_off.group(1)) if int_off else 0,
                float_offset=int(float_off.group(1)) if float_off else 0,
            )
        )
        end = match.end()
    return programs, buffer[end:]


class CustomProgram:
    """A program that is not ur-rtde's control script: applies its register writes, then ends."""

    def __init__(self, ctrl: Controller, program: Program) -> None:
        self.ctrl = ctrl
        self.program = program

    def start(self) -> None:
        skipped = 0
        for line in self.program.body.splitlines()[1:-1]:
            match = _WRITE_INT_REGISTER.search(line)
            if match:
                index = int(match.group(1)) + int(match.group(2) or 0)
                if 0 <= index < len(self.ctrl.out_int):
                    self.ctrl.out_int[index] = int(match.group(3))
            elif line.strip() and not line.strip().startswith(b"#"):
                skipped += 1
        if skipped:
            self.ctrl.message(f"program {self.program.name}: {skipped} statements not simulated")

    def step(self) -> bool:
        return False  # ends on its first cycle

    def stop(self) -> None:
        pass


class IdleProgram:
    """A program started with the dashboard's ``play``: runs, does nothing, until stopped."""

    def start(self) -> None:
        pass

    def step(self) -> bool:
        return True

    def stop(self) -> None:
        pass


class ControlScript:
    """ur-rtde's ``rtde_control`` script, run on the controller's registers."""

    def __init__(self, ctrl: Controller, program: Program) -> None:
        self.ctrl = ctrl
        self.program = program
        self.ioff = program.int_offset
        self.foff = program.float_offset
        self.executing = False
        self.blocking: m.Motion | None = None
        self.async_move: m.Motion | None = None
        self.async_stop: m.Motion | None = None
        self.speed_motion: m.Motion | None = None
        self.speed_type = 0
        self.servo_motion: m.Motion | None = None
        self.jog: tuple[m.Motion, list[float]] | None = None
        self.stop_type = 0
        self.async_wr_count = 0
        self.async_op_id = 0
        self.freedrive = False
        self.force_mode_warned = False
        self._commands: dict[int, Callable[[], None]] = self._command_table()

    # --- registers ----------------------------------------------------------------

    def _f(self, i: int) -> float:
        v = self.ctrl.in_double[self.foff + i]
        if not math.isfinite(v):
            raise ScriptError(f"input_double_register_{self.foff + i} is not finite: {v}")
        return v

    def _i(self, i: int) -> int:
        return self.ctrl.in_int[self.ioff + i]

    def _vec(self, i: int) -> list[float]:
        return [self._f(i + k) for k in range(6)]

    def _out_int(self, i: int, value: int) -> None:
        self.ctrl.out_int[self.ioff + i] = int(value)

    def _out_vec(self, i: int, values: list[float]) -> None:
        for k, v in enumerate(values):
            self.ctrl.out_double[self.foff + i + k] = float(v)

    def _signal_ready(self) -> None:
        self._out_int(0, READY)

    def _signal_done(self) -> None:
        self._out_int(0, DONE)

    def _async_progress(self, value: int) -> None:
        # Bit layout of the script's write_async_progress_register.
        self.async_wr_count = self.async_wr_count + 1 if self.async_wr_count < 127 else 0
        if value == 0:
            self.async_op_id = self.async_op_id + 1 if self.async_op_id < 127 else 0
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._out_int(2, reg)

    # --- life cycle ---------------------------------------------------------------

    def start(self) -> None:
        self._async_progress(-1)  # reset_async_progress
        self._signal_ready()

    def stop(self) -> None:
        """The program ends: its threads die with it."""
        self.blocking = self.async_move = self.async_stop = None
        self.speed_motion = self.servo_motion = None
        self.jog = None

    def step(self) -> bool:
        """One cycle of the script's main loop; False when the script has ended."""
        arm = self.ctrl.arm
        if self.async_move is not None and (self.async_move.done or arm.motion is not self.async_move):
            self.async_move = None
            self._async_progress(-1)
        if self.async_stop is not None and (self.async_stop.done or arm.motion is not self.async_stop):
            self.async_stop = None
            self._async_progress(-1)
        if self.jog is not None:
            motion, twist = self.jog
            if arm.motion is motion:
                motion.set_target(twist, motion.acc)  # type: ignore[attr-defined]
            else:
                self.jog = None
        if self.blocking is not None:
            if not self.blocking.done and arm.motion is self.blocking:
                return True
            self.blocking = None
            self._signal_done()
            return True
        cmd = self._i(0)
        if cmd in REALTIME_COMMANDS:
            keep = self._process(cmd)
            self._signal_ready()
            return keep
        if cmd == 0:
            self.executing = False
            self._signal_ready()
            return True
        keep = True
        if not self.executing:
            keep = self._process(cmd)
        self.executing = True
        return keep

    def _process(self, cmd: int) -> bool:
        if cmd == CMD_STOP_SCRIPT:
            return False
        handler = self._commands.get(cmd)
        if handler is not None:
            handler()
        if self.blocking is None:
            self._signal_done()
        return True

    # --- commands -----------------------------------------------------------------

    def _command_table(self) -> dict[int, Callable[[], None]]:
        return {
            1: lambda: self._move_joint(self._vec(0), ik=False),
            2: lambda: self._move_joint(self._vec(0), ik=True),
            3: lambda: self._move_linear(self._vec(0), fk=False),
            4: lambda: self._move_linear(self._vec(0), fk=True),
            6: self._force_mode,
            7: lambda: self._blocking_stop(linear=True, decel=FORCE_STOP_DECEL),
            9: lambda: self._speed(joint=True),
            10: lambda: self._speed(joint=False),
            11: lambda: self._servo(self._vec(0)),
            12: self._servo_c,
            15: self._speed_stop,
            16: self._servo_stop,
            17: self._set_payload,
            18: lambda: self._set_freedrive(True),
            19: lambda: self._set_freedrive(False),
            24: lambda: self._servo(self._ik(self._vec(0), self.ctrl.arm.q)),
            25: lambda: self._out_int(1, 0),  # tool_contact: the simulated tool never touches
            26: lambda: self._out_vec(0, [STEP_TIME]),
            27: self._joint_history,
            28: self._target_waypoint,
            29: lambda: self.ctrl.arm.set_tcp(self._vec(0)),
            30: lambda: self._out_vec(0, self._ik(self._vec(0), self._vec(6))),
            31: lambda: self.ctrl.protective_stop("protective_stop() called by the program"),
            33: lambda: self._stop_command("stopl"),
            34: lambda: self._stop_command("stopj"),
            35: self._set_watchdog,
            36: lambda: self._out_int(1, self._pose_is_safe(self._vec(0))),
            37: lambda: self._out_int(1, self._joints_are_safe(self._vec(0))),
            38: lambda: self._out_vec(0, [0.0] * 6),  # no dynamics model: zero torques
            39: self._pose_trans,
            40: lambda: self._out_vec(0, self.ctrl.arm.tcp_offset),
            41: self._start_jog,
            42: self._stop_jog,
            43: lambda: self._out_vec(0, g.pose_from_rows(self.ctrl.arm.T_tcp)),
            44: lambda: self._out_vec(0, g.pose_from_rows(self.ctrl.arm.fk_tcp(self._vec(0), g.rows_from_pose(self._vec(6))))),
            45: lambda: self._not_simulated("move_path"),
            46: lambda: self._out_vec(0, self._ik(self._vec(0), self.ctrl.arm.q)),
            47: lambda: self._out_int(1, int(self.ctrl.arm.steady)),
            51: lambda: self._not_simulated("move_until_contact (the simulated tool has no contact sensing)"),
            52: lambda: self._set_freedrive(True),
            53: lambda: self._set_freedrive(False),
            54: lambda: self._out_int(1, int(self.freedrive)),
            58: lambda: self._out_vec(0, g.pose_from_rows(self.ctrl.arm.T_flange)),
            60: lambda: self._out_int(1, self._has_ik(self._vec(0), self.ctrl.arm.q)),
            61: lambda: self._out_int(1, self._has_ik(self._vec(0), self._vec(6))),
            62: lambda: None,
            63: lambda: self._out_int(1, 0),
            64: lambda: self._out_int(1, 0),
            65: self._set_payload,
        }

    def _ik(self, pose: list[float], q_near: list[float]) -> list[float]:
        q = self.ctrl.arm.ik(g.rows_from_pose(pose), q_near)
        if q is None:
            raise ScriptError(f"get_inverse_kin(): no solution for p{[round(v, 5) for v in pose]}")
        return q

    def _has_ik(self, pose: list[float], q_near: list[float]) -> int:
        return int(self.ctrl.arm.ik(g.rows_from_pose(pose), q_near) is not None)

    def _stop_async_move(self) -> None:
        if self.async_move is not None:
            self.async_move = None
            self._async_progress(-1)

    def _run_move(self, motion: m.Motion) -> None:
        """Run ``motion`` synchronously or in the move thread, as int register 1 says."""
        self._stop_async_move()
        self.ctrl.arm.start(motion)
        if self._i(1) == 1:
            self.async_move = motion
            self._async_progress(0)
        else:
            self.blocking = motion

    def _move_joint(self, target: list[float], ik: bool) -> None:
        speed, acc = self._f(6), self._f(7)
        q = self._ik(target, self.ctrl.arm.q) if ik else target
        speed, acc = self.ctrl.limit_joint_move(speed, acc)
        self._run_move(m.JointTrajectory(self.ctrl.arm, q, speed, acc))

    def _move_linear(self, target: list[float], fk: bool) -> None:
        speed, acc = self._f(6), self._f(7)
        arm = self.ctrl.arm
        T_goal = arm.fk_tcp(target) if fk else g.rows_from_pose(target)
        if arm.ik(T_goal, arm.q) is None:
            raise ScriptError(f"movel: inverse kinematics failed for p{[round(v, 5) for v in g.pose_from_rows(T_goal)]}")
        speed, acc = self.ctrl.limit_linear_move(speed, acc)
        self._run_move(m.LinearTrajectory(arm, T_goal, speed, acc))

    def _speed(self, joint: bool) -> None:
        target, acc = self._vec(0), self._f(6)
        arm = self.ctrl.arm
        self.speed_type = 1 if joint else 0
        motion = self.speed_motion
        if joint:
            acc = self.ctrl.limit_acc(acc, joint=True)
            if isinstance(motion, m.JointVelocity) and arm.motion is motion and not motion.stopping:
                motion.set_target(target, acc)
            else:
                self.speed_motion = arm.start(m.JointVelocity(arm, target, acc))
        else:
            acc = self.ctrl.limit_acc(acc, joint=False)
            if isinstance(motion, m.CartesianVelocity) and arm.motion is motion and not motion.stopping:
                motion.set_target(target, acc)
            else:
                self.speed_motion = arm.start(m.CartesianVelocity(arm, target, acc))

    def _servo(self, q: list[float]) -> None:
        lookahead, gain = self._f(9), self._f(10)
        arm = self.ctrl.arm
        motion = self.servo_motion
        if isinstance(motion, m.JointServo) and arm.motion is motion:
            motion.set_target(q, lookahead, gain)
        else:
            self.servo_motion = arm.start(m.JointServo(arm, q, lookahead, gain))

    def _servo_c(self) -> None:
        speed, acc = self.ctrl.limit_linear_move(self._f(6), self._f(7))
        arm = self.ctrl.arm
        T_goal = g.rows_from_pose(self._vec(0))
        if arm.ik(T_goal, arm.q) is None:
            raise ScriptError("servoc: inverse kinematics failed for the target")
        self.servo_motion = arm.start(m.LinearTrajectory(arm, T_goal, speed, acc))

    def _blocking_stop(self, linear: bool, decel: float) -> None:
        decel = self.ctrl.limit_acc(decel, joint=not linear)
        arm = self.ctrl.arm
        self.blocking = arm.stop_linear(decel) if linear else arm.stop_joint(decel)

    def _speed_stop(self) -> None:
        self.speed_motion = None
        self._blocking_stop(linear=self.speed_type == 0, decel=self._f(0))

    def _servo_stop(self) -> None:
        self.servo_motion = None
        self._blocking_stop(linear=True, decel=self._f(0))

    def _stop_command(self, name: str) -> None:
        # exec_stopl_stopj of the script, including its use of the global stop_type:
        # a synchronous stop is a stopj until an asynchronous stop has set stop_type = 1.
        decel = self._f(0)
        stop_move = True
        if self.async_stop is not None:
            stop_move = False
            self.async_stop = None
            self._async_progress(-1)
        if stop_move:
            self._stop_async_move()
        arm = self.ctrl.arm
        if self._i(1) == 1:
            self.stop_type = 1
            decel = self.ctrl.limit_acc(decel, joint=False)
            self.async_stop = arm.stop_linear(decel)
            self._async_progress(0)
        else:
            self._blocking_stop(linear=self.stop_type == 1, decel=decel)

    def _set_watchdog(self) -> None:
        self.ctrl.set_watchdog(self.ioff, self._f(0))

    def _pose_is_safe(self, pose: list[float]) -> int:
        arm = self.ctrl.arm
        T = g.rows_from_pose(pose)
        return int(arm.within_safety(T) and arm.ik(T, arm.q) is not None)

    def _joints_are_safe(self, q: list[float]) -> int:
        arm = self.ctrl.arm
        return int(arm.joints_within_limits(q) and arm.within_safety(arm.fk_tcp(q)))

    def _pose_trans(self) -> None:
        T = kin.compose_rows(g.rows_from_pose(self._vec(0)), g.rows_from_pose(self._vec(6)))
        self._out_vec(0, g.pose_from_rows(T))

    def _joint_history(self) -> None:
        history = self.ctrl.arm.history
        steps = max(0, min(self._i(1), len(history) - 1))
        self._out_vec(0, history[-1 - steps])

    def _target_waypoint(self) -> None:
        arm = self.ctrl.arm
        T = arm.motion.target_pose(arm) if arm.motion is not None else None
        self._out_vec(0, g.pose_from_rows(T if T is not None else arm.T_tcp))

    def _set_payload(self) -> None:
        ctrl = self.ctrl
        ctrl.payload = self._f(0)
        cog = [self._f(1), self._f(2), self._f(3)]
        if any(cog):
            ctrl.payload_cog = cog
        if self._i(0) == 65:
            ctrl.payload_inertia = [self._f(4 + k) for k in range(6)]

    def _set_freedrive(self, on: bool) -> None:
        self.freedrive = on

    def _force_mode(self) -> None:
        if not self.force_mode_warned:
            self.force_mode_warned = True
            self.ctrl.message("force_mode is not simulated: the arm holds its motion")

    def _start_jog(self) -> None:
        arm = self.ctrl.arm
        speed, feature, acc = self._vec(0), int(self._f(6)), self._f(7)
        if feature == 1:
            R = g.rot_of(arm.T_tcp)
        elif feature == 2:
            R = g.rot_of(g.rows_from_pose(self._vec(8)))
        else:
            R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        twist = _rotate(R, speed[:3]) + _rotate(R, speed[3:])
        acc = self.ctrl.limit_acc(acc, joint=False)
        if self.jog is not None and arm.motion is self.jog[0]:
            self.jog = (self.jog[0], twist)
        else:
            self.jog = (arm.start(m.CartesianVelocity(arm, twist, acc)), twist)

    def _stop_jog(self) -> None:
        self.jog = None
        self._blocking_stop(linear=True, decel=JOG_STOP_DECEL)

    def _not_simulated(self, what: str) -> None:
        self.ctrl.message(f"{what}: not simulated, command ignored")


def _rotate(R: list[float], v: list[float]) -> list[float]:
    return [
        R[0] * v[0] + R[1] * v[1] + R[2] * v[2],
        R[3] * v[0] + R[4] * v[1] + R[5] * v[2],
        R[6] * v[0] + R[7] * v[1] + R[8] * v[2],
    ]
