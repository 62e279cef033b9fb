"""The controller, ur-rtde's script protocol, the dashboard and fault parsing, without sockets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.errors import ConfigError, InputError
from celld.sim.robot import controller as c
from celld.sim.robot import dashboard
from celld.sim.robot import geometry as g
from celld.sim.robot import rtde_protocol as P
from celld.sim.robot.faults import parse_fault
from celld.sim.robot.options import SimOptions
from celld.sim.robot.script import DONE, READY, find_programs


def control_script(offset: int = 0) -> bytes:
    """A stand-in with the parts of ur-rtde's control script the simulator recognises."""
    return (
        "def rtde_control():\n"
        "    global reg_offset_float = # float register offset\n"
        f"{offset}    global reg_offset_int = # int register offset\n"
        f"{offset}\n"
        "    def rtde_cmd():\n"
        "      cmd = read_input_integer_reg(0)\n"
        "      return cmd\n"
        "    end\n"
        "    while keep_running:\n"
        "        cmd = rtde_cmd()\n"
        "        keep_running = process_cmd(cmd)\n"
        "    end\n"
        "end\n"
    ).encode()


def started(offset: int = 0, **options) -> c.Controller:
    ctrl = c.Controller(SimOptions(**options))
    programs, rest = find_programs(control_script(offset))
    assert len(programs) == 1 and rest == b""
    ctrl.receive_program(programs[0])
    assert ctrl.runtime_state == c.RUNTIME_PLAYING
    return ctrl


def command(ctrl: c.Controller, cmd: int, doubles=(), ints=(), offset: int = 0) -> None:
    for i, v in enumerate(doubles):
        ctrl.in_double[offset + i] = float(v)
    for i, v in enumerate(ints, start=1):
        ctrl.in_int[offset + i] = int(v)
    ctrl.in_int[offset] = cmd
    ctrl.in_int_written[offset] = ctrl.time


def ticks(ctrl: c.Controller, n: int) -> None:
    for _ in range(n):
        ctrl.tick()


def test_find_programs_recognises_the_control_script_and_its_offset() -> None:
    text = control_script(24) + b"def other():\n  write_output_integer_register(0 + 24, 2)\nend\n" + b"def partial():\n  x = 1\n"
    programs, rest = find_programs(text)
    assert [(p.name, p.is_control_script, p.int_offset) for p in programs] == [("rtde_control", True, 24), ("other", False, 0)]
    assert rest.startswith(b"def partial")


def test_non_realtime_command_handshake_ready_done_ready() -> None:
    ctrl = started()
    assert ctrl.out_int[0] == READY
    pose = g.pose_from_rows(ctrl.arm.T_tcp)
    pose[0] += 0.05
    command(ctrl, 3, doubles=[*pose, 0.25, 1.2], ints=[0])  # moveL, synchronous
    ctrl.tick()
    assert ctrl.out_int[0] == READY  # busy: no done while the move runs
    ticks(ctrl, 300)
    assert ctrl.out_int[0] == DONE
    np.testing.assert_allclose(g.pose_from_rows(ctrl.arm.T_tcp), pose, atol=1e-12)
    ticks(ctrl, 5)
    assert ctrl.out_int[0] == DONE  # stays done until the client writes NO_CMD
    command(ctrl, 0)
    ctrl.tick()
    assert ctrl.out_int[0] == READY


def test_realtime_commands_answer_ready_every_cycle_with_the_upper_register_range() -> None:
    ctrl = started(offset=24)
    command(ctrl, 10, doubles=[0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 10.0, 0.0], offset=24)  # speedL
    y0 = ctrl.arm.T_tcp[7]
    ticks(ctrl, 100)
    assert ctrl.out_int[24] == READY and ctrl.out_int[0] == 0
    assert ctrl.arm.T_tcp[7] - y0 == pytest.approx(0.1 * 0.2 - 0.1**2 / (2 * 10.0), abs=1e-6)
    command(ctrl, 15, doubles=[10.0], offset=24)  # speedStop
    ticks(ctrl, 10)
    assert ctrl.out_int[24] == DONE and ctrl.arm.steady


