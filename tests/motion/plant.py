"""A kinematic stand-in for the robot in unit tests of the pure motion code.

It integrates the commanded TCP twist with a fixed latency of whole cycles,
the way speedL on a controller applies the last command it received. It is
no simulated controller (that is :mod:`celld.sim.robot`); it only lets the
core's logic be stepped deterministically.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.spatial.transform import Rotation

from celld.motion.core import Action, CycleInput, CycleOutput, MotionCore
from celld.motion.types import RobotState
from celld.robot import kinematics as kin


class KinematicPlant:
    def __init__(self, T_base_tcp: np.ndarray, period: float, latency_cycles: int = 2) -> None:
        self.T = np.array(T_base_tcp, dtype=np.float64)
        self.period = period
        self.v = np.zeros(6)
        self._pending: deque[np.ndarray] = deque([np.zeros(6)] * latency_cycles)
        self.stamp_ns = 0

    def apply(self, out: CycleOutput, dt: float | None = None) -> None:
        """The robot on ``out`` until the next cycle, one period later or ``dt`` s (a cycle that came late or early)."""
        if out.action == Action.SPEED:
            cmd = out.twist.copy()
        else:
            cmd = self._pending[-1].copy() if self._pending else np.zeros(6)
        step = self.period if dt is None else dt
        self._pending.append(cmd)
        self.v = self._pending.popleft()
        self.T[:3, 3] += self.v[:3] * step
        self.T[:3, :3] = Rotation.from_rotvec(self.v[3:] * step).as_matrix() @ self.T[:3, :3]
        self.stamp_ns += int(round(step * 1e9))

    def state(self) -> RobotState:
        return RobotState(self.stamp_ns, np.zeros(6), np.zeros(6), self.T.copy(), self.v.copy())

    def cycle_input(self, **kw) -> CycleInput:
        base = dict(
            state=self.state(),
            state_age=0.0,
            safety_bits=1,
            tactile=None,
            tactile_age=float("inf"),
            setpoint=np.zeros(6),
            setpoint_age=float("inf"),
        )
        base.update(kw)
        return CycleInput(**base)


def run(core: MotionCore, plant: KinematicPlant, cycles: int, **kw) -> list[CycleOutput]:
    """Step core and plant together; keyword arguments go into the first cycle's input."""
    outs = []
    for k in range(cycles):
        out = core.step(plant.cycle_input(**(kw if k == 0 else {})))
        plant.apply(out)
        outs.append(out)
    return outs


class JointPlant:
    """The same for joint moves: integrates the commanded joint speeds (speedJ) with a latency.

    ``follow`` (6,) scales what each joint does of its command (1: exactly;
    below 1 a robot that lags its speeds, 0 a joint that does not move).
    The TCP is the UR10e flange by forward kinematics.
    """

    def __init__(self, q: np.ndarray, period: float, latency_cycles: int = 2, follow: np.ndarray | None = None) -> None:
        self.q = np.array(q, dtype=np.float64)
        self.period = period
        self.qd = np.zeros(6)
        self.follow = np.ones(6) if follow is None else np.asarray(follow, dtype=np.float64)
        self._pending: deque[np.ndarray] = deque([np.zeros(6)] * latency_cycles)
        self.stamp_ns = 0
        self.sent: list[np.ndarray] = []  # the joint speeds the core sent, one per cycle (zero with a kick)

    def apply(self, out: CycleOutput, periods: int = 1) -> None:
        """The robot over the next ``periods`` control periods, on ``out`` (more than one: the loop's next cycle came late)."""
        if out.action == Action.SPEED_J:
            cmd = out.twist.copy()
        else:
            assert out.action == Action.KICK, "a joint plant takes only speedJ and kicks"
            cmd = self._pending[-1].copy() if self._pending else np.zeros(6)
        self.sent.append(out.twist.copy() if out.action == Action.SPEED_J else np.zeros(6))
        for _ in range(periods):
            self._pending.append(cmd)
            self.qd = self._pending.popleft() * self.follow
            self.q = self.q + self.qd * self.period
            self.stamp_ns += int(self.period * 1e9)

    def state(self) -> RobotState:
        T = kin.forward(self.q)
        v = kin.jacobian(self.q) @ self.qd
        return RobotState(self.stamp_ns, self.q.copy(), self.qd.copy(), T, v)

    def cycle_input(self, **kw) -> CycleInput:
        base = dict(
            state=self.state(),
            state_age=0.0,
            safety_bits=1,
            tactile=None,
            tactile_age=float("inf"),
            setpoint=np.zeros(6),
            setpoint_age=float("inf"),
        )
        base.update(kw)
        return CycleInput(**base)
