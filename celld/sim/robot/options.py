"""Options of the simulated controller: one frozen value, its command line, its checks.

The same options reach the simulator from ``celld sim robot``, from
``python -m celld.sim.robot`` (what :func:`celld.sim.robot.launch` starts) and
from test fixtures; :func:`add_arguments` and :meth:`SimOptions.to_argv` keep
the three in step.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

from celld.errors import ConfigError, InputError
from celld.robot import kinematics as kin
from celld.sim.robot.source import SourceOptions
from celld.sim.robot.truearm import ArmTruth

# UR ports: dashboard, primary/secondary/real-time script interfaces, RTDE.
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
RTDE_PORT = 30004
# The simulator's own JSON-lines control endpoint (faults, teleport, status).
CONTROL_PORT = 30100

_SOURCE = "sim robot options"


@dataclass(frozen=True)
class SimOptions:
    """What the simulated UR10e controller is and allows (SI units)."""

    host: str = "127.0.0.2"
    # The UR model the controller is (its nominal DH table and joint limits).
    model: str = "ur10e"
    # How the physical arm differs from the controller's model (celld.sim.world
    # draws it); None: the arm is the model exactly.
    arm: ArmTruth | None = None
    # The DH table the controller computes with, its model's published one plus
    # its factory calibration (celld.sim.world draws it; it is served on the
    # primary interface, port 30001); None: the published table.
    kinematics: kin.DH | None = None
    # Initial joint vector, rad.
    q0: tuple[float, ...] = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)
    # TCP in the flange frame, UR pose [x, y, z, rx, ry, rz].
    tcp_offset: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    # Safety workspace box of the TCP in the base frame, m.
    workspace_min: tuple[float, float, float] = (-1.4, -1.4, -0.2)
    workspace_max: tuple[float, float, float] = (1.4, 1.4, 1.6)
    # Safety limit of the TCP speed, m/s (UR default, normal mode).
    tcp_speed_limit: float = 1.5
    # Planner limits: TCP acceleration (m/s^2) and joint acceleration (rad/s^2).
    tcp_acc_limit: float = 15.0
    joint_acc_limit: float = 40.0
    # A protective stop cannot be unlocked sooner than this, s (the controller says 5 s).
    unlock_delay: float = 5.0
    # Robot mode at start: "running" (powered, brakes released) or "power_off".
    boot: str = "running"
    # Controller version reported on RTDE and the dashboard.
    version: tuple[int, int, int, int] = (5, 11, 6, 1123438)
    serial_number: str = "20235500123"
    # Publish the true state in shared memory (see celld.sim.robot.truth).
    truth: bool = True
    # Run the tick at SCHED_FIFO where the OS allows it.
    realtime: bool = False
    # Exit when this process dies (set by the launcher), 0 for never.
    parent_pid: int = 0
    # Text messages to RTDE clients: script errors, watchdog, protective stops.
    text_messages: bool = True
    # The I/O set-up "standard outputs go low when the program stops" (on in a
    # correctly set-up cell: it is the arc's interlock); False keeps them.
    outputs_low_at_stop: bool = True
    # The teach pendant in Remote Control (as celld needs it); False: in Local Control, where an e-Series
    # controller takes no URScript from the network: it closes every connection to 30001-30003, and its
    # dashboard says "false" to "is in remote control".
    remote_control: bool = True
    # A welding power source on the controller's I/O: its wiring, the CTWD's geometry and
    # its behaviour (celld.sim.robot.source; celld.sim.cell fills it); None: nothing is wired.
    power_source: SourceOptions | None = None

    def __post_init__(self) -> None:
        check_host(self.host)
        if self.model not in kin.MODELS:
            raise ConfigError(_SOURCE, "model", f"expected one of {', '.join(kin.MODELS)}, got {self.model!r}")
        if self.arm is not None and not isinstance(self.arm, ArmTruth):
            raise ConfigError(_SOURCE, "arm", f"expected an ArmTruth or None, got {type(self.arm).__name__}")
        if self.power_source is not None and not isinstance(self.power_source, SourceOptions):
            raise ConfigError(_SOURCE, "power_source", f"expected a SourceOptions or None, got {type(self.power_source).__name__}")
        if self.kinematics is not None:
            rows = tuple(self.kinematics)
            if len(rows) != 4 or any(len(r) != 6 for r in rows) or not all(math.isfinite(v) for r in rows for v in r):
                raise ConfigError(_SOURCE, "kinematics", f"expected a DH table of 6 joints (d, a, alpha, theta), got {rows}")
        _check_vector("q0", self.q0, 6)
        _check_vector("tcp_offset", self.tcp_offset, 6)
        _check_vector("workspace_min", self.workspace_min, 3)
        _check_vector("workspace_max", self.workspace_max, 3)
        if not all(a < b for a, b in zip(self.workspace_min, self.workspace_max)):
            raise ConfigError(
                _SOURCE,
                "workspace_max",
                f"expected every value above workspace_min {self.workspace_min}, got {self.workspace_max}",
            )
        for name, lo, hi in (
            ("tcp_speed_limit", 0.01, 5.0),
            ("tcp_acc_limit", 0.1, 200.0),
            ("joint_acc_limit", 0.1, 200.0),
            ("unlock_delay", 0.0, 60.0),
        ):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and lo <= value <= hi):
                raise ConfigError(_SOURCE, name, f"expected a number in [{lo}, {hi}], got {value!r}")
        if self.boot not in ("running", "power_off"):
            raise ConfigError(_SOURCE, "boot", f"expected 'running' or 'power_off', got {self.boot!r}")
        if len(self.version) != 4 or self.version[0] < 5:
            raise ConfigError(_SOURCE, "version", f"expected a 5.x version of 4 numbers, got {self.version}")
        if not self.serial_number.isdigit():
            raise ConfigError(_SOURCE, "serial_number", f"expected digits only, got {self.serial_number!r}")

    def with_(self, **changes: Any) -> SimOptions:
        """A copy with ``changes`` applied (and checked)."""
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            known = sorted(f.name for f in fields(self))
            raise ConfigError(_SOURCE, sorted(unknown)[0], f"unknown option; expected one of {known}")
        return replace(self, **changes)

    def to_argv(self) -> list[str]:
        """Command-line arguments that :func:`from_args` turns back into these options."""
        argv = ["--host", self.host, "--model", self.model]
        if self.arm is not None:
            argv += ["--arm-truth", self.arm.to_json()]
        if self.kinematics is not None:
            argv += ["--kinematics", json.dumps(kin.dh_as_dict(self.kinematics))]
        if self.power_source is not None:
            argv += ["--power-source", self.power_source.to_json()]
        argv += ["--q0", *map(repr, self.q0), "--tcp-offset", *map(repr, self.tcp_offset)]
        argv += ["--workspace", *map(repr, self.workspace_min), *map(repr, self.workspace_max)]
        argv += ["--tcp-speed-limit", repr(self.tcp_speed_limit), "--tcp-acc-limit", repr(self.tcp_acc_limit)]
        argv += ["--joint-acc-limit", repr(self.joint_acc_limit), "--unlock-delay", repr(self.unlock_delay)]
        argv += ["--boot", self.boot, "--version-number", ".".join(map(str, self.version))]
        argv += ["--serial-number", self.serial_number, "--parent-pid", str(self.parent_pid)]
        if not self.truth:
            argv.append("--no-truth")
        if self.realtime:
            argv.append("--realtime")
        if not self.text_messages:
            argv.append("--no-text-messages")
        if not self.outputs_low_at_stop:
            argv.append("--keep-outputs-at-stop")
        if not self.remote_control:
            argv.append("--local-control")
        return argv


def check_host(host: str) -> str:
    """Return ``host`` if it is an IPv4 loopback address, else raise ConfigError."""
    try:
        addr = ipaddress.IPv4Address(host)
    except ValueError as exc:
        raise ConfigError(_SOURCE, "host", f"expected an IPv4 address 127.x.y.z, got {host!r}") from exc
    if not addr.is_loopback:
        raise ConfigError(_SOURCE, "host", f"the simulator binds loopback only (127.0.0.0/8), got {host}")
    return host


def _check_vector(name: str, value: Sequence[float], n: int) -> None:
    if len(value) != n or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value):
        raise ConfigError(_SOURCE, name, f"expected {n} finite numbers, got {list(value)}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulator's options as command-line arguments (defaults from :class:`SimOptions`)."""
    d = SimOptions()
    parser.add_argument("--host", required=True, help="loopback address to bind, 127.x.y.z")
    parser.add_argument("--model", default=d.model, choices=sorted(kin.MODELS), help="the UR model the controller is")
    parser.add_argument(
        "--arm-truth",
        default=None,
        metavar="JSON",
        help="how the physical arm differs from the controller's model (celld.sim.robot.truearm.ArmTruth as JSON)",
    )
    parser.add_argument(
        "--kinematics",
        default=None,
        metavar="JSON",
        help="the DH table the controller computes with ({d, a, alpha, theta}, 6 numbers each; default: the model's)",
    )
    parser.add_argument(
        "--power-source",
        default=None,
        metavar="JSON",
        help="a welding power source on the I/O: wiring, CTWD geometry, behaviour (celld.sim.robot.source.SourceOptions as JSON)",
    )
    parser.add_argument("--q0", nargs=6, type=float, default=d.q0, metavar="RAD", help="initial joints")
    parser.add_argument("--tcp-offset", nargs=6, type=float, default=d.tcp_offset, metavar="V", help="TCP pose in the flange [m, rad]")
    parser.add_argument(
        "--workspace", nargs=6, type=float, default=(*d.workspace_min, *d.workspace_max),
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"), help="safety box of the TCP in the base frame, m",
    )  # fmt: skip
    parser.add_argument("--tcp-speed-limit", type=float, default=d.tcp_speed_limit, help="m/s; above it: protective stop")
    parser.add_argument("--tcp-acc-limit", type=float, default=d.tcp_acc_limit, help="planner limit, m/s^2")
    parser.add_argument("--joint-acc-limit", type=float, default=d.joint_acc_limit, help="planner limit, rad/s^2")
    parser.add_argument("--unlock-delay", type=float, default=d.unlock_delay, help="s before a protective stop can be unlocked")
    parser.add_argument("--boot", choices=("running", "power_off"), default=d.boot)
    parser.add_argument("--version-number", default=".".join(map(str, d.version)), help="controller version a.b.c.d")
    parser.add_argument("--serial-number", default=d.serial_number)
    parser.add_argument("--no-truth", action="store_true", help="do not publish the true state in shared memory")
    parser.add_argument("--realtime", action="store_true", help="run the tick at SCHED_FIFO where allowed")
    parser.add_argument("--no-text-messages", action="store_true", help="send no RTDE text messages")
    parser.add_argument(
        "--keep-outputs-at-stop",
        action="store_true",
        help="model a cell whose standard outputs stay as they are when the program stops (no arc interlock)",
    )
    parser.add_argument("--local-control", action="store_true", help="the teach pendant in Local Control: no URScript from the network")
    parser.add_argument("--parent-pid", type=int, default=0, help=argparse.SUPPRESS)


