"""The simulated part on the table: its true pose, its scene, the wall the finger truly touches.

A workpiece (metal) on the welding table (steel, top at base z = 0) under the cell's
scanner, placed at a nominal pose or at a random pose off it. Only the
simulator reads the true pose; it is returned beside the scene so tests can
score the seam against it. :func:`true_wall` is the finger wall of the part
at its true pose, which the simulated SRM touches.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from celld import se3
from celld.seam.weldpath import WeldGeometry, model_seam_frames, wall_offset, weld_geometry
from celld.seam.workpiece import Workpiece
from celld.sim.scene import SceneObject, box

Array = NDArray[np.float64]

# The cell's table top, base frame (celld.sim.scene uses the same plane).
TABLE_Z = 0.0
# Nominal place of a workpiece on the table, base frame, m.
NOMINAL_XY = (0.6, 0.0)
# Nominal heading of the seam: along base y, which is the direction of the
# simulated PhoXi's projector baseline (camera x = base -y). Across the
# baseline, one bevel of a V-groove faces away from the projector and is lit
# at grazing angles (no returns): the joint could be registered but not
# measured. Along it, both bevels are lit. A cell places grooves this way.
NOMINAL_YAW = math.pi / 2
# The table slab: extent and thickness, m.
_TABLE_SIZE = (1.2, 1.0, 0.03)


def nominal_pose(workpiece: Workpiece, yaw: float = NOMINAL_YAW) -> Array:
    """Pose of a part lying on the table at the nominal place, its model x
    axis (the seam's heading) turned by ``yaw`` from base x."""
    z = TABLE_Z - float(workpiece.vertices[:, 2].min())
    return se3.from_xyz_rpy([NOMINAL_XY[0], NOMINAL_XY[1], z], [0.0, 0.0, yaw])


def random_pose(workpiece: Workpiece, rng: np.random.Generator, max_angle: float, max_offset: float, yaw: float = NOMINAL_YAW) -> Array:
    """A pose off the nominal one by a rotation of up to ``max_angle`` (rad) about a
    random axis and a shift of up to ``max_offset`` (m) across the table; the
    part is then set down so its lowest point touches the table (held there by
    a fixture when tilted)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0.0, max_angle)
    r, phi = max_offset * math.sqrt(rng.uniform()), rng.uniform(-math.pi, math.pi)
    T_nom = nominal_pose(workpiece, yaw)
    R = Rotation.from_rotvec(axis * angle).as_matrix() @ T_nom[:3, :3]
    t = T_nom[:3, 3] + np.array([r * math.cos(phi), r * math.sin(phi), 0.0])
    return set_down(workpiece, se3.transform_from(R, t))


def set_down(workpiece: Workpiece, T_base_obj: Array) -> Array:
    """``T_base_obj`` moved up or down so the part's lowest point touches the table."""
    T = np.array(T_base_obj, dtype=np.float64)
    T[2, 3] += TABLE_Z - float(se3.apply(T, workpiece.vertices)[:, 2].min())
    return T


def workpiece_scene(workpiece: Workpiece, T_base_obj: Array, table: bool = True, table_material: str = "metal") -> list[SceneObject]:
    """The scanner's scene: the part (metal) first, then the table (a steel
    welding table by default)."""
    objects = [SceneObject(workpiece.name, workpiece.mesh(), T_base_obj, "metal")]
    if table:
        centre = [NOMINAL_XY[0], NOMINAL_XY[1], TABLE_Z - _TABLE_SIZE[2] / 2.0]
        objects.append(SceneObject("table", box(_TABLE_SIZE), se3.transform_from(np.eye(3), centre), table_material))
    return objects


def true_wall(workpiece: Workpiece, T_base_obj: Array, tip_height: float, finger_wall: str = "left") -> WeldGeometry:
    """The finger wall of a part at its true pose (the simulated SRM's wall)."""
    offset = wall_offset(workpiece, tip_height, finger_wall)
    P, T, N = model_seam_frames(workpiece, finger_wall)
    R = np.asarray(T_base_obj, dtype=np.float64)[:3, :3]
    a = R @ np.asarray(workpiece.approach, dtype=np.float64)
    return weld_geometry(se3.apply(T_base_obj, P), T @ R.T, N @ R.T, a, offset, tip_height)
