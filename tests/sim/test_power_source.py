"""The simulated welding power source, stepped as the controller steps it, and the world's [sim.power_source]."""

from __future__ import annotations

import argparse
import math
import statistics
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest

from celld.config import parse
from celld.errors import ConfigError
from celld.sim.cell import sim_part, source_options
from celld.sim.power_source import SOURCE_PRESETS
from celld.sim.robot.options import SimOptions, add_arguments, from_args
from celld.sim.robot.source import FAULT_RESET, JOB_VOLTAGE, SimPowerSource, SourceOptions, SourceTruth
from celld.sim.robot.truth import TRUTH_DTYPE
from celld.sim.score import arc_figures
from celld.sim.world import world_from_table, world_of

# The controller's cycle, s. The source sees an output the cycle after it was set: a time measured from a
# change of the outputs is one cycle late, give or take one cycle of the 2 ms grid.
PERIOD = 0.002
# Every role on the control box: outputs 0-1, inputs 0-6, analog output 0-1 and input 0-1 (default spans).
STANDARD = (
    ("arc_start", "do0"), ("gas", "do1"),
    ("ready", "di0"), ("arc_stable", "di1"), ("process_active", "di2"), ("wire_stuck", "di3"),
    ("fault", "di4"), ("collision", "di5"), ("heartbeat", "di6"),
    ("wire_feed", "ao0"), ("voltage_set", "ao1"), ("current", "ai0"), ("voltage", "ai1"),
)  # fmt: skip
# Booted at 0.1 s, a fixed ignition delay and post-flow, nothing else scheduled.
QUIET = SourceTruth(boot=0.1, ignition_delay=(0.05, 0.05), post_flow=0.3, ctwd_nominal=0.015)
# Wire feed 8 m/min on 0-25 m/min over 0-10 V, as the ratio ur-rtde writes; 24 V on 0-50 V.
FEED = 8.0 / 60.0
FEED_RATIO = 8.0 / 25.0
VOLTAGE_RATIO = 24.0 / 50.0
# The flange pointing down, 0.2 m above the wire end (the wire end 0.2 m out along the flange's z).
P_FLANGE_WIRE = (0.0, 0.0, 0.2)


def flange_at(z: float) -> list[float]:
    """A flange pointing down with the wire end ``z`` above the work plane z = 0 (12 row-major floats)."""
    return [1.0, 0.0, 0.0, 0.5, 0.0, -1.0, 0.0, 0.1, 0.0, 0.0, -1.0, z + P_FLANGE_WIRE[2]]


class Rig:
    """A source on a bench: the controller's outputs held as set, stepped cycle by cycle."""

    def __init__(self, truth: SourceTruth = QUIET, signals: tuple[tuple[str, str], ...] = STANDARD, geometry: bool = False) -> None:
        plane = {"p_flange_wire": P_FLANGE_WIRE, "p_base_plane": (0.0, 0.0, 0.0), "n_base_plane": (0.0, 0.0, 1.0)} if geometry else {}
        self.src = SimPowerSource(SourceOptions(signals, truth=truth, **plane))  # type: ignore[arg-type]
        self.ticks = 0
        self.digital_out = 0
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.analog_out = [FEED_RATIO, VOLTAGE_RATIO]
        self.flange = flange_at(0.015)
        self.digital_in = 0
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.analog_in = [0.0, 0.0]

    @property
    def t(self) -> float:
        return self.ticks * PERIOD

    def set(self, bit: int, on: bool) -> None:
        self.digital_out = (self.digital_out | 1 << bit) if on else (self.digital_out & ~(1 << bit))

    def arc_start(self, on: bool) -> None:
        self.set(0, on)

    def gas(self, on: bool) -> None:
        self.set(1, on)

    def step(self) -> None:
        self.ticks += 1
        self.src.step(self.t, self.digital_out, self.in_int, self.in_double, self.analog_out, self.flange)
        self.digital_in = self.src.write(self.digital_in, self.out_int, self.out_double, self.analog_in)

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / PERIOD)):
            self.step()

    def until(self, what: Callable[[SimPowerSource], bool], timeout: float) -> float:
        """Step until ``what`` holds; the controller time it first did (inf: not within ``timeout``)."""
        for _ in range(round(timeout / PERIOD)):
            self.step()
            if what(self.src):
                return self.t
        return math.inf

    def weld(self, arc_seconds: float) -> float:
        """Strike (gas and arc_start high), burn ``arc_seconds``, arc off, both low through the post-flow; the strike time."""
        self.gas(True)
        self.arc_start(True)
        t0 = self.t
        self.until(lambda s: s.arc_stable, 1.0)
        self.run(arc_seconds)
        self.arc_start(False)
        self.gas(False)
        self.until(lambda s: not s.process_active, 2.0)
        return t0


