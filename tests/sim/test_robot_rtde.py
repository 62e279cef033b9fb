"""Unmodified ur-rtde 1.6.5 against the simulated UR10e: receive, control, motions, getters."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import rtde_control
import rtde_receive

from celld import se3
from celld.robot import kinematics as kin
from celld.sim.robot import SimRobotHandle, launch

pytestmark = pytest.mark.process


@pytest.fixture
def robot(sim_robot: SimRobotHandle):
    """Receive and control interfaces on the simulator, disconnected at the end."""
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    c = rtde_control.RTDEControlInterface(sim_robot.host)
    yield sim_robot, r, c
    c.stopScript()
    c.disconnect()
    r.disconnect()


def test_receive_interface_streams_the_arm_at_500_hz(sim_robot: SimRobotHandle) -> None:
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    try:
        q = np.array(r.getActualQ())
        np.testing.assert_allclose(q, sim_robot.options.q0, atol=1e-12)
        T = se3.from_ur_pose(r.getActualTCPPose())
        np.testing.assert_allclose(T, kin.forward(q), atol=1e-9)
        assert r.getRobotMode() == 7 and r.getSafetyMode() == 1 and r.getRuntimeState() == 1
        stamps = []
        for _ in range(100):
            t = r.initPeriod()
            stamps.append(r.getTimestamp())
            r.waitPeriod(t)
        # Controller time advances 2 ms per package; the client may see a package twice or skip one.
        steps = np.diff(stamps)
        assert np.median(steps) == pytest.approx(0.002, abs=1e-9)
    finally:
        r.disconnect()


def test_move_l_ends_within_a_tenth_of_a_millimetre(robot) -> None:
    sim, r, c = robot
    assert c.isProgramRunning()
    start = np.array(r.getActualTCPPose())
    target = start + [0.12, -0.05, -0.08, 0.0, 0.0, 0.0]
    t0 = time.monotonic()
    assert c.moveL(target.tolist(), 0.25, 1.2)
    elapsed = time.monotonic() - t0
    # 0.153 m at 0.25 m/s and 1.2 m/s^2: 0.61 s of trapezoid plus the handshake.
    assert 0.55 < elapsed < 3.0
    end = np.array(r.getActualTCPPose())
    assert np.linalg.norm(end[:3] - target[:3]) < 1e-4
    _, T_truth, _ = sim.truth()
    assert np.linalg.norm(T_truth[:3, 3] - target[:3]) < 1e-4


def test_move_j_and_the_query_getters(robot) -> None:
    sim, r, c = robot
    q_goal = np.array(sim.options.q0) + [0.3, -0.1, 0.2, 0.1, -0.2, 0.4]
    assert c.moveJ(q_goal.tolist(), 1.0, 1.4)
    np.testing.assert_allclose(r.getActualQ(), q_goal, atol=1e-9)
    T_goal = kin.forward(q_goal)
    np.testing.assert_allclose(c.getForwardKinematics(), se3.to_ur_pose(T_goal), atol=1e-9)
    q_ik = np.array(c.getInverseKinematics(se3.to_ur_pose(T_goal).tolist()))
    np.testing.assert_allclose(kin.forward(q_ik), T_goal, atol=1e-9)
    np.testing.assert_allclose(q_ik, q_goal, atol=1e-9)  # nearest the current joints
    assert c.getTCPOffset() == pytest.approx([0.0] * 6)
    assert c.isSteady()
    assert c.isPoseWithinSafetyLimits(se3.to_ur_pose(T_goal).tolist())
    assert not c.isPoseWithinSafetyLimits([3.0, 0.0, 0.5, 0.0, math.pi, 0.0])
    assert c.isJointsWithinSafetyLimits(q_goal.tolist())
    assert c.getInverseKinematicsHasSolution(se3.to_ur_pose(T_goal).tolist())
    assert not c.getInverseKinematicsHasSolution([3.0, 0.0, 0.5, 0.0, math.pi, 0.0])
    # Real-time getters: ur-rtde reads the registers right after sending, so it sees the
    # previous answer; the second call returns the value.
    c.getActualToolFlangePose()
    time.sleep(0.01)
    np.testing.assert_allclose(c.getActualToolFlangePose(), se3.to_ur_pose(T_goal), atol=1e-9)
    c.getStepTime()
    time.sleep(0.01)
    assert c.getStepTime() == pytest.approx(0.002)
    offset = [0.0, 0.0, 0.2, 0.0, 0.0, 0.0]
    assert c.setTcp(offset)
    T_tcp = T_goal @ se3.from_ur_pose(offset)
    time.sleep(0.01)
    np.testing.assert_allclose(r.getActualTCPPose()[:3], T_tcp[:3, 3], atol=1e-9)


def test_speed_l_at_500_hz_integrates_the_commanded_profile(loopback_host: str) -> None:
    """10 s of speedL from a 500 Hz loop: the TCP follows the integral of the commands.

    The commanded profile is each command held from the moment it was sent
    (client clock) until the next one. The simulator runs at SCHED_FIFO where
    the OS allows it, so that a loaded test machine does not stall its cycle
    (a real controller never stalls); start and end come from its true state.
    """
    acc = 0.5
    n = 5000  # 10 s at 500 Hz
    with launch(loopback_host, realtime=True) as sim:
        c = rtde_control.RTDEControlInterface(sim.host)
        try:
            _, T_start, _ = sim.truth()
            sent_ns, commands = [], []
            for k in range(n):
                t = c.initPeriod()
                phase = 2 * math.pi * k / n
                # A velocity whose acceleration (<= 0.13 m/s^2) stays under acc: no ramp lag.
                xd = [0.04 * math.sin(phase), 0.03 * (1 - math.cos(phase)), 0.02 * math.sin(2 * phase), 0.0, 0.0, 0.0]
                assert c.speedL(xd, acc, 0.0)
                sent_ns.append(time.monotonic_ns())
                commands.append(xd[:3])
                c.waitPeriod(t)
            sent_ns.append(time.monotonic_ns())
            assert c.speedStop(acc)
            time.sleep(0.02)
            _, T_end, _ = sim.truth()
        finally:
            c.stopScript()
            c.disconnect()
    expected = (np.array(commands) * (np.diff(sent_ns) * 1e-9)[:, None]).sum(axis=0)
    assert np.linalg.norm(expected) > 0.3
    # The last command (v = 0 at phase 2 pi) is what speedStop decelerates from.
    assert np.linalg.norm((T_end[:3, 3] - T_start[:3, 3]) - expected) < 5e-4


def test_the_robot_keeps_the_last_speed_until_speed_stop(robot) -> None:
    sim, r, c = robot
    assert c.speedL([0.0, 0.0, -0.05, 0.0, 0.0, 0.0], 1.0, 0.0)
    time.sleep(0.3)
    t0, T0, _ = sim.truth()
    time.sleep(0.2)
    t1, T1, _ = sim.truth()
    # Still moving at the commanded speed, with no command since.
    assert (T1[2, 3] - T0[2, 3]) / ((t1 - t0) * 1e-9) == pytest.approx(-0.05, rel=1e-3)
    assert c.speedStop(1.0)
    time.sleep(0.02)  # the receive interface's copy may be a few cycles older than the control's
    assert max(abs(v) for v in r.getActualTCPSpeed()) < 1e-12


def test_watchdog_expiry_stops_the_robot_and_the_program(robot) -> None:
    sim, r, c = robot
    assert c.setWatchdog(5.0)  # 200 ms: a loaded test machine can stall the client loop for tens of ms
    for _ in range(100):
        t = c.initPeriod()
        c.speedL([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 1.0, 0.0)
        c.kickWatchdog()
        c.waitPeriod(t)
    assert c.isProgramRunning()
    assert abs(r.getActualTCPSpeed()[0] - 0.05) < 1e-6
    # The client goes silent: within 200 ms plus the stop ramp, the arm is still.
    time.sleep(0.5)
    assert not c.isProgramRunning()
    assert max(abs(v) for v in r.getActualQd()) < 1e-12
    assert sim.status()["last_stop_reason"] == "RTDE watchdog expired"
    assert c.reuploadScript()


def test_async_move_reports_progress_and_stop_l_cancels_it(robot) -> None:
    _sim, r, c = robot
    target = np.array(r.getActualTCPPose()) + [0.0, 0.2, 0.0, 0.0, 0.0, 0.0]
    assert c.moveL(target.tolist(), 0.1, 0.5, True)
    time.sleep(0.2)
    assert c.getAsyncOperationProgress() >= 0  # running
    assert np.linalg.norm(r.getActualTCPSpeed()[:3]) > 0.01
    c.stopL(2.0)  # returns nothing in 1.6.5
    assert c.getAsyncOperationProgress() < 0  # finished
    time.sleep(0.02)
    assert max(abs(v) for v in r.getActualQd()) < 1e-12


def test_servo_l_follows_a_step_with_its_time_constant(robot) -> None:
    sim, r, c = robot
    start = np.array(r.getActualTCPPose())
    lookahead, gain, step = 0.05, 300, 0.005
    target = start + [step, 0.0, 0.0, 0.0, 0.0, 0.0]
    for _ in range(200):  # 0.4 s of the same target at 500 Hz
        t = c.initPeriod()
        assert c.servoL(target.tolist(), 0.0, 0.0, 0.002, lookahead, gain)
        c.waitPeriod(t)
    assert c.servoStop(2.0)
    # The step response in the simulator's own time, from its true state.
    history = sim.truth_history()
    x = history["T_base_tcp"][:, 0, 3] - start[0]
    moving = np.flatnonzero(x > 1e-7)
    first, t = moving[0], history["stamp_ns"] * 1e-9
    t63 = t[first + np.flatnonzero(x[first:] >= (1 - math.exp(-1)) * step)[0]]
    # First order with tau = lookahead + 1/gain: 63 % of the step after tau (one cycle
    # less, since the first cycle already moves).
    tau = lookahead + 1 / gain
    assert t63 - t[first] + 0.002 == pytest.approx(tau, rel=0.1)
    assert x.max() == pytest.approx(step, rel=0.02)


def test_second_control_interface_is_refused_with_in_use(robot) -> None:
    sim, _r, c = robot
    with pytest.raises(RuntimeError, match="IN_USE|in use"):
        rtde_control.RTDEControlInterface(sim.host)
    assert c.isConnected()


def test_upper_register_range_speed_j_stop_j_and_stop_script(sim_robot: SimRobotHandle) -> None:
    flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT | rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
    c = rtde_control.RTDEControlInterface(sim_robot.host, 500.0, flags)
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host, 125.0)
    try:
        assert c.isProgramRunning()
        q0 = np.array(r.getActualQ())
        assert c.speedJ([0.2, 0.0, 0.0, 0.0, 0.0, -0.1], 2.0, 0.0)
        time.sleep(0.3)
        c.stopJ(2.0)
        time.sleep(0.05)
        assert max(abs(v) for v in r.getActualQd()) < 1e-12
        dq = np.array(r.getActualQ()) - q0
        assert dq[0] > 0.03 and dq[5] == pytest.approx(-dq[0] / 2, rel=1e-9)  # one ramp for all joints
        target = np.array(r.getActualTCPPose()) + [0.0, 0.0, 0.05, 0.0, 0.0, 0.0]
        assert c.moveL(target.tolist(), 0.25, 1.2)
        # The 125 Hz receiver sees the controller clock in steps of 8 ms.
        stamps = []
        for _ in range(15):
            stamps.append(r.getTimestamp())
            time.sleep(0.01)
        steps = np.round(np.diff(stamps) / 0.008, 6)
        assert np.all(steps == np.round(steps)) and steps.max() >= 1
        c.stopScript()
        assert _wait(lambda: sim_robot.status()["runtime_state"] == "STOPPED")
        assert sim_robot.status()["last_stop_reason"] == "program ended"
    finally:
        c.disconnect()
        r.disconnect()


def _wait(predicate, timeout: float = 1.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()
