"""The simulated cell: its world, the devices it hands to the daemon, and a launcher.

The truth is the simulator's own :class:`~celld.sim.world.World`, drawn from
the cell config's ``[sim]`` table (the nominal cell, the preset's error
budget, the seed; :func:`celld.sim.world.world_of`), never from the
controller's sections. How it reaches each device:

- the simulated robot process gets the world's physical arm
  (:attr:`World.arm`) through its options (:func:`robot_options`): it
  publishes the true pose in shared memory while RTDE reports the
  controller's nominal kinematics. In a cell with a ``[power_source]`` it
  also runs the world's power source (:attr:`World.power_source`) on the
  signals the config wires it to, with the tool's true wire end and the
  part's true work plane for the CTWD (:func:`source_options`);
- :func:`sim_devices` builds the simulated scanner (the world's unit at its
  true pose, ray casting the scene at the arm's true flange pose, read from
  the robot's shared memory, with the flange as made and the part as placed)
  and the simulated SRM camera (the tool as built, the finger's mechanics,
  the true wall of the part), and hands them to the daemon through the same
  :class:`~celld.daemon.devices.DeviceFactories` a real cell uses: ``celld
  sim run`` is the daemon on them. The scanner ray casts in a process of its
  own (:class:`~celld.scanner.process.ScannerProcess`), as the ray casting
  holds the GIL the daemon's event loop needs;
- :func:`run_cell` starts a whole simulated cell (robot and daemon, both
  given the same world: it is deterministic from the ``[sim]`` table and the
  :class:`~celld.sim.world.WorldOptions`) for the demo, the tests and
  benchmarks, which score results against the truth after the jobs end.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import IO, Any, NamedTuple

import numpy as np

from celld import config as config_mod
from celld.bus.client import CellClient
from celld.config import Config
from celld.daemon.devices import DeviceFactories, real_devices
from celld.errors import BusError, CelldError, ConfigError, WorkpieceError
from celld.scanner.base import Scanner
from celld.scanner.process import ScannerProcess
from celld.sim.robot import SimRobotHandle, launch
from celld.sim.robot.source import SourceOptions
from celld.sim.srm import ContactParams, SimSrmSource, SrmSimParams
from celld.sim.workpiece import SimWorkpiece, true_part
from celld.sim.world import World, WorldOptions, world_of
from celld.sim.world_scanner import open_world_scanner

# A wall this far away (m) stands for "no workpiece": the finger touches nothing.
_FAR = 100.0


def sim_part(world: World) -> SimWorkpiece | None:
    """The world's part as made and placed, with the finger's true wall, or None for a bare table."""
    if world.part is None:
        return None
    try:
        return true_part(world.part, world.tool.config.wall_side)
    except WorkpieceError as exc:
        raise ConfigError("[sim]", "sim.part", str(exc)) from exc


def srm_source(world: World, robot_host: str, part: SimWorkpiece | None) -> SimSrmSource:
    """The simulated SRM camera: the world's camera, tool and finger on the true wall of ``part``, in its plane."""
    f = world.finger
    contact = replace(
        ContactParams(),
        stiffening=f.stiffening,
        static_friction_ratio=f.static_friction_ratio,
        hysteresis=f.hysteresis,
        tag_gain=f.tag_gain,
        tag_softening=f.tag_softening,
    )
    cam = world.camera
    params = SrmSimParams(contact=contact, fps=0.0, seed=cam.seed, stamp_sigma=cam.stamp_sigma, delivery_jitter=cam.delivery_jitter)
    tool = world.tool.config
    if part is None:
        wall = np.array([[_FAR, _FAR], [_FAR + 1.0, _FAR]])
        side = 1.0 if tool.wall_side == "left" else -1.0
        return SimSrmSource(robot_host, wall, -side, np.eye(4), tool, params, camera=world.srm)
    return SimSrmSource(robot_host, part.wall, part.wall.free, part.T_base_plane, tool, params, far_wall=part.far_wall, camera=world.srm)


