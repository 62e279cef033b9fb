"""Workpiece scan to seam path: crop, register, measure the groove, hand over.

:func:`find_seam` takes one scanner cloud (camera frame), the part model and
the hand-eye transform ``T_base_cam`` and returns a :class:`SeamPath` in the
robot base frame, ready for the tactile servo (paper section 3.3: register the
scan with the CAD model to place the seam in the camera frame, then move it to
the base with the hand-eye calibration). Steps:

1. Check the cloud (shape, units) and cut it to the part with numpy: points
   above the table in the region of interest, in the base frame.
2. Register the model (:mod:`celld.seam.register`): FPFH + RANSAC, ICP,
   fitness gate with re-seeding.
3. Check the scan shows the seam: every seam station must have scan points
   near it (else the scan is partial), and the joint walls the camera should
   see must be there (else it is a different part or a wrong fit).
4. Measure the joint model-free (:mod:`celld.seam.groove`): the two walls'
   bisector gives the joint's position across the seam. Where the walls were
   measured along the seam and differ from the registered model by more than
   their own uncertainty, the seam moves across onto them (its depth stays
   the registration's: two walls cannot tell a wider gap from a deeper
   groove); the walls contradicting the model is a refusal. The joint's two
   ends in the scan slide the seam along itself (registration is weak along
   a seam whose end faces the camera sees at grazing angles).
5. Resample at a fixed spacing, order from start to end, and attach tangents,
   normals and quality figures.

Every refusal is a :class:`~celld.errors.SeamError` subclass with a reason;
no wrong path is ever returned in place of a refusal.

Seam plane and normals (the contract with the servo): ``plane_normal`` is the
approach direction of the part (out of the joint toward the tool; +z for a
part lying on the table). The servo works in the plane normal to it, which
holds the seam (paper section 2.2.2, Fig. 8: the 2D plane of Algorithm 2). At
each point ``tangent`` is the unit travel direction and ``normal`` =
``plane_normal x tangent`` (the paper's n = [-sin a, cos a] for t = [cos a,
sin a]): it lies in the seam plane, across the seam, pointing to the wall on
the left of travel seen from the tool. With ``finger_wall = "right"`` the
normals point the other way. The finger rides on the wall the normals point
to, pressing along +normal; its deformation grows along -normal.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from celld import polyline, se3
from celld.config.seam import SeamParams
from celld.errors import GrooveError, RegistrationError, ScanError
from celld.log import get_logger
from celld.scanner.base import OrganizedCloud
from celld.seam.groove import CONTRADICTS, GrooveFit, fit_groove, lateral_offsets, smooth_offsets, wall_distances
from celld.seam.register import PreparedModel, prepare_model, register
from celld.seam.workpiece import NO_WALL, Workpiece

log = get_logger(__name__)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SeamQuality:
    """Quality figures of one seam (SI units; NaN where not measured).

    source : ``"groove"`` (measured walls) or ``"model"`` (registered model)
    source_reason : why the model seam was used, ``""`` for the groove
    fitness : share of scan points on the registered model
    inlier_rmse : RMS distance of those points, m
    attempts : RANSAC seeds tried
    coverage : share of seam stations with scan points near them
    across_support : share of the points near the seam on faces facing across it
    wall_support : share of the wall samples the camera should see that it saw
    groove_coverage : share of stations where the groove was measured
    groove_windows_ok : share of groove windows with a good wall pair
    groove_contradicting : share of windows whose walls contradict the model
    apex_sigma : median 1-sigma uncertainty of the groove windows' across-seam
        position, m
    wall_rms : median RMS residual of the wall plane fits, m
    model_groove_rms, model_groove_max : distance between the measured and
        the registered seam, RMS and max, m
    deviation_sigma : median standard error of that distance, m
    lateral_shift_mean : mean shift of the measured seam from the model's
        across the seam, toward the left wall positive, m
    along_shift : the seam's ends measured in the scan lie this far along
        the seam from the registered model's (mean of both ends); the path is
        slid by it, m (NaN: not measured)
    n_points : part points in the scan after cropping
    reversed : the model seam was reversed to match the nominal direction
    duration : s, from cloud to path
    """

    source: str
    source_reason: str
    fitness: float
    inlier_rmse: float
    attempts: int
    coverage: float
    across_support: float
    wall_support: float
    groove_coverage: float
    groove_windows_ok: float
    groove_contradicting: float
    apex_sigma: float
    wall_rms: float
    model_groove_rms: float
    model_groove_max: float
    deviation_sigma: float
    lateral_shift_mean: float
    along_shift: float
    n_points: int
    reversed: bool
    duration: float

    def to_dict(self) -> dict[str, Any]:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}


@dataclass(frozen=True, eq=False)
class SeamPath:
    """The seam in the robot base frame, ready for the tactile servo.

    Attributes
    ----------
    points_base : (n, 3) m, ordered from start to end, ``spacing`` apart
    tangents : (n, 3) unit travel directions
    normals : (n, 3) unit, in the seam plane, ``plane_normal x tangent``
        (toward the left wall; toward the right one if ``finger_wall`` is right)
    plane_normal : (3,) unit approach direction, normal of the seam plane
    spacing : m between consecutive points
    model_points_base : (n, 3) the registered model's seam at the same stations
    T_base_obj : (4, 4) registered pose of the part model
    quality : SeamQuality
    wall_across : (n, 2) the finger wall as the scan measured it beside each
        point: rows ``(t0, slope)``, the wall ``t0 + slope h`` m across from the
        point (along ``normals``) at ``h`` above it; NaN where unmeasured
    far_wall_across : (n, 2) the joint's other wall the same way, across from
        each point against ``normals``
    """

    points_base: Array
    tangents: Array
    normals: Array
    plane_normal: Array
    spacing: float
    model_points_base: Array
    T_base_obj: Array
    quality: SeamQuality
    wall_across: Array = field(default_factory=lambda: np.zeros((0, 2)))
    far_wall_across: Array = field(default_factory=lambda: np.zeros((0, 2)))

    def __post_init__(self) -> None:
        for name in ("wall_across", "far_wall_across"):
            if len(getattr(self, name)) == 0:  # not measured
                object.__setattr__(self, name, np.full((len(self.points_base), 2), np.nan))
        for name in (
            "points_base",
            "tangents",
            "normals",
            "plane_normal",
            "model_points_base",
            "T_base_obj",
            "wall_across",
            "far_wall_across",
        ):
            a = np.array(getattr(self, name), dtype=np.float64)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def length(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.points_base, axis=0), axis=1)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: lengths in metres, frame ``base``."""
        return {
            "frame": "base",
            "units": "m",
            "spacing": self.spacing,
            "points_base": self.points_base.tolist(),
            "tangents": self.tangents.tolist(),
            "normals": self.normals.tolist(),
            "plane_normal": self.plane_normal.tolist(),
            "model_points_base": self.model_points_base.tolist(),
            "T_base_obj": self.T_base_obj.tolist(),
            "wall_across": _rows(self.wall_across),
            "far_wall_across": _rows(self.far_wall_across),
            "quality": self.quality.to_dict(),
        }


