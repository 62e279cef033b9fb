"""The loop around the core: link checks, channels, cancellation, records, the process output (fake port, real shared memory)."""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence

import numpy as np
import pytest

from celld.config import MotionLimits
from celld.motion import commands as cmd
from celld.motion.channels import CONTROL_DTYPE, SETPOINT_DTYPE, ChannelNames, Channels, decode_reason
from celld.motion.core import Action, CoreParams, Mode, MotionCore
from celld.motion.limits import CartesianLimits
from celld.motion.loop import LoopParams, MotionLoop
from celld.motion.types import ControlStatus, ServoPlan
from celld.robot.link import RawState
from celld.se3 import from_ur_pose, to_ur_pose
from celld.tactile.sample import ContactState, TactileSample, to_record
from tests.motion.laws import make_probe

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
        self.outputs: list[tuple[int, bool]] = []  # every set_digital_out call
        self.output_ok = True  # what set_digital_out returns
        self.output_bits = 0  # the controller's actual outputs
        self.reads_left = -1  # >= 0: the link drops after this many reads
        self.watchdog_hz = 0.0
        self.closed = False
        self.script_stopped = False

    def connected(self) -> bool:
        return self.is_connected and self.reads_left != 0

    def read(self) -> RawState:
        if self.reads_left > 0:
            self.reads_left -= 1
        if self.fresh:
            self.stamp += 0.002
            T = from_ur_pose(self.pose)
            T[:3, 3] += self.twist[:3] * 0.002
            self.pose = to_ur_pose(T)
        return RawState(self.stamp, [0.0] * 6, [0.0] * 6, self.pose.tolist(), self.twist.tolist(), self.safety_bits, self.runtime_state)

    def speed(self, twist: Sequence[float], accel: float) -> bool:
        self.sent.append(("speedL", list(twist)))
        self.twist = np.array(twist)
        return True

    def speed_joints(self, qd: Sequence[float], accel: float) -> bool:
        self.sent.append(("speedJ", list(qd)))
        return True

    def kick(self) -> None:
        self.sent.append(("kick", []))

    def set_digital_out(self, index: int, value: bool) -> bool:
        self.outputs.append((index, value))
        if self.output_ok:
            self.output_bits = self.output_bits | (1 << index) if value else self.output_bits & ~(1 << index)
        return self.output_ok

    def digital_outputs(self) -> int:
        return self.output_bits

    def set_watchdog(self, min_frequency_hz: float) -> None:
        self.watchdog_hz = min_frequency_hz

    def stop_script(self) -> None:
        self.script_stopped = True

    def close(self, stop_script: bool = False) -> None:
        self.closed = True


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


CORE = CoreParams(CartesianLimits.from_config(MotionLimits()), 0.002, (-1.0, -1.0, 0.0), (1.0, 1.0, 1.2), 0.006, 0.1)


def _loop(channels: Channels, port: FakePort, clock: Clock, process_output: int = -1) -> MotionLoop:
    core = MotionCore(CORE, {"probe": make_probe})
    return MotionLoop(port, core, channels, LoopParams(PERIOD_NS, speed_accel=8.0, process_output=process_output), clock=clock)


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
    recs, _head, lost = channels.state.read_since(0)
    assert len(recs) == 20 and lost == 0
    assert list(recs["cycle"]) == list(range(1, 21))
    assert np.all(recs["mode"] == int(Mode.ACTIVE)) and np.all(recs["command_id"] == 1)
    speeds = [tw for kind, tw in port.sent if kind == "speedL"]
    assert len(speeds) == 20
    np.testing.assert_allclose(recs["twist"], np.array(speeds))
    assert np.all(recs["period_ns"][1:] == PERIOD_NS)


def test_the_zero_speeds_that_end_a_motion_go_on_until_the_controller_has_run_on_them(channels: Channels) -> None:
    # The robot reads its command registers once a cycle: a kick written right after the final zero
    # speeds could hide them, and the arm would creep on at its last speed. The loop sends the zero
    # speeds in place of kicks until the controller's clock has run three cycles past the first.
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock)
    sp = np.zeros(1, SETPOINT_DTYPE)
    channels.commands.post(cmd.encode(cmd.stream()))
    for _ in range(10):
        sp["t_ns"], sp["twist"] = clock.t, [0.05, 0, 0, 0, 0, 0]
        channels.setpoint.write(sp)
        _cycles(loop, clock, 1)
    _stop(channels)
    port.sent.clear()
    # A stalled controller: its clock stands still, so the zero speeds go on however many cycles pass.
    while not port.sent or port.sent[-1][0] != "speedL" or any(port.sent[-1][1]):
        _cycles(loop, clock, 1)
    first_zero = len(port.sent) - 1
    port.fresh = False
    _cycles(loop, clock, 20)
    assert all(kind == "speedL" and not any(tw) for kind, tw in port.sent[first_zero:])
    port.fresh = True
    _cycles(loop, clock, 10)
    kinds = [kind for kind, _ in port.sent[first_zero:]]
    assert kinds[-1] == "kick" and "kick" not in kinds[: 20 + 3]
    recs, _, _ = channels.state.read_since(0)
    assert int(recs["action"][-1]) == int(Action.KICK) and int(recs["action"][-11]) == int(Action.SPEED)


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


