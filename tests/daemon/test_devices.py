"""The cell's devices: the tactile process's supervision (the motion process's has its own tests), an arm's moves after a
stale state, robot 1 beside a robot 2 whose place is unknown."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import numpy as np
import pytest

from celld.config import Config
from celld.daemon import devices as devices_mod
from celld.daemon.arm import STALE_RETRIES, Arm
from celld.daemon.devices import CellDevices, Tactile
from celld.errors import DeviceError, LinkLost, StaleState
from celld.supervision import Backoff


class FakeTactile:
    def __init__(self, fail: bool = False) -> None:
        self.up = True
        self.ready = True
        self.fail = fail
        self.restarts = 0
        self.exitcode: int | None = None

    def alive(self) -> bool:
        return self.up

    def running(self) -> bool:
        return self.up and self.ready

    def restart(self) -> int | None:
        self.restarts += 1
        if self.fail:
            raise DeviceError("the tactile process exited at start (exit code 1)")
        self.up = True
        return self.exitcode


def test_the_cell_waits_for_its_finger_camera_until_its_process_reads_it() -> None:
    srm = Tactile(Config(), None)
    srm.process = FakeTactile()  # type: ignore[assignment]
    assert srm.wait_reason() == ""
    # Restarted, alive but not yet reading the camera (it may still fail at open): a weld must not count on it.
    srm.process.ready = False
    assert srm.wait_reason() == "finger camera not running: waiting (its process is starting)"
    srm.process.up = False
    assert srm.wait_reason() == "finger camera not running: waiting (its process ended; restarting it)"
    srm.error = "the tactile process exited at start (exit code 1)"
    assert srm.wait_reason().endswith("(the tactile process exited at start (exit code 1))")


def test_a_dead_tactile_process_is_restarted_with_a_delay_between_attempts(monkeypatch) -> None:
    async def scenario() -> None:
        srm = Tactile(Config(), None)
        srm.process = FakeTactile()  # type: ignore[assignment]
        await srm.supervise()
        assert srm.process.restarts == 0  # alive: left alone
        srm.process.up, srm.process.exitcode = False, -9
        await srm.supervise()
        assert srm.process.restarts == 1 and srm.process.alive()

        failing = FakeTactile(fail=True)
        failing.up = False
        srm.process = failing  # type: ignore[assignment]
        monkeypatch.setattr(devices_mod, "TACTILE_BACKOFF", Backoff(delays=(3600.0,)))
        await srm.supervise()  # restarted just before: waits
        assert failing.restarts == 0
        monkeypatch.setattr(devices_mod, "TACTILE_BACKOFF", Backoff(delays=(0.0,)))
        await srm.supervise()
        await srm.supervise()  # a failed restart is logged and tried again, never raised
        assert failing.restarts == 2 and not failing.alive()
        assert srm._failures == 2 and "exited at start" in srm.error  # the wait doubles each time
        failing.fail = False
        await srm.supervise()
        assert failing.alive() and srm.error == "" and srm._failures == 0

        srm.process = None
        await srm.supervise()  # a cell without a finger camera: nothing to do

    asyncio.run(asyncio.wait_for(scenario(), 10))


class FakeMotion:
    """A motion handle whose first ``stale`` moves end on a stale robot state."""

    def __init__(self, stale: int, ready: bool = True) -> None:
        self.stale, self.ready = stale, ready
        self.posted: list[object] = []
        self.waits: list[str] = []

    def state(self):
        from celld.motion.types import RobotState

        return RobotState(0, np.zeros(6), np.zeros(6), np.eye(4), np.zeros(6))

    async def move_to(self, T, speed_scale: float = 1.0):
        self.posted.append(T)
        if self.stale:
            self.stale -= 1
            raise StaleState("robot state is 12 cycles old (limit 10): stopped")
        return self.state()

    async def wait_idle(self, timeout: float) -> None:
        self.waits.append("idle")

    async def wait_ready(self, timeout: float) -> bool:
        self.waits.append("ready")
        return self.ready


class FakePlanner:
    def __init__(self) -> None:
        self.checked = 0

    def plan_move(self, q, T, speed_scale, tool) -> SimpleNamespace:
        self.checked += 1
        return SimpleNamespace(speed_scale=speed_scale, joint_speed=0.0)


def test_a_move_stopped_on_a_stale_state_is_checked_and_posted_again_a_few_times() -> None:
    async def scenario() -> None:
        dev = Arm(Config())
        dev.planner = FakePlanner()  # type: ignore[assignment]
        # Stale once: after rest and fresh state, checked again from there and posted again.
        dev.motion = FakeMotion(stale=1)
        await dev.move_to(np.eye(4))
        assert len(dev.motion.posted) == 2 and dev.motion.waits == ["idle", "ready"] and dev.planner.checked == 2
        # Stale as often as it is retried: the last post arrives.
        dev.motion = FakeMotion(stale=STALE_RETRIES)
        await dev.move_to(np.eye(4))
        assert len(dev.motion.posted) == STALE_RETRIES + 1
        # Stale once more than that: the job gets the error, after the last retry.
        dev.motion = FakeMotion(stale=STALE_RETRIES + 1)
        with pytest.raises(StaleState, match="cycles old"):
            await dev.move_to(np.eye(4))
        assert len(dev.motion.posted) == STALE_RETRIES + 1
        # State that does not come back fresh: no second post.
        dev.motion = FakeMotion(stale=1, ready=False)
        with pytest.raises(StaleState):
            await dev.move_to(np.eye(4))
        assert len(dev.motion.posted) == 1
        # Any other failure is never retried.
        dev.motion = FakeMotion(stale=0)

        async def lost(T, speed_scale: float = 1.0):
            dev.motion.posted.append(T)
            raise LinkLost("the robot link is restarting")

        dev.motion.move_to = lost
        with pytest.raises(LinkLost):
            await dev.move_to(np.eye(4))
        assert len(dev.motion.posted) == 1 and dev.motion.waits == []

    asyncio.run(asyncio.wait_for(scenario(), 10))


def test_a_stale_state_is_its_own_link_error_and_a_lost_link_is_not_one() -> None:
    from celld.motion.handle import error_for
    from celld.motion.types import ControlStatus

    stale = error_for(ControlStatus.STALE_STATE, "")
    assert isinstance(stale, StaleState) and isinstance(stale, LinkLost) and "STALE_STATE" in str(stale)
    lost = error_for(ControlStatus.LINK_LOST, "rtde dropped")
    assert isinstance(lost, LinkLost) and not isinstance(lost, StaleState)


def test_robot_1_does_not_move_beside_a_second_robot_whose_place_is_unknown() -> None:
    from pathlib import Path

    from celld.config import load

    async def scenario() -> None:
        one = CellDevices(Config())
        planner = one.robot.planner
        async with one.beside_robot2():  # a one-robot cell: nothing to avoid
            assert one.robot.planner is planner
        two = CellDevices(load(Path(__file__).resolve().parents[2] / "configs" / "sim-cell-two-robots.toml"))
        planner = two.robot.planner
        with pytest.raises(DeviceError, match="robot 2's place is unknown .*the robot is not connected"):
            async with two.beside_robot2():
                pytest.fail("robot 1 would move beside robot 2 with its link down")
        assert two.robot.planner is planner

    asyncio.run(scenario())


def test_a_move_of_robot_2_needs_a_second_robot_and_robot_1_where_it_stands(tmp_path) -> None:
    from pathlib import Path

    from celld.bus.requests import MoveJob
    from celld.config import load
    from celld.daemon.jobs import JobContext
    from celld.daemon.runners import build_runners
    from celld.errors import JobError

    job = MoveJob(space="joint", target=(0.0, -1.57, 1.57, -1.57, -1.57, 0.0), robot=2)

    def context() -> JobContext:
        return JobContext("j", job, tmp_path, lambda *a, **k: None)

    async def scenario() -> None:
        one = CellDevices(Config())
        with pytest.raises(JobError) as err:
            await build_runners(one.config, one)["move"](context())
        assert err.value.field == "$.robot" and "no second robot" in err.value.reason
        two = CellDevices(load(Path(__file__).resolve().parents[2] / "configs" / "sim-cell-two-robots.toml"))
        planner = two.robot2.planner
        with pytest.raises(DeviceError, match="robot 1's place is unknown .*the robot is not connected"):
            await build_runners(two.config, two)["move"](context())
        assert two.robot2.planner is planner

    asyncio.run(scenario())


def test_a_robot_that_answers_again_is_tried_at_once_not_after_the_back_off() -> None:
    # A cell that booted before its robot: each failed connect lengthened the motion supervisor's back-off
    # (to 10 s), and the cell waited it out after the robot came up. The dashboard's answer cuts it short.
    from celld.robot.dashboard import DashboardReading

    class Supervisor:
        retries = 0

        def retry_now(self) -> None:
            self.retries += 1

        def outage_cause(self) -> str:
            return ""

    class Motion:
        supervisor = Supervisor()

        def link_running(self) -> bool:
            return False

    def reading(reachable: bool) -> DashboardReading:
        return DashboardReading(reachable, "RUNNING" if reachable else "", "NORMAL" if reachable else "", "", "", 0.0)

    dev = CellDevices(Config())
    dev.robot.motion = Motion()  # type: ignore[assignment]
    for reachable in (False, False, True, True, False, True):
        dev.life.dashboard.last = reading(reachable)
        dev._on_dashboard()
    assert Motion.supervisor.retries == 2  # each time it answered after it had not, and only then