def test_the_source_is_ready_once_booted_and_its_heartbeat_toggles_every_half_second() -> None:
    rig = Rig()
    assert rig.until(lambda s: s.ready, 1.0) == pytest.approx(0.1, abs=PERIOD)
    assert rig.digital_in & 1  # ready on di0
    edges, last = [], rig.src.heartbeat
    for _ in range(round(3.0 / PERIOD)):
        rig.step()
        if rig.src.heartbeat != last:
            edges.append(rig.t)
            last = rig.src.heartbeat
    assert len(edges) == 6
    np.testing.assert_allclose(np.diff(edges), 0.5, atol=PERIOD)


def test_nothing_happens_before_the_source_has_booted() -> None:
    rig = Rig()
    rig.arc_start(True)
    rig.run(0.09)
    assert not rig.src.ready and not rig.src.process_active and rig.src.voltage == 0.0
    rig.run(0.5)  # booted with arc_start held: a start is a rise, so no arc until it is cycled
    assert rig.src.ready and rig.src.process_active and not rig.src.arc_on
    assert rig.src.voltage == pytest.approx(QUIET.open_circuit_voltage)


def test_the_arc_is_stable_after_the_ignition_delay_drawn_per_start() -> None:
    rig = Rig(replace(QUIET, ignition_delay=(0.03, 0.15)))
    rig.run(0.2)
    delays = []
    for _ in range(40):
        rig.arc_start(True)
        t0 = rig.t
        delays.append(rig.until(lambda s: s.arc_stable, 1.0) - t0)
        assert rig.digital_in >> 1 & 1  # arc_stable on di1
        rig.run(0.05)
        rig.arc_start(False)
        rig.run(0.05)
    assert 0.03 <= min(delays) and max(delays) <= 0.15 + PERIOD
    assert max(delays) - min(delays) > 0.06  # drawn anew per start, over the range


def test_a_failed_start_stays_dark_until_arc_start_is_cycled_and_the_restrike_burns() -> None:
    rig = Rig(replace(QUIET, fail_first_start=True))
    rig.run(0.2)
    rig.arc_start(True)
    assert rig.until(lambda s: s.arc_stable, 1.5) == math.inf  # held high 1.5 s: never stable
    assert rig.src.current == 0.0 and rig.src.voltage == pytest.approx(QUIET.open_circuit_voltage)
    rig.arc_start(False)
    rig.run(0.1)
    assert rig.src.voltage == 0.0
    rig.arc_start(True)
    t0 = rig.t
    assert rig.until(lambda s: s.arc_stable, 1.0) - t0 == pytest.approx(0.05 + PERIOD, abs=PERIOD)
    assert rig.src.weld == 1  # the re-strike is the same weld's


