"""The cell model: the static objects around the arm, the tool on its flange, and the allowed contacts.

What the collision checks (:mod:`celld.robot.collision`) test the arm against:

- **objects** of the cell, fixed in the base frame: the table, the scanner
  and its mount, fixtures, free-standing obstacles. Each is a primitive
  (:class:`Box`, :class:`Cylinder`, :class:`Sphere`) or a closed triangle
  :class:`Mesh` (STL, PLY, OBJ), placed by ``T_base_obj``; a job adds
  another robot's arm where it waits as :class:`Rod` objects (capsules);
- the **tool** on the flange: its parts (the SRM finger, the torch, a
  housing) as capsules, a segment and a radius in the flange frame;
- **allowed contacts**: an object lists the arm links or tool parts that may
  touch it (the base link stands on the table), a tool part lists the objects
  it may touch (the SRM finger touches the workpiece during a weld; objects
  added at run time, such as the registered workpiece, count).
- the **margin**: the clearance every other part keeps from every object.

Each shape answers its own signed distance (negative inside), in its own
frame, in metres: closed forms for the primitives, Open3D's ray-casting scene
for meshes (a mesh must be closed, or inside and outside are not defined).

The ``[cell_model]`` table of a cell's TOML (read by
:func:`celld.config.cell_model.read_cell_model`) (lengths in metres, poses as UR
poses ``[x, y, z, rx, ry, rz]`` of the object frame in the base frame)::

    [cell_model]
    margin_mm = 5.0                        # default 5 mm

    [[cell_model.objects]]
    name = "table"
    shape = "box"                          # box | cylinder | sphere | mesh
    size = [1.2, 1.0, 0.8]                 # box: edge lengths along its x, y, z, centred on its frame
    pose = [0.6, 0.0, -0.4, 0.0, 0.0, 0.0]
    allow = ["base"]                       # arm links or tool parts that may touch it

    [[cell_model.objects]]
    name = "mount"
    shape = "cylinder"
    radius = 0.03                          # cylinder: along its z, centred on its frame
    length = 0.5
    pose = [0.6, 0.0, 1.3, 0.0, 0.0, 0.0]

    [[cell_model.objects]]
    name = "clamp"
    shape = "mesh"
    path = "fixtures/clamp.stl"            # relative to the config file
    units = "mm"                           # of the file: m or mm
    pose = [0.5, 0.2, 0.0, 0.0, 0.0, 0.0]  # of the mesh's own frame

    [[cell_model.tool]]                    # capsules in the flange frame
    name = "srm_finger"
    from = [0.0, 0.0, 0.0]
    to = [0.0, 0.0, 0.2]
    radius = 0.012
    allow = ["workpiece"]                  # objects it may touch

``shape = "sphere"`` takes ``radius`` (its centre is the pose's position).
Arm link names: :data:`ARM_LINKS`. Without ``objects``, the objects of
:meth:`CellModel.default` are used: a table top at base z = 0 all around the
base; without ``tool``, the flange carries none.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from celld import se3
from celld.errors import InputError

if TYPE_CHECKING:
    import open3d as o3d

Array = NDArray[np.float64]

# The arm's links, base to flange, as celld.robot.collision names them.
ARM_LINKS = ("base", "shoulder", "upper_arm", "elbow", "forearm", "wrist1", "wrist2", "wrist3")
# Clearance every part keeps from every object unless their contact is allowed, m.
DEFAULT_MARGIN = 0.005
# The default cell's table: its top at base z = 0, this wide around the base and
# this deep (a solid block, so nothing passes under its top), m.
_DEFAULT_TABLE = (4.0, 4.0, 1.0)
# Units a mesh file may be in, and their scale to metres.
MESH_UNITS = {"m": 1.0, "mm": 1e-3}


def _positive(name: str, value: float) -> float:
    if not (math.isfinite(value) and value > 0.0):
        raise InputError(f"{name}: expected a positive length in metres, got {value}")
    return float(value)


@dataclass(frozen=True)
class Box:
    """A box centred on its frame; ``size`` is its edge lengths along x, y, z (m)."""

    size: tuple[float, float, float]

    def __post_init__(self) -> None:
        if len(self.size) != 3:
            raise InputError(f"box size: expected 3 edge lengths, got {self.size}")
        for v in self.size:
            _positive("box size", v)

    def signed_distance(self, P_obj: Array) -> Array:
        """Signed distance (n,) of points ``P_obj`` (n, 3) in the box frame, m."""
        q = np.abs(P_obj) - 0.5 * np.asarray(self.size)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        return outside + np.minimum(q.max(axis=1), 0.0)


@dataclass(frozen=True)
class Cylinder:
    """A solid cylinder along its frame's z axis, centred on the frame (m)."""

    radius: float
    length: float

    def __post_init__(self) -> None:
        _positive("cylinder radius", self.radius)
        _positive("cylinder length", self.length)

    def signed_distance(self, P_obj: Array) -> Array:
        """Signed distance (n,) of points ``P_obj`` (n, 3) in the cylinder frame, m."""
        dr = np.hypot(P_obj[:, 0], P_obj[:, 1]) - self.radius
        dz = np.abs(P_obj[:, 2]) - 0.5 * self.length
        outside = np.hypot(np.maximum(dr, 0.0), np.maximum(dz, 0.0))
        return outside + np.minimum(np.maximum(dr, dz), 0.0)


