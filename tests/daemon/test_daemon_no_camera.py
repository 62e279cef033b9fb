"""A cell whose SRM camera is missing still starts: it calibrates and moves, refuses welds, and says why."""

from __future__ import annotations

from pathlib import Path

import pytest

from celld.sim.cell import run_cell

pytestmark = pytest.mark.cell


def test_without_its_camera_the_daemon_runs_reports_it_and_refuses_welds(tmp_path: Path, cell_config) -> None:
    cfg = cell_config(
        "sim-cell.toml",
        "no-camera",
        {"sim": {"scanner": {"resolution_scale": 0.25}}, "tactile": {"kind": "opencv", "device": "/dev/celld-no-such-camera"}},
        recording=False,  # nothing here reads a recording
    )
    with run_cell(cfg, tmp_path / "daemon.log", timeout=90) as cell:
        client = cell.client
        _, health = client.submit_and_wait({"kind": "health", "check": "tactile"}, timeout=60)
        assert health["state"] == "failed" and "tactile process is not running" in health["reason"], health
        _, weld = client.submit_and_wait({"kind": "weld"}, timeout=60)
        assert weld["state"] == "failed" and "tactile sensor is not running" in weld["reason"], weld
        _, robot = client.submit_and_wait({"kind": "health", "check": "robot"}, timeout=60)
        assert robot["state"] == "succeeded", robot["reason"]
        assert cell.daemon.poll() is None