def _rows(a: Array) -> list[list[float | None]]:
    """JSON-ready rows, NaN as null."""
    return [[v if math.isfinite(v) else None for v in row] for row in np.asarray(a).tolist()]


@dataclass(frozen=True, eq=False)
class PreparedWorkpiece:
    """A part made ready once for many scans.

    model : the registration model; groove_prior : the groove fitted on the
    model's own samples (None without labelled walls); wall_points,
    wall_normals : (k, 3) model wall samples within the wall band of the seam;
    scene : the model mesh for ray casting (what hides the joint from the camera).
    """

    workpiece: Workpiece
    model: PreparedModel
    groove_prior: GrooveFit | None
    wall_points: Array
    wall_normals: Array
    scene: o3d.t.geometry.RaycastingScene
    params: SeamParams


def prepare(workpiece: Workpiece, params: SeamParams | None = None) -> PreparedWorkpiece:
    """Sample and describe ``workpiece`` for :func:`find_seam` (once per part and params)."""
    params = params or SeamParams()
    model = prepare_model(workpiece, params.registration)
    prior = None
    if workpiece.has_walls:
        prior = fit_groove(model.points, model.labels, workpiece.seam, workpiece.approach, workpiece.wall_band, params.groove)
    walls = model.labels != NO_WALL
    proj = polyline.project(model.points[walls], workpiece.seam)
    radial = np.linalg.norm(model.points[walls] - proj.point, axis=1)
    band = (radial >= workpiece.wall_band[0]) & (radial <= workpiece.wall_band[1])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(workpiece.vertices.astype(np.float32)), o3d.core.Tensor(workpiece.triangles.astype(np.uint32)))
    return PreparedWorkpiece(workpiece, model, prior, model.points[walls][band], model.normals[walls][band], scene, params)