@dataclass(frozen=True)
class Sphere:
    """A solid sphere centred on its frame (m)."""

    radius: float

    def __post_init__(self) -> None:
        _positive("sphere radius", self.radius)

    def signed_distance(self, P_obj: Array) -> Array:
        """Signed distance (n,) of points ``P_obj`` (n, 3) in the sphere frame, m."""
        return np.linalg.norm(P_obj, axis=1) - self.radius


@dataclass(frozen=True)
class Rod:
    """A segment along its frame's z axis, centred on the frame, swept by a sphere of ``radius`` (m): a
    capsule, the shape of an arm link (another robot's arm as an obstacle). ``length`` 0 is a sphere."""

    radius: float
    length: float

    def __post_init__(self) -> None:
        _positive("rod radius", self.radius)
        if not (math.isfinite(self.length) and self.length >= 0.0):
            raise InputError(f"rod length: expected a length >= 0 m, got {self.length}")

    def signed_distance(self, P_obj: Array) -> Array:
        """Signed distance (n,) of points ``P_obj`` (n, 3) in the rod frame, m."""
        z = np.clip(P_obj[:, 2], -0.5 * self.length, 0.5 * self.length)
        return np.hypot(np.hypot(P_obj[:, 0], P_obj[:, 1]), P_obj[:, 2] - z) - self.radius


@dataclass(frozen=True, eq=False)
class Mesh:
    """A closed triangle mesh in its own frame, metres.

    Attributes
    ----------
    source : str
        Where it came from (a file path), for messages.
    vertices : (n, 3) float64, m
    triangles : (m, 3) int
    """

    source: str
    vertices: Array
    triangles: NDArray[np.int64]

    def __post_init__(self) -> None:
        V = np.array(self.vertices, dtype=np.float64)
        F = np.array(self.triangles, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
            raise InputError(f"mesh {self.source}: expected (n, 3) vertices and (m > 0, 3) triangles, got {V.shape} and {F.shape}")
        if not np.all(np.isfinite(V)) or F.min() < 0 or F.max() >= len(V):
            raise InputError(f"mesh {self.source}: non-finite vertices or triangle indices outside 0..{len(V) - 1}")
        V.setflags(write=False)
        F.setflags(write=False)
        object.__setattr__(self, "vertices", V)
        object.__setattr__(self, "triangles", F)

    @classmethod
    def load(cls, path: str | Path, units: str) -> Mesh:
        """Read a closed mesh file (STL, PLY, OBJ) whose lengths are in ``units`` ("m" or "mm")."""
        import open3d as o3d

        if units not in MESH_UNITS:
            raise InputError(f"mesh {path}: units must be one of {', '.join(MESH_UNITS)}, got {units!r}")
        if not Path(path).is_file():
            raise InputError(f"mesh {path}: file not found")
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) == 0:
            raise InputError(f"mesh {path}: no triangles could be read")
        # STL stores every triangle's corners apart; merge them before asking whether it is closed.
        mesh = mesh.remove_duplicated_vertices().remove_degenerate_triangles()
        if not mesh.is_watertight():
            raise InputError(f"mesh {path}: not closed (watertight): its inside, and so a collision, is not defined")
        return cls(str(path), np.asarray(mesh.vertices) * MESH_UNITS[units], np.asarray(mesh.triangles))

    @functools.cached_property
    def _scene(self) -> o3d.t.geometry.RaycastingScene:
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)), o3d.core.Tensor(self.triangles.astype(np.uint32)))
        return scene

    def signed_distance(self, P_obj: Array) -> Array:
        """Signed distance (n,) of points ``P_obj`` (n, 3) in the mesh frame, m (float32 precision)."""
        import open3d as o3d

        d = self._scene.compute_signed_distance(o3d.core.Tensor(np.asarray(P_obj, dtype=np.float32)))
        return d.numpy().astype(np.float64)


