"""The controllers of the motion loop: hold, Cartesian move, velocity stream, servo slot.

Each is stepped once per cycle as ``step(input) -> (demand, status)`` and never
raises in the loop. A demand is the twist the controller wants (and, for a
move, the acceleration it wants to arrive with); the loop passes every demand
through :class:`~celld.motion.limits.TwistLimiter`, which alone decides what
is sent, so the limits hold whichever controller runs.

The Cartesian move is straight in SE(3). A 6-DOF ruckig in its position
interface plans ``[x, y, z, phi_x, phi_y, phi_z]`` from the pose at the start
to the goal, where ``phi`` is the rotation vector of ``R(t) R_start^T`` in the
base frame: ``R_ref(t) = exp([phi(t)]) R_start``. Phase synchronisation keeps
the 6-vector on the straight line from start to goal, so ``phi`` keeps its
direction and ``dphi/dt`` is exactly the angular velocity (base frame) that
speedL takes. The per-axis bounds are boxes inscribed in the norm balls and
stretched along the move, so a straight move gets the whole speed,
acceleration and jerk budget and never more. The trajectory is computed once,
when the move starts, and sampled at each cycle's own time (the robot state's
stamp): the robot holds the last twist it was sent for as long as a late cycle
takes, so a reference stepped once per cycle would fall behind the clock and
the robot run past it. The reference is open loop; a
proportional term on the pose error (against the reference delayed by the
link's latency) closes the loop, and the move is done when the measured pose
is within tolerance of the goal and the robot is still.

Rotations in the loop go through :mod:`celld.motion.so3` (scipy's Rotation
is too slow for a 2 ms cycle). Pure: the robot state comes in as values; no
clock, no I/O.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray
from ruckig import ControlInterface, InputParameter, Ruckig, RuckigError, Synchronization, Trajectory

from celld.motion import so3
from celld.motion.limits import CartesianLimits, axis_weights
from celld.motion.types import NO_TELEMETRY, ControlStatus, RobotState, ServoInput, ServoLaw, ServoTelemetry
from celld.tactile.sample import TactileSample

Array = NDArray[np.float64]

_ZERO6 = np.zeros(6)
# Share of each limit the move's reference may use; the rest is room for the
# feedback term, so the limiter can follow the reference exactly.
_REFERENCE_SHARE = 0.95
# A cycle this many periods after the one before it came late; in a move's first _START_CYCLES cycles the
# plan's clock skips the delay (CartesianMove.step).
_LATE_START = 2.5
_START_CYCLES = 4


class ControlInput(NamedTuple):
    """What every controller sees in one cycle."""

    state: RobotState
    tactile: TactileSample | None  # latest good tactile sample, None before the first
    tactile_age: float  # s since the tactile sample was captured, inf without one
    setpoint: Array  # (6,) latest streaming twist setpoint, base frame
    setpoint_age: float  # s since the setpoint was written, inf without one
    travel: int | None = None  # the arc sequence's travel gate for a servo law (ServoInput.travel)


class Demand(NamedTuple):
    """A controller's wish for this cycle; the limiter shapes it."""

    twist: Array  # (6,) m/s, rad/s, base frame
    accel: Array | None = None  # (6,) acceleration to arrive with, or None for zero


class Controller(Protocol):
    """The interface the loop steps."""

    name: str
    reason: str  # why the last fault status was returned, "" otherwise

    def start(self, state: RobotState, twist: Array, accel: Array) -> None:
        """Take over from the current state and the limiter's current twist and acceleration."""

    def step(self, inp: ControlInput) -> tuple[Demand, ControlStatus]: ...


class Hold:
    """Stand still: zero twist. The loop sends nothing while it holds at rest."""

    name = "hold"
    reason = ""

    def start(self, state: RobotState, twist: Array, accel: Array) -> None:
        pass

    def step(self, inp: ControlInput) -> tuple[Demand, ControlStatus]:
        return Demand(_ZERO6), ControlStatus.HOLD


