"""3D circles: the vectorised RANSAC fit with a radius check, and least-squares refinement.

Pure maths on (n, 3) point arrays in any one frame, metres. The flange
detector (:mod:`celld.calib.detect`) finds the rim of a flange with
:func:`ransac_circle` and polishes it with :func:`refine_circle`; the
parameters are those of the paper's section 3.2.2: the radius R with its
tolerance e_r (a model check before verification), the inlier distance e_d
and at most k_max samples.

A circle is a centre c, a unit normal n and a radius r. The distance of a
point p to it is sqrt(h**2 + (rho - r)**2), with h = (p - c) . n the height
above its plane and rho the distance from c within that plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from celld.errors import InputError

# RANSAC draws triples in vectorised batches, from this many up to _BATCH
# (doubling): a clean rim stops the search after the first small batch.
_FIRST_BATCH = 32
_BATCH = 256
# Probability that the adaptive stop has drawn at least one all-inlier triple.
_CONFIDENCE = 0.999
# Three points closer to collinear than this (|a x b| / (|a| |b|)) define no circle.
_MIN_SINE = 1e-3


@dataclass(frozen=True, eq=False)
class CircleFit:
    """A circle fitted to points, with the points that support it.

    Attributes
    ----------
    centre : numpy.ndarray
        (3,) centre, frame of the input points, m.
    normal : numpy.ndarray
        (3,) unit normal of the circle's plane (sign arbitrary).
    radius : float
        m.
    inliers : numpy.ndarray
        (n,) bool, points within the inlier distance of the circle.
    residual : float
        RMS distance of the inliers to the circle, m.
    samples : int
        Triples drawn (RANSAC) or iterations run (refinement).
    """

    centre: np.ndarray
    normal: np.ndarray
    radius: float
    inliers: np.ndarray
    residual: float
    samples: int = 0


def circles_through(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Circles through triples of points, vectorised.

    Parameters
    ----------
    A, B, C : numpy.ndarray
        (k, 3) the three points of each triple.

    Returns
    -------
    centres, normals, radii, ok
        (k, 3), (k, 3) unit, (k,), and (k,) bool: False where the triple is
        (nearly) collinear or repeated and defines no circle.
    """
    a, b = A - C, B - C
    axb = np.cross(a, b)
    axb2 = np.einsum("ij,ij->i", axb, axb)
    la2, lb2 = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
    ok = axb2 > (_MIN_SINE**2) * la2 * lb2
    ok &= axb2 > 0
    safe = np.where(ok, axb2, 1.0)
    centres = C + np.cross(la2[:, None] * b - lb2[:, None] * a, axb) / (2.0 * safe[:, None])
    radii = np.sqrt(la2 * lb2 * np.einsum("ij,ij->i", a - b, a - b) / (4.0 * safe))
    normals = axb / np.sqrt(safe)[:, None]
    return centres, normals, radii, ok


