"""The command line's parser: subcommands whose arguments are defined when they are used.

``celld --help`` lists every subcommand, and ``celld status`` parses one; neither
should import Open3D, scipy or the simulator because some other subcommand's
arguments take their choices or defaults from there. A subcommand added with
:func:`add_command` to a :class:`CommandParser` gets its arguments from a
function that runs only when that subcommand is parsed or its help printed;
the function imports what the arguments need. The help texts and arguments are
the same as if they had been added at once: to any other parser (a test's
plain :class:`argparse.ArgumentParser`) :func:`add_command` adds them at once.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable, Sequence
from typing import Any

# Where an installed cell keeps its config, and the variable that names another.
SYSTEM_CONFIG = "/etc/celld/cell.toml"
CONFIG_ENV = "CELLD_CONFIG"
CONFIG_HELP = f"the cell config (default: ${CONFIG_ENV}, else {SYSTEM_CONFIG})"


def default_config() -> str:
    """The cell config a command reads without ``--config``: ``$CELLD_CONFIG`` when set and not empty, else
    :data:`SYSTEM_CONFIG`."""
    return os.environ.get(CONFIG_ENV, "").strip() or SYSTEM_CONFIG


# Adds a subcommand's arguments (and set_defaults(func=...)) to its parser.
Define = Callable[[argparse.ArgumentParser], None]


class CommandParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose arguments may be defined on first use (see the module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._define: Define | None = None

    def define_later(self, define: Define) -> None:
        """Have ``define(self)`` add this parser's arguments before it first parses or formats anything."""
        self._define = define

    def _defined(self) -> None:
        define, self._define = self._define, None
        if define is not None:
            define(self)

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self._defined()
        return super().parse_known_args(args, namespace)

    def format_usage(self) -> str:
        self._defined()
        return super().format_usage()

    def format_help(self) -> str:
        self._defined()
        return super().format_help()


def add_command(sub: argparse._SubParsersAction, name: str, define: Define, **kwargs: Any) -> argparse.ArgumentParser:
    """Add subcommand ``name`` (``help=``, ``parents=``, ... as ``sub.add_parser`` takes) whose arguments ``define`` adds.

    Under a :class:`CommandParser` ``define`` runs when the subcommand is used;
    under any other parser, now.
    """
    parser = sub.add_parser(name, **kwargs)
    if isinstance(parser, CommandParser):
        parser.define_later(define)
    else:
        define(parser)
    return parser
