"""The world's welding power source: its ``[sim.power_source]`` table, its presets and the source drawn from them (pure).

A real source takes its time to boot, ignites after a delay that varies
from start to start, now and then fails a start, loses an arc or leaves the
wire stuck in the pool, and measures a current and voltage that follow the
torch's height. :class:`SourceBudget` says what the world draws that from;
:func:`draw_source` draws one source's behaviour
(:class:`~celld.sim.robot.source.SourceTruth`), which the simulated
controller runs on its I/O. The cell's wiring (which signal is which role)
is the cell config's ``[power_source]``, never drawn: the simulated cell
(:mod:`celld.sim.cell`) joins the two. Nothing outside ``celld.sim`` reads
what is drawn here.

Two presets, as the world's: ``"ideal"`` (no failed start, arc loss, stuck
wire, fault or noise) and ``"realistic"`` (small rates of each, a few amperes
and tenths of a volt of noise). The table, over the preset::

    [sim.power_source]
    boot_s = [0.2, 0.6]              # the source is ready this long after the controller starts (drawn once)
    post_flow_s = [0.2, 0.5]         # its gas post-flow (drawn once)
    ignition_delay_ms = [30, 150]    # start to stable arc (drawn per start)
    open_circuit_v = [55, 65]        # the voltage with arc_start high and no arc (drawn once)
    current_base_a = 40.0            # the synergic line: current at zero wire feed ...
    current_per_feed_a_m_min = 23.0  # ... and per m/min of wire feed
    current_per_ctwd_a_mm = [6, 8]   # the current falls this much per mm of CTWD over nominal (drawn once)
    voltage_per_ctwd_v_mm = [0.4, 0.6]  # the voltage rises this much per mm (drawn once)
    current_noise_a = 3.0            # 1 sigma on the arc's current
    voltage_noise_v = 0.2            # 1 sigma on its voltage
    failed_start_rate = 0.05         # probability that a start fails (a weld's first, and each re-strike)
    arc_loss_rate_per_s = 0.01       # arcs lost per second of arc time
    stuck_wire_rate = 0.03           # probability that a weld ends in a stuck wire
    stuck_clear_s = [2, 5]           # until an operator has cut a stuck wire (drawn per stick)
    fault_rate_per_h = 0.05          # source faults per hour the controller runs (one drawn time)
    collision_s = 1.0                # how long a collision (torch breakaway) lasts
    ctwd_nominal_mm = 4.0            # the CTWD the job is set up for (default: the height the cell plans its torch at)
    # Schedules that force a fault deterministically:
    fail_first_start = false         # every weld's first start fails
    arc_loss_after_s = 2.0           # every weld loses its arc once after this much arc time
    stuck_every = 3                  # a stuck wire at the end of every 3rd weld (0: none)
    fault_at_s = 20.0                # a source fault at this controller time
    collision_at_s = 30.0            # a collision at this controller time

A range is ``[lo, hi]`` (``[x, x]`` for a fixed value). A weld is an episode
of the source's ``process_active``, counted from 1; controller time starts
when the simulated controller does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from celld.config.reader import TableReader
from celld.errors import InputError
from celld.sim.robot.source import SourceTruth

Range = tuple[float, float]


@dataclass(frozen=True)
class SourceBudget:
    """What the world draws its power source from (SI units). Pairs are the ends of a uniform range."""

    # The boot time and the post-flow: plausible for an inverter source (a TPS/i is ready in well under a
    # second once powered with the cell; post-flow is set per job, a few tenths of a second for steel).
    boot: Range = (0.2, 0.6)  # s
    post_flow: Range = (0.2, 0.5)  # s
    # Start to stable arc: the wire's run-in to contact and the ignition, a few tens to about 150 ms.
    ignition_delay: Range = (0.03, 0.15)  # s
    # The open-circuit voltage of an inverter MIG source (TPS/i: about 60 V). Plausible spread.
    open_circuit_voltage: Range = (55.0, 65.0)  # V
    # The synergic line of 1.0 mm steel wire: about 40 A + 23 A per m/min of wire feed. Plausible.
    current_base: float = 40.0  # A
    current_per_feed: float = 23.0 * 60.0  # A per m/s
    # A longer stick-out heats the wire more before the arc: the current falls 6-8 A and the voltage
    # rises 0.4-0.6 V per mm of CTWD (constant-voltage characteristic). Plausible.
    current_per_ctwd: Range = (6.0e3, 8.0e3)  # A/m
    voltage_per_ctwd: Range = (400.0, 600.0)  # V/m
    current_noise: float = 0.0  # A, 1 sigma
    voltage_noise: float = 0.0  # V, 1 sigma
    failed_start_rate: float = 0.0
    arc_loss_rate: float = 0.0  # per s of arc time
    stuck_wire_rate: float = 0.0
    stuck_clear: Range = (2.0, 5.0)  # s
    fault_rate: float = 0.0  # per s of controller time
    collision_for: float = 1.0  # s
    ctwd_nominal: float | None = None  # m; None: the height the cell plans its torch at
    fail_first_start: bool = False
    arc_loss_after: float | None = None  # s of arc time
    stuck_every: int = 0
    fault_at: float | None = None  # s of controller time
    collision_at: float | None = None  # s of controller time

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None or isinstance(v, bool):
                continue
            values = v if isinstance(v, tuple) else (v,)
            if not all(isinstance(x, (int, float)) and math.isfinite(x) and x >= 0.0 for x in values):
                raise InputError(f"power source budget: {f.name} must be finite and >= 0, got {v!r}")
            if isinstance(v, tuple) and (len(v) != 2 or v[0] > v[1]):
                raise InputError(f"power source budget: {f.name} must be a range (lo, hi) with lo <= hi, got {v!r}")
        for name in ("failed_start_rate", "stuck_wire_rate"):
            if getattr(self, name) > 1.0:
                raise InputError(f"power source budget: {name} is a probability, got {getattr(self, name)!r}")


SOURCE_PRESETS: dict[str, SourceBudget] = {
    "ideal": SourceBudget(),
    # Small rates, sized so that a day of short welds shows each failure a few times. Plausible.
    "realistic": SourceBudget(
        current_noise=3.0,
        voltage_noise=0.2,
        failed_start_rate=0.05,
        arc_loss_rate=0.01,
        stuck_wire_rate=0.03,
        fault_rate=0.05 / 3600.0,
    ),
}

# Keys of the table: field -> (key, scale from the key's unit to SI, upper bound in the key's unit).
_KEYS: dict[str, tuple[str, float, float]] = {
    "boot": ("boot_s", 1.0, 30.0),
    "post_flow": ("post_flow_s", 1.0, 10.0),
    "ignition_delay": ("ignition_delay_ms", 1e-3, 5000.0),
    "open_circuit_voltage": ("open_circuit_v", 1.0, 120.0),
    "current_base": ("current_base_a", 1.0, 1000.0),
    "current_per_feed": ("current_per_feed_a_m_min", 60.0, 1000.0),
    "current_per_ctwd": ("current_per_ctwd_a_mm", 1e3, 100.0),
    "voltage_per_ctwd": ("voltage_per_ctwd_v_mm", 1e3, 10.0),
    "current_noise": ("current_noise_a", 1.0, 100.0),
    "voltage_noise": ("voltage_noise_v", 1.0, 10.0),
    "failed_start_rate": ("failed_start_rate", 1.0, 1.0),
    "arc_loss_rate": ("arc_loss_rate_per_s", 1.0, 100.0),
    "stuck_wire_rate": ("stuck_wire_rate", 1.0, 1.0),
    "stuck_clear": ("stuck_clear_s", 1.0, 3600.0),
    "fault_rate": ("fault_rate_per_h", 1.0 / 3600.0, 3600.0),
    "collision_for": ("collision_s", 1.0, 3600.0),
    "ctwd_nominal": ("ctwd_nominal_mm", 1e-3, 100.0),
    "arc_loss_after": ("arc_loss_after_s", 1.0, 1e6),
    "fault_at": ("fault_at_s", 1.0, 1e7),
    "collision_at": ("collision_at_s", 1.0, 1e7),
}


# Keys that must be above zero, not only at or above it.
_ABOVE_ZERO = frozenset(("ctwd_nominal", "arc_loss_after"))


def read_source_budget(r: TableReader, preset: str) -> SourceBudget:
    """The preset's source budget with the ``[sim.power_source]`` table (reader ``r``) over it."""
    b = SOURCE_PRESETS[preset]
    changes: dict[str, Any] = {}
    for name, (key, scale, hi) in _KEYS.items():
        if not r.has(key):
            continue
        if isinstance(getattr(b, name), tuple):
            lo_v, hi_v = r.vector(key, 2)
            if not 0.0 <= lo_v <= hi_v <= hi:
                raise r.error(key, f"expected [lo, hi] with 0 <= lo <= hi <= {hi:g}, got {[lo_v, hi_v]}")
            changes[name] = (lo_v * scale, hi_v * scale)
        else:
            # A nominal CTWD and a forced arc loss are after something: above zero.
            changes[name] = r.float(key, lo=0.0, hi=hi, scale=scale, open_lo=name in _ABOVE_ZERO)
    if r.has("fail_first_start"):
        changes["fail_first_start"] = r.bool("fail_first_start")
    if r.has("stuck_every"):
        changes["stuck_every"] = r.int("stuck_every", lo=0, hi=1_000_000)
    return replace(b, **changes)