def circle_distances(P: np.ndarray, centres: np.ndarray, normals: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Distances (m, n) of points P (n, 3) to m circles (centres (m, 3), unit normals (m, 3), radii (m,))."""
    # Expand |p - c|^2 and (p - c) . n as matrix products: no (m, n, 3) temporary.
    PP = np.einsum("ij,ij->i", P, P)
    d2 = PP[None, :] - 2.0 * (centres @ P.T) + np.einsum("ij,ij->i", centres, centres)[:, None]
    h = normals @ P.T - np.einsum("ij,ij->i", normals, centres)[:, None]
    rho = np.sqrt(np.maximum(d2 - h * h, 0.0))
    return np.sqrt(h * h + (rho - radii[:, None]) ** 2)


def ransac_circle(
    P: np.ndarray,
    radius: float,
    e_r: float,
    e_d: float,
    k_max: int,
    rng: np.random.Generator,
    normal: np.ndarray | None = None,
    max_normal_angle: float = math.pi / 2,
) -> CircleFit | None:
    """RANSAC of a 3D circle of radius ``radius +- e_r`` through points P.

    Triples are drawn in vectorised batches (32, 64, ... 256). A sampled circle is verified
    only when it passes the model checks: its radius within ``e_r`` of
    ``radius`` and, when ``normal`` is given, its normal within
    ``max_normal_angle`` of it (either sign). Sampling stops after ``k_max``
    triples or once, at 99.9 % confidence, a triple of inliers has been drawn.

    Parameters
    ----------
    P : numpy.ndarray
        (n, 3) candidate points, m.
    radius, e_r, e_d : float
        Expected radius, its tolerance and the inlier distance, m.
    k_max : int
        Most triples to draw.
    rng : numpy.random.Generator
        Source of the samples (seeded by the caller).
    normal : numpy.ndarray or None
        (3,) expected normal of the circle's plane.
    max_normal_angle : float
        Largest angle between a sampled circle's normal and ``normal``, rad.

    Returns
    -------
    CircleFit or None
        The circle with the most inliers, None when no sample passed the checks.
    """
    P = np.asarray(P, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"ransac_circle: expected (n, 3) points, got shape {P.shape}")
    n = len(P)
    if n < 3:
        return None
    cos_min = math.cos(max_normal_angle)
    best_count, best = 0, None
    drawn, needed = 0, k_max
    batch = _FIRST_BATCH
    while drawn < min(k_max, needed):
        k = min(batch, k_max - drawn)
        batch = min(2 * batch, _BATCH)
        idx = rng.integers(0, n, size=(k, 3))
        drawn += k
        c, nrm, r, ok = circles_through(P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]])
        ok &= np.abs(r - radius) <= e_r  # the model check of section 3.2.2
        if normal is not None:
            ok &= np.abs(nrm @ normal) >= cos_min
        if not ok.any():
            continue
        c, nrm, r = c[ok], nrm[ok], r[ok]
        counts = (circle_distances(P, c, nrm, r) <= e_d).sum(axis=1)
        i = int(np.argmax(counts))
        if counts[i] > best_count:
            best_count, best = int(counts[i]), (c[i], nrm[i], float(r[i]))
            w = best_count / n
            needed = drawn if w >= 1.0 else math.ceil(math.log(1 - _CONFIDENCE) / math.log(1 - w**3))
    if best is None:
        return None
    c_best, n_best, r_best = best
    dist = circle_distances(P, c_best[None], n_best[None], np.array([r_best]))[0]
    inl = dist <= e_d
    return CircleFit(c_best, n_best, r_best, inl, float(np.sqrt(np.mean(dist[inl] ** 2))), drawn)


def fit_plane(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares plane of points P (n, 3): (a point on it, unit normal, RMS distance)."""
    P = np.asarray(P, dtype=np.float64)
    if len(P) < 3:
        raise InputError(f"fit_plane: need at least 3 points, got {len(P)}")
    centroid = P.mean(axis=0)
    Q = P - centroid
    _, s, Vt = np.linalg.svd(Q.T @ Q)
    normal = Vt[2]
    return centroid, normal, float(np.sqrt(max(s[2], 0.0) / len(P)))


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3) two orthonormal vectors spanning the plane normal to ``normal``."""
    n = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)])


def _circle_residuals(x: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Distances of the 2D points ``Q`` from the circle ``x = (cu, cv, r)``."""
    return np.hypot(Q[:, 0] - x[0], Q[:, 1] - x[1]) - x[2]


def refine_circle(
    P: np.ndarray, init: CircleFit, plane_point: np.ndarray, plane_normal: np.ndarray, e_d: float, iterations: int = 3
) -> CircleFit:
    """Geometric least-squares circle in a given plane, from a RANSAC start.

    The points within ``e_d`` of the current circle are projected onto the
    plane (``plane_point``, ``plane_normal``: fitted to the whole face, far
    better determined than from the rim alone) and the circle minimising the
    sum of squared radial residuals is solved (Levenberg-Marquardt); the
    inliers are re-selected and the fit repeated ``iterations`` times.

    Returns
    -------
    CircleFit
        Centre on the plane, the plane's normal, and the final inliers; the
        residual is the RMS 3D distance of those inliers to the circle.
    """
    P = np.asarray(P, dtype=np.float64)
    nrm = plane_normal / np.linalg.norm(plane_normal)
    E = plane_basis(nrm)
    uv = (P - plane_point) @ E.T
    centre_uv = (init.centre - plane_point) @ E.T
    r = init.radius
    inl = init.inliers.copy()
    for _ in range(iterations):
        if inl.sum() < 3:
            break
        sol = least_squares(_circle_residuals, np.array([centre_uv[0], centre_uv[1], r]), method="lm", args=(uv[inl],))
        centre_uv, r = sol.x[:2], float(sol.x[2])
        centre = plane_point + centre_uv @ E
        dist = circle_distances(P, centre[None], nrm[None], np.array([r]))[0]
        inl = dist <= e_d
    centre = plane_point + centre_uv @ E
    dist = circle_distances(P, centre[None], nrm[None], np.array([r]))[0]
    res = float(np.sqrt(np.mean(dist[inl] ** 2))) if inl.any() else math.inf
    return CircleFit(centre, nrm, abs(r), inl, res, iterations)


def angular_coverage(P: np.ndarray, centre: np.ndarray, normal: np.ndarray, bins: int = 36) -> float:
    """Fraction of ``bins`` equal sectors around the circle that hold at least one point of P."""
    if len(P) == 0:
        return 0.0
    uv = (np.asarray(P, dtype=np.float64) - centre) @ plane_basis(normal).T
    angle = np.arctan2(uv[:, 1], uv[:, 0])
    sector = np.floor((angle + math.pi) / (2 * math.pi) * bins).astype(np.int64) % bins
    return len(np.unique(sector)) / bins
