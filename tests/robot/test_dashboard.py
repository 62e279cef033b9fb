"""The dashboard: why the robot is down and what clears it; ur-rtde's DashboardClient against the simulated controller."""

from __future__ import annotations

import asyncio
import time

import pytest

from celld.errors import InputError, RobotError
from celld.robot.dashboard import CONDITIONS, Dashboard, DashboardReading, foreign_program, reply_value, robot_condition


def _reading(mode: str, safety: str) -> DashboardReading:
    return DashboardReading(True, mode, safety, "PLAYING rtde_control", "", 0.0)


def test_the_conditions_are_every_state_a_condition_can_have() -> None:
    # The bus's vocabulary (status-reply, a health job's result) is this tuple.
    seen = {
        robot_condition(link, r).state
        for link in ("up", "down")
        for r in (
            None,
            _reading("RUNNING", "NORMAL"),
            _reading("RUNNING", "PROTECTIVE_STOP"),
            _reading("POWER_OFF", "ROBOT_EMERGENCY_STOP"),
            _reading("RUNNING", "VIOLATION"),
            _reading("POWER_OFF", "NORMAL"),
            _reading("IDLE", "NORMAL"),
            _reading("BOOTING", "NORMAL"),
            _reading("WEIRD", "NORMAL"),
            _reading("RUNNING", "NORMAL")._replace(remote=False),
        )
    }
    assert seen == set(CONDITIONS)


def test_reply_values_are_read_with_or_without_their_prefix() -> None:
    assert reply_value("Robotmode: RUNNING", "Robotmode") == "RUNNING"
    assert reply_value("Safetystatus: PROTECTIVE_STOP\n", "Safetystatus") == "PROTECTIVE_STOP"
    assert reply_value("POWER_OFF", "Robotmode") == "POWER_OFF"


@pytest.mark.parametrize(
    ("link", "mode", "safety", "state", "words"),
    [
        ("up", "RUNNING", "NORMAL", "ready", ()),
        ("down", "RUNNING", "PROTECTIVE_STOP", "protective_stop", ("protective stop", "celld robot unlock", "5 s")),
        ("down", "POWER_OFF", "ROBOT_EMERGENCY_STOP", "emergency_stop", ("emergency stop", "release the emergency stop", "power-on")),
        ("down", "RUNNING", "SAFEGUARD_STOP", "protective_stop", ("safeguard stop", "close the safeguard")),
        ("down", "RUNNING", "VIOLATION", "safety_fault", ("VIOLATION", "safety restart")),
        ("down", "POWER_OFF", "NORMAL", "power_off", ("powered off", "power-on", "brake-release")),
        ("down", "IDLE", "NORMAL", "brakes", ("brakes on", "brake-release")),
        ("down", "RUNNING", "NORMAL", "link_lost", ("RTDE link is down", "reconnects")),
    ],
)
def test_the_condition_says_why_and_what_clears_it(link: str, mode: str, safety: str, state: str, words: tuple[str, ...]) -> None:
    c = robot_condition(link, _reading(mode, safety), "the robot program stopped: protective stop")
    assert c.state == state and c.ready == (state == "ready")
    text = f"{c.reason} | {c.remedy}"
    assert all(w in text for w in words), text
    if not c.ready:
        assert "celld saw: the robot program stopped" in c.reason


def test_a_pendant_in_local_control_is_named_with_the_switch_that_clears_it() -> None:
    local = _reading("RUNNING", "NORMAL")._replace(remote=False)
    c = robot_condition("down", local)
    assert c.state == "local_control" and not c.ready
    assert "Local Control" in c.reason and "Remote Control" in c.remedy
    # A safety stop comes first: it is what the pendant shows and what must be cleared there.
    assert robot_condition("down", _reading("RUNNING", "PROTECTIVE_STOP")._replace(remote=False)).state == "protective_stop"


@pytest.mark.process
def test_a_simulated_controller_in_local_control_says_so_and_takes_no_script(loopback_host: str) -> None:
    import socket

    from celld.sim.robot import launch
    from celld.sim.robot.options import SCRIPT_PORTS

    async def read(host: str) -> DashboardReading:
        dash = Dashboard(host)
        try:
            return await dash.read()
        finally:
            await dash.close()

    with launch(loopback_host, remote_control=False):
        r = asyncio.run(read(loopback_host))
        assert r.reachable and not r.remote, r
        assert robot_condition("down", r).state == "local_control"
        for port in SCRIPT_PORTS:
            with socket.create_connection((loopback_host, port), timeout=2.0) as s:
                s.settimeout(2.0)
                try:
                    s.sendall(b"def p():\n  textmsg(1)\nend\n")
                    closed = s.recv(1) == b""
                except ConnectionResetError:
                    closed = True  # closed with the program unread
                assert closed, f"port {port} must close the connection in Local Control"


def test_an_unreachable_robot_is_a_lost_link_unless_rtde_is_up() -> None:
    down = DashboardReading(False, "", "", "", "RuntimeError: connection refused", 0.0)
    c = robot_condition("down", down, "no fresh robot state for 120 ms")
    assert c.state == "link_lost" and "connection refused" in c.reason and "no fresh robot state" in c.reason
    assert robot_condition("up", down).ready
    assert robot_condition("unknown", None).state == "link_lost"


@pytest.mark.process
def test_the_dashboard_reads_the_simulated_controller_and_passes_on_its_refusals(loopback_host: str) -> None:
    from celld.sim.robot import launch

    async def scenario(sim) -> None:
        dash = Dashboard(sim.host)
        try:
            r = await dash.read()
            assert r.reachable and r.robot_mode == "RUNNING" and r.safety == "NORMAL" and r.remote, r
            sim.inject("protective_stop")
            r = await dash.read()
            assert r.safety == "PROTECTIVE_STOP"
            assert robot_condition("down", r).state == "protective_stop"
            # Too early: the controller's own reason comes through.
            with pytest.raises(RobotError, match="5s after occurrence"):
                await dash.act("unlock")
            with pytest.raises(InputError, match="expected one of unlock"):
                await dash.act("reboot")
            # The failed call dropped the connection; the next read reconnects.
            sim.inject("power_off")
            r = await dash.read()
            assert r.reachable and r.robot_mode == "POWER_OFF"
            await dash.act("power-on")
            deadline = time.monotonic() + 5.0
            while (await dash.read()).robot_mode != "IDLE":
                assert time.monotonic() < deadline, dash.last
                await asyncio.sleep(0.1)
        finally:
            await dash.close()

    with launch(loopback_host, unlock_delay=5.0) as sim:
        asyncio.run(scenario(sim))


def test_a_robot_that_does_not_answer_reads_as_unreachable(loopback_host: str) -> None:
    async def scenario() -> DashboardReading:
        dash = Dashboard(loopback_host, timeout=0.5)
        try:
            return await dash.read()
        finally:
            await dash.close()

    r = asyncio.run(scenario())
    assert not r.reachable and r.error


def test_a_program_playing_or_paused_is_one_that_holds_the_robot() -> None:
    def reading(program: str, reachable: bool = True) -> DashboardReading:
        return DashboardReading(reachable, "RUNNING", "NORMAL", program, "", 0.0)

    assert foreign_program(reading("PLAYING fixture.urp")) == "PLAYING fixture.urp"
    assert foreign_program(reading("PAUSED weld.urp")) == "PAUSED weld.urp"
    assert foreign_program(reading("STOPPED weld.urp")) == ""
    assert foreign_program(reading("PLAYING x", reachable=False)) == ""  # unread: nothing is known to hold it
    assert foreign_program(None) == ""
