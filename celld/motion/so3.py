"""Rotation-vector maps for the 500 Hz loop: exp (rotation vector -> matrix) and log.

Everywhere else celld uses :class:`scipy.spatial.transform.Rotation`. In the
loop it cannot: with scipy 1.17 one ``Rotation.from_matrix(R).as_rotvec()``
costs about 220 µs and ``from_rotvec(r).as_matrix()`` about 50 µs on these
machines (measured), a tenth of the 2 ms period. These two maps do the same on
plain floats in a few microseconds; ``tests/motion/test_so3.py`` checks them
against scipy, including near 0 and near pi.

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

# Below this angle the series of sin(t)/t and (1 - cos(t))/t^2 are used.
_SMALL_ANGLE = 1e-4
# Above this cosine-distance from pi the log uses the skew part; below it the
# symmetric part, whose axis is well conditioned there.
_NEAR_PI_COS = -0.9


def exp(rotvec: ArrayLike) -> Array:
    """Rotation matrix (3, 3) of a rotation vector (3,), rad (Rodrigues)."""
    x, y, z = (float(v) for v in np.asarray(rotvec, dtype=np.float64).reshape(3))
    t2 = x * x + y * y + z * z
    if t2 < _SMALL_ANGLE * _SMALL_ANGLE:
        a = 1.0 - t2 / 6.0  # sin(t)/t
        b = 0.5 - t2 / 24.0  # (1 - cos(t))/t^2
    else:
        t = math.sqrt(t2)
        a = math.sin(t) / t
        b = (1.0 - math.cos(t)) / t2
    # R = I + a K + b K^2, K the skew matrix of (x, y, z).
    return np.array(
        [
            [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
            [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
            [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
        ]
    )


def log(R: ArrayLike) -> Array:
    """Rotation vector (3,), rad, angle in [0, pi], of a rotation matrix (3, 3)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R, dtype=np.float64).tolist()
    c = max(-1.0, min(1.0, 0.5 * (r00 + r11 + r22 - 1.0)))
    sx, sy, sz = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)  # sin(t) * axis
    s = math.sqrt(sx * sx + sy * sy + sz * sz)
    t = math.atan2(s, c)
    if c > _NEAR_PI_COS:
        k = 1.0 + t * t / 6.0 if t < _SMALL_ANGLE else t / s
        return np.array([sx * k, sy * k, sz * k])
    # Near pi: axis from the symmetric part, S = c I + (1 - c) k k^T.
    d = 1.0 - c
    kk = ((r00 - c) / d, (r11 - c) / d, (r22 - c) / d)
    i = max(range(3), key=lambda j: kk[j])
    off = {
        (0, 1): 0.5 * (r01 + r10),
        (0, 2): 0.5 * (r02 + r20),
        (1, 2): 0.5 * (r12 + r21),
    }
    ki = math.sqrt(max(kk[i], 0.0))
    axis = [0.0, 0.0, 0.0]
    axis[i] = ki
    for j in range(3):
        if j != i:
            axis[j] = off[(min(i, j), max(i, j))] / (d * ki)
    if axis[0] * sx + axis[1] * sy + axis[2] * sz < 0.0:
        axis = [-a for a in axis]
    n = math.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
    return np.array([a * t / n for a in axis])