def crop_cloud(cloud_cam: ArrayLike | OrganizedCloud, T_base_cam: Array, params: SeamParams) -> Array:
    """Check a camera-frame cloud and cut it to what may be the part, in the base frame.

    Accepts an organized (H, W, 3) or flat (n, 3) array (NaN = no return), or
    an object with such a ``points`` attribute. Returns ``P_base`` (m, 3).

    Raises
    ------
    ScanError
        The cloud is empty, has no points above the table in the region, or its
        ranges say it is not in metres.
    """
    P = np.asarray(getattr(cloud_cam, "points", cloud_cam))
    if P.ndim not in (2, 3) or P.shape[-1] != 3:
        raise ScanError(f"cloud: expected an (H, W, 3) or (n, 3) array of camera-frame points, got shape {P.shape}")
    Q = P.reshape(-1, 3)
    if not np.issubdtype(Q.dtype, np.floating):
        Q = Q.astype(np.float32)
    # Units and the table from a thinned copy: millions of points say no more.
    thin = Q[:: max(1, len(Q) // 50000)]
    thin = thin[np.isfinite(thin).all(axis=1)]
    if len(thin) == 0:
        thin = Q[np.isfinite(Q).all(axis=1)]
        if len(thin) == 0:
            raise ScanError("the scan is empty: no valid point in the cloud")
    median = float(np.median(np.linalg.norm(thin, axis=1)))
    if median > params.max_range:
        raise ScanError(
            f"cloud ranges have a median of {median:.4g} m, beyond the scanner's {params.max_range} m: "
            "is the cloud in millimetres? (expected metres)",
            {"median_range": median},
        )
    if median < 0.01:
        raise ScanError(f"cloud ranges have a median of {median * 1e3:.3g} mm: expected metres", {"median_range": median})
    # Height above the table, as one dot product per point in the camera frame
    # (cheap on millions of points); only the survivors go to the base frame.
    n_base, d_base = _table_plane(thin, T_base_cam, params)
    n_cam = T_base_cam[:3, :3].T @ n_base
    offset = float(n_base @ T_base_cam[:3, 3]) - d_base
    with np.errstate(invalid="ignore"):
        above = (Q @ n_cam.astype(Q.dtype) + offset) > params.table_margin
    P_base = se3.apply(T_base_cam, Q[above])
    inside = np.all((P_base >= params.roi_min) & (P_base <= params.roi_max), axis=1)
    P_base = P_base[inside]
    if params.outlier_radius > 0.0 and len(P_base):
        # Noisy scanners leave a sprinkle of table points above the margin;
        # alone in their neighbourhood, they go.
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P_base))
        _, keep = cloud.remove_radius_outlier(params.outlier_neighbours, params.outlier_radius)
        P_base = P_base[np.asarray(keep, dtype=np.int64)]
    if len(P_base) < params.min_points:
        raise ScanError(
            f"the scan is empty where the part should be: {len(P_base)} points above the table "
            f"in the region of interest, expected at least {params.min_points}",
            {"n_points": float(len(P_base))},
        )
    return P_base


