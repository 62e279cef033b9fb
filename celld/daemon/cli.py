"""``celld run``: the daemon, as systemd starts it; ``celld bus schema``: the bundle of the bus it serves.

``bus schema`` is the daemon's command, not the bus's: the bundle holds each
job kind's result schema, which lives with the runners above the bus
(:data:`celld.daemon.results.BUNDLE`).
"""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the cell daemon (robot link, jobs over zenoh, recordings)")
    p.add_argument("--config", default="/etc/celld/cell.toml", help="the cell config (default: %(default)s)")
    p.set_defaults(func=_run)

    b = sub.add_parser("bus", help="bus tools")
    bsub = b.add_subparsers(dest="bus_command", metavar="ACTION", required=True)
    e = bsub.add_parser("schema", help="export the JSON Schema of every bus message and job result, and the AsyncAPI document")
    e.add_argument("--out", required=True, help="directory to write <name>.schema.json files and asyncapi.json into")
    e.set_defaults(func=_schema)


def _run(args: argparse.Namespace) -> int:
    from celld import config as config_mod
    from celld.daemon.app import serve
    from celld.daemon.devices import real_devices

    cfg = config_mod.load(args.config)  # refused here, before any device is opened
    serve(cfg, real_devices())
    return 0


def _schema(args: argparse.Namespace) -> int:
    from celld.bus.asyncapi import export_schemas
    from celld.daemon.results import BUNDLE

    for path in export_schemas(args.out, BUNDLE):
        print(path)
    return 0