# -- the process output (welding arc) ------------------------------------------------------

ARC = 3


def _probe(cycles: int = 200, process_from: int = 20, process: bool = True) -> cmd.Command:
    plan = ServoPlan(
        "probe",
        {"direction": np.array([0.0, 1.0, 0.0])},
        {"speed": 0.01, "cycles": cycles, "process": process, "process_from": process_from},
    )
    return cmd.start_servo(plan)


def _touching(
    loop: MotionLoop, channels: Channels, clock: Clock, n: int, port: FakePort | None = None, ok_from: dict[int, bool] | None = None
) -> list[int]:
    """``n`` cycles with a fresh tactile sample each; returns the loop cycle of each set_digital_out call."""
    at: list[int] = []
    for _ in range(n):
        clock.t += PERIOD_NS
        channels.tactile.write(to_record(TactileSample(clock.t, loop.cycles + 1, np.zeros(3), ContactState.CONTACT, 1.0, True, 0)))
        if port is not None and ok_from and loop.cycles + 1 in ok_from:
            port.output_ok = ok_from[loop.cycles + 1]
        before = len(port.outputs) if port is not None else 0
        assert loop.cycle(clock.t, clock.t) is None
        if port is not None:
            at += [loop.cycles] * (len(port.outputs) - before)
    return at


def test_the_process_output_is_written_on_transitions_only(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock, process_output=ARC)
    channels.commands.post(cmd.encode(_probe(cycles=200, process_from=20)))
    at = _touching(loop, channels, clock, 300, port)
    # Off once at the first cycle (a predecessor may have left it on), on at the probe's
    # 20th cycle, off at its 200th (DONE: the stop begins).
    assert port.outputs == [(ARC, False), (ARC, True), (ARC, False)]
    assert at == [1, 20, 200]
    recs, _, _ = channels.state.read_since(0)
    recs = recs[-64:]  # the ring holds 64: cycles 237..300, after the servo ended
    assert not recs["process_on"].any() and np.all(recs["servo_phase"] == -1)
    assert np.all(np.isnan(recs["delta_n"])) and np.all(np.isnan(recs["refined_base"]))
    # Already off: nothing to do on exit.
    assert loop.release_output() and len(port.outputs) == 3


def test_the_servo_telemetry_is_recorded_each_cycle(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock, process_output=ARC)
    channels.commands.post(cmd.encode(_probe(cycles=1000, process_from=20)))
    _touching(loop, channels, clock, 50)
    recs, _, _ = channels.state.read_since(0)
    by_cycle = {int(r["cycle"]): r for r in recs}
    r10, r40 = by_cycle[10], by_cycle[40]
    assert r10["servo_phase"] == 0 and not r10["process_on"]
    assert r40["servo_phase"] == 1 and r40["process_on"]
    assert r40["delta_n"] == pytest.approx(0.040)
    np.testing.assert_allclose(r40["refined_base"], [0.0, 0.0, 0.040])


def test_without_a_process_output_nothing_is_written_but_the_wish_is_recorded(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock, process_output=-1)
    channels.commands.post(cmd.encode(_probe(cycles=1000, process_from=5)))
    _touching(loop, channels, clock, 30)
    assert port.outputs == []
    assert channels.state.latest(1)["process_on"][0]
    assert loop.release_output() and port.outputs == []


