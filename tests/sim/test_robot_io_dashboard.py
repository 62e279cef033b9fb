"""ur-rtde's IO interface and dashboard client against the simulated controller."""

from __future__ import annotations

import time

import dashboard_client
import pytest
import rtde_control
import rtde_io
import rtde_receive

from celld.sim.robot import SimRobotHandle, launch

pytestmark = pytest.mark.process

# The welding arc is switched by standard digital output 0 in the simulated cell.
ARC_OUTPUT = 0


def _wait_for(predicate, timeout: float = 1.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_digital_outputs_switch_the_arc_and_read_back(sim_robot: SimRobotHandle) -> None:
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    io = rtde_io.RTDEIOInterface(sim_robot.host)
    try:
        assert io.setStandardDigitalOut(ARC_OUTPUT, True)
        assert _wait_for(lambda: r.getDigitalOutState(ARC_OUTPUT))
        assert io.setStandardDigitalOut(5, True)
        assert io.setToolDigitalOut(1, True)
        assert _wait_for(lambda: r.getActualDigitalOutputBits() == (1 << ARC_OUTPUT) | (1 << 5) | (1 << 17))
        assert sim_robot.status()["digital_out"] == (1 << ARC_OUTPUT) | (1 << 5) | (1 << 17)
        assert io.setStandardDigitalOut(ARC_OUTPUT, False)
        assert _wait_for(lambda: not r.getDigitalOutState(ARC_OUTPUT))
        assert r.getDigitalOutState(5)  # the mask leaves the other outputs alone
        assert io.setSpeedSlider(0.5)
        assert _wait_for(lambda: r.getSpeedScaling() == pytest.approx(0.5))
        assert io.setAnalogOutputVoltage(1, 0.25)
        assert _wait_for(lambda: r.getStandardAnalogOutput1() == pytest.approx(0.25))
        sim_robot.set_digital_inputs(0b101)
        assert _wait_for(lambda: r.getActualDigitalInputBits() == 0b101)
        with pytest.raises(RuntimeError):
            rtde_io.RTDEIOInterface(sim_robot.host)  # its registers are IN_USE
    finally:
        io.disconnect()
        r.disconnect()


def test_dashboard_commands_of_ur_rtde(sim_robot: SimRobotHandle) -> None:
    d = dashboard_client.DashboardClient(sim_robot.host)
    d.connect()
    try:
        assert d.isConnected()
        assert "5.11" in d.polyscopeVersion()
        assert d.getSerialNumber().isdigit()
        assert d.getRobotModel() == "UR10"
        assert d.isInRemoteControl()
        assert str(d.robotmode()) == "Robotmode: RUNNING"
        assert str(d.safetystatus()) == "Safetystatus: NORMAL"
        assert not d.running()
        d.powerOff()
        assert str(d.robotmode()) == "Robotmode: POWER_OFF"
        d.powerOn()
        assert str(d.robotmode()) == "Robotmode: IDLE"
        d.brakeRelease()
        assert str(d.robotmode()) == "Robotmode: RUNNING"
        d.loadURP("weld.urp")
        assert "weld.urp" in d.getLoadedProgram()
        d.play()
        assert d.running()
        d.pause()
        assert "PAUSED" in str(d.programState())
        d.stop()
        assert not d.running()
        d.popup("hello")
        d.closePopup()
        d.closeSafetyPopup()
        d.addToLog("from the test")
        assert d.isProgramSaved()
        d.send("no such command\n")
        assert "could not understand" in d.receive()
    finally:
        d.disconnect()


def test_protective_stop_shows_and_unlock_clears_it(loopback_host: str) -> None:
    with launch(loopback_host, unlock_delay=0.3, realtime=True) as sim:
        r = rtde_receive.RTDEReceiveInterface(sim.host)
        c = rtde_control.RTDEControlInterface(sim.host)
        d = dashboard_client.DashboardClient(sim.host)
        d.connect()
        try:
            assert c.speedL([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 1.0, 0.0)
            time.sleep(0.1)
            sim.inject("protective_stop")
            assert _wait_for(r.isProtectiveStopped)
            assert r.getSafetyMode() == 3
            assert str(d.safetystatus()) == "Safetystatus: PROTECTIVE_STOP"
            assert _wait_for(lambda: not c.isProgramRunning())  # its own RTDE session sees it a cycle or more later
            assert max(abs(v) for v in r.getActualQd()) == 0.0
            # The controller refuses to unlock too early, then clears it.
            with pytest.raises(RuntimeError, match="Cannot unlock"):
                d.unlockProtectiveStop()
            time.sleep(0.35)
            d.unlockProtectiveStop()
            assert _wait_for(lambda: not r.isProtectiveStopped())
            assert r.getSafetyMode() == 1
            assert c.reuploadScript()
            assert _wait_for(c.isProgramRunning)
            # The control script's own protective_stop() command.
            c.triggerProtectiveStop()
            assert _wait_for(r.isProtectiveStopped)
        finally:
            d.disconnect()
            c.disconnect()
            r.disconnect()


def test_tool_speed_over_the_safety_limit_is_a_protective_stop(loopback_host: str) -> None:
    with launch(loopback_host, tcp_speed_limit=0.25, realtime=True) as sim:
        r = rtde_receive.RTDEReceiveInterface(sim.host)
        c = rtde_control.RTDEControlInterface(sim.host)
        try:
            assert c.speedL([0.0, 0.0, -0.4, 0.0, 0.0, 0.0], 2.0, 0.0)
            assert _wait_for(r.isProtectiveStopped)
            assert "tool speed limit" in sim.status()["last_stop_reason"]
            # The simulator keeps running and answers.
            assert r.getRuntimeState() == 1 and sim.status()["robot_mode"] == "RUNNING"
        finally:
            c.disconnect()
            r.disconnect()


def test_leaving_the_workspace_box_is_a_protective_stop(loopback_host: str) -> None:
    # The home pose has the TCP at z = 0.677 m; the box floor is 5 cm below it.
    with launch(loopback_host, workspace_min=(-1.5, -1.5, 0.627), workspace_max=(1.5, 1.5, 1.5), realtime=True) as sim:
        r = rtde_receive.RTDEReceiveInterface(sim.host)
        c = rtde_control.RTDEControlInterface(sim.host)
        try:
            target = r.getActualTCPPose()
            target[2] -= 0.2
            assert not c.moveL(target, 0.25, 1.2)  # ur-rtde sees its script stop
            # This receive interface's own thread may hold the packet before the stop for a cycle or two
            # (the control interface saw the stop through its own): it says so within a few packets.
            assert _wait_for(r.isProtectiveStopped)
            assert r.getActualTCPPose()[2] == pytest.approx(0.627, abs=0.002)
            assert "workspace limit" in sim.status()["last_stop_reason"]
        finally:
            c.disconnect()
            r.disconnect()


def test_pose_out_of_reach_is_a_runtime_error_and_the_simulator_keeps_running(sim_robot: SimRobotHandle) -> None:
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    c = rtde_control.RTDEControlInterface(sim_robot.host)
    try:
        far = [2.5, 0.0, 0.5, 0.0, 3.14159, 0.0]
        assert not c.moveL(far, 0.25, 1.2)
        assert not c.isProgramRunning()
        assert not r.isProtectiveStopped()
        assert "inverse kinematics failed" in sim_robot.status()["last_stop_reason"]
        assert c.reuploadScript()
        assert _wait_for(c.isProgramRunning)
        home = r.getActualTCPPose()
        home[0] += 0.01
        assert c.moveL(home, 0.1, 1.0)
    finally:
        c.disconnect()
        r.disconnect()
