"""``celld config check FILE``: validate a cell config without opening a device."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict

from celld import config


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="configuration tools")
    psub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    check = psub.add_parser("check", help="validate a config file and print it resolved")
    check.add_argument("file")
    check.add_argument("--json", action="store_true", help="print the resolved config as JSON")
    check.set_defaults(func=_check)


def _check(args: argparse.Namespace) -> int:
    cfg = config.load(args.file)
    if args.json:
        print(json.dumps(asdict(cfg)))
    else:
        print(f"{cfg.source}: ok (cell {cfg.cell.name!r}, robot {cfg.robot.host}, scanner {cfg.scanner.kind}/{cfg.scanner.model})")
    return 0
