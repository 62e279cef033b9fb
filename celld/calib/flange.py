"""Parametric robot tool flanges (ISO 9409-1) and the presets celld knows.

A :class:`FlangeModel` holds the geometry of a tool flange in its own frame:
origin at the centre of the mounting face, +z out of the face (the UR ``tool0``
z axis), all lengths in metres. From it come a closed triangle mesh for ray
casting (the simulated scanner) and a sampled model cloud ``P_flange`` for ICP
(the ground-truth cloud of the paper's Fig. 6 and Eq. 13).

The solid, as a profile revolved about z (r, z):

- the mounting face, an annulus at z = 0 from the centring bore to the start
  of the chamfer, pierced by the threaded holes and the dowel-pin hole on the
  pitch circle;
- the centring bore (recess), radius ``bore_diameter / 2``, ``bore_depth`` deep;
- a 45 degree chamfer on the outer edge, then the side wall down to
  z = -``thickness``;
- the shoulder annulus out to the wrist radius at z = -``thickness`` and the
  wrist cylinder behind it, ``wrist_depth`` long, closed at the back.

The detector fits one circle per model: ``circle_radius`` in the plane
z = ``circle_z``. For the mounting-face presets that is the edge of the face
where the chamfer starts (``outer_diameter / 2 - chamfer``: 31 mm on the
50-4-M6 flange, the paper's R of section 3.2.2). For ``ur10e-wrist`` it is the
90 mm outer circle of the UR10e wrist, 6.5 mm behind the face, which the paper
uses with a noisy time-of-flight camera (section 4.2).

Finishes: the tool flange itself (face, chamfer, bore, holes, side wall) is
bare machined metal; the wrist body it stands on (the shoulder annulus and
the wrist cylinder) is painted on the arms of the presets (``wrist_finish``).
A time-of-flight camera reads bare metal long (multipath), paint much less:
the face and the shoulder then read a step that is not the model's 6.5 mm,
which is what measures the camera's range bias on metal
(:mod:`celld.calib.rangebias`). That the wrist housings are painted is read
from the arms' appearance (UR, Franka, AUBO), not from a drawing.

Dimensions come from ISO 9409-1 where the standard fixes them (pitch circle,
face and centring diameters, threads, pin) and from the UR10e manual drawing
(bore depth, the 6.5 mm the flange stands proud of the 90 mm wrist); see
``research/handeye_anchors.md`` section 5. Values the standard leaves open
(chamfer, bore depth on other robots, wrist sizes of Franka and AUBO) are
plausible choices, marked as such below; check them against a drawing before
relying on a model for a real robot.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import Delaunay

from celld.errors import InputError

# Target chord of the polygonal circles of the mesh, metres: fine enough that
# the polygon deviates from the true circle by under 1 um at r = 50 mm.
_MESH_CHORD = 0.0003
# Vertices closer than this are merged when the parts of the mesh are joined, metres.
_MERGE_EPS = 1e-9
# Seed of the model-cloud sampler: the model cloud is a fixed function of the model.
_MODEL_CLOUD_SEED = 9409
# Finishes of the wrist body: painted (the presets' arms) or bare metal.
FINISHES = ("painted", "metal")
# A shoulder narrower than this (radial width, m) shows too few points to measure the face's step over it.
_MIN_SHOULDER = 0.005


@dataclass(frozen=True)
class FlangeModel:
    """Geometry of one tool flange, metres and radians, in the flange frame.

    Attributes
    ----------
    name : str
        Preset name (``"ur10e"``) or a user's label.
    pitch_diameter : float
        d1, the circle of the threaded holes.
    outer_diameter : float
        d2, the diameter of the mounting face.
    bore_diameter, bore_depth : float
        d3, the centring recess, and its depth.
    n_holes : int
        Number of threaded holes on the pitch circle.
    hole_diameter, hole_depth : float
        Nominal thread diameter (the hole seen in the face) and thread depth.
    dowel_diameter, dowel_depth : float
        The dowel-pin hole on the pitch circle.
    chamfer : float
        Leg of the 45 degree chamfer on the outer edge of the face.
    thickness : float
        How far the flange stands proud of the wrist (side wall height).
    wrist_diameter, wrist_depth : float
        The wrist body the flange sits on (at least ``outer_diameter``) and
        the length of it that belongs to the model.
    circle_radius : float
        Radius of the circle the detector fits.
    circle_z : float
        z of the plane of that circle in the flange frame (0 on the face,
        negative behind it).
    dowel_angle : float
        Angle of the dowel pin about z from +x, rad; the threaded holes sit
        half a step either side of it.
    wrist_finish : str
        ``"painted"`` or ``"metal"``: the finish of the wrist body (shoulder
        and wrist cylinder). The tool flange itself is always bare metal.
    """

    name: str
    pitch_diameter: float
    outer_diameter: float
    bore_diameter: float
    bore_depth: float
    n_holes: int
    hole_diameter: float
    dowel_diameter: float
    chamfer: float
    thickness: float
    hole_depth: float = 0.008
    dowel_depth: float = 0.006
    wrist_diameter: float = 0.0
    wrist_depth: float = 0.025
    circle_radius: float = 0.0
    circle_z: float = 0.0
    dowel_angle: float = math.pi / 2
    wrist_finish: str = "painted"

    def __post_init__(self) -> None:
        # Defaults that depend on other fields: flush wrist, face-edge circle.
        if self.wrist_diameter == 0.0:
            object.__setattr__(self, "wrist_diameter", self.outer_diameter)
        if self.circle_radius == 0.0:
            object.__setattr__(self, "circle_radius", self.outer_diameter / 2 - self.chamfer)
        self._check()

    def _check(self) -> None:
        lengths = {
            "pitch_diameter": self.pitch_diameter,
            "outer_diameter": self.outer_diameter,
            "bore_diameter": self.bore_diameter,
            "bore_depth": self.bore_depth,
            "hole_diameter": self.hole_diameter,
            "hole_depth": self.hole_depth,
            "dowel_diameter": self.dowel_diameter,
            "dowel_depth": self.dowel_depth,
            "thickness": self.thickness,
            "wrist_depth": self.wrist_depth,
            "circle_radius": self.circle_radius,
        }
        for key, value in lengths.items():
            if not (math.isfinite(value) and 0.0 < value < 1.0):
                raise InputError(f"flange {self.name!r}: {key} must be in (0, 1) m, got {value!r}")
        if not (math.isfinite(self.chamfer) and 0.0 <= self.chamfer):
            raise InputError(f"flange {self.name!r}: chamfer must be >= 0 m, got {self.chamfer!r}")
        if self.n_holes < 1:
            raise InputError(f"flange {self.name!r}: n_holes must be >= 1, got {self.n_holes}")
        r_face = self.outer_diameter / 2 - self.chamfer
        r_hole = max(self.hole_diameter, self.dowel_diameter) / 2
        if not self.bore_diameter / 2 + r_hole < self.pitch_diameter / 2 < r_face - r_hole:
            raise InputError(
                f"flange {self.name!r}: holes on the pitch circle (d1 = {self.pitch_diameter * 1e3:.2f} mm, "
                f"hole {2 * r_hole * 1e3:.2f} mm) must lie between the bore "
                f"({self.bore_diameter * 1e3:.2f} mm) and the chamfer (face {2 * r_face * 1e3:.2f} mm)"
            )
        if self.chamfer >= self.thickness:
            raise InputError(f"flange {self.name!r}: chamfer {self.chamfer} m must be less than thickness {self.thickness} m")
        if self.wrist_diameter < self.outer_diameter:
            raise InputError(
                f"flange {self.name!r}: wrist_diameter {self.wrist_diameter} m must be at least outer_diameter {self.outer_diameter} m"
            )
        if max(self.hole_depth, self.dowel_depth, self.bore_depth) >= self.thickness + self.wrist_depth:
            raise InputError(f"flange {self.name!r}: holes and bore must end inside the body (thickness + wrist_depth)")
        if not -(self.thickness + self.wrist_depth) < self.circle_z <= 0.0:
            raise InputError(f"flange {self.name!r}: circle_z must lie on the body, got {self.circle_z} m")
        if self.wrist_finish not in FINISHES:
            raise InputError(f"flange {self.name!r}: wrist_finish must be one of {', '.join(FINISHES)}, got {self.wrist_finish!r}")

    # -- derived geometry ----------------------------------------------------

    @property
    def circle_on_metal(self) -> bool:
        """The detector's circle (and the height it is placed at) lies on bare metal: the tool flange, or a metal wrist."""
        return self.circle_radius <= self.outer_diameter / 2 + 1e-9 or self.wrist_finish == "metal"

    @property
    def finish_step(self) -> float | None:
        """Height of the metal face above the painted shoulder, m (``thickness``); None without a painted shoulder to see."""
        if self.wrist_finish != "painted" or self.wrist_diameter / 2 - self.outer_diameter / 2 < _MIN_SHOULDER:
            return None
        return self.thickness

    @property
    def face_radius(self) -> float:
        """Radius of the flat part of the face, where the chamfer starts (m)."""
        return self.outer_diameter / 2 - self.chamfer

    def hole_centres(self) -> np.ndarray:
        """Centres (n_holes + 1, 2) of the threaded holes and, last, the dowel hole (x, y, m)."""
        r = self.pitch_diameter / 2
        step = 2 * math.pi / self.n_holes
        angles = self.dowel_angle + step * (np.arange(self.n_holes) + 0.5)
        angles = np.append(angles, self.dowel_angle)
        return r * np.column_stack([np.cos(angles), np.sin(angles)])

    def hole_radii(self) -> np.ndarray:
        """Radii (n_holes + 1,) matching :meth:`hole_centres` (m)."""
        return np.append(np.full(self.n_holes, self.hole_diameter / 2), self.dowel_diameter / 2)

    def hole_depths(self) -> np.ndarray:
        """Depths (n_holes + 1,) matching :meth:`hole_centres` (m)."""
        return np.append(np.full(self.n_holes, self.hole_depth), self.dowel_depth)

    # -- mesh and model cloud ------------------------------------------------

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """Closed triangle mesh of the flange and the wrist stub, flange frame, metres.

        Outward normals; watertight. A new mesh on every call (callers may
        transform it in place).
        """
        V, F = _flange_mesh_arrays(self)
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))
        mesh.merge_close_vertices(_MERGE_EPS)
        mesh.remove_degenerate_triangles()
        mesh.remove_duplicated_triangles()
        mesh.remove_unreferenced_vertices()
        mesh.compute_triangle_normals()
        mesh.compute_vertex_normals()
        return mesh

    def model_cloud(self, spacing: float = 0.0005) -> np.ndarray:
        """Points (n, 3) on the surfaces a camera in front of the face can see, flange frame, m.

        Every surface whose outward normal does not point behind the face
        (face, chamfer, bore, holes, shoulder, side walls) is sampled
        uniformly by area with about one point per ``spacing`` squared. The
        sampler is seeded: the same model gives the same cloud.
        """
        if not (math.isfinite(spacing) and 1e-5 <= spacing <= 0.01):
            raise InputError(f"model_cloud: spacing must be in [1e-5, 0.01] m, got {spacing!r}")
        V, F = _flange_mesh_arrays(self)
        tri = V[F]  # (m, 3, 3)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(cross, axis=1)
        keep = area2 > 0
        normal_z = np.zeros_like(area2)
        normal_z[keep] = cross[keep, 2] / area2[keep]
        keep &= normal_z > -1e-6  # drop the back cap: it faces away from the camera
        tri, area = tri[keep], 0.5 * area2[keep]
        n = int(math.ceil(area.sum() / spacing**2))
        rng = np.random.default_rng(_MODEL_CLOUD_SEED)
        idx = rng.choice(len(tri), size=n, p=area / area.sum())
        u, v = rng.random(n), rng.random(n)
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        t = tri[idx]
        return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def _n_segments(radius: float, min_segments: int = 24) -> int:
    return max(min_segments, int(math.ceil(2 * math.pi * radius / _MESH_CHORD)))


