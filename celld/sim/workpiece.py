"""The simulated part on the table: the part as made and as placed, its scene, the wall the finger truly touches.

A workpiece (metal) lies on the welding table (steel, top at base z = 0) under
the cell's scanner. The seam finder knows the part's model; the simulator
owns the part as it is (:class:`~celld.sim.world.PartTruth`):

- placed off its place by the world's placement error, set down on the table;
- made off its model by the world's shape error: :func:`distorted_groove`
  sweeps the single-V profile along a bowed, lifted, twisted and tack-kinked
  seam with a root gap that varies along it (the model is straight, flat,
  with a constant gap);
- its finger wall measured on the true part by the simulator itself
  (:func:`true_part`): rays from the true seam across the joint onto the
  labelled wall, at every station and at heights from just above the root
  face to just below the plate's top, so the simulated finger touches the
  wall at the height where its tip truly is (on a V-groove's leaning bevel a
  tip riding 1 mm lower meets the wall 0.58 mm nearer the seam). Nothing here
  uses the daemon's weld-path functions, which work on the nominal model.

Only the simulator reads the truth; it is returned beside the scene so the
demo and the benchmarks can score the torch against the true seam.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from celld import se3
from celld.errors import WorkpieceError
from celld.seam.workpiece import LEFT_WALL, NO_WALL, RIGHT_WALL, Workpiece, example, v_groove_butt
from celld.sim.scene import SceneObject, box
from celld.sim.srm import WallSurface

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
# Stations of the true part along its seam, m apart.
_STATION = 0.001
# The true wall is measured at these heights above the root face (m): from just
# above it to just below the plate's top, every half millimetre.
_WALL_STEP = 0.0005
_WALL_MARGIN = 0.0005
# A tack weld pulls the joint sideways over about this length either side, m.
_TACK_WIDTH = 0.010


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


# -- the part as made ----------------------------------------------------------------


class Stations(NamedTuple):
    """The true part's seam, station by station, model frame (m).

    ``seam`` (n, 3) is the root line (the gap's centre on top of the root
    faces), ``lateral`` (n, 3) the unit direction across the joint towards the
    left plate, ``up`` (n, 3) the unit direction out of the joint.
    """

    seam: Array
    lateral: Array
    up: Array


def _sweep_stations(
    profiles: Array, path: Array, lateral: Array, up: Array, labels: dict[int, int]
) -> tuple[Array, NDArray[np.int64], NDArray[np.int8]]:
    """A convex profile that changes along the path, swept into a closed prism mesh.

    ``profiles`` (m, k, 2) are counter-clockwise (lateral, up) coordinates at
    each of the m path points; otherwise as :func:`celld.seam.workpiece._sweep`.
    """
    m, k = profiles.shape[:2]
    V = (path[:, None, :] + profiles[:, :, 0, None] * lateral[:, None, :] + profiles[:, :, 1, None] * up[:, None, :]).reshape(-1, 3)
    i = np.arange(m - 1)[:, None]
    tris, lab = [], []
    for j in range(k):
        jn = (j + 1) % k
        a, b = i * k + j, i * k + jn
        c, d = (i + 1) * k + jn, (i + 1) * k + j
        tris += [np.hstack([a, b, c]), np.hstack([a, c, d])]
        lab += [np.full(m - 1, labels.get(j, NO_WALL))] * 2
    end = (m - 1) * k
    caps = [(0, j + 1, j) for j in range(1, k - 1)] + [(end, end + j, end + j + 1) for j in range(1, k - 1)]
    F = np.vstack([*tris, np.asarray(caps)])
    L = np.concatenate([*lab, np.full(len(caps), NO_WALL)])
    return V, F.astype(np.int64), L.astype(np.int8)


def _nominal_path(workpiece: Workpiece) -> tuple[Array, Array, str]:
    """The undistorted root path at z = 0 (m, 3) of a groove model, with its lateral directions."""
    p = workpiece.params
    if workpiece.name == "v-groove":
        n = max(2, int(round(p["length"] / _STATION)) + 1)
        x = np.linspace(-p["length"] / 2.0, p["length"] / 2.0, n)
        path = np.column_stack([x, np.zeros(n), np.zeros(n)])
        return path, np.tile([0.0, 1.0, 0.0], (n, 1)), "v-groove"
    if workpiece.name == "curved-groove":
        R, arc = p["radius"], p["arc_angle"]
        n = max(4, int(round(R * arc / _STATION)) + 1)
        theta = np.linspace(-arc / 2.0, arc / 2.0, n)
        path = np.array([0.0, R, 0.0]) + R * np.column_stack([np.sin(theta), -np.cos(theta), np.zeros(n)])
        return path, np.column_stack([-np.sin(theta), np.cos(theta), np.zeros(n)]), "curved-groove"
    raise WorkpieceError(f"{workpiece.name}: the simulator distorts grooves only (v-groove, curved-groove)")


def distorted_groove(name: str, shape: object) -> tuple[Workpiece, Stations]:
    """The example groove ``name`` as made: its model's profile swept along a distorted seam.

    ``shape`` is a :class:`celld.sim.world.PartShape`: a sideways bow and a
    vertical bow (half a sine over the seam, largest at mid-length), tack-weld
    kinks (a Gaussian bump sideways at each tack), a twist of the joint about
    the seam growing linearly from start to end, and a root gap varying as a
    sine of ``gap_waves`` half-waves. The model's parameters (thickness,
    groove angle, gap, root face, plate width) are the nominal ones.
    """
    model = example(name)
    p = model.params
    t, alpha, b, c, W = p["thickness"], p["groove_angle"], p["root_gap"], p["root_face"], p["plate_width"]
    path0, lat0, _ = _nominal_path(model)
    n = len(path0)
    s = np.linspace(0.0, 1.0, n)
    arch = np.sin(math.pi * s)
    side = shape.bow * arch  # type: ignore[attr-defined]
    length = float(np.sum(np.linalg.norm(np.diff(path0, axis=0), axis=1)))
    for x_t, kink in shape.tacks:  # type: ignore[attr-defined]
        side = side + kink * np.exp(-(((s - x_t) * length / _TACK_WIDTH) ** 2))
    up0 = np.array([0.0, 0.0, 1.0])
    path = path0 + side[:, None] * lat0 + (shape.bow_vertical * arch)[:, None] * up0  # type: ignore[attr-defined]
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    lateral = np.cross(up0, tangent)
    lateral /= np.linalg.norm(lateral, axis=1)[:, None]
    up = np.cross(tangent, lateral)
    # The twist turns each station's profile about its tangent.
    phi = shape.twist * (s - 0.5)  # type: ignore[attr-defined]
    lat_t = np.cos(phi)[:, None] * lateral + np.sin(phi)[:, None] * up
    up_t = -np.sin(phi)[:, None] * lateral + np.cos(phi)[:, None] * up
    gap = b + shape.gap_amplitude * np.sin(shape.gap_waves * math.pi * s + shape.gap_phase)  # type: ignore[attr-defined]
    if np.any(gap < 0.0):
        raise WorkpieceError(f"{name}: the root gap's variation closes the gap (min {gap.min() * 1e3:.2f} mm)")
    h = (t - c) * math.tan(alpha / 2.0)
    g = gap / 2.0
    zeros, ones = np.zeros(n), np.ones(n)
    left = np.stack(
        [
            np.column_stack([g, zeros]),
            np.column_stack([g + W, zeros]),
            np.column_stack([g + W, t * ones]),
            np.column_stack([g + h, t * ones]),
            np.column_stack([g, c * ones]),
        ],
        axis=1,
    )
    right = np.stack(
        [
            np.column_stack([-g, c * ones]),
            np.column_stack([-g - h, t * ones]),
            np.column_stack([-g - W, t * ones]),
            np.column_stack([-g - W, zeros]),
            np.column_stack([-g, zeros]),
        ],
        axis=1,
    )
    parts = [_sweep_stations(left, path, lat_t, up_t, {3: LEFT_WALL}), _sweep_stations(right, path, lat_t, up_t, {0: RIGHT_WALL})]
    V = np.vstack([parts[0][0], parts[1][0]])
    F = np.vstack([parts[0][1], parts[1][1] + len(parts[0][0])])
    L = np.concatenate([parts[0][2], parts[1][2]])
    seam = path + c * up_t
    bevel = (t - c) / math.cos(alpha / 2.0)
    band = (math.hypot(b / 2.0, c) + 0.5e-3, b / 2.0 + 0.85 * bevel)
    wp = Workpiece(name, V, F, seam, up0, L, band, "v-groove", dict(p))
    return wp, Stations(seam, lat_t, up_t)


def _model_stations(workpiece: Workpiece) -> Stations:
    """Stations of a model swept along a flat path with the profile across it (the shipped generators)."""
    from celld.seam.weldpath import model_seam_frames

    P, _, lat = model_seam_frames(workpiece, "left", _STATION)  # lat = approach x tangent
    up = np.asarray(workpiece.approach, dtype=np.float64)
    return Stations(P, lat, np.tile(up, (len(P), 1)))


def part_model(part: object) -> tuple[Workpiece, Stations]:
    """The true part of a :class:`~celld.sim.world.PartTruth`, model frame, and its seam's stations."""
    shape = part.shape  # type: ignore[attr-defined]
    name = part.workpiece  # type: ignore[attr-defined]
    if shape.bow_only and (shape.bow == 0.0 or name == "v-groove"):
        # The model itself (bowed as the shipped generator bows it): the cell before it had a world.
        wp = v_groove_butt(bow=shape.bow) if shape.bow else example(name)
        return wp, _model_stations(wp)
    return distorted_groove(name, shape)


