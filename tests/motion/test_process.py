"""The motion process against the simulated UR10e, through the real ur-rtde.

Each test starts the simulated controller on its own loopback address and a
:class:`MotionHandle` (which spawns the motion process) against it.

Bounds relaxed for the simulator, and why: the simulated controller is a
Python process that, on a loaded 2-core machine, can miss its 2 ms tick by
tens of milliseconds (it also stalls ~15 ms when the first speedl arrives).
A real controller does not. With the cell's defaults (state stale after 3
cycles, link lost after 100 ms without state) those stalls would stop the
robot, correctly but not usefully, so here the state may be 25 cycles old,
the link may be silent 0.5 s, and the RTDE watchdog allows 200 ms (its first
ready handshake after setWatchdog can take ~100 ms in the simulator). The
3-cycle logic itself is tested
deterministically in ``test_core.py``. The simulator runs at SCHED_FIFO on
CPU 0, away from the loop's CPU, where the OS allows it.
"""

from __future__ import annotations

import asyncio
import dataclasses
import os
import signal
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np
import pytest

from celld.config import Config, parse
from celld.errors import LinkLost, MotionError, SafetyStop
from celld.motion.channels import STATE_DTYPE
from celld.motion.core import Action, Mode
from celld.motion.handle import MotionHandle
from celld.motion.limits import CartesianLimits, sequence_peaks
from celld.motion.supervisor import LinkState
from celld.motion.types import ServoPlan
from celld.se3 import error
from celld.supervision import Backoff
from celld.tactile.sample import ContactState, TactileSample, to_record

pytestmark = [pytest.mark.process, pytest.mark.realtime]

PERIOD = 0.002


def _config() -> Config:
    cfg = parse({"robot": {"workspace_min": [-1.0, -1.0, 0.02], "workspace_max": [1.0, 1.0, 1.2]}})
    return dataclasses.replace(cfg, motion=dataclasses.replace(cfg.motion, state_stale_cycles=25))


@pytest.fixture
def sim(loopback_host: str):
    from celld.sim.robot import launch

    with launch(loopback_host, realtime=True) as handle:
        try:
            os.sched_setaffinity(handle.process.pid, {0})
        except OSError:
            pass
        yield handle


def _spacing(records: np.ndarray) -> np.ndarray:
    """Seconds from each record's cycle to the one before: the times the limiter shaped the twists over."""
    period = records["period_ns"].astype(np.float64) * 1e-9
    return np.where(period > 0.0, period, PERIOD)


def _run(sim: Any, scenario: Callable[[MotionHandle], Awaitable[None]], config: Config | None = None, **open_kw: Any) -> list[np.ndarray]:
    """Open a handle on ``sim``, run ``scenario``, close; return every state record read."""
    records: list[np.ndarray] = []

    async def main() -> None:
        kw = {"link_timeout": 0.5, "watchdog_hz": 5.0, "backoff": Backoff(delays=(0.2, 0.5))} | open_kw
        motion = await MotionHandle.open(config or _config(), host=sim.host, connect_timeout=20.0, **kw)
        motion.add_listener(records.append)
        try:
            await scenario(motion)
        finally:
            await motion.close()

    asyncio.run(main())
    return [r for r in records if len(r)] or [np.zeros(0, STATE_DTYPE)]


def _offset(T: np.ndarray, dp: list[float]) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += dp
    return out


async def _far_move_under_way(motion: MotionHandle) -> tuple[asyncio.Future[Any], int]:
    """A move 0.37 m away, 0.6 s under way (at full speed): the move and the motion process's pid."""
    start = motion.state()
    assert start is not None
    move = asyncio.ensure_future(motion.move_to(_offset(start.T_base_tcp, [0.3, 0.2, -0.1])))
    await asyncio.sleep(0.6)
    pid = motion.supervisor.pid
    assert pid is not None
    return move, pid


async def _at_rest_since(sim: Any, t0: float, step: float, within: float = 2.0) -> float | None:
    """When (monotonic s) the simulated arm came to rest for good (still for 0.1 s), looking from ``t0``
    for ``within`` s every ``step`` s; None if it did not."""
    q_prev, still_since = sim.truth()[2], None
    while time.monotonic() - t0 < within:
        await asyncio.sleep(step)
        q = sim.truth()[2]
        if np.max(np.abs(q - q_prev)) < 1e-9:
            still_since = still_since or time.monotonic()
            if time.monotonic() - still_since > 0.1:
                return still_since
        else:
            still_since = None
        q_prev = q
    return None


