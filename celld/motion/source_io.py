"""The welding power source's signals through ur-rtde, as the cell's ``[power_source]`` wires them.

:class:`SourceIO` reads the source's inputs once a cycle from the receive
interface (the variables it needs are subscribed when the link opens:
:meth:`SourceIO.variables`) and writes the cell's outputs through the IO
interface, each only when it changes (a write is a round trip to the
controller). A digital output or register bit is written with
``setStandardDigitalOut`` / ``setConfigurableDigitalOut`` /
``setToolDigitalOut`` / ``setInputIntRegister`` (the whole word of the roles
that share a register), an analog set point with ``setAnalogOutputVoltage``
(a ratio of the 0-10 V span over the role's range) or ``setInputDoubleRegister``
(SI). A write that fails is retried every cycle; :meth:`SourceIO.release`
switches every output off and every set point to zero.

The source's inputs are active high; a wire that is not configured reads as
False (``ready`` is always wired).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from celld.config.power_source import ANALOG_SPAN_V, PowerSourceConfig, Signal
from celld.motion.arc import ArcOutput, SourceSignals

# Offsets of the configurable and tool bits in actual_digital_input_bits / actual_digital_output_bits.
_BIT_BASE = {"do": 0, "cdo": 8, "tdo": 16, "di": 0, "cdi": 8, "tdi": 16}
# The order of the input roles in SourceReading.bits.
BIT_ROLES = ("ready", "arc_stable", "process_active", "wire_stuck", "fault", "collision", "heartbeat")


class SourceReading(NamedTuple):
    """The source's inputs of one cycle."""

    signals: SourceSignals
    collision: bool
    current: float  # A, NaN when not wired
    voltage: float  # V, NaN when not wired
    bits: int  # the input roles as bits, in BIT_ROLES order (for the state record)


