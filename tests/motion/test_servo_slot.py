"""The servo slot passes a law's fault on with the law's own reason."""

from __future__ import annotations

import math

import numpy as np

from celld.motion.controllers import ControlInput, ServoSlot
from celld.motion.types import ControlStatus, RobotState, ServoInput

STATE = RobotState(0, np.zeros(6), np.zeros(6), np.eye(4), np.zeros(6))
INPUT = ControlInput(STATE, None, math.inf, np.zeros(6), math.inf)


class StaleLaw:
    reason = ""

    def start(self, state: RobotState) -> None:
        self.reason = ""

    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        self.reason = "no valid tactile sample for 102 ms (last: WRONG_ID)"
        return np.zeros(6), ControlStatus.STALE_TACTILE


class QuietLaw(StaleLaw):
    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        return np.zeros(6), ControlStatus.CONTACT_LOST


def test_the_law_reason_reaches_the_slot_reason() -> None:
    slot = ServoSlot(StaleLaw(), "algorithm2")
    slot.start(STATE, np.zeros(6), np.zeros(6))
    demand, status = slot.step(INPUT)
    assert status == ControlStatus.STALE_TACTILE
    np.testing.assert_array_equal(demand.twist, np.zeros(6))
    assert slot.reason == "servo law 'algorithm2' reported STALE_TACTILE: no valid tactile sample for 102 ms (last: WRONG_ID)"


def test_a_law_without_a_reason_still_names_its_status() -> None:
    slot = ServoSlot(QuietLaw(), "algorithm2")
    slot.start(STATE, np.zeros(6), np.zeros(6))
    _, status = slot.step(INPUT)
    assert status == ControlStatus.CONTACT_LOST
    assert slot.reason == "servo law 'algorithm2' reported CONTACT_LOST"
