"""Model-free groove measurement: fit the two joint walls and intersect them.

Registration places the *nominal* seam; the actual joint can differ (fit-up,
root gap, distortion). Here the two walls of the joint (the bevels of a
V-groove, the flange and web faces of a fillet) are fitted as planes in short
windows along the seam and intersected; the intersection line is the joint's
apex as built (research/seam_anchors.md section 5: 0.02-0.4 mm at scanner
noise 0.05-0.3 mm). The walls' bisector plane gives the joint's position
across the seam (:func:`lateral_offsets`).

The only model knowledge used is where to look: which scan points belong to
which wall (``labels``, from the registered model) and the radial band around
the seam that holds the walls. The plane fits are the scan's own.

Everything here is pure: arrays in, arrays out, model frame, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from celld import polyline
from celld.config.seam import GrooveParams
from celld.seam.workpiece import LEFT_WALL, RIGHT_WALL

Array = NDArray[np.float64]

# Window outcomes.
OK = 0
UNSEEN = 1  # a wall has too few points in the window
ILL_CONDITIONED = 2  # walls near parallel, or the apex is too uncertain
CONTRADICTS = 3  # a wall's plane disagrees with the model's wall
# Robust plane fit: residual cut in robust sigmas, and its iterations.
_TRIM_SIGMAS = 3.0
_TRIM_ITERATIONS = 4
# 1.4826 * MAD is the standard deviation of a Gaussian.
_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class GrooveFit:
    """Per-window result of :func:`fit_groove` (model frame, metres).

    Attributes
    ----------
    arc : (w,) window centres, arc length along the seam from its start
    apex : (w, 3) apex point nearest the window's seam point; NaN unless OK
    direction : (w, 3) unit direction of the wall intersection, along the seam
    normals : (w, 2, 3) unit normals of the left and right wall planes (NaN if
        unfitted), facing out of the material into the joint
    offsets : (w, 2) plane offsets: a wall is ``normals . x = offsets``
    offset_var : (w, 2) variance of each wall's signed distance at the
        window's seam point, from its fit, m^2
    sigma : (w,) 1-sigma apex uncertainty estimated from the fits, m
    rms : (w, 2) RMS plane residual of the left and right wall fits, m
    count : (w, 2) points used on each wall
    length : (w,) longest window used for a wall there (see ``max_window``), m
    status : (w,) ``OK``, ``UNSEEN``, ``ILL_CONDITIONED`` or ``CONTRADICTS``
    """

    arc: Array
    apex: Array
    direction: Array
    normals: Array
    offsets: Array
    offset_var: Array
    sigma: Array
    rms: Array
    count: NDArray[np.int64]
    length: Array
    status: NDArray[np.int8]

    @property
    def ok(self) -> NDArray[np.bool_]:
        return self.status == OK


@dataclass(frozen=True)
class _Plane:
    normal: Array
    offset: float  # normal . x = offset
    centroid: Array
    rms: float
    count: int
    points: Array  # inliers


def fit_plane(X: Array) -> _Plane:
    """Least-squares plane through ``X`` (n, 3), refitted on the points within
    three robust sigmas of the previous fit, so stray points of a neighbouring
    face do not tilt it."""
    keep = np.ones(len(X), dtype=bool)
    for _ in range(_TRIM_ITERATIONS):
        c = X[keep].mean(axis=0)
        _, _, Vt = np.linalg.svd(X[keep] - c, full_matrices=False)
        n = Vt[2]
        r = (X - c) @ n
        sigma = _MAD_TO_SIGMA * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        new = np.abs(r) <= max(_TRIM_SIGMAS * sigma, 1e-7)
        if np.count_nonzero(new) < 3 or np.array_equal(new, keep):
            break
        keep = new
    c = X[keep].mean(axis=0)
    _, _, Vt = np.linalg.svd(X[keep] - c, full_matrices=False)
    n = Vt[2]
    r = (X[keep] - c) @ n
    return _Plane(n, float(n @ c), c, float(np.sqrt(np.mean(r**2))), int(np.count_nonzero(keep)), X[keep])


def intersect(p1: _Plane, p2: _Plane, near: Array) -> tuple[Array, Array, float]:
    """Point of the planes' intersection line nearest ``near``, its direction,
    and the 1-sigma uncertainty of that point (m) from the two fits.

    The point solves min |x - near|^2 subject to N x = d (N the (2, 3) normals).
    Each plane's offset uncertainty at the apex is rms^2/n (1 + r^2/s^2), with
    r the in-plane distance of the apex from the fit's centroid and s the
    spread of the points along r; it propagates through the pseudo-inverse.
    """
    N = np.vstack([p1.normal, p2.normal])
    d = np.array([p1.offset, p2.offset])
    pinv = N.T @ np.linalg.inv(N @ N.T)
    x: Array = near + pinv @ (d - N @ near)
    direction: np.ndarray = np.cross(p1.normal, p2.normal)
    direction /= np.linalg.norm(direction)
    cov = pinv @ np.diag([_offset_variance(p1, x), _offset_variance(p2, x)]) @ pinv.T
    return x, direction, float(math.sqrt(np.trace(cov)))


def _offset_variance(p: _Plane, x: Array) -> float:
    """Variance (m^2) of a fitted plane's signed distance at ``x``: the offset
    error rms^2 / n, grown by the tilt error's lever (r / s)^2, with r the
    in-plane distance of x from the fit's centroid and s the spread of the
    points along r."""
    rvec = x - p.centroid
    rvec = rvec - (rvec @ p.normal) * p.normal
    r = float(np.linalg.norm(rvec))
    lever = 0.0
    if r > 1e-9:
        s2 = float(np.mean(((p.points - p.centroid) @ (rvec / r)) ** 2))
        lever = r * r / max(s2, 1e-12)
    return max(p.rms, 1e-6) ** 2 / p.count * (1.0 + lever)


def window_centres(seam: Array, step: float) -> tuple[Array, Array, Array]:
    """Arc lengths (w,), points (w, 3) and unit tangents (w, 3) of window centres
    every ``step`` along the seam polyline, both ends included."""
    D, actual = polyline.resample(seam, step)
    arc: np.ndarray = np.arange(len(D)) * actual
    T: np.ndarray = np.gradient(D, axis=0)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    return arc, D, T


def fit_groove(
    P: Array,
    labels: NDArray[np.int8],
    seam: Array,
    approach: Array,
    band: tuple[float, float],
    params: GrooveParams,
    prior: GrooveFit | None = None,
) -> GrooveFit:
    """Fit the two joint walls in windows along the seam and intersect them.

    Parameters
    ----------
    P : (n, 3) points, model frame, m (scan points mapped by the registration,
        or the model's own samples to make the ``prior``)
    labels : (n,) wall label of each point, ``LEFT_WALL``, ``RIGHT_WALL`` or other
    seam : (m, 3) seam polyline, model frame
    approach : (3,) unit vector from the seam toward the tool, model frame
    band : (inner, outer) radial distance from the seam (m) that holds the walls
    params : GrooveParams
    prior : the same fit on the model; a wall more than
        ``params.max_normal_deviation`` from the prior's wall is ``CONTRADICTS``

    Returns
    -------
    GrooveFit with one entry per window centre of :func:`window_centres`.
    """
    arc_c, C, Tc = window_centres(seam, params.step)
    left = np.cross(approach, Tc)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    w = len(arc_c)
    apex = np.full((w, 3), np.nan)
    direction = np.full((w, 3), np.nan)
    normals = np.full((w, 2, 3), np.nan)
    offsets = np.full((w, 2), np.nan)
    offset_var = np.full((w, 2), np.nan)
    sigma = np.full(w, np.nan)
    rms = np.full((w, 2), np.nan)
    count = np.zeros((w, 2), dtype=np.int64)
    length = np.full(w, params.window)
    status = np.full(w, UNSEEN, dtype=np.int8)

    on_wall = (labels == LEFT_WALL) | (labels == RIGHT_WALL)
    P, labels = P[on_wall], labels[on_wall]
    if len(P):
        proj = polyline.project(P, seam)
        radial = np.linalg.norm(P - proj.point, axis=1)
        keep = (radial >= band[0]) & (radial <= band[1])
        P, labels, s = P[keep], labels[keep], proj.arc[keep]
        order = np.argsort(s, kind="stable")
        P, labels, s = P[order], labels[order], s[order]
    else:
        s = np.zeros(0)

    for k in range(w):
        planes = []
        for j, wall in enumerate((LEFT_WALL, RIGHT_WALL)):
            # A sparsely seen wall (grazing light, projector shadow) gets a
            # longer window, up to max_window.
            half = params.window / 2.0
            while True:
                lo, hi = np.searchsorted(s, [arc_c[k] - half, arc_c[k] + half])
                X = P[lo:hi][labels[lo:hi] == wall]
                if len(X) >= params.min_points or 2.0 * half >= params.max_window:
                    break
                half = min(2.0 * half, params.max_window / 2.0)
            count[k, j] = len(X)
            length[k] = max(length[k], 2.0 * half)
            if len(X) < params.min_points:
                break
            plane = fit_plane(X)
            # Normals face out of the material, into the joint's open side:
            # up the approach and across toward the other wall.
            across = -left[k] if wall == LEFT_WALL else left[k]
            if plane.normal @ (approach + across) < 0:
                plane = _Plane(-plane.normal, -plane.offset, plane.centroid, plane.rms, plane.count, plane.points)
            normals[k, j] = plane.normal
            offsets[k, j] = plane.offset
            offset_var[k, j] = _offset_variance(plane, C[k])
            rms[k, j] = plane.rms
            count[k, j] = plane.count
            planes.append(plane)
        if len(planes) < 2:
            continue
        if prior is not None and prior.status[k] == OK:
            dev = [math.acos(float(np.clip(planes[j].normal @ prior.normals[k, j], -1.0, 1.0))) for j in (0, 1)]
            if max(dev) > params.max_normal_deviation:
                status[k] = CONTRADICTS
                continue
        angle = math.acos(float(np.clip(abs(planes[0].normal @ planes[1].normal), 0.0, 1.0)))
        if angle < params.min_wall_angle:
            status[k] = ILL_CONDITIONED
            continue
        x, dvec, sig = intersect(planes[0], planes[1], C[k])
        sigma[k] = sig
        if sig > params.max_apex_sigma or np.linalg.norm(x - C[k]) > band[1]:
            status[k] = ILL_CONDITIONED
            continue
        apex[k] = x
        direction[k] = dvec if dvec @ Tc[k] >= 0 else -dvec
        status[k] = OK
    return GrooveFit(arc_c, apex, direction, normals, offsets, offset_var, sigma, rms, count, length, status)


def lateral_offsets(scan: GrooveFit, model: GrooveFit, seam: Array, approach: Array, step: float) -> tuple[Array, Array, NDArray[np.bool_]]:
    """How far the joint's centre line moved across the seam, per window.

    Two walls fix the joint's side-to-side position, not its depth: a V-groove
    whose gap opened looks the same to its bevels as one sitting deeper. So
    the seam keeps the registered model's depth and moves only across, in the
    seam plane, onto the walls' bisector plane (the points equally far from
    both walls) as measured: by s such that the scan's bisector distance at
    ``seam + s * left`` equals the model's at the seam.

    Parameters
    ----------
    scan, model : fits of the scan and of the model's own samples
    seam, approach : the model seam polyline and approach, model frame
    step : the window spacing the fits used, m

    Returns
    -------
    s (w,) signed shift along ``approach x tangent`` (to the left), m; its
    1-sigma (w,); and the mask of windows where both fits are OK.
    """
    _, C, T = window_centres(seam, step)
    left: np.ndarray = np.cross(approach, T)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    valid = scan.ok & model.ok
    shift = np.full(len(C), np.nan)
    sigma: np.ndarray = np.full(len(C), np.nan)
    for k in np.flatnonzero(valid):
        m_scan, g_scan = _bisector_distance(scan, k, C[k])
        _, g_model = _bisector_distance(model, k, C[k])
        across = float(m_scan @ left[k])
        if abs(across) < 0.2:  # a bisector along the seam plane cannot place it
            valid[k] = False
            continue
        diff = scan.normals[k, 0] - scan.normals[k, 1]
        shift[k] = (g_model - g_scan) / across
        sigma[k] = math.sqrt(scan.offset_var[k].sum()) / float(np.linalg.norm(diff)) / abs(across)
    return shift, sigma, valid


def wall_distances(
    fit: GrooveFit, side: int, points: Array, toward: Array, approach: Array
) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
    """How far one wall stands across the seam, per window, as the scan measured it.

    From the seam point ``x`` raised by ``h`` along ``approach``, the ray along
    ``toward`` meets the wall's fitted plane ``n . y = d`` at ``t(h) = t0 +
    slope h`` (a plane: linear in the height). A finger pressing that wall at
    height h stands t(h) off the seam; a part's gap variation, twist and tacks
    move it, its model does not.

    Parameters
    ----------
    fit : the scan's groove fit (model frame)
    side : 0 for the left wall, 1 for the right one
    points : (w, 3) the seam at the window centres
    toward : (w, 3) unit directions across the seam towards the wall
    approach : (3,) unit direction out of the joint

    Returns
    -------
    t0 (w,) m, slope (w,), the 1-sigma of t0 (w,) m from the wall's fit, and the
    mask of windows whose wall was fitted, agrees with the model and meets the ray
    at an angle.
    """
    n, d = fit.normals[:, side], fit.offsets[:, side]
    nu = np.einsum("ij,ij->i", n, toward)
    ok = np.all(np.isfinite(n), axis=1) & np.isfinite(d) & (fit.status != CONTRADICTS) & (fit.status != UNSEEN)
    ok &= np.abs(np.nan_to_num(nu)) > 0.2
    safe = np.where(ok, nu, 1.0)
    t0 = np.where(ok, (d - np.einsum("ij,ij->i", n, points)) / safe, np.nan)
    slope = np.where(ok, -(n @ approach) / safe, np.nan)
    sigma = np.where(ok, np.sqrt(np.abs(fit.offset_var[:, side])) / np.abs(safe), np.nan)
    return t0, slope, sigma, ok


def _bisector_distance(fit: GrooveFit, k: int, x: Array) -> tuple[Array, float]:
    """Unit normal of the walls' bisector plane and the signed distance of x from it."""
    n1, n2 = fit.normals[k]
    diff = n1 - n2
    scale = float(np.linalg.norm(diff))
    g = ((n1 @ x - fit.offsets[k, 0]) - (n2 @ x - fit.offsets[k, 1])) / scale
    return diff / scale, g


