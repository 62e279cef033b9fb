"""The cell's devices as the daemon sees them: robots, tactile sensor, scanner, and what keeps them.

:class:`CellDevices` is composed of its parts: robot 1 and, on a cell with
``[robot2]``, robot 2 (each an :class:`~celld.daemon.arm.Arm`: its motion
process and its checked moves), the SRM camera's process (:class:`Tactile`),
the scanner (:class:`CellScanner`) and the life cycle (:class:`Lifecycle`:
the leftovers of a killed daemon, the heartbeat the children watch, robot
1's dashboard). It opens, in order, the heartbeat, the tactile camera process
when the cell has one, each robot's motion process (through
:class:`~celld.motion.handle.MotionHandle`, which owns the robot link and
restarts its process) and the scanner; it closes them in the reverse order,
robots first, after a jerk-limited stop.

The same code path serves the real cell and the simulated one. What differs
is the :class:`DeviceFactories` the daemon is given: a real cell opens the
drivers its config names (:func:`real_devices`); the simulated cell
(:mod:`celld.sim.cell`) hands factories of its own simulated scanner and
SRM camera, which show its world. Nothing here knows which it got.

Blocking device calls (a scan takes up to a second) run in worker threads so
the daemon's event loop never stalls.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
import uuid
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from celld import schemadoc, se3
from celld.config import Config
from celld.daemon.arm import Arm, robot2_config
from celld.daemon.planning import arm_obstacles
from celld.errors import CelldError, ConfigError, DeviceError, InputError
from celld.log import get_logger
from celld.motion.algorithm2 import NAME as ALGORITHM2
from celld.motion.loop import INTERLOCK_MISSING
from celld.robot.cellmodel import CellObject
from celld.robot.dashboard import ACTIONS, Dashboard, RobotCondition, foreign_program, robot_condition
from celld.scanner.base import OrganizedCloud, Scanner
from celld.scanner.factory import open_scanner
from celld.supervision import Backoff, BeatThread, ChildRecords, Heartbeat, exit_notes
from celld.tactile.camera import FrameSourceFactory, opencv_camera
from celld.tactile.process import CAMERA_REALTIME, TactileProcess
from celld.tactile.sample import TactileSample

if TYPE_CHECKING:
    from celld.recording.job import JobRecording

log = get_logger(__name__)

# Servo laws the motion process may be asked to run, by name.
SERVO_LAWS = {ALGORITHM2: "celld.motion.algorithm2:make_algorithm2"}
# How often the daemon's heartbeat beats, s (its children wait motion.parent_timeout for it at rest,
# motion.hang_stop while the arm moves or the arc is on). It beats from a thread of its own
# (celld.supervision.BeatThread) while the event loop has run within LOOP_HANG s: a frozen daemon is
# seen within hang_stop, a stuck event loop within LOOP_HANG more.
HEARTBEAT_PERIOD = 0.02
LOOP_HANG = 1.0
# Least time between two restarts of a dying tactile process, s: it doubles
# after each failed restart, up to a minute.
TACTILE_BACKOFF = Backoff(delays=(2.0, 4.0, 8.0, 16.0, 32.0, 60.0))
# How long to wait between attempts to open a scanner that did not open (off, unplugged), s.
SCANNER_BACKOFF = Backoff(delays=(2.0, 4.0, 8.0, 16.0, 30.0))
# What to do about a robot another program keeps.
HELD_REMEDY = "celld takes the robot once it stops: stop it on the teach pendant, or start celld with --take-over"
# Job kinds and the devices they need beyond robot 1 (a health job needs none).
_NEEDS_SCANNER = frozenset({"calibrate", "weld", "tool-calibrate", "verify"})
# The dashboard server is read this often, s.
DASHBOARD_PERIOD = 0.5
# The JSON shape of CellDevices.interlock_report.
INTERLOCK_SCHEMA = schemadoc.obj(
    "What celld can say about the arc interlock (the robot's standard outputs low when the program stops).",
    {
        "verified": schemadoc.boolean("Always false: the setting cannot be read over RTDE or the dashboard."),
        "missing_seen": schemadoc.boolean("A motion process found the arc output left on by the one before it: the setting is missing."),
        "detail": schemadoc.string("What it found, empty when nothing."),
        "note": schemadoc.string(),
    },
    ("verified", "missing_seen", "detail", "note"),
)


@dataclass(frozen=True)
class DeviceFactories:
    """How the daemon opens a cell's scanner and SRM camera.

    Attributes
    ----------
    scanner : callable(Config) -> Scanner
        Opens the scanner, ready to capture (blocking; run in a worker thread).
    camera : FrameSourceFactory or None
        Builds the SRM camera inside the tactile process (picklable); None:
        the config's ``tactile.kind`` names it.
    """

    scanner: Callable[[Config], Scanner]
    camera: FrameSourceFactory | None = None


def _open_configured_scanner(config: Config) -> Scanner:
    return open_scanner(config.scanner)


def real_devices() -> DeviceFactories:
    """The factories of a real cell: the drivers its config names."""
    return DeviceFactories(scanner=_open_configured_scanner)


def make_tactile(
    config: Config, camera: FrameSourceFactory | None = None, heartbeat: str = "", records: ChildRecords | None = None
) -> TactileProcess | None:
    """The tactile process of a cell (not started), or None when ``tactile.kind = "none"``.

    It watches this process and the ``heartbeat`` slot, and is recorded in ``records``.

    Raises
    ------
    ConfigError
        ``tactile.kind = "sim"`` without a camera factory: only the simulated
        cell provides that camera.
    """
    kind = config.tactile.kind
    if kind == "none":
        return None
    if camera is None:
        if kind == "sim":
            raise ConfigError(
                config.source,
                "tactile.kind",
                "'sim' is the simulated cell's SRM camera: run this config with `celld sim run`, or use 'opencv'",
            )
        camera = opencv_camera
    realtime = replace(CAMERA_REALTIME, priority=config.tactile.rt_priority)
    return TactileProcess(
        config.tactile,
        config.tool,
        f"celld-{uuid.uuid4().hex[:8]}",
        camera,
        realtime,
        heartbeat=heartbeat,
        parent_timeout=config.motion.parent_timeout,
        records=records,
        rest_file=Path(config.cell.state_dir) / "tactile" / "rest.json",
    )


class Tactile:
    """The SRM camera's process as the daemon keeps it: started, watched, restarted with back-off.

    ``process`` is None on a cell without a finger camera (``tactile.kind =
    "none"``); ``error`` says why the process is not running ("" while it is).
    """

    def __init__(self, config: Config, camera: FrameSourceFactory | None) -> None:
        self.config = config
        self._camera = camera
        self.process: TactileProcess | None = None
        self.error = ""
        self._restart_at = -math.inf
        self._failures = 0

    def prepare(self, heartbeat: str, records: ChildRecords) -> None:
        """Make the process and its shared-memory slots (when the cell has a finger camera), not started yet:
        the motion process reads the samples from :attr:`slot_name`."""
        self.process = make_tactile(self.config, self._camera, heartbeat, records)

    async def open(self) -> None:
        """Start the process made by :meth:`prepare`; a failed start is retried by :meth:`supervise`."""
        if self.process is None:
            return
        try:
            await asyncio.to_thread(self.process.start)
        except CelldError as exc:
            # The cell still calibrates and moves; welds are refused until
            # the supervision brings the camera back (supervise).
            self.error = str(exc)
            self._restart_at = time.monotonic()
            log.error("tactile_start_retrying", error=str(exc))

    async def close(self) -> None:
        if self.process is not None:
            await asyncio.to_thread(self.process.stop)
            self.process = None

    @property
    def slot_name(self) -> str | None:
        """The shared-memory slot the motion loop reads the samples from (None without a finger camera)."""
        return None if self.process is None else self.process.slot_name

    async def supervise(self) -> None:
        """Restart the process if it died, waiting between attempts as TACTILE_BACKOFF says.

        The daemon calls this periodically. While the process is down the
        motion loop sees no fresh sample, so a running servo stops on a stale
        sample with that reason; the restarted process tares before it
        reports deformation again.
        """
        process = self.process
        if process is None or process.alive():
            return
        now = time.monotonic()
        delay = TACTILE_BACKOFF.delay(self._failures + 1)
        if now - self._restart_at < delay:
            return
        self._restart_at = now
        log.error("tactile_process_restarting", exitcode=process.exitcode, restarts=process.restarts)
        try:
            await asyncio.to_thread(process.restart)
            self._failures = 0
            self.error = ""
            log.info("tactile_process_restarted", restarts=process.restarts)
        except CelldError as exc:
            self._failures += 1
            self.error = str(exc)
            log.error("tactile_process_restart_failed", error=str(exc), next_try_s=TACTILE_BACKOFF.delay(self._failures + 1))

    def wait_reason(self) -> str:
        """Why the cell waits for its finger camera ("" when it reads): its process ended, failed to start, or is
        starting (alive, but not yet reading its camera: it may still fail, so no job counts on it yet)."""
        process = self.process
        if process is None or process.running():
            return ""
        why = self.error or ("its process is starting" if process.alive() else "its process ended; restarting it")
        return f"finger camera not running: waiting ({why})"

    def sample(self) -> TactileSample | None:
        return None if self.process is None else self.process.latest()

    def state_message(self) -> dict[str, Any] | None:
        sample = self.sample()
        if sample is None:
            return None
        msg: dict[str, Any] = {"t_ns": max(0, sample.stamp_ns), "valid": bool(sample.valid), "contact": int(sample.contact) > 0}
        if sample.valid:
            msg["delta"] = np.asarray(sample.delta_tool).tolist()
        return msg


class CellScanner:
    """The cell's scanner, opened by its factory in a worker thread; a capture runs in one too.

    A scanner that does not open (off at boot, unplugged, its SDK missing) is
    not the daemon's end: ``error`` says why, the jobs that need it are
    refused with that, and :meth:`supervise` tries again with back-off.
    """

    def __init__(self, config: Config, factory: Callable[[Config], Scanner]) -> None:
        self.config = config
        self._factory = factory
        self.device: Scanner | None = None
        self.error = ""
        self._failures = 0
        self._retry_at = -math.inf

    async def open(self) -> None:
        try:
            self.device = await asyncio.to_thread(self._factory, self.config)
        except CelldError as exc:
            self._failures += 1
            self.error = str(exc)
            self._retry_at = time.monotonic() + SCANNER_BACKOFF.delay(self._failures)
            log.error(
                "scanner_open_retrying",
                error=self.error,
                next_try_s=SCANNER_BACKOFF.delay(self._failures),
            )
            return
        if self._failures:
            log.info("scanner_open", after_attempts=self._failures + 1)
        self.error, self._failures = "", 0

    async def supervise(self) -> None:
        """Open the scanner again if it did not open, when its back-off has passed."""
        if self.device is None and self.error and time.monotonic() >= self._retry_at:
            await self.open()

    async def close(self) -> None:
        if self.device is not None:
            await asyncio.to_thread(self.device.close)
            self.device = None

    async def capture(self) -> OrganizedCloud:
        if self.device is None:
            raise DeviceError(f"the scanner is not open: {self.error or 'not opened yet'}")
        return await asyncio.to_thread(self.device.capture)


class Lifecycle:
    """What keeps the cell's processes honest: the leftovers of a killed daemon cleaned up, the daemon's
    heartbeat for its children (a hung loop stops the robot), and robot 1's dashboard read periodically."""

    def __init__(self, config: Config) -> None:
        self.records = ChildRecords(Path(config.cell.state_dir) / "run")
        self.leftovers: list[str] = []  # what was cleaned up after a previous daemon
        # Why the previous daemon's children took it for gone (hung, killed), oldest first (exit_notes).
        self.exit_notes: list[dict[str, Any]] = []
        self.heartbeat: Heartbeat | None = None
        self._beater: BeatThread | None = None
        self.dashboard = Dashboard(config.robot.host)
        self._reading: asyncio.Task[None] | None = None

    async def open(self, loop_ticked: Callable[[], float]) -> Heartbeat:
        """Clean up after a killed daemon and start beating; the heartbeat the children watch. It beats while
        ``loop_ticked()`` (when the event loop last ran, monotonic s: the loop watch's ticker) is within
        :data:`LOOP_HANG`."""
        # A daemon that was killed may have left children that still drive the
        # robot (they stop on their own within the heartbeat timeout) and
        # shared memory: clean up before starting our own.
        self.leftovers = await asyncio.to_thread(self.records.reap)
        self.exit_notes = await asyncio.to_thread(exit_notes, self.records.dir)
        for note in self.exit_notes:
            log.warning("previous_daemon_child_orphaned", role=note["role"], reason=note["reason"])
        self.heartbeat = Heartbeat(f"celld-{uuid.uuid4().hex[:8]}-heartbeat")
        self._beater = BeatThread(self.heartbeat, lambda: time.monotonic() - loop_ticked() < LOOP_HANG, HEARTBEAT_PERIOD)
        self._beater.start()
        return self.heartbeat

    def read_dashboard(self, on_reading: Callable[[], None]) -> None:
        """Read the dashboard every :data:`DASHBOARD_PERIOD` s, calling ``on_reading`` after each reading."""
        self._reading = asyncio.get_running_loop().create_task(self._read(on_reading), name="celld-dashboard")

    async def close(self) -> None:
        if self._reading is not None:
            self._reading.cancel()
            await asyncio.gather(self._reading, return_exceptions=True)
            self._reading = None
            await self.dashboard.close()
        if self._beater is not None:
            await asyncio.to_thread(self._beater.stop)
            self._beater = None
        if self.heartbeat is not None:
            self.heartbeat.close()
            self.heartbeat = None

    async def _read(self, on_reading: Callable[[], None]) -> None:
        while True:
            await self.dashboard.read()
            on_reading()
            await asyncio.sleep(DASHBOARD_PERIOD)


