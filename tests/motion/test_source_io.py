"""The power source's signals through ur-rtde's interfaces, as the config wires them (fake interfaces: the calls
and their arguments; tests/sim/test_power_source.py runs them against the simulated controller)."""

from __future__ import annotations

import pytest

from celld.config.cell import parse
from celld.motion.arc import ArcOutput, ArcPhase
from celld.motion.source_io import BIT_ROLES, SourceIO

CONTROL_BOX = {
    "arc_start": "do0",
    "gas": "cdo2",
    "ready": "di0",
    "arc_stable": "di1",
    "process_active": "di2",
    "wire_stuck": "cdi3",
    "fault": "tdi1",
    "collision": "di5",
    "wire_feed": "ao0",
    "wire_feed_range": [0.0, 0.5],
    "current": "ai1",
    "current_range": [0.0, 400.0],
}
GATEWAY = {
    "arc_start": "ireg18.0",
    "gas": "ireg18.1",
    "robot_ready": "ireg18.2",
    "ready": "oreg12.0",
    "arc_stable": "oreg12.1",
    "wire_stuck": "oreg13.4",
    "wire_feed": "dreg19",
    "voltage_set": "dreg20",
    "current": "odreg12",
    "voltage": "odreg13",
}


class FakeReceive:
    def __init__(self) -> None:
        self.din = 0
        self.ai = [0.0, 0.0]
        self.oint: dict[int, int] = {}
        self.odouble: dict[int, float] = {}

    def getActualDigitalInputBits(self) -> int:  # ur-rtde's names
        return self.din

    def getStandardAnalogInput0(self) -> float:
        return self.ai[0]

    def getStandardAnalogInput1(self) -> float:
        return self.ai[1]

    def getOutputIntRegister(self, n: int) -> int:
        return self.oint.get(n, 0)

    def getOutputDoubleRegister(self, n: int) -> float:
        return self.odouble.get(n, 0.0)


class FakeIO:
    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.fail = False

    def _call(self, *args) -> bool:
        if self.fail:
            raise RuntimeError("Could not connect to 127.0.0.1")
        self.calls.append(args)
        return True

    def setStandardDigitalOut(self, n: int, v: bool) -> bool:
        return self._call("do", n, v)

    def setConfigurableDigitalOut(self, n: int, v: bool) -> bool:
        return self._call("cdo", n, v)

    def setToolDigitalOut(self, n: int, v: bool) -> bool:
        return self._call("tdo", n, v)

    def setAnalogOutputVoltage(self, n: int, ratio: float) -> bool:
        return self._call("ao", n, ratio)

    def setInputIntRegister(self, n: int, v: int) -> bool:
        return self._call("ireg", n, v)

    def setInputDoubleRegister(self, n: int, v: float) -> bool:
        return self._call("dreg", n, v)


def _io(table: dict) -> tuple[SourceIO, FakeReceive, FakeIO]:
    src = SourceIO(parse({"power_source": table}).power_source)
    rx, io = FakeReceive(), FakeIO()
    src.attach(rx, io)
    return src, rx, io


def _out(arc_start: bool, gas: bool, wire_feed: float = 0.0, voltage: float = 0.0) -> ArcOutput:
    return ArcOutput(arc_start, gas, wire_feed, voltage, 0, ArcPhase.WELD)


def test_it_subscribes_only_what_the_wiring_reads() -> None:
    assert SourceIO(parse({"power_source": CONTROL_BOX}).power_source).variables() == (
        "actual_digital_input_bits",
        "standard_analog_input1",
    )
    assert SourceIO(parse({"power_source": GATEWAY}).power_source).variables() == (
        "output_int_register_12",
        "output_int_register_13",
        "output_double_register_12",
        "output_double_register_13",
    )


def test_control_box_inputs_are_read_from_their_bits_and_the_analog_span() -> None:
    src, rx, _ = _io(CONTROL_BOX)
    # di0 ready, di1 arc stable, cdi3 (bit 11) wire stuck, tdi1 (bit 17) fault, di5 collision; di2 low.
    rx.din = (1 << 0) | (1 << 1) | (1 << 11) | (1 << 17) | (1 << 5)
    rx.ai[1] = 4.5  # V of 10 over 0-400 A
    r = src.read()
    assert r.signals.ready and r.signals.arc_stable and r.signals.wire_stuck and r.signals.fault
    assert not r.signals.process_active and r.collision
    assert r.current == pytest.approx(180.0) and r.voltage != r.voltage  # voltage not wired: NaN
    assert r.bits == sum(1 << BIT_ROLES.index(k) for k in ("ready", "arc_stable", "wire_stuck", "fault", "collision"))


def test_gateway_inputs_are_read_from_register_bits_and_doubles() -> None:
    src, rx, _ = _io(GATEWAY)
    rx.oint = {12: 0b11, 13: 1 << 4}
    rx.odouble = {12: 151.5, 13: 18.25}
    r = src.read()
    assert r.signals.ready and r.signals.arc_stable and r.signals.wire_stuck and not r.signals.fault
    assert (r.current, r.voltage) == (151.5, 18.25)


def test_outputs_are_written_once_per_change_with_their_scaling() -> None:
    src, _, io = _io(CONTROL_BOX)
    assert src.write(_out(False, True))
    assert ("cdo", 2, True) in io.calls and ("do", 0, False) in io.calls and ("ao", 0, 0.0) in io.calls
    io.calls.clear()
    assert src.write(_out(False, True))
    assert io.calls == []  # nothing changed: nothing written
    assert src.write(_out(True, True, wire_feed=0.1))
    assert io.calls == [("do", 0, True), ("ao", 0, pytest.approx(0.2))]
    io.calls.clear()
    src.write(_out(True, True, wire_feed=2.0))  # beyond the span: clipped to 10 V
    assert io.calls == [("ao", 0, 1.0)]


def test_register_roles_share_one_word_and_set_points_go_in_si() -> None:
    src, _, io = _io(GATEWAY)
    assert src.write(_out(True, True, wire_feed=0.1, voltage=19.0))
    assert ("ireg", 18, 0b111) in io.calls  # arc start, gas, robot ready in one word
    assert ("dreg", 19, 0.1) in io.calls and ("dreg", 20, 19.0) in io.calls
    io.calls.clear()
    src.write(_out(False, True, wire_feed=0.1, voltage=19.0))
    assert io.calls == [("ireg", 18, 0b110)]
    io.calls.clear()
    assert src.release()
    assert ("ireg", 18, 0) in io.calls and ("dreg", 19, 0.0) in io.calls and ("dreg", 20, 0.0) in io.calls


def test_a_failed_write_is_reported_and_retried_until_it_succeeds() -> None:
    src, _, io = _io(CONTROL_BOX)
    io.fail = True
    assert not src.write(_out(True, True))
    assert "Could not connect" in src.write_error and "arc_start (do0)" in src.write_error
    io.fail = False
    assert src.write(_out(True, True))
    assert ("do", 0, True) in io.calls and src.write_error == ""


def test_the_interlock_check_reads_the_arc_start_bit() -> None:
    src = SourceIO(parse({"power_source": {**CONTROL_BOX, "arc_start": "cdo1", "gas": "do1"}}).power_source)
    assert src.left_on(1 << 9) and not src.left_on(1 << 1)
    assert not SourceIO(parse({"power_source": GATEWAY}).power_source).left_on(0xFFFF)
