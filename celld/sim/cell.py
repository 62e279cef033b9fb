"""The simulated cell's truth, read from the cell config's ``[sim]`` table.

What the simulated devices show and no estimator reads: the workpiece and its
true pose on the table (the scanner's scene), and the wall the SRM finger
touches (the tactile process's simulated camera). The daemon builds its
simulated devices from here; the demo and the tests score results against it.
"""

from __future__ import annotations

import uuid
from typing import Any, NamedTuple

import numpy as np

from celld import se3
from celld.config import Config
from celld.errors import ConfigError, WorkpieceError

# A wall this far away (m) stands for "no workpiece": the finger touches nothing.
_FAR = 100.0


class SimWorkpiece(NamedTuple):
    """The simulated part: model, true pose, and the finger's true wall at the weld's tip height."""

    workpiece: Any  # celld.seam.workpiece.Workpiece
    T_base_obj: np.ndarray
    wall: Any  # celld.seam.weldpath.WeldGeometry


def sim_workpiece(config: Config) -> SimWorkpiece | None:
    """The part of ``[sim]`` at its true pose, or None for a bare table."""
    if not config.sim.workpiece:
        return None
    from celld.seam.simscene import nominal_pose
    from celld.seam.weldpath import true_wall
    from celld.seam.workpiece import example, v_groove_butt

    try:
        if config.sim.workpiece_bow != 0.0:
            if config.sim.workpiece != "v-groove":
                raise ConfigError(config.source, "sim.workpiece_bow_mm", f"only the v-groove can bow, not {config.sim.workpiece!r}")
            wp = v_groove_butt(bow=config.sim.workpiece_bow)
        else:
            wp = example(config.sim.workpiece)
    except WorkpieceError as exc:
        raise ConfigError(config.source, "sim.workpiece", str(exc)) from exc
    T = se3.from_ur_pose(config.sim.workpiece_pose) if config.sim.workpiece_pose else nominal_pose(wp)
    finger = config.seam.finger_wall if config.seam is not None else config.tactile.wall_side
    return SimWorkpiece(wp, T, true_wall(wp, T, config.weld.tip_height, finger))


def scene_extra(part: SimWorkpiece | None):
    """The scanner's extra scene objects (the part of :func:`sim_workpiece` and the table), as a callable for CellDevices."""
    from celld.seam.simscene import workpiece_scene

    objects = [] if part is None else workpiece_scene(part.workpiece, part.T_base_obj)
    return lambda: objects


def tactile_source(config: Config, part: SimWorkpiece | None):
    """The SimSourceSpec of the tactile process: the true finger wall of ``part`` (:func:`sim_workpiece`) in its plane."""
    from celld.seam.weldpath import in_plane
    from celld.sim.srm import SrmSimParams
    from celld.tactile.camera import SimSourceSpec

    side = 1.0 if config.tactile.wall_side == "left" else -1.0
    params = SrmSimParams(fps=config.tactile.fps)
    if part is None:
        wall = np.array([[_FAR, _FAR], [_FAR + 1.0, _FAR]])
        return SimSourceSpec(config.robot.host, wall, -side, np.eye(4), params)
    g = part.wall
    return SimSourceSpec(config.robot.host, in_plane(g, g.wall_base), -side, g.T_base_plane, params)


def make_tactile(config: Config, part: SimWorkpiece | None):
    """The tactile process of a cell (None when ``tactile.kind = "none"``); ``part`` feeds the simulated finger."""
    from celld.tactile.camera import TactileProcess

    kind = config.tactile.kind
    if kind == "none":
        return None
    sim = tactile_source(config, part) if kind == "sim" else None
    return TactileProcess(config.tactile, f"celld-{uuid.uuid4().hex[:8]}", sim, fifo_priority=config.tactile.rt_priority)


# -- running a whole simulated cell --------------------------------------------------


class RunningCell(NamedTuple):
    """A simulated cell with its daemon, as :func:`run_cell` yields it."""

    client: Any  # celld.bus.client.CellClient
    daemon: Any  # subprocess.Popen of ``celld run``
    config: Config
    robot: Any  # celld.sim.robot.SimRobotHandle


def run_cell(config_path, log_path, timeout: float = 90.0):
    """Start the simulated robot of a cell config and ``celld run`` on it; a context manager.

    The daemon runs as its own process, as systemd would start it, with its
    output in ``log_path``; it gets SIGTERM on exit. Yields a
    :class:`RunningCell` once the bus answers and the robot link is up.

    Raises
    ------
    CelldError
        The daemon exited, or the bus or the robot link did not come up in ``timeout`` s.
    """
    import contextlib
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from celld import config as config_mod
    from celld.bus.client import CellClient
    from celld.errors import BusError, CelldError
    from celld.sim.robot import launch

    @contextlib.contextmanager
    def _run():
        cfg = config_mod.load(config_path)
        sim_workpiece(cfg)  # a bad [sim] table is refused before anything starts
        with launch(cfg.robot.host, realtime=True, q0=tuple(cfg.robot.home_q)) as robot:
            log = open(log_path, "ab")
            proc = subprocess.Popen(
                [sys.executable, "-m", "celld.cli", "run", "--config", str(Path(config_path).resolve())],
                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            )
            client = None
            try:
                deadline = time.monotonic() + timeout

                def check(what: str) -> None:
                    if proc.poll() is not None:
                        raise CelldError(f"the daemon exited with code {proc.returncode}; see {log_path}")
                    if time.monotonic() > deadline:
                        raise CelldError(f"{what} did not come up within {timeout:g} s; see {log_path}")

                while client is None:
                    check("the daemon's bus")
                    try:
                        client = CellClient(cfg.bus, cfg.cell.name, timeout=20.0)
                    except BusError:
                        time.sleep(0.5)
                while client.status().get("robot_link") != "up":
                    check("the robot link")
                    time.sleep(0.5)
                yield RunningCell(client, proc, cfg, robot)
            finally:
                if client is not None:
                    client.close()
                if proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)
                    try:
                        proc.wait(30)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
                log.close()

    return _run()
