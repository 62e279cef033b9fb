"""Stops and the arc on every fault, and the checks before a move, on the simulated UR10e.

The motion process runs against the simulated controller (unmodified
ur-rtde), as in the daemon. A servo law of this module drives the TCP at a
constant speed along +y with the process output (the arc, standard digital
output 0) on, fed by fresh tactile samples, until a fault ends it. The
simulator drops its standard outputs when its program stops (the UR I/O
setting the cell must have; README). Every figure is read from the
simulator's own record of the true arm and outputs, not from what celld
believes:

- ``stop_request``: the operator's stop (a cancelled job): the loop's
  jerk-limited stop;
- ``workspace``: the TCP heads for a wall of the workspace box 60 mm ahead;
  the loop stops it (figures: the stop, and where it ended from the wall);
- ``protective_stop``: the robot's safety system stops the arm itself;
- ``link_drop``: every connection to the controller reset and refused for
  2 s (cable pulled);
- ``kill_motion``: ``kill -9`` of the motion process; the RTDE watchdog
  stops the program;
- ``kill_daemon``: ``kill -9`` of the process that owns the motion process
  (the daemon); the motion process sees its parent die, stops the arm
  jerk-limited and switches the arc off itself.

Per fault: the time from the fault to the arm at rest (TCP below 0.1 mm/s),
the distance the TCP travelled meanwhile, and the time to the arc off;
median and max over the trials. Then the checks the daemon runs before a
move (:class:`celld.daemon.planning.MotionPlanner`, the simulated cell's
model): a Cartesian move, a joint move (with its speed scale) and a weld's
150 mm path, median time per check.

Targets (issue 12): arc off within 0.1 s of the stop beginning and the arm
at rest within 0.5 s of a daemon's death; the RTDE watchdog bounds the arc
where celld cannot act (one period, 0.1 s at the default 10 Hz).

``--quick``: 1 trial per fault at 0.1 m/s (about 1 min); default 3 trials.
``--speed`` sets the TCP speed (m/s, up to 0.25). ``--json`` prints the
figures as one JSON object on the last line. Exit code 1 when a trial failed:
it never reached its fault (the weld law did not reach its speed, the loop
did not stop at the wall, the stand-in daemon did not arm), or after it the
arc was still on or the orphaned motion process still ran; each named on
stderr and in the JSON's ``failed``, the other trials run on. 0 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing as mp
import os
import signal
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _common import Failures

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from celld import se3  # noqa: E402
from celld.config import load, parse  # noqa: E402
from celld.errors import CelldError  # noqa: E402
from celld.motion.handle import MotionHandle  # noqa: E402
from celld.motion.types import ControlStatus, ServoInput, ServoPlan, ServoTelemetry  # noqa: E402
from celld.sim.robot import launch  # noqa: E402
from celld.supervision import Backoff  # noqa: E402
from celld.tactile.sample import ContactState, TactileSample, to_record  # noqa: E402

# Loopback addresses of its own, clear of the tests' and the demo's.
HOSTS = [f"127.0.9.{n}" for n in range(40, 60)]
ARC = 0
# Below this TCP speed the arm counts as at rest, m/s.
REST_SPEED = 1e-4
# How long after a fault the simulator's record is read (its history holds about 2 s).
SETTLE_S = 1.2
# The workspace wall ahead of the TCP in the workspace scenario, m.
WALL_AHEAD = 0.06
FAULTS = ("stop_request", "workspace", "protective_stop", "link_drop", "kill_motion", "kill_daemon")
TARGET_ARC_OFF_S = 0.1
TARGET_REST_S = 0.5


# -- the servo law the motion process runs ------------------------------------------


class _WeldLaw:
    """A constant twist with the process output on from the 10th cycle, until stopped."""

    reason = ""

    def __init__(self, plan: ServoPlan) -> None:
        self.twist = np.asarray(plan.arrays["twist"], dtype=np.float64)
        self.cycles = 0

    def start(self, state: Any) -> None:
        self.cycles = 0

    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        self.cycles += 1
        return self.twist, ControlStatus.OK

    def telemetry(self) -> ServoTelemetry:
        return ServoTelemetry(0, 0.0, np.full(3, math.nan), self.cycles >= 10)


def make_weld_law(plan: ServoPlan) -> _WeldLaw:
    return _WeldLaw(plan)


LAWS = {"weld": "bench.safety:make_weld_law"}


# -- one trial ------------------------------------------------------------------------


def _config(workspace_max_y: float = 1.0) -> Any:
    # The config refuses taught poses outside the box: with a near wall, move the
    # verification pose (unused here) behind it; the scan pose is already at y = -0.35.
    y_v = min(0.0, workspace_max_y - 0.05)
    return parse(
        {
            "robot": {"workspace_min": [-1.0, -1.0, 0.02], "workspace_max": [1.0, workspace_max_y, 1.2], "arc_output": ARC},
            "calibration": {"verification_pose": [0.6, y_v, 0.45, 0.0, 0.0, 0.0]},
            # The simulator shares this machine's cores with the benchmark.
            "motion": {"state_stale_cycles": 50, "link_timeout_ms": 500, "tactile_stale_ms": 500},
        }
    )


async def _feed(motion: MotionHandle) -> None:
    seq = 0
    while True:
        seq += 1
        motion.ch.tactile.write(to_record(TactileSample(time.monotonic_ns(), seq, np.zeros(3), ContactState.CONTACT, 1.0, True, 0)))
        await asyncio.sleep(1 / 60)


async def _weld_until_arc(motion: MotionHandle, sim: Any, speed: float) -> int:
    """Start the law at ``speed`` along +y; return its command id once the arc is on and the TCP at speed."""
    plan = ServoPlan("weld", {"twist": np.array([0.0, speed, 0.0, 0.0, 0.0, 0.0])}, {})
    cid = await motion.start_servo(plan)
    deadline = time.monotonic() + 10.0
    while True:
        state = motion.state()
        on = int(sim.status()["digital_out"]) >> ARC & 1
        if on and state is not None and float(np.linalg.norm(state.v_tcp[:3])) > 0.98 * speed:
            return cid
        if time.monotonic() > deadline:
            raise RuntimeError(f"the weld law did not reach its speed with the arc on: {list(motion.loop_events)}")
        await asyncio.sleep(0.005)


def _figures(history: np.ndarray, t_fault: int) -> dict[str, float]:
    """Stop time and distance, and the arc-off time, from the simulator's true record after ``t_fault``."""
    h = history[history["stamp_ns"] >= t_fault - 10_000_000]
    t = h["stamp_ns"].astype(np.int64)
    p = h["T_base_tcp"][:, :3, 3]
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / np.maximum(np.diff(t) * 1e-9, 1e-6)
    after = t[1:] >= t_fault
    moving = np.nonzero(after & (v > REST_SPEED))[0]
    i_rest = int(moving[-1]) + 1 if len(moving) else int(np.argmax(after))
    i0 = int(np.searchsorted(t, t_fault))
    on = (h["digital_out"] >> ARC) & 1
    on_after = np.nonzero((t >= t_fault) & (on == 1))[0]
    arc_off = ((int(t[on_after[-1]]) - t_fault) * 1e-9 + 0.002) if len(on_after) else 0.0
    return {
        "rest_s": max(0.0, (int(t[i_rest]) - t_fault) * 1e-9),
        "distance_mm": float(np.linalg.norm(p[i_rest] - p[i0])) * 1e3,
        "arc_off_s": arc_off,
        "arc_on_at_end": bool(on[-1]),
        "y_end": float(p[-1][1]),
    }


