"""RTDE protocol version 2: package framing, field types, recipes (pure, no sockets).

Everything here turns bytes into values and values into bytes; the server in
:mod:`celld.sim.robot.rtde_server` owns the sockets. The wire format is the one
of the UR RTDE guide: every package is ``>HB`` (total size including the 3-byte
header, then the type), big-endian payloads.

The field table gives each RTDE name the type a UR controller of the 5.11
series gives it. The client decodes data packages by name with its own table
and ignores the types the server returns, so these types must be right.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass

from celld.errors import InputError

# Message types (ASCII codes).
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
CONTROL_PACKAGE_START = ord("S")
CONTROL_PACKAGE_PAUSE = ord("P")

MESSAGE_TYPES = frozenset(
    (
        REQUEST_PROTOCOL_VERSION,
        GET_URCONTROL_VERSION,
        TEXT_MESSAGE,
        DATA_PACKAGE,
        CONTROL_PACKAGE_SETUP_OUTPUTS,
        CONTROL_PACKAGE_SETUP_INPUTS,
        CONTROL_PACKAGE_START,
        CONTROL_PACKAGE_PAUSE,
    )
)

# The highest protocol version this server speaks.
PROTOCOL_VERSION = 2
# Header: uint16 size (header included), uint8 type.
HEADER = struct.Struct(">HB")
# A package larger than this is refused (the client's own limit is 4 KB).
MAX_PACKAGE_SIZE = 4096
# Output frequencies a controller accepts, Hz.
MIN_FREQUENCY_HZ = 1.0
MAX_FREQUENCY_HZ = 500.0

# Text message levels (server to client).
LEVEL_EXCEPTION = 0
LEVEL_ERROR = 1
LEVEL_WARNING = 2
LEVEL_INFO = 3

# Answers in a recipe setup reply for names the controller refuses.
NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"

# struct format of each RTDE type.
TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
# Number of scalars each type packs to.
TYPE_WIDTH = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}

# Registers 0-47 exist for int and double, bits 64-127 as single booleans.
N_REGISTERS = 48
_BIT_REGISTERS = range(64, 128)


def _register_fields(prefix: str) -> dict[str, str]:
    fields = {f"{prefix}_bit_registers0_to_31": "UINT32", f"{prefix}_bit_registers32_to_63": "UINT32"}
    fields.update({f"{prefix}_bit_register_{i}": "BOOL" for i in _BIT_REGISTERS})
    fields.update({f"{prefix}_int_register_{i}": "INT32" for i in range(N_REGISTERS)})
    fields.update({f"{prefix}_double_register_{i}": "DOUBLE" for i in range(N_REGISTERS)})
    return fields


# Fields a client may read (output recipes).
OUTPUT_FIELDS: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "actual_current_window": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
    **_register_fields("output"),
    **_register_fields("input"),
}

# Fields a client may write (input recipes).
INPUT_FIELDS: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "external_force_torque": "VECTOR6D",
    **_register_fields("input"),
}


class RtdeProtocolError(InputError):
    """A package from a client breaks the RTDE protocol."""


@dataclass(frozen=True)
class Recipe:
    """An output or input recipe of one connection.

    ``names`` are RTDE field names, ``types`` their RTDE types; ``codec``
    packs or unpacks the body after the recipe id byte.
    """

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    codec: struct.Struct

    @property
    def widths(self) -> tuple[int, ...]:
        """Number of scalars each field takes in the packed tuple."""
        return tuple(TYPE_WIDTH.get(t, 1) for t in self.types)


def make_recipe(recipe_id: int, names: tuple[str, ...], types: tuple[str, ...]) -> Recipe:
    """A recipe with the struct that packs ``types`` after a uint8 recipe id."""
    fmt = ">B" + "".join(TYPE_FORMATS[t] for t in types)
    return Recipe(recipe_id, names, types, struct.Struct(fmt))


def resolve(names: tuple[str, ...], table: dict[str, str]) -> tuple[str, ...]:
    """The type of each name in ``table``, ``NOT_FOUND`` for names it lacks."""
    return tuple(table.get(n, NOT_FOUND) for n in names)


# --- framing ----------------------------------------------------------------------


def package(msg_type: int, payload: bytes = b"") -> bytes:
    """One package: header and payload."""
    return HEADER.pack(HEADER.size + len(payload), msg_type) + payload


class PackageReader:
    """Split a byte stream into ``(type, payload)`` packages.

    Feed whatever the socket returned; iterate for the complete packages. A
    header whose size is below 3 or above :data:`MAX_PACKAGE_SIZE` cannot be
    resynchronised: :meth:`packages` raises :class:`RtdeProtocolError` and the
    connection must be closed.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        self._buf += data

    def packages(self) -> Iterator[tuple[int, bytes]]:
        buf = self._buf
        while len(buf) >= HEADER.size:
            size, msg_type = HEADER.unpack_from(buf)
            if size < HEADER.size or size > MAX_PACKAGE_SIZE:
                raise RtdeProtocolError(f"package size {size} outside [{HEADER.size}, {MAX_PACKAGE_SIZE}] (type {msg_type})")
            if len(buf) < size:
                return
            payload = bytes(buf[HEADER.size : size])
            del buf[:size]
            yield msg_type, payload


