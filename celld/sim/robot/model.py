"""The simulated UR10e arm: joint state, motion generators and safety limits (pure).

No sockets, no clocks: :meth:`Arm.step` advances the arm by ``dt`` and returns
the reason of a protective stop, or None. Plain floats throughout, because the
simulator calls it 500 times a second.

Motions, as the UR controller runs them:

- :class:`CartesianVelocity` (``speedl``, ``stopl``): the TCP twist ramps to its
  target at the given acceleration; the pose is integrated and mapped to joints
  by the analytic inverse nearest the current joints. It keeps its twist until
  replaced or stopped, like the controller's re-issued ``speedl``.
- :class:`JointVelocity` (``speedj``, ``stopj``): the same in joint space.
- :class:`JointTrajectory` (``movej``) and :class:`LinearTrajectory` (``movel``):
  trapezoidal profiles of the leading axis / of the path, starting from the
  current speed along the path, ending exactly on the target.
- :class:`JointServo` (``servoj``, and ``servol`` through the inverse): a
  first-order lag of time constant ``lookahead_time + 1/gain`` towards the
  target, within the joint speed limits. This approximates the controller's
  filter; it is not its exact dynamics.

Safety, checked on every step: joint range, joint speed, TCP speed above the
safety limit, and the TCP leaving the workspace box. A violation halts the arm.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import NamedTuple

from celld.robot import kinematics as kin
from celld.robot.kinematics import Rows
from celld.sim.robot import geometry as g

# Joint and TCP speeds may exceed their limits by this factor before the safety stops the arm.
_SPEED_TOLERANCE = 1.02
# Distances (m) and angles (rad) below these count as "no motion" for a trajectory.
_EPS_DIST = 1e-9
_EPS_ANGLE = 1e-9
# Joint positions kept for get_actual_joint_positions_history (one per step).
HISTORY_LENGTH = 512
# Tool rotation limits of linear moves: speed rad/s, acceleration rad/s^2.
TOOL_ROT_SPEED = math.pi
TOOL_ROT_ACC = 4 * math.pi


class ArmLimits(NamedTuple):
    """Kinematic and safety limits of the simulated arm (SI)."""

    joints: kin.JointLimits
    tcp_speed: float
    tcp_acc: float
    joint_acc: float
    workspace_min: tuple[float, float, float]
    workspace_max: tuple[float, float, float]


class Trapezoid:
    """A 1-D trapezoidal profile over ``length`` from speed ``v0`` to rest.

    Accelerates (or decelerates) from ``v0`` to the cruise speed at ``acc``,
    cruises, then decelerates at ``acc`` to stop at ``length``. When ``v0`` is
    too high to stop within ``length`` at ``acc``, it decelerates uniformly
    (harder than ``acc``) so it still ends on the target.
    """

    def __init__(self, length: float, v0: float, vmax: float, acc: float) -> None:
        self.length = length
        v0 = max(0.0, v0)
        self.v0 = v0
        if length <= 0.0:
            self.t1 = self.t2 = self.t3 = 0.0
            self.vp = self.a1 = self.a3 = 0.0
        elif v0 * v0 / (2.0 * acc) >= length:
            self._uniform_stop(v0, length)
        else:
            vp = math.sqrt(acc * length + 0.5 * v0 * v0)
            if vp <= vmax:
                self.vp, self.t1, self.t2, self.t3 = vp, (vp - v0) / acc, 0.0, vp / acc
            else:
                t1 = abs(v0 - vmax) / acc
                d1 = 0.5 * (v0 + vmax) * t1
                d3 = vmax * vmax / (2.0 * acc)
                if d1 + d3 > length:  # v0 above vmax and too close to brake to vmax first
                    self._uniform_stop(v0, length)
                    return
                self.vp, self.t1, self.t2, self.t3 = vmax, t1, (length - d1 - d3) / vmax, vmax / acc
            self.a1 = (self.vp - v0) / self.t1 if self.t1 > 0.0 else 0.0
            self.a3 = self.vp / self.t3 if self.t3 > 0.0 else 0.0
        self.s1 = self.v0 * self.t1 + 0.5 * self.a1 * self.t1 * self.t1
        self.s2 = self.s1 + self.vp * self.t2
        self.duration = self.t1 + self.t2 + self.t3

    def _uniform_stop(self, v0: float, length: float) -> None:
        self.vp, self.t1, self.t2 = v0, 0.0, 0.0
        self.t3 = 2.0 * length / v0
        self.a1, self.a3 = 0.0, v0 / self.t3

    def sample(self, t: float) -> tuple[float, float]:
        """``(s, v)`` at time ``t`` after the start."""
        if t >= self.duration:
            return self.length, 0.0
        if t < self.t1:
            return self.v0 * t + 0.5 * self.a1 * t * t, self.v0 + self.a1 * t
        if t < self.t1 + self.t2:
            return self.s1 + self.vp * (t - self.t1), self.vp
        tau = t - self.t1 - self.t2
        return self.s2 + self.vp * tau - 0.5 * self.a3 * tau * tau, self.vp - self.a3 * tau


class Motion:
    """A motion generator. :meth:`advance` returns the next joints, or None on a fault."""

    done = False
    fault: str | None = None
    cartesian = False

    def advance(self, arm: Arm, dt: float) -> list[float] | None:  # pragma: no cover - interface
        raise NotImplementedError

    def target_pose(self, arm: Arm) -> Rows | None:
        """``T_base_tcp`` this motion heads for, if it has one."""
        return None


class CartesianVelocity(Motion):
    """TCP twist ``[vx, vy, vz, wx, wy, wz]`` (base frame) ramped at ``acc`` (m/s^2) and ``acc_rot`` (rad/s^2)."""

    cartesian = True

    def __init__(self, arm: Arm, target: Sequence[float], acc: float, acc_rot: float | None = None, stopping: bool = False) -> None:
        self.v = list(arm.current_twist())
        self.T = list(arm.T_tcp)
        self.stopping = stopping
        self.set_target(target, acc, acc_rot)

    def set_target(self, target: Sequence[float], acc: float, acc_rot: float | None = None) -> None:
        self.target = [float(x) for x in target]
        self.acc = acc
        self.acc_rot = acc if acc_rot is None else acc_rot

    def advance(self, arm: Arm, dt: float) -> list[float] | None:
        v0 = self.v
        v1 = _ramp3(v0[0:3], self.target[0:3], self.acc * dt) + _ramp3(v0[3:6], self.target[3:6], self.acc_rot * dt)
        T = self.T
        h = 0.5 * dt
        p = [T[3] + (v0[0] + v1[0]) * h, T[7] + (v0[1] + v1[1]) * h, T[11] + (v0[2] + v1[2]) * h]
        dR = g.rot_from_rotvec((v0[3] + v1[3]) * h, (v0[4] + v1[4]) * h, (v0[5] + v1[5]) * h)
        T_new = g.with_rotation(g.rot_mul(dR, g.rot_of(T)), p)
        q = arm.ik(T_new, arm.q)
        if q is None:
            self.fault = "position limit: the TCP path leaves the reach of the arm"
            return None
        self.v, self.T = v1, T_new
        if self.stopping and not any(v1):
            self.done = True
        return q


class JointVelocity(Motion):
    """Joint speeds (rad/s) ramped at ``acc`` (rad/s^2, leading joint)."""

    def __init__(self, arm: Arm, target: Sequence[float], acc: float, stopping: bool = False) -> None:
        self.qd = list(arm.qd)
        self.stopping = stopping
        self.set_target(target, acc)

    def set_target(self, target: Sequence[float], acc: float) -> None:
        self.target = [float(x) for x in target]
        self.acc = acc

    def advance(self, arm: Arm, dt: float) -> list[float] | None:
        qd0 = self.qd
        d = [t - v for t, v in zip(self.target, qd0)]
        m = max(abs(x) for x in d)
        step = self.acc * dt
        qd1 = list(self.target) if m <= step else [v + x * (step / m) for v, x in zip(qd0, d)]
        q = [qi + 0.5 * (a + b) * dt for qi, a, b in zip(arm.q, qd0, qd1)]
        self.qd = qd1
        if self.stopping and not any(qd1):
            self.done = True
        return q


class JointTrajectory(Motion):
    """``movej``: straight line in joint space, trapezoid on the leading joint."""

    def __init__(self, arm: Arm, q_goal: Sequence[float], speed: float, acc: float) -> None:
        self.q0 = list(arm.q)
        self.q1 = [float(x) for x in q_goal]
        delta = [b - a for a, b in zip(self.q0, self.q1)]
        length = max(abs(x) for x in delta)
        self.u = [x / length for x in delta] if length > 0.0 else [0.0] * 6
        # Speed along the line now: least squares of qd on the direction u.
        uu = sum(x * x for x in self.u)
        v0 = sum(a * b for a, b in zip(arm.qd, self.u)) / uu if uu > 0.0 else 0.0
        self.profile = Trapezoid(length, v0, speed, acc)
        self.t = 0.0

    def advance(self, arm: Arm, dt: float) -> list[float] | None:
        self.t += dt
        if self.t >= self.profile.duration:
            self.done = True
            return list(self.q1)
        s, _ = self.profile.sample(self.t)
        return [a + u * s for a, u in zip(self.q0, self.u)]

    def target_pose(self, arm: Arm) -> Rows | None:
        return arm.fk_tcp(self.q1)


class LinearTrajectory(Motion):
    """``movel``: straight TCP line and a uniform turn, one trapezoid on the path parameter."""

    cartesian = True

    def __init__(self, arm: Arm, T_goal: Rows, speed: float, acc: float) -> None:
        self.T0 = list(arm.T_tcp)
        self.T1 = list(T_goal)
        self.dp = [self.T1[3] - self.T0[3], self.T1[7] - self.T0[7], self.T1[11] - self.T0[11]]
        self.rv = g.relative_rotvec(self.T0, self.T1)
        self.R0 = g.rot_of(self.T0)
        dist = g.norm3(*self.dp)
        angle = g.norm3(*self.rv)
        v_lim, a_lim, v0 = math.inf, math.inf, 0.0
        twist = arm.current_twist()
        if dist > _EPS_DIST:
            v_lim, a_lim = speed / dist, acc / dist
            v0 = (twist[0] * self.dp[0] + twist[1] * self.dp[1] + twist[2] * self.dp[2]) / (dist * dist)
        if angle > _EPS_ANGLE:
            v_lim, a_lim = min(v_lim, TOOL_ROT_SPEED / angle), min(a_lim, TOOL_ROT_ACC / angle)
            if dist <= _EPS_DIST:
                v0 = (twist[3] * self.rv[0] + twist[4] * self.rv[1] + twist[5] * self.rv[2]) / (angle * angle)
        length = 1.0 if (dist > _EPS_DIST or angle > _EPS_ANGLE) else 0.0
        self.profile = Trapezoid(length, v0, v_lim, a_lim) if length else Trapezoid(0.0, 0.0, 1.0, 1.0)
        self.t = 0.0

    def pose_at(self, s: float) -> Rows:
        T0 = self.T0
        p = [T0[3] + s * self.dp[0], T0[7] + s * self.dp[1], T0[11] + s * self.dp[2]]
        R = g.rot_mul(g.rot_from_rotvec(s * self.rv[0], s * self.rv[1], s * self.rv[2]), self.R0)
        return g.with_rotation(R, p)

    def advance(self, arm: Arm, dt: float) -> list[float] | None:
        self.t += dt
        if self.t >= self.profile.duration:
            T = self.T1
            self.done = True
        else:
            T = self.pose_at(self.profile.sample(self.t)[0])
        q = arm.ik(T, arm.q)
        if q is None:
            self.fault = "position limit: the linear path leaves the reach of the arm"
            self.done = False
        return q

    def target_pose(self, arm: Arm) -> Rows | None:
        return list(self.T1)


class JointServo(Motion):
    """``servoj``: first-order lag towards the latest target, joint speeds within limits."""

    def __init__(self, arm: Arm, q_target: Sequence[float], lookahead_time: float, gain: float) -> None:
        self.set_target(q_target, lookahead_time, gain)

    def set_target(self, q_target: Sequence[float], lookahead_time: float, gain: float) -> None:
        self.q_target = [float(x) for x in q_target]
        self.tau = max(lookahead_time, 0.0) + 1.0 / max(gain, 1.0)

    def advance(self, arm: Arm, dt: float) -> list[float] | None:
        k = min(1.0, dt / self.tau)
        q = []
        for qi, ti, vmax in zip(arm.q, self.q_target, arm.limits.joints.qd_max):
            step = (ti - qi) * k
            bound = vmax * dt
            q.append(qi + max(-bound, min(bound, step)))
        return q

    def target_pose(self, arm: Arm) -> Rows | None:
        return arm.fk_tcp(self.q_target)


def _ramp3(v: Sequence[float], target: Sequence[float], max_step: float) -> list[float]:
    """``v`` moved towards ``target`` by at most ``max_step`` (Euclidean)."""
    dx, dy, dz = target[0] - v[0], target[1] - v[1], target[2] - v[2]
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    if n <= max_step:
        return [target[0], target[1], target[2]]
    k = max_step / n
    return [v[0] + dx * k, v[1] + dy * k, v[2] + dz * k]


class Arm:
    """Joint state of the simulated arm, its TCP, the active motion and the safety checks."""

    def __init__(self, limits: ArmLimits, q0: Sequence[float], tcp_offset: Sequence[float], dh: kin.DH = kin.UR10E) -> None:
        self.dh = dh
        self.limits = limits
        self.motion: Motion | None = None
        self.history: deque[list[float]] = deque(maxlen=HISTORY_LENGTH)
        self.set_tcp(tcp_offset)
        self.set_q(q0)

    # --- state --------------------------------------------------------------------

    def set_q(self, q: Sequence[float]) -> None:
        """Teleport to ``q`` at rest, cancelling any motion."""
        self.q = [float(x) for x in q]
        self.qd = [0.0] * 6
        self.qdd = [0.0] * 6
        self.motion = None
        self.T_flange = kin.forward_rows(self.q, self.dh)
        self.T_tcp = kin.compose_rows(self.T_flange, self.T_flange_tcp)
        self.tcp_speed = [0.0] * 6
        self.history.clear()
        self.history.append(list(self.q))

    def set_tcp(self, tcp_offset: Sequence[float]) -> None:
        """Set the TCP pose in the flange frame (UR pose)."""
        self.tcp_offset = [float(x) for x in tcp_offset]
        self.T_flange_tcp = g.rows_from_pose(self.tcp_offset)
        self.T_tcp_flange = kin.invert_rows(self.T_flange_tcp)
        if hasattr(self, "T_flange"):
            self.T_tcp = kin.compose_rows(self.T_flange, self.T_flange_tcp)

    def fk_tcp(self, q: Sequence[float], T_flange_tcp: Rows | None = None) -> Rows:
        """``T_base_tcp`` of joints ``q`` (with the current TCP unless one is given)."""
        return kin.compose_rows(kin.forward_rows(q, self.dh), T_flange_tcp or self.T_flange_tcp)

    def ik(self, T_base_tcp: Rows, q_near: Sequence[float]) -> list[float] | None:
        """Joints that put the TCP at ``T_base_tcp``, nearest ``q_near`` within the joint range."""
        T_flange = kin.compose_rows(T_base_tcp, self.T_tcp_flange)
        return kin.inverse_nearest_rows(T_flange, self.dh, q_near, self.limits.joints)

    def current_twist(self) -> list[float]:
        """TCP twist now: the active Cartesian velocity's own, else the measured one."""
        m = self.motion
        if isinstance(m, CartesianVelocity):
            return list(m.v)
        return list(self.tcp_speed)

    @property
    def steady(self) -> bool:
        """True when no motion runs and the joints are at rest."""
        return self.motion is None and not any(self.qd)

    # --- commands -----------------------------------------------------------------

    def start(self, motion: Motion) -> Motion:
        """Make ``motion`` the active motion (it starts from the current state)."""
        self.motion = motion
        return motion

    def stop_linear(self, decel: float) -> Motion:
        """``stopl``: bring the TCP twist to zero at ``decel`` (m/s^2)."""
        return self.start(CartesianVelocity(self, [0.0] * 6, decel, stopping=True))

    def stop_joint(self, decel: float) -> Motion:
        """``stopj``: bring the joint speeds to zero at ``decel`` (rad/s^2)."""
        return self.start(JointVelocity(self, [0.0] * 6, decel, stopping=True))

    def halt(self) -> None:
        """Stop at once (the protective stop's brake ramp is not simulated)."""
        self.motion = None
        self.qd = [0.0] * 6
        self.qdd = [0.0] * 6
        self.tcp_speed = [0.0] * 6

    # --- integration --------------------------------------------------------------

    def step(self, dt: float) -> str | None:
        """Advance the arm by ``dt`` seconds; return why the safety stopped it, or None."""
        m = self.motion
        if m is None:
            if any(self.qd):
                self.halt()
            self.history.append(self.q)
            return None
        q_new = m.advance(self, dt)
        if q_new is None:
            self.halt()
            return m.fault or "motion failed"
        T_flange = kin.forward_rows(q_new, self.dh)
        T_tcp = kin.compose_rows(T_flange, self.T_flange_tcp)
        fault = self._check(q_new, T_tcp, dt)
        if fault is not None:
            self.halt()
            return fault
        inv_dt = 1.0 / dt
        qd_new = [(b - a) * inv_dt for a, b in zip(self.q, q_new)]
        self.qdd = [(b - a) * inv_dt for a, b in zip(self.qd, qd_new)]
        rx, ry, rz = g.relative_rotvec(self.T_tcp, T_tcp)
        T0 = self.T_tcp
        self.tcp_speed = [
            (T_tcp[3] - T0[3]) * inv_dt, (T_tcp[7] - T0[7]) * inv_dt, (T_tcp[11] - T0[11]) * inv_dt,
            rx * inv_dt, ry * inv_dt, rz * inv_dt,
        ]  # fmt: skip
        self.q, self.qd, self.T_flange, self.T_tcp = q_new, qd_new, T_flange, T_tcp
        self.history.append(q_new)
        if m.done:
            self.motion = None
        return None

    def _check(self, q: Sequence[float], T_tcp: Rows, dt: float) -> str | None:
        lim = self.limits
        for j in range(6):
            if not lim.joints.q_min[j] <= q[j] <= lim.joints.q_max[j]:
                return f"joint position limit: joint {j} at {q[j]:.4f} rad, range [{lim.joints.q_min[j]:.4f}, {lim.joints.q_max[j]:.4f}]"
            qd = abs(q[j] - self.q[j]) / dt
            if qd > lim.joints.qd_max[j] * _SPEED_TOLERANCE:
                return f"joint speed limit: joint {j} at {qd:.3f} rad/s, limit {lim.joints.qd_max[j]:.3f} rad/s"
        T0 = self.T_tcp
        speed = g.norm3(T_tcp[3] - T0[3], T_tcp[7] - T0[7], T_tcp[11] - T0[11]) / dt
        if speed > lim.tcp_speed * _SPEED_TOLERANCE:
            return f"tool speed limit: TCP at {speed:.3f} m/s, limit {lim.tcp_speed:.3f} m/s"
        outside_new = _outside((T_tcp[3], T_tcp[7], T_tcp[11]), lim)
        if outside_new > 0.0 and outside_new > _outside((T0[3], T0[7], T0[11]), lim):
            p = (round(T_tcp[3], 4), round(T_tcp[7], 4), round(T_tcp[11], 4))
            return f"workspace limit: TCP at {p} m leaves the box {lim.workspace_min}..{lim.workspace_max}"
        return None

    def within_safety(self, T_tcp: Rows) -> bool:
        """True when a TCP pose lies in the workspace box."""
        return _outside((T_tcp[3], T_tcp[7], T_tcp[11]), self.limits) == 0.0

    def joints_within_limits(self, q: Sequence[float]) -> bool:
        lim = self.limits.joints
        return all(lo <= x <= hi for x, lo, hi in zip(q, lim.q_min, lim.q_max))


def _outside(p: Sequence[float], lim: ArmLimits) -> float:
    """How far (m) point ``p`` lies outside the workspace box, 0 inside."""
    d2 = 0.0
    for x, lo, hi in zip(p, lim.workspace_min, lim.workspace_max):
        e = lo - x if x < lo else (x - hi if x > hi else 0.0)
        d2 += e * e
    return math.sqrt(d2)