async def _trial_in_process(fault: str, sim: Any, speed: float) -> dict[str, float]:
    config = _config()
    wall = math.nan
    if fault == "workspace":
        _, T, _ = sim.truth()
        wall = float(T[1, 3]) + WALL_AHEAD
        config = _config(workspace_max_y=wall)
    motion = await MotionHandle.open(
        config,
        host=sim.host,
        servo_laws=LAWS,
        connect_timeout=20.0,
        link_timeout=0.5,
        watchdog_hz=config.motion.rtde_watchdog_hz,
        backoff=Backoff(delays=(5.0,)),
    )
    feeder = asyncio.ensure_future(_feed(motion))
    try:
        await asyncio.sleep(0.05)
        t_fault = 0
        if fault == "workspace":
            faulted: list[int] = []

            def watch(records: np.ndarray) -> None:
                hit = records["t_ns"][records["faults"] != 0]
                if len(hit) and not faulted:
                    faulted.append(int(hit[0]))

            motion.add_listener(watch)
            await motion.start_servo(ServoPlan("weld", {"twist": np.array([0.0, speed, 0.0, 0.0, 0.0, 0.0])}, {}))
            # The fault is the loop's own decision: its first record with a fault bit.
            deadline = time.monotonic() + 10.0
            while not faulted and time.monotonic() < deadline:
                await asyncio.sleep(0.005)
            if not faulted:
                raise RuntimeError("the loop never stopped the TCP at the workspace wall")
            t_fault = faulted[0]
        else:
            await _weld_until_arc(motion, sim, speed)
            t_fault = time.monotonic_ns()
            if fault == "stop_request":
                motion.stop()
            elif fault == "protective_stop":
                sim.inject("protective_stop")
            elif fault == "link_drop":
                sim.inject("drop_all", down_ms=2000)
            elif fault == "kill_motion":
                os.kill(motion.supervisor.pid, signal.SIGKILL)
        await asyncio.sleep(SETTLE_S)
        out = _figures(sim.truth_history(), t_fault)
        if fault == "workspace":
            out["past_wall_mm"] = (out.pop("y_end") - wall) * 1e3
        else:
            out.pop("y_end")
        return out
    finally:
        feeder.cancel()
        await motion.close()


