"""Flange detection: the centre and normal of a robot's tool flange in a point cloud.

:func:`detect_flange` takes a cloud in the camera frame, metres, either
organized (H, W, 3) as a scanner gives it, any non-finite value marking a
missing return, or unorganized (n, 3) as a user may have cropped it: there
points with a NaN coordinate are dropped and counted (``n_dropped``) and
infinite values are refused. It returns a :class:`FlangeDetection`: the
centre of the flange frame (the TCP of the paper's Eq. 9) and the face
normal, toward the camera, with a quality record. When no flange is found it
raises :class:`~celld.errors.DetectionError` naming the stage; it never
returns a centre it has not verified.

Its parameters, and their presets per scanner, are in
:mod:`celld.calib.detect_params`. The pipeline follows the paper's section 2.1.4 in two passes. The coarse
pass (:mod:`celld.calib.segment`: crop, background planes, outlier filter,
plane segmentation, clustering with the size constraint, a coarse rim circle)
works on a thinned copy, a stride of the organized image (cut with numpy:
converting 3.2 M points to Open3D alone costs about 0.4 s) or a voxel grid of
an unorganized cloud, so that Open3D gets thousands of points, not millions.

The fine pass goes back to the full cloud around each coarse candidate (an
image window of an organized cloud):

- the face plane by least squares, trimmed from the coarse plane's slab down
  to 3 sigma of the measured noise;
- the rim: the outer edge of the face region with its holes filled. In an
  organized cloud a pixel is face by a vote of its 5 x 5 neighbourhood in a
  thin slab, so a chamfer lit on one side and in shadow on the other pulls
  the circle toward the lit side by tens of micrometres, not by half the
  slab;
- circle RANSAC on the rim with the paper's R, e_r, e_d, k_max (section
  3.2.2), then a geometric least-squares circle in the face plane.

The circle is accepted only if its radius is within e_r of R, its inliers
cover ``min_coverage`` of the circumference, and the points around it show
the model's step: the centring bore empty in the plane of the face, or the
face 6.5 mm above the shoulder for the UR10e wrist circle (an ISO 9409-1 face
is an annulus: a solid disc of the right radius is not a flange).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from celld.calib.circle import angular_coverage, fit_plane, ransac_circle, refine_circle
from celld.calib.detect_params import DetectParams
from celld.calib.flange import FlangeModel
from celld.calib.rangebias import FinishStep, measure_finish_step
from celld.calib.segment import (
    COVERAGE_BINS,
    CROSS,
    MIN_POINTS,
    CoarseCandidate,
    SearchLog,
    coarse_candidates,
    crop_mask,
    hollow,
    outer_edge,
    pcd,
    project,
    raster_cells,
    spacing,
)
from celld.errors import DetectionError, InputError

# A cloud in the camera frame whose median range is outside this window (m)
# is not in metres: scanners see from about 0.1 m to a few metres.
_PLAUSIBLE_RANGE = (0.05, 20.0)
# Points sampled to check the scale of a cloud.
_SCALE_SAMPLE = 4096
# The rim of an unorganized cloud is cut from the face plane at this many sigmas of its noise.
_RIM_SIGMAS = 2.5
# Organized: a pixel is face when most of its (2 h + 1)^2 neighbourhood is within this many sigmas.
_VOTE_SIGMAS = 2.0
_VOTE_BELOW = 0.5
_VOTE_HALF = 2
# Floor of the slabs above, m (a noise-free cloud has sigma 0).
_SLAB_MIN = 2e-5
# Fine-pass circle normal against the face plane, rad (the rim is projected on it).
_FINE_NORMAL_ANGLE = math.radians(5)
# Voxel size of the coarse pass on an unorganized cloud, in flange radii.
_COARSE_VOXELS_PER_RADIUS = 12
# Coarse candidates tried in the fine pass before giving up.
_MAX_CANDIDATES = 3


@dataclass(frozen=True, eq=False)
class FlangeDetection:
    """A verified flange in a cloud: pose of its centre and the quality of the fit.

    Attributes
    ----------
    center : numpy.ndarray
        (3,) origin of the flange frame (face centre, the TCP), camera frame, m.
    normal : numpy.ndarray
        (3,) unit face normal (flange +z), pointing toward the camera.
    radius : float
        Fitted radius of the model's circle, m.
    inliers : int
        Rim points within e_d of the circle.
    residual : float
        RMS distance of the rim inliers to the circle, m.
    n_input : int
        Points given (H * W for an organized cloud).
    circle_center : numpy.ndarray
        (3,) centre of the fitted circle (differs from ``center`` when the
        circle lies behind the face, as on ``ur10e-wrist``), m.
    coverage : float
        Fraction of the circumference covered by rim inliers.
    plane_rms : float
        RMS distance of the face points to their plane, m.
    n_face : int
        Points of the face plane in the fine pass.
    n_dropped : int
        NaN points dropped from an unorganized cloud.
    window_px : tuple of 4 int or None
        ``(row0, row1, col0, col1)``: the image window (rows row0:row1, cols
        col0:col1) of the full-resolution pixels the fine pass fitted on, of
        an organized cloud; None for an unorganized one. The fine pass reads
        nothing outside it, the coarse pass nothing off :func:`coarse_grid`
        (finiteness aside): a copy of the cloud exact on both gives the same
        detection.
    finish_step : FinishStep or None
        The metal face's height over the painted shoulder in this capture
        (:func:`~celld.calib.rangebias.measure_finish_step`): what measures a
        time-of-flight camera's range bias on metal. None when the flange has
        no painted shoulder in view.
    """

    center: np.ndarray
    normal: np.ndarray
    radius: float
    inliers: int
    residual: float
    n_input: int
    circle_center: np.ndarray
    coverage: float
    plane_rms: float
    n_face: int
    n_dropped: int = 0
    window_px: tuple[int, int, int, int] | None = None
    finish_step: FinishStep | None = None


class _Input(NamedTuple):
    P: np.ndarray  # (H, W, 3) organized, or (n, 3) finite
    organized: bool
    n_input: int
    n_dropped: int


# -- input --------------------------------------------------------------------


def _validate(points: np.ndarray) -> _Input:
    try:
        P = np.asarray(points)
    except (TypeError, ValueError) as exc:
        raise InputError(f"points: expected a numeric array, got {type(points).__name__}") from exc
    if P.dtype.kind not in "fiu":
        raise InputError(f"points: expected real numbers, got dtype {P.dtype}")
    if P.dtype.kind != "f":
        P = P.astype(np.float64)
    if P.ndim == 3 and P.shape[2] == 3:
        if P.shape[0] * P.shape[1] == 0:
            raise InputError(f"points: the organized cloud is empty, shape {P.shape}")
        return _Input(P, True, P.shape[0] * P.shape[1], 0)
    if P.ndim == 2 and P.shape[1] == 3:
        if len(P) == 0:
            raise InputError("points: the cloud is empty")
        if np.isinf(P).any():
            raise InputError(f"points: {int(np.isinf(P).any(axis=1).sum())} points have infinite coordinates")
        finite = ~np.isnan(P).any(axis=1)
        n_dropped = int(len(P) - finite.sum())
        if n_dropped == len(P):
            raise InputError(f"points: all {len(P)} points are NaN")
        return _Input(P[finite] if n_dropped else P, False, len(P), n_dropped)
    raise InputError(f"points: expected an organized (H, W, 3) or an (n, 3) cloud, got shape {P.shape}")


def _check_scale(P: np.ndarray, units: str = "m") -> None:
    """Refuse a cloud whose distances from the camera are not plausible in metres."""
    flat = P.reshape(-1, 3)
    step = max(1, len(flat) // _SCALE_SAMPLE)
    sample = flat[::step]
    sample = sample[np.isfinite(sample).all(axis=1)]
    if len(sample) == 0:
        return
    r = float(np.median(np.linalg.norm(sample, axis=1)))
    lo, hi = _PLAUSIBLE_RANGE
    if r > hi:
        raise InputError(
            f"points: the median distance from the camera is {r:.4g} m, expected {lo}-{hi} m; "
            f"the data look like millimetres declared as {units!r} (use to_metres(points, 'mm'))"
        )
    if r < lo:
        raise InputError(
            f"points: the median distance from the camera is {r:.4g} m, expected {lo}-{hi} m; "
            f"the data are not in the declared units {units!r} (metres given as millimetres?)"
        )


def to_metres(points: np.ndarray, units: str) -> np.ndarray:
    """Convert a camera-frame cloud from ``units`` ("mm" or "m") to metres, checking the scale.

    The floating dtype is kept (float32 stays float32); integers become float64.

    Raises
    ------
    InputError
        Unknown units, or data that do not look like the stated units (their
        median distance from the camera would be outside 0.05-20 m).
    """
    scale = {"m": 1.0, "mm": 1e-3}.get(units)
    if scale is None:
        raise InputError(f"units: expected 'm' or 'mm', got {units!r}")
    P = np.asarray(points)
    if P.dtype.kind not in "fiu":
        raise InputError(f"points: expected real numbers, got dtype {P.dtype}")
    P = P.astype(P.dtype if P.dtype.kind == "f" else np.float64) * scale
    _check_scale(P, units)
    return P


# -- fine pass ----------------------------------------------------------------


class _Face(NamedTuple):
    """The face plane fitted at full resolution."""

    point: np.ndarray  # (3,) on the plane, camera frame, m
    normal: np.ndarray  # (3,) unit
    sigma: float  # robust noise of the face points along the normal, m
    rms: float  # RMS distance of the face points to the plane, m
    h: np.ndarray  # (n,) signed distance of every region point to the plane, m


def _fit_face(P: np.ndarray, point: np.ndarray, normal: np.ndarray, params: DetectParams) -> _Face:
    """Least-squares plane, trimmed from the coarse slab down to 3 sigma of the measured noise.

    Points of a chamfer inside a wide slab would lower and tilt the plane.
    """
    slab = params.e_plane_coarse
    # The first rounds on a quarter of the points: they only need to find the slab.
    for sub in (P[::4], P[::4], P, P):
        h = (sub - point) @ normal
        face = np.abs(h) <= slab
        if face.sum() < MIN_POINTS:
            raise DetectionError("plane", f"only {int(face.sum())} points on the face plane")
        point, normal, rms = fit_plane(sub[face])
        h = (sub - point) @ normal
        sigma = 1.4826 * float(np.median(np.abs(h[face])))
        slab = min(params.e_plane, max(3.0 * sigma, _SLAB_MIN))
    return _Face(point, normal, sigma, rms, h)


def _rim_image(h_img: np.ndarray, region: np.ndarray, sigma: float, e_plane: float) -> np.ndarray:
    """Rim pixels (bool image) of the face in an image of heights toward the camera (NaN: no point).

    Only pixels of ``region`` (bool image) can be face. A pixel is face when
    its height lies in a thin slab (0.5 sigma below the plane to 2 sigma
    above: whatever lies beyond a face edge is lower) and at least half the
    expected share of its valid 5 x 5 neighbours does too; missing returns
    are not counted. A single noisy pixel cannot carry the rim outward, and
    a chamfer just beyond the edge moves the rim about as little where it
    is lit (seen just below the plane) as where it is in shadow (missing).
    """
    with np.errstate(invalid="ignore"):
        near = (h_img <= min(e_plane, max(_VOTE_SIGMAS * sigma, _SLAB_MIN))) & region
        near &= h_img >= -min(e_plane, max(_VOTE_BELOW * sigma, _SLAB_MIN))
        # Fraction of face pixels inside the slab: the vote expects that many.
        wide = region & (np.abs(h_img) <= e_plane)
    p_near = near.sum() / max(int(wide.sum()), 1)
    size = 2 * _VOTE_HALF + 1
    valid = region & np.isfinite(h_img)
    # Box means (separable) of the two masks: the share of near pixels among the valid ones.
    votes = ndimage.uniform_filter(near.astype(np.float32), size, mode="constant")
    seen = ndimage.uniform_filter(valid.astype(np.float32), size, mode="constant")
    face = (votes >= 0.5 * p_near * np.maximum(seen, 0.5 / size**2)) & near & valid
    filled = ndimage.binary_fill_holes(face, structure=CROSS)
    return filled & ~ndimage.binary_erosion(filled, structure=CROSS) & face


def _region(
    inp: _Input, cells: np.ndarray | None, stride: int, cand: CoarseCandidate, flange: FlangeModel, params: DetectParams
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int] | None]:
    """Full-resolution points near the coarse circle.

    Returns the points as an image window (h, w, 3) float64 (organized) or
    (n, 1, 3) (unorganized), the mask (h, w) of those near the circle, and
    the bounding box ``(row0, row1, col0, col1)`` of the mask in the full
    image (None when unorganized).
    """
    lo = None
    if cells is not None:
        rc = cells[cand.idx]
        lo, hi = rc.min(axis=0), rc.max(axis=0)
        margin = 2 * stride + (hi - lo) // 5
        lo = np.maximum(lo - margin, 0)
        hi = np.minimum(hi + margin + 1, inp.P.shape[:2])
        window = inp.P[lo[0] : hi[0], lo[1] : hi[1]].astype(np.float64)
    else:
        window = inp.P.astype(np.float64, copy=False)[:, None, :]
    c0, n0 = cand.circle.centre, cand.circle.normal
    reach = cand.circle.radius + max(2 * cand.spacing, 0.1 * flange.circle_radius)
    with np.errstate(invalid="ignore"):
        d = window - c0
        h = d @ n0
        rho2 = np.einsum("...i,...i->...", d, d) - h * h
        mask = (np.abs(h) < 2 * params.e_plane_coarse) & (rho2 < reach**2)
    box = None
    if lo is not None and mask.any():
        rc = np.argwhere(mask)
        (r0, c0), (r1, c1) = lo + rc.min(axis=0), lo + rc.max(axis=0) + 1
        box = (int(r0), int(r1), int(c0), int(c1))
    return window, mask, box


def _fine(
    inp: _Input,
    cells: np.ndarray | None,
    stride: int,
    cand: CoarseCandidate,
    flange: FlangeModel,
    params: DetectParams,
    rng: np.random.Generator,
) -> FlangeDetection:
    """Face plane, rim, RANSAC and least squares at full resolution around one coarse candidate."""
    R = flange.circle_radius
    window, mask, box = _region(inp, cells, stride, cand, flange, params)
    P = window[mask]
    if len(P) < MIN_POINTS:
        raise DetectionError("plane", f"only {len(P)} points near the coarse circle")
    face = _fit_face(P, cand.circle.centre, cand.circle.normal, params)
    on_face = np.abs(face.h) <= params.e_plane
    F = P[on_face]
    if cells is not None:
        # Heights of every pixel of the window, so that the medians see what
        # lies beyond the face (a shoulder, a wall) and skip only missing returns.
        up = face.normal if face.normal @ face.point < 0 else -face.normal  # toward the camera
        with np.errstate(invalid="ignore"):
            h_img = (window - face.point) @ up
        rim = _rim_image(h_img, mask, face.sigma, params.e_plane)[mask]
    else:
        near = np.abs(face.h) <= min(params.e_plane, max(_RIM_SIGMAS * face.sigma, _SLAB_MIN))
        cell = 1.5 * spacing(P[near])
        rim = np.zeros(len(P), dtype=bool)
        rim[np.flatnonzero(near)[outer_edge(raster_cells(P[near], face.normal, cell))]] = True
    Q = project(P[rim], face.point, face.normal)
    fit = ransac_circle(Q, R, params.e_r, params.e_d, params.k_max, rng, face.normal, _FINE_NORMAL_ANGLE)
    if fit is None:
        raise DetectionError("circle", f"no rim circle of radius {R * 1e3:.2f} +- {params.e_r * 1e3:.2f} mm in {len(Q)} rim points")
    fit = refine_circle(Q, fit, face.point, face.normal, params.e_d)
    n_in = int(fit.inliers.sum())
    coverage = angular_coverage(Q[fit.inliers], fit.centre, face.normal, COVERAGE_BINS)
    if abs(fit.radius - R) > params.e_r:
        raise DetectionError("refine", f"fitted radius {fit.radius * 1e3:.3f} mm is outside {R * 1e3:.2f} +- {params.e_r * 1e3:.2f} mm")
    if n_in < params.min_inliers or coverage < params.min_coverage:
        raise DetectionError(
            "refine",
            f"the circle is supported by {n_in} rim points over {coverage:.0%} of its circumference "
            f"(need {params.min_inliers} and {params.min_coverage:.0%})",
        )
    if not hollow(F, fit.centre, face.normal, flange, params.e_plane, params.hollow_fraction, params.max_range_bias > 0.0, P):
        raise DetectionError("refine", "the model's hollow (the centring bore) holds points: a solid disc, not a flange")
    # Height of the circle's plane from the face points just inside the rim:
    # with a slab thicker than a step (ToF on ur10e-wrist) the plane averages both.
    d = F - fit.centre
    h = d @ face.normal
    rho = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))
    band = (rho > 0.85 * fit.radius) & (rho < fit.radius)
    circle_center = fit.centre + (float(np.mean(h[band])) if band.any() else 0.0) * face.normal
    normal = -face.normal if face.normal @ circle_center > 0 else face.normal  # toward the camera
    center = circle_center - flange.circle_z * normal
    return FlangeDetection(
        center=center,
        normal=normal,
        radius=fit.radius,
        inliers=n_in,
        residual=fit.residual,
        n_input=inp.n_input,
        circle_center=circle_center,
        coverage=coverage,
        plane_rms=face.rms,
        n_face=len(F),
        n_dropped=inp.n_dropped,
        window_px=box,
        finish_step=measure_finish_step(window, center, normal, flange),
    )


# -- entry point ----------------------------------------------------------------


def coarse_grid(P: np.ndarray, params: DetectParams, roi_center: np.ndarray | None = None) -> tuple[tuple[int, int, int, int], int]:
    """The pixels the coarse pass reads of an organized cloud: ``P[row0:row1:stride, col0:col1:stride]``.

    Returns ``((row0, row1, col0, col1), stride)``: the grid of every
    ``stride``-th pixel of the whole image (about ``params.coarse_points`` of
    them); or, when few of those are inside the crop (a scanner ROI, a crop
    box, a predicted centre), a finer grid over the bounding box of those that
    are, so the flange keeps its points and the crop stays cheap. Of the first
    grid only whether a point is finite and inside the crop counts.
    """
    H, W = P.shape[:2]
    stride = max(1, math.ceil(math.sqrt(H * W / params.coarse_points)))
    mask = crop_mask(P[::stride, ::stride], params, roi_center)
    n = int(mask.sum())
    if stride > 1 and 0 < n < params.coarse_points / 4:
        rc = np.argwhere(mask) * stride
        r0, c0 = np.maximum(rc.min(axis=0) - stride, 0)
        r1, c1 = np.minimum(rc.max(axis=0) + stride + 1, (H, W))
        return (int(r0), int(r1), int(c0), int(c1)), max(1, math.floor(stride * math.sqrt(n / (params.coarse_points / 3))))
    return (0, H, 0, W), stride


def _coarse_cloud(
    inp: _Input, flange: FlangeModel, params: DetectParams, roi: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, int]:
    """Thinned, cropped points (m, 3) float64, their full-resolution pixels (m, 2) (or None), and the stride."""
    if inp.organized:
        (r0, r1, c0, c1), stride = coarse_grid(inp.P, params, roi)
        mask = crop_mask(inp.P[r0:r1:stride, c0:c1:stride], params, roi)
        pix = np.array([r0, c0]) + np.argwhere(mask) * stride
        return inp.P[pix[:, 0], pix[:, 1]].astype(np.float64), pix, stride
    P = inp.P[crop_mask(inp.P, params, roi)].astype(np.float64)
    if len(P) > params.coarse_points:
        # A voxel grid, not a random subset: the spacing must stay even for the
        # DBSCAN radius and the rim raster, which are set from it.
        voxel = flange.circle_radius / _COARSE_VOXELS_PER_RADIUS
        P = np.asarray(pcd(P).voxel_down_sample(voxel).points)
        # Open3D's voxel grid comes out in a thread-dependent order: sort it,
        # so that seeded sampling downstream sees the same cloud every time.
        P = P[np.lexsort(P.T[::-1])]
    return P, None, 1


def detect_flange(
    points: np.ndarray, flange: FlangeModel, params: DetectParams | None = None, roi_center: np.ndarray | None = None
) -> FlangeDetection:
    """Find the flange in a cloud and return its centre and normal in the camera frame.

    Parameters
    ----------
    points : numpy.ndarray
        (H, W, 3) organized cloud (non-finite: no return) or (n, 3) points
        (NaN rows dropped and counted), camera frame, metres.
    flange : FlangeModel
        The flange to look for; its ``circle_radius`` is the R of the fit.
    params : DetectParams or None
        Tolerances and crop; ``DetectParams()`` (the paper's values) when None.
    roi_center : numpy.ndarray or None
        (3,) predicted flange centre in the camera frame, m (from the current
        calibration estimate); only points within ``params.roi_radius`` of it
        are searched.

    Returns
    -------
    FlangeDetection

    Raises
    ------
    InputError
        Malformed input: shape, dtype, empty, infinite values, all NaN, or a
        scale that is not metres.
    DetectionError
        No flange found; ``stage`` is crop, cluster, circle, plane or refine.
    """
    params = params or DetectParams()
    if not isinstance(flange, FlangeModel):
        raise InputError(f"flange: expected a FlangeModel, got {type(flange).__name__}")
    inp = _validate(points)
    _check_scale(inp.P)
    roi = None
    if roi_center is not None:
        roi = np.asarray(roi_center, dtype=np.float64)
        if roi.shape != (3,) or not np.isfinite(roi).all():
            raise InputError(f"roi_center: expected 3 finite numbers (camera frame, m), got {roi_center!r}")
    P, cells, stride = _coarse_cloud(inp, flange, params, roi)
    if len(P) < MIN_POINTS:
        raise DetectionError("crop", f"{len(P)} points left after the crop (box {params.crop_min}-{params.crop_max}, roi {roi})")
    rng = np.random.default_rng(params.seed)
    log = SearchLog()
    failures: list[DetectionError] = []
    for cand in coarse_candidates(P, cells, stride, flange, params, rng, log):
        try:
            return _fine(inp, cells, stride, cand, flange, params, rng)
        except DetectionError as exc:
            failures.append(exc)
            if len(failures) >= _MAX_CANDIDATES:
                break
    if failures:
        raise failures[0]
    D = 2 * flange.circle_radius
    if log.clusters == 0:
        seen = ", ".join(f"{e * 1e3:.0f}" for e in sorted(log.extents, reverse=True)[:8]) or "none"
        raise DetectionError(
            "cluster",
            f"no planar cluster {params.min_extent * D * 1e3:.0f}-{(1 + params.size_tol) * D * 1e3:.0f} mm wide "
            f"in {log.planes} planes after {log.background} background planes (widest seen, mm: {seen})",
        )
    raise DetectionError(
        "circle",
        f"none of {log.clusters} clusters has a hollow rim circle of radius {flange.circle_radius * 1e3:.2f} "
        f"+- {params.e_r * 1e3:.2f} mm covering {params.min_coverage:.0%} of it",
    )
