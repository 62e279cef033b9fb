"""From a seam to what the SRM finger touches: the wall line in the welding plane.

The finger does not ride the seam itself: its tip (a sphere) sits in the
joint at ``tip_height`` above the seam and presses sideways against one wall
of it, the finger wall (``finger_wall``, left or right of travel). Algorithm 2
works in the plane normal to the approach direction at that height (the
paper's Fig. 8 plane), and there the wall is a line beside the seam:

- a fillet T-joint's web stands upright: the wall line is the seam itself;
- a V-groove's bevel leans out: at height h the wall is ``b/2 + h tan(a/2)``
  beside the root line.

:func:`wall_offset` measures that distance on the part model by casting rays
from the seam across the joint at the tip height onto the labelled wall
triangles (Open3D). :func:`weld_geometry` turns a found seam into the planned
wall line the servo follows, the seam line the torch must follow (the same
line, moved back by the offset) and the welding plane.

Pure: arrays in, arrays out, SI units, base frame unless a name says otherwise.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from celld import polyline, se3
from celld.errors import WorkpieceError
from celld.seam.workpiece import LEFT_WALL, RIGHT_WALL, Workpiece

Array = NDArray[np.float64]

# Stations along the seam where the wall offset is measured.
_STATIONS = 9
# The offset may vary along the seam by at most this much (m) before the part
# counts as one whose wall does not run beside its seam at a constant distance.
_MAX_SPREAD = 2e-4
# Rays longer than this (m) miss: no wall of a joint stands that far off its seam.
_MAX_REACH = 0.05
# How far (m) the scan's finger wall may stand off the model's before the weld is refused.
MAX_WALL_DEVIATION = 1.0e-3
# The least widening of a joint per unit of height (both walls' slopes) for its width to tell the height.
MIN_OPENING = 0.3


class WeldGeometry(NamedTuple):
    """What a weld needs of a seam, in the base frame.

    Attributes
    ----------
    T_base_plane : (4, 4) the welding plane: z along the approach direction,
        x along the first tangent, origin on the wall line's first point
    wall_base : (n, 3) the wall line the finger presses against (the servo's plan)
    seam_base : (n, 3) the seam moved up to the tip height (the torch's line)
    tangents : (n, 3) unit travel directions
    normals : (n, 3) unit, in the plane, pointing from the seam to the finger wall
    tip_height : m above the seam along the plane normal
    offsets : (n,) m from each seam point to the wall line
    """

    T_base_plane: Array
    wall_base: Array
    seam_base: Array
    tangents: Array
    normals: Array
    tip_height: float
    offsets: Array

    @property
    def offset(self) -> float:
        """m from the seam line to the wall line: the median of ``offsets``."""
        return float(np.median(self.offsets))

    def stations(self, leads: ArrayLike) -> NDArray[np.intp]:
        """The indices of the wall line's points ``leads`` (m) along it."""
        s = polyline.arc_length(self.wall_base)
        return np.minimum(np.searchsorted(s, np.asarray(leads, dtype=np.float64)), len(s) - 1)


def _side_label(finger_wall: str) -> int:
    if finger_wall not in ("left", "right"):
        raise WorkpieceError(f"finger_wall: expected 'left' or 'right', got {finger_wall!r}")
    return LEFT_WALL if finger_wall == "left" else RIGHT_WALL


def model_seam_frames(workpiece: Workpiece, finger_wall: str = "left", spacing: float = 0.001) -> tuple[Array, Array, Array]:
    """The model's seam resampled at ``spacing``: points, tangents and normals
    towards the finger wall (model frame; the conventions of
    :class:`~celld.seam.pipeline.SeamPath`)."""
    _side_label(finger_wall)
    P, _ = polyline.resample(workpiece.seam, spacing)
    T = np.gradient(P, axis=0)
    T /= np.linalg.norm(T, axis=1)[:, None]
    a = np.asarray(workpiece.approach, dtype=np.float64)
    N = np.cross(a, T)
    N /= np.linalg.norm(N, axis=1)[:, None]
    if finger_wall == "right":
        N = -N
    return P, T, N


def wall_offset(workpiece: Workpiece, tip_height: float, finger_wall: str = "left") -> float:
    """Distance (m) from the seam to the finger wall at ``tip_height`` above it.

    Measured on the model's labelled wall triangles at stations along the
    seam; their median is returned.

    Raises
    ------
    WorkpieceError
        The model has no labelled walls, a ray across the joint misses the
        wall, or the distance varies along the seam by more than 0.2 mm (the
        finger's wall would not run beside the seam).
    """
    label = _side_label(finger_wall)
    if not workpiece.has_walls:
        raise WorkpieceError(f"{workpiece.name}: the model has no labelled joint walls; the finger's wall is unknown")
    if not 0.0 <= tip_height <= _MAX_REACH:
        raise WorkpieceError(f"tip_height: expected 0 <= h <= {_MAX_REACH} m, got {tip_height}")
    tris = workpiece.triangles[workpiece.wall_labels == label]
    if len(tris) == 0:
        raise WorkpieceError(f"{workpiece.name}: no triangle is labelled as the {finger_wall} wall")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(workpiece.vertices.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32)))
    P, _, N = model_seam_frames(workpiece, finger_wall)
    idx = np.linspace(0, len(P) - 1, _STATIONS + 2)[1:-1].round().astype(int)
    a = np.asarray(workpiece.approach, dtype=np.float64)
    origins = P[idx] + tip_height * a
    rays = np.hstack([origins, N[idx]]).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    if not np.all(np.isfinite(t_hit)) or np.any(t_hit > _MAX_REACH):
        raise WorkpieceError(
            f"{workpiece.name}: at {tip_height * 1e3:.1f} mm above the seam the {finger_wall} wall is not beside it "
            f"(a ray across the joint missed it); lower weld.tip_height"
        )
    spread = float(t_hit.max() - t_hit.min())
    if spread > _MAX_SPREAD:
        raise WorkpieceError(
            f"{workpiece.name}: the {finger_wall} wall's distance from the seam varies by {spread * 1e3:.2f} mm "
            f"along it (at most {_MAX_SPREAD * 1e3:.1f} mm): the finger cannot stand in for the seam"
        )
    return float(np.median(t_hit))


