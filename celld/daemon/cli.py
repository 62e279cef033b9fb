"""``celld run``: the daemon, as systemd starts it."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the cell daemon (robot link, jobs over zenoh, recordings)")
    p.add_argument("--config", default="/etc/celld/cell.toml", help="the cell config (default: %(default)s)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from celld import config as config_mod
    from celld.daemon.app import serve
    from celld.daemon.devices import real_devices

    cfg = config_mod.load(args.config)  # refused here, before any device is opened
    serve(cfg, real_devices())
    return 0