def test_a_failed_write_is_retried_every_cycle_and_reported_once(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    port.output_ok = False
    loop = _loop(channels, port, clock, process_output=ARC)
    channels.commands.post(cmd.encode(_probe(cycles=1000, process_from=20)))
    # The first off fails for cycles 1-5; the on fails for cycles 20-29.
    at = _touching(loop, channels, clock, 60, port, ok_from={6: True, 20: False, 30: True})
    assert at == [1, 2, 3, 4, 5, 6] + list(range(20, 31))
    assert port.outputs == [(ARC, False)] * 6 + [(ARC, True)] * 11
    assert loop.output_on is True
    events = [e for e in _events(channels) if "process output" in e[2]]
    assert events == [
        (0, ControlStatus.FAULT, "process output 3: switching it off failed; retrying every cycle"),
        (0, ControlStatus.FAULT, "process output 3: switching it on failed; retrying every cycle"),
    ]


def test_release_output_switches_it_off_after_the_loop_ended(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock, process_output=ARC)
    channels.commands.post(cmd.encode(_probe(cycles=1000, process_from=5)))
    _touching(loop, channels, clock, 20)
    assert port.outputs[-1] == (ARC, True)
    port.is_connected = False
    end = _cycles(loop, clock, 1)
    assert end is not None and end.status == ControlStatus.LINK_LOST
    port.output_ok = False
    assert not loop.release_output()
    assert _events(channels)[-1] == (0, ControlStatus.FAULT, "process output 3: switching it off failed; retrying every cycle")
    port.output_ok = True
    assert loop.release_output() and loop.output_on is False
    assert port.outputs[-3:] == [(ARC, True), (ARC, False), (ARC, False)]
    assert loop.release_output() and len(port.outputs) == 4  # known off: not written again


def test_the_motion_process_switches_the_output_off_when_the_link_drops(channels: Channels, monkeypatch: pytest.MonkeyPatch) -> None:
    from celld.motion import process
    from celld.realtime import RealtimeOptions
    from celld.robot import link

    class Port(FakePort):
        def read(self) -> RawState:
            self.reads += 1
            if self.reads == 5:  # after the loop started: a command posted earlier would be cancelled
                channels.commands.post(cmd.encode(_probe(cycles=100_000, process_from=10)))
            if self.reads == 300:
                self.is_connected = False
            return super().read()

    port = Port()
    port.reads = 0
    monkeypatch.setattr(link.RtdeLink, "connect", classmethod(lambda cls, host, frequency_hz=500.0, variables=(): port))
    monkeypatch.setattr(process.gc, "freeze", lambda: None)  # keep the test process's collector as it is
    channels.tactile.write(to_record(TactileSample(time.monotonic_ns(), 1, np.zeros(3), ContactState.CONTACT, 1.0, True, 0)))
    spec = process.MotionSpec(
        host="fake",
        channels=channels.names,
        core=CORE._replace(tactile_stale=60.0),
        loop=LoopParams(PERIOD_NS, speed_accel=8.0, process_output=ARC),
        realtime=RealtimeOptions(enabled=False),
        servo_laws=(("probe", "tests.motion.laws:make_probe"),),
    )
    hold: list[object] = []
    end = process.run(spec, hold)
    assert end.status == ControlStatus.LINK_LOST
    assert port.outputs == [(ARC, False), (ARC, True), (ARC, False)]
    assert port.watchdog_hz == spec.watchdog_hz
    # On a lost link nothing is stopped politely (the robot's watchdog ends its program), and the link is
    # kept for the process's exit to close its sockets, not disconnected here (ur-rtde's disconnect: 1 s).
    assert not port.script_stopped and not port.closed and hold == [port]


def test_the_handle_reports_loop_events_about_no_command_and_resolves_nothing_with_them(channels: Channels) -> None:
    from types import SimpleNamespace

    from celld.motion.channels import EVENT_DTYPE, encode_reason
    from celld.motion.handle import MotionHandle

    supervisor = SimpleNamespace(spec=SimpleNamespace(loop=SimpleNamespace(period_ns=2_000_000)), on_exit=lambda callback: None)
    handle = MotionHandle(supervisor, channels, None, ((-1.0,) * 3, (1.0,) * 3))  # type: ignore[arg-type]
    e = np.zeros(1, EVENT_DTYPE)
    e["command_id"] = 0
    e["status"] = int(ControlStatus.FAULT)
    e["reason"] = encode_reason("process output 0: switching it on failed; retrying every cycle")
    channels.events.append(e)
    handle._drain()
    assert list(handle.loop_events) == ["process output 0: switching it on failed; retrying every cycle"]
    assert handle.loop_event_count == 1 and 0 not in handle._reasons  # no command is ended by it


class _Watch:
    """A ParentWatch stand-in: the daemon goes at cycle ``gone_at``."""

    def __init__(self, loop_cycles, gone_at: int) -> None:  # type: ignore[no-untyped-def]
        self.cycles, self.gone_at = loop_cycles, gone_at

    def check(self, now_ns: int | None = None, timeout_ns: int | None = None) -> str:
        return "the daemon (pid 1234) is gone" if self.cycles() >= self.gone_at else ""


def test_without_its_daemon_the_loop_stops_the_servo_drops_the_output_and_ends(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _loop(channels, port, clock, process_output=ARC)
    loop.parent = _Watch(lambda: loop.cycles, gone_at=60)  # type: ignore[assignment]
    channels.commands.post(cmd.encode(_probe(cycles=10_000, process_from=20)))
    at = _touching(loop, channels, clock, 60, port)
    assert port.outputs == [(ARC, False), (ARC, True)] and at == [1, 20]
    end = None
    for _ in range(500):
        clock.t += PERIOD_NS
        end = loop.cycle(clock.t, clock.t)
        if end is not None:
            break
    assert end is not None and end.status == ControlStatus.OK and "is gone" in end.reason, end
    # The arc went off on the first cycle the loop looked (every 5 cycles), the stop began then.
    assert port.outputs[-1] == (ARC, False)
    recs, _, _ = channels.state.read_since(0)
    off = int(recs["cycle"][np.flatnonzero(~recs["process_on"] & (recs["cycle"] > 20))[0]])
    assert off <= 61 + 5
    # The stop was a ramp to rest, not a jump: the last twists fall to zero.
    assert np.all(recs["twist"][-1] == 0.0) and recs["mode"][-1] == int(Mode.IDLE)
    speeds = np.linalg.norm(recs["twist"][recs["cycle"] >= off][:, :3], axis=1)
    assert speeds[0] > 0.0 and np.all(np.diff(speeds) <= 1e-12)


class _Heartbeat:
    """A ParentWatch stand-in on the test's clock: the daemon's heartbeat stands still from ``frozen_ns``."""

    def __init__(self, frozen_ns: int, timeout_ns: int) -> None:
        self.frozen_ns, self.timeout_ns = frozen_ns, timeout_ns

    def check(self, now_ns: int | None = None, timeout_ns: int | None = None) -> str:
        age = (now_ns or 0) - self.frozen_ns
        return f"the daemon's heartbeat is {age / 1e6:.0f} ms old (it hangs)" if age > (timeout_ns or self.timeout_ns) else ""


HANG_NS = 250_000_000  # motion.hang_stop
PARENT_NS = 3_000_000_000  # motion.parent_timeout


def _hang_loop(channels: Channels, port: FakePort, clock: Clock) -> MotionLoop:
    core = MotionCore(CORE, {"probe": make_probe})
    params = LoopParams(PERIOD_NS, speed_accel=8.0, process_output=ARC, hang_timeout_ns=HANG_NS)
    return MotionLoop(port, core, channels, params, clock=clock)


def test_a_daemon_that_hangs_while_the_arc_is_on_stops_the_arc_and_the_arm_within_the_hang_bound(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _hang_loop(channels, port, clock)
    channels.commands.post(cmd.encode(_probe(cycles=10_000, process_from=20)))
    _touching(loop, channels, clock, 60, port)
    assert port.outputs[-1] == (ARC, True)
    frozen = clock.t
    loop.parent = _Heartbeat(frozen, PARENT_NS)  # type: ignore[assignment]
    end = None
    for _ in range(2000):
        clock.t += PERIOD_NS
        channels.tactile.write(to_record(TactileSample(clock.t, loop.cycles + 1, np.zeros(3), ContactState.CONTACT, 1.0, True, 0)))
        end = loop.cycle(clock.t, clock.t)
        if end is not None:
            break
    assert end is not None and "hangs" in end.reason, end
    assert port.outputs[-1] == (ARC, False)
    seen_after = (loop.orphaned_ns - frozen) * 1e-9
    # Seen within the hang bound and one look (every 5 cycles), not the parent timeout of an idle loop.
    assert HANG_NS * 1e-9 < seen_after <= HANG_NS * 1e-9 + 5 * PERIOD_NS * 1e-9, seen_after
    # The command ends saying why: not an operator's stop.
    reasons = [r for _, _, r in _events(channels)]
    assert any(r.startswith("stopped: the daemon's heartbeat is") for r in reasons), reasons


def test_an_idle_loop_waits_the_parent_timeout_before_it_takes_a_still_heartbeat_for_a_hang(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    loop = _hang_loop(channels, port, clock)
    loop.parent = _Heartbeat(clock.t, PARENT_NS)  # type: ignore[assignment]
    assert _cycles(loop, clock, int(2 * HANG_NS / PERIOD_NS)) is None and loop.orphaned == ""
    end = _cycles(loop, clock, int(PARENT_NS / PERIOD_NS))
    assert end is not None and "hangs" in end.reason and loop.orphaned_ns - 1_000_000_000 > PARENT_NS, end


def test_an_output_left_on_by_the_previous_process_is_reported_as_a_missing_interlock(channels: Channels) -> None:
    port, clock = FakePort(), Clock()
    port.output_bits = 1 << ARC  # the robot's program stopped, and the output stayed on
    loop = _loop(channels, port, clock, process_output=ARC)
    _cycles(loop, clock, 3)
    assert port.outputs == [(ARC, False)] and port.output_bits == 0
    [(cid, status, reason)] = _events(channels)
    assert cid == 0 and status == ControlStatus.FAULT and reason.startswith(f"arc interlock missing: process output {ARC} was still on")
    # A well set-up robot (the output went low at program stop): nothing to say.
    port2 = FakePort()
    loop2 = _loop(channels, port2, Clock(), process_output=ARC)
    _cycles(loop2, Clock(), 3)
    assert len(_events(channels)) == 1
