"""The coarse pass of flange detection: from a thinned scene to candidate flange circles.

Steps 1-6 of :mod:`celld.calib.detect`, on a thinned copy of the cloud (tens
of thousands of points, so Open3D stays fast):

1. crop to the workspace box and the sphere around a predicted centre;
2. segment the background planes (Open3D RANSAC), far wider than the
   flange, and remove them whole;
3. statistical outlier filter (Open3D) on what is left;
4. plane segmentation (Open3D RANSAC), plane after plane;
5. clustering of each plane (Open3D DBSCAN), keeping the clusters whose
   extent lies between ``min_extent`` and ``1 + size_tol`` flange diameters
   (the paper's size constraint, section 2.1.4);
6. the rim of each such cluster, a circle RANSAC with the radius check on
   it (tolerances widened by the coarse point spacing), and the checks:
   coverage of the circumference and the model's step (:func:`hollow`).

:func:`coarse_candidates` yields the candidates one by one as the planes are
segmented, so the caller can stop at the first one its fine pass verifies.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import open3d as o3d
from scipy import ndimage

from celld.calib.circle import CircleFit, angular_coverage, fit_plane, plane_basis, ransac_circle
from celld.calib.detect_params import DetectParams
from celld.calib.flange import FlangeModel

# Fewest points a plane or a cluster needs to be considered.
MIN_POINTS = 12
# A plane wider than this many flange diameters is background (table, floor).
_BACKGROUND_EXTENT = 3.0
# ... and holds at least this share of the thinned scene.
_BACKGROUND_SHARE = 0.25
# Most background planes removed before the outlier filter.
_MAX_BACKGROUND = 3
# In-plane directions over which the extent (largest width) of a cluster is taken.
_EXTENT_DIRECTIONS = 8
# Plane RANSAC iterations. No early stop (probability 1): Open3D decides it
# across its threads, so under load the result would depend on the timing.
PLANE_ITERATIONS = 150
PLANE_PROBABILITY = 1.0
# Coarse RANSAC draws at most this many triples: a flange rim is most of its
# cluster's edge (found in tens of draws); anything else should be given up fast.
_COARSE_K_MAX = 1000
# DBSCAN: fewest neighbours of a core point.
_DBSCAN_MIN_POINTS = 4
# Smallest height difference between two levels of the model that counts as a step, m.
_MIN_STEP = 0.002
# Angular sectors of the coverage check.
COVERAGE_BINS = 36
# Largest angle between a coarse circle's normal and its cluster's plane.
_COARSE_NORMAL_ANGLE = math.radians(10)
# 4-connected structuring element of the occupancy grids.
CROSS = ndimage.generate_binary_structure(2, 1)


class CoarseCandidate(NamedTuple):
    """A cluster of the thinned cloud with a verified rim circle."""

    idx: np.ndarray  # (k,) indices into the coarse points
    circle: CircleFit  # in the camera frame
    coverage: float
    spacing: float  # median point spacing of the cluster, m


@dataclass
class SearchLog:
    """What the coarse pass saw, for the error message when nothing is found."""

    background: int = 0
    planes: int = 0
    extents: list[float] = field(default_factory=list)
    clusters: int = 0


def crop_mask(P: np.ndarray, params: DetectParams, roi_center: np.ndarray | None) -> np.ndarray:
    """Mask (...,) of the finite points of P (..., 3) inside the crop box and the ROI sphere."""
    mask = np.isfinite(P).all(axis=-1)
    with np.errstate(invalid="ignore"):
        if params.crop_min is not None and params.crop_max is not None:
            mask &= np.all((P >= np.asarray(params.crop_min)) & (P <= np.asarray(params.crop_max)), axis=-1)
        if roi_center is not None:
            mask &= np.sum((P - roi_center) ** 2, axis=-1) <= params.roi_radius**2
    return mask


def pcd(P: np.ndarray) -> o3d.geometry.PointCloud:
    """An Open3D cloud of P (n, 3)."""
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(P, dtype=np.float64)))


def segment_plane(P: np.ndarray, distance: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Open3D RANSAC plane of P (n, 3): (unit normal (3,), inlier indices)."""
    o3d.utility.random.seed(seed)
    model, inliers = pcd(P).segment_plane(distance, 3, PLANE_ITERATIONS, PLANE_PROBABILITY)
    normal = np.asarray(model[:3], dtype=np.float64)
    return normal / np.linalg.norm(normal), np.asarray(inliers, dtype=np.int64)


