"""The kinematics the UR controller itself uses, read from its primary interface (port 30001).

A UR leaves the factory with a kinematic calibration: its controller computes
every pose it reports, and every straight move it makes, from the published
DH table plus that calibration's deltas. Without it a model's published table
puts the flange millimetres, up to centimetres, from where the controller
does (the UR ROS driver's calibration notes say "in the magnitude of
centimeters"). celld's own kinematics (joint moves, collision checks, the
arm's calibration on top) must be the controller's, so it reads them.

ur-rtde does not read them: the controller sends them on its primary
interface, a stream of messages each ``int32 size, uint8 type`` (big-endian,
the size counting the header). A robot state message (type 16) is a run of
packages of the same framing; its kinematics info package (type 5) holds a
checksum per joint, the table's theta, a, d and alpha (six doubles each) and
the calibration's status. The controller sends robot state at 10 Hz from the
moment a client connects (the UR client library's calibration reader, and
UR's primary interface documentation, describe the same layout).

Pure parsing (:func:`parse_message`, :func:`kinematics_of`) is apart from the
blocking socket read (:func:`read_kinematics`), which the daemon runs off its
event loop.
"""

from __future__ import annotations

import hashlib
import math
import socket
import struct
import time
from dataclasses import dataclass

import numpy as np

from celld.errors import InputError, RobotError
from celld.robot import kinematics as kin

PRIMARY_PORT = 30001
MESSAGE_ROBOT_STATE = 16
PACKAGE_KINEMATICS_INFO = 5
HEADER = struct.Struct(">iB")
# checksum (6 x uint32), theta, a, d, alpha (6 x double each), calibration status (uint32).
KINEMATICS_INFO = struct.Struct(">6I6d6d6d6dI")
# The largest message taken: a robot state message is about 1.5 kB; anything beyond a megabyte is not one.
MAX_MESSAGE = 1 << 20
# How long a read waits for the kinematics, s (robot state comes at 10 Hz).
READ_TIMEOUT = 3.0
# The joint vectors at which a controller's table is compared with its model's (rad): the home pose and
# three spread out, flange up, out front and folded.
_CHECK_POSES = (
    (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0),
    (0.5, -1.2, 1.0, -1.4, -1.6, 0.3),
    (-1.0, -2.0, 2.2, -0.4, 1.2, -2.0),
    (2.0, -0.6, -1.2, 0.8, 0.5, 1.0),
)
# A controller's table may put the flange at most this far from its model's table (m): a factory
# calibration moves it millimetres to centimetres; a different model (robot.model wrong) decimetres.
MODEL_TOLERANCE = 0.05


def table_id(dh: kin.DH) -> str:
    """A DH table's identity: the first 16 hex digits of the SHA-256 of its 24 numbers, rounded to 0.1 um and
    0.1 urad (a calibration made on one controller's table is not used on another)."""
    values = [round(v * 1e7) for row in (dh.theta, dh.a, dh.d, dh.alpha) for v in row]
    return hashlib.sha256(struct.pack(">24q", *values)).hexdigest()[:16]


@dataclass(frozen=True)
class ControllerKinematics:
    """The DH table a UR controller computes with (its model's, calibrated), as its primary interface sent it."""

    dh: kin.DH
    checksums: tuple[int, ...]
    calibration_status: int

    @property
    def id(self) -> str:
        """:func:`table_id` of the table."""
        return table_id(self.dh)


def check_model(dh: kin.DH, model: kin.URModel) -> float:
    """The largest distance (m) between where table ``dh`` and ``model``'s published one put the flange, over a
    few spread-out joint vectors; or raise when ``dh`` is not a table of that model.

    Raises
    ------
    RobotError
        The table puts the flange more than :data:`MODEL_TOLERANCE` from ``model``'s: the robot is not a
        ``model`` (``robot.model`` names another).
    """
    offset = max(float(np.linalg.norm(kin.forward(q, dh)[:3, 3] - kin.forward(q, model.dh)[:3, 3])) for q in _CHECK_POSES)
    if offset > MODEL_TOLERANCE:
        raise RobotError(
            f"robot.model: the controller's kinematics put the flange {offset * 1e3:.0f} mm from a {model.name}'s "
            f"(at most {MODEL_TOLERANCE * 1e3:.0f} mm for a factory calibration): is the robot a {model.name}?"
        )
    return offset


