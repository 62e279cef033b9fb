"""What the simulated scanner sees: scene objects and the robot-cell scene.

A :class:`SceneObject` is any triangle mesh in its own frame, placed in the
base frame by ``T_base_obj``, with a material that the scanner's noise model
reads (``"metal"`` or ``"matte"``). :func:`robot_scene` builds the calibration
scene: the flange on the wrist, the other robot links as simple solids behind
it, the table and, on request, random clutter on the table, and the welding
tool as built (:func:`tool_objects`) when it is given one.

The tool is drawn as the scanner needs it for a tool calibration: the SRM
finger as a thin shaft from the flange's centre to the tip, and the tip ball
(the tool's ``tip_radius``) at the true tip, both matte. The shaft is thinner
than the ball (:data:`_SHAFT_OF_TIP`), so the ball's end stands out, and thin
enough to leave the flange's face and bore to the calibration's detector
(only a shadow stripe of about a millimetre crosses them). Given the true
torch point, the torch is drawn too: the welding wire (the tool's
``wire_diameter``, bare metal) sticking :data:`_STICK_OUT` out of a gas
nozzle (a metal cylinder), both along the finger's axis, the wire's cut end
at the torch point.

Materials: the tool flange (face, chamfer, bore, holes, side wall) is bare
machined metal; the wrist body it stands on (the shoulder annulus and the
wrist cylinder of the flange model) has the model's ``wrist_finish``: painted
(``"matte"``) on the presets' arms, so a time-of-flight camera's metal bias
lies on the flange and not on the 90 mm wrist circle around it.

The link solids are stand-ins with UR10e-like sizes (wrist Ø90, d6 = 116 mm,
forearm Ø90): they occlude, cast shadows and offer false planes and edges to
the detector, which is all the calibration needs of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from celld import se3
from celld.calib.flange import FlangeModel
from celld.config import ToolConfig
from celld.errors import InputError

# Materials the scanner noise models know.
MATERIALS = ("metal", "matte")
# UR10e-like link sizes of the stand-in arm, metres.
_WRIST_TO_WRIST2 = 0.1155  # d6: flange face to the wrist-2 axis
_LINK_RADIUS = 0.045
_FOREARM_LENGTH = 0.57
_BASE_RADIUS = 0.095
_BASE_HEIGHT = 0.18
# Triangles within this of the shoulder's plane (or behind it) are the wrist's, m.
_SPLIT_EPS = 1e-7
# The table top is the plane z = 0 of the base frame; its extent, metres.
_TABLE_MIN = (-0.3, -0.8)
_TABLE_MAX = (1.5, 0.8)
_TABLE_THICKNESS = 0.03
# Clutter is dropped in this box on the table (base frame x, y), metres.
_CLUTTER_MIN = (0.25, -0.35)
_CLUTTER_MAX = (0.95, 0.35)
# The finger's shaft radius as a fraction of the tip ball's.
_SHAFT_OF_TIP = 0.6
# The torch: the wire's stick-out from the nozzle, the nozzle's radius and length, m.
_STICK_OUT = 0.015
_NOZZLE_RADIUS = 0.008
_NOZZLE_LENGTH = 0.04
# Facets of the tip ball (30: the mesh lies within 3 um of a 1 mm sphere).
_BALL_RESOLUTION = 30


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One rigid object of a simulated scene.

    Attributes
    ----------
    name : str
        Label (``"flange"``, ``"table"``, ...); the scanner reports per-pixel labels by index.
    mesh : open3d.geometry.TriangleMesh
        The surface in the object frame, metres. The scanner never modifies it.
    T_base_obj : numpy.ndarray
        (4, 4) pose of the object frame in the base frame.
    material : str
        ``"metal"`` or ``"matte"``; selects the scanner's material effects.
    """

    name: str
    mesh: o3d.geometry.TriangleMesh
    T_base_obj: np.ndarray
    material: str = "matte"

    def __post_init__(self) -> None:
        if self.material not in MATERIALS:
            raise InputError(f"scene object {self.name!r}: material must be one of {MATERIALS}, got {self.material!r}")
        T = se3.check_transform(self.T_base_obj, f"scene object {self.name!r}: T_base_obj")
        T.setflags(write=False)
        object.__setattr__(self, "T_base_obj", T)
        if len(self.mesh.triangles) == 0:
            raise InputError(f"scene object {self.name!r}: the mesh has no triangles")


def cylinder(radius: float, length: float, resolution: int = 64) -> o3d.geometry.TriangleMesh:
    """Closed cylinder along z from z = 0 to z = -length (its top cap at the origin)."""
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=radius, height=length, resolution=resolution, split=1)
    mesh.translate([0.0, 0.0, -length / 2])
    return mesh


