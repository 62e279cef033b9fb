"""A servo law for tests of the servo slot: importable by the spawned motion process.

``probe``: moves along ``direction`` at ``speed`` while the tactile sample
says contact, for ``cycles`` cycles, then reports DONE; a sample that says
overload ends it with OVERLOAD.
"""

from __future__ import annotations

import numpy as np

from celld.motion.types import ControlStatus, RobotState, ServoInput, ServoPlan
from celld.tactile.sample import ContactState


class Probe:
    def __init__(self, plan: ServoPlan) -> None:
        self.twist = np.zeros(6)
        self.twist[:3] = plan.arrays["direction"] * float(plan.params["speed"])
        self.cycles = int(plan.params["cycles"])
        self.seen: list[int] = []

    def start(self, state: RobotState) -> None:
        self.count = 0

    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        self.count += 1
        if inp.tactile is not None and inp.tactile.contact == ContactState.OVERLOAD:
            return np.zeros(6), ControlStatus.OVERLOAD
        if self.count >= self.cycles:
            return np.zeros(6), ControlStatus.DONE
        return self.twist, ControlStatus.OK


def make_probe(plan: ServoPlan) -> Probe:
    return Probe(plan)