def _revolve(profile: list[tuple[float, float]], n: int, centre: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Revolve a polyline profile [(r, z), ...] about a z axis through ``centre``.

    Triangles are wound so that their normal is (-dz, dr) in the (r, z) plane
    for a profile step (dr, dz): walk a profile with the solid on its left.
    """
    theta = 2 * math.pi * np.arange(n) / n
    c, s = np.cos(theta), np.sin(theta)
    verts, faces = [], []
    base = 0
    for (r0, z0), (r1, z1) in itertools.pairwise(profile):
        if r0 == r1 and z0 == z1:
            continue
        ring0 = np.column_stack([centre[0] + r0 * c, centre[1] + r0 * s, np.full(n, z0)])
        ring1 = np.column_stack([centre[0] + r1 * c, centre[1] + r1 * s, np.full(n, z1)])
        verts += [ring0, ring1]
        k = np.arange(n)
        k1 = (k + 1) % n
        a, b = base + k, base + k1  # ring0 at theta_k, theta_k+1
        cc, d = base + n + k, base + n + k1  # ring1
        faces += [np.column_stack([a, cc, b]), np.column_stack([b, cc, d])]
        base += 2 * n
    return np.vstack(verts), np.vstack(faces)


def _ring(radius: float, n: int, centre: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    theta = 2 * math.pi * np.arange(n) / n
    return np.column_stack([centre[0] + radius * np.cos(theta), centre[1] + radius * np.sin(theta)])


def _face_triangulation(model: FlangeModel, n_outer: int, n_bore: int, hole_ns: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The face annulus at z = 0 with the holes cut out, triangles facing +z.

    Delaunay of the boundary vertices only: every boundary chord is much
    shorter than the gap to the next boundary, so each chord is an edge of the
    triangulation and a triangle lies wholly inside or outside the face.
    """
    centres, radii = model.hole_centres(), model.hole_radii()
    rings = [_ring(model.face_radius, n_outer), _ring(model.bore_diameter / 2, n_bore)]
    rings += [_ring(r, n, (float(cx), float(cy))) for (cx, cy), r, n in zip(centres, radii, hole_ns)]
    P = np.vstack(rings)
    tri = Delaunay(P).simplices
    g = P[tri].mean(axis=1)
    rho = np.linalg.norm(g, axis=1)
    inside = (rho < model.face_radius) & (rho > model.bore_diameter / 2)
    for (cx, cy), r in zip(centres, radii):
        inside &= np.hypot(g[:, 0] - cx, g[:, 1] - cy) > r
    tri = tri[inside]
    # Wind every triangle counter-clockwise seen from +z.
    a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    cw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
    tri[cw] = tri[cw][:, [0, 2, 1]]
    return np.column_stack([P, np.zeros(len(P))]), tri


def _flange_mesh_arrays(model: FlangeModel) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and triangles (m, 3) of the whole solid, parts not yet merged."""
    r_face, r_out = model.face_radius, model.outer_diameter / 2
    r_bore, r_wrist = model.bore_diameter / 2, model.wrist_diameter / 2
    t, back = model.thickness, model.thickness + model.wrist_depth
    n_outer = _n_segments(r_wrist)
    n_bore = _n_segments(r_bore)
    hole_ns = [_n_segments(r, 32) for r in model.hole_radii()]

    parts = [_face_triangulation(model, n_outer, n_bore, hole_ns)]
    # Outside, from the face edge round to the back cap (solid on the left).
    outer = [(r_face, 0.0), (r_out, -model.chamfer), (r_out, -t), (r_wrist, -t), (r_wrist, -back), (0.0, -back)]
    parts.append(_revolve(outer, n_outer))
    # The centring recess: bottom outwards, then its wall up to the face.
    parts.append(_revolve([(0.0, -model.bore_depth), (r_bore, -model.bore_depth), (r_bore, 0.0)], n_bore))
    for (cx, cy), r, depth, n in zip(model.hole_centres(), model.hole_radii(), model.hole_depths(), hole_ns):
        parts.append(_revolve([(0.0, -depth), (r, -depth), (r, 0.0)], n, (float(cx), float(cy))))

    verts, faces, base = [], [], 0
    for V, F in parts:
        verts.append(V)
        faces.append(F + base)
        base += len(V)
    return np.vstack(verts), np.vstack(faces).astype(np.int32)


# -- presets ------------------------------------------------------------------

_ISO_50_4_M6: dict[str, Any] = dict(
    pitch_diameter=0.050,
    outer_diameter=0.063,
    bore_diameter=0.0315,
    bore_depth=0.0062,  # UR drawing; ISO fixes only a minimum engagement
    n_holes=4,
    hole_diameter=0.006,
    hole_depth=0.008,
    dowel_diameter=0.006,
    dowel_depth=0.006,
    chamfer=0.0005,  # not in the standard; gives the paper's R = 31 mm
    thickness=0.0065,  # UR: the flange stands 6.5 mm proud of the wrist
)

PRESETS: dict[str, FlangeModel] = {
    "iso9409-1-50-4-m6": FlangeModel(name="iso9409-1-50-4-m6", **_ISO_50_4_M6),
    "iso9409-1-31.5-4-m5": FlangeModel(
        name="iso9409-1-31.5-4-m5",
        pitch_diameter=0.0315,
        outer_diameter=0.040,  # R10 step above d1
        bore_diameter=0.020,  # R10 steps below d1
        bore_depth=0.005,  # plausible value, not from a drawing
        n_holes=4,
        hole_diameter=0.005,
        hole_depth=0.0075,
        dowel_diameter=0.005,
        dowel_depth=0.005,
        chamfer=0.0005,
        thickness=0.006,
    ),
    "iso9409-1-80-6-m8": FlangeModel(
        name="iso9409-1-80-6-m8",
        pitch_diameter=0.080,
        outer_diameter=0.100,
        bore_diameter=0.050,
        bore_depth=0.008,
        n_holes=6,
        hole_diameter=0.008,
        hole_depth=0.01725,  # UR20/UR30 drawing as transcribed
        dowel_diameter=0.008,
        dowel_depth=0.008,
        chamfer=0.0005,
        thickness=0.008,
    ),
    "ur5": FlangeModel(name="ur5", wrist_diameter=0.075, **_ISO_50_4_M6),  # CB3 wrist 75 mm
    "ur10e": FlangeModel(name="ur10e", wrist_diameter=0.090, **_ISO_50_4_M6),
    # Franka and AUBO: the 50-4-M6 face; wrist bodies are plausible sizes, not from drawings.
    "franka": FlangeModel(name="franka", wrist_diameter=0.075, **_ISO_50_4_M6),
    "aubo-i5": FlangeModel(name="aubo-i5", wrist_diameter=0.080, **_ISO_50_4_M6),
    # The 90 mm outer circle of the UR10e wrist, 6.5 mm behind the face (paper section 4.2).
    "ur10e-wrist": FlangeModel(name="ur10e-wrist", wrist_diameter=0.090, circle_radius=0.045, circle_z=-0.0065, **_ISO_50_4_M6),
}


def preset(name: str) -> FlangeModel:
    """Return the preset flange called ``name`` (case-insensitive).

    Raises
    ------
    InputError
        The name is not a preset; the message lists the known names.
    """
    key = str(name).strip().lower()
    try:
        return PRESETS[key]
    except KeyError:
        raise InputError(f"unknown flange {name!r}; known presets: {', '.join(PRESETS)}") from None