class CellDevices:
    """The devices of one cell: robot 1, robot 2 when the cell has one, the tactile sensor, the scanner, and
    the life cycle that keeps them.

    Parameters
    ----------
    config : Config
    factories : DeviceFactories
        How to open the scanner and the SRM camera (:func:`real_devices`
        unless the simulated cell hands its own). With ``tactile.kind =
        "none"`` the cell runs without a tactile process, and weld jobs are
        refused.
    take_over : bool
        Take the robots over even when another program runs on one at start
        (``celld run --take-over``). Without it, a program a robot runs that
        the previous celld did not leave (no child of it was reaped, none left
        a note) keeps that robot: :attr:`held` (robot 1) or :attr:`held2`
        (robot 2) says which, its motion process is not started, every moving
        job is refused (robot 1 moves only beside robot 2 where it stands),
        and the motion process is started once the program has stopped.
    """

    def __init__(self, config: Config, factories: DeviceFactories | None = None, take_over: bool = False) -> None:
        factories = factories or real_devices()
        self.config = config
        self.robot = Arm(config)
        # The second robot, when the cell has one ([robot2]): calibrate jobs with robot2 set drive it.
        self.robot2: Arm | None = Arm(robot2_config(config), robot=2) if config.robot2 is not None else None
        self.tactile = Tactile(config, factories.camera)
        self.scanner = CellScanner(config, factories.scanner)
        self.life = Lifecycle(config)
        self._recordings: list[Any] = []
        self._condition = ""
        self._dashboard_reachable = False  # whether the last dashboard reading reached the robot
        self.take_over = take_over
        self.held = ""  # the program of another controller robot 1 runs, not taken over ("" when none)
        self.held2 = ""  # the same for robot 2
        # Robot 2's dashboard, read at start and, while robot 2 is held, beside robot 1's readings.
        self._dashboard2 = Dashboard(self.robot2.config.robot.host) if self.robot2 is not None else None
        self._reading2: asyncio.Task[None] | None = None
        self._heartbeat = ""
        self._opening: asyncio.Task[None] | None = None

    # -- the second robot as an obstacle ------------------------------------------------

    def robot2_obstacles(self, q2: np.ndarray) -> tuple[CellObject, ...]:
        """Robot 2's arm at its joints ``q2`` as obstacles of robot 1 (placed by its drawn base)."""
        if self.robot2 is None or self.config.robot2 is None:
            return ()
        return arm_obstacles(self.robot2.planner.bare, q2, se3.from_ur_pose(self.config.robot2.base_pose), "robot2")

    def robot1_obstacles(self, q1: np.ndarray) -> tuple[CellObject, ...]:
        """Robot 1's arm and tool at its joints ``q1`` as obstacles of robot 2 (none in a one-robot cell)."""
        if self.config.robot2 is None:
            return ()
        return arm_obstacles(self.robot.planner.with_tool, q1, se3.invert(se3.from_ur_pose(self.config.robot2.base_pose)), "robot1")

    @contextlib.asynccontextmanager
    async def beside_robot2(self) -> AsyncIterator[None]:
        """Within the block, robot 1's moves are checked against robot 2's arm where it stands now (nothing
        moves robot 2 meanwhile); in a one-robot cell, nothing changes.

        Raises
        ------
        DeviceError
            Robot 2's joints cannot be read (its link is down): robot 1 does not move beside an arm whose
            place is unknown.
        """
        if self.robot2 is None:
            yield
            return
        try:
            q2 = await self.robot2.current_q()
        except DeviceError as exc:
            raise DeviceError(f"robot 2's place is unknown ({exc}); robot 1 does not move beside it") from exc
        with self.robot.avoiding(self.robot2_obstacles(q2)):
            yield

    # -- life cycle ----------------------------------------------------------------

    async def open(self, loop_ticked: Callable[[], float]) -> None:
        """The heartbeat (beating while ``loop_ticked()``, when the event loop last ran, is recent), then side
        by side the tactile process, each robot's motion process and the scanner (each a process of its own
        to start: one after the other they held the daemon's start up by seconds), then the dashboard
        reading."""
        cfg = self.config
        heartbeat = await self.life.open(loop_ticked)
        self._heartbeat = heartbeat.name
        self.tactile.prepare(heartbeat.name, self.life.records)
        await asyncio.gather(self.tactile.open(), self._open_robots(heartbeat.name), self.scanner.open())
        self.life.read_dashboard(self._on_dashboard)
        log.info(
            "devices_open",
            robot=cfg.robot.host,
            scanner=f"{cfg.scanner.kind}/{cfg.scanner.model}",
            tactile=cfg.tactile.kind if self.tactile.process is not None else "none",
        )

    async def _take(self, running: str, ours: bool, dashboard: Dashboard, robot: int) -> bool:
        """Whether celld takes robot ``robot``, on which ``running`` runs ("" for nothing) at start: not from
        another program unless told to (``take_over``) or it is the previous celld's (``ours``); a program it
        takes the robot from is stopped first."""
        if not running:
            return True
        if not (self.take_over or ours):
            log.error("robot_program_foreign_kept", robot=robot, program=running, remedy=HELD_REMEDY)
            return False
        log.warning("robot_program_taken_over", robot=robot, program=running, take_over=self.take_over)
        try:
            await dashboard.stop_program()
        except CelldError as exc:  # the motion process's connect says the rest
            log.error("robot_program_not_stopped", robot=robot, program=running, error=str(exc))
        return True

    async def _open_robots(self, heartbeat: str) -> None:
        """Each robot's motion process, unless another program runs on it (:meth:`_take`)."""
        ours = bool(self.life.leftovers or self.life.exit_notes)  # the previous celld's own program
        running = foreign_program(await self.life.dashboard.read())
        if await self._take(running, ours, self.life.dashboard, 1):
            await self._open_robot()
        else:
            self.held = running
        if self.robot2 is not None and self._dashboard2 is not None:
            running2 = foreign_program(await self._dashboard2.read())
            if await self._take(running2, ours, self._dashboard2, 2):
                await self.robot2.open_motion(heartbeat, self.life.records)
            else:
                self.held2 = running2

    async def _open_robot(self) -> None:
        motion = await self.robot.open_motion(self._heartbeat, self.life.records, SERVO_LAWS, self.tactile.slot_name)
        motion.add_listener(self._on_state_batch)

    async def close(self) -> None:
        if self._opening is not None:
            await asyncio.gather(self._opening, return_exceptions=True)
        self.held2 = ""  # no more readings of robot 2's dashboard from here
        if self._reading2 is not None:
            await asyncio.gather(self._reading2, return_exceptions=True)
        if self._dashboard2 is not None:
            await self._dashboard2.close()
        if self.robot2 is not None:
            await self.robot2.close_motion()
        await self.robot.close_motion()
        await asyncio.gather(self.scanner.close(), self.tactile.close())
        await self.life.close()

    # -- robots ----------------------------------------------------------------------

    async def stop_robot(self) -> None:
        """Jerk-limited stop of every robot of the cell; returns once they hold still (or their links are gone)."""
        others = [] if self.robot2 is None else [self.robot2.stop_robot()]
        await asyncio.gather(self.robot.stop_robot(), *others)

    def link_state(self) -> str:
        """Robot 1's link: ``up``, ``down`` or ``unknown``."""
        return self.robot.link_state()

    def unready(self, kind: str, dry_run: bool = False) -> str:
        """Why a job of ``kind`` cannot run now for want of a device, "" when it can: robot 1's link (with the
        robot's condition and what clears it), the scanner, the finger's camera (a weld that touches)."""
        if kind == "health":
            return ""
        checks = [self._robot_wait]
        if kind in _NEEDS_SCANNER:
            checks.append(self._scanner_wait)
        if kind == "weld" and not dry_run:
            checks.append(self._camera_wait)
        return next((why for why in (check() for check in checks) if why), "")

    def waiting(self) -> list[str]:
        """What the cell waits for (robot link, scanner, finger camera), [] when nothing: the status says it."""
        return [why for why in (self._robot_wait(), self._scanner_wait(), self._camera_wait()) if why]

    def _robot_wait(self) -> str:
        if self.held:
            return f"robot held by another program: waiting ({self.held} runs on it; {HELD_REMEDY})"
        if self.held2:
            # Robot 1 moves only beside robot 2 where it stands, and nobody knows where that is.
            return f"robot 2 held by another program: waiting ({self.held2} runs on it; {HELD_REMEDY})"
        if self.robot.link_state() == "up":
            return ""
        cond = self.robot_condition()
        why = cond.reason or "the motion process has not read the robot yet"
        return f"robot link down: waiting ({why}" + (f"; {cond.remedy})" if cond.remedy else ")")

    def _scanner_wait(self) -> str:
        return "" if self.scanner.device is not None else f"scanner not open: waiting ({self.scanner.error or 'not opened yet'})"

    def _camera_wait(self) -> str:
        return self.tactile.wait_reason()

    def _on_dashboard(self) -> None:
        reading = self.life.dashboard.last
        reachable = reading is not None and reading.reachable
        motion = self.robot.motion
        if reachable and not self._dashboard_reachable and motion is not None and not self.held:
            # The robot answers again (powered on, cable back): its link is tried now, not after the motion
            # supervisor's back-off, which by then may be 10 s (a cell that booted before its robot waited it out).
            motion.supervisor.retry_now()
        self._dashboard_reachable = reachable
        if self.held and self.life.dashboard.last is not None and self.life.dashboard.last.reachable:
            if not foreign_program(self.life.dashboard.last):
                log.info("robot_program_foreign_stopped", program=self.held)
                self.held = ""
                self._opening = asyncio.get_running_loop().create_task(self._open_robot(), name="celld-open-robot")
        if self.held2 and (self._reading2 is None or self._reading2.done()):
            self._reading2 = asyncio.get_running_loop().create_task(self._check_robot2(), name="celld-robot2-dashboard")
        cond = self.robot_condition()
        if cond.state != self._condition:
            (log.info if cond.ready else log.warning)("robot condition", state=cond.state, reason=cond.reason)
            self._condition = cond.state

    async def _check_robot2(self) -> None:
        """While robot 2 is held: read its dashboard, and take the robot once the other program has stopped."""
        if self._dashboard2 is None or self.robot2 is None:
            return
        reading = await self._dashboard2.read()
        if not self.held2 or not reading.reachable or foreign_program(reading):
            return
        log.info("robot_program_foreign_stopped", robot=2, program=self.held2)
        self.held2 = ""
        await self.robot2.open_motion(self._heartbeat, self.life.records)

    def robot_condition(self) -> RobotCondition:
        """Whether robot 1 can move, and if not why and what clears it (:mod:`celld.robot.dashboard`)."""
        motion = self.robot.motion
        cause = motion.supervisor.outage_cause() if motion is not None else ""
        return robot_condition(self.robot.link_state(), self.life.dashboard.last, cause)

    def robot_report(self) -> dict[str, Any]:
        """The robot's condition and the dashboard's last reading, for the status reply."""
        r = self.life.dashboard.last
        out: dict[str, Any] = self.robot_condition().as_dict()
        out["link"] = self.robot.link_state()
        out["mode"] = r.robot_mode if r is not None and r.reachable else None
        out["safety"] = r.safety if r is not None and r.reachable else None
        out["dashboard"] = "reachable" if r is not None and r.reachable else (r.error if r is not None else "not read yet")
        if self.robot2 is not None:
            out["robot2_link"] = self.robot2.link_state()
            out["robot2_held"] = self.held2 or None
        return out

    async def robot_action(self, action: str) -> dict[str, Any]:
        """Send an operator's recovery command (:data:`~celld.robot.dashboard.ACTIONS`) through the dashboard.

        The caller refuses it while a job runs. After it, the motion supervisor
        reconnects at once instead of waiting out its back-off.

        Raises
        ------
        InputError
            Unknown action.
        RobotError
            The controller refused it, with its reason.
        """
        if action not in ACTIONS:
            raise InputError(f"robot action: expected one of {', '.join(ACTIONS)}, got {action!r}")
        dashboard = self.life.dashboard
        reply = await dashboard.act(action)
        if self.robot.motion is not None:
            self.robot.motion.supervisor.retry_now()
        await dashboard.read()
        return {"action": action, "reply": reply, "robot": self.robot_report()}

    def interlock_report(self) -> dict[str, Any]:
        """What celld can say about the arc interlock (standard outputs low when the program stops; :data:`INTERLOCK_SCHEMA`).

        The I/O setting itself cannot be read over RTDE or the dashboard. What
        can be seen: each motion process, when it starts, checks whether the
        arc output was left on by the one before it (killed, or its link lost),
        which only happens without the setting.
        """
        motion = self.robot.motion
        missing = [e for e in (motion.loop_events if motion is not None else ()) if e.startswith(INTERLOCK_MISSING)]
        return {
            "verified": False,
            "missing_seen": bool(missing),
            "detail": missing[-1] if missing else "",
            "note": (
                "the robot's I/O setting 'standard outputs low when the program stops' cannot be read over RTDE or the "
                "dashboard; set it on the teach pendant (README). celld checks at every motion process start that the "
                "arc output was not left on, which would show the setting missing"
            ),
        }

    def supervised(self, max_age: float = 1.0) -> bool:
        """Robot 1's motion process is supervised: its supervisor runs and made progress within ``max_age`` s.

        True through link losses, protective stops and restarts (the
        supervisor keeps trying); False when the supervision itself has
        stopped or hangs.
        """
        motion = self.robot.motion
        if motion is None:
            return bool(self.held)  # nothing to supervise while another program keeps the robot
        sup = motion.supervisor
        return sup.running() and time.monotonic() - sup.last_tick < max_age

    def heartbeat_age(self) -> float | None:
        motion = self.robot.motion
        return None if motion is None else motion.heartbeat_age()

    def robot_state_message(self) -> dict[str, Any] | None:
        motion = self.robot.motion
        if motion is None:
            return None
        rec = motion.last_record()
        if rec is None:
            return {"t_ns": 0, "link": "down"}
        return {
            "t_ns": max(0, int(rec["t_ns"])),
            "link": self.robot.link_state(),
            "q": np.asarray(rec["q"]).tolist(),
            "qd": np.asarray(rec["qd"]).tolist(),
            "tcp_pose": np.asarray(rec["tcp_pose"]).tolist(),
            "tcp_speed": np.asarray(rec["tcp_speed"]).tolist(),
        }

    # -- recordings -----------------------------------------------------------------

    def attach_recording(self, recording: JobRecording) -> None:
        """Feed robot 1's motion state batches to ``recording`` until it closes."""
        self._recordings.append(recording)

    def _on_state_batch(self, batch: np.ndarray) -> None:
        """Hand robot 1's state to each open recording's feed thread (the event loop does not wait for rerun)."""
        live = []
        for rec in self._recordings:
            if rec.closed:
                continue
            rec.feed_state_batch(batch)
            live.append(rec)
        self._recordings = live
