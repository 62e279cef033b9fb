"""Calibration poses: where the robot shows its flange to the scanner.

Pure: a verification pose, a workspace box around it and a tilt bound in,
flange poses ``T_base_flange`` out. Positions fill the box on a jittered grid
(never collinear, which Eq. 9-12 cannot solve, and spread in all three
directions, which fixes every rotation of the solution well); orientations
tilt the flange face, which looks up at a scanner above the table, by up to
``max_tilt`` about the base x and y axes and turn it about its own axis by up
to ``max_spin``. Deterministic for a seed.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from celld import se3
from celld.errors import InputError

# Turn about the flange's own axis, rad: the circle does not care, the wrist does.
MAX_SPIN = 0.5


def calibration_poses(
    T_base_flange_v: ArrayLike,
    box: ArrayLike,
    n: int,
    max_tilt: float,
    seed: int = 0,
    max_spin: float = MAX_SPIN,
) -> np.ndarray:
    """Return ``n`` flange poses (n, 4, 4) in a box centred on the verification pose.

    Parameters
    ----------
    T_base_flange_v : (4, 4)
        The verification pose; its orientation is the reference the tilts apply to.
    box : (3,)
        Edge lengths of the workspace box along the base axes, metres.
    n : int
        Number of poses, at least 4.
    max_tilt : float
        Largest tilt of the flange axis, rad (about 0.3 in the paper's set-up).
    """
    T_v = se3.check_transform(T_base_flange_v, "T_base_flange_v")
    box = np.asarray(box, dtype=np.float64)
    if box.shape != (3,) or not np.all(box > 0):
        raise InputError(f"box: expected 3 positive edge lengths in metres, got {box.tolist()}")
    if n < 4:
        raise InputError(f"n: a calibration needs at least 4 poses, got {n}")
    if not 0.0 <= max_tilt < math.pi / 2:
        raise InputError(f"max_tilt: expected 0 <= tilt < pi/2 rad, got {max_tilt}")
    rng = np.random.default_rng(seed)
    # A grid with about n cells, each pose jittered inside its cell.
    k = max(2, math.ceil(n ** (1.0 / 3.0)))
    cells: np.ndarray = np.stack(np.meshgrid(*(np.arange(k),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    cells = cells[rng.permutation(len(cells))[:n]] if len(cells) >= n else cells[rng.integers(0, len(cells), n)]
    u = (cells + rng.uniform(0.2, 0.8, (n, 3))) / k - 0.5
    P_base = T_v[:3, 3] + u * box
    tilt = rng.uniform(-max_tilt, max_tilt, (n, 2)) / math.sqrt(2.0)
    spin = rng.uniform(-max_spin, max_spin, n)
    R_tilt = Rotation.from_euler("xy", tilt)
    R_spin = Rotation.from_euler("z", spin[:, None])
    R = (R_tilt * Rotation.from_matrix(T_v[:3, :3]) * R_spin).as_matrix()
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = P_base
    return T
