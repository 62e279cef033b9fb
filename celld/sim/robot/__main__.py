"""``python -m celld.sim.robot --host 127.0.0.N``: run the simulated UR10e controller."""

from __future__ import annotations

import argparse
import sys

from celld.errors import CelldError
from celld.log import configure
from celld.sim.robot.options import add_arguments, from_args
from celld.sim.robot.server import serve


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m celld.sim.robot", description="Simulated UR10e controller.")
    add_arguments(parser)
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))
    parser.add_argument("--log-json", action="store_true", help="one JSON object per log line")
    args = parser.parse_args(argv)
    configure(args.log_level, json=args.log_json)
    try:
        options = from_args(args)
    except CelldError as exc:
        print(f"celld sim robot: error: {exc}", file=sys.stderr)
        return 2
    return serve(options)


if __name__ == "__main__":
    sys.exit(main())