class SourceIO:
    """The source's wiring on one ur-rtde link (module docstring)."""

    def __init__(self, config: PowerSourceConfig) -> None:
        self.config = config
        # The wiring by role, and the output registers read, once (PowerSourceConfig.signal builds a dict per call).
        self._signals: dict[str, Signal] = dict(config.signals)
        self._out_registers = tuple(dict.fromkeys(sig.number for sig in self._signals.values() if sig.kind == "oreg"))
        self._last_out: ArcOutput | None = None  # the last output written in full (None: owed, or a write failed)
        self._receive: Any = None
        self._io: Any = None
        self._readers: list[tuple[int, Callable[[], bool]]] = []
        self._current: Callable[[], float] | None = None
        self._voltage: Callable[[], float] | None = None
        self._digital_in = False
        self._in_bits = 0
        self._regs: dict[int, int] = {}
        # What was last written, by role (None: never written, or the write failed).
        self._written: dict[str, bool | float | None] = {}
        self.write_error = ""  # the first failure since the last success, "" when none

    def variables(self) -> tuple[str, ...]:
        """The RTDE output variables the receive interface must subscribe to for the wired inputs."""
        names: list[str] = []
        for _role, sig in self.config.signals:
            if sig.kind in ("di", "cdi", "tdi"):
                names.append("actual_digital_input_bits")
            elif sig.kind == "oreg":
                names.append(f"output_int_register_{sig.number}")
            elif sig.kind == "ai":
                names.append(f"standard_analog_input{sig.number}")
            elif sig.kind == "odreg":
                names.append(f"output_double_register_{sig.number}")
        return tuple(dict.fromkeys(names))

    def attach(self, receive: Any, io: Any) -> None:
        """Bind to a link's ur-rtde receive and IO interfaces."""
        self._receive, self._io = receive, io
        self._readers = []
        for k, role in enumerate(BIT_ROLES):
            sig = self._signals.get(role)
            if sig is not None:
                self._readers.append((k, self._digital_reader(sig)))
        self._digital_in = any(sig.kind in ("di", "cdi", "tdi") for _, sig in self.config.signals)
        self._current = self._analog_reader("current")
        self._voltage = self._analog_reader("voltage")

    def _digital_reader(self, sig: Signal) -> Callable[[], bool]:
        if sig.kind == "oreg":
            number, bit = sig.number, sig.bit
            return lambda: bool(self._regs[number] >> bit & 1)
        shift = _BIT_BASE[sig.kind] + sig.number
        return lambda: bool(self._in_bits >> shift & 1)

    def _analog_reader(self, role: str) -> Callable[[], float] | None:
        sig = self._signals.get(role)
        if sig is None:
            return None
        r = self._receive
        if sig.kind == "odreg":
            number = sig.number
            return lambda: float(r.getOutputDoubleRegister(number))
        lo, hi = self.config.range(role)
        get = r.getStandardAnalogInput0 if sig.number == 0 else r.getStandardAnalogInput1
        return lambda: lo + (hi - lo) * float(get()) / ANALOG_SPAN_V

    def read(self) -> SourceReading:
        """The source's inputs now (the receive interface's latest package)."""
        r = self._receive
        if self._digital_in:
            self._in_bits = int(r.getActualDigitalInputBits())
        for number in self._out_registers:
            self._regs[number] = int(r.getOutputIntRegister(number))
        bits = 0
        for k, get in self._readers:
            if get():
                bits |= 1 << k
        current = self._current() if self._current is not None else float("nan")
        voltage = self._voltage() if self._voltage is not None else float("nan")
        b = [bool(bits >> k & 1) for k in range(len(BIT_ROLES))]
        return SourceReading(SourceSignals(b[0], b[1], b[2], b[3], b[4], b[6]), b[5], current, voltage, bits)

    # -- outputs -------------------------------------------------------------------------------------------

    def write(self, out: ArcOutput) -> bool:
        """Write what changed of ``out`` (robot ready held high); False when a write failed (retried at the next
        call). An output like the last one written in full costs nothing: most cycles."""
        if out == self._last_out:
            return True
        ok = self._apply(
            {"arc_start": out.arc_start, "gas": out.gas, "robot_ready": True, "wire_feed": out.wire_feed, "voltage_set": out.voltage}
        )
        self._last_out = out if ok else None
        return ok

    def release(self) -> bool:
        """Every output off, every set point zero (after the loop ended); never raises."""
        self._written = {}
        self._last_out = None
        return self._apply({"arc_start": False, "gas": False, "robot_ready": False, "wire_feed": 0.0, "voltage_set": 0.0})

    def left_on(self, digital_outputs: int) -> bool:
        """Whether the arc_start output is on in ``digital_outputs`` (actual_digital_output_bits) before any write."""
        sig = self._signals.get("arc_start")
        if sig is None or sig.kind == "ireg":
            return False
        return bool(digital_outputs >> (_BIT_BASE[sig.kind] + sig.number) & 1)

    def _apply(self, wanted: dict[str, bool | float]) -> bool:
        ok = True
        words: dict[int, int] = {}
        dirty_words: set[int] = set()
        for role, value in wanted.items():
            sig = self._signals.get(role)
            if sig is None:
                continue
            if sig.kind == "ireg":
                words.setdefault(sig.number, 0)
                if value:
                    words[sig.number] |= 1 << sig.bit
                if self._written.get(role) != value:
                    dirty_words.add(sig.number)
                continue
            if self._written.get(role) == value:
                continue
            done = self._send(sig, role, value)
            self._written[role] = value if done else None
            ok = ok and done
        for number in dirty_words:
            done = self._send_word(number, words[number])
            for role, value in wanted.items():
                sig = self._signals.get(role)
                if sig is not None and sig.kind == "ireg" and sig.number == number:
                    self._written[role] = value if done else None
            ok = ok and done
        if ok:
            self.write_error = ""
        return ok

    def _send(self, sig: Signal, role: str, value: bool | float) -> bool:
        io = self._io
        try:
            if sig.kind == "do":
                return bool(io.setStandardDigitalOut(sig.number, bool(value)))
            if sig.kind == "cdo":
                return bool(io.setConfigurableDigitalOut(sig.number, bool(value)))
            if sig.kind == "tdo":
                return bool(io.setToolDigitalOut(sig.number, bool(value)))
            if sig.kind == "dreg":
                return bool(io.setInputDoubleRegister(sig.number, float(value)))
            lo, hi = self.config.range(role)
            ratio = min(max((float(value) - lo) / (hi - lo), 0.0), 1.0)
            return bool(io.setAnalogOutputVoltage(sig.number, ratio))
        except Exception as exc:  # ur-rtde raises RuntimeError on a dead link; the loop must not die of it  # noqa: BLE001
            self.write_error = self.write_error or f"power source {role} ({sig}): {exc}"
            return False

    def _send_word(self, number: int, word: int) -> bool:
        try:
            return bool(self._io.setInputIntRegister(number, word))
        except Exception as exc:  # noqa: BLE001 (as _send)
            self.write_error = self.write_error or f"power source register ireg{number}: {exc}"
            return False


def source_state(record: np.void | None) -> dict[str, bool | float] | None:
    """The power source's inputs in a motion state record (STATE_DTYPE), by role; None when the record has none."""
    if record is None or int(record["arc_phase"]) < 0:
        return None
    bits = int(record["source_bits"])
    out: dict[str, bool | float] = {role: bool(bits >> k & 1) for k, role in enumerate(BIT_ROLES)}
    out["current_a"] = float(record["weld_current"])
    out["voltage_v"] = float(record["weld_voltage"])
    return out


def source_problem(state: dict[str, bool | float]) -> str:
    """Why the source cannot weld now ("" when it can)."""
    if state["fault"]:
        return "the power source reports a fault: clear it at the source first"
    if state["wire_stuck"]:
        return "the power source says the wire is stuck: cut the wire first"
    if not state["ready"]:
        return "the power source is not ready (its ready signal is low)"
    if state["collision"]:
        return "the torch's collision input is set: reseat the torch first"
    return ""