# -- the part on the table and the wall the finger touches ------------------------------


class SimWorkpiece(NamedTuple):
    """The simulated part: as made, as placed, its true seam and its true finger wall.

    ``workpiece`` is the true part (model frame), ``T_base_obj`` its true
    pose; ``seam_base`` (n, 3) the true root line in the base frame (the line
    the torch must follow); ``T_base_plane`` the welding plane (z out of the
    joint, x along the seam's chord, origin on its first station); ``wall``
    the finger wall in that plane, at heights above the root (what the SRM
    touches); ``wall_side`` which wall the finger presses; ``far_wall`` the
    joint's other wall (None for a joint with one).
    """

    workpiece: Workpiece
    T_base_obj: Array
    seam_base: Array
    T_base_plane: Array
    wall: WallSurface
    wall_side: str
    far_wall: WallSurface | None = None


def place(part: object, workpiece: Workpiece) -> Array:
    """The true pose of ``workpiece`` for a :class:`~celld.sim.world.PartTruth`: its place, the placement error, set down."""
    T = np.array(part.T_base_place, dtype=np.float64)  # type: ignore[attr-defined]
    dx, dy = part.offset_xy  # type: ignore[attr-defined]
    yaw = part.yaw  # type: ignore[attr-defined]
    if dx == 0.0 and dy == 0.0 and yaw == 0.0 and part.shape.bow_only:  # type: ignore[attr-defined]
        if T[2, 3] == 0.0 and np.allclose(T[:3, 2], [0.0, 0.0, 1.0]):
            return set_down(workpiece, T)
        return T
    T[:3, :3] = se3.from_xyz_rpy([0.0, 0.0, 0.0], [0.0, 0.0, yaw])[:3, :3] @ T[:3, :3]
    T[0, 3] += dx
    T[1, 3] += dy
    return set_down(workpiece, T)


