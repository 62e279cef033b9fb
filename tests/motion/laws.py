"""A servo law for tests of the servo slot: importable by the spawned motion process.

``probe``: moves along ``direction`` at ``speed`` while the tactile sample
says contact, for ``cycles`` cycles, then reports DONE; a sample that says
overload ends it with OVERLOAD. With the plan parameter ``process`` true its
telemetry asks for the process output from its cycle ``process_from``
(default 1) until it ends.
"""

from __future__ import annotations

import numpy as np

from celld.motion.types import ControlStatus, RobotState, ServoInput, ServoPlan, ServoTelemetry
from celld.tactile.sample import ContactState


class Probe:
    def __init__(self, plan: ServoPlan) -> None:
        self.twist = np.zeros(6)
        self.twist[:3] = plan.arrays["direction"] * float(plan.params["speed"])
        self.cycles = int(plan.params["cycles"])
        self.process = bool(plan.params.get("process", False))
        self.process_from = int(plan.params.get("process_from", 1))
        self.seen: list[int] = []
        self.count = 0
        self.ended = False
        self.reason = ""

    def start(self, state: RobotState) -> None:
        self.count = 0
        self.ended = False

    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        self.count += 1
        if inp.tactile is not None and inp.tactile.contact == ContactState.OVERLOAD:
            self.ended = True
            return np.zeros(6), ControlStatus.OVERLOAD
        if self.count >= self.cycles:
            self.ended = True
            return np.zeros(6), ControlStatus.DONE
        return self.twist, ControlStatus.OK

    def telemetry(self) -> ServoTelemetry:
        on = self.process and not self.ended and self.count >= self.process_from
        return ServoTelemetry(1 if on else 0, 0.001 * self.count, np.array([0.0, 0.0, 0.001 * self.count]), on)


def make_probe(plan: ServoPlan) -> Probe:
    return Probe(plan)