def from_args(args: argparse.Namespace) -> SimOptions:
    """:class:`SimOptions` of parsed :func:`add_arguments` arguments."""
    try:
        version = tuple(int(v) for v in args.version_number.split("."))
    except ValueError as exc:
        raise ConfigError(_SOURCE, "version", f"expected a.b.c.d, got {args.version_number!r}") from exc
    arm = ArmTruth.from_json(args.arm_truth) if args.arm_truth else None
    source = SourceOptions.from_json(args.power_source) if args.power_source else None
    table = None
    if args.kinematics:
        try:
            table = kin.dh_from_dict(json.loads(args.kinematics), "kinematics")
        except (ValueError, InputError) as exc:
            raise ConfigError(_SOURCE, "kinematics", f"expected a JSON object of d, a, alpha, theta: {exc}") from exc
    return SimOptions(
        host=args.host,
        model=args.model,
        arm=arm,
        kinematics=table,
        q0=tuple(args.q0),
        tcp_offset=tuple(args.tcp_offset),
        workspace_min=tuple(args.workspace[:3]),
        workspace_max=tuple(args.workspace[3:]),
        tcp_speed_limit=args.tcp_speed_limit,
        tcp_acc_limit=args.tcp_acc_limit,
        joint_acc_limit=args.joint_acc_limit,
        unlock_delay=args.unlock_delay,
        boot=args.boot,
        version=version,  # type: ignore[arg-type]
        serial_number=args.serial_number,
        truth=not args.no_truth,
        realtime=args.realtime,
        parent_pid=args.parent_pid,
        text_messages=not args.no_text_messages,
        outputs_low_at_stop=not args.keep_outputs_at_stop,
        remote_control=not args.local_control,
        power_source=source,
    )