def true_part(part: object, wall_side: str = "left") -> SimWorkpiece:
    """The simulated part of a :class:`~celld.sim.world.PartTruth` with the finger on its ``wall_side`` wall."""
    wp, st = part_model(part)
    return on_table(wp, st, place(part, wp), wall_side)


def on_table(workpiece: Workpiece, stations: Stations, T_base_obj: Array, wall_side: str = "left") -> SimWorkpiece:
    """A part at ``T_base_obj`` with its finger wall measured by ray casting at every station and height.

    Raises
    ------
    WorkpieceError
        The part has no labelled wall on ``wall_side``, or no ray finds it.
    """
    if wall_side not in ("left", "right"):
        raise WorkpieceError(f"wall_side: expected 'left' or 'right', got {wall_side!r}")
    T = np.asarray(T_base_obj, dtype=np.float64)
    hit, W_base, heights = _wall_hits(workpiece, stations, T, wall_side)
    seam_base = se3.apply(T, stations.seam[hit])
    z = T[:3, :3] @ np.asarray(workpiece.approach, dtype=np.float64)
    x = seam_base[-1] - seam_base[0]
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    T_base_plane = se3.transform_from(np.column_stack([x, np.cross(z, x), z]), seam_base[0])
    wall = _surface(W_base, heights, seam_base, T_base_plane, wall_side)
    far_side = "right" if wall_side == "left" else "left"
    try:
        far_hit, far_base, _ = _wall_hits(workpiece, stations, T, far_side)
        far_wall = _surface(far_base, heights, se3.apply(T, stations.seam[far_hit]), T_base_plane, far_side)
    except WorkpieceError:
        far_wall = None  # a joint with one wall (a fillet's web): nothing across
    return SimWorkpiece(workpiece, T, seam_base, T_base_plane, wall, wall_side, far_wall)


