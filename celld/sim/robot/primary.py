"""The simulated controller's primary interface (port 30001): its messages, as bytes.

What a client reads there (:mod:`celld.robot.primary` reads the kinematics):
a version message when it connects, then a robot state message at 10 Hz. The
robot state carries a robot mode package (its contents zeros here: nothing
reads them) and the kinematics info package, the table the controller
computes with (:attr:`celld.sim.robot.controller.Controller.kinematics`).
"""

from __future__ import annotations

import struct
import zlib

from celld.robot import kinematics as kin
from celld.robot import primary as pi

MESSAGE_ROBOT_MESSAGE = 20
ROBOT_MESSAGE_VERSION = 3
PACKAGE_ROBOT_MODE = 0
# A robot mode data package's body on an e-series controller (its header aside), bytes.
ROBOT_MODE_BODY = 42
# Robot state is sent every this many 2 ms cycles (10 Hz).
STATE_EVERY = 50
# The calibration status a factory-calibrated arm reports (UR: "linearised"; the number is the simulator's).
CALIBRATED = 2


def _framed(kind: int, body: bytes) -> bytes:
    return pi.HEADER.pack(pi.HEADER.size + len(body), kind) + body


def checksums(dh: kin.DH) -> tuple[int, ...]:
    """A checksum per joint: CRC-32 of the joint's four numbers (the controller's own function is not published)."""
    return tuple(zlib.crc32(struct.pack(">4d", dh.theta[j], dh.a[j], dh.d[j], dh.alpha[j])) for j in range(6))


def kinematics_package(dh: kin.DH, status: int = CALIBRATED) -> bytes:
    """The kinematics info package of table ``dh``."""
    return _framed(pi.PACKAGE_KINEMATICS_INFO, pi.KINEMATICS_INFO.pack(*checksums(dh), *dh.theta, *dh.a, *dh.d, *dh.alpha, status))


def robot_state_message(dh: kin.DH, status: int = CALIBRATED) -> bytes:
    """A robot state message: robot mode, then the kinematics of ``dh``."""
    body = _framed(PACKAGE_ROBOT_MODE, bytes(ROBOT_MODE_BODY)) + kinematics_package(dh, status)
    return _framed(pi.MESSAGE_ROBOT_STATE, body)


def version_message(version: tuple[int, int, int, int], timestamp_us: int = 0) -> bytes:
    """The version message a client gets when it connects."""
    name = b"URControl"
    major, minor, bugfix, build = version
    body = struct.pack(">QbbB", timestamp_us, -1, ROBOT_MESSAGE_VERSION, len(name)) + name
    body += struct.pack(">BBii", major, minor, bugfix, build) + b"01-01-2026, 00:00:00"
    return _framed(MESSAGE_ROBOT_MESSAGE, body)