def _table_plane(thin_cam: NDArray, T_base_cam: Array, params: SeamParams) -> tuple[Array, float]:
    """The table plane ``n . p = d`` in the base frame (n up), fixed or measured.

    Measured on a thinned copy of the cloud (finite points, camera frame) in
    the region of interest: the largest plane, which must be within 10
    degrees of horizontal.
    """
    if params.table_z is not None:
        return np.array([0.0, 0.0, 1.0]), float(params.table_z)
    thin = se3.apply(T_base_cam, thin_cam)
    thin = thin[np.all((thin >= params.roi_min) & (thin <= params.roi_max), axis=1)]
    if len(thin) < 100:
        raise ScanError(f"no table in the region of interest to measure ({len(thin)} points): give table_z")
    o3d.utility.random.seed(params.registration.seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(thin))
    plane, inliers = cloud.segment_plane(params.table_tolerance, 3, 500)
    n, d = np.asarray(plane[:3], dtype=np.float64), float(plane[3])
    scale = float(np.linalg.norm(n))
    n, d = n / scale, -d / scale
    if n[2] < 0:
        n, d = -n, -d
    if n[2] < math.cos(math.radians(10.0)) or len(inliers) < 0.2 * len(thin):
        raise ScanError(
            f"no table plane found: the largest plane holds {len(inliers) / len(thin):.0%} of the region "
            f"and is tilted {math.degrees(math.acos(min(1.0, abs(n[2])))):.0f} degrees: give table_z"
        )
    return n, d


def find_seam(
    cloud_cam: ArrayLike | OrganizedCloud,
    model: Workpiece | PreparedWorkpiece,
    T_base_cam: ArrayLike,
    params: SeamParams | None = None,
    T_base_obj_nominal: ArrayLike | None = None,
) -> SeamPath:
    """Find the seam of ``model`` in one scan and return it in the base frame.

    Parameters
    ----------
    cloud_cam : (H, W, 3) or (n, 3) camera-frame points, m, NaN for no return
        (or an ``OrganizedCloud``)
    model : the part, or the part prepared by :func:`prepare` (faster when
        the same part is scanned many times)
    T_base_cam : (4, 4) hand-eye transform, pose of the camera in the base frame
    params : SeamParams; defaults to the prepared model's, or ``SeamParams()``
    T_base_obj_nominal : (4, 4) expected placement of the part, optional. The
        registration then only considers poses within
        ``params.registration.max_rotation`` of it (the part's position is
        free), which rules out the symmetric twins of symmetric parts; the
        seam is ordered along the nominal travel direction. Without it the
        search is global and the order of a symmetric part's seam is the
        model's as registered.

    Raises
    ------
    ScanError, RegistrationError, GrooveError
        The scan cannot give a trustworthy seam; the message says why.
    """
    t0 = time.perf_counter()
    T_base_cam = se3.check_transform(T_base_cam, "T_base_cam")
    if isinstance(model, PreparedWorkpiece):
        prepared = model if params is None or params == model.params else prepare(model.workpiece, params)
    else:
        prepared = prepare(model, params)
    params = prepared.params
    wp = prepared.workpiece

    P_base = crop_cloud(cloud_cam, T_base_cam, params)
    cam_base = T_base_cam[:3, 3]
    T_nom = None if T_base_obj_nominal is None else se3.check_transform(T_base_obj_nominal, "T_base_obj_nominal")
    registration = register(P_base, cam_base, prepared.model, params.registration, T_nom)
    T_base_obj = registration.T_base_obj
    T_obj_base = se3.invert(T_base_obj)

    # Scan points near the seam, in the model frame.
    band_out = wp.wall_band[1]
    stations, spacing = polyline.resample(wp.seam, params.spacing)
    P_obj = se3.apply(T_obj_base, P_base)
    # Exact projection only for points the stations' k-d tree finds near the seam.
    reach = band_out + 0.005
    d_st, _ = cKDTree(stations).query(P_obj, distance_upper_bound=reach + spacing)
    P_obj = P_obj[np.isfinite(d_st)]
    proj = polyline.project(P_obj, wp.seam)
    near = np.linalg.norm(P_obj - proj.point, axis=1) <= reach
    P_near = P_obj[near]
    figures = {"fitness": registration.fitness, "inlier_rmse": registration.inlier_rmse, "attempts": float(registration.attempts)}

    cam_obj = se3.apply(T_obj_base, cam_base[None])[0]
    coverage, across, support = _check_seam_seen(prepared, P_near, proj, near, stations, reach, cam_obj, params, figures)
    points_obj, source, reason, gq, fit = _seam_points(prepared, P_near, stations, params, figures)
    stations_obj = points_obj
    along = _along_shift(P_obj[near], proj, near, wp, params)
    if math.isfinite(along):
        points_obj = polyline.slide(points_obj, along)

    # Order: follow the nominal travel direction if one is given.
    reversed_ = False
    if T_nom is not None:
        nominal_dir = se3.rotate(T_nom, wp.seam[-1] - wp.seam[0])
        found_dir = se3.rotate(T_base_obj, wp.seam[-1] - wp.seam[0])
        reversed_ = bool(nominal_dir @ found_dir < 0)
    points_base = se3.apply(T_base_obj, points_obj)
    model_base = se3.apply(T_base_obj, stations)
    # The finger wall is on its side of the travel, so on the model's other side when the order is reversed.
    wall_across, far_across = _walls_across(fit, stations_obj, wp, params, (params.finger_wall == "left") != reversed_)
    if reversed_:
        points_base, model_base, wall_across, far_across = points_base[::-1], model_base[::-1], wall_across[::-1], far_across[::-1]
    plane_normal = se3.rotate(T_base_obj, wp.approach)
    tangents = _tangents(points_base, max(1, int(round(params.tangent_span / 2.0 / spacing))))
    normals: np.ndarray = np.cross(plane_normal, tangents)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    if params.finger_wall == "right":
        normals = -normals

    quality = SeamQuality(
        source=source,
        source_reason=reason,
        fitness=registration.fitness,
        inlier_rmse=registration.inlier_rmse,
        attempts=registration.attempts,
        coverage=coverage,
        across_support=across,
        wall_support=support,
        n_points=len(P_base),
        along_shift=along,
        reversed=reversed_,
        duration=time.perf_counter() - t0,
        **gq,
    )
    log.debug("seam_found", workpiece=wp.name, source=source, fitness=round(quality.fitness, 4), duration=round(quality.duration, 3))
    return SeamPath(points_base, tangents, normals, plane_normal, spacing, model_base, T_base_obj, quality, wall_across, far_across)