def test_query_commands_write_the_output_registers() -> None:
    ctrl = started()

    def query(cmd: int, doubles) -> None:
        command(ctrl, cmd, doubles=doubles)
        ctrl.tick()
        assert ctrl.out_int[0] == DONE
        command(ctrl, 0)  # the client's NO_CMD after done
        ctrl.tick()

    query(46, g.pose_from_rows(ctrl.arm.T_tcp))  # get_inverse_kin(x)
    np.testing.assert_allclose(ctrl.out_double[:6], ctrl.arm.q, atol=1e-9)
    query(36, [5.0, 0.0, 0.5, 0.0, math.pi, 0.0])  # is_pose_within_safety_limits
    assert ctrl.out_int[1] == 0
    query(36, g.pose_from_rows(ctrl.arm.T_tcp))
    assert ctrl.out_int[1] == 1
    query(39, [0.1, 0.0, 0.0, 0.0, 0.0, math.pi / 2, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0])  # pose_trans
    np.testing.assert_allclose(ctrl.out_double[:6], [0.1, 0.1, 0.0, 0.0, 0.0, math.pi / 2], atol=1e-12)


def test_async_move_progress_register() -> None:
    ctrl = started()
    pose = g.pose_from_rows(ctrl.arm.T_tcp)
    pose[1] += 0.05
    command(ctrl, 3, doubles=[*pose, 0.25, 1.2], ints=[1])  # moveL, asynchronous
    ctrl.tick()
    assert ctrl.out_int[0] == DONE
    assert ctrl.out_int[2] & 32768  # running bit
    command(ctrl, 0)
    ticks(ctrl, 300)
    assert not ctrl.out_int[2] & 32768


def test_unreachable_move_is_a_runtime_error_that_stops_the_program() -> None:
    ctrl = started()
    command(ctrl, 3, doubles=[3.0, 0.0, 0.5, 0.0, math.pi, 0.0, 0.25, 1.2], ints=[0])
    ctrl.tick()
    assert ctrl.runtime_state == c.RUNTIME_STOPPED
    assert ctrl.safety_mode == c.SAFETY_NORMAL
    assert any("inverse kinematics failed" in text and level == P.LEVEL_ERROR for text, level in ctrl.outbox)


def test_watchdog_stops_the_program_when_the_register_goes_silent() -> None:
    ctrl = started()
    command(ctrl, 35, doubles=[50.0])  # 20 ms
    ctrl.tick()
    command(ctrl, 10, doubles=[0.05, 0, 0, 0, 0, 0, 1.0, 0.0])
    ticks(ctrl, 9)
    assert ctrl.runtime_state == c.RUNTIME_PLAYING
    ticks(ctrl, 2)  # 22 ms without a write
    assert ctrl.runtime_state == c.RUNTIME_STOPPED
    assert ctrl.last_stop_reason == "RTDE watchdog expired"
    ticks(ctrl, 50)
    assert ctrl.arm.steady


def test_stop_script_ends_the_program_and_a_custom_program_reports_through_registers() -> None:
    ctrl = started()
    command(ctrl, 255)
    ctrl.tick()
    assert ctrl.runtime_state == c.RUNTIME_STOPPED
    (program,), _ = find_programs(b"def custom():\n  movej([0,0,0,0,0,0])\n  write_output_integer_register(0 + 0, 2)\nend\n")
    ctrl.receive_program(program)
    assert ctrl.out_int[0] == DONE
    ctrl.tick()
    assert ctrl.runtime_state == c.RUNTIME_STOPPED
    assert any("not simulated" in text for text, _ in ctrl.outbox)


def test_protective_stop_unlocks_only_after_the_delay() -> None:
    ctrl = started(unlock_delay=0.1)
    ctrl.protective_stop("test")
    assert ctrl.safety_mode == c.SAFETY_PROTECTIVE_STOP and ctrl.runtime_state == c.RUNTIME_STOPPED
    assert ctrl.safety_status_bits() & (1 << 2)
    assert dashboard.handle(ctrl, "unlock protective stop").text.startswith("Cannot unlock protective stop")
    ticks(ctrl, 50)
    assert dashboard.handle(ctrl, "unlock protective stop").text == "Protective stop releasing"
    assert ctrl.safety_mode == c.SAFETY_NORMAL


def test_programs_do_not_start_unless_the_robot_runs() -> None:
    ctrl = c.Controller(SimOptions(boot="power_off"))
    (program,), _ = find_programs(control_script())
    ctrl.receive_program(program)
    assert ctrl.runtime_state == c.RUNTIME_STOPPED
    assert dashboard.handle(ctrl, "robotmode").text == "Robotmode: POWER_OFF"
    assert dashboard.handle(ctrl, "power on").text == "Powering on"
    assert dashboard.handle(ctrl, "robotmode").text == "Robotmode: IDLE"
    assert dashboard.handle(ctrl, "brake release").text == "Brake releasing"
    ctrl.receive_program(program)
    assert ctrl.runtime_state == c.RUNTIME_PLAYING