def _plane(origin: Array, tangent: Array, normal: Array) -> Array:
    x = tangent - float(tangent @ normal) * normal
    x /= np.linalg.norm(x)
    return se3.transform_from(np.column_stack([x, np.cross(normal, x), normal]), origin)


def weld_geometry(
    points: Array, tangents: Array, normals: Array, plane_normal: Array, offset: float | Array, tip_height: float
) -> WeldGeometry:
    """The wall line, the torch's line and the welding plane of a seam (base frame).

    ``points``, ``tangents``, ``normals`` (n, 3) and ``plane_normal`` (3,) are a
    seam in the conventions of :class:`~celld.seam.pipeline.SeamPath` (normals
    towards the finger wall); ``offset`` from :func:`wall_offset`, or one per
    point (:func:`measured_offsets`).
    """
    P = np.asarray(points, dtype=np.float64)
    T = np.asarray(tangents, dtype=np.float64)
    N = np.asarray(normals, dtype=np.float64)
    z = np.asarray(plane_normal, dtype=np.float64)
    z = z / np.linalg.norm(z)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2 or T.shape != P.shape or N.shape != P.shape:
        raise WorkpieceError(
            f"seam: expected matching (n, 3) points, tangents and normals with n >= 2, got {P.shape}, {T.shape}, {N.shape}"
        )
    offsets = np.broadcast_to(np.asarray(offset, dtype=np.float64), (len(P),)).copy()
    if not np.all(np.isfinite(offsets)):
        raise WorkpieceError("seam: the wall offsets must be finite")
    seam_up = P + tip_height * z
    wall = seam_up + offsets[:, None] * N
    return WeldGeometry(_plane(wall[0], T[0], z), wall, seam_up, T, N, float(tip_height), offsets)


def measured_offsets(wall_across: Array, tip_height: float, model_offset: float, max_deviation: float = MAX_WALL_DEVIATION) -> Array:
    """The finger wall's distance from each seam point at ``tip_height``, as the scan measured it.

    ``wall_across`` (n, 2) are a :class:`~celld.seam.pipeline.SeamPath`'s rows
    ``(t0, slope)``; points where it is NaN take their measured neighbours'
    (interpolated along the seam), and the model's ``model_offset`` (from
    :func:`wall_offset`) when none was measured.

    Raises
    ------
    WorkpieceError
        The measured wall stands more than ``max_deviation`` (m) off the model's
        somewhere: the finger would press a wall the plan does not know.
    """
    t = wall_at_height(wall_across, tip_height)
    if not np.all(np.isfinite(t)):
        return np.full(len(t), float(model_offset))
    dev = float(np.abs(t - model_offset).max())
    if dev > max_deviation:
        raise WorkpieceError(
            f"the finger wall in the scan stands up to {dev * 1e3:.2f} mm off the model's ({model_offset * 1e3:.2f} mm from the seam "
            f"at {tip_height * 1e3:.1f} mm), more than the {max_deviation * 1e3:.1f} mm accepted: check the joint's fit-up"
        )
    return t


