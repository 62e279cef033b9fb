"""Fixtures of the daemon's end-to-end tests: a cell config per test, and calibrations solved once per world."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from celld import config as config_mod
from celld.sim.world import world_of
from tests.daemon.cells import solve_offline, stored_calibration, write_cell_config


@pytest.fixture
def cell_config(tmp_path: Path, loopback_host: str, request: pytest.FixtureRequest) -> Callable[..., Path]:
    """Factory: write this test's cell config (``tmp_path / "cell.toml"``) and return its path.

    ``cell_config(include, name, tables=None, *, robot2=False, recording=True)``
    builds on ``configs/<include>`` with this test's loopback address
    (``loopback_host``; with ``robot2`` the second robot's on
    ``loopback_host2``), state directory and bus endpoint, and ``tables`` on
    top (:func:`tests.daemon.cells.write_cell_config`).
    """

    def write(
        include: str | Sequence[str], name: str, tables: dict[str, Any] | None = None, *, robot2: bool = False, recording: bool = True
    ) -> Path:
        host2 = request.getfixturevalue("loopback_host2") if robot2 else None
        return write_cell_config(tmp_path / "cell.toml", include, name, loopback_host, tables, host2=host2, recording=recording)

    return write


@pytest.fixture(scope="session")
def offline_calibration(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., dict[str, Any]]:
    """Factory: a real calibration of a cell config's scanner in its world, solved once per world in this run.

    ``offline_calibration(config_path, n_poses, seed, whole_view_scale=None)``
    returns the calibration as the daemon keeps an accepted one
    (:func:`tests.daemon.cells.stored_calibration`; install it with
    :func:`tests.daemon.cells.install_calibration`), solved offline from
    ``n_poses`` generated poses (:func:`tests.daemon.cells.solve_offline`),
    for tests whose subject comes after the calibration. A scanner with a
    region of interest is calibrated on its whole view at
    ``whole_view_scale`` when it is given (an ROI is a capture setting; the
    flange's calibration poses span the view). The same world (its
    ``[sim]`` table but its power source), scanner, calibration settings, poses and seed give the
    same calibration, job id included.
    """
    cache: dict[tuple[Any, ...], dict[str, Any]] = {}

    def solve(config_path: str | Path, n_poses: int, seed: int, whole_view_scale: float | None = None) -> dict[str, Any]:
        cfg = config_mod.load(config_path)
        key = (
            # The world but its power source (drawn apart from the rest: it does not touch the calibration).
            json.dumps({k: v for k, v in cfg.sim.items() if k != "power_source"}, sort_keys=True, default=str),
            repr(cfg.scanner),
            repr(cfg.calibration),
            cfg.robot.model,
            tuple(cfg.robot.home_q),
            n_poses,
            seed,
            whole_view_scale,
        )
        if key not in cache:
            world = world_of(cfg)
            if whole_view_scale is not None:
                world = replace(world, scanner=replace(world.scanner, roi_px=None, resolution_scale=whole_view_scale))
            dataset = tmp_path_factory.mktemp("calibration") / "dataset"
            cache[key] = stored_calibration(cfg, solve_offline(cfg, world, n_poses, seed, dataset), dataset)
        return copy.deepcopy(cache[key])

    return solve