def test_the_arc_goes_out_at_its_scheduled_arc_time_and_only_a_cycled_start_reignites_it() -> None:
    rig = Rig(replace(QUIET, arc_loss_after=0.5))
    rig.run(0.2)
    rig.arc_start(True)
    t_on = rig.until(lambda s: s.arc_on, 1.0)
    t_off = rig.until(lambda s: not s.arc_stable, 2.0)
    assert t_off - t_on == pytest.approx(0.5, abs=PERIOD)
    assert rig.until(lambda s: s.arc_stable, 1.0) == math.inf  # arc_start still high: it stays out
    assert rig.src.current == 0.0
    rig.arc_start(False)
    rig.run(0.05)
    rig.arc_start(True)
    assert rig.until(lambda s: s.arc_stable, 1.0) < math.inf
    assert rig.until(lambda s: not s.arc_stable, 2.0) == math.inf  # forced once per weld


def test_process_active_runs_from_gas_through_the_post_flow_and_counts_the_welds() -> None:
    rig = Rig()
    rig.run(0.2)
    rig.gas(True)
    rig.step()
    assert rig.src.process_active and rig.src.weld == 1 and rig.digital_in >> 2 & 1
    rig.run(0.2)
    rig.arc_start(True)
    rig.run(0.5)
    rig.arc_start(False)
    rig.run(0.1)
    assert rig.src.process_active  # the gas is still on
    rig.gas(False)
    t_low = rig.t
    assert rig.until(lambda s: not s.process_active, 1.0) - t_low == pytest.approx(0.3 + PERIOD, abs=PERIOD)
    rig.arc_start(True)
    rig.step()
    assert rig.src.process_active and rig.src.weld == 2


def test_the_scheduled_weld_ends_in_a_stuck_wire_until_the_operator_cuts_it() -> None:
    rig = Rig(replace(QUIET, stuck_every=2, stuck_clear=(3.0, 3.0)))
    rig.run(0.2)
    rig.weld(0.5)
    assert not rig.src.wire_stuck  # weld 1
    rig.gas(True)
    rig.arc_start(True)
    rig.until(lambda s: s.arc_stable, 1.0)
    rig.run(0.5)
    rig.arc_start(False)
    rig.step()
    t_stuck = rig.t
    assert rig.src.wire_stuck and rig.src.weld == 2 and rig.digital_in >> 3 & 1
    rig.arc_start(True)  # a start on a stuck wire does not strike
    assert rig.until(lambda s: s.arc_on, 1.0) == math.inf
    rig.arc_start(False)
    rig.gas(False)
    assert rig.until(lambda s: not s.wire_stuck, 5.0) - t_stuck == pytest.approx(3.0, abs=PERIOD)


def test_current_and_voltage_follow_the_synergic_line_and_the_ctwd() -> None:
    rig = Rig(geometry=True)
    rig.run(0.2)
    rig.arc_start(True)
    rig.until(lambda s: s.arc_on, 1.0)
    rig.step()
    i0 = QUIET.current_base + QUIET.current_per_feed * FEED  # 40 A + 23 A per m/min x 8 m/min = 224 A
    assert i0 == pytest.approx(224.0)
    assert rig.src.current == pytest.approx(i0, abs=1e-9) and rig.src.voltage == pytest.approx(24.0, abs=1e-9)
    # Over the default spans: 224 A of 500 A and 24 V of 50 V over 0-10 V.
    assert rig.analog_in == pytest.approx([224.0 / 50.0, 24.0 / 5.0])
    rig.flange = flange_at(0.017)  # 2 mm further: 14 A less (7 A/mm), 1 V more (0.5 V/mm)
    rig.step()
    assert rig.src.ctwd(rig.flange) == pytest.approx(0.017, abs=1e-12)
    assert rig.src.current == pytest.approx(i0 - 14.0, abs=1e-6) and rig.src.voltage == pytest.approx(25.0, abs=1e-9)
    rig.analog_out[0] = 10.0 / 25.0  # 10 m/min
    rig.step()
    assert rig.src.current == pytest.approx(i0 - 14.0 + 46.0, abs=1e-6)
    rig.arc_start(False)
    rig.step()
    assert rig.src.current == 0.0 and rig.src.voltage == 0.0 and rig.analog_in == [0.0, 0.0]


