"""``celld config check FILE``: validate a cell config without opening a device.

It also says what is unsafe in the bus settings (an open bus on a
non-loopback address, traffic without TLS off this machine, certificate files
that cannot be read): one ``warning:`` line each on stderr; the exit code
stays 0, the config is valid. Passwords are never printed: ``--json``
replaces every ``password`` with ``"***"``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from typing import Any

from celld import config

# What a password is printed as.
REDACTED = "***"
# Keys whose values are secrets.
_SECRET_KEYS = frozenset({"password"})


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="configuration tools")
    psub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    check = psub.add_parser("check", help="validate a config file and print it resolved")
    check.add_argument("file")
    check.add_argument("--json", action="store_true", help="print the resolved config as JSON (passwords shown as ***)")
    check.set_defaults(func=_check)


def redact(value: Any) -> Any:
    """``value`` with every non-empty secret (``password``) replaced by :data:`REDACTED`."""
    if isinstance(value, dict):
        return {k: (REDACTED if k in _SECRET_KEYS and v else redact(v)) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [redact(v) for v in value]
    return value


def _check(args: argparse.Namespace) -> int:
    from celld.bus.session import config_warnings

    cfg = config.load(args.file)
    for warning in config_warnings(cfg.bus):
        print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        print(json.dumps(redact(asdict(cfg))))
    else:
        print(f"{cfg.source}: ok (cell {cfg.cell.name!r}, robot {cfg.robot.host}, scanner {cfg.scanner.kind}/{cfg.scanner.model})")
    return 0
