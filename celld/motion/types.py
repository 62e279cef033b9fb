"""Values exchanged by the motion loop and its controllers.

A controller is stepped once per cycle as ``step(input) -> (output, status)``
and never raises in the loop: it reports a :class:`ControlStatus` instead.
Twists are ``[vx, vy, vz, wx, wy, wz]`` in the base frame, m/s and rad/s.
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple, Protocol

import numpy as np

from celld.tactile.sample import TactileSample


class ControlStatus(IntEnum):
    """What a controller (or the loop) reports each cycle."""

    OK = 0  # running normally
    DONE = 1  # reached its goal (end of a move, end of the path)
    HOLD = 2  # holding still on purpose (e.g. a singularity guard in hold mode)
    STOPPING = 3  # a jerk-limited stop is under way
    STOPPED = 4  # stopped after a stop request or a fault
    # Faults: each ends in a jerk-limited stop.
    WORKSPACE = 10  # the TCP would leave the workspace box
    LIMIT = 11  # a speed, acceleration or jerk limit would be exceeded
    STALE_STATE = 12  # robot state older than the configured number of cycles
    STALE_TACTILE = 13  # tactile sample older than its bound, or invalid too long
    SAFETY = 14  # protective stop or e-stop reported by the robot
    CONTACT_LOST = 15  # the finger lost the seam for longer than the search distance
    OVERLOAD = 16  # the finger deformed beyond its maximum
    LINK_LOST = 17  # the RTDE link dropped
    BAD_COMMAND = 18  # a command could not be decoded or was refused
    FAULT = 19  # any other failure
    ARC = 20  # the weld's arc could not be established or kept (celld.motion.arc), or its source failed
    COLLISION = 21  # the torch's collision (breakaway) input


class RobotState(NamedTuple):
    """The robot as read at one cycle.

    Attributes
    ----------
    stamp_ns : int
        Time the state was read, ``time.monotonic_ns()``.
    q, qd : np.ndarray, shape (6,)
        Joint positions (rad) and speeds (rad/s).
    T_base_tcp : np.ndarray, shape (4, 4)
        TCP pose in the base frame.
    v_tcp : np.ndarray, shape (6,)
        TCP twist in the base frame (m/s, rad/s).
    """

    stamp_ns: int
    q: np.ndarray
    qd: np.ndarray
    T_base_tcp: np.ndarray
    v_tcp: np.ndarray


class ServoInput(NamedTuple):
    """What a servo law sees each cycle."""

    state: RobotState
    tactile: TactileSample | None  # the latest good sample, None before the first
    tactile_age: float  # seconds since the sample's capture
    # The arc sequence's travel gate (celld.motion.arc): +1 travel, 0 hold (the arc is not established:
    # come to rest at the seam's start or where the arc went out), -1 back off along the welded path.
    # None: the cell has no power source, travel as planned.
    travel: int | None = None


class ServoTelemetry(NamedTuple):
    """What a servo law reports about itself each cycle, for the state ring and the process output.

    Attributes
    ----------
    phase : int
        The law's own phase, -1..127 (for Algorithm 2 :class:`celld.motion.algorithm2.Phase`); -1: no servo.
    delta_n : float
        Normal deformation the law used this cycle, m; NaN: none.
    refined_base : np.ndarray, shape (3,)
        Latest point of the refined path in the base frame, m; NaN: none yet.
    process_on : bool
        The law wants the process (the welding arc) on. The core switches it
        on only while the law runs undisturbed (:mod:`celld.motion.core`).
    delta_d : float
        The normal deformation the law holds the finger at, m, signed as
        ``delta_n``; NaN: none.
    """

    phase: int
    delta_n: float
    refined_base: np.ndarray
    process_on: bool
    delta_d: float = math.nan


def _nan3() -> np.ndarray:
    v = np.full(3, math.nan)
    v.flags.writeable = False
    return v


# What is recorded when no servo runs, or its law's telemetry failed.
NO_TELEMETRY = ServoTelemetry(-1, math.nan, _nan3(), False)


class ServoLaw(Protocol):
    """A seam-tracking law stepped in the motion loop's servo slot.

    Besides ``start`` and ``step`` a law has ``reason``, what it saw when it
    last reported a fault ("" otherwise), and ``telemetry()``, its state after
    its last step (cheap: it is called every cycle). The slot checks both once,
    when the law starts, and refuses a law that lacks them.
    """

    reason: str

    def start(self, state: RobotState) -> None:
        """Called once, in the loop, when the servo takes over."""

    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        """Return the desired twist (6,) in the base frame and a status.

        The loop shapes the twist with its jerk-limited velocity limiter and
        applies its own safety checks; the law must not raise.
        """
        ...

    def telemetry(self) -> ServoTelemetry:
        """The law's state after its last step (before the first: its state at start)."""
        ...


class ServoPlan(NamedTuple):
    """What starts a servo law in the loop: the law's name, its arrays and its parameters.

    It crosses the command mailbox as bytes (:mod:`celld.motion.commands`) and
    is turned into a :class:`ServoLaw` in the motion process by the factory
    registered under ``name``, so the loop imports no law it is not given.

    Attributes
    ----------
    name : str
        Key of the factory, e.g. ``"algorithm2"``.
    arrays : dict of str to np.ndarray
        Float64 arrays, e.g. ``{"P_base": (n, 3) planned path points, m}``.
    params : dict of str to float, int, bool or str
        Scalar parameters of the law (SI units).
    """

    name: str
    arrays: dict[str, np.ndarray]
    params: dict[str, float | int | bool | str]


class ServoFactory(Protocol):
    """Builds a ServoLaw from a plan; called in the motion process when the plan arrives.

    It may raise :class:`~celld.errors.InputError` for a plan it refuses; the
    loop then reports ``BAD_COMMAND`` and keeps holding.
    """

    def __call__(self, plan: ServoPlan) -> ServoLaw: ...
