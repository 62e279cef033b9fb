"""Registration of a workpiece model to a scan: FPFH + RANSAC, then point-to-plane ICP.

This places the part model in the base frame (paper section 3.3: the scan is
registered with the CAD model to put the seam in the scanner's frame, and the
hand-eye transform moves it to the robot base). Scan points arrive already in
the base frame, so the result is ``T_base_obj``.

Global registration of flat plates is known to fall into wrong minima
(research/seam_anchors.md section 5: 10-20 % of trials; here a plate slid
along its seam by 18 mm still had 92 % of its points on the model). Each
attempt is therefore gated on its fitness (share of scan points within
``gate_distance`` of the model after ICP), and a failed gate re-seeds RANSAC,
up to ``attempts`` times. Inlier RMSE does not separate good from bad fits;
fitness does. RANSAC also checks matched normals, and with a nominal pose it
only proposes poses near it, which raised the share of good first attempts
on the shipped parts from about half to nearly all (measured on PhoXi M
scans). The model is sampled on the faces that can face a scanner above the
part (the underside is left out), so a scan point with no model point near
it is clutter or a different part.

Determinism: each attempt seeds Open3D's global generator
(``o3d.utility.random.seed``) with ``seed + attempt``. Open3D's RANSAC draws
from it in parallel threads (research/seam_anchors.md, Open3D #7475), so
bit-identical results are not promised; the gate and the ICP make the pose
the same to well under the scan noise (tests/seam: 1 um).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from celld import se3
from celld.config.seam import RegistrationParams
from celld.errors import RegistrationError
from celld.seam.workpiece import Workpiece, sample_surface

Array = NDArray[np.float64]

reg = o3d.pipelines.registration

# Faces whose normal points more than this far below the approach plane
# (cosine) are never seen by a scanner above the part.
_HIDDEN_COS = -0.5


@dataclass(frozen=True, eq=False)
class PreparedModel:
    """A workpiece sampled and described once, reused for every scan of it.

    Attributes
    ----------
    workpiece : Workpiece
    points, normals : (n, 3) dense samples of the faces a scanner can see, model frame
    labels : (n,) wall label of each sample (``NO_WALL``, ``LEFT_WALL``, ``RIGHT_WALL``)
    edge : (n,) samples within ``edge_margin`` of an edge of the part
    tree : k-d tree over ``points``
    coarse : Open3D cloud at ``voxel`` with normals, the RANSAC target
    coarse_fpfh : its FPFH features
    fine : Open3D cloud of ``points`` with normals, the ICP target
    """

    workpiece: Workpiece
    params: RegistrationParams
    points: Array
    normals: Array
    labels: NDArray[np.int8]
    edge: NDArray[np.bool_]
    tree: cKDTree
    coarse: o3d.geometry.PointCloud
    coarse_fpfh: o3d.pipelines.registration.Feature
    fine: o3d.geometry.PointCloud


def prepare_model(workpiece: Workpiece, params: RegistrationParams) -> PreparedModel:
    """Sample the model's visible faces and compute its FPFH features (once per part)."""
    V, F = workpiece.vertices, workpiece.triangles
    P, N, tri = sample_surface(V, F, params.model_spacing, seed=params.seed)
    seen = N @ workpiece.approach >= _HIDDEN_COS
    P, N, tri = P[seen], N[seen], tri[seen]
    fine = _cloud(P, N)
    coarse = fine.voxel_down_sample(params.voxel)
    coarse.normalize_normals()
    fpfh = _fpfh(coarse, params.voxel)
    labels = workpiece.wall_labels[tri].astype(np.int8)
    labels.setflags(write=False)
    tree = cKDTree(P)
    return PreparedModel(workpiece, params, P, N, labels, _edge_flags(tree, N, params.edge_margin), tree, coarse, fpfh, fine)