def test_move_to_ends_within_a_tenth_of_a_millimetre(sim: Any) -> None:
    results: list[tuple[float, float]] = []

    async def scenario(motion: MotionHandle) -> None:
        start = motion.state()
        assert start is not None
        for dp in ([0.12, 0.05, -0.08], [-0.05, 0.10, 0.04]):
            goal = _offset(start.T_base_tcp, dp)
            await motion.move_to(goal)
            await asyncio.sleep(0.1)
            _, T_true, _ = sim.truth()
            results.append(error(T_true, goal))

    records = np.concatenate(_run(sim, scenario))
    for dt, dr in results:
        assert dt < 1e-4, f"{dt * 1e3:.3f} mm from the goal (simulator truth)"
        assert dr < 1e-3
    sent = records[records["action"] == int(Action.SPEED)]
    assert len(sent) > 100


def _schedules(pid: int) -> dict[int, tuple[int, int]]:
    """(SCHED_FIFO priority or 0, niceness) of each thread of process ``pid``."""
    out = {}
    for name in os.listdir(f"/proc/{pid}/task"):
        tid = int(name)
        try:
            fifo = os.sched_getscheduler(tid) == os.SCHED_FIFO
            out[tid] = (os.sched_getparam(tid).sched_priority if fifo else 0, os.getpriority(os.PRIO_PROCESS, tid))
        except ProcessLookupError:
            continue
    return out


def test_ur_rtde_receive_threads_run_ahead_of_best_effort_work(sim: Any) -> None:
    """ur-rtde's commands wait for the state its receive threads take in: at plain best effort on a busy
    machine they held the real-time loop past the robot's watchdog. Through the watchdog handshake they
    run at SCHED_FIFO below the loop (the log says so); after it, best effort ahead of other work."""
    seen: dict[str, Any] = {}

    async def scenario(motion: MotionHandle) -> None:
        while motion.health().cycles < 50:  # the loop runs: the handshake is over
            await asyncio.sleep(0.05)
        pid = motion.supervisor.pid
        assert pid is not None
        seen["schedules"] = _schedules(pid)
        seen["realtime"] = motion.health().realtime

    _run(sim, scenario)
    if not seen["realtime"]:
        pytest.skip("the OS refused SCHED_FIFO here: the loop itself runs best effort")
    schedules = list(seen["schedules"].values())
    assert max(fifo for fifo, _ in schedules) == 80, schedules  # the loop
    assert not any(0 < fifo < 80 for fifo, _ in schedules), schedules  # nothing left at SCHED_FIFO after the handshake
    # The control interface's receive thread and the receive interface's.
    assert sum(nice == _config().motion.link_nice for _, nice in schedules) >= 2, schedules


