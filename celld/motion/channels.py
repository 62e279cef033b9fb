"""The shared-memory channels between the main process and the motion process.

The main process (the supervisor) creates them once and keeps them across
restarts of the motion process, which attaches to them:

========== ============== ============================ =========================================
channel    kind           writer -> reader             holds
========== ============== ============================ =========================================
state      Ring           motion -> main               one :data:`STATE_DTYPE` record per cycle
events     Ring           motion -> main               why a command was refused or ended badly
commands   Mailbox        main -> motion               encoded commands (:mod:`.commands`)
setpoint   SeqlockSlot    main -> motion               the streamed twist
tactile    SeqlockSlot    tactile process -> motion    the latest TactileSample
control    SeqlockSlot    main -> motion               stop requests and shutdown
status     SeqlockSlot    motion -> main               phase, pid, real-time set-up, exit reason
========== ============== ============================ =========================================
"""

from __future__ import annotations

import os
import uuid
from enum import IntEnum
from typing import NamedTuple

import numpy as np

from celld.shm import Mailbox, Ring, SeqlockSlot
from celld.tactile.sample import TACTILE_DTYPE

# Room for reasons in the event and status records (UTF-8 bytes, truncated).
REASON_BYTES = 240
# Depth of the command mailbox and the largest command (a servo plan with its path).
MAILBOX_SLOTS = 8
MAILBOX_SLOT_BYTES = 1 << 20
EVENT_CAPACITY = 256

STATE_DTYPE = np.dtype(
    [
        ("cycle", np.uint64),  # cycle counter of this process
        ("t_ns", np.int64),  # wake-up time, monotonic
        ("late_ns", np.int64),  # wake-up minus deadline
        ("period_ns", np.int64),  # since the previous wake-up
        ("work_ns", np.int64),  # wake-up to the command sent
        ("robot_stamp", np.float64),  # controller timestamp, s
        ("state_age_ns", np.int64),  # since the robot state last changed
        ("q", np.float64, (6,)),  # rad
        ("qd", np.float64, (6,)),  # rad/s
        ("tcp_pose", np.float64, (6,)),  # UR pose [x, y, z, rx, ry, rz], m and rad
        ("tcp_speed", np.float64, (6,)),  # measured twist, base frame
        ("safety_bits", np.uint32),  # UR safety_status_bits
        ("runtime_state", np.int8),  # UR runtime_state (2 = playing)
        ("mode", np.int8),  # core Mode
        ("action", np.int8),  # core Action sent
        ("guarded", np.bool_),  # the limiter's viability guard acted
        ("status", np.int16),  # ControlStatus
        ("faults", np.uint32),  # safety Fault bits
        ("command_id", np.uint64),  # the command served
        ("twist", np.float64, (6,)),  # the twist sent with speedL, the joint speeds (rad/s) with speedJ, else zero
        ("tactile_seq", np.int64),  # frame counter of the tactile sample used, -1 without
        ("tactile_age_ns", np.int64),
        ("tactile_torn", np.uint32),  # torn tactile reads so far
        ("overruns", np.uint32),  # cycles that ended after the next deadline, so far
        # The servo law's telemetry (celld.motion.types.ServoTelemetry).
        ("servo_phase", np.int8),  # the law's phase, -1 without a servo
        ("delta_n", np.float64),  # m, normal deformation the law used, NaN without
        ("refined_base", np.float64, (3,)),  # latest refined path point, base frame, m; NaN without
        ("process_on", np.bool_),  # the core asked for the process output (welding arc) this cycle
        ("delta_d", np.float64),  # m, the normal deformation the law holds (signed as delta_n), NaN without
        # The tactile sample the loop holds (celld.tactile.sample.TactileSample).
        ("delta_tool", np.float64, (3,)),  # m, tool frame: tangential, normal, out of plane; NaN when not valid
        ("contact", np.int8),  # ContactState, -1 without a sample
        # The welding power source (celld.motion.arc, celld.motion.source_io); -1 and NaN without one.
        ("arc_phase", np.int8),  # ArcPhase of the weld's sequence
        ("source_bits", np.uint16),  # the source's inputs, bits in celld.motion.source_io.BIT_ROLES order
        ("weld_current", np.float64),  # A, as the source reports it; NaN when not wired
        ("weld_voltage", np.float64),  # V, likewise
    ]
)

EVENT_DTYPE = np.dtype(
    [
        ("t_ns", np.int64),
        ("command_id", np.uint64),
        ("status", np.int16),
        ("reason", f"S{REASON_BYTES}"),
    ]
)

