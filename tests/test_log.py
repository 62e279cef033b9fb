"""Logs a plant can read: snake_case event names everywhere, JSON lines from every process when asked."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from celld.log import LogSettings, read_events

ROOT = Path(__file__).resolve().parents[1]
LEVELS = {"debug", "info", "warning", "warn", "error", "exception", "critical", "msg"}
SNAKE = re.compile(r"^[a-z][a-z0-9]*(_[a-z0-9]+)*$")


def _log_calls() -> list[tuple[str, int, ast.expr]]:
    """Every call of a logger's level method in celld/ (a receiver whose source names ``log``): where, and its event."""
    calls = []
    for path in sorted((ROOT / "celld").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr in LEVELS
                and "log" in ast.unparse(node.func.value)
                and node.args
            ):
                calls.append((str(path.relative_to(ROOT)), node.lineno, node.args[0]))
    return calls


def test_every_event_name_is_a_snake_case_constant() -> None:
    calls = _log_calls()
    assert len(calls) > 100, "the scan finds the cell's log calls"
    bad = [
        f"{path}:{line}: {ast.unparse(event)}"
        for path, line, event in calls
        if not (isinstance(event, ast.Constant) and isinstance(event.value, str) and SNAKE.match(event.value))
    ]
    assert not bad, "event names must be snake_case string constants (what varies goes in fields):\n" + "\n".join(bad)


def _python(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)


def _json_lines(text: str) -> list[dict]:
    lines = [line for line in text.splitlines() if line.strip()]
    records = [json.loads(line) for line in lines]  # every line a JSON object, or this raises
    assert all(isinstance(r, dict) for r in records), lines
    return records


@pytest.mark.process
def test_with_json_a_process_s_uncaught_exception_and_a_library_s_record_are_json_lines() -> None:
    run = _python(
        "import logging\n"
        "from celld.log import configure, get_logger\n"
        "configure('info', json=True)\n"
        "get_logger('t').info('job_ended', job='j1')\n"
        "logging.getLogger('somelib').warning('a library speaks %s', 'plainly')\n"
        "raise ValueError('bad thing')\n"
    )
    assert run.returncode == 1
    records = _json_lines(run.stderr)
    assert [r["event"] for r in records] == ["job_ended", "a library speaks plainly", "uncaught_exception"]
    assert records[0]["job"] == "j1" and records[0]["level"] == "info" and records[0]["timestamp"].endswith("Z")
    assert records[1]["logger"] == "somelib" and records[1]["level"] == "warning"
    assert "Traceback" in records[2]["exception"] and "ValueError: bad thing" in records[2]["exception"]


@pytest.mark.process
def test_a_child_logs_as_its_parent_and_its_failure_is_an_event_with_the_traceback() -> None:
    run = _python(
        "import multiprocessing as mp\n"
        "from celld.log import configure, get_logger, run_child, settings\n"
        "from tests.test_log import child_that_fails\n"
        "configure('debug', json=True)\n"
        "p = mp.get_context('spawn').Process(target=run_child, args=(settings(), child_that_fails, 3), name='celld-x')\n"
        "p.start(); p.join()\n"
        "get_logger('t').info('child_ended', exitcode=p.exitcode)\n"
    )
    assert run.returncode == 0, run.stderr
    records = _json_lines(run.stderr)
    assert [r["event"] for r in records] == ["child_debug", "child_process_failed", "child_ended"]
    assert records[0]["n"] == 3, "the child logs at its parent's level (debug)"
    assert records[1]["process"] == "celld-x" and "RuntimeError: child 3 failed" in records[1]["exception"]
    assert records[2]["exitcode"] == 1


def child_that_fails(n: int) -> None:
    from celld.log import get_logger

    get_logger("child").debug("child_debug", n=n)
    raise RuntimeError(f"child {n} failed")


def test_read_events_reads_fields_and_passes_over_what_is_not_an_event() -> None:
    text = "\n".join(
        [
            '{"event": "motion_loop_ended", "host": "127.0.0.9", "reason": "daemon gone: no heartbeat"}',
            "a library's own print",
            '{"event": "job_failed", "error": "stale state"',  # cut short by a kill
            "[1, 2]",
            '{"event": "motion_loop_ended", "host": "127.0.0.8"}',
        ]
    )
    assert [e["host"] for e in read_events(text, "motion_loop_ended")] == ["127.0.0.9", "127.0.0.8"]
    assert list(read_events(text, "job_failed")) == []
    assert len(list(read_events(text))) == 2


def test_log_settings_pass_to_a_celld_program_as_its_options() -> None:
    assert LogSettings("debug", True).argv() == ["--log-level", "debug", "--log-json"]
    assert LogSettings().argv() == ["--log-level", "info"]