def test_velocity_streaming_holds_the_limits_in_every_cycle(sim: Any, rng: np.random.Generator) -> None:
    config = _config()
    limits = CartesianLimits.from_config(config.motion)

    async def scenario(motion: MotionHandle) -> None:
        # Steps to random twists at or beyond the limits, and sign flips, 100 Hz for 2.5 s.
        twist = np.zeros(6)
        t_end = time.monotonic() + 2.5
        k = 0
        while time.monotonic() < t_end:
            if k % 25 == 0:
                twist = rng.normal(size=6)
                twist[:3] *= 0.3 / np.linalg.norm(twist[:3])
                twist[3:] *= 1.2 / np.linalg.norm(twist[3:])
                # Keep the TCP near its start: reverse the linear part every other step.
                twist[:3] *= 1 if (k // 25) % 2 else -1
            motion.stream(twist)
            k += 1
            await asyncio.sleep(0.01)
        motion.stop()
        await motion.wait_idle()

    records = np.concatenate(_run(sim, scenario))
    active = records[records["command_id"] > 0]
    assert np.count_nonzero(active["action"] == int(Action.SPEED)) > 800
    # Every cycle's sent twist (zero when nothing was sent), in order, with no gap.
    assert np.all(np.diff(records["cycle"].astype(np.int64)) == 1)
    twists = np.where((records["action"] == int(Action.SPEED))[:, None], records["twist"], 0.0)
    ratios = sequence_peaks(twists, PERIOD, initial=np.zeros((2, 6)), spacing=_spacing(records)).ratios(limits)
    assert max(ratios) <= 1.0 + 1e-6, ratios
    # The stream reached the speed limit it was asked to exceed.
    assert ratios.linear_speed > 0.99


def test_kill_9_watchdog_stops_the_robot_and_the_next_motion_works(sim: Any) -> None:
    async def scenario(motion: MotionHandle) -> None:
        move, pid = await _far_move_under_way(motion)
        os.kill(pid, signal.SIGKILL)
        t_kill = time.monotonic()
        with pytest.raises(LinkLost, match="SIGKILL"):
            await move
        # The RTDE watchdog (5 Hz here) stops the program, and the arm comes to rest.
        still_since = await _at_rest_since(sim, t_kill, step=0.02)
        assert still_since is not None and still_since - t_kill < 0.5
        assert "watchdog" in sim.status()["last_stop_reason"].lower()
        # The supervisor restarts the process; the next motion works.
        assert await motion.wait_ready(20.0)
        assert motion.supervisor.pid != pid and motion.supervisor.restarts >= 1
        here = motion.state()
        assert here is not None
        goal = _offset(here.T_base_tcp, [0.0, -0.05, 0.05])
        await motion.move_to(goal)
        assert error(sim.truth()[1], goal)[0] < 1e-4

    _run(sim, scenario)


def test_a_link_drop_fails_the_motion_with_its_reason_and_the_link_comes_back(sim: Any) -> None:
    async def scenario(motion: MotionHandle) -> None:
        start = motion.state()
        assert start is not None
        move = asyncio.ensure_future(motion.move_to(_offset(start.T_base_tcp, [0.25, 0.0, 0.0])))
        await asyncio.sleep(0.5)
        sim.inject("drop_rtde", down_ms=1000)
        with pytest.raises(LinkLost) as info:
            await move
        assert str(info.value)  # the reason the loop or the supervisor gave
        # The daemon side keeps running and reconnects once the controller is back.
        assert await motion.wait_ready(30.0)
        sup = motion.supervisor
        # The drop's end is history once a process ran again: the status gives no old cause for a new outage.
        assert sup.last_exit is not None and sup.outage_cause() == ""
        here = motion.state()
        assert here is not None
        goal = _offset(here.T_base_tcp, [-0.05, 0.0, 0.0])
        await motion.move_to(goal)
        assert motion.health().restarts >= 1 and motion.health().link == LinkState.RUNNING.value
        sim.inject("drop_rtde", down_ms=1000)  # a second drop: its cause is its own as soon as its process ended
        before = sup.last_exit
        for _ in range(100):
            if sup.last_exit is not before:
                break
            assert sup.outage_cause() == ""  # its process has not ended yet: no cause rather than the last drop's
            await asyncio.sleep(0.05)
        assert sup.last_exit is not before and sup.outage_cause() == sup.last_exit.reason
        assert await motion.wait_ready(30.0)

    _run(sim, scenario)


def test_the_link_state_follows_the_loop_within_a_few_cycles(sim: Any) -> None:
    seen: dict[str, Any] = {}

    async def scenario(motion: MotionHandle) -> None:
        assert motion.link_running()
        sim.inject("stall", ms=2000)  # no robot state: the loop ends on its link timeout (0.5 s here)
        deadline = time.monotonic() + 5.0
        while motion.link_running():
            assert time.monotonic() < deadline, "the link still reads up"
            await asyncio.sleep(0.001)
        t_down = time.monotonic_ns()
        seen["late_ms"] = (t_down - int(motion.ch.state.latest(1)["t_ns"][0])) * 1e-6
        # The process is still on its way out: its supervisor has not seen it end yet.
        seen["supervisor"] = motion.supervisor.state

    _run(sim, scenario)
    # Down within the fresh window (10 cycles, 20 ms) of the loop's last record, and polling.
    assert seen["late_ms"] < 40.0, seen


def test_stop_ends_the_motion_and_nothing_is_sent_after_it(sim: Any) -> None:
    async def scenario(motion: MotionHandle) -> None:
        start = motion.state()
        assert start is not None
        move = asyncio.ensure_future(motion.move_to(_offset(start.T_base_tcp, [0.3, 0.0, 0.0])))
        await asyncio.sleep(0.4)
        motion.stop()
        with pytest.raises(MotionError, match="stopped on request"):
            await move
        await motion.wait_idle()
        await asyncio.sleep(0.3)

    records = np.concatenate(_run(sim, scenario))
    idle_at = np.flatnonzero((records["mode"] == int(Mode.IDLE)) & (records["command_id"] > 0))
    assert len(idle_at)
    after = records[idle_at[0] + 1 :]
    assert len(after) > 100
    # After the stop only its zero speeds go on, until the controller has run on them (a few cycles), then kicks.
    speeds = np.flatnonzero(after["action"] != int(Action.KICK))
    assert np.all(after["action"][speeds] == int(Action.SPEED)) and not after["twist"][speeds].any(), (
        "a command was sent after the stop completed"
    )
    assert len(speeds) < 50 and (len(speeds) == 0 or speeds[-1] == len(speeds) - 1), "kicks only once the zero speeds ran"
    # The ramp to rest held the limits.
    limits = CartesianLimits.from_config(_config().motion)
    twists = np.where((records["action"] == int(Action.SPEED))[:, None], records["twist"], 0.0)
    assert max(sequence_peaks(twists, PERIOD, initial=np.zeros((2, 6)), spacing=_spacing(records)).ratios(limits)) <= 1.0 + 1e-6


def test_a_protective_stop_raises_safety_stop(sim: Any) -> None:
    async def scenario(motion: MotionHandle) -> None:
        start = motion.state()
        assert start is not None
        move = asyncio.ensure_future(motion.move_to(_offset(start.T_base_tcp, [0.3, 0.0, 0.0])))
        await asyncio.sleep(0.4)
        sim.inject("protective_stop")
        with pytest.raises(SafetyStop, match="protective stop"):
            await move

    # The robot's state may go stale only well after the stop (0.5 s): on a loaded test machine ur-rtde's
    # receive thread, which runs best effort, is left unscheduled for more than 50 ms now and then.
    config = _config()
    _run(sim, scenario, config=dataclasses.replace(config, motion=dataclasses.replace(config.motion, state_stale_cycles=250)))


def test_the_servo_slot_runs_a_registered_law_fed_by_the_tactile_slot(sim: Any) -> None:
    moved: list[float] = []

    async def feed(motion: MotionHandle, contact: ContactState, stop: asyncio.Event) -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            sample = TactileSample(time.monotonic_ns(), seq, np.zeros(3), contact, 1.0, True, 0)
            motion.ch.tactile.write(to_record(sample))
            await asyncio.sleep(1 / 60)

    async def scenario(motion: MotionHandle) -> None:
        plan = ServoPlan("probe", {"direction": np.array([0.0, 1.0, 0.0])}, {"speed": 0.02, "cycles": 500})
        stop = asyncio.Event()
        feeder = asyncio.ensure_future(feed(motion, ContactState.CONTACT, stop))
        await asyncio.sleep(0.05)  # a sample is in the slot before the servo starts
        start = motion.state()
        assert start is not None
        cid = await motion.start_servo(plan)
        await motion.wait(cid, timeout=10.0)  # DONE after 500 cycles
        here = motion.state()
        assert here is not None
        moved.append(float(here.T_base_tcp[1, 3] - start.T_base_tcp[1, 3]))
        # Tactile samples stop: the servo is stopped for stale tactile data.
        cid = await motion.start_servo(plan)
        await asyncio.sleep(0.3)
        stop.set()
        await feeder
        with pytest.raises(MotionError, match="stale tactile"):
            await motion.wait(cid, timeout=10.0)

    # The robot's state may go stale only well after the tactile samples
    # (0.1 s): a loaded test machine stalls the simulated controller now and then.
    config = _config()
    config = dataclasses.replace(config, motion=dataclasses.replace(config.motion, state_stale_cycles=250))
    _run(sim, scenario, config=config, servo_laws={"probe": "tests.motion.laws:make_probe"})
    # 500 cycles at 20 mm/s, less the jerk-limited ramps: about 18-20 mm along +y. A late cycle on a
    # loaded machine lengthens it (the controller holds the last speed until the next command comes).
    assert 0.015 < moved[0] < 0.03


def test_a_servo_law_switches_the_arc_output_of_the_simulated_controller(sim: Any) -> None:
    arc = 0  # the simulated cell's arc output
    config = _config()
    # The feeder below shares the event loop with the truth sampling: allow it a late frame.
    config = dataclasses.replace(
        config, robot=dataclasses.replace(config.robot, arc_output=arc), motion=dataclasses.replace(config.motion, tactile_stale=0.5)
    )
    truth: list[np.ndarray] = []  # the simulator's own digital outputs, every cycle
    marks: dict[str, int] = {}

    def sample_truth() -> None:
        h = sim.truth_history()[["stamp_ns", "digital_out"]]
        truth.append(h[h["stamp_ns"] > truth[-1]["stamp_ns"][-1]] if truth and len(truth[-1]) else h)

    async def feed(motion: MotionHandle, stop: asyncio.Event) -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            sample = TactileSample(time.monotonic_ns(), seq, np.zeros(3), ContactState.CONTACT, 1.0, True, 0)
            motion.ch.tactile.write(to_record(sample))
            sample_truth()
            await asyncio.sleep(1 / 60)

    async def scenario(motion: MotionHandle) -> None:
        stop = asyncio.Event()
        feeder = asyncio.ensure_future(feed(motion, stop))
        await asyncio.sleep(0.05)  # a sample is in the slot before the servo starts
        # 600 cycles (1.2 s) at 10 mm/s; the process is asked for from the 100th to the end.
        plan = ServoPlan(
            "probe", {"direction": np.array([0.0, 1.0, 0.0])}, {"speed": 0.01, "cycles": 600, "process": True, "process_from": 100}
        )
        marks["start"] = time.monotonic_ns()
        cid = await motion.start_servo(plan)
        await motion.wait(cid, timeout=10.0)
        marks["done"] = time.monotonic_ns()
        await asyncio.sleep(0.3)
        stop.set()
        await feeder
        sample_truth()

    records = np.concatenate(_run(sim, scenario, config=config, servo_laws={"probe": "tests.motion.laws:make_probe"}))
    t = np.concatenate(truth)
    bit = (t["digital_out"] >> arc) & 1 == 1
    assert np.all(np.diff(t["stamp_ns"]) > 0), "truth samples overlap or are out of order"
    assert not bit[t["stamp_ns"] < marks["start"]].any(), "the arc was on before the servo started"
    on_at = t["stamp_ns"][bit]
    assert len(on_at), "the simulated controller's arc output never went on"
    assert np.count_nonzero(np.diff(bit.astype(np.int8)) == 1) == 1, "the arc went on more than once"
    assert not bit[-1], "the arc stayed on after the servo ended"
    # The state records: asked for over the law's 500 cycles (fewer if records were lost), one interval.
    asked = records["process_on"]
    assert 450 <= np.count_nonzero(asked) <= 500
    assert np.count_nonzero(np.diff(asked.astype(np.int8)) == 1) == 1 and not asked[-1]
    assert np.all(records["servo_phase"][asked] == 1)
    # The controller followed the loop: on after the cycle that asked, off after the cycle
    # that stopped asking, each within the link's delay (bounded loosely for a loaded machine).
    t_on = int(records["t_ns"][asked][0])
    t_off = int(records["t_ns"][np.flatnonzero(asked)[-1] + 1])
    assert t_on < on_at[0] < t_on + 100_000_000
    assert t_off - 10_000_000 < on_at[-1] < t_off + 100_000_000
    # The loop commands the arc off before it reports the servo done; the controller applies it in its
    # next cycle, and the truth stamps that cycle: within a few ms of the report.
    assert on_at[-1] < marks["done"] + 20_000_000


def test_cli_status_reports_the_robot_and_the_loop(sim: Any) -> None:
    import json
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "celld.cli", "--log-level", "error", "motion", "status", "--host", sim.host, "--seconds", "1", "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(report["tcp_pose"]) == 6 and len(report["q"]) == 6
    assert report["health"]["cycles"] > 100
    assert report["health"]["link"] in ("running", "restarting", "starting")


@pytest.mark.parametrize("interlock", [True, False], ids=["outputs-low-at-stop", "no-interlock"])
def test_kill_9_of_the_motion_process_with_the_arc_on(loopback_host: str, interlock: bool) -> None:
    """With the robot's I/O set up to drop outputs at program stop, the watchdog (5 Hz here) drops the
    arc within its period; without it the arc stays on, and the next motion process says so."""
    from celld.sim.robot import launch

    arc = 0
    config = _config()
    config = dataclasses.replace(
        config, robot=dataclasses.replace(config.robot, arc_output=arc), motion=dataclasses.replace(config.motion, tactile_stale=0.5)
    )
    seen: dict[str, Any] = {}

    async def scenario(motion: MotionHandle) -> None:
        async def feed() -> None:
            seq = 0
            while True:
                seq += 1
                motion.ch.tactile.write(to_record(TactileSample(time.monotonic_ns(), seq, np.zeros(3), ContactState.CONTACT, 1.0, True, 0)))
                await asyncio.sleep(1 / 60)

        feeder = asyncio.ensure_future(feed())
        await asyncio.sleep(0.05)  # a sample is in the slot before the servo starts
        try:
            plan = ServoPlan(
                "probe", {"direction": np.array([0.0, 1.0, 0.0])}, {"speed": 0.005, "cycles": 100_000, "process": True, "process_from": 10}
            )
            await motion.start_servo(plan)
            deadline = time.monotonic() + 10
            while not int(sim.status()["digital_out"]) & (1 << arc):
                assert time.monotonic() < deadline, f"the arc never came on: {list(motion.loop_events)}"
                await asyncio.sleep(0.01)
            os.kill(motion.supervisor.pid, signal.SIGKILL)
            t_kill = time.monotonic_ns()
            await asyncio.sleep(1.0)
            h = sim.truth_history()
            after = h[h["stamp_ns"] > t_kill]
            on = after["stamp_ns"][(after["digital_out"] >> arc) & 1 == 1]
            seen["arc_off_s"] = ((int(on[-1]) - t_kill) * 1e-9 + 0.002) if len(on) else 0.0
            seen["arc_on_at_end"] = bool(after["digital_out"][-1] >> arc & 1)
            assert await motion.wait_ready(20.0)
            await asyncio.sleep(0.2)
            seen["events"] = list(motion.loop_events)
        finally:
            feeder.cancel()

    with launch(loopback_host, realtime=True, outputs_low_at_stop=interlock) as sim:
        _run(sim, scenario, config=config, servo_laws={"probe": "tests.motion.laws:make_probe"})
    missing = [e for e in seen["events"] if "arc interlock missing" in e]
    if interlock:
        assert seen["arc_off_s"] <= 1 / 5.0 + 0.05, seen  # one watchdog period, and a few cycles
        assert not seen["arc_on_at_end"] and not missing, seen
    else:
        # On long after the watchdog stopped the program: until the next motion
        # process switched it off (its first write), or past the window.
        assert seen["arc_on_at_end"] or seen["arc_off_s"] > 0.4, seen
        assert missing, seen  # the next process found the output on and said why


def test_a_daemon_that_freezes_mid_move_has_the_arm_stopped_within_the_hang_bound_and_says_so(sim: Any, tmp_path: Any) -> None:
    """The daemon's heartbeat stands still while the arm moves: the motion process stops it once the beat is
    ``motion.hang_stop`` old (not after ``parent_timeout``), ends naming the hang, and leaves its note."""
    from celld.supervision import BeatThread, ChildRecords, Heartbeat, exit_notes, exited

    cfg = _config()
    hb = Heartbeat(f"t-hb-{os.getpid()}-{time.monotonic_ns() % 100000}")
    runs = [True]
    beater = BeatThread(hb, lambda: runs[0], period=0.02)
    beater.start()
    records = ChildRecords(tmp_path / "run")

    async def scenario(motion: MotionHandle) -> None:
        move, pid = await _far_move_under_way(motion)
        runs[0] = False  # the daemon freezes: no beat from now on
        t_hang = time.monotonic()
        with pytest.raises((LinkLost, MotionError), match="hangs"):
            await move
        seen = time.monotonic() - t_hang
        # The orphan exits as soon as its stop is done, not after ur-rtde's disconnect (2 s before).
        while not exited(pid):
            assert time.monotonic() - t_hang < seen + 0.2, "the orphaned motion process lingers"
            await asyncio.sleep(0.005)
        still_since = await _at_rest_since(sim, t_hang, step=0.01)
        # At rest within the hang bound, the beat and look periods (20 + 10 ms), a jerk-limited stop from
        # full speed (v/a + a/j: 0.35 s here) and 0.1 s for the simulator's late ticks on a loaded machine
        # (module docstring; 0.61-0.65 s measured), far inside the idle parent_timeout (3 s).
        m = cfg.motion
        stop = m.max_linear_speed / m.max_linear_accel + m.max_linear_accel / m.max_linear_jerk
        bound = m.hang_stop + 0.03 + stop + 0.1
        assert still_since is not None and still_since - t_hang < bound, (still_since - t_hang, seen, bound)
        assert seen < bound
        runs[0] = True

    try:
        _run(sim, scenario, cfg, heartbeat=hb.name, records=records)
    finally:
        beater.stop()
        hb.close()
    notes = exit_notes(records.dir)
    assert notes and notes[0]["role"] == "motion" and "(it hangs)" in notes[0]["reason"], notes
