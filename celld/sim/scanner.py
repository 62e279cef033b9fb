"""Simulated 3D scanners: Open3D ray casting with a noise model per scanner kind.

:class:`SimScanner` casts one ray per pixel of a pinhole camera (OpenCV
convention: x right, y down, z along the optical axis) at the meshes of a
scene and returns an :class:`OrganizedCloud` at the scanner's resolution:
(H, W, 3) float32 points in the camera frame, metres, NaN where there is no
return. It is generic: any :class:`~celld.sim.scene.SceneObject` meshes, the
robot-cell scene of :func:`~celld.sim.scene.robot_scene` or a workpiece.
:class:`SimulatedScanner` puts one behind the cell's
:class:`~celld.scanner.base.Scanner` protocol: fixed at its true pose, it
captures whatever a scene source says is in view at that instant.

Noise models (:class:`ScannerModel`), applied in this order:

- range: no return outside ``[min_range, max_range]``;
- grazing angles: no return beyond ``max_incidence`` between the ray and the
  surface normal, a return dropped with a probability rising linearly from
  ``dropout_incidence`` up to it;
- structured light (PhoXi S / M): the projector sits ``baseline`` along +x of
  the camera; a point the projector cannot see (shadow) has no return, and
  the projector's own incidence counts for the grazing test;
- depth noise along the ray, Gaussian, ``sigma`` at ``sigma_range`` growing
  as ``(range / sigma_range) ** sigma_exponent`` (2 for triangulation),
  times ``metal_sigma_scale`` on metal;
- time of flight (Azure Kinect DK): a range bias ``metal_bias`` on metal
  (multipath makes bright machined metal read long), and flying pixels: a
  pixel next to a depth step larger than ``flying_jump`` takes, with
  probability ``flying_probability``, a depth between its own and its
  neighbour's;
- the unit's own measuring error, when it is given one (``measure``, the
  simulated world's depth scale and smooth distortion,
  :class:`celld.sim.world.ScannerTruth`): applied to every point last.

Figures: PhoXi M 2064 x 1544, 0.458-1.118 m, about 0.29 mm point spacing at
0.65 m, sigma 0.1 mm; PhoXi S 0.384-0.520 m, 0.16 mm spacing at 0.442 m,
sigma 0.05 mm (the 0.05-0.1 mm of the paper, section 3.2.1). Azure Kinect DK
NFOV unbinned 640 x 576, 75 x 65 degrees, 0.5-3.86 m, a few mm of noise and a
cm-level bias on metal (``research/handeye_anchors.md`` section 4). Values
not on a datasheet (bias, dropout angles, flying-pixel rate) are plausible
choices, named in each model.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import open3d as o3d

from celld import se3
from celld.calib.flange import FlangeModel
from celld.config import ToolConfig
from celld.errors import DeviceError, InputError
from celld.scanner.base import CaptureStats, OrganizedCloud
from celld.sim.scene import SceneObject, robot_scene

__all__ = [
    "SCANNER_MODELS",
    "OrganizedCloud",
    "ScannerModel",
    "SceneObject",
    "SceneSource",
    "SimScanner",
    "SimulatedScanner",
    "robot_scene",
    "robot_scene_source",
    "scanner_model",
]

# A scene source: called at each capture, returns the objects in view.
SceneSource = Callable[[], Sequence[SceneObject]]

# Projector shadow rays stop this far (fraction of the projector-point distance)
# before the point, so a surface does not shadow itself.
_SHADOW_EPS = 1e-4


@dataclass(frozen=True)
class ScannerModel:
    """Intrinsics, range and noise of one scanner kind (SI units, pixels with _px)."""

    name: str
    kind: str  # "structured-light" | "time-of-flight"
    width_px: int
    height_px: int
    fx: float  # px
    fy: float  # px
    cx: float  # px
    cy: float  # px
    min_range: float  # m, along the optical axis
    max_range: float  # m
    sigma: float  # m, depth noise (1 sigma, along the ray) at sigma_range
    sigma_range: float  # m
    sigma_exponent: float  # growth of sigma with range
    max_incidence: float  # rad, no return beyond
    dropout_incidence: float  # rad, returns start to drop out beyond
    baseline: float = 0.0  # m, projector offset along +x (structured light); 0: no shadows
    metal_sigma_scale: float = 1.0
    metal_bias: float = 0.0  # m, added to the range on metal
    flying_jump: float = math.inf  # m, depth step that makes flying pixels
    flying_probability: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("structured-light", "time-of-flight"):
            raise InputError(f"scanner {self.name!r}: kind must be structured-light or time-of-flight, got {self.kind!r}")
        if self.width_px < 1 or self.height_px < 1 or self.fx <= 0 or self.fy <= 0:
            raise InputError(f"scanner {self.name!r}: expected a positive size and focal lengths")
        if not 0 < self.min_range < self.max_range:
            raise InputError(f"scanner {self.name!r}: expected 0 < min_range < max_range")
        if not 0 <= self.dropout_incidence <= self.max_incidence <= math.pi / 2:
            raise InputError(f"scanner {self.name!r}: expected 0 <= dropout_incidence <= max_incidence <= pi/2")
        if self.sigma < 0 or not 0 <= self.flying_probability <= 1:
            raise InputError(f"scanner {self.name!r}: sigma must be >= 0 and flying_probability in [0, 1]")

    def scaled(self, scale: float) -> ScannerModel:
        """The same scanner with its image scaled by ``scale`` (fewer, wider pixels)."""
        if not (math.isfinite(scale) and 0.01 <= scale <= 1.0):
            raise InputError(f"resolution_scale must be in [0.01, 1], got {scale!r}")
        if scale == 1.0:
            return self
        return replace(
            self,
            width_px=max(1, round(self.width_px * scale)),
            height_px=max(1, round(self.height_px * scale)),
            fx=self.fx * scale,
            fy=self.fy * scale,
            cx=(self.cx + 0.5) * scale - 0.5,
            cy=(self.cy + 0.5) * scale - 0.5,
        )


SCANNER_MODELS: dict[str, ScannerModel] = {
    "phoxi-m": ScannerModel(
        name="phoxi-m",
        kind="structured-light",
        width_px=2064,
        height_px=1544,
        fx=2270.0,  # 0.29 mm spacing at the 0.65 m sweet spot
        fy=2270.0,
        cx=1031.5,
        cy=771.5,
        min_range=0.458,
        max_range=1.118,
        sigma=0.0001,
        sigma_range=0.65,
        sigma_exponent=2.0,
        max_incidence=math.radians(80.0),  # plausible, not a datasheet value
        dropout_incidence=math.radians(65.0),
        baseline=0.350,
    ),
    "phoxi-s": ScannerModel(
        name="phoxi-s",
        kind="structured-light",
        width_px=2064,
        height_px=1544,
        fx=2760.0,  # 0.16 mm spacing at the 0.442 m sweet spot
        fy=2760.0,
        cx=1031.5,
        cy=771.5,
        min_range=0.384,
        max_range=0.520,
        sigma=0.00005,
        sigma_range=0.442,
        sigma_exponent=2.0,
        max_incidence=math.radians(80.0),
        dropout_incidence=math.radians(65.0),
        baseline=0.230,
    ),
    "azure-kinect": ScannerModel(
        name="azure-kinect",
        kind="time-of-flight",
        width_px=640,  # NFOV unbinned
        height_px=576,
        fx=504.0,
        fy=504.0,
        cx=319.5,
        cy=287.5,
        min_range=0.5,
        max_range=3.86,
        sigma=0.0015,  # typical on diffuse targets at 1 m; the spec bound is 17 mm
        sigma_range=1.0,
        sigma_exponent=1.0,
        max_incidence=math.radians(75.0),
        dropout_incidence=math.radians(55.0),
        metal_sigma_scale=2.0,
        metal_bias=0.008,  # cm-level, reads long on machined metal (users report 8-15 mm)
        flying_jump=0.01,
        flying_probability=0.5,
    ),
}


def scanner_model(name: str) -> ScannerModel:
    """Return the scanner model called ``name``, or raise InputError listing the known ones."""
    try:
        return SCANNER_MODELS[name]
    except KeyError:
        raise InputError(f"unknown scanner model {name!r}; known: {', '.join(SCANNER_MODELS)}") from None


class SimScanner:
    """A scanner fixed at ``T_base_cam`` that ray casts scenes.

    Parameters
    ----------
    model : ScannerModel or str
        The scanner, or a key of :data:`SCANNER_MODELS`.
    T_base_cam : numpy.ndarray
        (4, 4) pose of the camera (optical frame) in the base frame.
    seed : int
        Seed of the noise; captures are a deterministic sequence per seed.
    resolution_scale : float
        Image scale in (0, 1]; 0.25 gives a 516 x 386 PhoXi for fast tests.
    clock : callable
        Source of the capture stamps, ``time.monotonic_ns`` by default.
    roi_px : tuple of 4 int or None
        Region of interest ``(row0, row1, col0, col1)`` of the (scaled) image:
        only its pixels are cast, the rest of the full-size cloud is NaN, as
        on a scanner with an ROI set. None for the whole image.
    measure : callable or None
        The unit's measuring error: maps true points (n, 3) of the camera
        frame (m, float64) to where the unit measures them; None: exact.
    """

    def __init__(
        self,
        model: ScannerModel | str,
        T_base_cam: np.ndarray,
        seed: int = 0,
        resolution_scale: float = 1.0,
        clock: Callable[[], int] = time.monotonic_ns,
        roi_px: tuple[int, int, int, int] | None = None,
        measure: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        base = scanner_model(model) if isinstance(model, str) else model
        self.model = base.scaled(resolution_scale)
        self._measure = measure
        self.move_to(T_base_cam)
        self._rng = np.random.default_rng(seed)
        self._clock = clock
        m = self.model
        u = (np.arange(m.width_px, dtype=np.float32) - np.float32(m.cx)) / np.float32(m.fx)
        v = (np.arange(m.height_px, dtype=np.float32) - np.float32(m.cy)) / np.float32(m.fy)
        # Ray directions with unit z: a hit at parameter t has depth t.
        D = np.empty((m.height_px, m.width_px, 3), dtype=np.float32)
        D[..., 0] = u[None, :]
        D[..., 1] = v[:, None]
        D[..., 2] = 1.0
        self._all_dirs = D
        self._cast = np.ones((m.height_px, m.width_px), dtype=bool)
        if roi_px is not None:
            r0, r1, c0, c1 = (int(x) for x in roi_px)
            if not (0 <= r0 < r1 <= m.height_px and 0 <= c0 < c1 <= m.width_px):
                raise InputError(f"roi_px: expected 0 <= row0 < row1 <= {m.height_px}, 0 <= col0 < col1 <= {m.width_px}, got {roi_px}")
            self._cast[:] = False
            self._cast[r0:r1, c0:c1] = True
        self._dirs = D[self._cast]
        self._dir_norm = np.linalg.norm(self._dirs, axis=1)
        self._rays = o3d.core.Tensor(np.hstack([np.zeros_like(self._dirs), self._dirs]))

    def move_to(self, T_base_cam: np.ndarray) -> None:
        """Put the scanner at ``T_base_cam`` (4, 4) for the next captures (a scanner on the arm)."""
        self.T_base_cam = se3.check_transform(T_base_cam, "T_base_cam")
        self._T_cam_base = se3.invert(self.T_base_cam)

    def capture(self, objects: Sequence[SceneObject]) -> OrganizedCloud:
        """Ray cast ``objects`` and return the noisy organized cloud."""
        return self.capture_labelled(objects)[0]

    def capture_labelled(self, objects: Sequence[SceneObject]) -> tuple[OrganizedCloud, np.ndarray]:
        """:meth:`capture`, and the (H, W) int16 index into ``objects`` of what each pixel saw (-1: nothing).

        The labels are the simulator's truth, for tests and benchmarks; no
        real scanner gives them.
        """
        m = self.model
        scene = o3d.t.geometry.RaycastingScene()
        metal = []
        for obj in objects:
            if not isinstance(obj, SceneObject):
                raise InputError(f"capture: expected SceneObject values, got {type(obj).__name__}")
            V = se3.apply(self._T_cam_base @ obj.T_base_obj, np.asarray(obj.mesh.vertices))
            F = np.asarray(obj.mesh.triangles, dtype=np.uint32)
            scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F))
            metal.append(obj.material == "metal")
        stamp = self._clock()
        hit = scene.cast_rays(self._rays)
        t = hit["t_hit"].numpy()
        gid = hit["geometry_ids"].numpy().astype(np.int64)
        n_hit = len(objects)
        hit_mask = np.isfinite(t) & (gid < n_hit)
        labels = np.where(hit_mask, gid, -1).astype(np.int16)

        idx = np.flatnonzero(hit_mask & (t >= m.min_range) & (t <= m.max_range))
        d = self._dirs[idx]
        dn = self._dir_norm[idx]
        tt = t[idx]
        N = hit["primitive_normals"].numpy()[idx]
        cos_cam = np.abs(np.einsum("ij,ij->i", N, d)) / dn
        keep = self._incidence_keep(cos_cam)
        if m.baseline > 0.0:
            keep &= self._projector_keep(scene, tt[:, None] * d, N)
        idx, d, dn, tt = idx[keep], d[keep], dn[keep], tt[keep]
        on_metal = np.asarray(metal, dtype=bool)[gid[idx]]

        # Range noise (and bias) along the ray; t is depth, so divide by |d|.
        rng_ = tt * dn
        sigma = m.sigma * (rng_ / m.sigma_range) ** m.sigma_exponent
        sigma = np.where(on_metal, sigma * m.metal_sigma_scale, sigma)
        dr = sigma * self._rng.standard_normal(len(idx), dtype=np.float32)
        if m.metal_bias:
            dr = dr + np.where(on_metal, np.float32(m.metal_bias), np.float32(0.0))
        cast = np.full(len(self._dirs), np.nan, dtype=np.float32)
        cast[idx] = tt + dr / dn
        depth = np.full((m.height_px, m.width_px), np.nan, dtype=np.float32)
        depth[self._cast] = cast
        if m.flying_probability > 0.0:
            depth = self._flying_pixels(depth)
        label_img = np.full((m.height_px, m.width_px), -1, dtype=np.int16)
        label_img[self._cast] = labels
        points = depth[..., None] * self._all_dirs
        if self._measure is not None:
            ok = np.isfinite(depth)
            points[ok] = self._measure(points[ok].astype(np.float64)).astype(np.float32)
        return OrganizedCloud(points=points, stamp_ns=int(stamp)), label_img

    def _incidence_keep(self, cos_inc: np.ndarray) -> np.ndarray:
        """Grazing-angle returns: lost beyond max_incidence, thinned beyond dropout_incidence."""
        m = self.model
        inc = np.arccos(np.clip(cos_inc, 0.0, 1.0))
        span = max(m.max_incidence - m.dropout_incidence, 1e-9)
        p_drop = np.clip((inc - m.dropout_incidence) / span, 0.0, 1.0)
        return (inc <= m.max_incidence) & (self._rng.random(len(inc)) >= p_drop)

    def _projector_keep(self, scene: o3d.t.geometry.RaycastingScene, P: np.ndarray, N: np.ndarray) -> np.ndarray:
        """Structured light: points the projector lights, at an angle it can be decoded."""
        origin = np.array([self.model.baseline, 0.0, 0.0], dtype=np.float32)
        to_point = P - origin
        rays = np.empty((len(P), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = to_point
        shadowed = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0 - _SHADOW_EPS).numpy().astype(bool)
        cos_proj = np.abs(np.einsum("ij,ij->i", N, to_point)) / np.linalg.norm(to_point, axis=1)
        return ~shadowed & self._incidence_keep(cos_proj)

    def _flying_pixels(self, depth: np.ndarray) -> np.ndarray:
        """Time of flight: mix depths across steps larger than flying_jump."""
        m = self.model
        padded = np.pad(depth, 1, constant_values=np.nan)
        H, W = depth.shape
        neighbours = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])  # up, down, left, right
        step = np.abs(neighbours - depth[None])
        step = np.where(np.isfinite(step), step, -1.0)
        which = np.argmax(step, axis=0)
        biggest = np.take_along_axis(step, which[None], axis=0)[0]
        fly = (biggest > m.flying_jump) & (self._rng.random((H, W)) < m.flying_probability)
        other = np.take_along_axis(neighbours, which[None], axis=0)[0]
        mix = self._rng.random((H, W), dtype=np.float32)
        out = depth.copy()
        out[fly] = depth[fly] + mix[fly] * (other[fly] - depth[fly])
        return out


# -- the simulated cell's scanner device ---------------------------------------------


def robot_scene_source(
    T_base_flange: Callable[[], np.ndarray],
    flange: FlangeModel,
    table: bool = True,
    clutter_seed: int | None = None,
    extra: Callable[[], Sequence[SceneObject]] | None = None,
    tool: ToolConfig | None = None,
    p_flange_torch: np.ndarray | None = None,
) -> SceneSource:
    """A scene source of the calibration scene at the robot's current pose.

    Parameters
    ----------
    T_base_flange : callable
        Returns the (4, 4) flange pose in the base frame now (in the simulated
        cell: the simulated controller's truth).
    flange : FlangeModel
        The flange on the wrist.
    table, clutter_seed
        As :func:`celld.sim.scene.robot_scene`.
    extra : callable, optional
        Returns more objects (a workpiece) to add to each capture.
    tool : ToolConfig, optional
        The welding tool as built on the flange (flange frame), drawn at each capture.
    p_flange_torch : (3,) array, optional
        The torch's wire end as built (flange frame): the torch is drawn too.
    """

    def scene() -> list[SceneObject]:
        T = se3.check_transform(T_base_flange(), "T_base_flange")
        objects = list(robot_scene(T, flange, table=table, clutter_seed=clutter_seed, tool=tool, p_flange_torch=p_flange_torch))
        if extra is not None:
            objects.extend(extra())
        return objects

    return scene


class SimulatedScanner:
    """A :class:`SimScanner` fixed at ``T_base_cam`` that captures a scene source (the Scanner protocol).

    Parameters
    ----------
    model : str or ScannerModel
        Scanner model of :data:`SCANNER_MODELS` (``"phoxi-m"``, ...), or one
        changed from it (the world's unit: its own metal bias).
    T_base_cam : array_like or callable
        (4, 4) true pose of the camera in the base frame (the simulator's
        truth), or a callable that returns it at the exposure (a scanner on
        the arm moves with it).
    scene : callable
        Returns the scene objects in view at capture time.
    seed : int
        Noise seed; captures are a deterministic sequence per seed and scene.
    resolution_scale : float
        Image scale in [0.01, 1].
    on_close : callable, optional
        Releases what the scene source holds (the truth reader), at :meth:`close`.
    measure : callable, optional
        The unit's measuring error (see :class:`SimScanner`).
    capture_delay : (float, float)
        The exposure happens this long (s, uniform in the range, seeded) after
        the capture is asked for: the scene is what is in view then, not when
        the caller last read the robot's state.
    roi_px : tuple of 4 int or None
        Region of interest ``(row0, row1, col0, col1)`` of the (scaled) image,
        as :class:`SimScanner`'s: only it is cast. None for the whole image.
    """

    def __init__(
        self,
        model: str | ScannerModel,
        T_base_cam: np.ndarray | Callable[[], np.ndarray],
        scene: SceneSource,
        seed: int = 0,
        resolution_scale: float = 1.0,
        clock: Callable[[], int] = time.monotonic_ns,
        on_close: Callable[[], None] | None = None,
        measure: Callable[[np.ndarray], np.ndarray] | None = None,
        capture_delay: tuple[float, float] = (0.0, 0.0),
        roi_px: tuple[int, int, int, int] | None = None,
    ) -> None:
        if not callable(scene):
            raise InputError(f"simulated scanner: expected a callable scene source, got {type(scene).__name__}")
        lo, hi = capture_delay
        if not 0.0 <= lo <= hi <= 10.0:
            raise InputError(f"simulated scanner: capture_delay must be 0 <= lo <= hi <= 10 s, got {capture_delay}")
        self.model_name = model if isinstance(model, str) else model.name
        self._scene = scene
        self._pose = T_base_cam if callable(T_base_cam) else None
        T0 = np.eye(4) if callable(T_base_cam) else np.asarray(T_base_cam, dtype=np.float64)  # a moving one is placed at each capture
        self._sim = SimScanner(model, T0, seed=seed, resolution_scale=resolution_scale, clock=clock, roi_px=roi_px, measure=measure)
        self._delay = (float(lo), float(hi))
        self._delay_rng = np.random.default_rng([seed, 0xDE1A])
        self._seed = seed
        self._lock = threading.Lock()
        self._stats = CaptureStats()
        self._open = True
        self._on_close = on_close

    def capture(self) -> OrganizedCloud:
        """Ray cast the scene as it is now."""
        with self._lock:
            if not self._open:
                raise DeviceError("simulated scanner: capture after close")
            started = time.monotonic_ns()
            if self._delay[1] > 0.0:
                time.sleep(self._delay_rng.uniform(*self._delay))
            try:
                if self._pose is not None:
                    self._sim.move_to(self._pose())
                cloud = self._sim.capture(self._scene())
            except InputError as exc:
                self._stats.failure(exc)
                raise
            self._stats.success(cloud.stamp_ns, started)
            return cloud

    def info(self) -> dict[str, Any]:
        m = self._sim.model
        return {
            "kind": "sim",
            "model": self.model_name,
            "device": "simulated",
            "width_px": m.width_px,
            "height_px": m.height_px,
            "intrinsics_px": (m.fx, m.fy, m.cx, m.cy),
            "range": (m.min_range, m.max_range),
            "seed": self._seed,
        }

    def health(self) -> dict[str, Any]:
        return self._stats.as_dict(self._open)

    def close(self) -> None:
        with self._lock:
            if self._open and self._on_close is not None:
                self._on_close()
            self._open = False
