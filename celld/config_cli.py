"""``celld config check FILE``: validate a cell config without opening a device.

The config on its own (:func:`celld.config.load`), then what it names on this
machine (:func:`celld.preflight.preflight`): exit code 1 and one line per
finding when something would stop the cell.

It also says what is unsafe in the bus settings (an open bus on a
non-loopback address, traffic without TLS off this machine, certificate files
that cannot be read): one ``warning:`` line each on stderr; warnings alone
leave the exit code 0. Passwords are never printed: ``--json``
replaces every ``password`` with ``"***"``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from dataclasses import fields, is_dataclass
from typing import Any

# What a password is printed as.
REDACTED = "***"
# Keys whose values are secrets.
_SECRET_KEYS = frozenset({"password"})


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="configuration tools")
    psub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    check = psub.add_parser("check", help="validate a config file and print it resolved")
    check.add_argument("file")
    check.add_argument(
        "--json",
        action="store_true",
        help="print the config as JSON by the file's own keys and units, defaults filled in (passwords as ***)",
    )
    check.add_argument("--client", action="store_true", help="a client's config (the CLI's, an MES's): it needs no [robot]")
    check.set_defaults(func=_check)


def plain(value: Any) -> Any:
    """A config value as JSON types: sections as objects, the raw ``[sim]`` table as it was read."""
    if is_dataclass(value) and not isinstance(value, type):
        # What the config derived (not a key of the file) is not printed as one.
        return {f.name: plain(getattr(value, f.name)) for f in fields(value) if not f.metadata.get("derived")}
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    import numpy as np

    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return value


def redact(value: Any) -> Any:
    """``value`` with every non-empty secret (``password``) replaced by :data:`REDACTED`."""
    if isinstance(value, dict):
        return {k: (REDACTED if k in _SECRET_KEYS and v else redact(v)) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [redact(v) for v in value]
    return value


def _check(args: argparse.Namespace) -> int:
    from celld import config
    from celld.bus.session import config_warnings
    from celld.preflight import preflight

    cfg = config.load(args.file)
    for warning in config_warnings(cfg.bus):
        print(f"warning: {warning}", file=sys.stderr)
    found = preflight(cfg, daemon=not args.client)
    if found:
        for f in found:
            print(f"{cfg.source}: {f.key}: {f.reason}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(redact(plain(cfg.resolved))))
    else:
        print(f"{cfg.source}: ok (cell {cfg.cell.name!r}, robot {cfg.robot.host}, scanner {cfg.scanner.kind}/{cfg.scanner.model})")
    return 0
