"""Workpiece models: a triangle mesh with a seam polyline, in model coordinates.

A :class:`Workpiece` holds everything the seam finder knows about a part
before it sees it:

- the surface as a triangle mesh (``vertices`` (v, 3) m, ``triangles`` (f, 3)),
- the seam as an ordered polyline ``seam`` (n, 3) m, from start to end,
- the ``approach`` direction (3,): the unit vector from the seam out of the
  joint toward the tool; the tracking servo works in the plane normal to it,
- ``wall_labels`` (f,): which triangles are the two walls of the joint (the
  fusion faces: the bevels of a groove, the flange and web faces of a fillet).
  ``LEFT_WALL`` is on the left of the travel direction seen from the tool
  (along ``approach x tangent``), ``RIGHT_WALL`` on the right. The walls let
  :mod:`celld.seam.groove` measure the actual joint, model-free.

Model frames of the shipped examples: z up (``approach`` = +z), the part's
underside at z = 0 so it lies on a table, the seam running along +x through
the origin in x and y. Seam definitions:

- V-groove butt joint (ISO 9692-1 single-V, t, alpha, b, c): the root line,
  at the gap centre on top of the root faces (y = 0, z = c);
- fillet T-joint: the corner line between the flange top and the web face
  (the web stands off centre);
- curved groove: the same V profile swept along a circular arc.

User parts come from a mesh file (STL, PLY, OBJ) plus a seam file (JSON or
CSV, units stated in the file); see :func:`load_workpiece`. The model is
checked where it enters: a missing or degenerate seam, a seam off the mesh,
or millimetres read as metres raise :class:`~celld.errors.WorkpieceError`.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from celld import polyline
from celld.errors import WorkpieceError

Array = NDArray[np.float64]

# Triangle labels of the joint walls.
NO_WALL, LEFT_WALL, RIGHT_WALL = 0, 1, 2
# A part outside this extent (m) is taken as a units mistake, not a part.
MIN_EXTENT, MAX_EXTENT = 0.005, 5.0
# A seam vertex farther than this from the mesh surface (m) is off the part.
SEAM_TOLERANCE = 0.005
# Shortest seam that can be tracked (m).
MIN_SEAM_LENGTH = 0.005
# Radial band around the seam (m) where user-mesh walls are looked for.
DEFAULT_WALL_BAND = (0.0015, 0.010)
# Seam units accepted in seam files, to metres.
_UNITS = {"m": 1.0, "mm": 1e-3}


def _readonly(a: ArrayLike, dtype: type = np.float64) -> NDArray:
    out: NDArray = np.array(a, dtype=dtype)  # a copy: the caller's array stays theirs
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Workpiece:
    """A part model: mesh, seam and joint walls, all in the model frame (metres).

    Construct through the generators or :func:`load_workpiece`; the
    constructor validates and raises :class:`~celld.errors.WorkpieceError`.

    Attributes
    ----------
    name : str
    vertices : (v, 3) float array, m, model frame
    triangles : (f, 3) int array, indices into ``vertices``
    seam : (n, 3) float array, m, model frame, ordered from start to end
    approach : (3,) unit vector, model frame, from the seam toward the tool
    wall_labels : (f,) int8 array of ``NO_WALL``, ``LEFT_WALL``, ``RIGHT_WALL``
    wall_band : (inner, outer) m, radial distance from the seam within which
        the walls are measured; ``inner`` skips the root faces and gap
    joint : str, ``"v-groove"``, ``"fillet"`` or ``"user"``
    """

    name: str
    vertices: Array
    triangles: NDArray[np.int64]
    seam: Array
    approach: Array
    wall_labels: NDArray[np.int8]
    wall_band: tuple[float, float] = DEFAULT_WALL_BAND
    joint: str = "user"
    params: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        V = _readonly(self.vertices)
        F = _readonly(self.triangles, np.int64)
        S = _readonly(self.seam)
        a = np.asarray(self.approach, dtype=np.float64)
        labels = _readonly(self.wall_labels, np.int8)
        if V.ndim != 2 or V.shape[1] != 3 or len(V) < 3 or not np.all(np.isfinite(V)):
            raise WorkpieceError(f"{self.name}: mesh vertices must be a finite (v, 3) array with v >= 3, got shape {V.shape}")
        if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
            raise WorkpieceError(f"{self.name}: mesh has no triangles (got shape {F.shape})")
        if F.min() < 0 or F.max() >= len(V):
            raise WorkpieceError(f"{self.name}: triangle indices outside 0..{len(V) - 1}")
        if labels.shape != (len(F),):
            raise WorkpieceError(f"{self.name}: wall_labels must have one label per triangle ({len(F)}), got {labels.shape}")
        if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-9:
            raise WorkpieceError(f"{self.name}: approach must be a non-zero 3-vector, got {a.tolist()}")
        inner, outer = self.wall_band
        if not 0.0 <= inner < outer:
            raise WorkpieceError(f"{self.name}: wall_band must be 0 <= inner < outer (m), got {self.wall_band}")
        extent = float(np.max(V.max(axis=0) - V.min(axis=0)))
        if extent > MAX_EXTENT:
            raise WorkpieceError(
                f"{self.name}: mesh spans {extent:.1f} m, expected at most {MAX_EXTENT} m: "
                "were millimetres read as metres? (give the mesh units)"
            )
        if extent < MIN_EXTENT:
            raise WorkpieceError(
                f"{self.name}: mesh spans {extent * 1e3:.3f} mm, expected at least {MIN_EXTENT * 1e3:.0f} mm: "
                "were metres read as millimetres? (give the mesh units)"
            )
        _check_seam(self.name, S, V, F, extent)
        object.__setattr__(self, "vertices", V)
        object.__setattr__(self, "triangles", F)
        object.__setattr__(self, "seam", S)
        object.__setattr__(self, "approach", _readonly(a / np.linalg.norm(a)))
        object.__setattr__(self, "wall_labels", labels)
        object.__setattr__(self, "params", dict(self.params))

    @property
    def has_walls(self) -> bool:
        """True when both joint walls are labelled, so the groove can be measured."""
        return bool(np.any(self.wall_labels == LEFT_WALL) and np.any(self.wall_labels == RIGHT_WALL))

    @property
    def seam_length(self) -> float:
        """Length of the seam polyline (m)."""
        return float(np.sum(np.linalg.norm(np.diff(self.seam, axis=0), axis=1)))

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """Return a new Open3D mesh of the part (model frame), with normals."""
        m = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(np.array(self.vertices)), o3d.utility.Vector3iVector(self.triangles.astype(np.int32))
        )
        m.compute_triangle_normals()
        m.compute_vertex_normals()
        return m


def _check_seam(name: str, S: Array, V: Array, F: NDArray[np.int64], extent: float) -> None:
    """Refuse a seam that is missing, degenerate, off the mesh or in other units."""
    if S.ndim != 2 or S.shape[1] != 3 or len(S) < 2:
        raise WorkpieceError(f"{name}: model has no seam: expected a polyline of at least 2 points (n, 3), got shape {S.shape}")
    if not np.all(np.isfinite(S)):
        raise WorkpieceError(f"{name}: seam contains NaN or infinite values")
    steps = np.linalg.norm(np.diff(S, axis=0), axis=1)
    if np.any(steps < 1e-9):
        raise WorkpieceError(f"{name}: seam has repeated consecutive points (at index {int(np.argmin(steps))})")
    length = float(steps.sum())
    seam_extent = float(np.max(S.max(axis=0) - S.min(axis=0)))
    if seam_extent > 100.0 * extent or (length > MIN_SEAM_LENGTH and length * 100.0 < extent and extent > 0.1):
        raise WorkpieceError(
            f"{name}: seam spans {seam_extent:.4g} m but the mesh {extent:.4g} m: the seam file and the mesh use different units"
        )
    if length < MIN_SEAM_LENGTH:
        raise WorkpieceError(f"{name}: seam is {length * 1e3:.2f} mm long, expected at least {MIN_SEAM_LENGTH * 1e3:.0f} mm")
    d = seam_distance_to_mesh(S, V, F)
    worst = int(np.argmax(d))
    if d[worst] > SEAM_TOLERANCE:
        raise WorkpieceError(
            f"{name}: seam lies outside the mesh: point {worst} {np.round(S[worst] * 1e3, 2).tolist()} mm "
            f"is {d[worst] * 1e3:.1f} mm from the surface (at most {SEAM_TOLERANCE * 1e3:.0f} mm allowed)"
        )


def seam_distance_to_mesh(S: Array, V: Array, F: NDArray[np.int64], step: float = 0.001) -> Array:
    """Distance (m) from the seam, sampled every ``step`` m, to the mesh surface.

    Returns one value per seam vertex: the largest distance over the samples
    of the segments that end at that vertex.
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    per_vertex = np.zeros(len(S))
    for i in range(len(S) - 1):
        n = max(2, int(math.ceil(np.linalg.norm(S[i + 1] - S[i]) / step)) + 1)
        q = np.linspace(S[i], S[i + 1], n).astype(np.float32)
        d = scene.compute_distance(o3d.core.Tensor(q)).numpy()
        per_vertex[i] = max(per_vertex[i], float(d[: n // 2 + 1].max()))
        per_vertex[i + 1] = max(per_vertex[i + 1], float(d[n // 2 :].max()))
    return per_vertex


# -- mesh building --------------------------------------------------------------


def _sweep(
    profile: Array,
    path: Array,
    lateral: Array,
    up: Array,
    labels: dict[int, int] | None = None,
    omit: frozenset[int] = frozenset(),
) -> tuple[Array, NDArray[np.int64], NDArray[np.int8]]:
    """Sweep a convex profile along a path into a closed prism mesh.

    Parameters
    ----------
    profile : (k, 2) counter-clockwise (lateral, up) coordinates, m
    path : (m, 3) path points, m
    lateral, up : (m, 3) unit vectors at each path point; ``lateral x up``
        must point along the path
    labels : wall label of profile edge j (from vertex j to j + 1)
    omit : profile edges to leave out (faces hidden against another solid)

    Returns
    -------
    vertices (m*k, 3), triangles (f, 3) with outward normals, labels (f,)
    """
    labels = labels or {}
    k, m = len(profile), len(path)
    V = (path[:, None, :] + profile[None, :, 0, None] * lateral[:, None, :] + profile[None, :, 1, None] * up[:, None, :]).reshape(-1, 3)
    tris: list[tuple[int, int, int]] = []
    lab: list[int] = []
    for j in range(k):
        if j in omit:
            continue
        jn = (j + 1) % k
        for i in range(m - 1):
            a, b = i * k + j, i * k + jn
            c, d = (i + 1) * k + jn, (i + 1) * k + j
            tris += [(a, b, c), (a, c, d)]
            lab += [labels.get(j, NO_WALL)] * 2
    end = (m - 1) * k
    for j in range(1, k - 1):
        tris.append((0, j + 1, j))  # start cap, facing back along the path
        tris.append((end, end + j, end + j + 1))  # end cap
        lab += [NO_WALL, NO_WALL]
    return V, np.asarray(tris, dtype=np.int64), np.asarray(lab, dtype=np.int8)


def _merge(*parts: tuple[Array, NDArray[np.int64], NDArray[np.int8]]) -> tuple[Array, NDArray[np.int64], NDArray[np.int8]]:
    Vs, Fs, Ls, offset = [], [], [], 0
    for V, F, L in parts:
        Vs.append(V)
        Fs.append(F + offset)
        Ls.append(L)
        offset += len(V)
    return np.vstack(Vs), np.vstack(Fs), np.concatenate(Ls)


def _v_profiles(thickness: float, groove_angle: float, root_gap: float, root_face: float, plate_width: float) -> tuple[Array, Array]:
    """Left and right plate profiles (lateral, up) of an ISO 9692-1 single-V groove."""
    h = (thickness - root_face) * math.tan(groove_angle / 2.0)
    g = root_gap / 2.0
    left = np.array([[g, 0.0], [g + plate_width, 0.0], [g + plate_width, thickness], [g + h, thickness], [g, root_face]])
    right = np.array([[-g, root_face], [-g - h, thickness], [-g - plate_width, thickness], [-g - plate_width, 0.0], [-g, 0.0]])
    return left, right


def _check_positive(**values: float) -> None:
    for key, v in values.items():
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise WorkpieceError(f"{key}: expected a positive length in metres, got {v!r}")


def _v_groove_along(name: str, path: Array, lateral: Array, params: dict[str, float]) -> Workpiece:
    """The single-V profile of ``params`` swept along ``path`` (z = 0, ``lateral`` towards the left plate)."""
    t, a, b, c = params["thickness"], params["groove_angle"], params["root_gap"], params["root_face"]
    left, right = _v_profiles(t, a, b, c, params["plate_width"])
    up = np.tile([0.0, 0.0, 1.0], (len(path), 1))
    V, F, L = _merge(
        _sweep(left, path, lateral, up, labels={3: LEFT_WALL}),
        _sweep(right, path, lateral, up, labels={0: RIGHT_WALL}),
    )
    bevel = (t - c) / math.cos(a / 2.0)
    band = (math.hypot(b / 2.0, c) + 0.5e-3, b / 2.0 + 0.85 * bevel)
    return Workpiece(name, V, F, path + np.array([0.0, 0.0, c]), np.array([0.0, 0.0, 1.0]), L, band, "v-groove", params)


def v_groove_butt(
    thickness: float = 0.010,
    groove_angle: float = math.radians(60.0),
    root_gap: float = 0.002,
    root_face: float = 0.001,
    length: float = 0.150,
    plate_width: float = 0.060,
    bow: float = 0.0,
) -> Workpiece:
    """Single-V butt joint of two plates (ISO 9692-1: t, alpha, b, c), SI units.

    The seam is the root line at the gap centre on top of the root faces,
    (x, 0, c) for x in [-length/2, length/2]; the left plate (y > 0) carries
    the left wall. The part lies on z = 0. ``bow`` (m) bends the joint
    sideways, ``y = bow sin(pi (x / length + 1/2))``, as tack welds pull real
    plates: the same profile swept along the bent line (0: straight).
    """
    _check_positive(thickness=thickness, groove_angle=groove_angle, length=length, plate_width=plate_width)
    if not 0.0 <= root_face < thickness:
        raise WorkpieceError(f"root_face: expected 0 <= c < t = {thickness} m, got {root_face}")
    if root_gap < 0.0 or not 0.0 < groove_angle < math.radians(120.0):
        raise WorkpieceError(f"expected root_gap >= 0 and 0 < groove_angle < 120 deg, got {root_gap}, {math.degrees(groove_angle):.1f} deg")
    if not math.isfinite(bow) or abs(bow) > 0.1 * length:
        raise WorkpieceError(f"bow: expected |bow| <= length / 10 = {0.1 * length} m, got {bow}")
    n = 2 if bow == 0.0 else 61
    x = np.linspace(-length / 2.0, length / 2.0, n)
    phase = math.pi * (x / length + 0.5)
    y = bow * np.sin(phase)
    dy = bow * math.pi / length * np.cos(phase)
    path = np.column_stack([x, y, np.zeros(n)])
    lat = np.column_stack([-dy, np.ones(n), np.zeros(n)]) / np.sqrt(1.0 + dy**2)[:, None]
    params = dict(
        thickness=thickness,
        groove_angle=groove_angle,
        root_gap=root_gap,
        root_face=root_face,
        length=length,
        plate_width=plate_width,
        bow=bow,
    )
    return _v_groove_along("v-groove", path, lat, params)


def fillet_t_joint(
    flange_thickness: float = 0.010,
    flange_width: float = 0.120,
    web_thickness: float = 0.010,
    web_height: float = 0.050,
    length: float = 0.150,
    web_offset: float = 0.020,
) -> Workpiece:
    """Fillet T-joint: a web plate standing on a flange plate, SI units.

    The flange lies on z = 0, centred on y = 0; the web stands with its centre
    at y = ``web_offset`` (off centre, so the part has no symmetric twin that
    would swap its two fillets). The seam is the corner between the flange
    top and the web's -y face, (x, web_offset - web_thickness/2,
    flange_thickness); the web is the left wall, the flange top the right.
    """
    _check_positive(
        flange_thickness=flange_thickness, flange_width=flange_width, web_thickness=web_thickness, web_height=web_height, length=length
    )
    if abs(web_offset) + web_thickness / 2.0 >= flange_width / 2.0:
        raise WorkpieceError(f"the web ({web_thickness} m thick at {web_offset} m) must stand on the flange ({flange_width} m wide)")
    y0, y1, tf = web_offset - web_thickness / 2.0, web_offset + web_thickness / 2.0, flange_thickness
    x = np.array([-length / 2.0, length / 2.0])
    path = np.column_stack([x, np.zeros(2), np.zeros(2)])
    lat = np.tile([0.0, 1.0, 0.0], (2, 1))
    up = np.tile([0.0, 0.0, 1.0], (2, 1))
    w = flange_width / 2.0
    flange = np.array([[-w, 0.0], [w, 0.0], [w, tf], [y1, tf], [y0, tf], [-w, tf]])
    web = np.array([[y0, tf], [y1, tf], [y1, tf + web_height], [y0, tf + web_height]])
    V, F, L = _merge(
        # flange edges: 0 bottom, 1 side, 2 top beyond the web, 3 under the web (hidden), 4 top before the web, 5 side
        _sweep(flange, path, lat, up, labels={4: RIGHT_WALL}, omit=frozenset({3})),
        # web edges: 0 bottom (hidden), 1 +y face, 2 top, 3 -y face
        _sweep(web, path, lat, up, labels={3: LEFT_WALL}, omit=frozenset({0})),
    )
    seam = np.column_stack([x, np.full(2, y0), np.full(2, tf)])
    band = (0.0015, min(0.012, 0.8 * web_height, 0.8 * (w + y0)))
    params = dict(
        flange_thickness=flange_thickness,
        flange_width=flange_width,
        web_thickness=web_thickness,
        web_height=web_height,
        length=length,
        web_offset=web_offset,
    )
    return Workpiece("fillet-t", V, F, seam, np.array([0.0, 0.0, 1.0]), L, band, "fillet", params)


def curved_groove(
    radius: float = 0.150,
    arc_angle: float = math.radians(60.0),
    thickness: float = 0.010,
    groove_angle: float = math.radians(60.0),
    root_gap: float = 0.002,
    root_face: float = 0.001,
    plate_width: float = 0.050,
    segments: int = 120,
) -> Workpiece:
    """Single-V groove along a circular arc of ``radius`` (m) and ``arc_angle`` (rad).

    The arc lies in the z = c plane, centred on (0, radius), starting and
    ending symmetric about x = 0 and travelled counter-clockwise seen from +z,
    so the inner plate is the left wall.
    """
    _check_positive(radius=radius, arc_angle=arc_angle, thickness=thickness, groove_angle=groove_angle, plate_width=plate_width)
    if plate_width + root_gap / 2.0 >= radius:
        raise WorkpieceError(f"plate_width {plate_width} m does not fit inside the radius {radius} m")
    if not 0.0 <= root_face < thickness or arc_angle > math.radians(300.0) or segments < 4:
        raise WorkpieceError("expected 0 <= root_face < thickness, arc_angle <= 300 deg and segments >= 4")
    theta = np.linspace(-arc_angle / 2.0, arc_angle / 2.0, segments + 1)
    centre = np.array([0.0, radius, 0.0])
    path = centre + radius * np.column_stack([np.sin(theta), -np.cos(theta), np.zeros_like(theta)])
    lat = np.column_stack([-np.sin(theta), np.cos(theta), np.zeros_like(theta)])  # toward the centre: left
    params = dict(
        radius=radius,
        arc_angle=arc_angle,
        thickness=thickness,
        groove_angle=groove_angle,
        root_gap=root_gap,
        root_face=root_face,
        plate_width=plate_width,
    )
    return _v_groove_along("curved-groove", path, lat, params)


# Shipped examples by name, built from their default parameters.
EXAMPLES: dict[str, Callable[[], Workpiece]] = {
    "v-groove": v_groove_butt,
    "fillet-t": fillet_t_joint,
    "curved-groove": curved_groove,
}


def example(name: str) -> Workpiece:
    """Return the shipped example ``name`` (one of :data:`EXAMPLES`)."""
    if name not in EXAMPLES:
        raise WorkpieceError(f"unknown example workpiece {name!r}: expected one of {', '.join(EXAMPLES)}")
    return EXAMPLES[name]()


# -- user parts ---------------------------------------------------------------------


@dataclass(frozen=True)
class SeamFile:
    """A seam file read and converted to metres."""

    points: Array  # (n, 3) m, model frame
    approach: Array  # (3,)
    wall_band: tuple[float, float]


def read_seam_file(path: str | Path) -> SeamFile:
    """Read a seam file: JSON or CSV, the units stated in the file.

    JSON::

        {"units": "mm", "points": [[x, y, z], ...],
         "approach": [0, 0, 1],            # optional, model frame, default +z
         "wall_band": [1.5, 10.0]}         # optional, in "units"

    CSV: a header row naming the columns with their unit, ``x_mm,y_mm,z_mm``
    or ``x_m,y_m,z_m``, then one point per row.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise WorkpieceError(f"{path}: cannot read seam file: {exc}") from exc
    if path.suffix.lower() == ".json":
        return _seam_from_json(path, text)
    if path.suffix.lower() == ".csv":
        return _seam_from_csv(path, text)
    raise WorkpieceError(f"{path}: seam file must be .json or .csv, got {path.suffix or 'no extension'!r}")


def _seam_from_json(path: Path, text: str) -> SeamFile:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise WorkpieceError(f"{path}: not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise WorkpieceError(f"{path}: expected a JSON object with 'units' and 'points'")
    unknown = set(data) - {"units", "points", "approach", "wall_band", "comment"}
    if unknown:
        raise WorkpieceError(f"{path}: unknown key {sorted(unknown)[0]!r} (known: units, points, approach, wall_band, comment)")
    units = data.get("units")
    if units not in _UNITS:
        raise WorkpieceError(f"{path}: 'units' must be one of {', '.join(_UNITS)}, got {units!r}")
    scale = _UNITS[units]
    pts = _as_points(path, data.get("points"), "points") * scale
    approach = np.asarray(data.get("approach", [0.0, 0.0, 1.0]), dtype=np.float64)
    if approach.shape != (3,) or not np.all(np.isfinite(approach)) or np.linalg.norm(approach) < 1e-9:
        raise WorkpieceError(f"{path}: 'approach' must be a non-zero 3-vector, got {data.get('approach')!r}")
    band = data.get("wall_band")
    wall_band = DEFAULT_WALL_BAND
    if band is not None:
        b = np.asarray(band, dtype=np.float64) * scale
        if b.shape != (2,) or not np.all(np.isfinite(b)) or not 0.0 <= b[0] < b[1]:
            raise WorkpieceError(f"{path}: 'wall_band' must be [inner, outer] with 0 <= inner < outer, got {band!r}")
        wall_band = (float(b[0]), float(b[1]))
    return SeamFile(pts, approach / np.linalg.norm(approach), wall_band)


def _seam_from_csv(path: Path, text: str) -> SeamFile:
    rows = [r for r in csv.reader(text.splitlines()) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise WorkpieceError(f"{path}: empty seam file (no seam)")
    header = [h.strip().lower() for h in rows[0]]
    units = next((u for u in _UNITS if header == [f"x_{u}", f"y_{u}", f"z_{u}"]), None)
    if units is None:
        raise WorkpieceError(f"{path}: first row must name the columns with their unit, 'x_mm,y_mm,z_mm' or 'x_m,y_m,z_m', got {rows[0]!r}")
    scale = _UNITS[units]
    try:
        values = [[float(v) for v in r] for r in rows[1:]]
    except ValueError as exc:
        raise WorkpieceError(f"{path}: non-numeric seam value: {exc}") from exc
    return SeamFile(_as_points(path, values, "rows") * scale, np.array([0.0, 0.0, 1.0]), DEFAULT_WALL_BAND)


def _as_points(path: Path, value: object, what: str) -> Array:
    if value is None or (isinstance(value, list) and not value):
        raise WorkpieceError(f"{path}: model has no seam: no {what} given")
    try:
        pts = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise WorkpieceError(f"{path}: seam {what} must be [x, y, z] triples: {exc}") from exc
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise WorkpieceError(f"{path}: seam {what} must be [x, y, z] triples, got shape {pts.shape}")
    return pts


def read_mesh(path: str | Path, units: str = "mm") -> tuple[Array, NDArray[np.int64]]:
    """Read an STL, PLY or OBJ mesh; return vertices in metres and triangles."""
    path = Path(path)
    if units not in _UNITS:
        raise WorkpieceError(f"mesh units must be one of {', '.join(_UNITS)}, got {units!r}")
    if path.suffix.lower() not in (".stl", ".ply", ".obj"):
        raise WorkpieceError(f"{path}: mesh must be .stl, .ply or .obj, got {path.suffix or 'no extension'!r}")
    if not path.is_file():
        raise WorkpieceError(f"{path}: mesh file not found")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise WorkpieceError(f"{path}: no triangles read (not a mesh, or an unreadable file)")
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    return np.asarray(mesh.vertices) * _UNITS[units], np.asarray(mesh.triangles, dtype=np.int64)


def load_workpiece(mesh_path: str | Path, seam_path: str | Path, mesh_units: str = "mm", name: str | None = None) -> Workpiece:
    """Load a user part: a mesh file plus a seam file (see :func:`read_seam_file`).

    The joint walls are found on the mesh by :func:`label_walls`; a part where
    they are not found can still be registered, but its groove is not measured.
    """
    V, F = read_mesh(mesh_path, mesh_units)
    seam = read_seam_file(seam_path)
    part_name = name or Path(mesh_path).stem
    # Validate mesh and seam before labelling (a wrong seam gives useless labels).
    bare = Workpiece(part_name, V, F, seam.points, seam.approach, np.zeros(len(F), np.int8), seam.wall_band)
    labels = label_walls(bare.vertices, bare.triangles, bare.seam, bare.approach, seam.wall_band)
    return Workpiece(part_name, V, F, seam.points, seam.approach, labels, seam.wall_band)


def label_walls(
    vertices: Array, triangles: NDArray[np.int64], seam: Array, approach: Array, band: tuple[float, float], plane_tol: float = 0.0015
) -> NDArray[np.int8]:
    """Find the two joint walls of a mesh: the faces whose planes run along the seam.

    A triangle is a wall candidate when part of it lies within ``band[1]`` of
    the seam, its plane passes within ``plane_tol`` of the seam there, and it
    does not face away from the approach direction. The
    candidates are split by their normal: a wall left of the seam faces back
    toward it, against ``approach x tangent``, and becomes ``LEFT_WALL``; the
    others become ``RIGHT_WALL``. Returns all ``NO_WALL`` when either side has
    no candidate.
    """
    samples, normals, tri = sample_surface(vertices, triangles, spacing=0.5e-3 if band[1] < 0.05 else band[1] / 100.0, seed=0)
    near = polyline.project(samples, seam)
    a = approach / np.linalg.norm(approach)
    left_dir = np.cross(a, near.tangent)
    radial = np.linalg.norm(samples - near.point, axis=1)
    plane_dist = np.abs(np.einsum("ij,ij->i", normals, samples - near.point))
    # Walls face the joint's open side, never away from the tool (the underside).
    open_side = normals @ a > -0.2
    cand = (radial <= band[1]) & (radial >= band[0]) & (plane_dist <= plane_tol) & near.inside & open_side
    labels = np.zeros(len(triangles), dtype=np.int8)
    if np.count_nonzero(cand) < 20:
        return labels
    side = np.einsum("ij,ij->i", normals[cand], left_dir[cand])
    # A left wall faces back toward the seam, so against the left direction.
    left_tris = np.unique(tri[cand][side < -0.2])
    right_tris = np.unique(tri[cand][side >= -0.2])
    if len(left_tris) == 0 or len(right_tris) == 0:
        return labels
    labels[right_tris] = RIGHT_WALL
    labels[left_tris] = LEFT_WALL
    return labels


# -- sampling (used by registration and groove measurement) ------------------------


def sample_surface(vertices: Array, triangles: NDArray[np.int64], spacing: float, seed: int = 0) -> tuple[Array, Array, NDArray[np.int64]]:
    """Sample a mesh surface with about one point per ``spacing**2`` of area.

    Returns points (n, 3), their triangle normals (n, 3) and triangle ids (n,).
    Deterministic for a given ``seed``.
    """
    A, B, C = (vertices[triangles[:, i]] for i in range(3))
    cross = np.cross(B - A, C - A)
    area2 = np.linalg.norm(cross, axis=1)
    ok = area2 > 1e-15
    normals = np.zeros_like(cross)
    normals[ok] = cross[ok] / area2[ok, None]
    counts = np.floor(area2 / 2.0 / spacing**2).astype(np.int64)
    rng = np.random.default_rng(seed)
    # Give small triangles their fair share by a random rounding of the fraction.
    frac = area2 / 2.0 / spacing**2 - counts
    counts += (rng.random(len(counts)) < frac).astype(np.int64)
    counts[~ok] = 0
    tri = np.repeat(np.arange(len(triangles)), counts)
    r1, r2 = rng.random(len(tri)), rng.random(len(tri))
    s = np.sqrt(r1)
    P = (1 - s)[:, None] * A[tri] + (s * (1 - r2))[:, None] * B[tri] + (s * r2)[:, None] * C[tri]
    return P, normals[tri], tri
