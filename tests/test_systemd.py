"""systemd/celld.service: parses without a warning and keeps its hardening.

``systemd-analyze`` comes with the ``systemd`` package (Debian 12: systemd 252).
``verify`` exits 0 even when it ignores an unknown key, so the test asserts
that stderr is empty; ``security --offline`` rates the unit and exits 1 above
``--threshold`` (tenths of the 0-10 exposure scale).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "celld.service"
# Highest accepted exposure, tenths (the unit rates 1.9 with systemd 252).
EXPOSURE_THRESHOLD = 25
ANALYZE = shutil.which("systemd-analyze")

pytestmark = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed (Debian: apt-get install systemd)")


def _installable_copy(tmp_path: Path, text: str | None = None) -> Path:
    """The unit with ExecStart pointing at an executable that exists here (verify checks it)."""
    text = UNIT.read_text() if text is None else text
    here = Path(sys.executable).with_name("celld")
    exe = here if here.exists() else Path(sys.executable)
    copy = tmp_path / "celld.service"
    copy.write_text(text.replace("/opt/celld/.venv/bin/celld", str(exe)))
    return copy


def _analyze(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([ANALYZE, *args], capture_output=True, text=True, timeout=60)


def test_unit_has_what_the_cell_needs() -> None:
    text = UNIT.read_text()
    for line in (
        "Type=notify",
        "WatchdogSec=2s",
        "Restart=on-failure",
        "LimitRTPRIO=90",
        "LimitMEMLOCK=infinity",
        "StateDirectory=celld",
        "ExecStart=/opt/celld/.venv/bin/celld --log-json run --config /etc/celld/cell.toml",
    ):
        assert re.search(rf"^{re.escape(line)}$", text, re.M), line


@pytest.mark.process
def test_systemd_analyze_verify_prints_nothing(tmp_path: Path) -> None:
    result = _analyze("verify", "--man=no", str(_installable_copy(tmp_path)))
    assert result.returncode == 0, result.stderr
    assert result.stderr == "", result.stderr


@pytest.mark.process
def test_verify_does_report_a_misspelt_key(tmp_path: Path) -> None:
    """The check above can fail: a typo is on stderr while the exit code stays 0."""
    broken = UNIT.read_text().replace("WatchdogSec=2s", "WatchdogSecs=2s")
    result = _analyze("verify", "--man=no", str(_installable_copy(tmp_path, broken)))
    assert "Unknown key 'WatchdogSecs'" in result.stderr


@pytest.mark.process
def test_security_exposure_is_below_threshold(tmp_path: Path) -> None:
    unit = _installable_copy(tmp_path)
    result = _analyze("security", "--offline=true", f"--threshold={EXPOSURE_THRESHOLD}", str(unit))
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr
    exposure = float(re.search(r"Overall exposure level for celld.service: ([0-9.]+)", result.stdout).group(1))
    assert exposure <= EXPOSURE_THRESHOLD / 10