def _walls_across(fit: GrooveFit | None, points: Array, wp: Workpiece, params: SeamParams, finger_left: bool) -> tuple[Array, Array]:
    """The finger wall (the model's left wall if ``finger_left``) and the joint's other wall across from
    each seam station as the scan measured them (:func:`wall_distances`), smoothed along the seam like
    the seam's own shifts: (k, 2) rows ``(t0 m, slope)`` each, NaN where the groove was not measured
    (no fit, or no good window within ``max_gap / 2``)."""
    if fit is None:
        return np.full((len(points), 2), np.nan), np.full((len(points), 2), np.nan)
    arc_st = np.linspace(0.0, wp.seam_length, len(points))
    at_windows = np.column_stack([np.interp(fit.arc, arc_st, points[:, k]) for k in range(3)])
    left = np.cross(wp.approach, np.gradient(at_windows, axis=0))
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    approach = np.asarray(wp.approach, dtype=np.float64)
    span, step = params.deviation_span, params.groove.step
    out = []
    for is_left in (finger_left, not finger_left):
        rows = np.full((len(points), 2), np.nan)
        t0, slope, sigma, ok = wall_distances(fit, 0 if is_left else 1, at_windows, left if is_left else -left, approach)
        if np.any(ok):
            t0_st, se = smooth_offsets(fit.arc, t0, sigma, fit.length, ok, arc_st, span, step)
            slope_st, _ = smooth_offsets(fit.arc, slope, sigma, fit.length, ok, arc_st, span, step)
            measured = np.isfinite(se) & np.isfinite(slope_st) & _near_windows(arc_st, fit.arc[ok], params)
            rows[measured, 0], rows[measured, 1] = t0_st[measured], slope_st[measured]
        out.append(rows)
    return out[0], out[1]