def _wall_hits(workpiece: Workpiece, stations: Stations, T_base_obj: Array, side: str) -> tuple[NDArray[np.bool_], Array, Array]:
    """Where rays across the joint from the seam meet the ``side`` wall: the stations hit at every
    height (n,), the wall points there (k, m, 3) in the base frame, and the heights (k,) above the root."""
    label = LEFT_WALL if side == "left" else RIGHT_WALL
    tris = workpiece.triangles[workpiece.wall_labels == label]
    if len(tris) == 0:
        raise WorkpieceError(f"{workpiece.name}: no triangle is labelled as the {side} wall")
    p = workpiece.params
    depth = p.get("thickness", 0.01) - p.get("root_face", 0.0)
    heights = np.arange(_WALL_MARGIN, depth - _WALL_MARGIN + 1e-9, _WALL_STEP)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(workpiece.vertices.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32)))
    sign = 1.0 if side == "left" else -1.0
    n, k = len(stations.seam), len(heights)
    origins = stations.seam[None, :, :] + heights[:, None, None] * stations.up[None, :, :]  # (k, n, 3)
    dirs = np.broadcast_to(sign * stations.lateral, (k, n, 3))
    rays = np.concatenate([origins, dirs], axis=2).reshape(-1, 6).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64).reshape(k, n)
    hit = np.all(np.isfinite(t_hit) & (t_hit < 0.05), axis=0)
    if hit.sum() < 2:
        raise WorkpieceError(f"{workpiece.name}: no ray across the joint meets the {side} wall")
    # Stations where a ray slips past the wall's end are left out (at most the end ones).
    W_obj = origins[:, hit] + t_hit[:, hit, None] * dirs[:, hit]
    return hit.astype(bool), se3.apply(T_base_obj, W_obj.reshape(-1, 3)).reshape(k, -1, 3), np.asarray(heights, dtype=np.float64)


def _surface(W_base: Array, heights: Array, seam_base: Array, T_base_plane: Array, side: str) -> WallSurface:
    o, R = T_base_plane[:3, 3], T_base_plane[:3, :3]
    lines = (W_base - o) @ R[:, :2]
    root_z = (seam_base - o) @ R[:, 2]
    # The free side (where the tip is) is right of the wall's travel for a left wall.
    return WallSurface(lines, heights, root_z, -1.0 if side == "left" else 1.0)
