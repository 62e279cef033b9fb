"""Commands to the motion process and their byte form in the command mailbox.

The main process posts a command as bytes (:class:`celld.shm.Mailbox`); the
loop decodes it in the cycle it arrives. A command is one of:

- :class:`MoveTo`: a jerk-limited Cartesian move to ``T_base_tcp``;
- :class:`MoveJoints`: a jerk-limited joint move to ``q_goal`` (speedJ);
- :class:`Stream`: velocity streaming from the setpoint slot;
- :class:`StartServo`: the servo slot, with a :class:`~celld.motion.types.ServoPlan`.

A stop is not a command: it goes through the control slot, so no queued
command can delay or overwrite it.

Byte form (little-endian)::

    b"CMD1"  u8 kind  u32 meta_len  meta (UTF-8 JSON)  array data (float64, C order)

``meta`` holds the scalar fields and, for each array, its name and shape; the
array bytes follow in that order. Decoding checks everything and raises
:class:`~celld.errors.InputError` that says what was expected and what came.
"""

from __future__ import annotations

import json
import math
import struct
from enum import IntEnum
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from celld.errors import InputError
from celld.motion.types import ServoPlan
from celld.se3 import check_transform

_MAGIC = b"CMD1"
_HEADER = struct.Struct("<4sBI")
# A plan path longer than this is refused (about 190 MB of float64 at 3 columns).
_MAX_ARRAY_ELEMENTS = 8_000_000


class CommandKind(IntEnum):
    MOVE_TO = 1
    STREAM = 2
    SERVO = 3
    MOVE_JOINTS = 4


class MoveTo(NamedTuple):
    """Move the TCP to ``T_base_tcp`` (4, 4), straight in SE(3), jerk-limited.

    ``speed_scale`` (0, 1] scales every limit of the move. ``tolerance`` (m)
    and ``angle_tolerance`` (rad) say when the move has arrived.
    """

    T_base_tcp: np.ndarray
    speed_scale: float = 1.0
    tolerance: float = 5e-5
    angle_tolerance: float = 5e-4


class MoveJoints(NamedTuple):
    """Move the joints to ``q_goal`` (6,) rad, straight in joint space, jerk-limited per joint.

    ``speed_scale`` (0, 1] scales every joint limit of the move; ``tolerance``
    (rad) is the largest joint error at arrival.
    """

    q_goal: np.ndarray
    speed_scale: float = 1.0
    tolerance: float = 5e-5


class Stream(NamedTuple):
    """Follow the twist in the setpoint slot; a setpoint older than ``timeout`` (s) means zero."""

    timeout: float = 0.1


class StartServo(NamedTuple):
    """Run the servo law built from ``plan`` by the factory registered under ``plan.name``."""

    plan: ServoPlan


Command = MoveTo | MoveJoints | Stream | StartServo

# Largest joint target accepted, rad: UR joints turn +-360 deg.
_MAX_JOINT = 2.0 * math.pi
# The slowest move a command may ask for, as a share of the limits.
MIN_SPEED_SCALE = 1e-3


def _positive(name: str, value: Any, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and 0.0 < v <= hi):
        raise InputError(f"{name}: expected 0 < value <= {hi}, got {v}")
    return v


def _speed_scale(value: Any) -> float:
    """A move's speed scale: (0, 1], and not so small that the move would take ages (the loop's plan degenerates)."""
    v = _positive("speed_scale", value, 1.0)
    if v < MIN_SPEED_SCALE:
        raise InputError(f"speed_scale: expected at least {MIN_SPEED_SCALE} (a move a thousand times slower than the limits), got {v}")
    return v


def move_to(T_base_tcp: ArrayLike, speed_scale: float = 1.0, tolerance: float = 5e-5, angle_tolerance: float = 5e-4) -> MoveTo:
    """Return a validated :class:`MoveTo`."""
    return MoveTo(
        check_transform(T_base_tcp, "T_base_tcp").copy(),
        _speed_scale(speed_scale),
        _positive("tolerance", tolerance, 0.01),
        _positive("angle_tolerance", angle_tolerance, 0.1),
    )


def move_joints(q_goal: ArrayLike, speed_scale: float = 1.0, tolerance: float = 5e-5) -> MoveJoints:
    """Return a validated :class:`MoveJoints`."""
    q = np.array(q_goal, dtype=np.float64)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise InputError(f"q_goal: expected 6 finite joint positions (rad), got {np.asarray(q_goal).tolist()!r}")
    if np.any(np.abs(q) > _MAX_JOINT):
        raise InputError(f"q_goal: every joint must lie within +-2 pi rad, got {q.tolist()}")
    return MoveJoints(q, _speed_scale(speed_scale), _positive("tolerance", tolerance, 0.01))


def stream(timeout: float = 0.1) -> Stream:
    """Return a validated :class:`Stream`."""
    return Stream(_positive("timeout", timeout, 5.0))