def _edge_flags(tree: cKDTree, N: Array, margin: float) -> NDArray[np.bool_]:
    """True for samples within ``margin`` of a face of another orientation (an edge)."""
    d, idx = tree.query(tree.data, k=24, distance_upper_bound=margin)
    found = np.isfinite(d)
    idx = np.where(found, idx, np.arange(len(N))[:, None])
    cos = np.einsum("ij,ikj->ik", N, N[idx])
    edge = np.any(cos < math.cos(math.radians(30.0)), axis=1)
    edge.setflags(write=False)
    return edge


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register`.

    Attributes
    ----------
    T_base_obj : (4, 4) pose of the model in the base frame
    fitness : share of scan points within ``gate_distance`` of the model
    inlier_rmse : RMS distance of those inliers, m
    attempts : RANSAC seeds tried
    fitness_per_attempt : fitness after ICP of each attempt, in order
    duration : s
    """

    T_base_obj: Array
    fitness: float
    inlier_rmse: float
    attempts: int
    fitness_per_attempt: tuple[float, ...]
    duration: float


def _cloud(P: Array, N: Array | None = None) -> o3d.geometry.PointCloud:
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(P, dtype=np.float64)))
    if N is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(N, dtype=np.float64))
    return pc


def _fpfh(pc: o3d.geometry.PointCloud, voxel: float) -> o3d.pipelines.registration.Feature:
    return reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100))


def scan_clouds(
    P_base: Array, cam_position_base: Array, params: RegistrationParams
) -> tuple[o3d.geometry.PointCloud, o3d.pipelines.registration.Feature, o3d.geometry.PointCloud]:
    """The scan (base frame) cut down for RANSAC (voxels, normals facing the
    camera, FPFH) and for ICP (every k-th point, about ``icp_points``).

    The ICP cloud is subsampled, not voxel-averaged: on the pixel grid of an
    organized cloud with noise along the rays, voxel centroids alias into a
    bias of tens of micrometres (measured 40 um at 1 mm voxels on a PhoXi M
    scan), which would become seam error.
    """
    full = _cloud(P_base)
    fine = full.uniform_down_sample(max(1, len(P_base) // params.icp_points))
    coarse = full.voxel_down_sample(params.voxel)
    coarse.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * params.voxel, max_nn=30))
    coarse.orient_normals_towards_camera_location(np.asarray(cam_position_base, dtype=np.float64))
    return coarse, _fpfh(coarse, params.voxel), fine


def _fitness(fine_scan: o3d.geometry.PointCloud, model: PreparedModel, T_obj_base: Array, gate: float) -> tuple[float, float]:
    P_obj = se3.apply(T_obj_base, np.asarray(fine_scan.points))
    d, _ = model.tree.query(P_obj, distance_upper_bound=gate)
    inl = np.isfinite(d)
    fitness = float(np.count_nonzero(inl)) / max(len(d), 1)
    rmse = float(np.sqrt(np.mean(d[inl] ** 2))) if np.any(inl) else math.inf
    return fitness, rmse


def register(
    P_base: Array,
    cam_position_base: Array,
    model: PreparedModel,
    params: RegistrationParams | None = None,
    T_base_obj_nominal: Array | None = None,
) -> Registration:
    """Register ``model`` to the scan points ``P_base`` (n, 3), base frame, metres.

    Parameters
    ----------
    P_base : (n, 3) scan points of the part, base frame
    cam_position_base : (3,) camera origin, base frame (orients the normals)
    model : the prepared part model
    params : defaults to the model's
    T_base_obj_nominal : (4, 4) expected placement, optional. When given, RANSAC
        only accepts poses turned less than ``params.max_rotation`` (about each
        axis) from it: the part's symmetric twins and the far-off wrong minima
        of flat plates are then never proposed. The shift is not limited.

    Returns the first attempt whose fitness passes ``min_fitness``.

    Raises
    ------
    RegistrationError
        No attempt passed the gate; ``figures`` holds the best fitness.
    """
    params = params or model.params
    if params.attempts < 1:
        raise RegistrationError(f"attempts: expected at least 1, got {params.attempts}")
    t0 = time.perf_counter()
    # Work in the nominal part frame, so the rotation limit is about identity.
    T_nom_base = np.eye(4) if T_base_obj_nominal is None else se3.invert(T_base_obj_nominal)
    P_nom = se3.apply(T_nom_base, P_base)
    cam_nom = se3.apply(T_nom_base, np.asarray(cam_position_base, dtype=np.float64)[None])[0]
    coarse, fpfh, fine = scan_clouds(P_nom, cam_nom, params)
    if len(coarse.points) < 10:
        raise RegistrationError(f"too few scan points to register: {len(coarse.points)} at {params.voxel * 1e3:.1f} mm voxels")
    v = params.voxel
    checkers = [
        reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        reg.CorrespondenceCheckerBasedOnDistance(1.5 * v),
        reg.CorrespondenceCheckerBasedOnNormal(params.max_normal_angle),
    ]
    if T_base_obj_nominal is not None:
        checkers.append(reg.CorrespondenceCheckerBasedOnSourceRotation(np.full(3, params.max_rotation)))
    criteria = reg.RANSACConvergenceCriteria(params.ransac_iterations, params.ransac_confidence)
    fitnesses: list[float] = []
    best_fitness, best_rmse, best_T = -1.0, math.inf, np.eye(4)
    for attempt in range(params.attempts):
        o3d.utility.random.seed(params.seed + attempt)
        # Source is the scan, target the model: the result maps the nominal
        # frame to the model. No mutual filter: a plate's faces look alike.
        glob = reg.registration_ransac_based_on_feature_matching(
            coarse,
            model.coarse,
            fpfh,
            model.coarse_fpfh,
            False,
            1.5 * v,
            reg.TransformationEstimationPointToPoint(False),
            3,
            checkers,
            criteria,
        )
        T = glob.transformation
        for dist in (2.0 * v, v, 0.5 * v):
            T = _icp(coarse, model.coarse, dist, T, 30)
        # Cheap pre-gate before the fine ICP: a wrong minimum stays wrong.
        fitness, _ = _fitness(fine, model, np.asarray(T), 2.0 * params.gate_distance)
        if fitness >= params.min_fitness:
            # Scan points at the part's edges are left out of the fine ICP: a
            # point a noise step off one face near an edge matches the other
            # face, and those false matches push the part sideways.
            flat = _away_from_edges(fine, model, np.asarray(T), 2.0 * params.gate_distance)
            for dist in (2.0 * params.icp_distance, params.icp_distance):
                T = _icp(flat, model.fine, dist, T, 40)
            fitness, rmse = _fitness(fine, model, np.asarray(T), params.gate_distance)
        else:
            rmse = math.inf
        fitnesses.append(fitness)
        if fitness > best_fitness:
            best_fitness, best_rmse, best_T = fitness, rmse, np.asarray(T)
        if fitness >= params.min_fitness:
            break
    duration = time.perf_counter() - t0
    if best_fitness < params.min_fitness:
        raise RegistrationError(
            f"the model does not fit the scan: best fitness {best_fitness:.2f} after {len(fitnesses)} seeds, "
            f"expected at least {params.min_fitness:.2f} (a different part, clutter on it, or a wrong model)",
            {"fitness": best_fitness, "attempts": float(len(fitnesses)), "duration": duration},
        )
    return Registration(se3.invert(best_T @ T_nom_base), best_fitness, best_rmse, len(fitnesses), tuple(fitnesses), duration)


def _away_from_edges(fine: o3d.geometry.PointCloud, model: PreparedModel, T_obj_scan: Array, gate: float) -> o3d.geometry.PointCloud:
    P = np.asarray(fine.points)
    d, idx = model.tree.query(se3.apply(T_obj_scan, P), distance_upper_bound=gate)
    keep = np.isfinite(d)
    keep[keep] = ~model.edge[idx[keep]]
    return _cloud(P[keep])


def _icp(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, distance: float, T: Array, iterations: int) -> Array:
    return reg.registration_icp(
        source,
        target,
        distance,
        T,
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=iterations),
    ).transformation
