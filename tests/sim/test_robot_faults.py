"""Fault injection and malformed input against the simulated controller."""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest
import rtde_control
import rtde_receive

from celld.errors import InputError
from celld.sim.robot import SimRobotHandle
from celld.sim.robot import rtde_protocol as P
from celld.sim.robot.options import RTDE_PORT

pytestmark = pytest.mark.process


def _wait_for(predicate, timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.0005)
    return predicate()


class RawRtde:
    """A minimal RTDE client on a plain socket, to send what ur-rtde never would."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, RTDE_PORT), timeout=2.0)
        self.reader = P.PackageReader()

    def send(self, msg_type: int, payload: bytes = b"") -> None:
        self.sock.sendall(P.package(msg_type, payload))

    def receive(self, msg_type: int) -> bytes:
        """The payload of the next package of ``msg_type`` (others are skipped)."""
        while True:
            for t, payload in self.reader.packages():
                if t == msg_type:
                    return payload
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed")
            self.reader.feed(data)

    def close(self) -> None:
        self.sock.close()


def test_a_dropped_rtde_link_is_seen_within_100_ms(sim_robot: SimRobotHandle) -> None:
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    try:
        # ur-rtde notices a closed socket after about 20 empty polls of its receive thread;
        # on a loaded machine one try can take longer, so the median of three counts.
        seen_s = []
        for _ in range(3):
            assert r.isConnected()
            sim_robot.inject("drop_rtde")
            t0 = time.monotonic()
            assert _wait_for(lambda: not r.isConnected(), timeout=1.0)
            seen_s.append(time.monotonic() - t0)
            assert r.reconnect()
        assert sorted(seen_s)[1] < 0.1, f"link loss seen after {[round(s * 1e3) for s in seen_s]} ms"
    finally:
        r.disconnect()


def test_control_interface_reconnects_after_every_link_dropped(sim_robot: SimRobotHandle) -> None:
    c = rtde_control.RTDEControlInterface(sim_robot.host)
    try:
        # Every link drops and the ports stay closed for 1 s: ur-rtde's one automatic
        # reconnect attempt fails (it gives up on the dashboard after its 2.5 s timeout),
        # a manual reconnect after that works. A manual reconnect while the automatic one
        # is still under way hangs or aborts ur-rtde (seen once at 3 s, on the suite's two
        # busy workers, taking the worker's process with it): 5 s leaves the attempt room.
        sim_robot.inject("drop_all", down_ms=1000)
        assert _wait_for(lambda: not c.isConnected(), timeout=1.0)
        time.sleep(5.0)
        assert c.reconnect()
        assert c.isProgramRunning()
        q = sim_robot.options.q0
        assert c.moveJ([q[0] + 0.05, *q[1:]], 1.0, 2.0)
    finally:
        c.stopScript()
        c.disconnect()


def test_stall_freezes_the_stream_then_it_resumes(sim_robot: SimRobotHandle) -> None:
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    try:
        sim_robot.inject("stall", ms=300)
        t0 = time.monotonic()
        time.sleep(0.05)
        frozen = r.getTimestamp()
        time.sleep(0.15)
        assert r.getTimestamp() == frozen
        assert _wait_for(lambda: r.getTimestamp() > frozen, timeout=1.0)
        assert time.monotonic() - t0 > 0.25
        assert r.isConnected()  # 300 ms is well inside ur-rtde's 2.5 s receive timeout
    finally:
        r.disconnect()


def test_latency_delays_commands_and_state(sim_robot: SimRobotHandle) -> None:
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    c = rtde_control.RTDEControlInterface(sim_robot.host)
    try:
        sim_robot.inject("latency", ms=100)
        time.sleep(0.15)
        x0 = r.getActualTCPPose()[0]
        t0 = time.monotonic()
        assert c.speedL([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 2.0, 0.0)
        assert _wait_for(lambda: r.getActualTCPPose()[0] > x0 + 1e-6, timeout=2.0)
        round_trip = time.monotonic() - t0
        assert 0.19 < round_trip < 0.6  # command 100 ms there, state 100 ms back
        sim_robot.clear_faults()
        assert c.speedStop(2.0)
    finally:
        c.stopScript()
        c.disconnect()
        r.disconnect()


def test_estop_powers_off_and_recovers_from_the_dashboard(sim_robot: SimRobotHandle) -> None:
    import dashboard_client

    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    c = rtde_control.RTDEControlInterface(sim_robot.host)
    d = dashboard_client.DashboardClient(sim_robot.host)
    d.connect()
    try:
        sim_robot.inject("estop")
        assert _wait_for(r.isEmergencyStopped)
        assert r.getRobotMode() == 3
        assert _wait_for(lambda: not c.isProgramRunning())
        d.powerOn()
        assert str(d.robotmode()) == "Robotmode: POWER_OFF"  # the e-stop is still pressed
        sim_robot.clear_faults()  # released
        assert _wait_for(lambda: not r.isEmergencyStopped())
        d.powerOn()
        d.brakeRelease()
        assert _wait_for(lambda: r.getRobotMode() == 7)
        # A refused upload: the script does not start until the fault is cleared.
        sim_robot.inject("refuse_upload")
        c.reuploadScript()
        time.sleep(0.2)
        assert not c.isProgramRunning()
        sim_robot.clear_faults()
        c.reuploadScript()
        assert _wait_for(c.isProgramRunning)
        sim_robot.inject("power_off")
        assert _wait_for(lambda: r.getRobotMode() == 3)
        assert _wait_for(lambda: not c.isProgramRunning())
    finally:
        d.disconnect()
        c.disconnect()
        r.disconnect()


def test_malformed_rtde_input_gets_text_messages_and_the_simulator_keeps_running(sim_robot: SimRobotHandle) -> None:
    raw = RawRtde(sim_robot.host)
    try:
        raw.send(P.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))
        assert raw.receive(P.REQUEST_PROTOCOL_VERSION) == b"\x01"
        # An output recipe with an unknown name is refused.
        raw.send(P.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"actual_q,no_such_field")
        reply = raw.receive(P.CONTROL_PACKAGE_SETUP_OUTPUTS)
        assert reply[0] == 0 and reply[1:] == b"VECTOR6D,NOT_FOUND"
        # A data package for a recipe that was never set up.
        raw.send(P.DATA_PACKAGE, bytes([9, 0, 0, 0, 1]))
        text, _, level = P.parse_text_message(raw.receive(P.TEXT_MESSAGE))
        assert "unknown input recipe id 9" in text and level == P.LEVEL_ERROR
        # A package of an unknown type.
        raw.send(ord("Z"), b"x")
        assert "unknown package type" in P.parse_text_message(raw.receive(P.TEXT_MESSAGE))[0]
        # The connection still works.
        raw.send(P.GET_URCONTROL_VERSION)
        assert struct.unpack(">IIII", raw.receive(P.GET_URCONTROL_VERSION))[:2] == (5, 11)
        # A header that cannot be resynchronised closes this connection, nothing else.
        raw.sock.sendall(struct.pack(">HB", 1, ord("U")))
        assert "package size" in P.parse_text_message(raw.receive(P.TEXT_MESSAGE))[0]
        with pytest.raises(ConnectionError):
            raw.receive(P.DATA_PACKAGE)
    finally:
        raw.close()
    assert sim_robot.status()["runtime_state"] == "STOPPED"
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    assert r.getRobotMode() == 7
    r.disconnect()


def test_control_endpoint_refuses_bad_requests(sim_robot: SimRobotHandle) -> None:
    with pytest.raises(InputError, match="unknown fault"):
        sim_robot.inject("meteor_strike")
    with pytest.raises(InputError, match="ms must be a number"):
        sim_robot.inject("stall", ms=-5)
    with pytest.raises(InputError, match="outside the joint range"):
        sim_robot.set_q([0.0, 0.0, 0.0, 0.0, 0.0, 7.0])
    q = np.array(sim_robot.options.q0) + 0.1
    sim_robot.set_q(q)
    np.testing.assert_allclose(sim_robot.status()["q"], q, atol=1e-12)