def smooth_offsets(
    arc_w: Array, shift: Array, sigma: Array, length: np.ndarray, valid: NDArray[np.bool_], arc: np.ndarray, span: float, step: float
) -> tuple[Array, Array]:
    """Shifts at seam stations: a local linear fit over the windows within
    ``span / 2`` of each station, weighted by 1 / sigma^2.

    Real deviations of a part from its model (fit-up, distortion) vary slowly
    along the seam; the fit averages the window noise away. Overlapping
    windows share points, so the standard error is inflated by the overlap
    (window length / ``step``).

    Parameters
    ----------
    arc_w, shift, sigma, length : (w,) window centres, shifts, their 1-sigma
        and window lengths (m); valid : (w,) windows to use
    arc : (k,) station arc lengths, m
    span : smoothing length, m; step : window spacing, m

    Returns
    -------
    shifts (k,) (NaN where no valid window is within ``span / 2``) and their
    1-sigma standard errors (k,), m
    """
    a, y = arc_w[valid], shift[valid]
    w = 1.0 / np.maximum(sigma[valid], 1e-7) ** 2
    overlap = np.maximum(length[valid] / step, 1.0)
    out = np.full(len(arc), np.nan)
    se = np.full(len(arc), np.nan)
    for i, s in enumerate(arc):
        near = np.abs(a - s) <= span / 2.0
        if not np.any(near):
            continue
        x, wi = a[near] - s, w[near]
        X = np.column_stack([np.ones_like(x), x]) if np.ptp(x) > step / 2.0 else np.ones((len(x), 1))
        cov = np.linalg.inv(X.T @ (wi[:, None] * X))
        out[i] = float((cov @ (X.T @ (wi * y[near])))[0])
        se[i] = math.sqrt(cov[0, 0] * float(np.mean(overlap[near])))
    return out, se