def test_without_a_wire_end_or_plane_the_ctwd_is_nominal_and_without_set_points_the_job_welds() -> None:
    rig = Rig(signals=(("arc_start", "do0"), ("ready", "di0"), ("arc_stable", "di1"), ("current", "ai0")))
    rig.flange = flange_at(0.5)  # far off the work: without the geometry it is not measured
    rig.run(0.2)
    rig.arc_start(True)
    rig.until(lambda s: s.arc_on, 1.0)
    rig.step()
    assert rig.src.ctwd(rig.flange) == QUIET.ctwd_nominal
    assert rig.src.current == pytest.approx(QUIET.current_base + QUIET.current_per_feed * 8.0 / 60.0)
    assert rig.src.voltage == pytest.approx(JOB_VOLTAGE)


def test_the_noise_on_current_and_voltage_is_as_drawn_and_replays_from_the_seed() -> None:
    truth = replace(QUIET, current_noise=3.0, voltage_noise=0.2, seed=5)

    def burn() -> tuple[list[float], list[float]]:
        rig = Rig(truth, geometry=True)
        rig.run(0.2)
        rig.arc_start(True)
        rig.until(lambda s: s.arc_on, 1.0)
        current, voltage = [], []
        for _ in range(2000):
            rig.step()
            current.append(rig.src.current)
            voltage.append(rig.src.voltage)
        return current, voltage

    current, voltage = burn()
    # 2000 samples: the mean within 4 standard errors, the sigma within 10 %.
    assert statistics.fmean(current) == pytest.approx(224.0, abs=4 * 3.0 / math.sqrt(2000))
    assert statistics.stdev(current) == pytest.approx(3.0, rel=0.1)
    assert statistics.fmean(voltage) == pytest.approx(24.0, abs=4 * 0.2 / math.sqrt(2000))
    assert statistics.stdev(voltage) == pytest.approx(0.2, rel=0.1)
    assert burn() == (current, voltage)


def test_a_scheduled_fault_drops_ready_and_the_arc_and_clears_after_a_quiet_second() -> None:
    rig = Rig(replace(QUIET, fault_at=1.0))
    rig.run(0.2)
    rig.gas(True)
    rig.arc_start(True)
    rig.until(lambda s: s.arc_on, 1.0)
    assert rig.until(lambda s: s.fault, 2.0) == pytest.approx(1.0, abs=PERIOD)
    assert not rig.src.ready and not rig.src.arc_on and rig.src.current == 0.0 and rig.digital_in & 0b10001 == 0b10000
    rig.run(1.5)
    assert rig.src.fault  # arc_start still high
    rig.arc_start(False)
    rig.run(0.5)
    assert rig.src.fault  # gas still high
    rig.gas(False)
    t_quiet = rig.t
    assert rig.until(lambda s: not s.fault, 2.0) - t_quiet == pytest.approx(FAULT_RESET + PERIOD, abs=PERIOD)
    assert rig.src.ready
    rig.arc_start(True)
    assert rig.until(lambda s: s.arc_stable, 1.0) < math.inf


def test_a_collision_is_high_over_its_scheduled_interval_only() -> None:
    rig = Rig(replace(QUIET, collision_at=1.0, collision_for=0.5))
    on = rig.until(lambda s: s.collision, 2.0)
    assert on == pytest.approx(1.0, abs=PERIOD) and rig.digital_in >> 5 & 1
    assert rig.until(lambda s: not s.collision, 2.0) - on == pytest.approx(0.5, abs=PERIOD)
    assert rig.until(lambda s: s.collision or s.fault, 5.0) == math.inf  # nothing else is scheduled


