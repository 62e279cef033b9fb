"""The welding power source on the simulated controller's I/O: a pure model the controller steps every cycle.

A real cell wires a source such as a Fronius TPS/i to the UR control box (or
a fieldbus gateway the robot program maps onto RTDE registers):
:mod:`celld.config.power_source` says which signal carries which role. The
simulated controller owns no such source unless its options give one
(:class:`SourceOptions`): then :class:`SimPowerSource` reads the controller's
outputs through that wiring (the cell's ``arc_start``, ``gas``,
``robot_ready`` and its analog or register set points) and drives the
controller's inputs (``ready``, ``arc_stable``, ``process_active``,
``wire_stuck``, ``fault``, ``collision``, ``heartbeat`` and the measured
current and voltage), as the wires would. Its behaviour is
:class:`SourceTruth`, drawn by the world (:mod:`celld.sim.power_source`):

- ``ready`` once the source has booted (:attr:`SourceTruth.boot` after the
  controller starts), low while it is in ``fault``; ``heartbeat`` toggles
  every half second (1 Hz) from then on;
- ``process_active`` from the first of ``gas`` or ``arc_start`` going high
  until the source's own post-flow time after both are low. One such episode
  is a *weld*, counted from 1; the schedules below are per weld;
- a rise of ``arc_start`` (with the source ready, the wire free and, when it
  is wired, ``robot_ready`` high) is a start attempt: the arc ignites after a
  delay drawn per start, and ``arc_stable`` follows it. An attempt that fails
  keeps ``arc_stable`` low for as long as ``arc_start`` stays high; only a
  new rise is a new attempt;
- at its scheduled arc time (arc time counts within the weld) a burning arc
  goes out and stays out until ``arc_start`` is cycled;
- the first arc-off (``arc_start`` falling on a burning arc) of a weld
  scheduled to stick raises ``wire_stuck`` until an operator has cut the
  wire (:attr:`SourceTruth.stuck_clear`, drawn per stick);
- a ``fault`` at its scheduled controller time puts the arc out; it clears
  once ``arc_start`` and ``gas`` have both been low for :data:`FAULT_RESET`;
  ``collision`` (the torch's breakaway) is high over its scheduled interval;
- no arc: no current, and the open-circuit voltage while ``arc_start`` is high
  on a ready source; an arc: the current on the synergic line of the wire
  feed set point, the voltage the voltage set point, each moved by the
  contact-tip-to-work distance off its nominal and a little noise.

The CTWD is the true height of the wire's end over the work plane (the
contact tip sits a fixed stick-out behind the end, so a change of that height
is a change of the CTWD): the wire end in the flange frame and the plane in
the base frame come with the options, the flange pose is the physical arm's.
Without them the CTWD is its nominal.

No sockets, no clock: :meth:`SimPowerSource.step` takes the controller time
and the controller's outputs, :meth:`SimPowerSource.write` puts what the
source drives into the controller's inputs. Plain floats and :mod:`random`
(no numpy) per cycle, seeded, so a world replays.
"""

from __future__ import annotations

import json
import math
import random
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from celld.config.power_source import (
    ANALOG_IN_KINDS,
    ANALOG_OUT_KINDS,
    ANALOG_SPAN_V,
    DIGITAL_IN_KINDS,
    DIGITAL_OUT_KINDS,
    INPUT_ROLES,
    MEASURE_ROLES,
    OUTPUT_ROLES,
    SETPOINT_ROLES,
    PowerSourceConfig,
    Signal,
    parse_signal,
)
from celld.errors import ConfigError

_SOURCE = "sim robot power source"

# A fault clears once arc_start and gas have been low this long, s.
FAULT_RESET = 1.0
# Controller times are sums of 2 ms cycles in floating point: a moment counts as reached this close to it, s.
_SLACK = 1e-9
# The heartbeat's half period, s (it toggles at 2 Hz: a 1 Hz square wave).
HEARTBEAT_HALF_PERIOD = 0.5
# The job the source welds when the cell wires no set point: wire feed (8 m/min) and voltage.
JOB_WIRE_FEED = 8.0 / 60.0  # m/s
JOB_VOLTAGE = 22.0  # V
# Where each kind of digital signal sits in the controller's 18-bit words (standard 0-7, configurable 8-15, tool 16-17).
_BIT_BASE = {"do": 0, "cdo": 8, "tdo": 16, "di": 0, "cdi": 8, "tdi": 16}
_KINDS_OF_ROLE = {
    **{role: DIGITAL_OUT_KINDS for role in OUTPUT_ROLES},
    **{role: DIGITAL_IN_KINDS for role in INPUT_ROLES},
    **{role: ANALOG_OUT_KINDS for role in SETPOINT_ROLES},
    **{role: ANALOG_IN_KINDS for role in MEASURE_ROLES},
}