def start_servo(plan: ServoPlan) -> StartServo:
    """Return a validated :class:`StartServo` (arrays become finite float64)."""
    if not isinstance(plan.name, str) or not plan.name:
        raise InputError(f"servo plan: expected a non-empty name, got {plan.name!r}")
    arrays: dict[str, np.ndarray] = {}
    for key, arr in plan.arrays.items():
        a = np.ascontiguousarray(arr, dtype=np.float64)
        if not np.all(np.isfinite(a)):
            raise InputError(f"servo plan array {key!r}: contains NaN or infinite values")
        if a.size > _MAX_ARRAY_ELEMENTS:
            raise InputError(f"servo plan array {key!r}: {a.size} elements exceed {_MAX_ARRAY_ELEMENTS}")
        arrays[str(key)] = a
    params: dict[str, float | int | bool | str] = {}
    for key, value in plan.params.items():
        if not isinstance(value, (bool, int, float, str)):
            raise InputError(f"servo plan parameter {key!r}: expected a number, bool or string, got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(f"servo plan parameter {key!r}: expected a finite number, got {value}")
        params[str(key)] = value
    return StartServo(ServoPlan(plan.name, arrays, params))


def encode(cmd: Command) -> bytes:
    """Return the mailbox bytes of a validated command."""
    arrays: list[tuple[str, np.ndarray]] = []
    if isinstance(cmd, MoveTo):
        kind = CommandKind.MOVE_TO
        meta: dict[str, Any] = {
            "speed_scale": cmd.speed_scale,
            "tolerance": cmd.tolerance,
            "angle_tolerance": cmd.angle_tolerance,
        }
        arrays.append(("T_base_tcp", np.ascontiguousarray(cmd.T_base_tcp, dtype=np.float64)))
    elif isinstance(cmd, MoveJoints):
        kind = CommandKind.MOVE_JOINTS
        meta = {"speed_scale": cmd.speed_scale, "tolerance": cmd.tolerance}
        arrays.append(("q_goal", np.ascontiguousarray(cmd.q_goal, dtype=np.float64)))
    elif isinstance(cmd, Stream):
        kind = CommandKind.STREAM
        meta = {"timeout": cmd.timeout}
    elif isinstance(cmd, StartServo):
        kind = CommandKind.SERVO
        meta = {"name": cmd.plan.name, "params": cmd.plan.params}
        arrays.extend((k, np.ascontiguousarray(v, dtype=np.float64)) for k, v in cmd.plan.arrays.items())
    else:
        raise InputError(f"command: expected MoveTo, MoveJoints, Stream or StartServo, got {type(cmd).__name__}")
    meta["arrays"] = [[name, list(a.shape)] for name, a in arrays]
    meta_bytes = json.dumps(meta).encode("utf-8")
    parts = [_HEADER.pack(_MAGIC, int(kind), len(meta_bytes)), meta_bytes]
    parts.extend(a.astype("<f8", copy=False).tobytes() for _, a in arrays)
    return b"".join(parts)


def decode(payload: bytes) -> Command:
    """Return the command held by mailbox bytes, or raise InputError."""
    if len(payload) < _HEADER.size:
        raise InputError(f"command: expected at least {_HEADER.size} bytes, got {len(payload)}")
    magic, kind_raw, meta_len = _HEADER.unpack_from(payload)
    if magic != _MAGIC:
        raise InputError(f"command: expected magic {_MAGIC!r}, got {magic!r}")
    try:
        kind = CommandKind(kind_raw)
    except ValueError as exc:
        raise InputError(f"command: unknown kind {kind_raw}") from exc
    end = _HEADER.size + meta_len
    try:
        meta = json.loads(payload[_HEADER.size : end].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"command: metadata is not UTF-8 JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise InputError("command: metadata must be a JSON object")
    arrays: dict[str, np.ndarray] = {}
    offset = end
    for entry in meta.get("arrays", []):
        if (
            not isinstance(entry, list)
            or len(entry) != 2
            or not isinstance(entry[0], str)
            or not all(isinstance(n, int) and n >= 0 for n in entry[1])
        ):
            raise InputError(f"command: bad array descriptor {entry!r}")
        name, shape = entry[0], tuple(entry[1])
        count = int(np.prod(shape)) if shape else 1
        if count > _MAX_ARRAY_ELEMENTS:
            raise InputError(f"command: array {name!r} of {count} elements exceeds {_MAX_ARRAY_ELEMENTS}")
        nbytes = 8 * count
        if offset + nbytes > len(payload):
            raise InputError(f"command: array {name!r} needs {nbytes} bytes, only {len(payload) - offset} left")
        arrays[name] = np.frombuffer(payload, dtype="<f8", count=count, offset=offset).reshape(shape).astype(np.float64)
        offset += nbytes
    if offset != len(payload):
        raise InputError(f"command: {len(payload) - offset} trailing bytes after the arrays")
    if kind is CommandKind.MOVE_TO:
        if "T_base_tcp" not in arrays:
            raise InputError("move_to: the target pose T_base_tcp is missing")
        return move_to(arrays["T_base_tcp"], meta.get("speed_scale", 1.0), meta.get("tolerance", 5e-5), meta.get("angle_tolerance", 5e-4))
    if kind is CommandKind.MOVE_JOINTS:
        if "q_goal" not in arrays:
            raise InputError("move_joints: the target joints q_goal are missing")
        return move_joints(arrays["q_goal"], meta.get("speed_scale", 1.0), meta.get("tolerance", 5e-5))
    if kind is CommandKind.STREAM:
        return stream(meta.get("timeout", 0.1))
    params = meta.get("params", {})
    if not isinstance(params, dict):
        raise InputError(f"servo plan: expected params as an object, got {params!r}")
    return start_servo(ServoPlan(str(meta.get("name", "")), arrays, params))
