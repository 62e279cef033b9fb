"""The simulated power source on the simulated controller's I/O, through ur-rtde as the motion process uses it."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest
import rtde_io
import rtde_receive

from celld.sim.robot import launch
from celld.sim.robot.source import SourceOptions, SourceTruth

pytestmark = pytest.mark.process

# Booted at 0.2 s, a fixed ignition delay of 50 ms, no noise, no failure: every figure is exact.
TRUTH = SourceTruth(boot=0.2, ignition_delay=(0.05, 0.05), post_flow=0.2)
# Wire feed 8 m/min: 40 A + 23 A per m/min on the synergic line.
FEED = 8.0 / 60.0
CURRENT = 40.0 + 23.0 * 8.0


def _wait_for(predicate: Callable[[], bool], timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return predicate()


def test_arc_start_on_a_standard_output_strikes_and_the_inputs_read_back(loopback_host: str) -> None:
    signals = (
        ("arc_start", "do2"), ("gas", "cdo1"), ("ready", "di0"), ("arc_stable", "di1"), ("process_active", "cdi3"),
        ("wire_feed", "ao0"), ("current", "ai0"), ("voltage", "ai1"),
    )  # fmt: skip
    ranges = (("wire_feed", (0.0, 25.0 / 60.0)), ("current", (0.0, 500.0)), ("voltage", (0.0, 100.0)))
    with launch(loopback_host, realtime=True, power_source=SourceOptions(signals, ranges, TRUTH)) as sim:
        variables = ["timestamp", "actual_digital_input_bits", "standard_analog_input0", "standard_analog_input1"]
        r = rtde_receive.RTDEReceiveInterface(sim.host, -1.0, variables)
        io = rtde_io.RTDEIOInterface(sim.host)
        try:
            assert _wait_for(lambda: r.getActualDigitalInputBits() & 1 == 1)  # ready once booted
            assert io.setAnalogOutputVoltage(0, FEED / (25.0 / 60.0))  # a ratio of the 0-10 V span
            assert io.setConfigurableDigitalOut(1, True)  # gas
            assert _wait_for(lambda: r.getActualDigitalInputBits() >> 11 & 1 == 1)  # process_active on cdi3
            t0 = time.monotonic()
            assert io.setStandardDigitalOut(2, True)
            assert _wait_for(lambda: r.getActualDigitalInputBits() >> 1 & 1 == 1)
            assert time.monotonic() - t0 >= 0.05  # not before the ignition delay
            # Current over 0-500 A and voltage over 0-100 V, both on 0-10 V: 224 A and the 22 V job.
            assert r.getStandardAnalogInput0() == pytest.approx(CURRENT / 50.0, abs=1e-9)
            assert r.getStandardAnalogInput1() == pytest.approx(22.0 / 10.0, abs=1e-9)
            recs = sim.truth_history()
            assert recs["arc_on"][-1] == 1 and recs["weld_current"][-1] == pytest.approx(CURRENT, abs=1e-3)
            assert sim.status()["power_source"]["weld"] == 1
            assert io.setStandardDigitalOut(2, False)
            assert _wait_for(lambda: r.getActualDigitalInputBits() >> 1 & 1 == 0)
            assert _wait_for(lambda: r.getStandardAnalogInput0() == 0.0)
            recs = sim.truth_history()
            assert recs["arc_on"][-1] == 0 and recs["weld_current"][-1] == 0.0
            # The arc burned 0.05 s after the start was seen and until arc_start fell: one run of cycles.
            on = np.flatnonzero(recs["arc_on"])
            assert len(on) and np.all(np.diff(on) == 1)
        finally:
            io.disconnect()
            r.disconnect()


def test_arc_start_on_a_register_bit_strikes_and_the_registers_read_back(loopback_host: str) -> None:
    signals = (
        ("arc_start", "ireg18.0"), ("gas", "ireg18.1"), ("ready", "oreg12.0"), ("arc_stable", "oreg12.1"),
        ("wire_feed", "dreg19"), ("voltage_set", "dreg20"), ("current", "odreg12"), ("voltage", "odreg13"),
    )  # fmt: skip
    with launch(loopback_host, realtime=True, power_source=SourceOptions(signals, truth=TRUTH)) as sim:
        variables = ["timestamp", "output_int_register_12", "output_double_register_12", "output_double_register_13"]
        r = rtde_receive.RTDEReceiveInterface(sim.host, -1.0, variables)
        io = rtde_io.RTDEIOInterface(sim.host)
        try:
            assert _wait_for(lambda: r.getOutputIntRegister(12) == 0b01)  # ready, no arc
            assert io.setInputDoubleRegister(19, FEED)
            assert io.setInputDoubleRegister(20, 23.5)
            assert io.setInputIntRegister(18, 0b11)  # gas and arc start
            assert _wait_for(lambda: r.getOutputIntRegister(12) == 0b11)
            assert r.getOutputDoubleRegister(12) == pytest.approx(CURRENT, abs=1e-9)
            assert r.getOutputDoubleRegister(13) == pytest.approx(23.5, abs=1e-9)
            assert io.setInputIntRegister(18, 0b10)  # arc off, gas on
            assert _wait_for(lambda: r.getOutputIntRegister(12) == 0b01)
            assert r.getOutputDoubleRegister(12) == 0.0
        finally:
            io.disconnect()
            r.disconnect()
