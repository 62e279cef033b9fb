"""The welding power source on the robot's I/O: which signal is wired where (``[power_source]``).

A source is driven through the UR's control box (digital and analog I/O) or
through a fieldbus gateway the robot program maps onto RTDE registers. Each
role names one signal:

=========  ===============================================  ======================
signal     what it is                                       roles
=========  ===============================================  ======================
``doN``    standard digital output N (0-7)                  arc_start, gas,
``cdoN``   configurable digital output N (0-7)              robot_ready
``tdoN``   tool digital output N (0-1)
``iregN.B``  bit B (0-31) of input int register N (18-22)
``diN``    standard digital input N (0-7)                   ready, arc_stable,
``cdiN``   configurable digital input N (0-7)               process_active,
``tdiN``   tool digital input N (0-1)                       wire_stuck, fault,
``oregN.B``  bit B of output int register N (12-23)         collision, heartbeat
``aoN``    standard analog output N (0-1), 0-10 V           wire_feed, voltage_set
``dregN``  input double register N (18-22)
``aiN``    standard analog input N (0-1), 0-10 V            current, voltage
``odregN`` output double register N (12-23)
=========  ===============================================  ======================

"Input" and "output" registers are the controller's: the cell writes input
registers (ur-rtde's IO interface writes 18-22 in its lower range) and reads
output registers, which the robot program fills from the gateway (ur-rtde's
control script answers in the registers below 12). An analog signal on the
control box carries its quantity linearly over 0-10 V (``*_range``: the values
at 0 V and at 10 V, SI); a register carries it in SI as it is.

Inputs are active high. ``arc_start`` (the source's "welding start") and
``ready`` and ``arc_stable`` are required; the rest may be left out, and the
sequence does without what it is not given (no ``process_active``: post-flow is
timed alone; no ``wire_stuck``: the check after arc off is not made, which the
daemon says at its start).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

from celld.config.reader import TableReader

# Signal kinds by direction.
DIGITAL_OUT_KINDS = ("do", "cdo", "tdo", "ireg")
DIGITAL_IN_KINDS = ("di", "cdi", "tdi", "oreg")
ANALOG_OUT_KINDS = ("ao", "dreg")
ANALOG_IN_KINDS = ("ai", "odreg")
# The register numbers each kind may name.
_INDEX_RANGE = {
    "do": (0, 7), "cdo": (0, 7), "tdo": (0, 1), "di": (0, 7), "cdi": (0, 7), "tdi": (0, 1),
    "ao": (0, 1), "ai": (0, 1), "ireg": (18, 22), "dreg": (18, 22), "oreg": (12, 23), "odreg": (12, 23),
}  # fmt: skip
_SIGNAL = re.compile(r"^(do|cdo|tdo|di|cdi|tdi|ao|ai|ireg|oreg|dreg|odreg)(\d{1,2})(?:\.(\d{1,2}))?$")
# The control box's analog span, V.
ANALOG_SPAN_V = 10.0

# The roles, by direction; the first ones of each are required.
OUTPUT_ROLES = ("arc_start", "gas", "robot_ready")
INPUT_ROLES = ("ready", "arc_stable", "process_active", "wire_stuck", "fault", "collision", "heartbeat")
SETPOINT_ROLES = ("wire_feed", "voltage_set")
MEASURE_ROLES = ("current", "voltage")
_REQUIRED = ("arc_start", "ready", "arc_stable")
# Default spans over 0-10 V: wire feed 0-25 m/min, voltage 0-50 V, current 0-500 A (SI: m/s, V, A).
_DEFAULT_RANGE = {"wire_feed": (0.0, 25.0 / 60.0), "voltage_set": (0.0, 50.0), "current": (0.0, 500.0), "voltage": (0.0, 50.0)}


class Signal(NamedTuple):
    """One wire or register bit: ``kind`` (see the module table), its ``number``, ``bit`` (-1: not a register bit)."""

    kind: str
    number: int
    bit: int = -1

    def __str__(self) -> str:
        return f"{self.kind}{self.number}" + (f".{self.bit}" if self.bit >= 0 else "")


def parse_signal(text: str, kinds: tuple[str, ...]) -> Signal:
    """``text`` as a :class:`Signal` of one of ``kinds``; ValueError naming what is wrong."""
    m = _SIGNAL.match(text)
    if not m:
        raise ValueError(f"expected a signal such as {kinds[0]}0 ({', '.join(kinds)}), got {text!r}")
    kind, index = m.group(1), int(m.group(2))
    bit = int(m.group(3)) if m.group(3) is not None else -1
    if kind not in kinds:
        raise ValueError(f"{text!r} is a {kind} signal; this role takes {', '.join(kinds)}")
    lo, hi = _INDEX_RANGE[kind]
    if not lo <= index <= hi:
        raise ValueError(f"{text!r}: {kind} numbers run {lo}-{hi}")
    if kind in ("ireg", "oreg"):
        if bit < 0 or bit > 31:
            raise ValueError(f"{text!r}: a register signal names its bit, {kind}{index}.0 to {kind}{index}.31")
    elif bit >= 0:
        raise ValueError(f"{text!r}: only ireg and oreg signals have a bit")
    return Signal(kind, index, bit)


@dataclass(frozen=True)
class PowerSourceConfig:
    """Where each of the source's signals is wired (module docstring); ``signals`` by role."""

    signals: tuple[tuple[str, Signal], ...] = ()
    # For the analog signals on the control box: (value at 0 V, value at 10 V), SI.
    ranges: tuple[tuple[str, tuple[float, float]], ...] = ()
    # The source's heartbeat must change at least this often while a weld runs, s (with a heartbeat input).
    heartbeat_timeout: float = 2.5

    @property
    def enabled(self) -> bool:
        return bool(self.signals)

    def signal(self, role: str) -> Signal | None:
        return dict(self.signals).get(role)

    def range(self, role: str) -> tuple[float, float]:
        return dict(self.ranges).get(role, _DEFAULT_RANGE.get(role, (0.0, 1.0)))

    @classmethod
    def read(cls, r: TableReader) -> PowerSourceConfig:
        if not any(r.has(role) for role in OUTPUT_ROLES + INPUT_ROLES + SETPOINT_ROLES + MEASURE_ROLES):
            return cls()  # no source (keys of none of its roles are refused as unknown)
        signals: list[tuple[str, Signal]] = []
        for roles, kinds in (
            (OUTPUT_ROLES, DIGITAL_OUT_KINDS),
            (INPUT_ROLES, DIGITAL_IN_KINDS),
            (SETPOINT_ROLES, ANALOG_OUT_KINDS),
            (MEASURE_ROLES, ANALOG_IN_KINDS),
        ):
            for role in roles:
                if not r.has(role):
                    if role in _REQUIRED:
                        raise r.error(role, f"a power source needs its {role} signal ({', '.join(kinds)})")
                    continue
                try:
                    signals.append((role, parse_signal(r.str(role), kinds)))
                except ValueError as exc:
                    raise r.error(role, str(exc)) from exc
        seen: dict[Signal, str] = {}
        for role, sig in signals:
            if sig in seen:
                raise r.error(role, f"{sig} is already {seen[sig]}'s signal: one wire, one role")
            seen[sig] = role
        ranges: list[tuple[str, tuple[float, float]]] = []
        for role in SETPOINT_ROLES + MEASURE_ROLES:
            key = f"{role}_range"
            if r.has(key):
                lo, hi = r.vector(key, 2)
                if lo == hi:
                    raise r.error(key, f"expected two different values (at 0 V and at {ANALOG_SPAN_V:g} V), got {lo} twice")
                ranges.append((role, (lo, hi)))
        return cls(tuple(signals), tuple(ranges), r.float("heartbeat_timeout_s", cls.heartbeat_timeout, lo=0.1, hi=60.0))
