"""``celld run``: the daemon, as systemd starts it."""

from __future__ import annotations

import argparse
import asyncio
import functools

from celld import config as config_mod


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the cell daemon (robot link, jobs over zenoh, recordings)")
    p.add_argument("--config", default="/etc/celld/cell.toml", help="the cell config (default: %(default)s)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from celld.daemon.app import Daemon
    from celld.daemon.devices import CellDevices
    from celld.daemon.runners import build_runners
    from celld.sim.cell import make_tactile, scene_extra, sim_workpiece

    cfg = config_mod.load(args.config)  # refused here, before any device is opened
    # The simulated scanner also sees the [sim] part; the simulated finger its wall (built once).
    part = sim_workpiece(cfg) if "sim" in (cfg.scanner.kind, cfg.tactile.kind) else None
    extra = scene_extra(part) if cfg.scanner.kind == "sim" else None
    devices = CellDevices(cfg, tactile_factory=functools.partial(make_tactile, part=part), scene_extra=extra)
    daemon = Daemon(cfg, devices, build_runners(cfg, devices))
    asyncio.run(daemon.run())
    return 0
