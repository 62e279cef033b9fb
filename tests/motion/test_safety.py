"""Per-cycle safety checks: robot safety bits, stop distance, workspace and sent-sequence limits."""

from __future__ import annotations

import numpy as np
import pytest

from celld.config import MotionLimits
from celld.motion.limits import CartesianLimits, JointMoveLimits
from celld.motion.safety import (
    Fault,
    JointSequenceMonitor,
    SequenceMonitor,
    StopDistance,
    WorkspaceGuard,
    describe,
    robot_faults,
    status_of,
)
from celld.motion.types import ControlStatus

LIMITS = CartesianLimits.from_config(MotionLimits())


@pytest.mark.parametrize(
    "bits, fault",
    [
        (1, Fault.NONE),
        (1 << 2, Fault.PROTECTIVE_STOP),
        (1 << 4, Fault.PROTECTIVE_STOP),
        (1 << 7, Fault.EMERGENCY_STOP),
        (1 << 9, Fault.ROBOT_FAULT),
    ],
)
def test_robot_safety_bits(bits: int, fault: Fault) -> None:
    assert robot_faults(bits) == fault


def test_status_priority_and_description() -> None:
    assert status_of(Fault.STALE_TACTILE | Fault.PROTECTIVE_STOP) == ControlStatus.SAFETY
    assert status_of(Fault.JERK | Fault.STALE_TACTILE) == ControlStatus.LIMIT
    assert status_of(Fault.NONE) == ControlStatus.OK
    assert describe(Fault.WORKSPACE | Fault.STALE_STATE) == "workspace, stale state"


def test_stop_distance_matches_the_closed_form() -> None:
    stop = StopDistance(accel=1.0, jerk=10.0)
    # From cruise (a = 0) at v >= a^2/j: t = v/a + a/j, d = v t / 2 (symmetric S-curve).
    for v in (0.1, 0.25):
        assert stop(v, 0.0) == pytest.approx(v * (v / 1.0 + 1.0 / 10.0) / 2, rel=1e-9)
    # Already decelerating stops sooner; still accelerating goes further.
    assert stop(0.25, -1.0) < stop(0.25, 0.0) < stop(0.25, 1.0)
    assert stop(0.0, 0.0) == 0.0


def test_workspace_guard_allows_moving_back_in() -> None:
    guard = WorkspaceGuard((-1, -1, 0), (1, 1, 1), LIMITS, latency=0.006)
    z = np.zeros(3)
    assert not guard(np.array([0.5, 0, 0.5]), np.array([0.25, 0, 0]), z)
    assert guard(np.array([0.97, 0, 0.5]), np.array([0.25, 0, 0]), z)
    assert guard(np.array([1.1, 0, 0.5]), np.array([0.01, 0, 0]), z)
    assert not guard(np.array([1.1, 0, 0.5]), np.array([-0.1, 0, 0]), z)
    assert not guard(np.array([1.1, 0, 0.5]), z, z)


def test_sequence_monitor_flags_each_breach() -> None:
    m = SequenceMonitor(LIMITS, 0.002)
    assert m.check([0.0] * 6) == Fault.NONE
    assert m.check([1e-5, 0, 0, 0, 0, 0]) == Fault.NONE  # jerk 2.5 m/s^3 from rest
    m.reset()
    assert m.check([0.001, 0, 0, 0, 0, 0]) & Fault.JERK  # 250 m/s^3
    m.reset()
    f = m.check([0.3, 0, 0, 0, 0, 0])
    assert f & Fault.SPEED and f & Fault.ACCEL and f & Fault.JERK
    m.reset()
    assert m.check([0, 0, 0, 0, 0, 0.02]) & Fault.JERK  # angular: 5000 rad/s^3 > 40


def test_the_joint_monitor_differences_the_speeds_over_the_times_they_went_out() -> None:
    # A smooth speed profile within the limits (jerk 15, then accel 1.5 rad/s^2), sent at 2 ms with jitter
    # and every seventh send 30 ms late: within the limits at every send, as the robot saw them.
    lim = JointMoveLimits(speed=1.0, accel=2.0, jerk=20.0)
    rng = np.random.default_rng(3)
    m = JointSequenceMonitor(lim, 0.002)
    u = np.array([1.0, -0.5, 0.3, 0.0, 0.2, -1.0])

    def v(t: float) -> np.ndarray:  # jerk 15 for 0.1 s, then accel 1.5 held: an s-curve from rest
        return u * (7.5 * t * t if t < 0.1 else 0.075 + 1.5 * (t - 0.1))

    t = 0.0
    for k in range(90):
        dt = 0.030 if k % 7 == 3 else 0.002 + rng.uniform(-5e-4, 5e-4)
        t += dt
        assert m.check(v(t), dt) == Fault.NONE, k
    # The same speeds with their times taken as one period apart break the acceleration limit...
    m.reset()
    faults = Fault.NONE
    t = 0.0
    for k in range(60):
        t += 0.030 if k % 7 == 3 else 0.002
        faults |= m.check(v(t))
    assert faults & Fault.ACCEL
    # ...and a jump is a jump however late it comes.
    m.reset()
    assert m.check([0.0] * 6) == Fault.NONE
    assert m.check([0.5, 0, 0, 0, 0, 0], 0.030) & Fault.ACCEL
