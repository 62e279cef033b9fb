"""Motion subcommands for commissioning: ``celld motion status`` and ``celld motion move``.

``celld motion status [--config FILE] [--host H] [--seconds S] [--json]``
starts the motion process against the configured robot, lets the loop run
``S`` seconds and prints the robot state (TCP pose as a UR pose, joints) and
the loop's health (link state, SCHED_FIFO granted, period error percentiles,
late cycles, overruns).

``celld motion move X Y Z RX RY RZ [--speed-scale F] ...`` moves the TCP
straight to a UR pose (m, rad) and prints where it arrived. Both stop the
robot and end the motion process before they return.
"""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from celld.config import Config
    from celld.motion.handle import MotionHandle


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("motion", help="robot link and motion loop tools (commissioning)")
    psub = p.add_subparsers(dest="motion_command", metavar="ACTION", required=True)

    s = psub.add_parser("status", help="run the motion loop briefly; print robot state and loop health")
    _common(s)
    s.add_argument("--seconds", type=float, default=3.0, help="how long the loop runs before the report")
    s.set_defaults(func=_status)

    m = psub.add_parser("move", help="move the TCP straight to a UR pose [x y z rx ry rz] (m, rad)")
    _common(m)
    m.add_argument("pose", type=float, nargs=6, metavar="V")
    m.add_argument("--speed-scale", type=float, default=0.25, help="share of the configured limits (default 0.25)")
    m.set_defaults(func=_move)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="cell config file (default: built-in defaults)")
    p.add_argument("--host", help="robot controller address (default: the config's robot.host)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _config(args: argparse.Namespace) -> Config:
    from celld.config import Config, load

    return load(args.config) if args.config else Config()


def _report(motion: MotionHandle) -> dict[str, Any]:
    from celld.se3 import to_ur_pose

    state = motion.state()
    out: dict[str, Any] = {"health": motion.health()._asdict()}
    if state is not None:
        out["tcp_pose"] = [round(float(x), 6) for x in to_ur_pose(state.T_base_tcp)]
        out["q"] = [round(float(x), 6) for x in state.q]
    return out


def _print(args: argparse.Namespace, report: dict[str, Any]) -> None:
    if args.json:
        print(json.dumps(report))
        return
    for key, value in report.items():
        if isinstance(value, dict):
            for k, v in value.items():
                print(f"{k:24s} {v}")
        else:
            print(f"{key:24s} {value}")


def _status(args: argparse.Namespace) -> int:
    import asyncio

    from celld.motion.handle import MotionHandle

    async def run() -> dict[str, Any]:
        async with await MotionHandle.open(_config(args), host=args.host) as motion:
            await asyncio.sleep(args.seconds)
            return _report(motion)

    _print(args, asyncio.run(run()))
    return 0


def _move(args: argparse.Namespace) -> int:
    import asyncio

    from celld.motion.handle import MotionHandle

    async def run() -> dict[str, Any]:
        async with await MotionHandle.open(_config(args), host=args.host) as motion:
            await motion.move_to(args.pose, speed_scale=args.speed_scale)
            return _report(motion)

    _print(args, asyncio.run(run()))
    return 0
