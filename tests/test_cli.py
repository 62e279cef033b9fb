"""``celld``'s command line: what building it and a status query import, and that lazily defined arguments are the same."""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from celld.cli import _COMMAND_MODULES, build_parser

# What no parser needs, nor a status query: each costs a second or hundreds of MB at import.
HEAVY = ("open3d", "scipy", "cv2", "rerun", "matplotlib", "ruckig", "rtde_control", "rtde_receive")
# The simulator's modules that building the parser may import: the sim area's own command line.
SIM_COMMAND_LINE = {"celld.sim", "celld.sim.cli", "celld.sim.demo"}

# Runs argv through celld's main in a fresh interpreter, then prints the modules it had loaded.
_PROBE = """
import json, sys
from celld.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps({"code": code, "modules": sorted(sys.modules)}))
"""


def _run_celld(*argv: str) -> tuple[int, set[str], str]:
    out = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, timeout=120, check=True)
    report = json.loads(out.stdout.strip().splitlines()[-1])
    return report["code"], set(report["modules"]), out.stdout + out.stderr


def _loaded(modules: set[str], roots: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules if m.split(".")[0] in roots)


def _simulator(modules: set[str]) -> list[str]:
    return sorted(m for m in modules if m.startswith("celld.sim.") and m not in SIM_COMMAND_LINE)


def test_help_imports_no_heavy_module_nor_the_simulator() -> None:
    code, modules, out = _run_celld("--help")
    assert code == 0 and "demo" in out and "status" in out, out
    assert _loaded(modules, HEAVY) == []
    assert _simulator(modules) == []
    # Listing the commands needs argparse, not numpy, the bus, the logger or an event loop.
    assert _loaded(modules, ("numpy", "zenoh", "structlog", "asyncio")) == []


def test_status_imports_what_one_bus_query_needs(tmp_path: Path, loopback_host: str) -> None:
    config = tmp_path / "cell.toml"
    config.write_text(
        f'[cell]\nname = "nobody"\nstate_dir = "{tmp_path / "state"}"\n\n'
        f'[bus]\nmode = "peer"\nlisten = ["tcp/{loopback_host}:7447"]\nconnect_timeout_s = 0.1\n'
    )
    code, modules, out = _run_celld("status", "--config", str(config))
    # No cell there: the query is refused, after loading the config and opening the bus.
    assert code == 2 and "no link" in out, out
    assert {"zenoh", "celld.config", "celld.bus.client"} <= modules
    assert _loaded(modules, HEAVY) == []
    assert _simulator(modules) == []


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> dict[tuple[str, ...], str]:
    """Every parser under ``parser`` by its command path, as its help text."""
    out = {path: parser.format_help()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.update(_parsers(sub, (*path, name)))
    return out


def test_arguments_defined_when_used_are_those_defined_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "120")
    eager = argparse.ArgumentParser(prog="celld")
    sub = eager.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)  # a plain parser: every argument added at once
    lazy = _parsers(build_parser())
    at_once = _parsers(eager)
    assert set(lazy) == set(at_once) and len(lazy) > 30
    for path in sorted(at_once):
        if path:
            assert lazy[path] == at_once[path], " ".join(path)
    # A lazily defined subcommand parses as before.
    args = build_parser().parse_args(["jobs", "--state", "failed", "--config", "c.toml"])
    assert (args.state, args.limit, args.config, args.func.__name__) == ("failed", 20, "c.toml", "_jobs")


def _readme_commands() -> set[tuple[str, ...]]:
    """Each ``celld`` command README.md names in its code (blocks and inline spans): the words that name the
    command, up to its first argument or option."""
    import re

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    code = re.findall(r"```.*?```", text, flags=re.S) + re.findall(r"`([^`\n]+)`", text)
    found = set()
    for chunk in code:
        for m in re.finditer(r"(?:^|bin/)celld((?: [a-z][a-z0-9-]*){1,3})", chunk, flags=re.M):
            found.add(tuple(m.group(1).split()))
    return found


def test_every_command_the_readme_names_exists() -> None:
    commands = _readme_commands()
    assert ("submit", "weld") in commands and ("status",) in commands and len(commands) > 15, commands
    parser = build_parser()
    for words in sorted(commands):
        # The longest prefix of the words the parser takes as commands (the rest are a command's values).
        for n in range(len(words), 0, -1):
            try:
                parser.parse_args([*words[:n], "--help"])
            except SystemExit as exc:
                if exc.code == 0:
                    break
        else:
            pytest.fail(f"README.md names `celld {' '.join(words)}`, which is no command")
