"""Polylines: arc length, resampling, nearest points, projection, thinning.

One home for the geometry of a path given as points in order, (n, d) with
d = 2 (a path in the welding plane) or d = 3 (base or model frame), metres.
The servo (Algorithm 2's nearest points), the seam finder, the weld job, the
figures and the simulator all use it.

- :func:`arc_length`: cumulative length at each point;
- :func:`resample`: equal arc-length steps;
- :func:`nearest`: the nearest point to one query, within a window of
  segments (the servo's hot path: no k-d tree, no allocation beyond the window);
- :func:`project`: nearest points for many queries (k-d tree, exact on the
  segments);
- :func:`distance`, :func:`signed_offset`: distances to a path, unsigned
  or (2D) signed to the left of travel;
- :func:`thin`, :func:`slide`: fewer points, and points moved along the path.

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

Array = NDArray[np.float64]


class Projection(NamedTuple):
    """Nearest points on a polyline for a set of query points."""

    point: Array  # (n, d) nearest point on the polyline
    tangent: Array  # (n, d) unit tangent of the polyline there
    arc: Array  # (n,) arc length of the nearest point from the start, m
    inside: NDArray[np.bool_]  # (n,) False where the nearest point is an end of the polyline


def arc_length(P: Array) -> Array:
    """Cumulative arc length (n,) at each point of ``P`` (n, d), 0 at the first."""
    P = np.asarray(P, dtype=np.float64)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])


def resample(P: Array, spacing: float) -> tuple[Array, float]:
    """``P`` (n, d) resampled at equal arc-length steps close to ``spacing`` (m).

    Returns the points (k, d), first and last kept, and the actual step (m).
    """
    P = np.asarray(P, dtype=np.float64)
    s = arc_length(P)
    n = max(1, int(round(s[-1] / spacing)))
    si = np.linspace(0.0, s[-1], n + 1)
    out = np.column_stack([np.interp(si, s, P[:, i]) for i in range(P.shape[1])])
    return out, float(s[-1] / n)


def nearest(P: Array, q: Array, lo: int = 0, hi: int | None = None) -> tuple[int, float, float]:
    """Nearest point to ``q`` (d,) on the segments of ``P[lo:hi]``.

    Returns the segment index ``i``, the fraction ``u`` in [0, 1] along the
    segment from ``P[i]`` to ``P[i + 1]``, and the distance. A window keeps
    the search local, so a path that comes back near itself is not mistaken
    for its other pass (Algorithm 2, lines 10 and 22).
    """
    lo = max(lo, 0)
    hi = len(P) if hi is None else min(hi, len(P))
    if hi - lo < 2:
        return lo, 0.0, float(np.linalg.norm(P[lo] - q))
    a = P[lo : hi - 1]
    ab = P[lo + 1 : hi] - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    L2 = np.where(L2 > 0.0, L2, 1e-30)
    u = np.clip(np.einsum("ij,ij->i", q - a, ab) / L2, 0.0, 1.0)
    X = a + u[:, None] * ab
    d2 = np.einsum("ij,ij->i", X - q, X - q)
    k = int(np.argmin(d2))
    return lo + k, float(u[k]), math.sqrt(float(d2[k]))


def is_inside(P: Array, i: int, u: float) -> bool:
    """Whether the point ``(i, u)`` of :func:`nearest` lies beside the path, not on one of its ends."""
    return not ((i == 0 and u <= 0.0) or (i == len(P) - 2 and u >= 1.0))


def project(Q: Array, P: Array, step: float = 2e-4) -> Projection:
    """Project points ``Q`` (n, d) onto the polyline ``P`` (m, d), exactly.

    The polyline is resampled every ``step`` m and searched with a k-d tree;
    the exact foot is then taken on the segments of the nearest sample and of
    its two neighbours (which covers a nearest point past a vertex).
    """
    Q = np.asarray(Q, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    D, _ = resample(P, step)
    seg = np.diff(P, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    T = seg / seg_len[:, None]
    arc_P = arc_length(P)
    arc_D = np.linspace(0.0, arc_P[-1], len(D))
    seg_of = np.clip(np.searchsorted(arc_P, arc_D, side="right") - 1, 0, len(seg) - 1)
    _, idx = cKDTree(D).query(Q)
    best_d = np.full(len(Q), np.inf)
    best_s = np.zeros(len(Q), dtype=np.int64)
    best_u = np.zeros(len(Q))
    for shift in (-1, 0, 1):
        s = seg_of[np.clip(idx + shift, 0, len(D) - 1)]
        u = np.clip(np.einsum("ij,ij->i", Q - P[s], T[s]), 0.0, seg_len[s])
        d = np.linalg.norm(Q - (P[s] + u[:, None] * T[s]), axis=1)
        better = d < best_d
        best_d[better], best_s[better], best_u[better] = d[better], s[better], u[better]
    point = P[best_s] + best_u[:, None] * T[best_s]
    arc = arc_P[best_s] + best_u
    inside = (arc > 1e-9) & (arc < arc_P[-1] - 1e-9)
    return Projection(point, T[best_s], arc, inside)


def distance(Q: Array, P: Array, step: float = 5e-5) -> Array:
    """Distance (n,) of each point of ``Q`` (n, d) from the polyline ``P`` (m, d)."""
    Q = np.asarray(Q, dtype=np.float64)
    return np.linalg.norm(Q - project(Q, P, step).point, axis=1)


def signed_offset(Q: Array, P: Array, step: float = 5e-5) -> tuple[Array, NDArray[np.bool_]]:
    """Signed distance (n,) of 2D points ``Q`` from the 2D polyline ``P``, positive left of travel.

    Also returns which points lie beside the path (not beyond one of its ends).
    """
    Q = np.asarray(Q, dtype=np.float64)
    proj = project(Q, P, step)
    r = Q - proj.point
    return proj.tangent[:, 0] * r[:, 1] - proj.tangent[:, 1] * r[:, 0], proj.inside


def thin(P: Array, step: float) -> Array:
    """The points of ``P`` at least ``step`` apart in order (first and last kept)."""
    P = np.asarray(P, dtype=np.float64)
    if len(P) < 3:
        return P
    keep = [0]
    for i in range(1, len(P)):
        if np.linalg.norm(P[i] - P[keep[-1]]) >= step:
            keep.append(i)
    if keep[-1] != len(P) - 1:
        keep.append(len(P) - 1)
    return P[keep]


def slide(P: Array, ds: float) -> Array:
    """The points of ``P`` moved ``ds`` (m) along it, extrapolated along the end tangents."""
    P = np.asarray(P, dtype=np.float64)
    s = arc_length(P)
    target = s + ds
    out = np.column_stack([np.interp(target, s, P[:, i]) for i in range(P.shape[1])])
    t0 = (P[1] - P[0]) / (s[1] - s[0])
    t1 = (P[-1] - P[-2]) / (s[-1] - s[-2])
    lo, hi = target < 0.0, target > s[-1]
    out[lo] = P[0] + target[lo, None] * t0
    out[hi] = P[-1] + (target[hi] - s[-1])[:, None] * t1
    return out