def box(size: tuple[float, float, float]) -> o3d.geometry.TriangleMesh:
    """Closed box of ``size`` (x, y, z) centred on the origin."""
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate([-size[0] / 2, -size[1] / 2, -size[2] / 2])
    return mesh


def flange_objects(T_base_flange: np.ndarray, flange: FlangeModel) -> list[SceneObject]:
    """The flange model as two objects: the tool flange (metal) and the wrist body behind it (its finish).

    The flange model's mesh is split at the shoulder's plane, z = -thickness:
    what lies behind it outside the flange's diameter (the shoulder, the
    wrist cylinder) and the back cap are the wrist; the bottoms of the
    threaded holes, deeper than the shoulder, are the flange's.
    """
    mesh = flange.mesh()
    V = np.asarray(mesh.vertices)
    F = np.asarray(mesh.triangles)
    tri = V[F]
    r_centroid = np.linalg.norm(tri.mean(axis=1)[:, :2], axis=1)
    z_max = tri[:, :, 2].max(axis=1)
    behind = z_max <= -flange.thickness + _SPLIT_EPS
    behind &= (r_centroid >= flange.outer_diameter / 2 - _SPLIT_EPS) | (z_max <= -(flange.thickness + flange.wrist_depth) + _SPLIT_EPS)
    parts = []
    for name, keep, material in (("flange", ~behind, "metal"), ("wrist", behind, "metal" if flange.wrist_finish == "metal" else "matte")):
        part = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F[keep]))
        part.remove_unreferenced_vertices()
        part.compute_triangle_normals()
        parts.append(SceneObject(name, part, T_base_flange, material))
    return parts


def _arm_links(T_base_flange: np.ndarray, flange: FlangeModel) -> list[SceneObject]:
    """Wrist 3, wrist 2 and the forearm as cylinders behind the flange, plus the base column."""
    r_w = flange.wrist_diameter / 2
    stub = flange.thickness + flange.wrist_depth  # length the flange model already covers
    wrist3_len = max(_WRIST_TO_WRIST2 - r_w - stub, 0.005)
    T_w3 = T_base_flange @ se3.transform_from(np.eye(3), [0.0, 0.0, -stub])
    # Wrist 2: axis along the flange y axis, centred on the point d6 behind the face.
    R_y = se3.from_xyz_rpy([0.0, 0.0, 0.0], [math.pi / 2, 0.0, 0.0])[:3, :3]
    T_w2 = T_base_flange @ se3.transform_from(R_y, [0.0, -1.1 * r_w, -_WRIST_TO_WRIST2])
    # Forearm: from the wrist-2 centre, horizontally toward the base axis.
    p_w2 = (T_base_flange @ np.array([0.0, 0.0, -_WRIST_TO_WRIST2, 1.0]))[:3]
    toward = -np.array([p_w2[0], p_w2[1], 0.0])
    toward = toward / np.linalg.norm(toward) if np.linalg.norm(toward) > 1e-6 else np.array([-1.0, 0.0, 0.0])
    T_fa = se3.frame_from_z(p_w2 - 0.02 * toward, -toward)
    objects = [
        SceneObject("wrist3", cylinder(r_w, wrist3_len), T_w3, "matte"),
        SceneObject("wrist2", cylinder(_LINK_RADIUS, 2.2 * r_w), T_w2, "matte"),
        SceneObject("forearm", cylinder(_LINK_RADIUS, _FOREARM_LENGTH), T_fa, "matte"),
        SceneObject("base", cylinder(_BASE_RADIUS, _BASE_HEIGHT), se3.transform_from(np.eye(3), [0, 0, _BASE_HEIGHT]), "matte"),
    ]
    return objects


def _clutter(seed: int) -> list[SceneObject]:
    """Three to six boxes and cylinders standing on the table at seeded places."""
    rng = np.random.default_rng(seed)
    objects = []
    for i in range(int(rng.integers(3, 7))):
        xy = rng.uniform(_CLUTTER_MIN, _CLUTTER_MAX)
        yaw = rng.uniform(-math.pi, math.pi)
        height = rng.uniform(0.02, 0.15)
        material = "metal" if rng.random() < 0.5 else "matte"
        if rng.random() < 0.5:
            size = (rng.uniform(0.03, 0.2), rng.uniform(0.03, 0.2), height)
            mesh, z = box(size), height / 2
        else:
            mesh, z = cylinder(rng.uniform(0.01, 0.06), height), height
        T = se3.from_xyz_rpy([xy[0], xy[1], z], [0.0, 0.0, yaw])
        objects.append(SceneObject(f"clutter{i}", mesh, T, material))
    return objects


