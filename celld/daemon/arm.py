"""One robot as the daemon drives it: its motion process, its planner, and every move checked first.

An :class:`Arm` owns the :class:`~celld.motion.handle.MotionHandle` of one
robot (the motion process it starts and supervises) and the
:class:`~celld.daemon.planning.MotionPlanner` of its view of the cell: every
straight or joint move is checked against the cell model before it is posted,
and a move the loop stopped on a stale robot state is checked and posted again
from where the arm came to rest. A cell's robots are composed by
:class:`~celld.daemon.devices.CellDevices`.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, Iterator, Sequence
from dataclasses import replace

import numpy as np

from celld import se3
from celld.config import Config
from celld.daemon.planning import MotionPlanner
from celld.errors import CelldError, ConfigError, DeviceError, RobotError, StaleState
from celld.log import get_logger
from celld.motion.handle import MotionHandle
from celld.motion.types import RobotState
from celld.realtime import RealtimeOptions
from celld.robot import kinematics as kin
from celld.robot import primary
from celld.robot.cellmodel import CellObject
from celld.supervision import ChildRecords

log = get_logger(__name__)

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
# While the controller's kinematics are not read (its primary interface not up yet), read again after this, s.
KINEMATICS_RETRY = 2.0
# Longest a job's first read of the joints waits for the controller's kinematics once the link is up, s (they
# come within milliseconds of a connection; a job planned before them would plan on the published table).
KINEMATICS_WAIT = 3.0


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
    robot's). :class:`~celld.daemon.devices.CellDevices` has robot 1's
    (:attr:`~celld.daemon.devices.CellDevices.robot`) and, on a cell with
    ``[robot2]``, one more (:attr:`~celld.daemon.devices.CellDevices.robot2`).
    """

    def __init__(self, config: Config, robot: int = 1) -> None:
        self.config = config
        self.robot = robot  # the cell's robot 1 or 2
        self.motion: MotionHandle | None = None
        self.planner = MotionPlanner(config)
        # The table the controller computes with (celld.robot.primary), read once the arm is opened; until
        # then the planner computes with robot.model's published table, and jobs that need the controller's
        # own (:meth:`require_kinematics`) wait for it.
        self.kinematics: primary.ControllerKinematics | None = None
        self.kinematics_error = "not read yet"
        self._reading: asyncio.Task[None] | None = None

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

    @property
    def dh(self) -> kin.DH:
        """The DH table celld computes this arm with: its controller's once read, else the published one."""
        return self.planner.arm.dh

    def require_kinematics(self) -> primary.ControllerKinematics:
        """The controller's own kinematics, or DeviceError naming why they are not known."""
        if self.kinematics is None:
            raise DeviceError(f"robot {self.robot}: the controller's kinematics (primary interface) are unknown: {self.kinematics_error}")
        return self.kinematics

    async def _read_kinematics(self) -> None:
        """Read the controller's kinematics, again every :data:`KINEMATICS_RETRY` s until they are read and
        are of ``robot.model``; then the planner computes with them."""
        cfg = self.config.robot
        model = kin.model(cfg.model)
        while True:
            try:
                k = await asyncio.to_thread(primary.read_kinematics, cfg.host)
                offset = primary.check_model(k.dh, model)
            except RobotError as exc:
                if str(exc) != self.kinematics_error:
                    log.warning("controller_kinematics_not_read", robot=self.robot, error=str(exc), retry_s=KINEMATICS_RETRY)
                self.kinematics_error = str(exc)
                await asyncio.sleep(KINEMATICS_RETRY)
                continue
            break
        self.kinematics = k
        self.planner = MotionPlanner(self.config, k.dh)
        log.info(
            "controller_kinematics_read",
            robot=self.robot,
            id=k.id,
            calibration_status=k.calibration_status,
            published_table_off_mm=round(offset * 1e3, 2),
        )

    async def open_motion(
        self, heartbeat: str, records: ChildRecords, servo_laws: dict[str, str] | None = None, tactile_slot: str | None = None
    ) -> MotionHandle:
        """Start its motion process, watching the daemon's ``heartbeat``; the supervisor keeps (re)connecting
        (:meth:`link_state` says whether it is up). Without ``servo_laws`` and ``tactile_slot`` it only moves and holds."""
        cfg = self.config
        self.motion = await MotionHandle.open(
            cfg,
            servo_laws=servo_laws,
            tactile_slot=tactile_slot,
            # Robot 1's loop on the last CPU, robot 2's on the one before: two 500 Hz loops never queue
            # behind each other on one core.
            realtime=RealtimeOptions(cpu=-self.robot),
            link_timeout=cfg.motion.link_timeout,
            watchdog_hz=cfg.motion.rtde_watchdog_hz,
            wait=False,
            heartbeat=heartbeat,
            records=records,
            role="motion" if self.robot == 1 else f"motion{self.robot}",  # its name in the daemon's child records
        )
        if self._reading is None:
            self._reading = asyncio.create_task(self._read_kinematics(), name=f"kinematics{self.robot}")
        return self.motion

    async def close_motion(self) -> None:
        """A jerk-limited stop, then the end of its motion process."""
        if self._reading is not None:
            self._reading.cancel()
            await asyncio.gather(self._reading, return_exceptions=True)
            self._reading = None
        if self.motion is None:
            return
        try:
            await self.stop_robot()
        except CelldError as exc:
            log.error("stop_before_close_failed", robot=self.config.robot.host, error=str(exc))
        await self.motion.close()
        self.motion = None

    async def move_to(self, T_base_tcp: np.ndarray, speed_scale: float = 1.0, *, tool: bool = True) -> RobotState:
        """A jerk-limited straight move of the TCP, checked against the cell first and slowed so every joint
        keeps ``max_joint_speed`` (:meth:`MotionPlanner.plan_move`).

        Raises
        ------
        PathRefused
            The move would hit the cell or cannot be reached; the robot did not move.
        """
        motion = self.require_motion()

        async def move() -> RobotState:
            q = await self.current_q()
            plan = await asyncio.to_thread(self.planner.plan_move, q, T_base_tcp, speed_scale, tool)
            if plan.speed_scale < speed_scale:
                log.info(
                    "cartesian_move_slowed_by_joint_limits",
                    asked=speed_scale,
                    scale=round(plan.speed_scale, 4),
                    joint_speed=round(plan.joint_speed, 4),
                )
            return await motion.move_to(T_base_tcp, speed_scale=plan.speed_scale)

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
                    "joint_move_slowed_by_tcp_limits",
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
                    "move_stale_state_rechecked",
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
        if self._reading is not None and not self._reading.done():
            # The link is up: the table follows within milliseconds (the reading ends with it); what plans next
            # should plan on it.
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._reading), KINEMATICS_WAIT)
            state = motion.state() or state
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
        if not self.motion.process_running():
            # No loop runs to hold still (the robot's own watchdog ends its program): waiting for one held a
            # daemon stopping beside a lost robot up by 5 s per robot, twice.
            return
        try:
            await self.motion.wait_idle(STOP_TIMEOUT)
        except CelldError as exc:
            log.warning("robot_rest_not_confirmed_after_stop", error=str(exc))

    def link_state(self) -> str:
        if self.motion is None:
            return "unknown"
        return "up" if self.motion.link_running() else "down"
