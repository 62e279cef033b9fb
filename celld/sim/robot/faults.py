"""Fault injection: the faults the simulator can play, their arguments and checks (pure).

Faults reach the simulator on its control endpoint (JSON lines on
:data:`~celld.sim.robot.options.CONTROL_PORT`), from
:meth:`SimRobotHandle.inject` or ``celld sim fault``:

============== ======================== ==============================================
fault          arguments                effect
============== ======================== ==============================================
drop_rtde      down_ms=0                reset every RTDE connection; refuse new ones for down_ms
drop_all       down_ms=0                reset every connection (RTDE, dashboard, script)
stall          ms                       send no RTDE data packages for ms
latency        ms                       delay RTDE traffic both ways by ms (0 clears)
protective_stop                         protective stop, as the safety system would
estop                                   robot e-stop pressed: stop, program ends, power off
power_off                               arm powered off, program ends
refuse_upload                           programs sent to the script ports do not start
============== ======================== ==============================================

Dropped connections are reset (RST), as a link that breaks rather than one
the controller ends. Beware: with only the RTDE link dropped, ur-rtde 1.6.5's
RTDEControlInterface reconnects in an endless loop and crashes its process
(research/ur_rtde.md, section 5); play ``drop_all`` with ``down_ms`` of a few
seconds on a control interface, then call its ``reconnect()``. The receive
interface takes ``drop_rtde`` well.

``clear`` undoes what the simulator set: latency, stall, refused uploads,
links held down, a protective stop (at once; on the robot, and here too, the
dashboard's ``unlock protective stop`` clears it 5 s after it occurred) and
a pressed e-stop. An arm the fault powered off stays off: power it on and
release the brakes from the dashboard (``celld robot power-on``,
``brake-release``), as on the robot.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

from celld.errors import InputError

# Fault name -> its arguments and their upper bounds.
FAULTS: dict[str, dict[str, float]] = {
    "drop_rtde": {"down_ms": 600_000.0},
    "drop_all": {"down_ms": 600_000.0},
    "stall": {"ms": 600_000.0},
    "latency": {"ms": 10_000.0},
    "protective_stop": {},
    "estop": {},
    "power_off": {},
    "refuse_upload": {},
}
# Arguments that must be given.
_REQUIRED = {"stall": ("ms",), "latency": ("ms",)}


class Fault(NamedTuple):
    """A checked fault request: its name and arguments (ms values in milliseconds)."""

    name: str
    args: dict[str, float]


def parse_fault(name: str, args: dict[str, Any]) -> Fault:
    """Check a fault request; raise InputError naming what was expected and what came."""
    key = name.replace("-", "_")
    if key not in FAULTS:
        raise InputError(f"unknown fault {name!r}: expected one of {', '.join(sorted(FAULTS))}")
    allowed = FAULTS[key]
    unknown = set(args) - set(allowed)
    if unknown:
        expected = ", ".join(sorted(allowed)) or "no arguments"
        raise InputError(f"fault {key}: unknown argument {sorted(unknown)[0]!r}; expected {expected}")
    for required in _REQUIRED.get(key, ()):
        if required not in args:
            raise InputError(f"fault {key}: argument {required!r} is required")
    checked: dict[str, float] = {}
    for arg, hi in allowed.items():
        if arg not in args:
            continue
        value = args[arg]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not 0 <= value <= hi:
            raise InputError(f"fault {key}: {arg} must be a number in [0, {hi:g}] ms, got {value!r}")
        checked[arg] = float(value)
    return Fault(key, checked)