def draw_source(b: SourceBudget, rng: np.random.Generator, seed: int) -> SourceTruth:
    """One source of budget ``b``: its once-drawn values from ``rng``, its per-start and per-weld draws seeded by ``seed``.

    Every value is drawn whatever the budget says of the others, so that
    changing one key leaves the rest of the source as it was.
    """
    once = (b.boot, b.post_flow, b.open_circuit_voltage, b.current_per_ctwd, b.voltage_per_ctwd)
    boot, post_flow, ocv, i_ctwd, u_ctwd = (float(rng.uniform(lo, hi)) for lo, hi in once)
    wait = float(rng.standard_exponential())
    fault_at = b.fault_at if b.fault_at is not None else (wait / b.fault_rate if b.fault_rate > 0.0 else None)
    return SourceTruth(
        boot=boot,
        post_flow=post_flow,
        ignition_delay=b.ignition_delay,
        open_circuit_voltage=ocv,
        current_base=b.current_base,
        current_per_feed=b.current_per_feed,
        current_per_ctwd=i_ctwd,
        voltage_per_ctwd=u_ctwd,
        current_noise=b.current_noise,
        voltage_noise=b.voltage_noise,
        failed_start_rate=b.failed_start_rate,
        arc_loss_rate=b.arc_loss_rate,
        stuck_wire_rate=b.stuck_wire_rate,
        stuck_clear=b.stuck_clear,
        fail_first_start=b.fail_first_start,
        arc_loss_after=b.arc_loss_after,
        stuck_every=b.stuck_every,
        fault_at=fault_at,
        collision_at=b.collision_at,
        collision_for=b.collision_for,
        ctwd_nominal=b.ctwd_nominal,
        seed=seed,
    )
