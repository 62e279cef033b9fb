"""``celld sim``: run simulated devices and play faults on them.

- ``celld sim robot --host 127.0.0.N [options]`` runs the simulated UR10e
  controller in the foreground until interrupted.
- ``celld sim cell --config CELL.toml`` runs the simulated cell of a cell
  config: the simulated arm on ``robot.host`` at ``robot.home_q``, in real
  time, as the world of the config's ``[sim]`` table makes it (its true
  kinematics and noise; :mod:`celld.sim.world`).
- ``celld sim run --config CELL.toml`` runs the daemon (``celld run``) on the
  simulated cell's devices: the scanner and the SRM camera the simulator
  builds from the same world (``scanner.kind = "sim"``, ``tactile.kind =
  "sim"``).

Both take ``--preset``, ``--world-seed``, ``--with`` and ``--without`` over
the ``[sim]`` table; give both the same, or the robot and the devices live in
different worlds (:func:`celld.sim.cell.run_cell` does it for you).
- ``celld sim calibrate`` calibrates the simulated scanner offline, without
  robot or daemon (:mod:`celld.sim.calib_demo`).
- ``celld sim fault --host 127.0.0.N <fault> [--ms N] [--down-ms N]`` plays a
  fault on a running simulator (see :mod:`celld.sim.robot.faults`);
  ``clear`` undoes them and ``status`` prints the simulator's state.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from celld.cliparse import add_command


def add_parser(sub: Any) -> None:
    """Add ``sim`` and its subcommands to the top-level subparsers ``sub``.

    Each subcommand's arguments come from the simulator's modules and are
    defined when it is used (:func:`celld.cliparse.add_command`).
    """
    sim = sub.add_parser("sim", help="run simulated devices and play faults on them")
    sim_sub = sim.add_subparsers(dest="sim_command", metavar="DEVICE")
    add_command(sim_sub, "robot", _robot_arguments, help="run the simulated UR10e controller (RTDE, dashboard, script ports)")
    add_command(sim_sub, "cell", _cell_arguments, help="run the simulated cell of a cell config (robot at its home pose)")
    add_command(sim_sub, "run", _run_arguments, help="run the cell daemon on the simulated cell's scanner and SRM camera")
    add_command(
        sim_sub,
        "calibrate",
        _calibrate_arguments,
        help="calibrate the simulated scanner from the robot's flange, offline (no robot, no daemon)",
    )
    add_command(sim_sub, "fault", _fault_arguments, help="play a fault on a running simulated robot")
    add_command(
        sim_sub,
        "world",
        _world_arguments,
        help="print the world a cell config draws: every error source, its budget, what was drawn, its anchor",
    )
    sim.set_defaults(func=lambda args: sim.print_help() or 2)


def _robot_arguments(robot: argparse.ArgumentParser) -> None:
    from celld.sim.robot.options import add_arguments

    add_arguments(robot)
    robot.set_defaults(func=_run_robot)


def _cell_arguments(cell: argparse.ArgumentParser) -> None:
    from celld.sim.world import add_world_arguments

    cell.add_argument("--config", required=True, help="the cell config (e.g. configs/sim-cell.toml)")
    add_world_arguments(cell)
    cell.set_defaults(func=_run_cell)


def _run_arguments(run: argparse.ArgumentParser) -> None:
    from celld.daemon.cli import TAKE_OVER_HELP
    from celld.sim.world import add_world_arguments

    run.add_argument("--config", required=True, help="the cell config (e.g. configs/sim-cell.toml)")
    run.add_argument("--take-over", action="store_true", help=TAKE_OVER_HELP)
    add_world_arguments(run)
    run.set_defaults(func=_run_daemon)


def _calibrate_arguments(p: argparse.ArgumentParser) -> None:
    from celld.sim import calib_demo

    calib_demo.add_arguments(p)


def _world_arguments(p: argparse.ArgumentParser) -> None:
    from celld.sim.world import add_world_arguments

    p.add_argument("--config", required=True, help="the cell config (e.g. configs/sim-cell.toml)")
    p.add_argument("--json", action="store_true", help="print the world as one JSON object")
    add_world_arguments(p)
    p.set_defaults(func=_run_world)


def _run_world(args: argparse.Namespace) -> int:
    import json

    from celld import config as config_mod
    from celld.sim.world import options_from_args, world_of
    from celld.sim.worldreport import report_lines, world_report

    report = world_report(world_of(config_mod.load(args.config), options_from_args(args)))
    print(json.dumps(report, indent=1) if args.json else "\n".join(report_lines(report)))
    return 0


def _fault_arguments(fault: argparse.ArgumentParser) -> None:
    from celld.sim.robot.faults import FAULTS

    fault.add_argument("--host", required=True, help="address the simulator listens on, 127.x.y.z")
    names = [*sorted(f.replace("_", "-") for f in FAULTS), "clear", "status"]
    fault.add_argument("fault", choices=names, help="the fault, or clear / status")
    fault.add_argument("--ms", type=float, help="duration of stall, delay of latency, in milliseconds")
    fault.add_argument("--down-ms", type=float, help="how long dropped ports stay closed, milliseconds")
    fault.set_defaults(func=_run_fault)


def _run_robot(args: argparse.Namespace) -> int:
    from celld.sim.robot.options import from_args
    from celld.sim.robot.server import serve

    return serve(from_args(args))


def _run_cell(args: argparse.Namespace) -> int:
    from celld import config as config_mod
    from celld.sim.cell import robot_options, sim_part
    from celld.sim.robot.options import SimOptions, check_host
    from celld.sim.robot.server import serve
    from celld.sim.world import options_from_args, world_of

    cfg = config_mod.load(args.config)
    host = check_host(cfg.robot.host)
    world = world_of(cfg, options_from_args(args))
    part = sim_part(world)  # refused here if [sim] names no usable part
    print(f"simulated cell {cfg.cell.name}: {world.describe()}", flush=True)
    if part is not None:
        print(f"  {part.workpiece.name} at {se3_text(part.T_base_obj)}", flush=True)
    return serve(SimOptions(host=host).with_(realtime=True, q0=tuple(cfg.robot.home_q), **robot_options(world, cfg, part)))


def _run_daemon(args: argparse.Namespace) -> int:
    from celld.sim.cell import serve_daemon
    from celld.sim.world import options_from_args

    return serve_daemon(args.config, options_from_args(args), take_over=args.take_over)


def se3_text(T: Any) -> str:
    from celld import se3

    return "[" + ", ".join(f"{v:.4f}" for v in se3.to_ur_pose(T)) + "]"


def _run_fault(args: argparse.Namespace) -> int:
    from celld.sim.robot.launcher import control_request
    from celld.sim.robot.options import check_host

    host = check_host(args.host)
    if args.fault == "status":
        reply = control_request(host, "status")
    elif args.fault == "clear":
        reply = control_request(host, "clear")
    else:
        extra = {k: v for k, v in (("ms", args.ms), ("down_ms", args.down_ms)) if v is not None}
        reply = control_request(host, "inject", fault=args.fault.replace("-", "_"), **extra)
    print(json.dumps(reply))
    return 0
