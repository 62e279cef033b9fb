"""Rotation and pose helpers on plain floats, for the simulator's 500 Hz tick.

numpy and scipy cost tens of microseconds per call on 3-vectors; these cost a
few. Transforms are 3x4 row-major lists of 12 floats as in
:mod:`celld.robot.kinematics`; UR poses are ``[x, y, z, rx, ry, rz]`` (m, rad).
Functions never modify their inputs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from celld.robot.kinematics import Rows

# Below this angle (rad) the series expansions replace the closed forms.
_SMALL_ANGLE = 1e-8


def rot_from_rotvec(rx: float, ry: float, rz: float) -> list[float]:
    """Rotation matrix (9 floats, row-major) of a rotation vector (Rodrigues)."""
    theta = math.sqrt(rx * rx + ry * ry + rz * rz)
    if theta < _SMALL_ANGLE:
        # First order: I + [r]x.
        return [1.0, -rz, ry, rz, 1.0, -rx, -ry, rx, 1.0]
    kx, ky, kz = rx / theta, ry / theta, rz / theta
    c, s = math.cos(theta), math.sin(theta)
    v = 1.0 - c
    return [
        c + kx * kx * v, kx * ky * v - kz * s, kx * kz * v + ky * s,
        ky * kx * v + kz * s, c + ky * ky * v, ky * kz * v - kx * s,
        kz * kx * v - ky * s, kz * ky * v + kx * s, c + kz * kz * v,
    ]  # fmt: skip


def rotvec_from_rot(R: Sequence[float]) -> tuple[float, float, float]:
    """Rotation vector of a rotation matrix (9 floats, row-major), angle in [0, pi]."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    cos_theta = max(-1.0, min(1.0, (r00 + r11 + r22 - 1.0) * 0.5))
    theta = math.acos(cos_theta)
    if theta < _SMALL_ANGLE:
        return (0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01))
    if theta < math.pi - 1e-6:
        k = theta / (2.0 * math.sin(theta))
        return (k * (r21 - r12), k * (r02 - r20), k * (r10 - r01))
    # Near pi the skew part vanishes: take the axis from the symmetric part, sign from the skew part.
    xx = max(0.0, (r00 + 1.0) * 0.5)
    yy = max(0.0, (r11 + 1.0) * 0.5)
    zz = max(0.0, (r22 + 1.0) * 0.5)
    if xx >= yy and xx >= zz:
        x = math.sqrt(xx)
        y, z = (r01 + r10) / (4.0 * x), (r02 + r20) / (4.0 * x)
    elif yy >= zz:
        y = math.sqrt(yy)
        x, z = (r01 + r10) / (4.0 * y), (r12 + r21) / (4.0 * y)
    else:
        z = math.sqrt(zz)
        x, y = (r02 + r20) / (4.0 * z), (r12 + r21) / (4.0 * z)
    n = math.sqrt(x * x + y * y + z * z)
    x, y, z = x / n, y / n, z / n
    # Pick the sign that agrees with the (small) skew part, if any.
    if x * (r21 - r12) + y * (r02 - r20) + z * (r10 - r01) < 0.0:
        x, y, z = -x, -y, -z
    return (theta * x, theta * y, theta * z)


def rows_from_pose(pose: Sequence[float]) -> Rows:
    """3x4 transform (12 floats) of a UR pose."""
    R = rot_from_rotvec(pose[3], pose[4], pose[5])
    return [R[0], R[1], R[2], pose[0], R[3], R[4], R[5], pose[1], R[6], R[7], R[8], pose[2]]


def pose_from_rows(T: Sequence[float]) -> list[float]:
    """UR pose of a 3x4 transform (12 floats)."""
    rx, ry, rz = rotvec_from_rot((T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]))
    return [T[3], T[7], T[11], rx, ry, rz]


def rot_of(T: Sequence[float]) -> list[float]:
    """The rotation block (9 floats) of a 3x4 transform."""
    return [T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]]


def rot_mul(A: Sequence[float], B: Sequence[float]) -> list[float]:
    """Product of two rotation matrices (9 floats each)."""
    return [
        A[0] * B[0] + A[1] * B[3] + A[2] * B[6], A[0] * B[1] + A[1] * B[4] + A[2] * B[7],
        A[0] * B[2] + A[1] * B[5] + A[2] * B[8],
        A[3] * B[0] + A[4] * B[3] + A[5] * B[6], A[3] * B[1] + A[4] * B[4] + A[5] * B[7],
        A[3] * B[2] + A[4] * B[5] + A[5] * B[8],
        A[6] * B[0] + A[7] * B[3] + A[8] * B[6], A[6] * B[1] + A[7] * B[4] + A[8] * B[7],
        A[6] * B[2] + A[7] * B[5] + A[8] * B[8],
    ]  # fmt: skip


def rot_transpose(A: Sequence[float]) -> list[float]:
    return [A[0], A[3], A[6], A[1], A[4], A[7], A[2], A[5], A[8]]


def with_rotation(R: Sequence[float], p: Sequence[float]) -> Rows:
    """3x4 transform of rotation ``R`` (9 floats) and translation ``p`` (3)."""
    return [R[0], R[1], R[2], p[0], R[3], R[4], R[5], p[1], R[6], R[7], R[8], p[2]]


def relative_rotvec(T_from: Sequence[float], T_to: Sequence[float]) -> tuple[float, float, float]:
    """Rotation vector (base frame) that turns the orientation of ``T_from`` into that of ``T_to``."""
    return rotvec_from_rot(rot_mul(rot_of(T_to), rot_transpose(rot_of(T_from))))


def norm3(x: float, y: float, z: float) -> float:
    return math.sqrt(x * x + y * y + z * z)