@dataclass(frozen=True)
class SourceTruth:
    """How the simulated source behaves (SI units), as the world drew it.

    Attributes
    ----------
    boot : float
        Controller time at which the source has booted and is ready, s.
    post_flow : float
        Gas after both gas and arc_start are low, s.
    ignition_delay : (float, float)
        Range of the delay from a start to a stable arc, s, uniform per start.
    open_circuit_voltage : float
        The voltage while arc_start is high without an arc, V.
    current_base, current_per_feed : float
        The synergic line: current at zero wire feed (A) and per m/s of wire feed (A s/m).
    current_per_ctwd, voltage_per_ctwd : float
        How far the current falls (A/m) and the voltage rises (V/m) per metre of CTWD over its nominal.
    current_noise, voltage_noise : float
        1 sigma of the white noise on the burning arc's current (A) and voltage (V).
    failed_start_rate : float
        Probability that a start attempt fails (a weld's first one, and each re-strike).
    arc_loss_rate : float
        Arcs lost per second of arc time.
    stuck_wire_rate : float
        Probability that a weld ends in a stuck wire.
    stuck_clear : (float, float)
        Range of the time until an operator has cut a stuck wire, s, uniform per stick.
    fail_first_start : bool
        Every weld's first start fails.
    arc_loss_after : float or None
        Every weld loses its arc once after this much arc time, s (None: none forced).
    stuck_every : int
        A stuck wire at the end of every n-th weld (0: none forced).
    fault_at : float or None
        Controller time of a source fault, s (None: none).
    collision_at, collision_for : float or None, float
        Controller time (s, None: none) and duration (s) of a torch collision.
    ctwd_nominal : float or None
        The CTWD the source's job is set up for, m; None only without a wire end and plane
        (the CTWD is then the nominal, whatever it is).
    seed : int
        Seed of the per-start, per-weld and noise draws.
    """

    boot: float = 0.5
    post_flow: float = 0.3
    ignition_delay: tuple[float, float] = (0.03, 0.15)
    open_circuit_voltage: float = 60.0
    current_base: float = 40.0
    current_per_feed: float = 23.0 * 60.0
    current_per_ctwd: float = 7000.0
    voltage_per_ctwd: float = 500.0
    current_noise: float = 0.0
    voltage_noise: float = 0.0
    failed_start_rate: float = 0.0
    arc_loss_rate: float = 0.0
    stuck_wire_rate: float = 0.0
    stuck_clear: tuple[float, float] = (2.0, 5.0)
    fail_first_start: bool = False
    arc_loss_after: float | None = None
    stuck_every: int = 0
    fault_at: float | None = None
    collision_at: float | None = None
    collision_for: float = 1.0
    ctwd_nominal: float | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        bounds: dict[str, tuple[float, float]] = {
            "boot": (0.0, 60.0),
            "post_flow": (0.0, 10.0),
            "open_circuit_voltage": (0.0, 120.0),
            "current_base": (0.0, 1000.0),
            "current_per_feed": (0.0, 1e5),
            "current_per_ctwd": (0.0, 1e6),
            "voltage_per_ctwd": (0.0, 1e5),
            "current_noise": (0.0, 100.0),
            "voltage_noise": (0.0, 10.0),
            "failed_start_rate": (0.0, 1.0),
            "arc_loss_rate": (0.0, 100.0),
            "stuck_wire_rate": (0.0, 1.0),
            "collision_for": (0.0, 3600.0),
        }
        for name, (lo, hi) in bounds.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and lo <= v <= hi):
                raise ConfigError(_SOURCE, name, f"expected a number in [{lo:g}, {hi:g}], got {v!r}")
            object.__setattr__(self, name, float(v))
        for name, hi in (("ignition_delay", 10.0), ("stuck_clear", 3600.0)):
            pair = tuple(getattr(self, name))
            if (
                len(pair) != 2
                or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in pair)
                or not 0.0 <= pair[0] <= pair[1] <= hi
            ):
                raise ConfigError(_SOURCE, name, f"expected a range [lo, hi] with 0 <= lo <= hi <= {hi:g} s, got {pair}")
            object.__setattr__(self, name, (float(pair[0]), float(pair[1])))
        for name in ("arc_loss_after", "fault_at", "collision_at", "ctwd_nominal"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0.0)):
                raise ConfigError(_SOURCE, name, f"expected a number >= 0 or None, got {v!r}")
        if not isinstance(self.fail_first_start, bool):
            raise ConfigError(_SOURCE, "fail_first_start", f"expected true or false, got {self.fail_first_start!r}")
        for name in ("stuck_every", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(_SOURCE, name, f"expected an integer >= 0, got {v!r}")


@dataclass(frozen=True)
class SourceOptions:
    """A power source on the simulated controller: its wiring, the CTWD's geometry and its behaviour.

    ``signals`` maps each wired role to its signal as the config writes it
    (``"do0"``, ``"ireg18.3"``, ...: :mod:`celld.config.power_source`);
    ``ranges`` the value at 0 V and at 10 V of each analog signal on the
    control box (SI; a role left out has the config's default span).
    ``p_flange_wire`` is the wire's end in the flange frame and
    ``p_base_plane``, ``n_base_plane`` a point and the unit normal (towards the
    torch) of the work plane in the base frame, m; without either the CTWD is
    the nominal.
    """

    signals: tuple[tuple[str, str], ...]
    ranges: tuple[tuple[str, tuple[float, float]], ...] = ()
    truth: SourceTruth = field(default_factory=SourceTruth)
    p_flange_wire: tuple[float, float, float] | None = None
    p_base_plane: tuple[float, float, float] | None = None
    n_base_plane: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "signals", tuple((str(role), str(text)) for role, text in self.signals))
        ranges = tuple((str(role), (float(lo), float(hi))) for role, (lo, hi) in self.ranges)
        object.__setattr__(self, "ranges", ranges)
        wiring = self.wiring  # parses and checks every signal
        for role, (lo, hi) in ranges:
            sig = wiring.signal(role)
            if sig is None or sig.kind not in ("ao", "ai"):
                raise ConfigError(_SOURCE, f"ranges.{role}", "only an analog signal on the control box (aoN, aiN) has a range")
            if not (math.isfinite(lo) and math.isfinite(hi) and lo != hi):
                raise ConfigError(_SOURCE, f"ranges.{role}", f"expected two different finite values, got {(lo, hi)}")
        for name in ("p_flange_wire", "p_base_plane", "n_base_plane"):
            v = getattr(self, name)
            if v is None:
                continue
            p = tuple(float(x) for x in v)
            if len(p) != 3 or not all(math.isfinite(x) and abs(x) < 100.0 for x in p):
                raise ConfigError(_SOURCE, name, f"expected 3 finite numbers (m), got {list(v)}")
            object.__setattr__(self, name, p)
        if (self.p_base_plane is None) != (self.n_base_plane is None):
            raise ConfigError(_SOURCE, "n_base_plane", "a work plane needs both its point and its normal")
        if self.n_base_plane is not None and abs(math.hypot(*self.n_base_plane) - 1.0) > 1e-6:
            raise ConfigError(_SOURCE, "n_base_plane", f"expected a unit normal, got {list(self.n_base_plane)}")
        if self.has_geometry and self.truth.ctwd_nominal is None:
            raise ConfigError(_SOURCE, "truth.ctwd_nominal", "a source that measures the CTWD needs its nominal CTWD")

    @property
    def has_geometry(self) -> bool:
        """True when the wire end and the work plane are given (the CTWD is measured, not nominal)."""
        return self.p_flange_wire is not None and self.p_base_plane is not None

    @property
    def wiring(self) -> PowerSourceConfig:
        """The signals as the cell's config holds them (checked: kinds, numbers, one wire one role)."""
        parsed: list[tuple[str, Signal]] = []
        seen: dict[Signal, str] = {}
        for role, text in self.signals:
            kinds = _KINDS_OF_ROLE.get(role)
            if kinds is None:
                raise ConfigError(_SOURCE, f"signals.{role}", f"unknown role; expected one of {', '.join(_KINDS_OF_ROLE)}")
            try:
                sig = parse_signal(text, kinds)
            except ValueError as exc:
                raise ConfigError(_SOURCE, f"signals.{role}", str(exc)) from exc
            if sig in seen:
                raise ConfigError(_SOURCE, f"signals.{role}", f"{sig} is already {seen[sig]}'s signal: one wire, one role")
            seen[sig] = role
            parsed.append((role, sig))
        return PowerSourceConfig(tuple(parsed), self.ranges)

    def to_json(self) -> str:
        """One line of JSON that :meth:`from_json` reads back exactly."""
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> SourceOptions:
        try:
            data = json.loads(text)
            data["truth"] = SourceTruth(**data.get("truth", {}))
            return cls(**data)
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            raise ConfigError(_SOURCE, "power_source", f"expected the JSON of a SourceOptions, got {text[:80]!r}: {exc}") from exc


