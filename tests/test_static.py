"""The code passes its linter, its formatter and its type checker (configured in pyproject.toml)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.process  # ruff and mypy run as child processes

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_ruff_finds_nothing() -> None:
    out = _run("ruff", "check", "--no-cache", "--output-format", "concise", "celld", "tests", "bench", "examples")
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_code_is_formatted() -> None:
    out = _run("ruff", "format", "--check", "--no-cache", "celld", "tests", "bench", "examples")
    assert out.returncode == 0, "run `ruff format celld tests bench examples`:\n" + out.stdout + out.stderr


def test_mypy_finds_nothing() -> None:
    out = _run("mypy", "celld")
    assert out.returncode == 0, out.stdout + out.stderr