def test_robot_ready_wired_must_be_high_for_the_source_to_strike() -> None:
    rig = Rig(signals=(*STANDARD, ("robot_ready", "do2")))
    rig.run(0.2)
    rig.arc_start(True)
    assert rig.until(lambda s: s.arc_on, 0.5) == math.inf
    rig.arc_start(False)
    rig.set(2, True)
    rig.step()
    rig.arc_start(True)
    assert rig.until(lambda s: s.arc_on, 0.5) < math.inf
    rig.set(2, False)
    rig.step()
    assert not rig.src.arc_on


def test_register_wiring_reads_int_and_double_registers_and_writes_bits_and_doubles() -> None:
    signals = (
        ("arc_start", "ireg18.0"), ("gas", "ireg18.1"), ("ready", "oreg12.0"), ("arc_stable", "oreg12.31"),
        ("process_active", "cdi2"), ("heartbeat", "tdi1"),
        ("wire_feed", "dreg19"), ("voltage_set", "dreg20"), ("current", "odreg12"), ("voltage", "odreg13"),
    )  # fmt: skip
    rig = Rig(signals=signals)
    rig.out_int[12] = 0b100  # a bit of the register the source does not drive
    rig.digital_in = 1 << 3  # an input the source does not drive
    rig.in_double[19], rig.in_double[20] = FEED, 21.0
    rig.run(0.2)
    assert rig.out_int[12] == 0b101 and rig.digital_in == 1 << 3
    rig.in_int[18] = 0b11
    rig.until(lambda s: s.arc_on, 1.0)
    rig.step()
    # Bit 31 set: the register holds the signed INT32 RTDE carries.
    assert rig.out_int[12] == 0b101 - (1 << 31)
    assert rig.digital_in & (1 << 10) and rig.out_double[12] == pytest.approx(224.0) and rig.out_double[13] == pytest.approx(21.0)
    rig.run(0.6)
    assert rig.digital_in >> 17 & 1  # the heartbeat on tool input 1 (0.5-1.0 s after booting)
    rig.in_int[18] = 0
    rig.step()
    assert rig.out_int[12] == 0b101 and rig.out_double[12] == 0.0


def test_rates_draw_failed_starts_arc_losses_and_stuck_wires_at_their_frequencies() -> None:
    truth = replace(QUIET, failed_start_rate=0.3, stuck_wire_rate=0.3, arc_loss_rate=0.5, post_flow=0.02, seed=3)
    rig = Rig(truth)
    rig.run(0.2)
    n, failed, stuck, lost, arc_time = 300, 0, 0, 0, 0.0
    for _ in range(n):
        rig.gas(True)
        rig.arc_start(True)
        if rig.until(lambda s: s.arc_on, 0.2) == math.inf:
            failed += 1
            while rig.until(lambda s: s.arc_on, 0.2) == math.inf:  # re-strike until it burns
                rig.arc_start(False)
                rig.step()
                rig.arc_start(True)
        t_on = rig.t
        if rig.until(lambda s: not s.arc_on, 0.4) < math.inf:
            lost += 1
        arc_time += rig.t - t_on
        rig.arc_start(False)
        rig.step()
        stuck += rig.src.wire_stuck
        rig.gas(False)
        rig.until(lambda s: not s.process_active and not s.wire_stuck, 10.0)
    # Binomial counts within 4 sigma of n p: 90 +- 32 of 300 (first starts only: the re-strikes fail at the
    # same rate, uncounted).
    for count in (failed, stuck):
        assert abs(count - 0.3 * n) < 4 * math.sqrt(n * 0.3 * 0.7), (failed, stuck)
    # Losses: a Poisson count over the arc time, within 4 sigma.
    expected = 0.5 * arc_time
    assert abs(lost - expected) < 4 * math.sqrt(expected), (lost, expected)


