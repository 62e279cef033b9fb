"""The planned seam as Algorithm 2 follows it: its welding plane, and the path in that plane.

The plan comes from the seam finder as points in the base frame. Algorithm 2
works in the paper's plane (Fig. 8): :func:`welding_plane` fits it (or takes
the one nearest a hint for a straight seam), :func:`prepare_plan` projects
the points into it, resamples them by arc length and smooths them, with the
tangents and normals the law's SERVO step reads (lines 21-26).

Pure: arrays in, arrays out, SI units.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.signal import savgol_filter

from celld import polyline
from celld.errors import InputError
from celld.se3 import check_points, check_transform

Array = np.ndarray

# Resampling step of the planned path, m.
PLAN_SPACING = 0.0005
# Plans whose second principal extent is below this share of the first are straight.
_STRAIGHT = 0.02


class PlannedPath(NamedTuple):
    """The planned seam in the plane, resampled and smoothed.

    ``P`` (m, 2) points, ``T`` (m, 2) unit tangents, ``N`` (m, 2) left normals,
    ``s`` (m,) arc length; ``T_base_plane`` (4, 4) embeds the plane.
    """

    T_base_plane: Array
    P: Array
    T: Array
    N: Array
    s: Array


def welding_plane(P_base: Array, normal_hint: Array) -> Array:
    """The welding plane of a planned path, ``T_base_plane`` (4, 4).

    The plane is fitted to the points; a straight path (or one that bends too
    little to fix a plane) gets the plane through it whose normal is nearest
    to ``normal_hint``. The normal points along the hint (away from the work,
    along the finger), x runs from the first point towards the last, the
    origin is the first point.
    """
    P = check_points(P_base, "P_base", min_points=2)
    hint = np.asarray(normal_hint, dtype=np.float64)
    hint = hint / np.linalg.norm(hint)
    _, sv, Vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
    if len(sv) >= 2 and sv[1] > _STRAIGHT * sv[0]:
        z = Vt[-1] if len(sv) == 3 else np.cross(Vt[0], Vt[1])
    else:
        line = Vt[0]
        z = hint - float(hint @ line) * line
        if np.linalg.norm(z) < 1e-6:
            raise InputError("welding plane: the planned path runs along the normal hint; give the plane explicitly")
    z = z / np.linalg.norm(z)
    if float(z @ hint) < 0.0:
        z = -z
    x = P[-1] - P[0]
    x = x - float(x @ z) * z
    if np.linalg.norm(x) < 1e-9:
        x = Vt[0] - float(Vt[0] @ z) * z
    x = x / np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = P[0]
    return T


def prepare_plan(P_base: Array, T_base_plane: Array, smoothing: float, spacing: float = PLAN_SPACING) -> PlannedPath:
    """Project the planned points into the plane, resample by arc length and smooth.

    Parameters
    ----------
    P_base : (n, 3)
        Planned seam points in the base frame, m, in order of travel.
    T_base_plane : (4, 4)
    smoothing : float
        Length of the Savitzky-Golay window (quadratic), m; 0 for none. A
        scanner's noise on single points would otherwise tilt the tangents.
    spacing : float
        Resampling step, m.
    """
    P = check_points(P_base, "P_base", min_points=2)
    T_bp = check_transform(T_base_plane, "T_base_plane")
    Q = (P - T_bp[:3, 3]) @ T_bp[:3, :2]
    step = np.linalg.norm(np.diff(Q, axis=0), axis=1)
    keep = np.concatenate([[True], step > 1e-9])
    Q = Q[keep]
    s = polyline.arc_length(Q)
    if len(Q) < 2 or s[-1] < 4 * spacing:
        raise InputError(f"planned path: expected at least {4 * spacing * 1e3:.1f} mm of travel in the plane, got {s[-1] * 1e3:.3f} mm")
    m = max(int(math.ceil(s[-1] / spacing)) + 1, 5)
    si = np.linspace(0.0, s[-1], m)
    R = np.column_stack([np.interp(si, s, Q[:, 0]), np.interp(si, s, Q[:, 1])])
    window = min(int(round(smoothing / (si[1] - si[0]))) | 1, m if m % 2 else m - 1)
    if window >= 5:
        # Tangents from the fitted quadratics' own slopes: differencing the
        # smoothed points would bring back the noise the filter lets through.
        Tg = savgol_filter(R, window, 2, deriv=1, axis=0, mode="interp")
        R = savgol_filter(R, window, 2, axis=0, mode="interp")
    else:
        Tg = np.gradient(R, axis=0)
    Tg /= np.linalg.norm(Tg, axis=1)[:, None]
    N = np.column_stack([-Tg[:, 1], Tg[:, 0]])
    sR = polyline.arc_length(R)
    return PlannedPath(T_bp, R, Tg, N, sR)