def extent(P: np.ndarray, normal: np.ndarray) -> float:
    """Largest width of points P (n, 3) within the plane normal to ``normal``, m."""
    E = plane_basis(normal)
    angles = np.pi * np.arange(_EXTENT_DIRECTIONS) / _EXTENT_DIRECTIONS
    D = np.cos(angles)[:, None] * E[0] + np.sin(angles)[:, None] * E[1]
    proj = P @ D.T
    return float(np.max(proj.max(axis=0) - proj.min(axis=0)))


def spacing(P: np.ndarray) -> float:
    """Median nearest-neighbour distance of points P (n, 3), m (Open3D KD-tree)."""
    return float(np.median(np.asarray(pcd(P).compute_nearest_neighbor_distance())))


def project(P: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Points P (n, 3) projected along ``normal`` onto the plane through ``point``."""
    return P - np.outer((P - point) @ normal, normal)


def outer_edge(cells: np.ndarray) -> np.ndarray:
    """Mask (n,) of the cells (n, 2) on the outer edge of the region they cover.

    The cells form an occupancy grid; its holes (the bore, the threaded
    holes, missing returns) are filled, so only the outer edge and the cuts
    of occluders remain. A cell is on the edge when it has an empty 4-neighbour.
    """
    c = cells - cells.min(axis=0) + 1
    grid = np.zeros(tuple(c.max(axis=0) + 2), dtype=bool)
    grid[c[:, 0], c[:, 1]] = True
    grid = ndimage.binary_fill_holes(grid, structure=CROSS)
    inner = ndimage.binary_erosion(grid, structure=CROSS)
    return ~inner[c[:, 0], c[:, 1]]


def raster_cells(P: np.ndarray, normal: np.ndarray, cell: float) -> np.ndarray:
    """Integer cells (n, 2) of points P (n, 3) on a grid of ``cell`` metres in their plane."""
    return np.floor((P @ plane_basis(normal).T) / cell).astype(np.int64)


def _levels(flange: FlangeModel) -> list[tuple[float, float, float, str]]:
    """The model's surfaces that face the camera, as (r_in, r_out, z, finish): bore bottom, face, shoulder."""
    return [
        (0.0, flange.bore_diameter / 2, -flange.bore_depth, "metal"),
        (flange.bore_diameter / 2, flange.face_radius, 0.0, "metal"),
        (flange.outer_diameter / 2, flange.wrist_diameter / 2, -flange.thickness, flange.wrist_finish),
    ]


class _Band(NamedTuple):
    """A trimmed radial band of one surface: (r_in, r_out), its height z in the flange frame, its finish."""

    radii: tuple[float, float]
    z: float
    finish: str
    carries_rim: bool

    @property
    def width(self) -> float:
        return self.radii[1] - self.radii[0]


def _bands(flange: FlangeModel, by_finish: bool = False) -> tuple[tuple[float, float] | None, tuple[float, float] | None, float]:
    """Two radial bands about the axis whose heights differ by a step of the model: (reference, other, dz).

    Of the model's surfaces that face the camera (:func:`_levels`),
    ``reference`` is the one whose outer edge is the circle, ``other`` the
    widest one inside the circle at a different height (a step of at least
    _MIN_STEP), ``dz`` its height above the reference. With ``by_finish``
    (a scanner that reads bare metal and paint at different ranges) the two
    must share a finish: when none inside the circle shares the reference's,
    the widest pair inside the circle that shares one is taken (on a painted
    UR wrist, the metal face over the metal bore bottom). Bands are trimmed by
    15 % of their width at each bounding edge; None when there is no such pair.
    """
    bands = []
    for r0, r1, z, finish in _levels(flange):
        if r0 >= flange.circle_radius:
            continue
        carries_rim = r1 >= flange.circle_radius - 1e-9
        r1 = min(r1, flange.circle_radius)
        trim = 0.15 * (r1 - r0)
        bands.append(_Band((r0 + trim if r0 > 0 else 0.0, r1 - trim), z, finish, carries_rim))
    surface = next((b for b in bands if b.carries_rim), None)
    if surface is None:
        return None, None, 0.0

    def widest(ref: _Band) -> _Band | None:
        partners = [b for b in bands if b is not ref and abs(b.z - ref.z) >= _MIN_STEP and (not by_finish or b.finish == ref.finish)]
        return max(partners, key=lambda b: b.width, default=None)

    other = widest(surface)
    if other is not None:
        return surface.radii, other.radii, other.z - surface.z
    if not by_finish:
        return surface.radii, None, 0.0
    pairs = [(ref, o) for ref in bands if ref is not surface for o in [widest(ref)] if o is not None]
    if not pairs:
        return surface.radii, None, 0.0
    ref, o = max(pairs, key=lambda p: min(p[0].width, p[1].width))
    return ref.radii, o.radii, o.z - ref.z


def hollow(
    face: np.ndarray,
    centre: np.ndarray,
    normal: np.ndarray,
    flange: FlangeModel,
    slab: float,
    fraction: float,
    by_finish: bool = False,
    around: np.ndarray | None = None,
    undecided: bool = False,
) -> bool:
    """True when the points around the circle show the model's step: a flange, not a solid disc.

    An ISO 9409-1 face is an annulus: seen in the plane of the face the
    centring bore is a hole; seen in the plane of the UR10e wrist shoulder,
    the face stands 6.5 mm above it. With a slab thinner than the step, the
    other band must be empty: at most ``fraction`` of the points the density
    on the surface band predicts. With a thicker slab (time of flight) both
    levels are in it, and the median height of the other band above the
    reference band must be the model's step within half of it. A
    time-of-flight camera reads bare metal long against paint
    (``by_finish``): the step is then judged between surfaces of one finish
    (:func:`_bands`), so a painted shoulder under a metal face that reads
    below it is still a flange and a solid disc still is not.

    Parameters
    ----------
    face : numpy.ndarray
        (n, 3) points within ``slab`` of the circle's plane, camera frame.
    centre, normal : numpy.ndarray
        (3,) the circle's centre and unit normal (either sign), camera frame.
    around : numpy.ndarray, optional
        (m, 3) the points near the circle at any height, for the thick-slab
        test (default ``face``): a bore read long may lie beyond the slab.
    undecided : bool
        The answer when a band of the thick-slab test holds too few points to
        judge (the coarse pass passes such a candidate on to the fine pass,
        which judges it at full resolution).
    """
    surface, other, dz = _bands(flange, by_finish)
    if surface is None or other is None:
        return True
    up = normal if normal @ centre < 0 else -normal  # toward the camera, as flange +z
    thick = abs(dz) <= 2 * slab
    d = (around if thick and around is not None else face) - centre
    h = d @ up
    rho = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))
    on_surface = (rho > surface[0]) & (rho < surface[1])
    on_other = (rho > other[0]) & (rho < other[1])
    if not thick:
        density = np.count_nonzero(on_surface) / (math.pi * (surface[1] ** 2 - surface[0] ** 2))
        return bool(np.count_nonzero(on_other) <= fraction * density * math.pi * (other[1] ** 2 - other[0] ** 2))
    if np.count_nonzero(on_other) < MIN_POINTS or np.count_nonzero(on_surface) < MIN_POINTS:
        return undecided
    step = float(np.median(h[on_other]) - np.median(h[on_surface]))
    return abs(step - dz) < 0.5 * abs(dz)