SETPOINT_DTYPE = np.dtype([("t_ns", np.int64), ("twist", np.float64, (6,))])

CONTROL_DTYPE = np.dtype(
    [
        ("stop_epoch", np.uint64),  # raised by every stop request
        ("stop_posted", np.uint64),  # commands posted up to the last stop are cancelled
        ("shutdown", np.bool_),  # stop, then exit
    ]
)


class Phase(IntEnum):
    """Where the motion process is in its life."""

    NONE = 0
    STARTING = 1
    CONNECTING = 2  # constructing the ur_rtde interfaces
    RUNNING = 3  # in the loop
    EXITED = 4


STATUS_DTYPE = np.dtype(
    [
        ("phase", np.int8),
        ("pid", np.int64),
        ("phase_ns", np.int64),  # when the phase began
        ("realtime", np.bool_),  # SCHED_FIFO granted
        ("cpu", np.int16),  # pinned CPU, -1 when not pinned
        ("exit_status", np.int16),  # ControlStatus of the exit
        ("reason", f"S{REASON_BYTES}"),  # exit reason, or why real time was refused
    ]
)


def encode_reason(text: str) -> bytes:
    """UTF-8 bytes of ``text`` cut to fit a reason field."""
    return text.encode("utf-8")[:REASON_BYTES]


def decode_reason(raw: bytes) -> str:
    return bytes(raw).rstrip(b"\0").decode("utf-8", errors="replace")


class ChannelNames(NamedTuple):
    """Shared-memory segment names; picklable, handed to the motion process."""

    state: str
    events: str
    commands: str
    setpoint: str
    tactile: str
    control: str
    status: str
    state_capacity: int

    @classmethod
    def unique(cls, state_capacity: int, tactile: str | None = None) -> ChannelNames:
        """Fresh names for one supervisor; ``tactile`` names an existing tactile slot to read."""
        tag = f"celld-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        return cls(
            f"{tag}-state",
            f"{tag}-events",
            f"{tag}-cmd",
            f"{tag}-setpoint",
            tactile or f"{tag}-tactile",
            f"{tag}-control",
            f"{tag}-status",
            state_capacity,
        )


class Channels:
    """The opened channels; :meth:`create` in the supervisor, :meth:`attach` in the motion process."""

    def __init__(self, names: ChannelNames, create: bool, create_tactile: bool) -> None:
        self.names = names
        self.owner = create
        self._owns_tactile = create and create_tactile
        n = names
        if create:
            self.state = Ring.create(n.state, STATE_DTYPE, n.state_capacity)
            self.events = Ring.create(n.events, EVENT_DTYPE, EVENT_CAPACITY)
            self.commands = Mailbox.create(n.commands, MAILBOX_SLOTS, MAILBOX_SLOT_BYTES)
            self.setpoint = SeqlockSlot.create(n.setpoint, SETPOINT_DTYPE)
            self.tactile = SeqlockSlot.create(n.tactile, TACTILE_DTYPE) if create_tactile else SeqlockSlot.attach(n.tactile, TACTILE_DTYPE)
            self.control = SeqlockSlot.create(n.control, CONTROL_DTYPE)
            self.status = SeqlockSlot.create(n.status, STATUS_DTYPE)
        else:
            self.state = Ring.attach(n.state, STATE_DTYPE, n.state_capacity)
            self.events = Ring.attach(n.events, EVENT_DTYPE, EVENT_CAPACITY)
            self.commands = Mailbox.attach(n.commands, MAILBOX_SLOTS, MAILBOX_SLOT_BYTES)
            self.setpoint = SeqlockSlot.attach(n.setpoint, SETPOINT_DTYPE)
            self.tactile = SeqlockSlot.attach(n.tactile, TACTILE_DTYPE)
            self.control = SeqlockSlot.attach(n.control, CONTROL_DTYPE)
            self.status = SeqlockSlot.attach(n.status, STATUS_DTYPE)

    @classmethod
    def create(cls, names: ChannelNames, create_tactile: bool = True) -> Channels:
        return cls(names, create=True, create_tactile=create_tactile)

    @classmethod
    def attach(cls, names: ChannelNames) -> Channels:
        return cls(names, create=False, create_tactile=False)

    def _all(self) -> list:
        return [self.state, self.events, self.commands, self.setpoint, self.tactile, self.control, self.status]

    def close(self) -> None:
        for ch in self._all():
            ch.close()

    def unlink(self) -> None:
        """Remove the segments this side created (the tactile slot only if it created it)."""
        if not self.owner:
            return
        for ch in self._all():
            if ch is self.tactile and not self._owns_tactile:
                continue
            ch.unlink()