def _reader(sig: Signal | None) -> tuple[int, int] | None:
    """Where a digital role is read or written: (-1, bit of the digital word) or (register, bit); None: not wired."""
    if sig is None:
        return None
    kind, index, bit = sig  # unpacked: a NamedTuple's "index" field reads as tuple.index to a type checker
    if kind in ("ireg", "oreg"):
        return index, bit
    return -1, _BIT_BASE[kind] + index


def _signed32(v: int) -> int:
    """A 32-bit pattern as the signed int an RTDE INT32 register holds."""
    v &= 0xFFFFFFFF
    return v - (1 << 32) if v & 0x80000000 else v


class SimPowerSource:
    """The source's state in the simulated controller's cycle.

    Call :meth:`step` once per cycle with the controller time and its
    outputs, then :meth:`write` with its inputs. The state after a step is in
    the attributes: the signals it drives (:attr:`ready`, :attr:`arc_stable`,
    ...), :attr:`arc_on` (an arc truly burns), :attr:`current` (A) and
    :attr:`voltage` (V), :attr:`weld` (the current or last weld's number, 0
    before the first).
    """

    def __init__(self, options: SourceOptions) -> None:
        tr = self.truth = options.truth
        w = options.wiring
        self._arc_start = _reader(w.signal("arc_start"))
        self._gas = _reader(w.signal("gas"))
        self._robot_ready = _reader(w.signal("robot_ready"))
        self._setpoints = tuple(self._setpoint_plan(w, role) for role in SETPOINT_ROLES)
        # What write() drives: digital-word bits, register bits (per register: its mask and (role index, bit)), measures.
        din: list[tuple[int, int]] = []
        regs: dict[int, list[tuple[int, int]]] = {}
        for i, role in enumerate(INPUT_ROLES):
            where = _reader(w.signal(role))
            if where is None:
                continue
            reg, bit = where
            if reg < 0:
                din.append((i, bit))
            else:
                regs.setdefault(reg, []).append((i, bit))
        self._din = tuple(din)
        self.digital_in_mask = sum(1 << bit for _, bit in din)
        self._oreg = tuple((reg, sum(1 << b for _, b in bits), tuple(bits)) for reg, bits in sorted(regs.items()))
        measures: list[tuple[int, str, int, float, float]] = []
        for i, role in enumerate(MEASURE_ROLES):
            sig = w.signal(role)
            if sig is not None:
                kind, index, _ = sig
                lo, hi = w.range(role)
                measures.append((i, kind, index, lo, hi))
        self._measures = tuple(measures)
        # Analog inputs the source drives (bit k: standard analog input k), for the controller's domain bits.
        self.analog_in_mask = sum(1 << k for _, kind, k, _, _ in measures if kind == "ai")
        p, o, n = options.p_flange_wire, options.p_base_plane, options.n_base_plane
        self._geometry = (*p, *o, *n) if p is not None and o is not None and n is not None else None
        self._ctwd_nominal = tr.ctwd_nominal if tr.ctwd_nominal is not None else 0.0
        self._events = random.Random(f"{tr.seed}/events")
        self._noise = random.Random(f"{tr.seed}/noise")
        # Schedules of controller time (inf: none).
        self._fault_at = math.inf if tr.fault_at is None else tr.fault_at
        self._collision = (math.inf, math.inf) if tr.collision_at is None else (tr.collision_at, tr.collision_at + tr.collision_for)
        self._t = 0.0
        self._arc_start_was = False
        self._demand_was = False
        self._post_until = -math.inf
        self._quiet_since = 0.0  # when gas and arc_start were last both low
        self._fault_since = 0.0
        self._ignite_at = math.inf
        self._attempt = 0  # start attempts in this weld
        self._arc_time = 0.0  # arc time in this weld, s
        self._loss_at = math.inf  # the arc time of this weld's next arc loss
        self._sticks = False  # this weld ends in a stuck wire
        self._stuck_until = math.inf
        self.weld = 0
        self.ready = False
        self.arc_stable = False
        self.process_active = False
        self.wire_stuck = False
        self.fault = False
        self.collision = False
        self.heartbeat = False
        self.arc_on = False
        self.current = 0.0
        self.voltage = 0.0

    @staticmethod
    def _setpoint_plan(w: PowerSourceConfig, role: str) -> tuple[int, int, float, float]:
        """(0 not wired / 1 analog output / 2 double register, index, value at 0 V, value at 10 V)."""
        sig = w.signal(role)
        if sig is None:
            return 0, 0, 0.0, 0.0
        kind, index, _ = sig
        lo, hi = w.range(role)
        return (1 if kind == "ao" else 2), index, lo, hi

    # --- geometry -------------------------------------------------------------------

    def ctwd(self, T_base_flange: Sequence[float]) -> float:
        """The CTWD with the flange at ``T_base_flange`` (12 row-major floats of the 3x4 pose), m:
        the wire end's height over the work plane, or the nominal without a wire end and plane."""
        g = self._geometry
        if g is None:
            return self._ctwd_nominal
        px, py, pz, ox, oy, oz, nx, ny, nz = g
        T = T_base_flange
        x = T[0] * px + T[1] * py + T[2] * pz + T[3]
        y = T[4] * px + T[5] * py + T[6] * pz + T[7]
        z = T[8] * px + T[9] * py + T[10] * pz + T[11]
        return (x - ox) * nx + (y - oy) * ny + (z - oz) * nz

    # --- the cycle ------------------------------------------------------------------

    def step(
        self,
        t: float,
        digital_out: int,
        in_int: Sequence[int],
        in_double: Sequence[float],
        analog_out: Sequence[float],
        T_base_flange: Sequence[float],
    ) -> None:
        """Advance to controller time ``t`` (s) with the controller's outputs as they are now.

        ``digital_out``: bits 0-7 standard, 8-15 configurable, 16-17 tool;
        ``in_int``, ``in_double``: the input registers; ``analog_out``: the
        standard analog outputs as ratios of their span (as ur-rtde writes
        them); ``T_base_flange``: the physical flange, 12 row-major floats.
        """
        tr = self.truth
        dt = t - self._t
        self._t = t
        now = t + _SLACK  # for "has the moment come" (t itself stamps the moments this step sets)
        booted = now >= tr.boot
        arc_start = self._read(self._arc_start, digital_out, in_int)
        gas = self._read(self._gas, digital_out, in_int)
        robot_ready = self._robot_ready is None or self._read(self._robot_ready, digital_out, in_int)
        demand = arc_start or gas
        if self._demand_was and not demand:
            self._quiet_since = t
            self._post_until = t + tr.post_flow
        self._demand_was = demand
        if now >= self._fault_at:
            self._fault_at = math.inf
            self.fault = True
            self._fault_since = t
            self._arc_out()
        elif self.fault and not demand and now - max(self._quiet_since, self._fault_since) >= FAULT_RESET:
            self.fault = False
        self.collision = self._collision[0] <= now < self._collision[1]
        active = booted and (demand or now < self._post_until)
        if active and not self.process_active:
            self._begin_weld()
        self.process_active = active
        self.ready = booted and not self.fault
        if arc_start and not self._arc_start_was:
            if self.ready and robot_ready and not self.wire_stuck:
                self._start(t)
        elif self._arc_start_was and not arc_start:
            if self.arc_on and self._sticks:
                self._sticks = False  # one stick per weld
                self.wire_stuck = True
                self._stuck_until = t + self._events.uniform(*tr.stuck_clear)
            self._arc_out()
        self._arc_start_was = arc_start
        if not robot_ready and (self.arc_on or self._ignite_at < math.inf):
            self._arc_out()  # robot ready dropped: the source stops welding
        if self.arc_on:
            self._arc_time += dt
            if self._arc_time + _SLACK >= self._loss_at:
                self._arc_out()
                self._loss_at = self._arc_time + self._events.expovariate(tr.arc_loss_rate) if tr.arc_loss_rate > 0.0 else math.inf
        elif now >= self._ignite_at:
            self._ignite_at = math.inf
            self.arc_on = True
        self.arc_stable = self.arc_on
        if self.wire_stuck and now >= self._stuck_until:
            self.wire_stuck = False
            self._stuck_until = math.inf
        self.heartbeat = booted and (int((now - tr.boot) / HEARTBEAT_HALF_PERIOD) & 1) == 1
        if self.arc_on:
            d = self.ctwd(T_base_flange) - self._ctwd_nominal
            feed = self._setpoint(0, JOB_WIRE_FEED, in_double, analog_out)
            u_set = self._setpoint(1, JOB_VOLTAGE, in_double, analog_out)
            current = tr.current_base + tr.current_per_feed * feed - tr.current_per_ctwd * d
            voltage = u_set + tr.voltage_per_ctwd * d
            if tr.current_noise:
                current += self._noise.gauss(0.0, tr.current_noise)
            if tr.voltage_noise:
                voltage += self._noise.gauss(0.0, tr.voltage_noise)
            self.current = current if current > 0.0 else 0.0
            self.voltage = voltage if voltage > 0.0 else 0.0
        else:
            self.current = 0.0
            self.voltage = tr.open_circuit_voltage if arc_start and self.ready else 0.0

    @staticmethod
    def _read(where: tuple[int, int] | None, digital_out: int, in_int: Sequence[int]) -> bool:
        if where is None:
            return False
        reg, bit = where
        return bool((digital_out if reg < 0 else in_int[reg]) >> bit & 1)

    def _setpoint(self, i: int, default: float, in_double: Sequence[float], analog_out: Sequence[float]) -> float:
        how, k, lo, hi = self._setpoints[i]
        if how == 0:
            return default
        if how == 2:
            return float(in_double[k])
        ratio = analog_out[k]
        ratio = 0.0 if ratio < 0.0 else 1.0 if ratio > 1.0 else ratio
        return lo + ratio * (hi - lo)

    def _begin_weld(self) -> None:
        """A weld begins (process_active rises): its number and its schedule."""
        tr = self.truth
        ev = self._events
        self.weld += 1
        self._attempt = 0
        self._arc_time = 0.0
        # Both draws are made whatever the rates, so that a forced schedule leaves the drawn ones where they were.
        sticks = ev.random() < tr.stuck_wire_rate
        loss = ev.expovariate(tr.arc_loss_rate) if tr.arc_loss_rate > 0.0 else math.inf
        self._sticks = sticks or (tr.stuck_every > 0 and self.weld % tr.stuck_every == 0)
        self._loss_at = tr.arc_loss_after if tr.arc_loss_after is not None else loss

    def _start(self, t: float) -> None:
        """A start attempt at ``t``: the arc ignites after a drawn delay, unless this attempt fails."""
        tr = self.truth
        ev = self._events
        self._attempt += 1
        fails = ev.random() < tr.failed_start_rate or (self._attempt == 1 and tr.fail_first_start)
        delay = ev.uniform(*tr.ignition_delay)
        self._ignite_at = math.inf if fails else t + delay

    def _arc_out(self) -> None:
        self.arc_on = False
        self.arc_stable = False
        self._ignite_at = math.inf

    # --- the wires into the controller ----------------------------------------------

    def write(self, digital_in: int, out_int: list[int], out_double: list[float], analog_in: list[float]) -> int:
        """Drive the controller's inputs: the source's register bits into ``out_int``, its measures into
        ``out_double`` or ``analog_in`` (V, 0-10), and the new ``digital_in`` word returned (bits the
        source does not drive kept)."""
        # In the order of INPUT_ROLES, which the plans index.
        v = (self.ready, self.arc_stable, self.process_active, self.wire_stuck, self.fault, self.collision, self.heartbeat)
        bits = 0
        for i, bit in self._din:
            if v[i]:
                bits |= 1 << bit
        for reg, mask, plan in self._oreg:
            word = out_int[reg] & ~mask
            for i, bit in plan:
                if v[i]:
                    word |= 1 << bit
            out_int[reg] = _signed32(word)
        m = (self.current, self.voltage)
        for i, kind, k, lo, hi in self._measures:
            if kind == "odreg":
                out_double[k] = m[i]
            else:
                volts = ANALOG_SPAN_V * (m[i] - lo) / (hi - lo)
                analog_in[k] = 0.0 if volts < 0.0 else ANALOG_SPAN_V if volts > ANALOG_SPAN_V else volts
        return (digital_in & ~self.digital_in_mask) | bits

    def status(self) -> dict[str, Any]:
        """The source's state for the simulator's status reply."""
        return {
            "weld": self.weld,
            "ready": self.ready,
            "arc_on": self.arc_on,
            "process_active": self.process_active,
            "wire_stuck": self.wire_stuck,
            "fault": self.fault,
            "collision": self.collision,
            "current": self.current,
            "voltage": self.voltage,
        }