class MoveParams(NamedTuple):
    """Tuning of the Cartesian move (SI)."""

    gain: float = 8.0  # 1/s, linear position feedback
    angle_gain: float = 8.0  # 1/s, orientation feedback
    latency: float = 0.004  # s from a command to its effect in the measured pose
    settle_timeout: float = 2.0  # s after the reference ends before the move gives up
    settle_speed: float = 0.002  # m/s, measured TCP speed below which the robot counts as still
    settle_angular_speed: float = 0.01  # rad/s
    feedback_share: float = 0.1  # the pose correction is at most this share of the speed limits


class CartesianMove:
    """A jerk-limited straight move of the TCP to ``T_goal`` (module docstring).

    Parameters
    ----------
    T_goal : np.ndarray, shape (4, 4)
        Target pose of the TCP in the base frame (``T_base_tcp``).
    limits : CartesianLimits
        The norm limits of the cell; the move uses ``speed_scale`` of them.
    period : float
        Control period, s.
    speed_scale : float
        0 < speed_scale <= 1.
    tolerance, angle_tolerance : float
        Arrival tolerances, m and rad.
    params : MoveParams
    """

    name = "move"

    def __init__(
        self,
        T_goal: Array,
        limits: CartesianLimits,
        period: float,
        speed_scale: float = 1.0,
        tolerance: float = 5e-5,
        angle_tolerance: float = 5e-4,
        params: MoveParams = MoveParams(),
    ) -> None:
        self.T_goal = np.array(T_goal, dtype=np.float64)
        self.limits = limits.scaled(speed_scale * _REFERENCE_SHARE)
        self.period = period
        self.tolerance = tolerance
        self.angle_tolerance = angle_tolerance
        self.params = params
        self.reason = ""
        self._otg = Ruckig(6)
        self._inp = InputParameter(6)
        self._traj = Trajectory(6)
        self._inp.control_interface = ControlInterface.Position
        self._inp.synchronization = Synchronization.Phase
        self._R0 = np.eye(3)
        self._t0_ns = 0  # the cycle the trajectory was planned in
        self._steps = 0  # cycles stepped since the move started
        self._last_ns = 0  # the stamp of the last cycle stepped
        self._failed = ""  # why the planner refused the move, "" when it did not
        self._fb_cap = (params.feedback_share * limits.linear_speed, params.feedback_share * limits.angular_speed)

    def start(self, state: RobotState, twist: Array, accel: Array) -> None:
        T0 = state.T_base_tcp
        self._R0 = T0[:3, :3].copy()
        p0 = T0[:3, 3]
        dp = self.T_goal[:3, 3] - p0
        dphi = so3.log(self.T_goal[:3, :3] @ self._R0.T)
        lim = self.limits
        lim = self.limits
        # Boxes stretched along the move, and along the motion the move takes
        # over (so ruckig can brake it with the whole budget); from rest the
        # path is straight.
        v0 = np.asarray(twist, dtype=np.float64)
        a0 = np.asarray(accel, dtype=np.float64)
        w_lin = axis_weights(
            (dp / max(float(np.linalg.norm(dp)), 1e-12)).tolist(),
            (v0[:3] / lim.linear_speed).tolist(),
            (a0[:3] / lim.linear_accel).tolist(),
        )
        w_ang = axis_weights(
            (dphi / max(float(np.linalg.norm(dphi)), 1e-12)).tolist(),
            (v0[3:] / lim.angular_speed).tolist(),
            (a0[3:] / lim.angular_accel).tolist(),
        )
        inp = self._inp
        inp.max_velocity = [lim.linear_speed * w for w in w_lin] + [lim.angular_speed * w for w in w_ang]
        inp.max_acceleration = [lim.linear_accel * w for w in w_lin] + [lim.angular_accel * w for w in w_ang]
        inp.max_jerk = [lim.linear_jerk * w for w in w_lin] + [lim.angular_jerk * w for w in w_ang]
        inp.current_position = [*p0.tolist(), 0.0, 0.0, 0.0]
        inp.current_velocity = [float(x) for x in twist]
        inp.current_acceleration = [float(x) for x in accel]
        inp.target_position = [*self.T_goal[:3, 3].tolist(), *dphi.tolist()]
        inp.target_velocity = [0.0] * 6
        inp.target_acceleration = [0.0] * 6
        self.reason = ""
        self._failed = ""
        self._t0_ns = state.stamp_ns
        self._last_ns = state.stamp_ns
        self._steps = 0
        try:
            res = self._otg.calculate(inp, self._traj)
        except RuckigError as exc:
            self._failed = f"move planner refused its input: {exc}"
            return
        if int(res) < 0:
            self._failed = f"move planner failed: {res}"

    def step(self, inp: ControlInput) -> tuple[Demand, ControlStatus]:
        if self._failed:
            self.reason = self._failed
            return Demand(_ZERO6), ControlStatus.FAULT
        self._steps += 1
        stamp = inp.state.stamp_ns
        gap = stamp - self._last_ns
        self._last_ns = stamp
        if 1 < self._steps <= _START_CYCLES and gap > _LATE_START * self.period * 1e9:
            # A twist of the move's first cycles went out late (ur-rtde waits for the control script's
            # handshake before the first command after a pause: 18 ms measured against the simulated
            # controller, the next cycle then 0.5 ms after it), while the robot, barely moving yet, had next
            # to nothing to follow. The plan's clock skips the delay, as if that twist had gone out on time.
            # Run on, the reference jumped ahead of the limiter stepped over the delay, whose chase of it
            # then lagged through the move and overshot the goal (22 mm in tests/motion/test_core.py's
            # plant, 9-37 mm on the simulated controller, a second to creep back). Later in a move the robot
            # holds the twist it was sent over a late cycle, and the clock must run on (module docstring).
            self._t0_ns += gap - int(round(self.period * 1e9))
        # The reference at this cycle's time, one period ahead (as the joint move samples its own):
        # a late cycle must not stretch the plan, or the robot, holding its last twist, runs past it.
        t = (inp.state.stamp_ns - self._t0_ns) * 1e-9 + self.period
        duration = self._traj.duration
        p, v, a = self._traj.at_time(min(t, duration))
        ref = np.array(p)
        v_ref = np.array(v)
        a_ref = np.array(a)

        T = inp.state.T_base_tcp
        R_meas = T[:3, :3]
        # The measured pose lags the commands by the link latency: compare it
        # with where the reference was that long ago (module docstring).
        delayed = ref - v_ref * self.params.latency
        R_ref = so3.exp(delayed[3:]) @ self._R0
        e_p = delayed[:3] - T[:3, 3]
        e_r = so3.log(R_ref @ R_meas.T)
        fb = np.concatenate([self.params.gain * e_p, self.params.angle_gain * e_r])
        # The correction is bounded: a large error (a robot that lagged far
        # behind) must not turn into a fast jerk-limited chase that overshoots.
        for sl, cap in ((slice(0, 3), self._fb_cap[0]), (slice(3, 6), self._fb_cap[1])):
            n = float(np.linalg.norm(fb[sl]))
            if n > cap:
                fb[sl] *= cap / n
        demand = v_ref + fb
        if t < duration:
            return Demand(demand, a_ref), ControlStatus.OK

        v = inp.state.v_tcp
        if (
            float(np.linalg.norm(e_p)) <= self.tolerance
            and float(np.linalg.norm(e_r)) <= self.angle_tolerance
            and float(np.linalg.norm(v[:3])) <= self.params.settle_speed
            and float(np.linalg.norm(v[3:])) <= self.params.settle_angular_speed
        ):
            return Demand(demand), ControlStatus.DONE
        if t - duration > self.params.settle_timeout:
            self.reason = (
                f"move did not settle within {self.params.settle_timeout} s: "
                f"{np.linalg.norm(e_p) * 1e3:.3f} mm, {np.linalg.norm(e_r):.4f} rad from the goal"
            )
            return Demand(_ZERO6), ControlStatus.FAULT
        return Demand(demand), ControlStatus.OK