def tool_objects(T_base_flange: np.ndarray, tool: ToolConfig, p_flange_torch: np.ndarray | None = None) -> list[SceneObject]:
    """The welding tool as built on the flange: the finger's shaft and the tip ball (both matte), and the torch.

    ``tool`` is in the keys of :class:`~celld.config.ToolConfig` with the
    flange as its TCP (the simulated world's :attr:`ToolTruth.config`): the
    ball's centre is ``tip_tcp``, the shaft runs from it along the tool's z
    axis (towards the flange) for the tip's distance from the flange's centre.
    ``p_flange_torch`` (the world's :attr:`ToolTruth.p_flange_torch`), when
    given, is the end of the welding wire: the wire and the nozzle run from it
    along the same axis.
    """
    T = se3.check_transform(T_base_flange, "T_base_flange")
    tip = np.asarray(tool.tip_tcp, dtype=np.float64)
    z = np.asarray(tool.tool_z_tcp, dtype=np.float64)
    z = z / np.linalg.norm(z)
    length = max(float(np.linalg.norm(tip)) - 1e-3, 5e-3)
    # cylinder() spans z in [-length, 0] of its frame: put that frame's origin at the shaft's flange end.
    T_shaft = T @ se3.frame_from_z(tip + length * z, z)
    shaft = cylinder(_SHAFT_OF_TIP * tool.tip_radius, length, resolution=24)
    ball = o3d.geometry.TriangleMesh.create_sphere(radius=tool.tip_radius, resolution=_BALL_RESOLUTION)
    ball.compute_triangle_normals()
    objects = [
        SceneObject("srm_finger", shaft, T_shaft, "matte"),
        SceneObject("srm_tip", ball, T @ se3.transform_from(np.eye(3), tip), "matte"),
    ]
    if p_flange_torch is not None:
        end = np.asarray(p_flange_torch, dtype=np.float64)
        wire = cylinder(tool.wire_diameter / 2.0, _STICK_OUT, resolution=24)
        nozzle = cylinder(_NOZZLE_RADIUS, _NOZZLE_LENGTH, resolution=48)
        objects += [
            SceneObject("torch_wire", wire, T @ se3.frame_from_z(end + _STICK_OUT * z, z), "metal"),
            SceneObject("torch_nozzle", nozzle, T @ se3.frame_from_z(end + (_STICK_OUT + _NOZZLE_LENGTH) * z, z), "metal"),
        ]
    return objects


def robot_scene(
    T_base_flange: np.ndarray,
    flange: FlangeModel,
    table: bool = True,
    clutter_seed: int | None = None,
    tool: ToolConfig | None = None,
    p_flange_torch: np.ndarray | None = None,
) -> list[SceneObject]:
    """The calibration scene: flange on the wrist, robot links, table, optional clutter.

    Parameters
    ----------
    T_base_flange : numpy.ndarray
        (4, 4) pose of the flange frame (face centre, +z out of the face) in the base frame.
    flange : FlangeModel
        The flange to place; its mesh is the ``"flange"`` (metal) and ``"wrist"`` objects.
    table : bool
        Add the table, its top at base z = 0.
    clutter_seed : int or None
        Seed of the random clutter on the table; ``None`` for none.
    tool : ToolConfig or None
        The welding tool as built, flange frame (:func:`tool_objects`); ``None``: no tool.
    p_flange_torch : (3,) array or None
        The torch's wire end as built, flange frame (:func:`tool_objects`); ``None``: no torch.

    Returns
    -------
    list of SceneObject
        The flange first (metal), then the wrist body it stands on (its
        finish, :func:`flange_objects`).
    """
    T_base_flange = se3.check_transform(T_base_flange, "T_base_flange")
    objects = flange_objects(T_base_flange, flange)
    objects += _arm_links(T_base_flange, flange)
    if table:
        size = (_TABLE_MAX[0] - _TABLE_MIN[0], _TABLE_MAX[1] - _TABLE_MIN[1], _TABLE_THICKNESS)
        centre = [(_TABLE_MAX[0] + _TABLE_MIN[0]) / 2, (_TABLE_MAX[1] + _TABLE_MIN[1]) / 2, -_TABLE_THICKNESS / 2]
        objects.append(SceneObject("table", box(size), se3.transform_from(np.eye(3), centre), "matte"))
    if clutter_seed is not None:
        objects += _clutter(clutter_seed)
    if tool is not None:
        objects += tool_objects(T_base_flange, tool, p_flange_torch)
    return objects
