"""The cell's devices as the daemon sees them: robot, scanner, tactile sensor.

:class:`CellDevices` opens, in order, the motion process (through
:class:`~celld.motion.handle.MotionHandle`, which owns the robot link and
restarts its process), the tactile camera process when the cell has one,
and the scanner. It closes them in the reverse order, robot last, after a
jerk-limited stop.

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
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from celld import se3
from celld.config import Config
from celld.daemon.planning import MotionPlanner, arm_obstacles
from celld.errors import CelldError, ConfigError, DeviceError, InputError, StaleState
from celld.log import get_logger
from celld.motion.algorithm2 import NAME as ALGORITHM2
from celld.motion.handle import MotionHandle
from celld.motion.loop import INTERLOCK_MISSING
from celld.motion.types import RobotState
from celld.robot.cellmodel import CellObject
from celld.robot.dashboard import ACTIONS, Dashboard, RobotCondition, robot_condition
from celld.scanner.base import OrganizedCloud, Scanner
from celld.scanner.factory import open_scanner
from celld.supervision import Backoff, ChildRecords, Heartbeat
from celld.tactile.camera import FrameSourceFactory, opencv_camera
from celld.tactile.process import CAMERA_REALTIME, TactileProcess
from celld.tactile.sample import TactileSample

log = get_logger(__name__)

# Servo laws the motion process may be asked to run, by name.
SERVO_LAWS = {ALGORITHM2: "celld.motion.algorithm2:make_algorithm2"}
# Longest a job waits for the robot's first state, s.
STATE_WAIT = 5.0
# Longest a stop may take before the daemon gives up waiting, s.
STOP_TIMEOUT = 5.0
# A point-to-point move the motion loop stopped on a stale robot state (the
# loop starved of state for a few cycles while the link stayed up; the stop
# was jerk-limited) is checked again from where the arm came to rest and
# posted again, this many times, before the job fails. On a loaded two-core
# cell PC two such stops have come within 2 s (a tool calibration's
# detections running beside the move).
STALE_RETRIES = 3
# How often the daemon's heartbeat beats, s (its children wait motion.parent_timeout for it).
HEARTBEAT_PERIOD = 0.02
# Least time between two restarts of a dying tactile process, s: it doubles
# after each failed restart, up to a minute.
TACTILE_BACKOFF = Backoff(delays=(2.0, 4.0, 8.0, 16.0, 32.0, 60.0))
# The dashboard server is read this often, s.
DASHBOARD_PERIOD = 0.5


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


def robot2_config(config: Config) -> Config:
    """The cell as the second robot sees it (``[robot2]``): its link, its calibration's verification pose and
    flange, the cell model moved into its base frame by its drawn place, no tool on its flange.

    Raises
    ------
    ConfigError
        The config has no ``[robot2]``.
    """
    r2 = config.robot2
    if r2 is None:
        raise ConfigError(config.source, "robot2", "the cell has no second robot")
    T_base2_base1 = se3.invert(se3.from_ur_pose(r2.base_pose))
    cal = replace(config.calibration, verification_pose=r2.verification_pose, flange=r2.flange or config.calibration.flange)
    return replace(
        config, robot=r2.robot, calibration=cal, cell_model=config.cell_model.seen_from(T_base2_base1).without_tool(), robot2=None
    )


class Arm:
    """One robot as the daemon drives it: its motion process and every move checked first.

    ``config`` is the robot's view of the cell: its ``[robot]`` section and
    the cell model in its base frame (:func:`robot2_config` makes the second
    robot's). :class:`CellDevices` is robot 1's; a cell with ``[robot2]``
    has one more (:attr:`CellDevices.robot2`), opened by :meth:`open_motion`.
    """

    def __init__(self, config: Config) -> None:
        self.config = config
        self.motion: MotionHandle | None = None
        self.planner = MotionPlanner(config)

    @contextlib.contextmanager
    def avoiding(self, objects: Sequence[CellObject]) -> Iterator[None]:
        """Within the block, every move and plan of this arm is checked against ``objects`` too (another
        robot's arm where it waits: :func:`~celld.daemon.planning.arm_obstacles`); a block inside it puts
        its own objects in their place."""
        planner = self.planner
        self.planner = planner.with_objects(objects)
        try:
            yield
        finally:
            self.planner = planner

    async def open_motion(
        self, heartbeat: str, records: ChildRecords, servo_laws: dict[str, str] | None = None, tactile_slot: str | None = None
    ) -> MotionHandle:
        """Start its motion process, watching the daemon's ``heartbeat``; the supervisor keeps (re)connecting
        (see :meth:`wait_robot`). Without ``servo_laws`` and ``tactile_slot`` it only moves and holds."""
        cfg = self.config
        self.motion = await MotionHandle.open(
            cfg,
            servo_laws=servo_laws,
            tactile_slot=tactile_slot,
            link_timeout=cfg.motion.link_timeout,
            watchdog_hz=cfg.motion.rtde_watchdog_hz,
            wait=False,
            heartbeat=heartbeat,
            records=records,
        )
        return self.motion

    async def close_motion(self) -> None:
        """A jerk-limited stop, then the end of its motion process."""
        if self.motion is None:
            return
        try:
            await self.stop_robot()
        except CelldError as exc:
            log.error("stop before close failed", robot=self.config.robot.host, error=str(exc))
        await self.motion.close()
        self.motion = None

    async def wait_robot(self, timeout: float) -> bool:
        """Wait until the motion loop runs and has read the robot; False on timeout."""
        return await self.require_motion().wait_ready(timeout)

    async def move_to(self, T_base_tcp: np.ndarray, speed_scale: float = 1.0, *, tool: bool = True) -> RobotState:
        """A jerk-limited straight move of the TCP, checked against the cell first (:class:`MotionPlanner`).

        Raises
        ------
        PathRefused
            The move would hit the cell or cannot be reached; the robot did not move.
        """
        motion = self.require_motion()

        async def move() -> RobotState:
            q = await self.current_q()
            await asyncio.to_thread(self.planner.check_move, q, T_base_tcp, tool)
            return await motion.move_to(T_base_tcp, speed_scale=speed_scale)

        return await self._after_stale(move, "move")

    async def move_joints(self, q_goal: np.ndarray, speed_scale: float = 1.0, *, tool: bool = True) -> RobotState:
        """A jerk-limited joint move, checked against the cell and the workspace box first, and slowed so the
        TCP keeps the Cartesian limits (:meth:`MotionPlanner.plan_joint_move`).

        Raises
        ------
        PathRefused
            The move would hit the cell, leave the workspace or cross a joint limit; the robot did not move.
        """
        motion = self.require_motion()

        async def move() -> RobotState:
            q = await self.current_q()
            plan = await asyncio.to_thread(self.planner.plan_joint_move, q, q_goal, speed_scale, tool)
            if plan.speed_scale < speed_scale:
                log.info(
                    "joint move slowed for the TCP's limits",
                    asked=speed_scale,
                    scale=round(plan.speed_scale, 4),
                    tcp_speed=round(plan.tcp_speed, 4),
                )
            return await motion.move_joints(q_goal, speed_scale=plan.speed_scale)

        return await self._after_stale(move, "joint move")

    async def _after_stale(self, move: Callable[[], Awaitable[RobotState]], what: str) -> RobotState:
        """Run ``move``; after a stop on stale robot state, wait for rest and fresh state and run it again
        (:data:`STALE_RETRIES` times). Any other failure, or a link that does not come back, is raised."""
        motion = self.require_motion()
        retries = 0
        while True:
            try:
                return await move()
            except StaleState as exc:
                if retries >= STALE_RETRIES:
                    raise
                retries += 1
                log.warning(
                    "a move stopped on a stale robot state; checking it again from where the arm rests",
                    move=what,
                    reason=str(exc),
                    retry=f"{retries} of {STALE_RETRIES}",
                )
                await motion.wait_idle(STOP_TIMEOUT)
                if not await motion.wait_ready(STATE_WAIT):
                    raise

    async def current_q(self, timeout: float = STATE_WAIT) -> np.ndarray:
        """The robot's joints now, waiting up to ``timeout`` s for the first state; DeviceError without one."""
        motion = self.require_motion()
        state = motion.state()
        if state is None and await motion.wait_ready(timeout):
            state = motion.state()
        if state is None:
            raise DeviceError(f"no robot state within {timeout:g} s: the robot link is not up")
        return np.asarray(state.q, dtype=np.float64)

    def require_motion(self) -> MotionHandle:
        if self.motion is None:
            raise DeviceError("the robot is not connected")
        return self.motion

    async def stop_robot(self) -> None:
        """Jerk-limited stop; returns once the robot holds still (or the link is gone)."""
        if self.motion is None:
            return
        self.motion.stop()
        try:
            await self.motion.wait_idle(STOP_TIMEOUT)
        except CelldError as exc:
            log.warning("robot not confirmed at rest after a stop", error=str(exc))

    def link_state(self) -> str:
        if self.motion is None:
            return "unknown"
        return "up" if self.motion.link_running() else "down"


class CellDevices(Arm):
    """Robot, tactile sensor and scanner of one cell.

    Parameters
    ----------
    config : Config
    factories : DeviceFactories
        How to open the scanner and the SRM camera (:func:`real_devices`
        unless the simulated cell hands its own). With ``tactile.kind =
        "none"`` the cell runs without a tactile process, and weld jobs are
        refused.
    """

    def __init__(self, config: Config, factories: DeviceFactories | None = None) -> None:
        super().__init__(config)
        # The second robot, when the cell has one ([robot2]): calibrate jobs with robot2 set drive it.
        self.robot2: Arm | None = Arm(robot2_config(config)) if config.robot2 is not None else None
        self.tactile: TactileProcess | None = None
        self.scanner: Scanner | None = None
        self._factories = factories or real_devices()
        self._recordings: list[Any] = []
        self._tactile_restart_at = -math.inf
        self._tactile_failures = 0
        self.tactile_error = ""  # why the tactile process is not running, "" while it is
        self.heartbeat: Heartbeat | None = None
        self._beating: asyncio.Task[None] | None = None
        self.leftovers: list[str] = []  # what was cleaned up after a previous daemon
        self.dashboard = Dashboard(config.robot.host)
        self._reading: asyncio.Task[None] | None = None

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
        return arm_obstacles(self.planner.with_tool, q1, se3.invert(se3.from_ur_pose(self.config.robot2.base_pose)), "robot1")

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
        with self.avoiding(self.robot2_obstacles(q2)):
            yield

    # -- life cycle ----------------------------------------------------------------

    async def open(self) -> None:
        cfg = self.config
        # A daemon that was killed may have left children that still drive the
        # robot (they stop on their own within the heartbeat timeout) and
        # shared memory: clean up before starting our own.
        records = ChildRecords(Path(cfg.cell.state_dir) / "run")
        self.leftovers = await asyncio.to_thread(records.reap)
        self.heartbeat = Heartbeat(f"celld-{uuid.uuid4().hex[:8]}-heartbeat")
        self._beating = asyncio.get_running_loop().create_task(self._beat(self.heartbeat), name="celld-heartbeat")
        self.tactile = make_tactile(cfg, self._factories.camera, self.heartbeat.name, records)
        if self.tactile is not None:
            try:
                await asyncio.to_thread(self.tactile.start)
            except CelldError as exc:
                # The cell still calibrates and moves; welds are refused until
                # the supervision brings the camera back (supervise_tactile).
                self.tactile_error = str(exc)
                self._tactile_restart_at = time.monotonic()
                log.error("the tactile process did not start; retrying in the background", error=str(exc))
        tactile_slot = None if self.tactile is None else self.tactile.slot_name
        motion = await self.open_motion(self.heartbeat.name, records, SERVO_LAWS, tactile_slot)
        motion.add_listener(self._on_state_batch)
        if self.robot2 is not None:
            await self.robot2.open_motion(self.heartbeat.name, records)
        self._reading = asyncio.get_running_loop().create_task(self._read_dashboard(), name="celld-dashboard")
        self.scanner = await asyncio.to_thread(self._factories.scanner, cfg)
        log.info(
            "devices open",
            robot=cfg.robot.host,
            scanner=f"{cfg.scanner.kind}/{cfg.scanner.model}",
            tactile=cfg.tactile.kind if self.tactile is not None else "none",
        )

    async def close(self) -> None:
        if self.robot2 is not None:
            await self.robot2.close_motion()
        await self.close_motion()
        if self.scanner is not None:
            await asyncio.to_thread(self.scanner.close)
            self.scanner = None
        if self.tactile is not None:
            await asyncio.to_thread(self.tactile.stop)
            self.tactile = None
        if self._reading is not None:
            self._reading.cancel()
            await asyncio.gather(self._reading, return_exceptions=True)
            self._reading = None
            await self.dashboard.close()
        if self._beating is not None:
            self._beating.cancel()
            await asyncio.gather(self._beating, return_exceptions=True)
            self._beating = None
        if self.heartbeat is not None:
            self.heartbeat.close()
            self.heartbeat = None

    @staticmethod
    async def _beat(heartbeat: Heartbeat) -> None:
        """The daemon's heartbeat for its children, from the event loop: a hung loop stops the robot (how late
        the loop runs is the daemon's loop watch's to log: :mod:`celld.daemon.loopwatch`)."""
        while True:
            heartbeat.beat()
            await asyncio.sleep(HEARTBEAT_PERIOD)

    # -- robot ----------------------------------------------------------------------

    async def stop_robot(self) -> None:
        """Jerk-limited stop of every robot of the cell; returns once they hold still (or their links are gone)."""
        others = [] if self.robot2 is None else [self.robot2.stop_robot()]
        await asyncio.gather(super().stop_robot(), *others)

    async def _read_dashboard(self) -> None:
        previous = ""
        while True:
            await self.dashboard.read()
            cond = self.robot_condition()
            if cond.state != previous:
                (log.info if cond.ready else log.warning)("robot condition", state=cond.state, reason=cond.reason)
                previous = cond.state
            await asyncio.sleep(DASHBOARD_PERIOD)

    def robot_condition(self) -> RobotCondition:
        """Whether the robot can move, and if not why and what clears it (:mod:`celld.robot.dashboard`)."""
        last = self.motion.supervisor.last_exit if self.motion is not None else None
        return robot_condition(self.link_state(), self.dashboard.last, last.reason if last is not None else "")

    def robot_report(self) -> dict[str, Any]:
        """The robot's condition and the dashboard's last reading, for the status reply."""
        r = self.dashboard.last
        out: dict[str, Any] = self.robot_condition().as_dict()
        out["link"] = self.link_state()
        out["mode"] = r.robot_mode if r is not None and r.reachable else None
        out["safety"] = r.safety if r is not None and r.reachable else None
        out["dashboard"] = "reachable" if r is not None and r.reachable else (r.error if r is not None else "not read yet")
        if self.robot2 is not None:
            out["robot2_link"] = self.robot2.link_state()
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
        reply = await self.dashboard.act(action)
        if self.motion is not None:
            self.motion.supervisor.retry_now()
        await self.dashboard.read()
        return {"action": action, "reply": reply, "robot": self.robot_report()}

    def interlock_report(self) -> dict[str, Any]:
        """What celld can say about the arc interlock (standard outputs low when the program stops).

        The I/O setting itself cannot be read over RTDE or the dashboard. What
        can be seen: each motion process, when it starts, checks whether the
        arc output was left on by the one before it (killed, or its link lost),
        which only happens without the setting.
        """
        missing = [e for e in (self.motion.loop_events if self.motion is not None else ()) if e.startswith(INTERLOCK_MISSING)]
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
        """The motion process is supervised: its supervisor runs and made progress within ``max_age`` s.

        True through link losses, protective stops and restarts (the
        supervisor keeps trying); False when the supervision itself has
        stopped or hangs.
        """
        if self.motion is None:
            return False
        sup = self.motion.supervisor
        return sup.running() and time.monotonic() - sup.last_tick < max_age

    def heartbeat_age(self) -> float | None:
        if self.motion is None:
            return None
        return self.motion.heartbeat_age()

    def robot_state_message(self) -> dict[str, Any] | None:
        if self.motion is None:
            return None
        rec = self.motion.last_record()
        if rec is None:
            return {"t_ns": 0, "link": "down"}
        return {
            "t_ns": max(0, int(rec["t_ns"])),
            "link": self.link_state(),
            "q": np.asarray(rec["q"]).tolist(),
            "qd": np.asarray(rec["qd"]).tolist(),
            "tcp_pose": np.asarray(rec["tcp_pose"]).tolist(),
            "tcp_speed": np.asarray(rec["tcp_speed"]).tolist(),
        }

    # -- tactile --------------------------------------------------------------------

    async def supervise_tactile(self) -> None:
        """Restart the tactile process if it died, waiting between attempts as TACTILE_BACKOFF says.

        The daemon calls this periodically. While the process is down the
        motion loop sees no fresh sample, so a running servo stops on a stale
        sample with that reason; the restarted process tares before it
        reports deformation again.
        """
        tactile = self.tactile
        if tactile is None or tactile.alive():
            return
        now = time.monotonic()
        delay = TACTILE_BACKOFF.delay(self._tactile_failures + 1)
        if now - self._tactile_restart_at < delay:
            return
        self._tactile_restart_at = now
        log.error("the tactile process is not running; restarting it", exitcode=tactile.exitcode, restarts=tactile.restarts)
        try:
            await asyncio.to_thread(tactile.restart)
            self._tactile_failures = 0
            self.tactile_error = ""
            log.info("tactile process restarted", restarts=tactile.restarts)
        except CelldError as exc:
            self._tactile_failures += 1
            self.tactile_error = str(exc)
            log.error("tactile process restart failed", error=str(exc), next_try_s=TACTILE_BACKOFF.delay(self._tactile_failures + 1))

    def tactile_sample(self) -> TactileSample | None:
        return None if self.tactile is None else self.tactile.latest()

    def tactile_state_message(self) -> dict[str, Any] | None:
        sample = self.tactile_sample()
        if sample is None:
            return None
        msg: dict[str, Any] = {"t_ns": max(0, sample.stamp_ns), "valid": bool(sample.valid), "contact": int(sample.contact) > 0}
        if sample.valid:
            msg["delta"] = np.asarray(sample.delta_tool).tolist()
        return msg

    # -- scanner --------------------------------------------------------------------

    async def capture(self) -> OrganizedCloud:
        if self.scanner is None:
            raise DeviceError("the scanner is not open")
        return await asyncio.to_thread(self.scanner.capture)

    # -- recordings -----------------------------------------------------------------

    def attach_recording(self, recording: Any) -> None:
        """Feed motion state batches to ``recording`` until it closes."""
        self._recordings.append(recording)

    def _on_state_batch(self, batch: np.ndarray) -> None:
        live = []
        for rec in self._recordings:
            if rec.closed:
                continue
            try:
                rec.log_state_batch(batch)
            except CelldError as exc:
                log.warning("state batch not recorded", error=str(exc))
            live.append(rec)
        self._recordings = live