def _coarse_circle(
    P: np.ndarray,
    cells: np.ndarray | None,
    stride: int,
    idx: np.ndarray,
    flange: FlangeModel,
    params: DetectParams,
    rng: np.random.Generator,
) -> CoarseCandidate | None:
    """Step 6 on one cluster: its rim circle at the coarse spacing, or None."""
    Q = P[idx]
    point, normal, _ = fit_plane(Q)
    step = spacing(Q)
    rim = outer_edge(raster_cells(Q, normal, 1.5 * step) if cells is None else cells[idx] // stride)
    R = project(Q[rim], point, normal)
    # The rim of a thinned cloud lies up to one spacing inside the true edge.
    e_r, e_d = params.e_r + step, max(params.e_d, 0.75 * step)
    k_max = min(params.k_max, _COARSE_K_MAX)
    fit = ransac_circle(R, flange.circle_radius, e_r, e_d, k_max, rng, normal, _COARSE_NORMAL_ANGLE)
    if fit is None or fit.inliers.sum() < MIN_POINTS:
        return None
    coverage = angular_coverage(R[fit.inliers], fit.centre, normal, COVERAGE_BINS)
    if coverage < params.min_coverage:
        return None
    # The thick-slab step test looks at every thinned point near the circle:
    # a bore read long can lie beyond the cluster's plane slab.
    near = np.einsum("ij,ij->i", P - fit.centre, P - fit.centre) < (1.2 * flange.circle_radius) ** 2
    by_finish = params.max_range_bias > 0.0
    if not hollow(Q, fit.centre, normal, flange, params.e_plane_coarse, params.hollow_fraction, by_finish, P[near], undecided=by_finish):
        return None
    return CoarseCandidate(idx, fit, coverage, step)


def coarse_candidates(
    P: np.ndarray,
    cells: np.ndarray | None,
    stride: int,
    flange: FlangeModel,
    params: DetectParams,
    rng: np.random.Generator,
    log: SearchLog,
) -> Iterator[CoarseCandidate]:
    """Yield flange candidates among the thinned points P (m, 3), camera frame, m.

    Parameters
    ----------
    P : numpy.ndarray
        (m, 3) thinned, cropped points.
    cells : numpy.ndarray or None
        (m, 2) their (row, column) in the full image of an organized cloud,
        on a grid of ``stride``; None for an unorganized cloud (the rim is
        then found on a raster).
    stride : int
        Pixel step of the thinned image.
    flange, params, rng
        The model, the parameters and the RANSAC sampler.
    log : SearchLog
        Filled in as the search goes.
    """
    diameter = 2 * flange.circle_radius
    lo, hi = params.min_extent * diameter, (1 + params.size_tol) * diameter
    remaining = np.arange(len(P))
    pending = None  # the first plane that is not background, found before the filter
    for i in range(_MAX_BACKGROUND):
        if len(remaining) < MIN_POINTS:
            return
        normal, inl = segment_plane(P[remaining], params.e_plane_coarse, params.seed + i)
        inl = remaining[inl]
        # Background: wide and a large share of the whole scene. A plane that
        # only happens to be wide (through the flange and a link beyond it) is
        # split by the clustering below instead.
        if len(inl) < _BACKGROUND_SHARE * len(P) or extent(P[inl], normal) <= _BACKGROUND_EXTENT * diameter:
            pending = (normal, inl)
            break
        remaining = np.setdiff1d(remaining, inl, assume_unique=True)
        log.background += 1
    if len(remaining) < MIN_POINTS:
        return
    _, keep = pcd(P[remaining]).remove_statistical_outlier(params.outlier_neighbours, params.outlier_std)
    remaining = remaining[np.asarray(keep, dtype=np.int64)].reshape(-1)
    for i in range(params.max_planes):
        if pending is not None:
            normal, inl = pending
            inl = np.intersect1d(inl, remaining, assume_unique=True)
            pending = None
        elif len(remaining) >= MIN_POINTS:
            normal, inl = segment_plane(P[remaining], params.e_plane_coarse, params.seed + _MAX_BACKGROUND + i)
            inl = remaining[inl]
        else:
            return
        remaining = np.setdiff1d(remaining, inl, assume_unique=True)
        log.planes += 1
        if len(inl) < MIN_POINTS:
            continue
        eps = params.cluster_eps * spacing(P[inl])
        labels = np.asarray(pcd(P[inl]).cluster_dbscan(eps, _DBSCAN_MIN_POINTS))
        for label in range(int(labels.max(initial=-1)) + 1):
            member = inl[labels == label]
            if len(member) < MIN_POINTS:
                continue
            width = extent(P[member], normal)
            log.extents.append(width)
            if not lo <= width <= hi:
                continue
            log.clusters += 1
            cand = _coarse_circle(P, cells, stride, member, flange, params, rng)
            if cand is not None:
                yield cand
