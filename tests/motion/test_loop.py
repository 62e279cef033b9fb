"""The loop around the core: link checks, channels, cancellation, records (fake port, real shared memory)."""

from __future__ import annotations

from typing import Iterator, Sequence

import numpy as np
import pytest

from celld.config import MotionLimits
from celld.motion import commands as cmd
from celld.motion.channels import CONTROL_DTYPE, SETPOINT_DTYPE, ChannelNames, Channels, decode_reason
from celld.motion.core import Action, CoreParams, Mode, MotionCore
from celld.motion.limits import CartesianLimits
from celld.motion.loop import LoopParams, MotionLoop
from celld.motion.types import ControlStatus
from celld.robot.link import RawState
from celld.se3 import from_ur_pose, to_ur_pose
from celld.tactile.sample import ContactState, TactileSample, to_record

PERIOD_NS = 2_000_000
POSE = [0.5, 0.1, 0.4, 3.1, 0.1, 0.0]


class FakePort:
    """Integrates speedL exactly, one cycle late; records what was sent."""

    def __init__(self) -> None:
        self.is_connected = True
        self.fresh = True
        self.runtime_state = 2
        self.safety_bits = 1
        self.stamp = 0.0
        self.pose = np.array(POSE, dtype=np.float64)
        self.twist = np.zeros(6)
        self.sent: list[tuple[str, list[float]]] = []

    def connected(self) -> bool:
        return self.is_connected

    def read(self) -> RawState:
        if self.fresh:
            self.stamp += 0.002
            T = from_ur_pose(self.pose)
            T[:3, 3] += self.twist[:3] * 0.002
            self.pose = to_ur_pose(T)
        return RawState(self.stamp, [0.0] * 6, [0.0] * 6, self.pose.tolist(), self.twist.tolist(),
                        self.safety_bits, self.runtime_state)

    def speed(self, twist: Sequence[float], accel: float) -> bool:
        self.sent.append(("speedL", list(twist)))
        self.twist = np.array(twist)
        return True

    def kick(self) -> None:
        self.sent.append(("kick", []))

    def close(self, stop_script: bool = False) -> None:
        pass


@pytest.fixture
def channels() -> Iterator[Channels]:
    ch = Channels.create(ChannelNames.unique(64))
    try:
        yield ch
    finally:
        ch.close()
        ch.unlink()


class Clock:
    def __init__(self) -> None:
        self.t = 1_000_000_000

    def __call__(self) -> int:
        return self.t


def _loop(channels: Channels, port: FakePort, clock: Clock) -> MotionLoop:
    limits = CartesianLimits.from_config(MotionLimits())
    core = MotionCore(CoreParams(limits, 0.002, (-1.0, -1.0, 0.0), (1.0, 1.0, 1.2), 0.006, 0.1))
    return MotionLoop(port, core, channels, LoopParams(PERIOD_NS, speed_accel=8.0), clock=clock)


def _cycles(loop: MotionLoop, clock: Clock, n: int):
    end = None
    for _ in range(n):
        clock.t += PERIOD_NS
        end = loop.cycle(clock.t, clock.t)
        if end is not None:
            return end
    return end


def _stop(channels: Channels) -> None:
    c = np.zeros(1, CONTROL_DTYPE)
    channels.control.read_into(c)
    c["stop_epoch"] = int(c["stop_epoch"][0]) + 1
    c["stop_posted"] = channels.commands.posted
    channels.control.write(c)


def _events(channels: Channels) -> list[tuple[int, ControlStatus, str]]:
    ev, _, _ = channels.events.read_since(0)
    return [(int(e["command_id"]), ControlStatus(int(e["status"])), decode_reason(e["reason"])) for e in ev]


def test_one_record_per_cycle_with_what_was_sent(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock)
    sp = np.zeros(1, SETPOINT_DTYPE)
    channels.commands.post(cmd.encode(cmd.stream()))
    for _ in range(20):
        sp["t_ns"] = clock.t
        sp["twist"] = [0.05, 0, 0, 0, 0, 0]
        channels.setpoint.write(sp)
        assert _cycles(loop, clock, 1) is None
    recs, head, lost = channels.state.read_since(0)
    assert len(recs) == 20 and lost == 0
    assert list(recs["cycle"]) == list(range(1, 21))
    assert np.all(recs["mode"] == int(Mode.ACTIVE)) and np.all(recs["command_id"] == 1)
    speeds = [tw for kind, tw in port.sent if kind == "speedL"]
    assert len(speeds) == 20
    np.testing.assert_allclose(recs["twist"], np.array(speeds))
    assert np.all(recs["period_ns"][1:] == PERIOD_NS)


def test_commands_posted_before_a_stop_never_run(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock)
    T = from_ur_pose(POSE)
    T[:3, 3] += [0.1, 0, 0]
    channels.commands.post(cmd.encode(cmd.move_to(T)))
    channels.commands.post(cmd.encode(cmd.move_to(T)))
    _stop(channels)
    _cycles(loop, clock, 5)
    assert all(kind == "kick" for kind, _ in port.sent)
    assert [(cid, st) for cid, st, _ in _events(channels)] == [(1, ControlStatus.STOPPED), (2, ControlStatus.STOPPED)]
    # A command posted after the stop runs.
    channels.commands.post(cmd.encode(cmd.move_to(T)))
    _cycles(loop, clock, 5)
    assert port.sent[-1][0] == "speedL"


def test_a_restarted_loop_cancels_what_its_predecessor_left(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    channels.commands.post(cmd.encode(cmd.stream()))
    loop = _loop(channels, port, clock)
    _cycles(loop, clock, 3)
    assert all(kind == "kick" for kind, _ in port.sent)
    assert _events(channels)[0][:2] == (1, ControlStatus.STOPPED)


def test_a_disconnected_link_ends_the_loop(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock)
    _cycles(loop, clock, 3)
    port.is_connected = False
    end = _cycles(loop, clock, 1)
    assert end is not None and end.status == ControlStatus.LINK_LOST and "disconnected" in end.reason


def test_state_that_stops_changing_is_stale_then_lost(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock)
    channels.commands.post(cmd.encode(cmd.stream()))
    _cycles(loop, clock, 10)
    port.fresh = False
    assert _cycles(loop, clock, 4) is None
    recs = channels.state.latest(1)
    assert recs["status"][0] == int(ControlStatus.STALE_STATE)
    end = _cycles(loop, clock, 100)
    assert end is not None and end.status == ControlStatus.LINK_LOST and "no fresh robot state" in end.reason


def test_a_stopped_robot_program_ends_the_loop_with_the_safety_reason(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock)
    _cycles(loop, clock, 3)
    port.runtime_state = 1
    port.safety_bits = 1 << 2
    end = _cycles(loop, clock, 100)
    assert end is not None and end.status == ControlStatus.SAFETY and "protective stop" in end.reason


def test_torn_tactile_reads_keep_the_last_good_sample_and_are_counted(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock)
    sample = TactileSample(clock.t, 42, np.array([0.0, 0.001, 0.0]), ContactState.CONTACT, 0.9, True, 1000)
    channels.tactile.write(to_record(sample))
    _cycles(loop, clock, 2)
    # A writer caught mid-write: the sequence counter is odd.
    channels.tactile._seq[0] += 1
    _cycles(loop, clock, 3)
    rec = channels.state.latest(1)[0]
    assert rec["tactile_seq"] == 42 and rec["tactile_torn"] == 3
    assert loop._tactile is not None and loop._tactile.seq == 42