class _CellScanner:
    """Opens the simulated scanner of a world in a process of its own (:class:`~celld.scanner.process.ScannerProcess`:
    the ray casting holds the GIL, which the daemon's event loop needs): the robot scene at the true flange pose
    with the tool as built, plus the part (:func:`celld.sim.world_scanner.open_world_scanner`, in a module of its own
    so the child imports only what the scanner needs, not the daemon)."""

    def __init__(self, world: World, part: SimWorkpiece | None) -> None:
        self.world = world
        self.part = part

    def __call__(self, config: Config) -> Scanner:
        host2 = config.robot2.robot.host if config.robot2 is not None else None
        return ScannerProcess(partial(open_world_scanner, self.world, self.part, config.robot.host, host2), name="sim-scanner")


def sim_devices(config: Config, world: World, part: SimWorkpiece | None) -> DeviceFactories:
    """The simulated scanner and SRM camera of the world, as the daemon opens devices."""
    camera = srm_source(world, config.robot.host, part) if config.tactile.kind == "sim" else None
    scanner = _CellScanner(world, part) if config.scanner.kind == "sim" else real_devices().scanner
    return DeviceFactories(scanner=scanner, camera=camera)


def source_options(config: Config, world: World, part: SimWorkpiece | None) -> SourceOptions | None:
    """The power source on the simulated robot's I/O, or None when the config wires none.

    The wires are where the config says (the signals of ``[power_source]``
    and the spans of its analog ones); the behaviour is the world's. The CTWD
    is measured from the tool's true wire end to ``part``'s true work plane
    (its welding plane: through the root line, normal out of the joint;
    without a part the CTWD is the nominal). The world's nominal CTWD, when
    ``[sim.power_source]`` gives none, is the height the cell plans its torch
    at (``weld.tip_height``): the job was set up for the weld as planned.
    """
    ps = config.power_source
    if not ps.enabled:
        return None
    signals = tuple((role, str(sig)) for role, sig in ps.signals)
    ranges = tuple((role, ps.range(role)) for role, sig in ps.signals if sig.kind in ("ao", "ai"))
    truth = world.power_source
    if truth.ctwd_nominal is None:
        truth = replace(truth, ctwd_nominal=config.weld.tip_height)
    plane: dict[str, Any] = {}
    if part is not None:
        T = part.T_base_plane
        plane = {"p_base_plane": tuple(T[:3, 3].tolist()), "n_base_plane": tuple(T[:3, 2].tolist())}
    return SourceOptions(signals, ranges, truth, p_flange_wire=tuple(world.tool.p_flange_torch.tolist()), **plane)


def robot_options(world: World, config: Config | None = None, part: SimWorkpiece | None = None) -> dict[str, Any]:
    """The simulated robot's options of the world: its model, the table its controller computes with, and its
    physical arm when it is not that table; with the cell's ``config``, the power source it wires
    (:func:`source_options`, on the world's ``part`` as :func:`sim_part` builds it)."""
    arm = None if world.arm.is_model(world.nominal_dh) else world.arm
    source = source_options(config, world, part) if config is not None else None
    return {"model": world.nominal.robot, "arm": arm, "kinematics": world.kinematics, "power_source": source}


def robot2_options(world: World) -> dict[str, Any]:
    """The simulated second robot's options, as :func:`robot_options`; the world must have one."""
    r2 = world.robot2
    if r2 is None:
        raise ConfigError("[sim]", "sim.robot2", "the world has no second robot")
    return {"model": r2.model, "arm": None if r2.arm.is_model(r2.nominal_dh) else r2.arm, "kinematics": r2.kinematics}


def check_robot2(config: Config, world: World) -> None:
    """A config's [robot2] and its world's [sim.robot2] come together or not at all."""
    if (config.robot2 is None) != (world.robot2 is None):
        have, lack = ("[robot2]", "[sim.robot2]") if config.robot2 is not None else ("[sim.robot2]", "[robot2]")
        raise ConfigError(config.source, "robot2", f"the config has {have} but no {lack}: the simulated cell needs both for a second robot")