def test_the_options_go_through_json_and_bad_ones_are_refused() -> None:
    opts = SourceOptions(
        STANDARD, (("wire_feed", (0.0, 0.5)),), replace(QUIET, fault_at=3.0), P_FLANGE_WIRE, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    )
    assert SourceOptions.from_json(opts.to_json()) == opts
    sim = SimOptions(power_source=opts)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert from_args(parser.parse_args(sim.to_argv())).power_source == opts
    for bad, key in (
        ({"signals": (("torch", "do0"),)}, "signals.torch"),
        ({"signals": (("arc_start", "di0"),)}, "signals.arc_start"),
        ({"signals": (("arc_start", "do0"), ("gas", "do0"))}, "signals.gas"),
        ({"ranges": (("arc_start", (0.0, 1.0)),)}, "ranges.arc_start"),
        ({"ranges": (("wire_feed", (1.0, 1.0)),)}, "ranges.wire_feed"),
        ({"n_base_plane": (0.0, 0.0, 2.0)}, "n_base_plane"),
        ({"p_base_plane": None}, "n_base_plane"),
        ({"truth": replace(QUIET, ctwd_nominal=None)}, "truth.ctwd_nominal"),
    ):
        with pytest.raises(ConfigError) as exc:
            replace(opts, **bad)
        assert exc.value.key == key, (exc.value.key, key)
    for bad_truth, key in (({"failed_start_rate": 1.5}, "failed_start_rate"), ({"ignition_delay": (0.2, 0.1)}, "ignition_delay")):
        with pytest.raises(ConfigError) as exc:
            replace(QUIET, **bad_truth)
        assert exc.value.key == key


# -- the world's [sim.power_source] ------------------------------------------------------


def test_the_presets_have_no_failures_ideally_and_small_rates_realistically() -> None:
    ideal, realistic = world_from_table({}).power_source, world_from_table({"preset": "realistic"}).power_source
    for rate in ("failed_start_rate", "arc_loss_rate", "stuck_wire_rate", "current_noise", "voltage_noise"):
        assert getattr(ideal, rate) == 0.0 and 0.0 < getattr(realistic, rate), rate
    assert ideal.fault_at is None and realistic.fault_at is not None and realistic.fault_at > 0.0
    assert (realistic.failed_start_rate, realistic.arc_loss_rate, realistic.stuck_wire_rate) == (0.05, 0.01, 0.03)
    for truth in (ideal, realistic):
        assert 0.2 <= truth.boot <= 0.6 and 0.2 <= truth.post_flow <= 0.5 and 55.0 <= truth.open_circuit_voltage <= 65.0
        assert 6e3 <= truth.current_per_ctwd <= 8e3 and 400.0 <= truth.voltage_per_ctwd <= 600.0
        assert truth.ignition_delay == (0.03, 0.15) and truth.ctwd_nominal is None


def test_the_table_sets_rates_and_forced_schedules_and_refuses_what_it_does_not_know() -> None:
    table = {
        "seed": 2,
        "power_source": {
            "fail_first_start": True, "arc_loss_after_s": 2.0, "stuck_every": 3, "fault_at_s": 20.0, "collision_at_s": 30.0,
            "collision_s": 0.5, "ignition_delay_ms": [50, 50], "ctwd_nominal_mm": 15.0, "failed_start_rate": 0.2,
            "current_noise_a": 1.0,
        },
    }  # fmt: skip
    w = world_from_table(table)
    s = w.power_source
    assert (s.fail_first_start, s.arc_loss_after, s.stuck_every, s.fault_at, s.collision_at, s.collision_for) == (
        True,
        2.0,
        3,
        20.0,
        30.0,
        0.5,
    )
    assert s.ignition_delay == pytest.approx((0.05, 0.05)) and s.ctwd_nominal == pytest.approx(0.015)
    assert s.failed_start_rate == 0.2 and s.current_noise == 1.0 and w.preset == "ideal (changed)"
    # The drawn values are the seed's: a forced schedule leaves them where they were.
    plain = world_from_table({"seed": 2}).power_source
    assert (s.boot, s.post_flow, s.current_per_ctwd, s.seed) == (plain.boot, plain.post_flow, plain.current_per_ctwd, plain.seed)
    assert world_from_table({"seed": 3}).power_source.boot != plain.boot
    for bad, key in (
        ({"colour": "red"}, "sim.power_source.colour"),
        ({"failed_start_rate": 2.0}, "sim.power_source.failed_start_rate"),
        ({"ignition_delay_ms": [150, 30]}, "sim.power_source.ignition_delay_ms"),
        ({"ignition_delay_ms": 50}, "sim.power_source.ignition_delay_ms"),
        ({"stuck_every": -1}, "sim.power_source.stuck_every"),
        ({"fail_first_start": 1}, "sim.power_source.fail_first_start"),
        ({"arc_loss_after_s": 0.0}, "sim.power_source.arc_loss_after_s"),
    ):
        with pytest.raises(ConfigError) as exc:
            world_from_table({"power_source": bad})
        assert exc.value.key == key, (exc.value.key, key)
    assert SOURCE_PRESETS["ideal"] != SOURCE_PRESETS["realistic"]