def _near_windows(arc_st: NDArray[np.floating], arc_w: NDArray[np.floating], params: SeamParams) -> NDArray[np.bool_]:
    """Stations (arc positions) within ``max_gap / 2`` of a good window's centre (``arc_w``)."""
    return np.asarray(np.abs(arc_st[:, None] - arc_w[None, :]).min(axis=1) <= params.max_gap / 2.0 + 1e-9)


def _check_seam_seen(
    prepared: PreparedWorkpiece,
    P_near: Array,
    proj: polyline.Projection,
    near: NDArray[np.bool_],
    stations: Array,
    reach: float,
    cam_obj: Array,
    params: SeamParams,
    figures: dict[str, float],
) -> tuple[float, float, float]:
    """Refuse a scan that does not show the seam well enough to place it.

    Returns the coverage, across-support and wall-support figures; raises
    ScanError (partial, not placeable sideways, joint hidden) or
    RegistrationError (the joint is not where the registered model has it).
    """
    coverage = _coverage(P_near, stations, reach)
    figures["coverage"] = coverage
    if coverage < params.min_coverage:
        raise ScanError(
            f"partial scan: {coverage:.0%} of the seam has scan points near it, expected at least {params.min_coverage:.0%}",
            figures,
        )
    across = _across_support(prepared, P_near, proj, near, params)
    figures["across_support"] = across
    if across < params.min_across_support:
        raise ScanError(
            f"the scan cannot place the seam across itself: {across:.1%} of the points near it lie on faces "
            f"that face across the seam, expected at least {params.min_across_support:.0%} (those faces are "
            "seen at grazing angles or not at all: tilt the part or the scanner)",
            figures,
        )
    support, n_visible = _wall_support(prepared, P_near, cam_obj, params)
    figures["wall_support"] = support
    if prepared.wall_points.size and n_visible < params.min_visible_wall:
        raise ScanError(
            "the joint is hidden from the scanner: the registered part covers its walls from the camera "
            f"({n_visible} of {len(prepared.wall_points)} wall samples visible); turn the part or the scanner",
            figures,
        )
    if math.isfinite(support) and support < params.min_wall_support:
        raise RegistrationError(
            f"the scan does not show the joint where the registered model has it: {support:.0%} of the wall "
            f"surface facing the camera was seen, expected at least {params.min_wall_support:.0%} "
            "(a different part, a wrong fit, or the joint in the projector's shadow)",
            figures,
        )
    return coverage, across, support


def _coverage(P_near: Array, stations: Array, radius: float) -> float:
    """Share of seam stations with at least one scan point within ``radius``."""
    if len(P_near) == 0:
        return 0.0
    counts = cKDTree(P_near).query_ball_point(stations, radius, return_length=True)
    return float(np.mean(np.asarray(counts) > 0))


def _across_support(
    prepared: PreparedWorkpiece, P_near: Array, proj: polyline.Projection, near: NDArray[np.bool_], params: SeamParams
) -> float:
    """Share of the scan points near the seam that lie on faces facing across it.

    Only such faces (bevels, a web) fix the part sideways; flat tops do not.
    A fillet's web under a camera straight above is seen at grazing angles by
    a few dozen points, whose small biases then decide the seam's position:
    measured 0.6-1.3 mm off on PhoXi M scans, while a V-groove has 15-20 %.
    """
    if len(P_near) == 0:
        return 0.0
    d, idx = prepared.model.tree.query(P_near, distance_upper_bound=params.label_distance)
    on = np.isfinite(d)
    left = np.cross(prepared.workpiece.approach, proj.tangent[near][on])
    n = prepared.model.normals[idx[on]]
    facing = np.abs(np.einsum("ij,ij->i", n, left)) >= 0.5
    return float(np.count_nonzero(facing)) / len(P_near)