def serve_daemon(config_path: str | Path, options: WorldOptions = WorldOptions(), take_over: bool = False) -> int:
    """``celld sim run``: the daemon of a cell config on the simulated devices of its world (the part built once);
    ``take_over`` as ``celld run --take-over``."""
    from celld.daemon.app import serve
    from celld.log import get_logger

    cfg = config_mod.load(config_path)
    world = world_of(cfg, options)
    check_robot2(cfg, world)
    get_logger(__name__).info("sim_world", world=world.describe())
    serve(cfg, sim_devices(cfg, world, sim_part(world)), take_over)
    return 0


# -- running a whole simulated cell --------------------------------------------------


class RunningCell(NamedTuple):
    """A simulated cell with its daemon, as :func:`run_cell` yields it."""

    client: CellClient
    daemon: subprocess.Popen[bytes]  # ``celld sim run``
    config: Config
    robot: SimRobotHandle
    world: World
    robot2: SimRobotHandle | None = None  # the second robot's simulator, when the cell has one


class DaemonProcess(NamedTuple):
    """``celld sim run`` as its own process, and a bus client to it."""

    process: subprocess.Popen[bytes]
    client: CellClient


def _links_up(status: dict[str, Any]) -> bool:
    """Whether the status reply has every robot link of the cell up (the second robot's too, when there is one)."""
    robot2 = status.get("robot", {}).get("robot2_link")
    return status.get("robot_link") == "up" and robot2 in (None, "up")


def start_daemon(
    config_path: str | Path,
    log: IO[bytes],
    timeout: float = 90.0,
    world: WorldOptions = WorldOptions(),
    *,
    links: bool = True,
    take_over: bool = False,
) -> DaemonProcess:
    """Start ``celld sim run`` (with ``--take-over`` when ``take_over``) on a cell config (its robot in the same
    ``world``) and wait for its bus and, with ``links``, its robot links (the robot must be up then).

    Raises
    ------
    CelldError
        The daemon exited, or the bus or the robot link did not come up in ``timeout`` s
        (the daemon is then stopped).
    """
    cfg = config_mod.load(config_path)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "celld.cli",
            "--log-json",  # its log is read by its fields (celld.log.read_events)
            "sim",
            "run",
            "--config",
            str(Path(config_path).resolve()),
            *world.to_argv(),
            *(["--take-over"] if take_over else []),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
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
                time.sleep(0.1)
        while links and not _links_up(client.status()):
            check("the robot link")
            time.sleep(0.1)
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


def run_cell(
    config_path: str | Path, log_path: str | Path, timeout: float = 90.0, world: WorldOptions = WorldOptions()
) -> contextlib.AbstractContextManager[RunningCell]:
    """Start the simulated robot of a cell config and ``celld sim run`` on it; a context manager.

    Both get the world of the config's ``[sim]`` table with ``world`` over it
    (the same one: it is drawn deterministically). The daemon runs as its own
    process, as systemd would start it, with its output in ``log_path``; it
    gets SIGTERM on exit. Yields a :class:`RunningCell` once the bus answers
    and the robot links are up.

    Raises
    ------
    CelldError
        The daemon exited, or the bus or the robot link did not come up in ``timeout`` s.
    """

    @contextlib.contextmanager
    def _run() -> Iterator[RunningCell]:
        cfg = config_mod.load(config_path)
        w = world_of(cfg, world)  # a bad [sim] table is refused before anything starts
        part = sim_part(w)
        check_robot2(cfg, w)
        with contextlib.ExitStack() as stack:
            options = robot_options(w, cfg, part)
            robot = stack.enter_context(launch(cfg.robot.host, realtime=True, q0=tuple(cfg.robot.home_q), **options))
            robot2 = None
            if cfg.robot2 is not None:
                r2 = cfg.robot2.robot
                robot2 = stack.enter_context(launch(r2.host, realtime=True, q0=tuple(r2.home_q), **robot2_options(w)))
            log = stack.enter_context(open(log_path, "ab"))
            daemon = start_daemon(config_path, log, timeout, world)
            try:
                yield RunningCell(daemon.client, daemon.process, cfg, robot, w, robot2)
            finally:
                daemon.client.close()
                stop_daemon(daemon.process)

    return _run()
