"""Benchmark: joint and Cartesian moves when the motion loop's cycles come late.

The robot keeps the speeds it was last sent until the next command arrives, so
a cycle that comes late (a loaded cell PC, a command that waited on the link)
is time the robot spends on the old speeds. This drives the motion loop's pure
core (:class:`celld.motion.core.MotionCore`, exactly as the motion process
steps it) against a stand-in robot that holds each command for as long as the
cycle took and answers with a fixed latency of two cycles, and scores where
the arm ends against where it was sent.

Cases: every ``k``-th cycle comes ``late_ms`` late (the rest on time), for
``late_ms`` in 0, 2, 4, 8, 28 ms and ``k`` = 7 (the two-robot cell measured
316 of 2193 cycles more than 1 ms late, the worst 31 ms), plus random
lateness (exponential, mean 0.4 ms, as that run's mean period 2.4 ms). Moves:
a joint move of 80 deg on the base (with the other joints, 0.25 speed scale)
and a Cartesian move of 0.44 m with a turn of 0.3 rad. Figures per case: the
move's end (DONE or the fault's reason), the final error, the largest
overshoot past the goal along the move while it ran, and the number of
cycles. Targets: every move ends DONE within its tolerance; overshoot at most
what the robot travels on one held command at the move's speed.

``--json`` prints one JSON object with every case as the last line. Exit code
1 when a move does not end DONE (named on stderr and in ``failed``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import deque
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from _common import Failures
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from celld.config import MotionLimits  # noqa: E402
from celld.motion.commands import Command, move_joints, move_to  # noqa: E402
from celld.motion.core import Action, CoreParams, CycleInput, CycleOutput, Mode, MotionCore  # noqa: E402
from celld.motion.limits import CartesianLimits, JointMoveLimits  # noqa: E402
from celld.motion.types import ControlStatus, RobotState  # noqa: E402
from celld.robot import kinematics as kin  # noqa: E402
from celld.se3 import error, from_ur_pose  # noqa: E402

PERIOD = 0.002
LATENCY = 2  # cycles from a command to its effect
Q0 = np.array([0.2, -1.6, 1.7, -1.7, -1.57, 0.1])
Q1 = np.array([1.6, -1.3, 1.4, -1.9, -1.4, 0.6])
T0 = from_ur_pose([0.5, 0.1, 0.4, 3.1, 0.1, 0.0])
T1 = from_ur_pose([0.3, -0.2, 0.5, 2.9, 0.3, 0.2])
# A shorter Cartesian move with a larger turn of the tool (0.24 m, 0.37 rad): the one whose first late twist
# overshot the goal by 22 mm (tests/motion/test_core.py).
T2 = T0.copy()
T2[:3, 3] += [0.2, 0.1, -0.1]
T2[:3, :3] = Rotation.from_rotvec([0.2, 0.1, 0.3]).as_matrix() @ T0[:3, :3]
EVERY = 7


class HeldRobot:
    """Holds each command for the cycle's real length, two cycles late; joints or TCP."""

    def __init__(self, q: np.ndarray | None, T: np.ndarray | None) -> None:
        self.q = None if q is None else q.copy()
        self.T = None if T is None else T.copy()
        self.v = np.zeros(6)
        self._pending: deque[np.ndarray] = deque([np.zeros(6)] * LATENCY)
        self._held: np.ndarray = np.zeros(6)
        self.t_ns = 0

    def hold(self, out: CycleOutput, seconds: float) -> None:
        if out.action in (Action.SPEED, Action.SPEED_J):
            self._held = out.twist.copy()
        steps = max(1, math.ceil(seconds / PERIOD - 1e-9))
        h = seconds / steps  # the controller's cycles over the time the command is held
        for _ in range(steps):
            self._pending.append(self._held)
            self.v = self._pending.popleft()
            if self.q is not None:
                self.q = self.q + self.v * h
            else:
                assert self.T is not None
                self.T[:3, 3] += self.v[:3] * h
                self.T[:3, :3] = Rotation.from_rotvec(self.v[3:] * h).as_matrix() @ self.T[:3, :3]
        self.t_ns += round(seconds * 1e9)

    def state(self) -> RobotState:
        if self.q is not None:
            return RobotState(self.t_ns, self.q.copy(), self.v.copy(), kin.forward(self.q), kin.jacobian(self.q) @ self.v)
        assert self.T is not None
        return RobotState(self.t_ns, np.zeros(6), np.zeros(6), self.T.copy(), self.v.copy())


