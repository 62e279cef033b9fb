"""Per-cycle safety checks of the motion loop (pure).

Checked every cycle, each a :class:`Fault` bit; any of them ends the active
motion in a jerk-limited stop with a status the job sees:

- the robot's own safety state (protective stop, e-stop, violation, fault),
  read from ``safety_status_bits``; the robot has then stopped by itself;
- stale robot state (older than the configured number of cycles);
- a stale tactile sample while the servo runs (bound from the config);
- the workspace box: where the TCP would come to rest if a jerk-limited stop
  started now, plus the link latency, must not be outside the box on a side
  it is moving towards (moving back in from outside is allowed);
- the speed, acceleration and jerk norms of the twists actually sent
  (finite differences), which the limiter guarantees, and of every joint's
  speed sent in a joint move, which its planner guarantees; a breach means a
  bug, and still stops the robot.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import IntFlag

import numpy as np
from numpy.typing import NDArray
from ruckig import ControlInterface, InputParameter, Ruckig, RuckigError, Trajectory

from celld.motion.limits import CartesianLimits, JointMoveLimits
from celld.motion.types import ControlStatus

Array = NDArray[np.float64]

# UR safety_status_bits (RTDE guide): which bits mean the robot stopped itself.
_BIT_PROTECTIVE = 1 << 2
_BIT_SAFEGUARD = 1 << 4
_BITS_ESTOP = (1 << 5) | (1 << 6) | (1 << 7)
_BITS_ROBOT_FAULT = (1 << 8) | (1 << 9) | (1 << 10)
# The limiter's stop uses boxes inside the norm balls, so it takes a little
# longer than the 1-DOF stop at the full budget: predict a bit further.
_STOP_MARGIN = 1.1
# Relative slack on the sent-sequence checks: floating-point rounding only.
_SEQUENCE_RTOL = 1e-6
_SEQUENCE_ATOL = 1e-12


class Fault(IntFlag):
    """Reasons to stop, one bit each (recorded in every state record)."""

    NONE = 0
    WORKSPACE = 1 << 0
    SPEED = 1 << 1
    ACCEL = 1 << 2
    JERK = 1 << 3
    STALE_STATE = 1 << 4
    STALE_TACTILE = 1 << 5
    PROTECTIVE_STOP = 1 << 6
    EMERGENCY_STOP = 1 << 7
    ROBOT_FAULT = 1 << 8
    COLLISION = 1 << 9  # the torch's collision (breakaway) input of the power source's wiring


ROBOT_STOPPED = Fault.PROTECTIVE_STOP | Fault.EMERGENCY_STOP | Fault.ROBOT_FAULT
LIMITS = Fault.SPEED | Fault.ACCEL | Fault.JERK


def robot_faults(safety_bits: int) -> Fault:
    """Faults the robot reports in its ``safety_status_bits``."""
    f = Fault.NONE
    if safety_bits & (_BIT_PROTECTIVE | _BIT_SAFEGUARD):
        f |= Fault.PROTECTIVE_STOP
    if safety_bits & _BITS_ESTOP:
        f |= Fault.EMERGENCY_STOP
    if safety_bits & _BITS_ROBOT_FAULT:
        f |= Fault.ROBOT_FAULT
    return f


def status_of(faults: Fault) -> ControlStatus:
    """The status a set of faults is reported as, most severe first."""
    if faults & ROBOT_STOPPED:
        return ControlStatus.SAFETY
    if faults & Fault.COLLISION:
        return ControlStatus.COLLISION
    if faults & Fault.STALE_STATE:
        return ControlStatus.STALE_STATE
    if faults & Fault.WORKSPACE:
        return ControlStatus.WORKSPACE
    if faults & LIMITS:
        return ControlStatus.LIMIT
    if faults & Fault.STALE_TACTILE:
        return ControlStatus.STALE_TACTILE
    return ControlStatus.OK


def describe(faults: Fault) -> str:
    """A short text naming every fault bit set."""
    return ", ".join(f.name.lower().replace("_", " ") for f in Fault if f and f in faults and f.name) or "none"


def inside(p: Sequence[float] | np.ndarray, lo: Sequence[float], hi: Sequence[float]) -> bool:
    """True when the point ``p`` (3,) lies in the box ``[lo, hi]``."""
    return all(lo[i] <= p[i] <= hi[i] for i in range(3))


class StopDistance:
    """Distance a jerk-limited stop covers, along the direction of motion (1-DOF ruckig)."""

    def __init__(self, accel: float, jerk: float) -> None:
        self._otg = Ruckig(1)
        self._inp = InputParameter(1)
        self._traj = Trajectory(1)
        self._inp.control_interface = ControlInterface.Velocity
        self._inp.max_velocity = [1e3]
        self._inp.max_acceleration = [accel]
        self._inp.max_jerk = [jerk]
        self._inp.target_velocity = [0.0]
        self._inp.target_acceleration = [0.0]

    def __call__(self, speed: float, accel_along: float) -> float:
        """Metres covered from ``speed`` (>= 0) and acceleration along the motion until rest."""
        inp = self._inp
        inp.current_position = [0.0]
        inp.current_velocity = [speed]
        inp.current_acceleration = [accel_along]
        try:
            self._otg.calculate(inp, self._traj)
        except RuckigError:
            return math.inf
        pos, _, _ = self._traj.at_time(self._traj.duration)
        return max(float(pos[0]), 0.0)


class WorkspaceGuard:
    """Would a stop started now end outside the box, on a side the TCP moves towards?

    Parameters
    ----------
    lo, hi : sequence of 3 floats
        The workspace box of the TCP in the base frame, m.
    limits : CartesianLimits
        The stop uses the linear acceleration and jerk limits.
    latency : float
        Seconds of travel at the current speed before a stop takes effect:
        the link's latency plus the cycle in which the breach is found.
    """

    def __init__(self, lo: Sequence[float], hi: Sequence[float], limits: CartesianLimits, latency: float) -> None:
        self.lo = tuple(float(x) for x in lo)
        self.hi = tuple(float(x) for x in hi)
        self.latency = latency
        self._stop = StopDistance(limits.linear_accel, limits.linear_jerk)

    def __call__(self, p: Array, v: Array, a: Array) -> bool:
        """True on a breach. ``p`` (3,) measured TCP position, ``v``, ``a`` (3,) commanded."""
        vx, vy, vz = float(v[0]), float(v[1]), float(v[2])
        speed = math.sqrt(vx * vx + vy * vy + vz * vz)
        reach = 0.0
        if speed > 1e-12:
            along = (float(a[0]) * vx + float(a[1]) * vy + float(a[2]) * vz) / speed
            reach = self._stop(speed, along) * _STOP_MARGIN / speed + self.latency
        for i, vi in enumerate((vx, vy, vz)):
            q = float(p[i]) + vi * reach
            if q > self.hi[i] and vi > 0.0:
                return True
            if q < self.lo[i] and vi < 0.0:
                return True
        return False


class SequenceMonitor:
    """Checks the norms of the twists actually sent: speed, and acceleration and jerk by finite differences."""

    def __init__(self, limits: CartesianLimits, period: float) -> None:
        self.limits = limits
        self.period = period
        self._prev1 = [0.0] * 6
        self._prev2 = [0.0] * 6
        self._dt1 = period  # s between prev2 and prev1

    def reset(self) -> None:
        """The robot is at rest and nothing is being sent."""
        self._prev1 = [0.0] * 6
        self._prev2 = [0.0] * 6
        self._dt1 = self.period

    def check(self, twist: Sequence[float] | np.ndarray, dt: float | None = None) -> Fault:
        """Record ``twist`` (6,) as sent this cycle, ``dt`` s after the last (one period by default), and
        return the limits it breaks: differences over the times the twists went out, as the limiter shapes them."""
        lim = self.limits
        d1 = self.period if dt is None else dt
        d0 = self._dt1
        mid = 0.5 * (d0 + d1)  # between the two accelerations' midpoints
        v = [float(x) for x in twist]
        p1, p2 = self._prev1, self._prev2
        f = Fault.NONE
        for o, vmax, amax, jmax in (
            (0, lim.linear_speed, lim.linear_accel, lim.linear_jerk),
            (3, lim.angular_speed, lim.angular_accel, lim.angular_jerk),
        ):
            s = math.hypot(v[o], v[o + 1], v[o + 2])
            a1 = [(v[i] - p1[i]) / d1 for i in range(o, o + 3)]
            acc = math.hypot(*a1)
            jerk = math.hypot(*(a1[i - o] - (p1[i] - p2[i]) / d0 for i in range(o, o + 3))) / mid
            if s > vmax * (1 + _SEQUENCE_RTOL) + _SEQUENCE_ATOL:
                f |= Fault.SPEED
            if acc > amax * (1 + _SEQUENCE_RTOL) + _SEQUENCE_ATOL / d1:
                f |= Fault.ACCEL
            if jerk > jmax * (1 + _SEQUENCE_RTOL) + _SEQUENCE_ATOL / (d1 * mid):
                f |= Fault.JERK
        self._prev2 = p1
        self._prev1 = v
        self._dt1 = d1
        return f


class JointSequenceMonitor:
    """Checks every joint's speed sent in a joint move: speed, and acceleration and jerk by finite differences.

    The differences are taken over the times the speeds went out (as
    :class:`SequenceMonitor`'s): a joint move samples its trajectory by the
    clock, so after a late cycle its speeds have moved on by the time that
    passed, which the robot saw pass too.
    """

    def __init__(self, limits: JointMoveLimits, period: float) -> None:
        self.limits = limits
        self.period = period
        self._prev1 = [0.0] * 6
        self._prev2 = [0.0] * 6
        self._dt1 = period  # s between prev2 and prev1

    def reset(self) -> None:
        """The robot is at rest and nothing is being sent."""
        self._prev1 = [0.0] * 6
        self._prev2 = [0.0] * 6
        self._dt1 = self.period

    def check(self, qd: Sequence[float] | np.ndarray, dt: float | None = None) -> Fault:
        """Record the joint speeds ``qd`` (6,) sent ``dt`` s after the last (one period by default) and
        return the limits they break."""
        lim = self.limits
        dt = self.period if dt is None else dt
        dt0 = self._dt1
        mid = 0.5 * (dt + dt0)  # between the two accelerations' midpoints
        v = [float(x) for x in qd]
        p1, p2 = self._prev1, self._prev2
        f = Fault.NONE
        for i in range(6):
            if abs(v[i]) > lim.speed * (1 + _SEQUENCE_RTOL) + _SEQUENCE_ATOL:
                f |= Fault.SPEED
            a1 = (v[i] - p1[i]) / dt
            if abs(a1) > lim.accel * (1 + _SEQUENCE_RTOL) + _SEQUENCE_ATOL / dt:
                f |= Fault.ACCEL
            if abs(a1 - (p1[i] - p2[i]) / dt0) / mid > lim.jerk * (1 + _SEQUENCE_RTOL) + _SEQUENCE_ATOL / (dt * mid):
                f |= Fault.JERK
        self._prev2 = p1
        self._prev1 = v
        self._dt1 = dt
        return f
