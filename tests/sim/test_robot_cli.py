"""``celld sim robot`` and ``celld sim fault`` argument handling against a running simulator."""

from __future__ import annotations

import argparse
import json

import pytest

from celld.errors import InputError
from celld.sim import cli
from celld.sim.robot import SimRobotHandle
from celld.sim.robot.options import SimOptions, from_args


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="celld")
    cli.add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_robot_subcommand_takes_the_workspace_and_limits() -> None:
    argv = ["sim", "robot", "--host", "127.0.0.40", "--workspace", "-1", "-1", "0", "1", "1", "1.2"]
    opts = from_args(_parse([*argv, "--tcp-speed-limit", "0.8"]))
    expected = SimOptions(host="127.0.0.40", workspace_min=(-1.0, -1.0, 0.0), workspace_max=(1.0, 1.0, 1.2), tcp_speed_limit=0.8)
    assert opts == expected


@pytest.mark.process
def test_fault_subcommand_plays_and_clears_faults(sim_robot: SimRobotHandle, capsys: pytest.CaptureFixture[str]) -> None:
    args = _parse(["sim", "fault", "--host", sim_robot.host, "protective-stop"])
    assert args.func(args) == 0
    assert json.loads(capsys.readouterr().out) == {}
    args = _parse(["sim", "fault", "--host", sim_robot.host, "status"])
    assert args.func(args) == 0
    assert json.loads(capsys.readouterr().out)["safety_mode"] == "PROTECTIVE_STOP"
    args = _parse(["sim", "fault", "--host", sim_robot.host, "latency"])
    with pytest.raises(InputError, match="'ms' is required"):
        args.func(args)
    args = _parse(["sim", "fault", "--host", sim_robot.host, "stall", "--ms", "50"])
    assert args.func(args) == 0
    # clear undoes what the simulator set, the protective stop included.
    args = _parse(["sim", "fault", "--host", sim_robot.host, "clear"])
    assert args.func(args) == 0
    capsys.readouterr()
    args = _parse(["sim", "fault", "--host", sim_robot.host, "status"])
    assert args.func(args) == 0
    assert json.loads(capsys.readouterr().out)["safety_mode"] == "NORMAL"