def _standin_daemon(host: str, speed: float, conn: Any) -> None:
    """The daemon stand-in: owns the motion process, welds, reports the arc on, then waits to be killed."""

    async def main() -> None:
        config = _config()
        motion = await MotionHandle.open(
            config, host=host, servo_laws=LAWS, connect_timeout=20.0, link_timeout=0.5, watchdog_hz=config.motion.rtde_watchdog_hz
        )
        feeder = asyncio.ensure_future(_feed(motion))  # held: an unreferenced task may be collected
        conn.send(("names", tuple(motion.ch.names)))

        class _Sim:
            """What the loop asked of the arc, as its records say (the simulator is the parent's to read)."""

            on = False

            def status(self) -> dict[str, Any]:
                return {"digital_out": int(self.on)}

        sim = _Sim()

        def watch(records: np.ndarray) -> None:
            if len(records):
                sim.on = bool(records["process_on"][-1])

        motion.add_listener(watch)

        await _weld_until_arc(motion, sim, speed)
        conn.send(("armed", motion.supervisor.pid))
        await asyncio.sleep(3600)
        feeder.cancel()

    asyncio.run(main())


def _trial_kill_daemon(sim: Any, speed: float) -> dict[str, float]:
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_standin_daemon, args=(sim.host, speed, child), daemon=False)
    proc.start()
    names: tuple[str, ...] = ()
    motion_pid = -1
    try:
        deadline = time.monotonic() + 40.0
        while motion_pid < 0:
            if not parent.poll(max(0.0, deadline - time.monotonic())):
                raise RuntimeError("the stand-in daemon did not arm")
            what, value = parent.recv()
            if what == "names":
                names = value
            else:
                motion_pid = int(value)
        # Its own record lags the controller's outputs by a cycle or two: wait for the truth.
        while not int(sim.status()["digital_out"]) >> ARC & 1:
            time.sleep(0.002)
        t_fault = time.monotonic_ns()
        os.kill(proc.pid, signal.SIGKILL)
        time.sleep(SETTLE_S)
        out = _figures(sim.truth_history(), t_fault)
        out.pop("y_end")
        deadline = time.monotonic() + 5.0
        while _alive(motion_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        out["motion_process_exited"] = not _alive(motion_pid)
        return out
    finally:
        proc.join(timeout=1.0)
        if proc.is_alive():
            proc.kill()
        _unlink_shm(names)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return False


def _unlink_shm(names: tuple[str, ...]) -> None:
    for name in names:
        if isinstance(name, str) and name:
            try:
                os.unlink(f"/dev/shm/{name.lstrip('/')}")
            except OSError:
                pass


def trial(fault: str, host: str, speed: float) -> dict[str, float]:
    with launch(host, realtime=True, outputs_low_at_stop=True) as sim:
        if fault == "kill_daemon":
            return _trial_kill_daemon(sim, speed)
        return asyncio.run(_trial_in_process(fault, sim, speed))


# -- planning ---------------------------------------------------------------------------


def planning(repeats: int) -> dict[str, float]:
    from celld.daemon.planning import MotionPlanner

    config = load(ROOT / "configs" / "sim-cell.toml")
    planner = MotionPlanner(config)
    q0 = np.array(config.robot.home_q)
    T0 = se3.from_ur_pose([0.6, 0.0, 0.3, math.pi, 0.0, 0.0])
    T1 = se3.from_ur_pose([0.45, 0.15, 0.25, math.pi, 0.2, 0.0])
    q_goal = q0 + np.array([-0.6, 0.2, -0.2, 0.1, 0.0, 0.4])
    # A 150 mm seam under the scanner, the flange 0.25 m above the table (the
    # torch and the finger reach below it), reached from above it.
    weld = np.array([se3.from_ur_pose([0.55 + 0.15 * s, 0.05, 0.25, math.pi, 0.0, 0.0]) for s in np.linspace(0, 1, 31)])
    q_above = planner.check_move(q0, se3.from_ur_pose([0.55, 0.05, 0.35, math.pi, 0.0, 0.0])).q[-1]
    q_weld = planner.check_move(q_above, weld[0]).q[-1]

    def timed(fn: Callable[[], Any]) -> float:
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return statistics.median(times) * 1e3

    plan = planner.plan_joint_move(q0, q_goal)
    return {
        "cartesian_move_ms": timed(lambda: planner.check_move(q0, T0)),
        "cartesian_move_2_ms": timed(lambda: planner.check_move(q0, T1)),
        "joint_move_ms": timed(lambda: planner.plan_joint_move(q0, q_goal)),
        "joint_move_scale": plan.speed_scale,
        "weld_path_150mm_ms": timed(lambda: planner.check_path(q_weld, weld)),
    }


# -- report -------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--speed", type=float, default=0.1, help="TCP speed when the fault comes, m/s")
    ap.add_argument("--faults", nargs="*", default=list(FAULTS), choices=FAULTS)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    trials = 1 if args.quick else args.trials
    if not 0.0 < args.speed <= 0.25:
        ap.error("--speed: expected 0 < speed <= 0.25 m/s")
    hosts = iter(HOSTS)
    report: dict[str, Any] = {"speed_m_s": args.speed, "trials": trials, "faults": {}}
    failures = Failures("safety")
    print(f"TCP at {args.speed * 1e3:.0f} mm/s with the arc on when the fault comes; {trials} trial(s) per fault")
    print(f"{'fault':<16} {'rest s (med/max)':>18} {'distance mm (med/max)':>22} {'arc off s (med/max)':>20}  notes")
    for fault in args.faults:
        rows = []
        for k in range(trials):
            job = f"{fault} trial {k + 1}"
            try:
                r = trial(fault, next(hosts), args.speed)
            except (RuntimeError, CelldError) as exc:  # the trial never reached its fault (a lost link, a late simulator)
                failures.add(job, f"{type(exc).__name__}: {exc}")
                continue
            if r["arc_on_at_end"]:
                failures.add(job, f"the arc was still on {SETTLE_S} s after the fault")
            if fault == "kill_daemon" and not r["motion_process_exited"]:
                failures.add(job, "the motion process still ran 5 s after its daemon's death")
            rows.append(r)
        fig: dict[str, Any] = {"trials_done": len(rows)}
        if not rows:
            report["faults"][fault] = fig
            print(f"{fault:<16} {'-':>18}  no trial reached its fault")
            continue
        for key in ("rest_s", "distance_mm", "arc_off_s"):
            vals = [r[key] for r in rows]
            fig[key] = {"median": statistics.median(vals), "max": max(vals)}
        notes = []
        if any(r["arc_on_at_end"] for r in rows):
            notes.append("ARC STILL ON")
        if fault == "workspace":
            past = [r["past_wall_mm"] for r in rows]
            fig["past_wall_mm"] = {"median": statistics.median(past), "max": max(past)}
            notes.append(f"ended {-max(past):.1f} mm before the wall (worst)")
        if fault == "kill_daemon":
            exited = all(r["motion_process_exited"] for r in rows)
            fig["motion_process_exited"] = exited
            notes.append("motion process exited" if exited else "MOTION PROCESS STILL RUNNING")
        report["faults"][fault] = fig
        print(
            f"{fault:<16} {fig['rest_s']['median']:>8.3f} / {fig['rest_s']['max']:<7.3f}  "
            f"{fig['distance_mm']['median']:>9.2f} / {fig['distance_mm']['max']:<9.2f}  "
            f"{fig['arc_off_s']['median']:>8.3f} / {fig['arc_off_s']['max']:<7.3f}  {'; '.join(notes)}"
        )
    plan = planning(5 if args.quick else 20)
    report["planning"] = plan
    print(
        "checks before a move (median): "
        f"Cartesian {plan['cartesian_move_ms']:.1f} / {plan['cartesian_move_2_ms']:.1f} ms, "
        f"joint {plan['joint_move_ms']:.1f} ms (speed scale {plan['joint_move_scale']:.2f}), "
        f"weld path 150 mm {plan['weld_path_150mm_ms']:.1f} ms"
    )
    kd = report["faults"].get("kill_daemon")
    if kd and kd["trials_done"]:
        ok = kd["arc_off_s"]["max"] <= TARGET_ARC_OFF_S and kd["rest_s"]["max"] <= TARGET_REST_S
        print(f"kill -9 of the daemon: arc off within {TARGET_ARC_OFF_S} s, at rest within {TARGET_REST_S} s: {'met' if ok else 'MISSED'}")
    report["failed"] = failures.jobs
    if args.json:
        print(json.dumps(report))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
