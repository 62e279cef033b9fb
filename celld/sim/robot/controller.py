"""The simulated controller's state: modes, registers, IO, the running program, one tick.

No sockets: the servers in :mod:`celld.sim.robot.server` read and write this
object; :meth:`Controller.tick` advances it by one 2 ms cycle. State machines,
as the UR controller has them:

- robot mode: POWER_OFF -> (``power on``) IDLE -> (``brake release``) RUNNING;
- safety mode: NORMAL, PROTECTIVE_STOP (cleared by ``unlock protective stop``
  after :attr:`SimOptions.unlock_delay`), ROBOT_EMERGENCY_STOP (cleared when the
  e-stop is released; the arm is then powered off);
- runtime state: STOPPED, PLAYING, PAUSED. A program runs only while the robot
  is RUNNING in NORMAL safety mode; a protective stop, an e-stop, a power-off,
  the RTDE watchdog or a runtime error stops it.

A welding power source on its I/O (:mod:`celld.sim.robot.source`, when the
options give one) is stepped at the end of every cycle, whatever the robot's
mode: it has its own supply.

Text messages for RTDE clients collect in :attr:`Controller.outbox`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

from celld.robot import kinematics as kin
from celld.sim.robot import geometry as g
from celld.sim.robot import model as m
from celld.sim.robot import rtde_protocol as P
from celld.sim.robot.options import SimOptions
from celld.sim.robot.script import ControlScript, CustomProgram, IdleProgram, Program, ScriptError
from celld.sim.robot.source import SimPowerSource
from celld.sim.robot.truearm import TrueArm

# Controller cycle, s (500 Hz).
PERIOD = 0.002

# runtime_state values.
RUNTIME_STOPPING, RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSING, RUNTIME_PAUSED, RUNTIME_RESUMING = range(6)
RUNTIME_NAMES = {RUNTIME_STOPPED: "STOPPED", RUNTIME_PLAYING: "PLAYING", RUNTIME_PAUSED: "PAUSED"}
# robot_mode values.
ROBOT_MODE_POWER_OFF = 3
ROBOT_MODE_POWER_ON = 4
ROBOT_MODE_IDLE = 5
ROBOT_MODE_RUNNING = 7
ROBOT_MODE_NAMES = {
    -1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
    4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING",
}  # fmt: skip
# safety_mode values.
SAFETY_NORMAL = 1
SAFETY_PROTECTIVE_STOP = 3
SAFETY_ROBOT_EMERGENCY_STOP = 7
SAFETY_NAMES = {
    1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
}  # fmt: skip
# safety_status_bits of each safety mode: bit 0 normal, 2 protective stop,
# 6 robot e-stop, 7 emergency stopped, 10 stopped due to safety.
_SAFETY_BITS = {
    SAFETY_NORMAL: 1 << 0,
    SAFETY_PROTECTIVE_STOP: (1 << 2) | (1 << 10),
    SAFETY_ROBOT_EMERGENCY_STOP: (1 << 6) | (1 << 7) | (1 << 10),
}
# joint_mode values.
JOINT_POWER_OFF = 239
JOINT_RUNNING = 254
JOINT_IDLE = 255
# Deceleration of the stop when a program ends while the arm moves, rad/s^2.
PROGRAM_STOP_DECEL = 4.0
# Nominal electrical readings (V, A, degC) reported on RTDE.
_MAIN_VOLTAGE = 48.0
_ROBOT_VOLTAGE = 48.0
_JOINT_TEMPERATURE = 35.0

# Input fields that are applied together (mask and value).
_IO_FIELDS = frozenset(
    (
        "standard_digital_output_mask", "standard_digital_output", "configurable_digital_output_mask",
        "configurable_digital_output", "tool_digital_output_mask", "tool_digital_output",
        "speed_slider_mask", "speed_slider_fraction", "standard_analog_output_mask",
        "standard_analog_output_type", "standard_analog_output_0", "standard_analog_output_1",
        "external_force_torque",
    )
)  # fmt: skip
# Plan codes of input fields.
_INT, _DOUBLE, _BIT, _BITS_LO, _BITS_HI, _IO = range(6)

InputPlan = tuple[tuple[int, Any, int], ...]


class Controller:
    """State of the simulated UR controller and its arm."""

    def __init__(self, options: SimOptions) -> None:
        self.options = options
        model = kin.model(options.model)
        # The table it computes with (its factory calibration's), served on the primary interface.
        self.kinematics = options.kinematics or model.dh
        self.arm = m.Arm(
            m.ArmLimits(
                joints=model.limits,
                tcp_speed=options.tcp_speed_limit,
                tcp_acc=options.tcp_acc_limit,
                joint_acc=options.joint_acc_limit,
                workspace_min=tuple(options.workspace_min),  # type: ignore[arg-type]
                workspace_max=tuple(options.workspace_max),  # type: ignore[arg-type]
            ),
            options.q0,
            options.tcp_offset,
            self.kinematics,
        )
        # The physical arm when it differs from the model (celld.sim.robot.truearm); None: it is the model.
        self.true_arm = TrueArm(options.arm) if options.arm is not None and not options.arm.is_model(self.kinematics) else None
        self.ticks = 0
        self.time = 0.0  # controller time, s: ticks * PERIOD
        self.robot_mode = ROBOT_MODE_RUNNING if options.boot == "running" else ROBOT_MODE_POWER_OFF
        self.safety_mode = SAFETY_NORMAL
        self.runtime_state = RUNTIME_STOPPED
        self.program: ControlScript | CustomProgram | IdleProgram | None = None
        self.program_name = ""
        self.loaded_program: str | None = None
        n = P.N_REGISTERS
        self.in_int = [0] * n
        self.in_double = [0.0] * n
        self.in_bits = [0, 0]  # bit registers 0-63 and 64-127
        self.out_int = [0] * n
        self.out_double = [0.0] * n
        self.out_bits = [0, 0]
        self.in_int_written = [0.0] * n  # watchdog clock (see tick) of the last write of each input int register
        self.now = 0.0  # the watchdog clock at the last tick
        self.digital_out = 0  # bits 0-7 standard, 8-15 configurable, 16-17 tool
        self.digital_in = 0
        self.analog_out = [0.0, 0.0]  # ratios of the span, as ur-rtde writes them
        self.analog_out_types = 0
        self.analog_in = [0.0, 0.0]  # V
        # The welding power source on the I/O (None: nothing is wired), and the analog inputs it drives,
        # which the installation sets to the voltage domain.
        self.source = SimPowerSource(options.power_source) if options.power_source is not None else None
        self.analog_in_types = self.source.analog_in_mask if self.source is not None else 0
        self.speed_fraction = 1.0
        self.external_ft = [0.0] * 6
        self.payload = 0.0
        self.payload_cog = [0.0, 0.0, 0.0]
        self.payload_inertia = [0.0] * 6
        self.watchdog: tuple[int, float] | None = None  # (input int register, max silence s)
        self.protective_stop_time = -math.inf
        self.estop_pressed = False
        self.refuse_upload = False
        self.last_stop_reason = ""
        self.outbox: list[tuple[str, int]] = []
        # What the controller reports as its actual joints and TCP (encoder readings), and
        # the physical arm's joints and TCP (the truth); see sense().
        self.q_actual: list[float] = list(self.arm.q)
        self.T_tcp_actual = list(self.arm.T_tcp)
        self.q_true: list[float] = list(self.arm.q)
        self.T_tcp_true = list(self.arm.T_tcp)
        self.T_flange_true = list(self.arm.T_flange)
        self.sense()

    # --- messages -----------------------------------------------------------------

    def message(self, text: str, level: int = P.LEVEL_INFO) -> None:
        """Queue a text message for the RTDE clients."""
        if self.options.text_messages:
            self.outbox.append((text, level))

    # --- limits of commands -------------------------------------------------------

    def limit_linear_move(self, speed: float, acc: float) -> tuple[float, float]:
        """Tool speed and acceleration of a linear move, within the safety and planner limits."""
        if speed <= 0.0 or acc <= 0.0:
            raise ScriptError(f"movel: speed and acceleration must be positive, got v={speed}, a={acc}")
        lim = self.arm.limits
        if speed > lim.tcp_speed:
            self.message(f"movel speed {speed:.3f} m/s reduced to the safety limit {lim.tcp_speed:.3f} m/s", P.LEVEL_WARNING)
            speed = lim.tcp_speed
        return speed, min(acc, lim.tcp_acc)

    def limit_joint_move(self, speed: float, acc: float) -> tuple[float, float]:
        """Joint speed and acceleration of a joint move, within the joint limits."""
        if speed <= 0.0 or acc <= 0.0:
            raise ScriptError(f"movej: speed and acceleration must be positive, got v={speed}, a={acc}")
        vmax = min(self.arm.limits.joints.qd_max)
        if speed > vmax:
            self.message(f"movej speed {speed:.3f} rad/s reduced to the joint limit {vmax:.3f} rad/s", P.LEVEL_WARNING)
            speed = vmax
        return speed, min(acc, self.arm.limits.joint_acc)

    def limit_acc(self, acc: float, joint: bool) -> float:
        """An acceleration or deceleration of a speed or stop command, within the planner limit."""
        if acc <= 0.0:
            raise ScriptError(f"acceleration must be positive, got {acc}")
        return min(acc, self.arm.limits.joint_acc if joint else self.arm.limits.tcp_acc)

    # --- program ------------------------------------------------------------------

    @property
    def can_run(self) -> bool:
        return self.robot_mode == ROBOT_MODE_RUNNING and self.safety_mode == SAFETY_NORMAL

    def receive_program(self, program: Program) -> None:
        """A program arrived on a script port: replace the running one and start it."""
        if self.refuse_upload:
            self.message(f"program {program.name} refused (fault injection)", P.LEVEL_ERROR)
            return
        if not self.can_run:
            mode = ROBOT_MODE_NAMES.get(self.robot_mode, str(self.robot_mode))
            self.message(
                f"program {program.name} cannot start: robot mode {mode}, safety {SAFETY_NAMES[self.safety_mode]}",
                P.LEVEL_ERROR,
            )
            return
        if self.program is not None:
            self.stop_program("replaced by a new program")
        self.program = ControlScript(self, program) if program.is_control_script else CustomProgram(self, program)
        self.program_name = program.name
        self.runtime_state = RUNTIME_PLAYING
        self.program.start()

    def start_idle_program(self, name: str) -> None:
        """Run a loaded ``.urp`` program (not simulated: it idles until stopped)."""
        self.program = IdleProgram()
        self.program_name = name
        self.runtime_state = RUNTIME_PLAYING

    def stop_program(self, reason: str, brake: bool = True) -> None:
        """End the running program; the arm stops (at once when ``brake`` is False).

        With the I/O set-up ``outputs_low_at_stop`` (the default, as a cell's
        arc interlock needs) the standard digital outputs go low.
        """
        if self.program is not None:
            self.program.stop()
        self.program = None
        if self.runtime_state != RUNTIME_STOPPED and self.options.outputs_low_at_stop:
            self.digital_out &= ~0xFF
        self.runtime_state = RUNTIME_STOPPED
        self.watchdog = None
        self.last_stop_reason = reason
        if brake and not self.arm.steady:
            self.arm.stop_joint(PROGRAM_STOP_DECEL)
        elif not brake:
            self.arm.halt()

    def pause_program(self) -> bool:
        if self.runtime_state != RUNTIME_PLAYING:
            return False
        self.runtime_state = RUNTIME_PAUSED
        if not self.arm.steady:
            self.arm.stop_joint(PROGRAM_STOP_DECEL)
        return True

    def resume_program(self) -> bool:
        if self.runtime_state != RUNTIME_PAUSED or not self.can_run:
            return False
        self.runtime_state = RUNTIME_PLAYING
        return True

    def set_watchdog(self, register: int, min_frequency: float) -> None:
        """``rtde_set_watchdog``: stop the program if ``register`` is not written for 1/f s."""
        if min_frequency <= 0.0:
            self.watchdog = None
            return
        self.watchdog = (register, 1.0 / min_frequency)
        self.in_int_written[register] = self.now

    # --- safety -------------------------------------------------------------------

    def protective_stop(self, reason: str) -> None:
        if self.safety_mode == SAFETY_PROTECTIVE_STOP:
            return
        self.safety_mode = SAFETY_PROTECTIVE_STOP
        self.protective_stop_time = self.time
        self.arm.halt()
        self.stop_program(f"protective stop: {reason}", brake=False)
        self.message(f"Protective stop: {reason}", P.LEVEL_ERROR)

    def unlock_protective_stop(self) -> str | None:
        """Clear a protective stop; return why it cannot be cleared, or None."""
        if self.safety_mode != SAFETY_PROTECTIVE_STOP:
            return None
        if self.time - self.protective_stop_time < self.options.unlock_delay:
            return (
                f"Cannot unlock protective stop until {self.options.unlock_delay:g}s after occurrence. "
                "Always inspect cause of protective stop before unlocking"
            )
        self.safety_mode = SAFETY_NORMAL
        return None

    def emergency_stop(self) -> None:
        """The robot's e-stop button is pressed: stop, program ends, arm powers off."""
        self.estop_pressed = True
        self.safety_mode = SAFETY_ROBOT_EMERGENCY_STOP
        self.arm.halt()
        self.stop_program("emergency stop", brake=False)
        self.robot_mode = ROBOT_MODE_POWER_OFF
        self.message("Robot emergency stop", P.LEVEL_ERROR)

    def clear_protective_stop(self) -> None:
        """End a protective stop at once (the simulator's ``clear``; on a robot only the unlock does)."""
        if self.safety_mode == SAFETY_PROTECTIVE_STOP:
            self.safety_mode = SAFETY_NORMAL

    def release_emergency_stop(self) -> None:
        if self.estop_pressed:
            self.estop_pressed = False
            self.safety_mode = SAFETY_NORMAL

    def power_off(self) -> None:
        self.arm.halt()
        self.stop_program("power off", brake=False)
        self.robot_mode = ROBOT_MODE_POWER_OFF

    def power_on(self) -> bool:
        if self.estop_pressed or self.robot_mode not in (ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE):
            return self.robot_mode == ROBOT_MODE_RUNNING
        self.robot_mode = ROBOT_MODE_IDLE
        return True

    def brake_release(self) -> bool:
        if self.robot_mode == ROBOT_MODE_IDLE and self.safety_mode == SAFETY_NORMAL:
            self.robot_mode = ROBOT_MODE_RUNNING
        return self.robot_mode == ROBOT_MODE_RUNNING

    # --- the cycle ----------------------------------------------------------------

    def tick(self, now: float | None = None) -> None:
        """One controller cycle: watchdog, program, arm, safety, the power source.

        ``now`` is the clock (s) the watchdog measures silence on, the one the
        server also stamps input writes with; by default the controller time.
        The server passes its monotonic clock, so that a stall of its own
        process is not taken for the client's silence.
        """
        self.ticks += 1
        self.time = self.ticks * PERIOD
        self.now = self.time if now is None else now
        if self.watchdog is not None:
            register, silence = self.watchdog
            if self.now - self.in_int_written[register] > silence:
                self.message(
                    f"RTDE watchdog: input_int_register_{register} not updated for {silence * 1e3:.0f} ms, program stopped",
                    P.LEVEL_ERROR,
                )
                self.stop_program("RTDE watchdog expired")
        if self.runtime_state == RUNTIME_PLAYING and self.program is not None:
            try:
                running = self.program.step()
            except ScriptError as exc:
                self.message(f"Runtime error in {self.program_name}: {exc}", P.LEVEL_ERROR)
                self.stop_program(f"runtime error: {exc}")
            else:
                if not running:
                    self.stop_program("program ended")
        if self.robot_mode != ROBOT_MODE_RUNNING or self.safety_mode != SAFETY_NORMAL:
            if not self.arm.steady:
                self.arm.halt()
        else:
            fault = self.arm.step(PERIOD * self.speed_fraction)
            if fault is not None:
                self.protective_stop(fault)
        self.sense()
        src = self.source
        if src is not None:
            src.step(self.time, self.digital_out, self.in_int, self.in_double, self.analog_out, self.T_flange_true)
            self.digital_in = src.write(self.digital_in, self.out_int, self.out_double, self.analog_in)

    def sense(self) -> None:
        """The joints and TCP the controller reports, and the physical arm's (joints, flange, TCP), for the arm as it is now.

        Without a physical arm of its own (:attr:`true_arm` None) all of them are
        the controller's model. With one, the physical joints and the true TCP
        come from :class:`~celld.sim.robot.truearm.TrueArm`, and the reported
        joints carry its encoder noise, the reported TCP being the model's
        forward kinematics of them (as a UR controller computes it).
        """
        arm = self.arm
        ta = self.true_arm
        if ta is None:
            self.q_actual = self.q_true = arm.q
            self.T_tcp_actual = self.T_tcp_true = arm.T_tcp
            self.T_flange_true = arm.T_flange
            return
        ta.update(arm.q, arm.qd, self.time)
        self.q_true = ta.q
        self.T_flange_true = ta.T_flange
        self.T_tcp_true = kin.compose_rows(ta.T_flange, arm.T_flange_tcp)
        if ta.truth.encoder_noise:
            self.q_actual = ta.q_reported
            self.T_tcp_actual = arm.fk_tcp(ta.q_reported)
        else:
            self.q_actual = arm.q
            self.T_tcp_actual = arm.T_tcp

    # --- inputs -------------------------------------------------------------------

    @staticmethod
    def input_plan(names: Sequence[str]) -> InputPlan:
        """How to apply a data package of an input recipe with ``names``."""
        plan: list[tuple[int, Any, int]] = []
        for name in names:
            width = P.TYPE_WIDTH.get(P.INPUT_FIELDS[name], 1)
            if name.startswith("input_int_register_"):
                plan.append((_INT, int(name.rsplit("_", 1)[1]), width))
            elif name.startswith("input_double_register_"):
                plan.append((_DOUBLE, int(name.rsplit("_", 1)[1]), width))
            elif name.startswith("input_bit_register_"):
                plan.append((_BIT, int(name.rsplit("_", 1)[1]), width))
            elif name == "input_bit_registers0_to_31":
                plan.append((_BITS_LO, 0, width))
            elif name == "input_bit_registers32_to_63":
                plan.append((_BITS_LO, 32, width))
            else:
                plan.append((_IO, name, width))
        return tuple(plan)

    def write_inputs(self, plan: InputPlan, values: Sequence[Any], now: float | None = None) -> None:
        """Apply the flat ``values`` of one data package that arrived at ``now`` (watchdog clock)."""
        io: dict[str, Any] | None = None
        i = 0
        t = self.time if now is None else now
        for code, key, width in plan:
            if code == _INT:
                self.in_int[key] = values[i]
                self.in_int_written[key] = t
            elif code == _DOUBLE:
                self.in_double[key] = values[i]
            elif code == _BIT:
                bit = 1 << (key - 64)
                self.in_bits[1] = (self.in_bits[1] | bit) if values[i] else (self.in_bits[1] & ~bit)
            elif code == _BITS_LO:
                self.in_bits[0] = (self.in_bits[0] & ~(0xFFFFFFFF << key)) | (int(values[i]) << key)
            else:
                if io is None:
                    io = {}
                io[key] = values[i] if width == 1 else list(values[i : i + width])
            i += width
        if io:
            self._apply_io(io)

    def _apply_io(self, io: dict[str, Any]) -> None:
        for mask_name, value_name, shift in (
            ("standard_digital_output_mask", "standard_digital_output", 0),
            ("configurable_digital_output_mask", "configurable_digital_output", 8),
            ("tool_digital_output_mask", "tool_digital_output", 16),
        ):
            mask = io.get(mask_name, 0) << shift
            if mask and value_name in io:
                self.digital_out = (self.digital_out & ~mask) | ((io[value_name] << shift) & mask)
        fraction = float(io.get("speed_slider_fraction", math.nan))
        if io.get("speed_slider_mask") and math.isfinite(fraction):
            self.speed_fraction = min(1.0, max(0.0, fraction))
        amask = io.get("standard_analog_output_mask", 0)
        for k in (0, 1):
            if amask & (1 << k) and f"standard_analog_output_{k}" in io:
                self.analog_out[k] = float(io[f"standard_analog_output_{k}"])
        if amask and "standard_analog_output_type" in io:
            self.analog_out_types = (self.analog_out_types & ~amask) | (io["standard_analog_output_type"] & amask)
        if "external_force_torque" in io:
            self.external_ft = list(io["external_force_torque"])

    # --- outputs ------------------------------------------------------------------

    def output_getter(self, name: str) -> Callable[[], Sequence[Any]]:
        """A function that returns the current value(s) of output field ``name``."""
        arm = self.arm
        for prefix, regs in (
            ("output_int_register_", self.out_int),
            ("output_double_register_", self.out_double),
            ("input_int_register_", self.in_int),
            ("input_double_register_", self.in_double),
        ):
            if name.startswith(prefix):
                return functools.partial(_register_value, regs, int(name[len(prefix) :]))
        for prefix, bits in (("output_bit_register_", self.out_bits), ("input_bit_register_", self.in_bits)):
            if name.startswith(prefix):
                return functools.partial(_bit_value, bits, int(name[len(prefix) :]) - 64)
        for prefix, bits in (("output_bit_registers", self.out_bits), ("input_bit_registers", self.in_bits)):
            if name.startswith(prefix):
                return functools.partial(_bit_word, bits, 0 if name.endswith("0_to_31") else 32)
        zeros6 = (0.0,) * 6
        getters: dict[str, Callable[[], Sequence[Any]]] = {
            "timestamp": lambda: (self.time,),
            "target_q": lambda: arm.q,
            "actual_q": lambda: self.q_actual,
            "target_qd": lambda: arm.qd,
            "actual_qd": lambda: arm.qd,
            "target_qdd": lambda: arm.qdd,
            "actual_TCP_pose": lambda: g.pose_from_rows(self.T_tcp_actual),
            "target_TCP_pose": lambda: g.pose_from_rows(arm.T_tcp),
            "actual_TCP_speed": lambda: arm.tcp_speed,
            "target_TCP_speed": lambda: arm.tcp_speed,
            "robot_mode": lambda: (self.robot_mode,),
            "joint_mode": lambda: (self.joint_mode(),) * 6,
            "safety_mode": lambda: (self.safety_mode,),
            "safety_status": lambda: (self.safety_mode,),
            "safety_status_bits": lambda: (self.safety_status_bits(),),
            "robot_status_bits": lambda: (self.robot_status_bits(),),
            "runtime_state": lambda: (self.runtime_state,),
            "speed_scaling": lambda: (self.speed_fraction,),
            "target_speed_fraction": lambda: (self.speed_fraction,),
            "actual_digital_output_bits": lambda: (self.digital_out,),
            "actual_digital_input_bits": lambda: (self.digital_in,),
            "standard_analog_output0": lambda: (self.analog_out[0],),
            "standard_analog_output1": lambda: (self.analog_out[1],),
            "standard_analog_input0": lambda: (self.analog_in[0],),
            "standard_analog_input1": lambda: (self.analog_in[1],),
            "analog_io_types": lambda: ((self.analog_out_types << 2) | self.analog_in_types,),
            "payload": lambda: (self.payload,),
            "payload_cog": lambda: self.payload_cog,
            "payload_inertia": lambda: self.payload_inertia,
            "joint_temperatures": lambda: (_JOINT_TEMPERATURE,) * 6,
            "actual_main_voltage": lambda: (_MAIN_VOLTAGE,),
            "actual_robot_voltage": lambda: (_ROBOT_VOLTAGE if self.robot_mode > ROBOT_MODE_POWER_OFF else 0.0,),
            "actual_joint_voltage": lambda: (_ROBOT_VOLTAGE if self.robot_mode > ROBOT_MODE_POWER_OFF else 0.0,) * 6,
            "actual_tool_accelerometer": lambda: (0.0, 0.0, -9.81),
            "elbow_position": lambda: self.elbow_position(),
            "ft_raw_wrench": lambda: self.external_ft,
        }
        if name in getters:
            return getters[name]
        # Everything else the simulator does not model reads as zero of its type.
        width = P.TYPE_WIDTH.get(P.OUTPUT_FIELDS[name], 1)
        zero: tuple[Any, ...] = zeros6[:width] if P.OUTPUT_FIELDS[name] in ("DOUBLE", "VECTOR3D", "VECTOR6D") else (0,) * width
        return lambda: zero

    def joint_mode(self) -> int:
        if self.robot_mode == ROBOT_MODE_RUNNING:
            return JOINT_RUNNING
        return JOINT_IDLE if self.robot_mode in (ROBOT_MODE_IDLE, ROBOT_MODE_POWER_ON) else JOINT_POWER_OFF

    def safety_status_bits(self) -> int:
        return _SAFETY_BITS.get(self.safety_mode, 1 << 10)

    def robot_status_bits(self) -> int:
        bits = 1 if self.robot_mode > ROBOT_MODE_POWER_OFF else 0
        if self.runtime_state == RUNTIME_PLAYING:
            bits |= 2
        return bits

    def elbow_position(self) -> list[float]:
        T = kin.forward_all_rows(self.arm.q, self.arm.dh)[1]  # frame 2: the elbow joint
        return [T[3], T[7], T[11]]


def _register_value(regs: Sequence[Any], i: int) -> tuple[Any]:
    return (regs[i],)


def _bit_value(bits: Sequence[int], i: int) -> tuple[bool]:
    """Bit ``i`` of the upper 64-bit word (the registers 64..127)."""
    return (bool(bits[1] >> i & 1),)


def _bit_word(bits: Sequence[int], shift: int) -> tuple[int]:
    """32 bits of the lower word from ``shift``."""
    return ((bits[0] >> shift) & 0xFFFFFFFF,)
