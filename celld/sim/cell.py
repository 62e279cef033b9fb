"""The simulated cell: its truth, the devices it hands to the daemon, and a launcher.

The truth is read from the cell config's ``[sim]`` table: what the simulated
devices show and no estimator reads (the workpiece and its true pose on the
table, the wall the SRM finger touches). :func:`sim_devices` builds the
simulated scanner (ray casting the scene at the simulated controller's true
flange pose, read from its shared memory as a camera would see the real
flange) and the simulated SRM camera, and hands them to the daemon through
the same :class:`~celld.daemon.devices.DeviceFactories` a real cell uses:
``celld sim run`` is the daemon on them. :func:`run_cell` starts a whole
simulated cell (robot and daemon) for the demo, the tests and benchmarks,
which score results against the truth.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, NamedTuple

import numpy as np

from celld import config as config_mod
from celld import se3
from celld.bus.client import CellClient
from celld.calib.flange import preset
from celld.config import Config
from celld.daemon.devices import DeviceFactories, real_devices
from celld.errors import BusError, CelldError, ConfigError, WorkpieceError
from celld.scanner.base import Scanner
from celld.seam.weldpath import WeldGeometry, in_plane
from celld.seam.workpiece import Workpiece, example, v_groove_butt
from celld.sim.robot import SimRobotHandle, launch
from celld.sim.robot.truth import TruthReader
from celld.sim.scanner import SceneObject, SimulatedScanner, robot_scene_source
from celld.sim.srm import SimSrmSource, SrmSimParams
from celld.sim.workpiece import nominal_pose, true_wall, workpiece_scene

# A wall this far away (m) stands for "no workpiece": the finger touches nothing.
_FAR = 100.0


class SimWorkpiece(NamedTuple):
    """The simulated part: model, true pose, and the finger's true wall at the weld's tip height."""

    workpiece: Workpiece
    T_base_obj: np.ndarray
    wall: WeldGeometry


def sim_workpiece(config: Config) -> SimWorkpiece | None:
    """The part of ``[sim]`` at its true pose, or None for a bare table."""
    if not config.sim.workpiece:
        return None
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
    return SimWorkpiece(wp, T, true_wall(wp, T, config.weld.tip_height, config.tool.wall_side))


def srm_source(config: Config, part: SimWorkpiece | None) -> SimSrmSource:
    """The simulated SRM camera on the true finger wall of ``part`` (:func:`sim_workpiece`), in its plane."""
    side = 1.0 if config.tool.wall_side == "left" else -1.0
    params = SrmSimParams(fps=config.tactile.fps)
    if part is None:
        wall = np.array([[_FAR, _FAR], [_FAR + 1.0, _FAR]])
        return SimSrmSource(config.robot.host, wall, -side, np.eye(4), config.tool, params)
    g = part.wall
    return SimSrmSource(config.robot.host, in_plane(g, g.wall_base), -side, g.T_base_plane, config.tool, params)


class _CellScanner:
    """Opens the simulated scanner of a cell: the robot scene at the true flange pose, plus the part."""

    def __init__(self, part: SimWorkpiece | None) -> None:
        self.objects: list[SceneObject] = [] if part is None else workpiece_scene(part.workpiece, part.T_base_obj)

    def __call__(self, config: Config) -> Scanner:
        truth = TruthReader(config.robot.host)
        objects = self.objects
        # One table: the part's scene brings the steel welding table (the robot
        # scene's would lie in the same plane, a matte twin a time-of-flight
        # camera reads 8 mm apart from it).
        return SimulatedScanner(
            config.scanner.model,
            config.T_base_cam_nominal(),
            robot_scene_source(
                lambda: truth.latest().T_base_tcp, preset(config.calibration.flange), table=not objects, extra=lambda: objects
            ),
            seed=config.scanner.seed,
            resolution_scale=config.scanner.resolution_scale,
            on_close=truth.close,
        )


def sim_devices(config: Config, part: SimWorkpiece | None) -> DeviceFactories:
    """The simulated scanner and SRM camera of the cell, as the daemon opens devices."""
    camera = srm_source(config, part) if config.tactile.kind == "sim" else None
    scanner = _CellScanner(part) if config.scanner.kind == "sim" else real_devices().scanner
    return DeviceFactories(scanner=scanner, camera=camera)


def serve_daemon(config_path: str | Path) -> int:
    """``celld sim run``: the daemon of a cell config on the simulated devices (the part built once)."""
    from celld.daemon.app import serve

    cfg = config_mod.load(config_path)
    serve(cfg, sim_devices(cfg, sim_workpiece(cfg)))
    return 0


# -- running a whole simulated cell --------------------------------------------------


class RunningCell(NamedTuple):
    """A simulated cell with its daemon, as :func:`run_cell` yields it."""

    client: CellClient
    daemon: subprocess.Popen[bytes]  # ``celld sim run``
    config: Config
    robot: SimRobotHandle


class DaemonProcess(NamedTuple):
    """``celld sim run`` as its own process, and a bus client to it."""

    process: subprocess.Popen[bytes]
    client: CellClient


def start_daemon(config_path: str | Path, log: IO[bytes], timeout: float = 90.0) -> DaemonProcess:
    """Start ``celld sim run`` on a cell config (its robot must be up) and wait for its bus and robot link.

    Raises
    ------
    CelldError
        The daemon exited, or the bus or the robot link did not come up in ``timeout`` s
        (the daemon is then stopped).
    """
    cfg = config_mod.load(config_path)
    proc = subprocess.Popen(
        [sys.executable, "-m", "celld.cli", "sim", "run", "--config", str(Path(config_path).resolve())],
        stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
    )
    client = None
    deadline = time.monotonic() + timeout

    def check(what: str) -> None:
        if proc.poll() is not None:
            raise CelldError(f"the daemon exited with code {proc.returncode}; see {log.name}")
        if time.monotonic() > deadline:
            raise CelldError(f"{what} did not come up within {timeout:g} s; see {log.name}")

    try:
        while client is None:
            check("the daemon's bus")
            try:
                client = CellClient(cfg.bus, cfg.cell.name, timeout=20.0)
            except BusError:
                time.sleep(0.5)
        while client.status().get("robot_link") != "up":
            check("the robot link")
            time.sleep(0.5)
    except BaseException:
        if client is not None:
            client.close()
        stop_daemon(proc)
        raise
    return DaemonProcess(proc, client)


def stop_daemon(proc: subprocess.Popen[bytes], timeout: float = 30.0) -> None:
    """SIGTERM, as systemd stops it; SIGKILL after ``timeout`` s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_cell(config_path: str | Path, log_path: str | Path, timeout: float = 90.0) -> contextlib.AbstractContextManager[RunningCell]:
    """Start the simulated robot of a cell config and ``celld sim run`` on it; a context manager.

    The daemon runs as its own process, as systemd would start it, with its
    output in ``log_path``; it gets SIGTERM on exit. Yields a
    :class:`RunningCell` once the bus answers and the robot link is up.

    Raises
    ------
    CelldError
        The daemon exited, or the bus or the robot link did not come up in ``timeout`` s.
    """

    @contextlib.contextmanager
    def _run() -> Iterator[RunningCell]:
        cfg = config_mod.load(config_path)
        sim_workpiece(cfg)  # a bad [sim] table is refused before anything starts
        with launch(cfg.robot.host, realtime=True, q0=tuple(cfg.robot.home_q)) as robot, open(log_path, "ab") as log:
            daemon = start_daemon(config_path, log, timeout)
            try:
                yield RunningCell(daemon.client, daemon.process, cfg, robot)
            finally:
                daemon.client.close()
                stop_daemon(daemon.process)

    return _run()