def test_the_sim_cell_wires_the_source_where_the_config_says_with_the_worlds_behaviour() -> None:
    cfg = parse(
        {
            "robot": {"arc_output": -1},
            "weld": {"tip_height_mm": 5.0},
            "power_source": {
                "arc_start": "do3", "ready": "cdi1", "arc_stable": "oreg13.2", "current": "ai0", "current_range": [0.0, 400.0],
                "wire_feed": "dreg18",
            },
            "sim": {"preset": "realistic", "part": {"workpiece": "v-groove"}},
        }
    )  # fmt: skip
    w = world_of(cfg)
    part = sim_part(w)
    opts = source_options(cfg, w, part)
    assert opts is not None
    assert dict(opts.signals) == {"arc_start": "do3", "ready": "cdi1", "arc_stable": "oreg13.2", "current": "ai0", "wire_feed": "dreg18"}
    assert dict(opts.ranges) == {"current": (0.0, 400.0)}
    assert opts.truth == replace(w.power_source, ctwd_nominal=0.005)  # the job is set up for the planned height
    assert part is not None
    np.testing.assert_allclose(opts.p_flange_wire, w.tool.p_flange_torch)  # the true wire end, not the config's
    np.testing.assert_allclose(opts.n_base_plane, part.T_base_plane[:3, 2])
    assert source_options(parse({"sim": {}}), world_of(parse({"sim": {}})), None) is None


def test_the_arc_figures_count_travel_with_and_without_the_true_arc() -> None:
    w = world_from_table({})
    n = 501  # 1 s of cycles, the torch along x at 10 mm/s
    recs = np.zeros(n, TRUTH_DTYPE)
    t = np.arange(n) * PERIOD
    recs["stamp_ns"] = np.round(t * 1e9).astype(np.int64)
    recs["T_base_tcp"] = np.eye(4)
    recs["T_flange_tcp"] = np.eye(4)
    recs["T_base_tcp"][:, 0, 3] = 0.01 * t
    # Lit 0.1-0.4 s and 0.5-0.9 s at 200 A: a lost arc of 0.1 s in the middle.
    on = ((t >= 0.1) & (t < 0.4)) | ((t >= 0.5) & (t < 0.9))
    recs["arc_on"] = on
    recs["weld_current"] = np.where(on, 200.0, 0.0)
    f = arc_figures(w, recs)
    step = 0.01 * PERIOD  # m per cycle
    assert f["arc_on_m"] == pytest.approx(0.007, abs=step) and f["no_arc_m"] == pytest.approx(0.001, abs=step)
    assert f["arc_s"] == pytest.approx(0.7, abs=PERIOD) and f["strikes"] == 2 and f["mean_current_a"] == pytest.approx(200.0)
    assert math.isnan(arc_figures(w, recs[:10])["mean_current_a"])
