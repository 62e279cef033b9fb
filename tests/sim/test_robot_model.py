"""The simulated arm without sockets: profiles, motions, safety limits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import trapezoid

from celld.robot import kinematics as kin
from celld.sim.robot import geometry as g
from celld.sim.robot import model as m

DT = 0.002
Q_HOME = [0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0]


def make_arm(q0=Q_HOME, tcp_speed: float = 1.5, box=((-1.5, -1.5, -0.5), (1.5, 1.5, 1.5))) -> m.Arm:
    limits = m.ArmLimits(kin.UR10E_LIMITS, tcp_speed, 15.0, 40.0, box[0], box[1])
    return m.Arm(limits, q0, [0.0] * 6)


def run(arm: m.Arm, seconds: float) -> str | None:
    for _ in range(round(seconds / DT)):
        fault = arm.step(DT)
        if fault:
            return fault
    return None


@pytest.mark.parametrize(
    ("length", "v0", "vmax", "acc"),
    [(0.3, 0.0, 0.25, 1.2), (0.01, 0.0, 0.25, 1.2), (0.3, 0.1, 0.25, 1.2), (0.3, 0.4, 0.25, 1.2), (0.01, 0.3, 0.25, 1.2)],
)
def test_trapezoid_ends_on_the_target_within_its_limits(length: float, v0: float, vmax: float, acc: float) -> None:
    p = m.Trapezoid(length, v0, vmax, acc)
    t = np.linspace(0.0, p.duration, 2001)
    s, v = np.array([p.sample(x) for x in t]).T
    assert s[-1] == pytest.approx(length, abs=1e-12) and v[-1] == 0.0
    assert np.all(np.diff(s) >= -1e-12)
    assert v[0] == pytest.approx(v0)
    if v0 <= vmax and v0 * v0 / (2 * acc) < length:
        assert v.max() <= vmax + 1e-12
        assert np.abs(np.diff(v) / np.diff(t)).max() <= acc * (1 + 1e-6)
    # Position is the integral of speed.
    assert trapezoid(v, t) == pytest.approx(length, rel=1e-4)


def test_speed_l_integrates_the_ramp_exactly_and_keeps_the_speed() -> None:
    arm = make_arm()
    T0 = list(arm.T_tcp)
    v, acc, seconds = 0.05, 0.25, 10.0
    arm.start(m.CartesianVelocity(arm, [v, 0.0, -v / 2, 0.0, 0.0, 0.1], acc))
    assert run(arm, seconds) is None
    # Ramp-up at acc, then constant: distance = v T - v^2 / (2 a) along the direction.
    speed = math.hypot(v, v / 2)
    expected = speed * seconds - speed**2 / (2 * acc)
    moved = g.norm3(arm.T_tcp[3] - T0[3], arm.T_tcp[7] - T0[7], arm.T_tcp[11] - T0[11])
    # (The ramp ends inside a cycle; the trapezoidal integration is exact except there, < 1e-7 m.)
    assert moved == pytest.approx(expected, abs=1e-6)
    assert g.norm3(*g.relative_rotvec(T0, arm.T_tcp)) == pytest.approx(0.1 * seconds - 0.1**2 / (2 * acc), abs=1e-6)
    # The joints carry the integrated pose.
    np.testing.assert_allclose(kin.forward_rows(arm.q), arm.T_tcp, atol=1e-12)
    assert arm.tcp_speed[0] == pytest.approx(v, abs=1e-12)


def test_stop_linear_decelerates_at_the_given_rate() -> None:
    arm = make_arm()
    arm.start(m.CartesianVelocity(arm, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0], 10.0))
    run(arm, 0.1)
    x0 = arm.T_tcp[3]
    stop = arm.stop_linear(0.5)
    steps = 0
    while not stop.done:
        assert arm.step(DT) is None
        steps += 1
    assert steps * DT == pytest.approx(0.1 / 0.5, abs=DT)
    assert arm.T_tcp[3] - x0 == pytest.approx(0.1**2 / (2 * 0.5), abs=1e-6)
    assert arm.step(DT) is None and arm.steady


def test_move_l_follows_a_straight_line_and_ends_exactly() -> None:
    arm = make_arm()
    T0 = list(arm.T_tcp)
    goal = g.pose_from_rows(T0)
    goal[0] += 0.2
    goal[2] -= 0.1
    goal[5] += 0.3
    T_goal = g.rows_from_pose(goal)
    arm.start(m.LinearTrajectory(arm, T_goal, 0.25, 1.2))
    direction = np.array([0.2, 0.0, -0.1]) / math.hypot(0.2, 0.1)
    speeds = []
    while arm.motion is not None:
        assert arm.step(DT) is None
        p = np.array([arm.T_tcp[3] - T0[3], arm.T_tcp[7] - T0[7], arm.T_tcp[11] - T0[11]])
        assert np.linalg.norm(p - direction * (p @ direction)) < 1e-9  # on the line
        speeds.append(g.norm3(*arm.tcp_speed[:3]))
    np.testing.assert_allclose(arm.T_tcp, T_goal, atol=1e-12)
    assert max(speeds) == pytest.approx(0.25, abs=1e-3)


def test_move_j_is_synchronised_and_ends_exactly() -> None:
    arm = make_arm()
    goal = np.array(Q_HOME) + [0.5, -0.2, 0.3, 0.0, 0.1, -0.4]
    arm.start(m.JointTrajectory(arm, goal.tolist(), 1.0, 2.0))
    peak = np.zeros(6)
    while arm.motion is not None:
        assert arm.step(DT) is None
        peak = np.maximum(peak, np.abs(arm.qd))
    np.testing.assert_allclose(arm.q, goal, atol=1e-15)
    # The leading joint (0.5 rad) reaches 1 rad/s, the others in proportion.
    # (Finite differences over 2 ms shave a little off the peak of the triangular profile.)
    np.testing.assert_allclose(peak, np.abs(goal - Q_HOME) / 0.5 * 1.0, rtol=5e-3, atol=1e-12)


def test_servo_lags_a_ramp_by_its_time_constant() -> None:
    arm = make_arm()
    lookahead, gain = 0.1, 300.0
    servo = m.JointServo(arm, arm.q, lookahead, gain)
    arm.start(servo)
    speed = 0.2  # rad/s on joint 0
    for k in range(1, 1001):
        target = list(Q_HOME)
        target[0] += speed * DT * k
        servo.set_target(target, lookahead, gain)
        assert arm.step(DT) is None
    lag = Q_HOME[0] + speed * DT * 1000 - arm.q[0]
    assert lag == pytest.approx(speed * (lookahead + 1 / gain), rel=0.02)


def test_joint_range_stops_the_arm() -> None:
    q0 = list(Q_HOME)
    q0[5] = 2 * math.pi - 0.01
    arm = make_arm(q0)
    arm.start(m.JointVelocity(arm, [0.0, 0.0, 0.0, 0.0, 0.0, 0.5], 5.0))
    fault = run(arm, 1.0)
    assert fault is not None and fault.startswith("joint position limit: joint 5")
    assert arm.q[5] <= 2 * math.pi and arm.steady


def test_tool_speed_above_the_safety_limit_stops_the_arm() -> None:
    arm = make_arm(tcp_speed=0.3)
    arm.start(m.CartesianVelocity(arm, [0.5, 0.0, 0.0, 0.0, 0.0, 0.0], 1.0))
    fault = run(arm, 1.0)
    assert fault is not None and fault.startswith("tool speed limit")
    # Stopped where the speed crossed 0.3 m/s: after 0.3 s of ramp at 1 m/s^2.
    assert g.norm3(*arm.tcp_speed[:3]) == 0.0


def test_workspace_box_stops_leaving_but_allows_returning() -> None:
    arm = make_arm(box=((-1.5, -1.5, 0.6), (1.5, 1.5, 1.5)))  # TCP starts at z = 0.677
    arm.start(m.CartesianVelocity(arm, [0.0, 0.0, -0.1, 0.0, 0.0, 0.0], 10.0))
    fault = run(arm, 2.0)
    assert fault is not None and fault.startswith("workspace limit")
    assert arm.T_tcp[11] == pytest.approx(0.6, abs=1e-3)
    # Outside by a hair after the stop: moving back in is allowed.
    arm.start(m.CartesianVelocity(arm, [0.0, 0.0, 0.1, 0.0, 0.0, 0.0], 10.0))
    assert run(arm, 0.2) is None


def test_cartesian_path_out_of_reach_is_a_fault() -> None:
    arm = make_arm()
    arm.start(m.CartesianVelocity(arm, [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0], 15.0))
    fault = run(arm, 3.0)
    assert fault is not None
    assert fault.startswith(("position limit", "joint speed limit", "tool speed limit"))
