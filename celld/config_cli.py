"""``celld config check FILE``: validate a cell config without opening a device.

The config on its own (:func:`celld.config.load`), then what it names on this
machine (:func:`celld.preflight.preflight`): exit code 1 and one line per
finding when something would stop the cell.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

from celld import config
from celld.preflight import preflight


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="configuration tools")
    psub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    check = psub.add_parser("check", help="validate a config file and print it resolved")
    check.add_argument("file")
    check.add_argument("--json", action="store_true", help="print the resolved config as JSON")
    check.set_defaults(func=_check)


def _check(args: argparse.Namespace) -> int:
    cfg = config.load(args.file)
    found = preflight(cfg)
    if found:
        for f in found:
            print(f"{cfg.source}: {f.key}: {f.reason}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(asdict(cfg)))
    else:
        print(f"{cfg.source}: ok (cell {cfg.cell.name!r}, robot {cfg.robot.host}, scanner {cfg.scanner.kind}/{cfg.scanner.model})")
    return 0