def _input(robot: HeldRobot, **kw: Any) -> CycleInput:
    base = dict(
        state=robot.state(),
        state_age=0.0,
        safety_bits=1,
        tactile=None,
        tactile_age=math.inf,
        setpoint=np.zeros(6),
        setpoint_age=math.inf,
    )
    base.update(kw)
    return CycleInput(**base)  # type: ignore[arg-type]


def run_case(kind: str, lateness: Any, rng: np.random.Generator) -> dict[str, Any]:
    """One move with the cycles' lengths from ``lateness(k)`` (s); its figures."""
    params = CoreParams(
        CartesianLimits.from_config(MotionLimits()),
        PERIOD,
        (-1.5, -1.5, -0.5),
        (1.5, 1.5, 1.5),
        state_stale=0.5,
        tactile_stale=0.1,
        joint_limits=JointMoveLimits(speed=1.0, accel=2.0, jerk=20.0),
    )
    core = MotionCore(params)
    command: Command
    if kind == "joint":
        robot = HeldRobot(Q0, None)
        command, start, goal = move_joints(Q1, speed_scale=0.25), Q0, Q1
    else:
        robot = HeldRobot(None, T0)
        T_goal = T2 if kind == "cartesian, turning" else T1
        command, start, goal = move_to(T_goal), T0[:3, 3], T_goal[:3, 3]
    u = (goal - start) / np.linalg.norm(goal - start)
    length = float(np.linalg.norm(goal - start))
    past, out = 0.0, None
    for k in range(60000):
        out = core.step(_input(robot, **({"command": command, "command_id": 1} if k == 0 else {})))
        robot.hold(out, PERIOD + lateness(k, rng))
        here = robot.q if kind == "joint" else robot.T[:3, 3]  # type: ignore[index]
        past = max(past, float((here - start) @ u) - length)
        if k > 0 and out.mode == Mode.IDLE:
            break
    assert out is not None
    if kind == "joint":
        assert robot.q is not None
        final = float(np.degrees(np.abs(robot.q - Q1).max()))
        figures = {"final_deg": round(final, 5), "past_goal_deg": round(math.degrees(past), 4)}
    else:
        assert robot.T is not None
        dt, dr = error(robot.T, T2 if kind == "cartesian, turning" else T1)
        figures = {"final_mm": round(dt * 1e3, 4), "final_deg": round(math.degrees(dr), 4), "past_goal_mm": round(past * 1e3, 3)}
    return {
        "move": kind,
        "status": ControlStatus(out.status).name,
        "reason": out.event,
        "cycles": k + 1,
        "seconds": round(robot.t_ns * 1e-9, 2),
        **figures,
    }


def _every(late: float, k: int, _rng: np.random.Generator) -> float:
    """Every EVERY-th cycle ``late`` s late, the rest on time."""
    return late if k % EVERY == 3 else 0.0


def _first(k: int, _rng: np.random.Generator) -> float:
    """The move's first twist 16 ms late (ur-rtde's wait for the control script's handshake before the first
    command after a pause), and the loop's next cycle 0.5 ms after it, back on its schedule."""
    return {0: 16e-3, 1: 0.5e-3 - PERIOD}.get(k, 0.0)


def _random(_k: int, rng: np.random.Generator) -> float:
    """Lateness drawn exponential, mean 0.4 ms."""
    return float(rng.exponential(0.4e-3))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object last")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    failures = Failures("late_cycles")
    rng = np.random.default_rng(args.seed)
    cases: list[tuple[str, Any]] = [(f"every {EVERY}th {ms} ms late", partial(_every, ms * 1e-3)) for ms in (0, 2, 4, 8, 28)]
    cases.append(("random, mean 0.4 ms late", _random))
    cases.append(("the first twist 16 ms late, the next cycle 0.5 ms after", _first))
    rows = []
    for name, lateness in cases:
        for kind in ("joint", "cartesian", "cartesian, turning"):
            row = {"case": name, **run_case(kind, lateness, rng)}
            rows.append(row)
            if row["status"] != "DONE":
                failures.add(f"{kind} move, {name}", row["reason"] or row["status"])
            if not args.json:
                print(json.dumps(row), flush=True)
    if args.json:
        print(json.dumps({"cases": rows, "failed": failures.jobs}))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
