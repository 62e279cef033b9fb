"""After a fault stops a weld, the arm moves only as weld.retract_after_fault says, never after a safety stop or
with the link down, and the job's reason says what it did."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import numpy as np
import pytest

from celld.config import parse
from celld.daemon.weld import CLEAR_SPEED, _after_fault
from celld.errors import CelldError, ConfigError, DeviceError, SafetyStop

Q_SCAN = np.array([0.1, -1.2, 1.3, -1.6, -1.5, 0.2])  # the joints the weld scanned from


class Arm:
    """Robot 1 as _after_fault sees it: its link, where it stands, the moves it is sent."""

    def __init__(self, link: bool) -> None:
        self.moves: list[tuple[str, np.ndarray, float]] = []
        here = np.eye(4)
        here[:3, 3] = [0.6, 0.0, 0.2]
        self.motion = SimpleNamespace(link_running=lambda: link, state=lambda: SimpleNamespace(T_base_tcp=here))

    def require_motion(self):
        return self.motion

    async def move_to(self, T: np.ndarray, speed_scale: float = 1.0) -> None:
        self.moves.append(("cartesian", T.copy(), speed_scale))

    async def move_joints(self, q: np.ndarray, speed_scale: float = 1.0) -> None:
        self.moves.append(("joint", np.array(q), speed_scale))


def after(mode: str, fault: CelldError, link: bool = True) -> tuple[list, str]:
    arm = Arm(link)
    stops = []

    async def stop_robot() -> None:
        stops.append(True)

    devices = SimpleNamespace(robot=arm, stop_robot=stop_robot)
    ctx = SimpleNamespace(job_id="j1", recording=None, progress=lambda *a, **k: None)
    wc = parse({"weld": {"retract_after_fault": mode, "retract_height_mm": 40}}).weld
    asyncio.run(_after_fault(ctx, devices, wc, fault, np.array([0.0, 0.0, 1.0]), Q_SCAN, 0.5))
    return arm.moves, "; ".join(fault.__notes__)


def test_clear_is_the_default_a_slow_move_straight_out_of_the_joint_and_said() -> None:
    assert parse({}).weld.retract_after_fault == "clear"
    moves, note = after("clear", DeviceError("the finger camera stopped"))
    assert len(moves) == 1
    ((space, T, speed),) = moves
    assert space == "cartesian"
    np.testing.assert_allclose(T[:3, 3], [0.6, 0.0, 0.24])  # 40 mm straight up, nothing else
    assert speed == CLEAR_SPEED
    assert note == "after the fault, the tool 40 mm straight up (weld.retract_after_fault = clear)"


def test_full_goes_on_to_the_scan_pose_and_none_leaves_the_arm() -> None:
    moves, note = after("full", DeviceError("the finger camera stopped"))
    # Up, then back to the joints the weld scanned from by a joint move (not a straight one: the tool may be
    # turned half a turn about its axis from the scan pose, where the shorter way round is a toss-up).
    assert [m[0] for m in moves] == ["cartesian", "joint"] and moves[0][1][2, 3] == pytest.approx(0.24)
    np.testing.assert_array_equal(moves[1][1], Q_SCAN)
    assert "then to the scan pose" in note
    moves, note = after("none", DeviceError("the finger camera stopped"))
    assert moves == [] and note == "the arm was left where it stopped (weld.retract_after_fault = none)"


@pytest.mark.parametrize("mode", ["clear", "full"])
def test_never_after_a_safety_stop_or_with_the_link_down(mode: str) -> None:
    moves, note = after(mode, SafetyStop("protective stop"))
    assert moves == [] and "no move after a safety stop" in note
    moves, note = after(mode, DeviceError("link gone"), link=False)
    assert moves == [] and "the robot link is down" in note


def test_an_unknown_mode_is_refused_by_the_config() -> None:
    with pytest.raises(ConfigError, match="retract_after_fault"):
        parse({"weld": {"retract_after_fault": "home"}})