def _wall_support(prepared: PreparedWorkpiece, P_near: Array, cam_obj: Array, params: SeamParams) -> tuple[float, int]:
    """Share of the model's wall samples near the seam that the camera should
    see (facing it, not hidden behind the part itself) with a scan point near
    them, and how many such samples there are."""
    Pw, Nw = prepared.wall_points, prepared.wall_normals
    to_cam = cam_obj - Pw
    dist = np.linalg.norm(to_cam, axis=1)
    facing = np.einsum("ij,ij->i", Nw, to_cam) > params.view_cos * dist
    if np.any(facing):
        start = Pw[facing] + 1e-4 * Nw[facing]
        rays = np.hstack([start, to_cam[facing]]).astype(np.float32)
        hidden = prepared.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy().astype(bool)
        facing[np.flatnonzero(facing)[hidden]] = False
    n_visible = int(np.count_nonzero(facing))
    if n_visible == 0 or len(P_near) == 0:
        return (0.0 if n_visible else math.nan), n_visible
    d, _ = cKDTree(P_near).query(Pw[facing], distance_upper_bound=params.support_distance)
    return float(np.mean(np.isfinite(d))), n_visible


def _seam_points(
    prepared: PreparedWorkpiece, P_near: Array, stations: Array, params: SeamParams, figures: dict[str, float]
) -> tuple[Array, str, str, dict[str, float], GrooveFit | None]:
    """The seam at the stations (model frame): measured groove or registered model; and the scan's groove fit
    where it covers enough of the seam to measure the finger wall by (None otherwise)."""
    nan = math.nan
    gq = dict(
        groove_coverage=nan,
        groove_windows_ok=nan,
        groove_contradicting=nan,
        apex_sigma=nan,
        wall_rms=nan,
        model_groove_rms=nan,
        model_groove_max=nan,
        deviation_sigma=nan,
        lateral_shift_mean=nan,
    )
    wp, prior = prepared.workpiece, prepared.groove_prior
    if prior is None:
        if params.seam_source == "groove":
            raise GrooveError(f"{wp.name}: the model has no labelled joint walls, so the groove cannot be measured", figures)
        return stations, "model", "the model has no labelled joint walls", gq, None

    d, idx = prepared.model.tree.query(P_near, distance_upper_bound=params.label_distance)
    labels = np.full(len(P_near), NO_WALL, dtype=np.int8)
    hit = np.isfinite(d)
    labels[hit] = prepared.model.labels[idx[hit]]
    fit = fit_groove(P_near, labels, wp.seam, wp.approach, wp.wall_band, params.groove, prior)
    shift, sigma, valid = lateral_offsets(fit, prior, wp.seam, wp.approach, params.groove.step)
    n_win = len(fit.arc)
    gq["groove_windows_ok"] = float(np.count_nonzero(valid)) / n_win
    gq["groove_contradicting"] = float(np.count_nonzero(fit.status == CONTRADICTS)) / n_win
    if np.any(valid):
        gq["apex_sigma"] = float(np.median(sigma[valid]))
        gq["wall_rms"] = float(np.nanmedian(fit.rms[valid]))
    figures.update({k: v for k, v in gq.items() if math.isfinite(v)})
    if gq["groove_contradicting"] > params.max_contradicting:
        raise GrooveError(
            f"the joint walls in the scan contradict the model in {gq['groove_contradicting']:.0%} of the seam "
            f"(at most {params.max_contradicting:.0%}): a different joint, or a wrong registration",
            figures,
        )
    arc_st = np.linspace(0.0, wp.seam_length, len(stations))
    s_st, se = smooth_offsets(fit.arc, shift, sigma, fit.length, valid, arc_st, params.deviation_span, params.groove.step)
    measured = np.isfinite(se)
    if np.any(measured):
        # Stations beyond max_gap / 2 of a good window count as unmeasured.
        measured &= _near_windows(arc_st, fit.arc[valid], params)
    groove_cov = float(np.mean(measured))
    gq["groove_coverage"] = groove_cov
    figures["groove_coverage"] = groove_cov
    if groove_cov < params.min_groove_coverage:
        why = f"the groove was measured along {groove_cov:.0%} of the seam, expected at least {params.min_groove_coverage:.0%}"
        if params.seam_source == "groove":
            raise GrooveError(why, figures)
        return stations, "model", why, gq, None

    # Bridge the short unmeasured stretches from their neighbours; move the
    # stations across the seam, in the seam plane.
    s_st = np.interp(arc_st, arc_st[measured], s_st[measured])
    se = np.interp(arc_st, arc_st[measured], se[measured])
    T_st = np.gradient(stations, axis=0)
    left = np.cross(wp.approach, T_st)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    Dst = s_st[:, None] * left
    dev = np.linalg.norm(Dst, axis=1)
    gq["model_groove_rms"] = float(np.sqrt(np.mean(dev**2)))
    gq["model_groove_max"] = float(dev.max())
    gq["deviation_sigma"] = float(np.median(se))
    gq["lateral_shift_mean"] = float(np.mean(s_st))
    figures.update(model_groove_rms=gq["model_groove_rms"], model_groove_max=gq["model_groove_max"])
    if gq["model_groove_max"] > params.max_model_deviation:
        raise GrooveError(
            f"the measured seam is up to {gq['model_groove_max'] * 1e3:.2f} mm from the registered model's, "
            f"more than the {params.max_model_deviation * 1e3:.2f} mm accepted: check the part's fit-up",
            figures,
        )
    if params.seam_source == "model":
        return stations, "model", "seam_source is 'model'", gq, fit
    z = float(np.max(dev / se))
    if params.seam_source == "auto" and z < params.deviation_sigmas:
        # The registered model seam is the more precise of the two here.
        why = (
            f"the measured groove agrees with the model within its uncertainty "
            f"(largest deviation {z:.1f} sigma, below {params.deviation_sigmas:.1f})"
        )
        return stations, "model", why, gq, fit
    return stations + Dst, "groove", "", gq, fit