Shape = Box | Cylinder | Sphere | Rod | Mesh


@dataclass(frozen=True, eq=False)
class CellObject:
    """One object of the cell, fixed in the base frame.

    ``allow`` names the arm links (:data:`ARM_LINKS`) and tool parts that may
    touch it; every other part keeps the cell's margin from it.
    """

    name: str
    shape: Shape
    T_base_obj: Array
    allow: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.name:
            raise InputError("cell object: expected a name")
        T = se3.check_transform(self.T_base_obj, f"cell object {self.name!r}: T_base_obj").copy()
        T.setflags(write=False)
        object.__setattr__(self, "T_base_obj", T)
        object.__setattr__(self, "allow", tuple(self.allow))

    def signed_distance(self, P_base: Array) -> Array:
        """Signed distance (n,) of points ``P_base`` (n, 3) to this object, m; negative inside."""
        T = self.T_base_obj
        return self.shape.signed_distance((np.asarray(P_base) - T[:3, 3]) @ T[:3, :3])


@dataclass(frozen=True)
class ToolPart:
    """A capsule of the tool: the segment ``p0_flange`` to ``p1_flange`` (m, flange frame) swept by ``radius``.

    ``allow`` names the objects this part may touch. A sphere is a capsule
    whose two ends coincide.
    """

    name: str
    p0_flange: tuple[float, float, float]
    p1_flange: tuple[float, float, float]
    radius: float
    allow: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.name:
            raise InputError("tool part: expected a name")
        for key in ("p0_flange", "p1_flange"):
            v = np.asarray(getattr(self, key), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise InputError(f"tool part {self.name!r}: {key} expected 3 finite coordinates (m), got {getattr(self, key)}")
            object.__setattr__(self, key, tuple(float(x) for x in v))
        _positive(f"tool part {self.name!r}: radius", self.radius)
        object.__setattr__(self, "allow", tuple(self.allow))


@dataclass(frozen=True)
class CellModel:
    """The objects of the cell, the tool on the flange, and the margin kept from the objects (m)."""

    objects: tuple[CellObject, ...] = ()
    tool: tuple[ToolPart, ...] = ()
    margin: float = DEFAULT_MARGIN

    def __post_init__(self) -> None:
        object.__setattr__(self, "objects", tuple(self.objects))
        object.__setattr__(self, "tool", tuple(self.tool))
        if not (math.isfinite(self.margin) and self.margin >= 0.0):
            raise InputError(f"cell model margin: expected a clearance >= 0 m, got {self.margin}")
        names = list(ARM_LINKS) + [o.name for o in self.objects] + [p.name for p in self.tool]
        seen: set[str] = set()
        for n in names:
            if n in seen:
                raise InputError(f"cell model: the name {n!r} is used twice (arm links: {', '.join(ARM_LINKS)})")
            seen.add(n)
        parts = set(ARM_LINKS) | {p.name for p in self.tool}
        for o in self.objects:
            unknown = [a for a in o.allow if a not in parts]
            if unknown:
                raise InputError(
                    f"cell object {o.name!r}: allow names {unknown}, expected arm links or tool parts: {', '.join(sorted(parts))}"
                )

    def allows(self, part: str, obj: str) -> bool:
        """True when arm link or tool part ``part`` may touch object ``obj``."""
        return any(o.name == obj and part in o.allow for o in self.objects) or any(p.name == part and obj in p.allow for p in self.tool)

    def with_object(self, obj: CellObject) -> CellModel:
        """A new model with ``obj`` added (e.g. the registered workpiece before a weld)."""
        return replace(self, objects=(*self.objects, obj))

    def seen_from(self, T_new_base: Array) -> CellModel:
        """The same objects in another robot's base frame: ``T_new_base`` is this model's base in that frame."""
        T = se3.check_transform(T_new_base, "T_new_base")
        return replace(self, objects=tuple(replace(o, T_base_obj=T @ o.T_base_obj) for o in self.objects))

    def without_tool(self) -> CellModel:
        """A new model with no tool on the flange (e.g. a calibration with the tool taken off)."""
        return replace(self, tool=())

    @classmethod
    def default(cls) -> CellModel:
        """A table top at base z = 0 all around the base (the base link stands on it), no tool."""
        size = _DEFAULT_TABLE
        table = CellObject("table", Box(size), se3.transform_from(np.eye(3), [0.0, 0.0, -size[2] / 2]), allow=("base",))
        return cls(objects=(table,))