def kinematics_of(payload: bytes) -> ControllerKinematics:
    """The kinematics info package's ``payload`` (after its 5-byte header), checked.

    Raises
    ------
    InputError
        The payload has the wrong length or a number that is not finite.
    """
    if len(payload) != KINEMATICS_INFO.size:
        raise InputError(f"primary interface: kinematics info of {len(payload)} bytes, expected {KINEMATICS_INFO.size}")
    v = KINEMATICS_INFO.unpack(payload)
    checksums, rows, status = v[:6], v[6:30], v[30]
    if not all(math.isfinite(x) for x in rows):
        raise InputError(f"primary interface: kinematics info holds numbers that are not finite: {list(rows)}")
    theta, a, d, alpha = (tuple(float(x) for x in rows[i : i + 6]) for i in range(0, 24, 6))
    return ControllerKinematics(kin.DH(d, a, alpha, theta), tuple(int(c) for c in checksums), int(status))  # type: ignore[arg-type]


def parse_message(message: bytes) -> ControllerKinematics | None:
    """The kinematics in one whole primary-interface ``message`` (its header included), or None when it
    carries none (another message type, or a robot state without the package).

    Raises
    ------
    InputError
        The message or one of its packages is framed wrong.
    """
    if len(message) < HEADER.size:
        raise InputError(f"primary interface: a message of {len(message)} bytes, shorter than its header")
    size, kind = HEADER.unpack_from(message)
    if size != len(message):
        raise InputError(f"primary interface: a message says {size} bytes and has {len(message)}")
    if kind != MESSAGE_ROBOT_STATE:
        return None
    at = HEADER.size
    while at < size:
        if size - at < HEADER.size:
            raise InputError(f"primary interface: {size - at} stray bytes at the end of a robot state message")
        length, package = HEADER.unpack_from(message, at)
        if length < HEADER.size or at + length > size:
            raise InputError(f"primary interface: a package of {length} bytes at byte {at} of a {size}-byte robot state message")
        if package == PACKAGE_KINEMATICS_INFO:
            return kinematics_of(message[at + HEADER.size : at + length])
        at += length
    return None


def _read_exactly(sock: socket.socket, n: int, deadline: float) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        left = deadline - time.monotonic()
        if left <= 0.0:
            raise TimeoutError
        sock.settimeout(left)
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("closed by the controller")
        buf += chunk
    return bytes(buf)


def read_kinematics(host: str, port: int = PRIMARY_PORT, timeout: float = READ_TIMEOUT) -> ControllerKinematics:
    """Connect to the controller's primary interface and read its kinematics (blocking, at most ``timeout`` s).

    Raises
    ------
    RobotError
        No connection, no kinematics within ``timeout``, or a stream that is not the primary interface's
        (each names the host and port).
    """
    where = f"{host}:{port}"
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            while True:
                header = _read_exactly(sock, HEADER.size, deadline)
                size, _ = HEADER.unpack(header)
                if not HEADER.size <= size <= MAX_MESSAGE:
                    raise InputError(f"primary interface: a message header says {size} bytes")
                found = parse_message(header + _read_exactly(sock, size - HEADER.size, deadline))
                if found is not None:
                    return found
    except TimeoutError:
        raise RobotError(f"primary interface {where}: no kinematics info within {timeout:g} s") from None
    except InputError as exc:
        raise RobotError(f"primary interface {where}: {exc}") from None
    except OSError as exc:
        raise RobotError(f"primary interface {where}: {exc}") from None
