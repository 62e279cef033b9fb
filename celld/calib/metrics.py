"""The calibration error metric e_icp (Eq. 13), its cost metrics and Eq. 21.

Owns the self-verification of an estimate, computed from measurements only:
the verification cloud ``P_v`` (camera frame) is registered by ICP onto the
flange model placed by the verification robot pose ``T_base_flange_v`` and the
estimate ``T_base_cam'``. The ICP result is the transform that takes the
measured camera frame {Cam} onto the estimated one {Cam'}, i.e.
``e_icp = T_cam'_cam``; an exact estimate gives the identity. When ICP does not
converge onto the model (too few correspondences) e_icp is infinite, as in
Eq. 13. No ground truth enters here.

Implementation: the model is kept in the flange frame and the registration
starts from ``T_flange_cam' = T_base_flange_v^-1 T_base_cam'``; ICP is invariant to
the rigid frame the target is expressed in, so this equals registering onto
the model moved to {Cam'} and avoids moving the model for every candidate.
ICP (point-to-plane, Open3D) runs at one correspondence distance, or coarse
to fine over several.

The cost metrics of section 4.2 map e_icp to a real number: the norm of the
translation error, or the norm of ``(dx, dy, dz, d_roll r, d_pitch r, d_yaw r)``
with the work radius ``r``. Eq. 21 compensates an estimate with its e_icp.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from celld.calib.flange import FlangeModel
from celld.calib.rangebias import correct_range_bias
from celld.calib.rigid import Array
from celld.errors import CalibrationError, InputError
from celld.schemadoc import const, number, obj, one_of, string, vector
from celld.se3 import check_points, check_transform, invert

# Cost metric names accepted by :func:`cost_function` (config: calibration.cost).
COSTS = ("translation", "se3")


@dataclass(frozen=True)
class IcpParams:
    """Parameters of the e_icp registration.

    Attributes
    ----------
    max_distances : tuple of float
        Correspondence distances, coarse to fine, metres. The last one also
        decides the fitness; keep it above about three times the scanner's
        point noise. One distance (the default, as the reference toolbox)
        makes ICP fail, and e_icp infinite, when an estimate places the model
        farther off than about that distance; more stages widen the basin and
        cost one more registration each.
    max_iterations : int
        ICP iterations per stage.
    min_fitness : float
        Fraction of verification points that must find a model point within
        the last distance; below it ICP has failed and e_icp is infinite.
    voxel : float
        Voxel size of the down-sampling of the verification cloud, metres
        (0: none).
    max_points : int
        Cap on the verification points after voxelling (an even, seeded
        subsample; 0: no cap). Fewer points make each evaluation cheaper.
    point_to_plane : bool
        Point-to-plane ICP (the model's normals) rather than point-to-point.
    relative_change : float
        ICP stops when fitness and RMSE change by less than this fraction.
        The rotation about the flange axis (fixed only by the holes) converges
        slowly: a loose criterion leaves a few hundredths of a degree there,
        which a ranking of candidates tolerates and a compensation (Eq. 21)
        does not; see :meth:`strict`.
    """

    max_distances: tuple[float, ...] = (0.003,)
    max_iterations: int = 30
    min_fitness: float = 0.5
    voxel: float = 0.0
    max_points: int = 1000
    point_to_plane: bool = True
    relative_change: float = 1e-6

    def strict(self) -> IcpParams:
        """The same registration run to convergence (for Eq. 21 and reports)."""
        return replace(self, relative_change=1e-9, max_iterations=max(self.max_iterations, 100))

    def __post_init__(self) -> None:
        if not self.max_distances or not all(d > 0 for d in self.max_distances):
            raise InputError(f"max_distances: expected positive distances in metres, got {self.max_distances}")
        if not 0.0 <= self.min_fitness <= 1.0:
            raise InputError(f"min_fitness: expected a fraction in [0, 1], got {self.min_fitness}")
        if self.max_iterations < 1 or self.max_points < 0 or self.voxel < 0:
            raise InputError("max_iterations >= 1, max_points >= 0 and voxel >= 0 expected")


@dataclass(frozen=True)
class IcpMetric:
    """The value of e_icp (Eq. 13) for one estimate.

    Attributes
    ----------
    T_camhat_cam : (4, 4) array
        ``T_cam'_cam``: takes the measured camera frame onto the estimated one.
        Meaningless when ``ok`` is False.
    ok : bool
        False when ICP failed: the metric is then infinite.
    fitness : float
        Fraction of verification points with a model point within the last
        correspondence distance.
    rmse : float
        RMS distance of those correspondences, metres.
    reason : str
        Why ICP failed, empty when it did not.
    """

    T_camhat_cam: Array
    ok: bool
    fitness: float
    rmse: float
    reason: str = ""

    @classmethod
    def failed(cls, reason: str, fitness: float = 0.0, rmse: float = math.inf) -> IcpMetric:
        return cls(np.full((4, 4), np.nan), False, fitness, rmse, reason)

    @property
    def translation(self) -> Array:
        """``(dx, dy, dz)``, metres; infinite when ICP failed."""
        return self.T_camhat_cam[:3, 3].copy() if self.ok else np.full(3, np.inf)

    @property
    def rpy(self) -> Array:
        """``(d_roll, d_pitch, d_yaw)``, rad (extrinsic x-y-z); infinite when ICP failed."""
        if not self.ok:
            return np.full(3, np.inf)
        return Rotation.from_matrix(self.T_camhat_cam[:3, :3]).as_euler("xyz")

    def as_dict(self) -> dict[str, object]:
        """JSON-ready (mm and deg at this boundary; :data:`E_ICP_SCHEMA`)."""
        if not self.ok:
            return {"ok": False, "reason": self.reason, "fitness": self.fitness}
        return {
            "ok": True,
            "translation_mm": (self.translation * 1e3).tolist(),
            "rpy_deg": np.degrees(self.rpy).tolist(),
            "fitness": self.fitness,
            "rmse_mm": self.rmse * 1e3,
        }


# The JSON shape of IcpMetric.as_dict.
E_ICP_SCHEMA = one_of(
    "e_icp (Eq. 13) of an estimate against the verification cloud: T_cam'_cam as a translation and roll, pitch, yaw; or why ICP failed.",
    obj(
        "ICP converged.",
        {
            "ok": const(True),
            "translation_mm": vector("(dx, dy, dz).", 3),
            "rpy_deg": vector("(d_roll, d_pitch, d_yaw), extrinsic x-y-z.", 3),
            "fitness": number("Fraction of verification points with a model point within the correspondence distance.", 0.0, 1.0),
            "rmse_mm": number("RMS distance of those correspondences."),
        },
        ("ok", "translation_mm", "rpy_deg", "fitness", "rmse_mm"),
    ),
    obj(
        "ICP failed: the metric is infinite.",
        {"ok": const(False), "reason": string(), "fitness": number(lo=0.0, hi=1.0)},
        ("ok", "reason", "fitness"),
    ),
)


def translation_cost(e: IcpMetric) -> float:
    """``|e_icp|_cost = |(dx, dy, dz)|_2``, metres (paper sections 3.1 and 4.2)."""
    return float(np.linalg.norm(e.T_camhat_cam[:3, 3])) if e.ok else math.inf


def se3_cost(e: IcpMetric, work_radius: float) -> float:
    """``|(dx, dy, dz, d_roll r, d_pitch r, d_yaw r)|_2``, metres (section 4.2)."""
    if not e.ok:
        return math.inf
    return float(np.linalg.norm(np.concatenate([e.translation, e.rpy * work_radius])))


def cost_function(name: str, work_radius: float = 0.5) -> Callable[[IcpMetric], float]:
    """The cost metric ``|.|_cost`` by name: ``translation`` or ``se3`` (with ``work_radius``, m)."""
    if name == "translation":
        return translation_cost
    if name == "se3":
        if not work_radius > 0.0:
            raise InputError(f"work_radius: expected a positive radius in metres, got {work_radius}")
        return lambda e: se3_cost(e, work_radius)
    raise InputError(f"cost: expected one of {', '.join(COSTS)}, got {name!r}")


def compensate(T_base_camhat: ArrayLike, e: IcpMetric) -> Array:
    """Eq. 21: ``H_compensated = H_optimal e_optimal``, i.e. ``T_base_cam' T_cam'_cam``.

    Raises
    ------
    CalibrationError
        When e_icp is infinite (ICP failed): there is nothing to compensate with.
    """
    T = check_transform(T_base_camhat, "T_base_cam")
    if not e.ok:
        raise CalibrationError(f"cannot compensate (Eq. 21): e_icp is infinite ({e.reason})")
    return T @ e.T_camhat_cam


def _even_subsample(n: int, k: int, seed: int = 0) -> Array:
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=k, replace=False))


class IcpVerifier:
    """e_icp (Eq. 13) of candidate estimates against one verification capture.

    Built once per calibration (the model's normals and the down-sampled
    verification cloud are prepared here), then called with each candidate
    ``T_base_cam``. Instances hold Open3D clouds and are not shared between
    threads.

    Parameters
    ----------
    P_v_cam : (n, 3) array
        The verification cloud in the camera frame, metres, cropped to the
        flange (and what the model also holds).
    P_model_flange : (m, 3) array
        The flange model (``Flan P_true``) in the flange frame, metres.
    T_base_flange_v : (4, 4) array
        The robot's flange pose at the verification capture.
    params : IcpParams
    normals_flange : (m, 3) array, optional
        Model normals; estimated from the model points when absent.
    on_metal : (n,) bool array, optional
        The verification points on bare metal, which a time-of-flight camera
        reads long (:meth:`with_range_bias` corrects them); default none.
    """

    def __init__(
        self,
        P_v_cam: ArrayLike,
        P_model_flange: ArrayLike,
        T_base_flange_v: ArrayLike,
        params: IcpParams = IcpParams(),
        normals_flange: ArrayLike | None = None,
        on_metal: ArrayLike | None = None,
    ) -> None:
        P_v = check_points(P_v_cam, "P_v_cam", min_points=10)
        P_model = check_points(P_model_flange, "P_model_flange", min_points=10)
        self.T_base_flange_v = check_transform(T_base_flange_v, "T_base_flange_v")
        self.params = params
        self._T_flange_base = invert(self.T_base_flange_v)
        metal = np.zeros(len(P_v), dtype=bool) if on_metal is None else np.asarray(on_metal, dtype=bool)
        if metal.shape != (len(P_v),):
            raise InputError(f"on_metal: expected a mask of {len(P_v)} verification points, got shape {metal.shape}")
        # Kept to build a verifier with the range bias corrected (with_range_bias).
        self._inputs = (P_v, P_model, normals_flange, metal)
        self.range_bias = 0.0

        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P_v))
        if params.voxel > 0.0:
            src = src.voxel_down_sample(params.voxel)
        if params.max_points and len(src.points) > params.max_points:
            keep = _even_subsample(len(src.points), params.max_points)
            src = src.select_by_index(keep.tolist())
        self._source = src
        self.n_verification_points = len(src.points)

        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P_model))
        if params.point_to_plane:
            if normals_flange is not None:
                normals = check_points(normals_flange, "normals_flange")
                if normals.shape != P_model.shape:
                    raise InputError(f"normals_flange: expected shape {P_model.shape}, got {normals.shape}")
                tgt.normals = o3d.utility.Vector3dVector(normals)
            else:
                spacing = float(np.median(np.asarray(tgt.compute_nearest_neighbor_distance())))
                tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=max(4 * spacing, 1e-4), max_nn=30))
        self._target = tgt
        self._estimation = (
            o3d.pipelines.registration.TransformationEstimationPointToPlane()
            if params.point_to_plane
            else o3d.pipelines.registration.TransformationEstimationPointToPoint()
        )
        self._criteria = o3d.pipelines.registration.ICPConvergenceCriteria(
            relative_fitness=params.relative_change, relative_rmse=params.relative_change, max_iteration=params.max_iterations
        )

    def with_range_bias(self, bias: float) -> IcpVerifier:
        """A verifier on the verification points on metal moved back along their rays by ``bias`` (m).

        :func:`celld.calib.rangebias.correct_range_bias`; the points not on
        metal stay. The bias is relative to the capture as measured, not to
        this verifier's own correction.
        """
        P_v, P_model, normals, metal = self._inputs
        if not np.any(metal) or bias == 0.0:
            out = copy.copy(self)
            out.range_bias = float(bias)
            return out
        out = IcpVerifier(correct_range_bias(P_v, bias, metal), P_model, self.T_base_flange_v, self.params, normals, metal)
        out._inputs = self._inputs
        out.range_bias = float(bias)
        return out

    def strict(self) -> IcpVerifier:
        """A verifier on the same clouds whose ICP runs to convergence (:meth:`IcpParams.strict`)."""
        other = copy.copy(self)
        other.params = self.params.strict()
        other._criteria = o3d.pipelines.registration.ICPConvergenceCriteria(
            relative_fitness=other.params.relative_change,
            relative_rmse=other.params.relative_change,
            max_iteration=other.params.max_iterations,
        )
        return other

    def __call__(self, T_base_camhat: ArrayLike) -> IcpMetric:
        """e_icp of the estimate ``T_base_cam'``."""
        T_base_camhat = np.asarray(T_base_camhat, dtype=np.float64)
        if T_base_camhat.shape != (4, 4) or not np.all(np.isfinite(T_base_camhat)):
            return IcpMetric.failed("the estimate is not a finite (4, 4) transform")
        # Start: the model placed by the robot pose and the estimate, Eq. 13.
        T = self._T_flange_base @ T_base_camhat  # T_flange_cam'
        reg = None
        for d in self.params.max_distances:
            reg = o3d.pipelines.registration.registration_icp(self._source, self._target, d, T, self._estimation, self._criteria)
            if reg.fitness == 0.0:
                return IcpMetric.failed(f"no verification point within {d * 1e3:.3g} mm of the placed model")
            T = np.asarray(reg.transformation)
        if reg is None or reg.fitness < self.params.min_fitness:
            fit = 0.0 if reg is None else float(reg.fitness)
            return IcpMetric.failed(
                f"fitness {fit:.2f} below {self.params.min_fitness:.2f} at {self.params.max_distances[-1] * 1e3:.3g} mm",
                fitness=fit,
            )
        # T maps {Cam} into {Flan}: T_cam'_cam = T_cam'_flange T_flange_cam.
        T_camhat_cam = invert(self._T_flange_base @ T_base_camhat) @ T
        return IcpMetric(T_camhat_cam=T_camhat_cam, ok=True, fitness=float(reg.fitness), rmse=float(reg.inlier_rmse))


def model_cloud_with_normals(flange: FlangeModel, spacing: float) -> tuple[Array, Array]:
    """The flange model cloud (``Flan P_true``) and the outward normals of its surfaces.

    The normals come from the closest triangle of the flange's mesh, so they
    stay exact at edges where normals estimated from neighbours would blend
    two faces; point-to-plane ICP then needs fewer model points.

    Returns
    -------
    P_flange : (m, 3) array
        Model points in the flange frame, metres.
    N_flange : (m, 3) array
        Unit outward normals.
    """
    P = np.asarray(flange.model_cloud(spacing), dtype=np.float64)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(flange.mesh()))
    closest = scene.compute_closest_points(o3d.core.Tensor(P.astype(np.float32)))
    N = closest["primitive_normals"].numpy().astype(np.float64)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return P, N
