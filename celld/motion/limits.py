"""Cartesian and joint motion limits, and the jerk-limited twist limiter (ruckig, velocity interface).

Every twist the motion loop sends passes through :class:`TwistLimiter`, so the
configured limits hold in every cycle whatever the controller asked for.

The limits are norms, like the TCP speed limit of the robot's own safety
system: the linear part of a twist ``[vx, vy, vz]`` and the angular part
``[wx, wy, wz]`` each have a speed, an acceleration and a jerk bound on their
Euclidean norm. ruckig limits each degree of freedom separately, so each cycle
the limiter gives it per-axis bounds that lie inside the norm balls:

- jerk: a box inscribed in the jerk ball, stretched along the velocity change
  still to do and the acceleration still to unwind, so a straight change gets
  (almost) the whole jerk budget;
- acceleration: a box inscribed in the acceleration ball that contains the
  current acceleration (so ruckig never has to brake it from outside its box),
  with the rest of the budget along the same direction;
- speed: ruckig's velocity interface has no velocity bound, so the target is
  clamped into the speed ball and a viability guard keeps every state one from
  which the acceleration can be unwound without leaving the ball. Unwinding
  along ``-a/|a|`` at the full jerk norm ``J`` moves the velocity on the
  straight segment from ``v`` to ``v + a |a| / (2 J)``; the ball is convex, so
  the state is viable when both ends lie inside. If the candidate state of a
  cycle is not viable, the cycle unwinds instead, which keeps that segment's
  far end fixed and moves ``v`` along it. Starting at rest, by induction, the
  speed, acceleration and jerk norms hold in every cycle.

Pure: arrays in, arrays out; no clock, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import IntEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, RuckigError, Synchronization

from celld.config import MotionLimits
from celld.errors import InputError

Array = NDArray[np.float64]

# Relative slack on the norm checks, for floating-point rounding only.
NORM_RTOL = 1e-9
# Share of each axis in the jerk/acceleration box before normalisation: keeps
# every axis able to move a little even when the change is along another axis.
_AXIS_FLOOR = 0.02
# Smallest share of the jerk norm an axis gets when unwinding, so a rounding-size
# acceleration never meets a zero jerk bound (which ruckig refuses).
_JERK_FLOOR = 1e-7
# Below this an acceleration has no direction.
_TINY_A = 1e-12


class CartesianLimits(NamedTuple):
    """Norm limits of the TCP twist, SI: m/s, m/s^2, m/s^3 and rad/s, rad/s^2, rad/s^3."""

    linear_speed: float
    linear_accel: float
    linear_jerk: float
    angular_speed: float
    angular_accel: float
    angular_jerk: float

    @classmethod
    def from_config(cls, m: MotionLimits) -> CartesianLimits:
        return cls(
            m.max_linear_speed,
            m.max_linear_accel,
            m.max_linear_jerk,
            m.max_angular_speed,
            m.max_angular_accel,
            m.max_angular_jerk,
        )

    def scaled(self, factor: float) -> CartesianLimits:
        """Return every limit times ``factor`` (0 < factor <= 1)."""
        if not 0.0 < factor <= 1.0:
            raise InputError(f"limit scale: expected 0 < factor <= 1, got {factor}")
        return CartesianLimits(*(x * factor for x in self))

    def speeds(self) -> tuple[float, float]:
        return self.linear_speed, self.angular_speed


class JointMoveLimits(NamedTuple):
    """Limits of every joint in a joint move, SI: rad/s, rad/s^2, rad/s^3."""

    speed: float
    accel: float
    jerk: float

    @classmethod
    def from_config(cls, m: MotionLimits) -> JointMoveLimits:
        return cls(m.max_joint_speed, m.max_joint_accel, m.max_joint_jerk)

    def scaled(self, factor: float) -> JointMoveLimits:
        """Return every limit times ``factor`` (0 < factor <= 1)."""
        if not 0.0 < factor <= 1.0:
            raise InputError(f"limit scale: expected 0 < factor <= 1, got {factor}")
        return JointMoveLimits(self.speed * factor, self.accel * factor, self.jerk * factor)


class LimiterResult(IntEnum):
    """How a limiter step went."""

    SHAPED = 0  # the target was followed within the limits
    GUARDED = 1  # the viability guard unwound the acceleration instead
    ERROR = 2  # ruckig refused the input; the output holds the previous twist


def check_twist(twist: ArrayLike, name: str = "twist") -> Array:
    """Return ``twist`` as a finite float64 (6,) array, or raise InputError."""
    arr = np.asarray(twist, dtype=np.float64)
    if arr.shape != (6,):
        raise InputError(f"{name}: expected 6 values [vx, vy, vz, wx, wy, wz] (m/s, rad/s), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinite values: {arr.tolist()}")
    return arr


def clamp_norms(twist: ArrayLike, limits: CartesianLimits) -> Array:
    """Return ``twist`` (6,) with its linear and angular parts scaled into the speed balls."""
    t = [float(x) for x in np.asarray(twist, dtype=np.float64)]
    return np.array([*_clamp_part(t[:3], limits.linear_speed), *_clamp_part(t[3:], limits.angular_speed)])


def _clamp_part(v: list[float], vmax: float) -> tuple[float, float, float]:
    n = math.hypot(v[0], v[1], v[2])
    k = vmax / n if n > vmax else 1.0
    return v[0] * k, v[1] * k, v[2] * k


def axis_weights(*parts: Sequence[float]) -> tuple[float, float, float]:
    """Unit weights (3,) of one twist part from per-axis demands ``parts`` (each (3,)).

    ``w_i`` grows with ``sum_k |parts[k][i]|`` over a small floor, and ``|w| = 1``,
    so per-axis bounds ``limit * w`` form a box inscribed in the ball of radius
    ``limit``, stretched along where the demands are. The demands must be
    scaled so that 1 means "needs the whole budget"; a demand far below 1 has
    too little direction to trust and leaves the box near its cube shape.
    """
    w = [_AXIS_FLOOR, _AXIS_FLOOR, _AXIS_FLOOR]
    for part in parts:
        w[0] += abs(part[0])
        w[1] += abs(part[1])
        w[2] += abs(part[2])
    n = math.hypot(*w)
    return w[0] / n, w[1] / n, w[2] / n


def _unwind_speed(v: Sequence[float], a: Sequence[float], jerk: float) -> float:
    """Largest speed on the way when a part unwinds its acceleration at jerk norm ``jerk``.

    Unwinding along ``-a/|a|`` at the full jerk norm moves the velocity on the
    straight segment from ``v`` to ``v + a |a| / (2 jerk)``; the ball is convex,
    so the larger end is the largest speed.
    """
    k = math.hypot(*a) / (2.0 * jerk)
    return max(math.hypot(*v), math.hypot(v[0] + a[0] * k, v[1] + a[1] * k, v[2] + a[2] * k))


class TwistLimiter:
    """Shapes commanded twists so the speed, acceleration and jerk norms hold every cycle.

    One ruckig instance in its velocity interface over the 6 twist components,
    fed back its own output (never the measured velocity), so a steady target
    costs no recalculation. The arithmetic around ruckig is on plain floats:
    numpy's per-call overhead on 3-vectors would cost more than ruckig itself.

    Parameters
    ----------
    limits : CartesianLimits
        The norm limits.
    period : float
        Control period, seconds.
    """

    def __init__(self, limits: CartesianLimits, period: float) -> None:
        if not all(math.isfinite(x) and x > 0.0 for x in limits):
            raise InputError(f"limiter: every limit must be finite and > 0, got {limits}")
        if not 0.0 < period < 1.0:
            raise InputError(f"limiter: expected a period in (0, 1) s, got {period}")
        self.limits = limits
        self.period = period
        self._otg = Ruckig(6, period)
        self._inp = InputParameter(6)
        self._out = OutputParameter(6)
        self._inp.control_interface = ControlInterface.Velocity
        # Velocity bounds are not used by the velocity interface; large but finite.
        self._inp.max_velocity = [1e3] * 6
        self._zeros = [0.0] * 6
        self._v: list[float] = [0.0] * 6
        self._a: list[float] = [0.0] * 6
        self.reset()

    @property
    def twist(self) -> Array:
        """The last output twist (6,)."""
        return np.array(self._v)

    @property
    def accel(self) -> Array:
        """The acceleration (6,) of the last output."""
        return np.array(self._a)

    def at_rest(self, tol: float = 1e-9) -> bool:
        """True when the output twist and acceleration are zero (within ``tol``)."""
        return all(abs(x) <= tol for x in self._v) and all(abs(x) <= tol for x in self._a)

    def reset(self, twist: ArrayLike | None = None, accel: ArrayLike | None = None) -> None:
        """Restart from a known state (rest by default), e.g. after the robot stopped on its own."""
        self._v = [0.0] * 6 if twist is None else check_twist(twist).tolist()
        self._a = [0.0] * 6 if accel is None else check_twist(accel, "accel").tolist()
        self._inp.current_position = self._zeros
        self._inp.current_velocity = self._v
        self._inp.current_acceleration = self._a

    def _viable(self, v: list[float], a: list[float]) -> bool:
        lim = self.limits
        return _unwind_speed(v[:3], a[:3], lim.linear_jerk) <= lim.linear_speed * (1 + NORM_RTOL) and _unwind_speed(
            v[3:], a[3:], lim.angular_jerk
        ) <= lim.angular_speed * (1 + NORM_RTOL)

    def _run(
        self,
        target_v: list[float],
        target_a: list[float],
        box_a: list[float],
        box_j: list[float],
        sync: Synchronization,
    ) -> int:
        inp = self._inp
        inp.synchronization = sync
        inp.max_acceleration = box_a
        inp.max_jerk = box_j
        inp.target_velocity = target_v
        inp.target_acceleration = target_a
        try:
            return int(self._otg.update(inp, self._out))
        except RuckigError:
            return int(Result.ErrorInvalidInput)

    def _shape(self, target: list[float], target_a: list[float], dt: float) -> int:
        """The candidate step over ``dt`` seconds: boxes inscribed in the balls, stretched along the change."""
        lim = self.limits
        v, a = self._v, self._a
        box_a = [0.0] * 6
        box_j = [0.0] * 6
        for o, amax, jmax in ((0, lim.linear_accel, lim.linear_jerk), (3, lim.angular_accel, lim.angular_jerk)):
            ap = a[o : o + 3]
            # Demands scaled to the budget: the acceleration now and at the
            # target, the jerk to go from one to the other in a period, and the
            # velocity change against what one jerk phase (amax^2 / jmax) covers.
            ka = 1.0 / amax
            kj = 1.0 / (jmax * dt)
            kv = jmax / (amax * amax)
            ta = target_a[o : o + 3]
            w = axis_weights(
                [x * ka for x in ap],
                [x * ka for x in ta],
                [(ta[i] - ap[i]) * kj for i in range(3)],
                [(target[o + i] - v[o + i]) * kv for i in range(3)],
            )
            spare = max(amax * amax - (ap[0] * ap[0] + ap[1] * ap[1] + ap[2] * ap[2]), 0.0)
            for i in range(3):
                box_a[o + i] = math.sqrt(ap[i] * ap[i] + spare * w[i] * w[i])
                box_j[o + i] = jmax * w[i]
        return self._run(target, target_a, box_a, box_j, Synchronization.Phase)

    def _unwind(self) -> int:
        """The fallback step: unwind the acceleration along -a/|a| at the full jerk norm."""
        lim = self.limits
        v, a = self._v, self._a
        target = [0.0] * 6
        box_a = [0.0] * 6
        box_j = [0.0] * 6
        for o, jmax in ((0, lim.linear_jerk), (3, lim.angular_jerk)):
            na = math.hypot(a[o], a[o + 1], a[o + 2])
            for i in range(o, o + 3):
                target[i] = v[i] + a[i] * na / (2.0 * jmax)
                box_a[i] = max(abs(a[i]), _TINY_A)
                box_j[i] = jmax * max(abs(a[i]) / na if na > _TINY_A else 0.0, _JERK_FLOOR)
        return self._run(target, self._zeros, box_a, box_j, Synchronization.No)

    def step(
        self,
        target_twist: Sequence[float] | Array,
        target_accel: Sequence[float] | Array | None = None,
        dt: float | None = None,
    ) -> tuple[Array, LimiterResult]:
        """Advance towards ``target_twist`` (6,), optionally arriving with ``target_accel``.

        ``dt`` is the time (s) since the last twist went out, one period by
        default: the robot held that twist for as long, so after a late cycle
        the next may differ from it by what the limits allow over that time.
        Returns the twist to send (a new (6,) array) and how the step went.
        The target is clamped into the speed balls first. Never raises on
        finite input: a ruckig failure returns the previous twist and
        ``LimiterResult.ERROR``.
        """
        t = [float(x) for x in target_twist]
        target = [*_clamp_part(t[:3], self.limits.linear_speed), *_clamp_part(t[3:], self.limits.angular_speed)]
        t_acc = self._zeros if target_accel is None else [float(x) for x in target_accel]
        d = self.period if dt is None else dt
        if d != self._otg.delta_time:
            self._otg.delta_time = d
        result = LimiterResult.SHAPED
        res = self._shape(target, t_acc, d)
        if res >= 0:
            v_new = self._out.new_velocity
            a_new = self._out.new_acceleration
            if not self._viable(v_new, a_new):
                res = -1
        if res < 0:
            result = LimiterResult.GUARDED
            if self._unwind() < 0:
                return np.array(self._v), LimiterResult.ERROR
            v_new = self._out.new_velocity
            a_new = self._out.new_acceleration
        self._v = v_new
        self._a = a_new
        self._inp.current_position = self._zeros
        self._inp.current_velocity = v_new
        self._inp.current_acceleration = a_new
        return np.array(v_new), result


class SequencePeaks(NamedTuple):
    """Largest norms found in a twist sequence, linear and angular parts (SI)."""

    linear_speed: float
    linear_accel: float
    linear_jerk: float
    angular_speed: float
    angular_accel: float
    angular_jerk: float

    def ratios(self, limits: CartesianLimits) -> SequencePeaks:
        """Each peak divided by its limit: every value <= 1 means the limits held."""
        return SequencePeaks(*(p / lim for p, lim in zip(self, limits)))


def sequence_peaks(twists: ArrayLike, period: float, initial: ArrayLike | None = None, spacing: ArrayLike | None = None) -> SequencePeaks:
    """Peak norms of speed, finite-difference acceleration and jerk of sent twists.

    Parameters
    ----------
    twists : array, shape (n, 6)
        Consecutive commanded twists, one per period.
    period : float
        Seconds between them.
    initial : array, shape (k, 6), optional
        Twists that came before (e.g. two zero twists for a start from rest), a period apart.
    spacing : array, shape (n,), optional
        Seconds from each twist's predecessor to it, where they did not go out a period apart (a loop's
        cycles as they ran): the differences are divided over them (the limiter shapes over them).
    """
    V = np.asarray(twists, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 6:
        raise InputError(f"twists: expected an (n, 6) array, got shape {V.shape}")
    d = np.full(len(V), period) if spacing is None else np.asarray(spacing, dtype=np.float64).reshape(-1)
    if len(d) != len(V) or not np.all(d > 0.0):
        raise InputError(f"spacing: expected {len(V)} positive times, got {len(d)}")
    if initial is not None:
        I0 = np.asarray(initial, dtype=np.float64).reshape(-1, 6)
        V = np.vstack([I0, V])
        d = np.concatenate([np.full(len(I0), period), d])
    A = np.diff(V, axis=0) / d[1:, None]
    J = np.diff(A, axis=0) / (0.5 * (d[1:-1] + d[2:]))[:, None]

    def peak(X: Array, sl: slice) -> float:
        return float(np.linalg.norm(X[:, sl], axis=1).max()) if len(X) else 0.0

    lin, ang = slice(0, 3), slice(3, 6)
    return SequencePeaks(peak(V, lin), peak(A, lin), peak(J, lin), peak(V, ang), peak(A, ang), peak(J, ang))