# --- requests (client to server) ---------------------------------------------------


def parse_protocol_version(payload: bytes) -> int:
    """The uint16 protocol version a ``V`` request asks for."""
    if len(payload) != 2:
        raise RtdeProtocolError(f"V: expected a uint16 protocol version, got {len(payload)} bytes")
    return int(struct.unpack(">H", payload)[0])


def _parse_names(text: bytes, what: str) -> tuple[str, ...]:
    try:
        names = [n.strip() for n in text.decode("ascii").split(",")]
    except UnicodeDecodeError as exc:
        raise RtdeProtocolError(f"{what}: field names must be ASCII") from exc
    if len(names) > 1 and not names[-1]:
        names.pop()  # ur-rtde ends its output list with a comma
    if any(not n for n in names):
        raise RtdeProtocolError(f"{what}: expected comma-separated field names, got {text[:80]!r}")
    return tuple(names)


def parse_setup_outputs(payload: bytes) -> tuple[float, tuple[str, ...]]:
    """``(frequency_hz, names)`` of an ``O`` request (protocol version 2)."""
    if len(payload) < 9:
        raise RtdeProtocolError(f"O: expected a double frequency and field names, got {len(payload)} bytes")
    (frequency,) = struct.unpack_from(">d", payload)
    return float(frequency), _parse_names(payload[8:], "O")


def parse_setup_inputs(payload: bytes) -> tuple[str, ...]:
    """The names of an ``I`` request."""
    return _parse_names(payload, "I")


def parse_text_message(payload: bytes) -> tuple[str, str, int]:
    """``(message, source, level)`` of a client's ``M`` package (protocol version 2)."""
    try:
        n = payload[0]
        message = payload[1 : 1 + n].decode("utf-8", "replace")
        m = payload[1 + n]
        source = payload[2 + n : 2 + n + m].decode("utf-8", "replace")
        level = payload[2 + n + m]
    except IndexError as exc:
        raise RtdeProtocolError(f"M: truncated text message of {len(payload)} bytes") from exc
    return message, source, int(level)


def parse_data(payload: bytes, recipes: dict[int, Recipe]) -> tuple[Recipe, tuple]:
    """``(recipe, values)`` of a ``U`` package, decoded by the recipe id it carries.

    ``values`` is the flat tuple of scalars (vectors expanded).
    """
    if not payload:
        raise RtdeProtocolError("U: empty data package, expected a recipe id")
    recipe = recipes.get(payload[0])
    if recipe is None:
        known = sorted(recipes) or "none"
        raise RtdeProtocolError(f"U: unknown input recipe id {payload[0]} (set up: {known})")
    if len(payload) != recipe.codec.size:
        raise RtdeProtocolError(f"U: recipe {recipe.recipe_id} expects {recipe.codec.size} bytes, got {len(payload)}")
    values = recipe.codec.unpack(payload)
    return recipe, values[1:]


# --- replies (server to client) ----------------------------------------------------


def reply_protocol_version(accepted: bool) -> bytes:
    return package(REQUEST_PROTOCOL_VERSION, struct.pack(">B", int(accepted)))


def reply_controller_version(major: int, minor: int, bugfix: int, build: int) -> bytes:
    return package(GET_URCONTROL_VERSION, struct.pack(">IIII", major, minor, bugfix, build))


def reply_setup(msg_type: int, recipe_id: int, types: tuple[str, ...]) -> bytes:
    """Reply to ``O`` or ``I``: the recipe id (0 when refused) and the types."""
    return package(msg_type, struct.pack(">B", recipe_id) + ",".join(types).encode("ascii"))


def reply_flag(msg_type: int, ok: bool) -> bytes:
    """Reply to ``S`` or ``P``: a uint8 success flag."""
    return package(msg_type, struct.pack(">B", int(ok)))


def text_message(message: str, source: str = "celld-sim", level: int = LEVEL_INFO) -> bytes:
    """A server-to-client ``M`` package; both strings are cut to 255 bytes."""
    msg = message.encode("utf-8")[:255]
    src = source.encode("utf-8")[:255]
    return package(TEXT_MESSAGE, bytes([len(msg)]) + msg + bytes([len(src)]) + src + bytes([level]))


def data_package(recipe: Recipe, values: tuple) -> bytes:
    """A ``U`` package of ``recipe`` with the flat scalar ``values``."""
    return package(DATA_PACKAGE, recipe.codec.pack(recipe.recipe_id, *values))