class VelocityStream:
    """Follow the streamed twist setpoint; a setpoint older than ``timeout`` means zero (dead man)."""

    name = "stream"
    reason = ""

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout

    def start(self, state: RobotState, twist: Array, accel: Array) -> None:
        pass

    def step(self, inp: ControlInput) -> tuple[Demand, ControlStatus]:
        if inp.setpoint_age <= self.timeout:
            return Demand(inp.setpoint), ControlStatus.OK
        return Demand(_ZERO6), ControlStatus.HOLD


class ServoSlot:
    """Runs a :class:`~celld.motion.types.ServoLaw` (e.g. Algorithm 2) in the loop.

    The law gets the robot state and the latest tactile sample; its twist is
    shaped by the limiter like any other demand. A law that raises or returns
    a twist that is not 6 finite numbers is a fault, never a crash of the loop;
    a fault the law reports carries the law's own ``reason``.

    The law's protocol is checked once, when it starts (:func:`check_telemetry`
    on its first telemetry, and a ``reason`` string): a law that fails it
    faults at its first step with the reason. After that :meth:`telemetry`
    passes the law's telemetry on unchecked, every cycle; should it raise,
    the slot reports :data:`~celld.motion.types.NO_TELEMETRY` (process off)
    and keeps the first failure in ``telemetry_error``.
    """

    name = "servo"

    def __init__(self, law: ServoLaw, law_name: str = "") -> None:
        self.law = law
        self.law_name = law_name
        self.reason = ""
        self.telemetry_error = ""
        self._failed = ""

    def start(self, state: RobotState, twist: Array, accel: Array) -> None:
        self.reason = ""
        try:
            self.law.start(state)
            if not isinstance(getattr(self.law, "reason", None), str):
                raise TypeError("the law has no reason string")
            check_telemetry(self.law.telemetry())
            self._failed = ""
        except Exception as exc:  # a law must not take the loop down  # noqa: BLE001
            self._failed = f"servo law {self.law_name!r} failed to start: {exc!r}"

    def step(self, inp: ControlInput) -> tuple[Demand, ControlStatus]:
        if self._failed:
            self.reason = self._failed
            return Demand(_ZERO6), ControlStatus.FAULT
        try:
            twist, status = self.law.step(ServoInput(inp.state, inp.tactile, inp.tactile_age, inp.travel))
            twist = np.asarray(twist, dtype=np.float64)
            status = ControlStatus(status)
        except Exception as exc:  # a law must not take the loop down  # noqa: BLE001
            self.reason = f"servo law {self.law_name!r} raised {exc!r}"
            return Demand(_ZERO6), ControlStatus.FAULT
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            self.reason = f"servo law {self.law_name!r} returned a twist of shape {twist.shape} with non-finite values"
            return Demand(_ZERO6), ControlStatus.FAULT
        if status >= ControlStatus.WORKSPACE:
            # The law's own reason says what it saw (e.g. the last tag status).
            detail = self.law.reason
            self.reason = f"servo law {self.law_name!r} reported {status.name}" + (f": {detail}" if detail else "")
        return Demand(twist), status

    def telemetry(self) -> ServoTelemetry:
        """The law's :class:`~celld.motion.types.ServoTelemetry`, or the fallback (class docstring)."""
        if self._failed:
            return NO_TELEMETRY
        try:
            return self.law.telemetry()
        except Exception as exc:  # a law must not take the loop down  # noqa: BLE001
            if not self.telemetry_error:
                self.telemetry_error = f"servo law {self.law_name!r}: telemetry failed: {exc!r}"
            return NO_TELEMETRY


def check_telemetry(t: object) -> ServoTelemetry:
    """``t`` if it is a well-formed :class:`~celld.motion.types.ServoTelemetry`, else raise naming what is wrong."""
    if not isinstance(t, ServoTelemetry):
        raise TypeError(f"expected a ServoTelemetry, got {type(t).__name__}")
    if not isinstance(t.phase, int) or not -1 <= t.phase <= 127:  # the state record holds it in an int8
        raise ValueError(f"phase {t.phase!r}, expected an integer -1..127")
    if not isinstance(t.delta_n, float):
        raise TypeError(f"delta_n {t.delta_n!r}, expected a float")
    if np.shape(t.refined_base) != (3,):
        raise ValueError(f"refined_base of shape {np.shape(t.refined_base)}, expected (3,)")
    if not isinstance(t.process_on, (bool, np.bool_)):
        raise TypeError(f"process_on {t.process_on!r}, expected a bool")
    return t