def test_io_masks_apply_only_the_masked_bits() -> None:
    ctrl = c.Controller(SimOptions())
    names = ("input_int_register_23", "standard_digital_output_mask", "standard_digital_output")
    plan = ctrl.input_plan(names)
    ctrl.write_inputs(plan, (13, 0b0000_1001, 0b1111_1111))
    assert ctrl.digital_out == 0b1001
    ctrl.write_inputs(plan, (13, 0b0000_0001, 0))
    assert ctrl.digital_out == 0b1000
    ctrl.write_inputs(ctrl.input_plan(("speed_slider_mask", "speed_slider_fraction")), (1, 0.3))
    assert ctrl.speed_fraction == 0.3
    assert ctrl.output_getter("speed_scaling")() == (0.3,)
    assert ctrl.output_getter("actual_digital_output_bits")() == (0b1000,)


def test_dashboard_replies_that_ur_rtde_parses() -> None:
    ctrl = c.Controller(SimOptions())
    assert dashboard.handle(ctrl, "PolyscopeVersion").text.startswith("URSoftware 5.11.6.1123438")
    assert dashboard.handle(ctrl, "get serial number").text.isdigit()
    assert dashboard.handle(ctrl, "safetystatus").text == "Safetystatus: NORMAL"
    assert dashboard.handle(ctrl, "stop").text == "Stopped"
    assert dashboard.handle(ctrl, "play").text == "Failed to execute: play"
    assert dashboard.handle(ctrl, "load /programs/weld.urp").text == "Loading program: /programs/weld.urp"
    assert dashboard.handle(ctrl, "play").text == "Starting program"
    assert dashboard.handle(ctrl, "programState").text == "PLAYING /programs/weld.urp"
    assert dashboard.handle(ctrl, "quit") == dashboard.Reply("Disconnected", close=True)
    assert dashboard.handle(ctrl, "fly").text == "could not understand: 'fly'"


def test_fault_requests_are_checked() -> None:
    assert parse_fault("drop-all", {"down_ms": 500}).args == {"down_ms": 500.0}
    assert parse_fault("stall", {"ms": 20}).name == "stall"
    with pytest.raises(InputError, match="unknown fault 'lightning'"):
        parse_fault("lightning", {})
    with pytest.raises(InputError, match="'ms' is required"):
        parse_fault("latency", {})
    with pytest.raises(InputError, match="unknown argument 'ms'"):
        parse_fault("estop", {"ms": 1})
    with pytest.raises(InputError, match="must be a number"):
        parse_fault("stall", {"ms": "soon"})


def test_options_are_checked_and_survive_the_command_line() -> None:
    import argparse

    from celld.sim.robot.options import add_arguments, from_args

    opts = SimOptions(host="127.0.0.9", workspace_min=(-1.0, -1.0, 0.0), tcp_speed_limit=0.5, realtime=True)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert from_args(parser.parse_args(opts.to_argv())) == opts
    with pytest.raises(ConfigError, match="loopback only"):
        SimOptions(host="10.0.0.2")
    with pytest.raises(ConfigError, match="workspace_max"):
        SimOptions(workspace_min=(0.0, 0.0, 2.0))
    with pytest.raises(ConfigError, match="tcp_speed_limit"):
        SimOptions(tcp_speed_limit=0.0)


def test_moves_faster_than_the_limits_are_slowed_with_a_warning() -> None:
    ctrl = started(tcp_speed_limit=0.2)
    pose = g.pose_from_rows(ctrl.arm.T_tcp)
    pose[0] += 0.1
    command(ctrl, 3, doubles=[*pose, 1.0, 100.0], ints=[0])  # 1 m/s, 100 m/s^2
    peak = 0.0
    for _ in range(1000):
        ctrl.tick()
        peak = max(peak, g.norm3(*ctrl.arm.tcp_speed[:3]))
        if ctrl.out_int[0] == DONE:
            break
    assert ctrl.out_int[0] == DONE and ctrl.safety_mode == c.SAFETY_NORMAL
    assert peak == pytest.approx(0.2, abs=1e-9)
    assert any("reduced to the safety limit" in text and level == P.LEVEL_WARNING for text, level in ctrl.outbox)