def _along_shift(P: Array, proj: polyline.Projection, near: NDArray[np.bool_], wp: Workpiece, params: SeamParams) -> float:
    """How far along the seam the joint's two ends in the scan lie from the model's.

    Registration fixes the part across the seam well but along it only through
    its end faces, which a camera above sees at grazing angles (a millimetre
    off on a curved groove). The part's points close to the seam end where
    the part ends; the mean of the two ends' offsets cancels the half-pixel
    by which the last points fall short of each edge. NaN when the measured
    length differs from the model's by more than ``max_model_deviation``.
    """
    arc = proj.arc[near]
    L = wp.seam_length
    radial = np.linalg.norm(P - proj.point[near], axis=1)
    close = radial <= wp.wall_band[1]
    T0 = wp.seam[1] - wp.seam[0]
    T1 = wp.seam[-1] - wp.seam[-2]
    # Past an end the projection sticks to it: measure how far past.
    before = close & (arc <= 1e-9)
    after = close & (arc >= L - 1e-9)
    ext_before = (P[before] - wp.seam[0]) @ (T0 / np.linalg.norm(T0))
    ext_after = L + (P[after] - wp.seam[-1]) @ (T1 / np.linalg.norm(T1))
    ext = np.concatenate([arc[close & ~before & ~after], ext_before, ext_after])
    if len(ext) < 20:
        return math.nan
    lo, hi = np.sort(ext)[[4, -5]]  # the fifth point in from each end: robust to strays
    if abs((hi - lo) - L) > params.max_model_deviation:
        return math.nan
    return float(((lo - 0.0) + (hi - L)) / 2.0)


def _tangents(P: Array, k: int) -> Array:
    """Unit tangents of a polyline from differences over +-k points (one-sided at the ends)."""
    n = len(P)
    hi = np.minimum(np.arange(n) + k, n - 1)
    lo = np.maximum(np.arange(n) - k, 0)
    T: Array = P[hi] - P[lo]
    return T / np.linalg.norm(T, axis=1, keepdims=True)
