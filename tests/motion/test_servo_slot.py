"""The servo slot passes a law's fault on with the law's own reason, and its telemetry with safe fallbacks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.motion.controllers import ControlInput, ServoSlot
from celld.motion.types import NO_TELEMETRY, ControlStatus, RobotState, ServoInput, ServoTelemetry

STATE = RobotState(0, np.zeros(6), np.zeros(6), np.eye(4), np.zeros(6))
INPUT = ControlInput(STATE, None, math.inf, np.zeros(6), math.inf)


class StaleLaw:
    reason = ""

    def start(self, state: RobotState) -> None:
        self.reason = ""

    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        self.reason = "no valid tactile sample for 102 ms (last: WRONG_ID)"
        return np.zeros(6), ControlStatus.STALE_TACTILE

    def telemetry(self) -> ServoTelemetry:
        return NO_TELEMETRY


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


# -- telemetry ----------------------------------------------------------------------------


class ReportingLaw(QuietLaw):
    def __init__(self, telemetry) -> None:
        self.reason = ""
        self._t = telemetry

    def telemetry(self):
        if isinstance(self._t, Exception):
            raise self._t
        return self._t


GOOD = ServoTelemetry(1, 0.0015, np.array([0.4, -0.1, 0.12]), True)


def _slot(law) -> ServoSlot:
    slot = ServoSlot(law, "algorithm2")
    slot.start(STATE, np.zeros(6), np.zeros(6))
    slot.step(INPUT)
    return slot


def test_a_law_with_telemetry_is_passed_on() -> None:
    t = _slot(ReportingLaw(GOOD)).telemetry()
    assert (t.phase, t.delta_n, t.process_on) == (1, 0.0015, True)
    np.testing.assert_array_equal(t.refined_base, [0.4, -0.1, 0.12])
    assert type(t.phase) is int and type(t.process_on) is bool


def test_a_law_without_telemetry_or_reason_is_refused_at_start() -> None:
    class NoTelemetry:
        reason = ""

        def start(self, state: RobotState) -> None:
            pass

        def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
            return np.zeros(6), ControlStatus.OK

    class NoReason(ReportingLaw):
        def start(self, state: RobotState) -> None:
            self.reason = None

    for law, why in ((NoTelemetry(), "telemetry"), (NoReason(GOOD), "no reason string")):
        slot = _slot(law)
        assert slot.telemetry() is NO_TELEMETRY
        demand, status = slot.step(INPUT)
        assert status == ControlStatus.FAULT and np.all(demand.twist == 0.0)
        assert slot.reason.startswith("servo law 'algorithm2' failed to start") and why in slot.reason


@pytest.mark.parametrize(
    "bad",
    [
        ZeroDivisionError("boom"),
        GOOD._replace(refined_base=np.zeros(2)),
        GOOD._replace(phase=300),
        GOOD._replace(delta_n="wide"),
        (1, 2),
    ],
    ids=["raises", "bad shape", "phase out of range", "not a number", "not telemetry"],
)
def test_telemetry_is_checked_once_at_start_and_a_bad_one_refuses_the_law(bad) -> None:
    slot = _slot(ReportingLaw(bad))
    assert slot.telemetry() is NO_TELEMETRY
    _, status = slot.step(INPUT)
    assert status == ControlStatus.FAULT and "failed to start" in slot.reason


def test_telemetry_that_raises_later_gets_the_fallback_and_the_slot_keeps_stepping() -> None:
    law = ReportingLaw(GOOD)
    slot = _slot(law)
    assert slot.telemetry() is GOOD
    law._t = ZeroDivisionError("boom")
    assert slot.telemetry() is NO_TELEMETRY
    assert slot.telemetry_error.startswith("servo law 'algorithm2': telemetry failed")
    first = slot.telemetry_error
    assert slot.telemetry() is NO_TELEMETRY and slot.telemetry_error == first  # kept once
    demand, status = slot.step(INPUT)
    assert status == ControlStatus.CONTACT_LOST and np.all(demand.twist == 0.0)


def test_a_law_that_failed_to_start_reports_no_telemetry() -> None:
    class NoStart(ReportingLaw):
        def start(self, state: RobotState) -> None:
            raise RuntimeError("cannot start")

    slot = _slot(NoStart(GOOD))
    assert slot.telemetry() is NO_TELEMETRY