def wall_at_height(wall_across: Array, h: float) -> Array:
    """A measured wall's distance (m) across from each seam point at ``h`` above it (rows ``(t0, slope)``
    of a :class:`~celld.seam.pipeline.SeamPath`); points not measured take their measured neighbours'
    (interpolated along the seam); all NaN when none was measured."""
    W = np.asarray(wall_across, dtype=np.float64)
    t = W[:, 0] + W[:, 1] * h
    ok = np.isfinite(t)
    if not np.any(ok):
        return t
    k = np.arange(len(t))
    return np.interp(k, k[ok], t[ok])


def joint_width(finger: Array, far: Array, h: float) -> float:
    """The joint's width (m) between its walls at ``h`` above the seam, from one station's rows of a
    :class:`~celld.seam.pipeline.SeamPath`'s ``wall_across`` and ``far_wall_across`` (NaN if unmeasured)."""
    return float(finger[0] + far[0] + (finger[1] + far[1]) * h)


def model_geometry(workpiece: Workpiece, T_base_obj: Array, tip_height: float, finger_wall: str = "left") -> WeldGeometry:
    """The weld geometry of a part model at a pose: what a perfect scan of the model itself would plan."""
    offset = wall_offset(workpiece, tip_height, finger_wall)
    P, T, N = model_seam_frames(workpiece, finger_wall)
    R = np.asarray(T_base_obj, dtype=np.float64)[:3, :3]
    a = R @ np.asarray(workpiece.approach, dtype=np.float64)
    return weld_geometry(se3.apply(T_base_obj, P), T @ R.T, N @ R.T, a, offset, tip_height)


def in_plane(geometry: WeldGeometry, P_base: Array) -> Array:
    """Base points (n, 3) as plane coordinates (n, 2) of the welding plane."""
    T = geometry.T_base_plane
    return (np.asarray(P_base, dtype=np.float64) - T[:3, 3]) @ T[:3, :2]


def start_pose(geometry: WeldGeometry, T_tcp_tool: Array, lead: float, clearance: float) -> Array:
    """TCP pose where the finger starts: ``lead`` (m) along the wall line,
    ``clearance`` (m) off the wall on the free side, the tool's x along the
    travel and its z (the finger, up) along the plane normal."""
    s = polyline.arc_length(geometry.wall_base)
    if s[-1] <= lead:
        raise WorkpieceError(f"the seam ({s[-1] * 1e3:.1f} mm) is shorter than the lead-in of {lead * 1e3:.1f} mm")
    return tool_poses(geometry, T_tcp_tool, np.array([lead]), clearance)[0]


def tool_poses(geometry: WeldGeometry, T_tcp_tool: Array, leads: np.ndarray, clearance: float = 0.0) -> Array:
    """TCP poses (n, 4, 4) with the finger ``leads`` (m, along the wall line) in and ``clearance`` off the wall.

    As :func:`start_pose` at each lead: the tool's x along the travel there,
    its z along the plane normal (what the weld's path check moves through).
    """
    W = geometry.wall_base
    z = geometry.T_base_plane[:3, 2]
    T_tool_tcp = se3.invert(np.asarray(T_tcp_tool, dtype=np.float64))
    out = np.empty((len(leads), 4, 4))
    for k, i in enumerate(geometry.stations(leads)):
        t = geometry.tangents[i] - float(geometry.tangents[i] @ z) * z
        t /= np.linalg.norm(t)
        p = W[i] - clearance * geometry.normals[i]
        out[k] = se3.transform_from(np.column_stack([t, np.cross(z, t), z]), p) @ T_tool_tcp
    return out


def height_from_width(width: float, finger: Array, far: Array) -> float:
    """The height (m) above the seam at which the joint is ``width`` (m) wide between its walls.

    ``finger`` and ``far`` are one station's rows of a
    :class:`~celld.seam.pipeline.SeamPath`'s ``wall_across`` and
    ``far_wall_across``: each wall stands ``t0 + slope h`` across from the seam,
    so the joint is ``(t0_f + t0_r) + (slope_f + slope_r) h`` wide at height h
    (:func:`joint_width`), which is inverted here.
    A V-groove's bevels open upwards (slopes tan(a/2) each); a joint whose
    walls do not (a fillet's web, a square butt) gives no height.

    Raises
    ------
    WorkpieceError
        A wall was not measured there, or the walls open by less than
        :data:`MIN_OPENING` per unit of height.
    """
    f, r = np.asarray(finger, dtype=np.float64), np.asarray(far, dtype=np.float64)
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(r)) and math.isfinite(width)):
        raise WorkpieceError("the scan did not measure both walls of the joint there")
    opening = float(f[1] + r[1])
    if opening < MIN_OPENING:
        raise WorkpieceError(
            f"the joint's walls open by {opening:.2f} per unit of height (at least {MIN_OPENING}): its width tells no height"
        )
    return (width - joint_width(f, r, 0.0)) / opening
