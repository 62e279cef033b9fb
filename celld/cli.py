"""``celld``: the one command-line entry point, with subcommands.

Each area owns its subcommands in its own ``cli`` module, which exposes
``add_parser(subparsers)``; this module only wires them. Building the parser
imports those modules and nothing heavier: a ``cli`` module imports what a
subcommand runs inside its handler, and arguments that need more than argparse
come through :func:`celld.cliparse.add_command`, so ``celld --help`` and
``celld status`` do not load Open3D, scipy or the simulator. A subcommand
handler returns the process exit code. Errors of the :mod:`celld.errors` tree become a
one-line message on stderr and exit code 2 (or a JSON ``error`` object where
the subcommand promised JSON).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from celld import __version__
from celld.cliparse import CommandParser
from celld.errors import CelldError

# Modules that contribute subcommands, in the order they are listed in --help.
_COMMAND_MODULES = (
    "celld.config_cli",
    "celld.calib.cli",
    "celld.seam.cli",
    "celld.sim.cli",
    "celld.motion.cli",
    "celld.bus.cli",
    "celld.daemon.cli",
    "celld.sim.demo",
)


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="celld", description="Controller of one robotic welding cell.")
    parser.add_argument("--version", action="version", version=f"celld {__version__}")
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))
    parser.add_argument("--log-json", action="store_true", help="one JSON object per log line")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue  # an area not built yet
            raise
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from celld.log import configure  # structlog: not needed for --help

    configure(args.log_level, json=args.log_json)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except CelldError as exc:
        print(f"celld: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
