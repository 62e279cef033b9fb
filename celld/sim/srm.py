"""Simulated SRM finger: contact with the seam wall and the in-finger camera image.

Three parts, each usable alone:

- :func:`finger_contact` (pure): the finger tip against the wall of a
  simulated seam. The wall is a polyline in the welding plane; the tip is a
  sphere of ``tip_radius`` whose undeformed centre is the tool origin P_r. A
  tip that would enter the wall is pushed back onto it (normal stiffness; the
  finger bottoms out at ``max_deformation``) and dragged back along the wall by
  friction (``friction * k_normal / k_tangential`` of the normal deflection).
  A :class:`WallSurface` is the wall at several heights above the seam's root
  (a V-groove's bevel leans: the higher, the farther); the finger meets it at
  the height where its tip is. :class:`Finger` adds what a real soft finger
  does over time: a stiffness that grows with the deflection, stick-slip
  (static friction above kinetic) and hysteresis between the tip and the tag
  (the tag follows the tip through a play), all off by default. The tag sits
  inside the finger, short of its tip: :func:`tag_of_tip` moves it less than
  the tip, per in-plane axis, and less still as the finger bends (world
  source ``tag_map``), a relation of the world's own that the controller
  measures by touch (:mod:`celld.tactile.fingermap`), never reads.
- :class:`TagRenderer`: renders the ArUco tag at a pose in the camera frame as
  an 8-bit grey image with perspective, lens blur, sensor noise and lighting
  changes. The tag is rendered supersampled in a window around it, then
  area-averaged, so edges land at sub-pixel positions.
- :class:`SimSrmCamera`: a frame source (same protocol as the real camera in
  :mod:`celld.tactile.camera`) driven by the true TCP pose at each frame's
  capture time; it also keeps the true deformation of each frame, which the
  benchmark compares the estimate against (the estimator never sees it).
- :class:`SimSrmSource`: the picklable frame-source factory that the
  simulated cell hands to the tactile process: it builds the camera there,
  driven by the simulated controller's truth, and optionally shares each
  frame's truth through a slot (:data:`SRM_TRUTH_DTYPE`) for benchmarks.

In the simulated cell the camera is the world's (:class:`SrmCamera`,
source ``srm_camera``): its intrinsics, its mount in the tool and the tag's
printed size drawn apart from what ``[tactile]`` tells the controller. The
simulated lens is a pinhole without distortion (not drawn); the detector still
applies the configured distortion coefficients, which are zero for the
simulated cell.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from celld import polyline
from celld.config import TactileConfig, ToolConfig
from celld.errors import InputError
from celld.se3 import invert, transform_from
from celld.shm import SeqlockSlot

if TYPE_CHECKING:
    from celld.config.reader import TableReader

Array = np.ndarray

# Pixels per tag cell in the texture; the tag spans about 20 px per cell on
# the default camera, so the texture is sampled below its resolution.
_TEXTURE_PX_PER_CELL = 40
# Supersampling of the rendered window. Measured read-back error of tag
# displacements: 3 gives 4-7 um RMS, 4 and 8 give 4-6 um (the rest is the
# detector's); 3 renders in 60 % of the time of 4.
_SUPERSAMPLE = 3
# White margin around the tag's black square, in cells (the tag's quiet zone).
_QUIET_CELLS = 1
# Grey levels of the tag's ink and paper under nominal light (paper is not a
# perfect white: a brighter light does not clip it at once).
_INK, _PAPER = 20.0, 205.0
# Pre-drawn sensor-noise frames, cropped at random offsets per frame.
_NOISE_BANK = 8
_NOISE_PAD = 32


# -- contact model -------------------------------------------------------------


@dataclass(frozen=True)
class ContactParams:
    """Mechanics of the finger against the wall (SI units).

    ``k_normal`` and ``k_tangential`` are the finger's stiffness (N/m); only
    their ratio matters to the quasi-static deflection, the normal one also
    gives the contact force.
    """

    k_normal: float = 400.0  # N/m
    k_tangential: float = 400.0  # N/m
    friction: float = 0.3  # Coulomb coefficient tip/wall (kinetic)
    max_deformation: float = 0.005  # m, the finger bottoms out here
    slip_speed: float = 0.0005  # m/s, speed over which the friction force builds up
    finger_length: float = 0.04  # m, bending length: the tag tilts by 1.5 * deflection / length
    # Normal force k d (1 + (d / stiffening)^2): the finger stiffens as it bends (inf: linear), m.
    stiffening: float = math.inf
    # Static over kinetic friction: above 1 the tip sticks to the wall until the
    # drag reaches the static limit, then slips back to the kinetic drag (:class:`Finger`).
    static_friction_ratio: float = 1.0
    # Width of the play between the tip's deflection and the tag's (:class:`Finger`), m.
    hysteresis: float = 0.0
    # The tag inside the finger: its in-plane shift over the tip's along the tool's x and y, and the deflection
    # at which it falls behind by a further (d / s)^2 (:func:`tag_of_tip`; inf: not at all).
    tag_gain: tuple[float, float] = (1.0, 1.0)
    tag_softening: float = math.inf  # m

    def force(self, normal: float) -> float:
        """The normal force (N) at a normal deflection (m)."""
        return self.k_normal * normal * (1.0 + (normal / self.stiffening) ** 2)


class Wall(NamedTuple):
    """A seam wall: a polyline in the welding plane and the side it faces.

    ``P`` (n, 2) are points of the wall line (plane coordinates, m); ``free``
    is +1 when the free side (where the tip is) is left of the direction of
    the points, -1 when right.
    """

    P: Array
    free: float


class FingerContact(NamedTuple):
    """The finger's state against the wall.

    ``tip_shift_plane`` (2,) is the deformed tip centre minus the undeformed one
    (m, plane coordinates, P_s - P_r); ``force`` the normal force (N);
    ``in_contact`` whether the tip touches the wall; ``bottomed`` whether the
    finger reached its maximum deformation.
    """

    tip_shift_plane: Array
    force: float
    in_contact: bool
    bottomed: bool


def finger_contact(p_rest: Array, v_rest: Array, wall: Wall, tip_radius: float, params: ContactParams) -> FingerContact:
    """Deflection of the finger tip against the wall.

    Parameters
    ----------
    p_rest : (2,)
        Undeformed tip centre P_r in plane coordinates, m.
    v_rest : (2,)
        Its velocity in the plane, m/s (sets the direction of friction).
    wall : Wall
    tip_radius : float
        m.
    params : ContactParams

    Returns
    -------
    FingerContact
        No contact beyond the ends of the wall: the wall stops there.
    """
    i, u, _ = polyline.nearest(wall.P, p_rest)
    if not polyline.is_inside(wall.P, i, u):
        return FingerContact(np.zeros(2), 0.0, False, False)
    X = wall.P[i] + u * (wall.P[i + 1] - wall.P[i])
    t = (wall.P[i + 1] - wall.P[i]) / np.linalg.norm(wall.P[i + 1] - wall.P[i])
    n_free = wall.free * np.array([-t[1], t[0]])
    clearance = float(np.dot(p_rest - X, n_free))
    penetration = tip_radius - clearance
    if penetration <= 0.0:
        return FingerContact(np.zeros(2), 0.0, False, False)
    normal = min(penetration, params.max_deformation)
    force = params.force(normal)
    # Friction drags the tip back against its sliding direction along the wall.
    v_slide = float(np.dot(v_rest, t))
    drag = params.friction * force / params.k_tangential * math.tanh(v_slide / params.slip_speed)
    shift = normal * n_free - drag * t
    return FingerContact(shift, force, True, penetration >= params.max_deformation)


class WallSurface(NamedTuple):
    """A seam wall at several heights: what a finger meets depends on where its tip is.

    ``lines`` (k, n, 2) are the wall's polyline at each of the ``heights``
    (k,) above the seam's root (m, increasing), in plane coordinates;
    ``root_z`` (n,) the root's height in the plane at each station; ``free``
    as :attr:`Wall.free`. A tip below the lowest line or above the highest
    meets the nearest line (the simulator does not model the root face or a
    tip riding above the plate).
    """

    lines: Array
    heights: Array
    root_z: Array
    free: float

    def at(self, p_plane: Array) -> Wall:
        """The wall line at the height of the plane point ``p_plane`` (3,) above the root beside it."""
        L, hs = self.lines, self.heights
        mid = L[len(hs) // 2]
        i, u, _ = polyline.nearest(mid, p_plane[:2])
        j = min(i + 1, len(self.root_z) - 1)
        h = float(p_plane[2]) - ((1.0 - u) * self.root_z[i] + u * self.root_z[j])
        if h <= hs[0]:
            return Wall(L[0], self.free)
        if h >= hs[-1]:
            return Wall(L[-1], self.free)
        k = int(np.searchsorted(hs, h))
        w = (h - hs[k - 1]) / (hs[k] - hs[k - 1])
        return Wall((1.0 - w) * L[k - 1] + w * L[k], self.free)


class Finger:
    """A finger with a memory: stick-slip along the wall and hysteresis of the tag.

    :meth:`touch` returns the contact and the tag's shift in the plane (the
    tip's shift seen through the play of width ``hysteresis``). With the
    default :class:`ContactParams` it is :func:`finger_contact` exactly and the
    tag follows the tip.

    Stick-slip (``static_friction_ratio > 1``): once in contact the tip sticks
    to the wall while the finger's base slides on, the drag growing with the
    travel, until it passes the static limit and slips back to the kinetic
    drag (quasi-static, one step per frame).
    """

    def __init__(self, params: ContactParams) -> None:
        self.params = params
        self._drag = 0.0  # m, the tip's lag along the wall's direction while in contact
        self._s_prev: float | None = None  # the undeformed tip's position along the wall at the last frame
        self._tag = np.zeros(2)  # the play's output

    def touch(self, p_rest: Array, v_rest: Array, wall: Wall, tip_radius: float) -> tuple[FingerContact, Array]:
        p = self.params
        c = finger_contact(p_rest, v_rest, wall, tip_radius, p)
        if p.static_friction_ratio > 1.0:
            c = self._stick_slip(c, p_rest, v_rest, wall)
        if p.hysteresis > 0.0:
            half = p.hysteresis / 2.0
            self._tag = np.asarray(np.clip(self._tag, c.tip_shift_plane - half, c.tip_shift_plane + half), dtype=np.float64).reshape(-1)
            return c, self._tag.copy()
        return c, c.tip_shift_plane

    def _stick_slip(self, c: FingerContact, p_rest: Array, v_rest: Array, wall: Wall) -> FingerContact:
        if not c.in_contact:
            self._drag, self._s_prev = 0.0, None
            return c
        p = self.params
        i, _, _ = polyline.nearest(wall.P, p_rest)
        t = (wall.P[i + 1] - wall.P[i]) / np.linalg.norm(wall.P[i + 1] - wall.P[i])
        s = float(np.dot(p_rest, t))
        n_free = wall.free * np.array([-t[1], t[0]])
        normal = float(np.dot(c.tip_shift_plane, n_free))
        kinetic = p.friction * c.force / p.k_tangential
        if self._s_prev is None:
            # First touch: the drag builds up from the kinetic drag of the motion so far.
            self._drag = kinetic * math.tanh(float(np.dot(v_rest, t)) / p.slip_speed)
        else:
            self._drag += s - self._s_prev  # stuck: the tip stays, the base moves on
            if abs(self._drag) > p.static_friction_ratio * kinetic:
                self._drag = math.copysign(kinetic, self._drag)  # slip back to the kinetic drag
        self._s_prev = s
        return c._replace(tip_shift_plane=normal * n_free - self._drag * t)


def tag_of_tip(shift_tool: Array, params: ContactParams) -> Array:
    """The tag's shift in the tool frame (3,) for the tip's (after the play): the in-plane part scaled per axis by
    ``tag_gain`` and by ``1 - (d / tag_softening)^2`` at the in-plane deflection ``d``; along the finger as is."""
    shift = np.array(shift_tool, dtype=np.float64)
    d = math.hypot(float(shift[0]), float(shift[1]))
    shift[:2] *= np.asarray(params.tag_gain, dtype=np.float64) * (1.0 - (d / params.tag_softening) ** 2)
    return shift


def tip_of_tag(tag: float, gain: float, softening: float) -> float:
    """The tip's deflection (m) at which the tag shows ``tag`` (m) along one axis of :func:`tag_of_tip` (``gain`` and
    ``softening`` that axis's): its inverse, by fixed-point iteration (the softening is a few % at most)."""
    tip = tag / gain
    for _ in range(50):
        tip = tag / (gain * (1.0 - (tip / softening) ** 2))
    return tip


def tag_pose_tool(tip_shift_tool: Array, finger_length: float) -> Array:
    """Pose of the tag in the tool frame for a tip shift (3,), (4, 4).

    The tag sits at the tip facing the camera (its z along the tool z); the
    finger bends as a cantilever, so the tag tilts by 1.5 * shift / length.
    """
    shift = np.asarray(tip_shift_tool, dtype=np.float64)
    tilt = -1.5 / finger_length * np.cross([0.0, 0.0, 1.0], shift)
    return transform_from(Rotation.from_rotvec(tilt).as_matrix(), shift)


# -- image rendering -------------------------------------------------------------


@dataclass(frozen=True)
class Imaging:
    """Image conditions of one frame.

    ``blur`` is the sigma of the lens blur in pixels; ``gain`` and ``offset``
    map the scene's grey levels (0-255) to the sensor's; ``gradient`` is the
    relative brightness change across the frame along ``gradient_angle``
    (rad); ``noise`` the sensor noise sigma in grey levels.
    """

    blur: float = 0.8
    gain: float = 1.0
    offset: float = 0.0
    gradient: float = 0.0
    gradient_angle: float = 0.0
    noise: float = 2.0


class TagRenderer:
    """Renders one ArUco tag seen by a pinhole camera.

    Parameters
    ----------
    dictionary : str
        OpenCV name, e.g. ``"DICT_4X4_50"``.
    tag_id : int
        The id drawn (tests draw a wrong one on purpose).
    tag_size : float
        Side of the black square, m.
    intrinsics_px : (fx, fy, cx, cy)
    size_px : (width, height)
    seed : int
        Seeds the background texture and the sensor noise.
    """

    def __init__(
        self,
        dictionary: str,
        tag_id: int,
        tag_size: float,
        intrinsics_px: tuple[float, float, float, float],
        size_px: tuple[int, int],
        seed: int = 0,
    ) -> None:
        try:
            aruco_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
            marker = cv2.aruco.generateImageMarker(aruco_dict, tag_id, (aruco_dict.markerSize + 2) * _TEXTURE_PX_PER_CELL)
        except (AttributeError, cv2.error) as exc:
            raise InputError(f"tag renderer: cannot draw id {tag_id} of {dictionary!r}: {exc}") from exc
        cells = aruco_dict.markerSize + 2
        q = _QUIET_CELLS * _TEXTURE_PX_PER_CELL
        texture = np.full((marker.shape[0] + 2 * q,) * 2, 255, np.uint8)
        texture[q:-q, q:-q] = marker
        # 8-bit: warping it is twice as fast as float, and 16 samples per pixel average the steps out.
        self._texture = np.round(_INK + (_PAPER - _INK) / 255.0 * texture).astype(np.uint8)
        # Side of the textured square (tag plus quiet zone) in metres.
        self._side = tag_size * (cells + 2 * _QUIET_CELLS) / cells
        fx, fy, cx, cy = intrinsics_px
        self._K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        self._w, self._h = size_px
        rng = np.random.default_rng(seed)
        # The inside of the finger: dark, softly textured.
        bg: np.ndarray = rng.normal(0.0, 1.0, (self._h // 8 + 1, self._w // 8 + 1)).astype(np.float32)
        bg = cv2.resize(cv2.GaussianBlur(bg, (0, 0), 1.5), (self._w, self._h), interpolation=cv2.INTER_CUBIC)
        self._background: np.ndarray = np.clip(55.0 + 25.0 * bg, 0, 255).astype(np.float32)
        self._noise = rng.standard_normal((_NOISE_BANK, self._h + _NOISE_PAD, self._w + _NOISE_PAD), dtype=np.float32)
        self._rng = rng
        yy, xx = np.mgrid[0 : self._h, 0 : self._w].astype(np.float32)
        self._xn = (xx - self._w / 2) / self._w
        self._yn = (yy - self._h / 2) / self._h

    @property
    def K(self) -> Array:
        return self._K.copy()

    def _project(self, T_cam_tag: Array, P_tag: Array) -> Array:
        P_cam = P_tag @ T_cam_tag[:3, :3].T + T_cam_tag[:3, 3]
        uvw = P_cam @ self._K.T
        return uvw[:, :2] / uvw[:, 2:3]

    def render(self, T_cam_tag: Array | None, imaging: Imaging = Imaging()) -> Array:
        """Return the (height, width) uint8 image of the tag at ``T_cam_tag``.

        ``None`` renders the finger without a tag (an occluded or lost tag).
        """
        img = self._background.copy()
        window = self._draw_tag(img, np.asarray(T_cam_tag, dtype=np.float64)) if T_cam_tag is not None else None
        if imaging.gradient != 0.0:
            g = imaging.gradient
            light = cv2.addWeighted(self._xn, g * math.cos(imaging.gradient_angle), self._yn, g * math.sin(imaging.gradient_angle), 1.0)
            cv2.multiply(img, light, dst=img)
        if imaging.blur > 0.0 and window is not None:
            # The background is smooth already: only the tag's window needs the lens blur.
            m = int(math.ceil(3.0 * imaging.blur)) + 1
            y0, y1, x0, x1 = window
            ys = slice(max(y0 - m, 0), min(y1 + m, self._h))
            xs = slice(max(x0 - m, 0), min(x1 + m, self._w))
            img[ys, xs] = cv2.GaussianBlur(img[ys, xs], (0, 0), imaging.blur)
        if imaging.noise > 0.0:
            k = int(self._rng.integers(_NOISE_BANK))
            dy, dx = (int(v) for v in self._rng.integers(_NOISE_PAD, size=2))
            cv2.scaleAdd(self._noise[k, dy : dy + self._h, dx : dx + self._w], imaging.noise, img, dst=img)
        return cv2.convertScaleAbs(img, alpha=imaging.gain, beta=imaging.offset)

    def _draw_tag(self, img: Array, T_cam_tag: Array) -> tuple[int, int, int, int] | None:
        """Draw the tag into ``img``; returns its window (y0, y1, x0, x1) or None when out of view."""
        if T_cam_tag[2, 3] <= 0.0:
            return None
        n = self._texture.shape[0]
        s = self._side
        # Texture pixel i covers [i - 0.5, i + 0.5]; its outer edges map to the square's edges.
        uv = np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]])
        P = np.column_stack([(uv[:, 0] + 0.5) / n * s - s / 2, s / 2 - (uv[:, 1] + 0.5) / n * s, np.zeros(4)])
        img_pts = self._project(T_cam_tag, P)
        x0 = max(int(math.floor(img_pts[:, 0].min())) - 2, 0)
        y0 = max(int(math.floor(img_pts[:, 1].min())) - 2, 0)
        x1 = min(int(math.ceil(img_pts[:, 0].max())) + 3, self._w)
        y1 = min(int(math.ceil(img_pts[:, 1].max())) + 3, self._h)
        if x1 <= x0 or y1 <= y0:
            return None
        ss = _SUPERSAMPLE
        roi = img[y0:y1, x0:x1]
        hi = cv2.resize(roi, ((x1 - x0) * ss, (y1 - y0) * ss), interpolation=cv2.INTER_LINEAR).astype(np.uint8)
        # Low-res pixel u (centre at u) covers hi-res [ss*(u - x0), ss*(u - x0 + 1)).
        dst = ss * (img_pts - [x0, y0] + 0.5) - 0.5
        H = cv2.getPerspectiveTransform(uv.astype(np.float32), dst.astype(np.float32))
        cv2.warpPerspective(
            self._texture,
            H,
            (hi.shape[1], hi.shape[0]),
            dst=hi,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_TRANSPARENT,
        )
        roi[:] = cv2.resize(hi.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
        return y0, y1, x0, x1


# -- the finger and its camera on a seam -------------------------------------------


@dataclass(frozen=True)
class SrmSimParams:
    """Everything the simulated finger camera does besides the tool geometry.

    ``lighting_swing`` is the amplitude of a slow change of the light's gain
    (period ``lighting_period``, s) and of a brightness gradient across the
    frame that turns with the same period.
    """

    contact: ContactParams = field(default_factory=ContactParams)
    blur: float = 0.8  # px, lens blur sigma
    noise: float = 2.0  # grey levels
    lighting_swing: float = 0.15
    lighting_period: float = 3.0  # s
    fps: float = 60.0
    latency: float = 0.002  # s from the end of exposure to the frame's delivery
    seed: int = 0
    # Timing errors: the exposure is off its stamp by this (1 sigma), and a
    # frame arrives up to this much later than ``latency`` (uniform), s.
    stamp_sigma: float = 0.0
    delivery_jitter: float = 0.0


class SrmFrame(NamedTuple):
    """One simulated frame with its truth (the truth is for benchmarks only)."""

    stamp_ns: int  # capture time
    image: Array  # (h, w) uint8
    delta_true: Array  # (3,) Eq. 15 delta in the tool frame, m
    in_contact: bool
    bottomed: bool


@dataclass(frozen=True)
class SrmCamera:
    """The SRM camera and the tag it watches (SI, pixels): as drawn in ``[sim.srm]``, or as built.

    ``T_tool_cam`` is the camera's mount in the tool frame; None: as the
    welding tool's drawing puts it (``[sim.tool] T_tool_cam``).
    """

    intrinsics_px: tuple[float, float, float, float] = (600.0, 600.0, 320.0, 240.0)  # fx, fy, cx, cy
    size_px: tuple[int, int] = (640, 480)
    tag_dictionary: str = "DICT_4X4_50"
    tag_id: int = 7
    tag_size: float = 0.008  # m, the side of the tag's black square
    T_tool_cam: tuple[tuple[float, ...], ...] | None = None

    @classmethod
    def read(cls, r: TableReader) -> SrmCamera:
        """The camera as drawn, from the ``[sim.srm]`` table's reader ``r``."""
        fx, fy, cx, cy = r.vector("intrinsics_px", 4, list(cls.intrinsics_px))
        w = r.int("width_px", cls.size_px[0], lo=16, hi=8192)
        h = r.int("height_px", cls.size_px[1], lo=16, hi=8192)
        if not (fx > 0.0 and fy > 0.0 and 0.0 <= cx <= w and 0.0 <= cy <= h):
            raise r.error(
                "intrinsics_px", f"expected fx, fy > 0 and the principal point inside the {w} x {h} image, got {[fx, fy, cx, cy]}"
            )
        return cls(
            intrinsics_px=(fx, fy, cx, cy),
            size_px=(w, h),
            tag_dictionary=r.str("tag_dictionary", cls.tag_dictionary),
            tag_id=r.int("tag_id", cls.tag_id, lo=0, hi=999),
            tag_size=r.float("tag_size_mm", cls.tag_size * 1e3, lo=0.5, hi=200.0, scale=1e-3),
        )


class SimSrm:
    """The finger on one seam wall, seen by its camera (pure apart from the noise generator).

    Parameters
    ----------
    cfg : TactileConfig
        Camera and tag.
    tool : ToolConfig
        The tool's geometry (tip, tip radius, the camera's mount) in the frame
        of the poses it is given (the TCP, or the flange with the simulated
        cell's true tool).
    wall : Wall or WallSurface
        The true seam wall in the plane of ``T_base_plane`` (a surface: at the
        tip's height).
    T_base_plane : (4, 4)
        The welding plane (z along the finger, away from the work).
    params : SrmSimParams
    far_wall : WallSurface, optional
        The joint's other wall: the tip meets it when moved across the joint
        (a probe of the joint's width), else only ``wall``.
    camera : SrmCamera, optional
        The camera as built and the tag as printed (the simulated cell's
        world, :class:`SrmCamera`); None: as ``cfg`` and
        ``tool`` say (a camera exactly as the controller was told).
    """

    def __init__(
        self,
        cfg: TactileConfig,
        tool: ToolConfig,
        wall: Wall | WallSurface,
        T_base_plane: Array,
        params: SrmSimParams = SrmSimParams(),
        far_wall: WallSurface | None = None,
        camera: SrmCamera | None = None,
    ) -> None:
        from celld.tactile.tool import ToolGeometry

        self.cfg = cfg
        self.wall = wall
        self.far_wall = far_wall
        self.tool = ToolGeometry.from_config(tool)
        self.T_base_plane = np.asarray(T_base_plane, dtype=np.float64)
        self.params = params
        self.finger = Finger(params.contact)
        if camera is None:  # the camera exactly as the controller was told
            camera = SrmCamera(cfg.intrinsics_px, (cfg.width_px, cfg.height_px), cfg.tag_dictionary, cfg.tag_id, cfg.tag_size)
        T_tool_cam = self.tool.T_tool_cam if camera.T_tool_cam is None else np.asarray(camera.T_tool_cam, dtype=np.float64)
        dictionary, tag_id, tag_size, K, size = camera.tag_dictionary, camera.tag_id, camera.tag_size, camera.intrinsics_px, camera.size_px
        self._T_cam_tool = invert(T_tool_cam)
        self.renderer = TagRenderer(dictionary, tag_id, tag_size, K, size, params.seed)
        self._foreign = TagRenderer(dictionary, (tag_id + 10) % 50, tag_size, K, size, params.seed + 1)
        # Fault injection: "" | "wrong_id" | "no_tag" | "blur".
        self.fault = ""

    def contact(self, T_base_tcp: Array, v_base_tip: Array) -> tuple[FingerContact, Array, Array]:
        """The finger's contact, the tip's shift and the tag's shift in the tool frame (3,) each, for a pose and tip velocity."""
        R_bp, o_bp = self.T_base_plane[:3, :3], self.T_base_plane[:3, 3]
        T_bt = np.asarray(T_base_tcp, dtype=np.float64) @ self.tool.T_tcp_tool
        p_plane = (T_bt[:3, 3] - o_bp) @ R_bp
        v_rest = np.asarray(v_base_tip, dtype=np.float64) @ R_bp[:, :2]
        wall = self.wall.at(p_plane) if isinstance(self.wall, WallSurface) else self.wall
        r, contact = self.tool.tip_radius, self.params.contact
        if self.far_wall is not None and not finger_contact(p_plane[:2], v_rest, wall, r, contact).in_contact:
            far = self.far_wall.at(p_plane)
            if finger_contact(p_plane[:2], v_rest, far, r, contact).in_contact:
                wall = far
        c, tag_plane = self.finger.touch(p_plane[:2], v_rest, wall, r)
        R_tb = T_bt[:3, :3].T
        return c, R_tb @ (R_bp[:, :2] @ c.tip_shift_plane), tag_of_tip(R_tb @ (R_bp[:, :2] @ tag_plane), contact)

    def imaging(self, t: float) -> Imaging:
        """The image conditions at time ``t`` (s): a slow change of the light."""
        p = self.params
        phase = 2.0 * math.pi * t / p.lighting_period
        blur = 6.0 if self.fault == "blur" else p.blur
        return Imaging(
            blur=blur,
            gain=1.0 + p.lighting_swing * math.sin(phase),
            offset=0.0,
            gradient=p.lighting_swing * 1.5,
            gradient_angle=phase,
            noise=p.noise,
        )

    def frame(self, stamp_ns: int, T_base_tcp: Array, v_base_tip: Array, t: float) -> SrmFrame:
        """Render the frame captured at ``stamp_ns`` for the TCP pose and tip velocity of that instant."""
        c, shift_tool, tag_tool = self.contact(T_base_tcp, v_base_tip)
        return SrmFrame(stamp_ns, self.image(tag_tool, self.imaging(t)), -shift_tool, c.in_contact, c.bottomed)

    def image(self, tag_tool: Array, imaging: Imaging) -> Array:
        """The camera's image with the tag shifted by ``tag_tool`` (3,) in the tool frame (the finger bent so)."""
        T_cam_tag = self._T_cam_tool @ tag_pose_tool(tag_tool, self.params.contact.finger_length)
        if self.fault == "no_tag":
            return self.renderer.render(None, imaging)
        if self.fault == "wrong_id":
            return self._foreign.render(T_cam_tag, imaging)
        return self.renderer.render(T_cam_tag, imaging)


PoseAt = Callable[[int], tuple[Array, Array]]
"""``pose_at(stamp_ns) -> (T_base_tcp (4, 4), v_base_tcp (6,))``: the true TCP pose and twist at an instant."""


class SimSrmCamera:
    """A frame source for the camera process, driven by the true TCP pose.

    Frames come at ``params.fps``; each is rendered for the pose at its
    capture time and handed over ``params.latency`` after it (or later, when
    rendering took longer). With ``params.stamp_sigma`` the exposure is off
    the stamp the frame carries, and ``params.delivery_jitter`` delays some
    frames more than others. ``unplug()`` makes :meth:`read` fail as a camera
    pulled from its socket does; ``extra_latency`` delays frames further.

    Parameters
    ----------
    srm : SimSrm
    pose_at : PoseAt
        The truth, e.g. from :class:`celld.sim.robot.truth.TruthReader`.
    clock : callable
        ``time.monotonic_ns`` unless a test drives time itself.
    sleep : callable
        ``time.sleep`` unless a test drives time itself.
    """

    def __init__(
        self,
        srm: SimSrm,
        pose_at: PoseAt,
        clock: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.srm = srm
        self.pose_at = pose_at
        self._clock = clock
        self._sleep = sleep
        self._period_ns = int(round(1e9 / srm.params.fps))
        self._next_ns = 0
        self._t0_ns = 0
        self.unplugged = False
        self.extra_latency = 0.0
        self.truth: list[tuple[int, Array, bool]] = []  # (stamp_ns, delta_true, in_contact), for benchmarks
        self.keep_truth = True
        self._timing = np.random.default_rng([srm.params.seed, 0x7157])

    def open(self) -> None:
        self._t0_ns = self._clock()
        self._next_ns = self._t0_ns

    def unplug(self) -> None:
        self.unplugged = True

    def read(self) -> tuple[int, Array] | None:
        """The next frame ``(capture stamp_ns, image)``, or None when the camera is gone."""
        if self.unplugged:
            self._sleep(self._period_ns * 1e-9)
            return None
        now = self._clock()
        if now < self._next_ns:
            self._sleep((self._next_ns - now) * 1e-9)
        else:
            # Late: skip the frames that were missed, as a free-running sensor does.
            missed = (now - self._next_ns) // self._period_ns
            self._next_ns += missed * self._period_ns
        stamp = self._next_ns
        self._next_ns += self._period_ns
        p = self.srm.params
        exposure = stamp + (int(self._timing.normal(0.0, p.stamp_sigma) * 1e9) if p.stamp_sigma > 0.0 else 0)
        T, v = self.pose_at(exposure)
        T_bt = T @ self.srm.tool.T_tcp_tool
        r = T_bt[:3, 3] - T[:3, 3]
        v_tip = v[:3] + np.cross(v[3:], r)
        f = self.srm.frame(stamp, T, v_tip, (stamp - self._t0_ns) * 1e-9)
        if self.keep_truth:
            self.truth.append((stamp, f.delta_true, f.in_contact))
        jitter = self._timing.uniform(0.0, p.delivery_jitter) if p.delivery_jitter > 0.0 else 0.0
        due = stamp + int((p.latency + self.extra_latency + jitter) * 1e9)
        now = self._clock()
        if now < due:
            self._sleep((due - now) * 1e-9)
        return stamp, f.image

    def close(self) -> None:
        pass


# -- the simulated cell's SRM camera, as the tactile process builds it ----------------

# The simulator's truth of each frame, for benchmarks: capture stamp, delta, contact.
SRM_TRUTH_DTYPE = np.dtype([("stamp_ns", np.int64), ("delta_true", np.float64, (3,)), ("in_contact", np.bool_)])


def _pose_at(history: Callable[[], np.ndarray]) -> PoseAt:
    """:data:`PoseAt` of the true *flange* over the simulated controller's ~2 s truth history (``TruthReader.history``).

    The flange, not the TCP: the simulated cell's tool is given in the flange
    frame, whatever TCP offset the controller was told (with a zero TCP offset
    the two are the same).
    """
    from celld.sim.robot.truth import flange_of

    def pose_at(stamp_ns: int) -> tuple[Array, Array]:
        # One copy of the history per frame; position interpolated, rotation
        # from the nearer cycle (2 ms apart: well under a milliradian here).
        recs = history()
        stamps = recs["stamp_ns"]
        i = min(max(int(np.searchsorted(stamps, stamp_ns)), 1), len(recs) - 1)
        j = max(i - 2, 0)
        F = flange_of(recs["T_base_tcp"][[j, i - 1, i]], recs["T_flange_tcp"][[j, i - 1, i]])
        t0, t1 = int(stamps[i - 1]), int(stamps[i])
        w = min(max((stamp_ns - t0) / max(t1 - t0, 1), 0.0), 1.0)
        T = np.array(F[2 if w >= 0.5 else 1])
        T[:3, 3] = (1 - w) * F[1][:3, 3] + w * F[2][:3, 3]
        v = np.zeros(6)
        dt = (t1 - int(stamps[j])) * 1e-9
        if dt > 0:
            v[:3] = (F[2][:3, 3] - F[0][:3, 3]) / dt
        return T, v

    return pose_at


class _TruthSharingCamera:
    """A :class:`SimSrmCamera` on the simulated controller's truth that closes its reader and shares each frame's truth."""

    def __init__(self, cam: SimSrmCamera, close_reader: Callable[[], None], truth_slot: str) -> None:
        self.cam = cam
        self._close_reader = close_reader
        self._slot = SeqlockSlot.attach(truth_slot, SRM_TRUTH_DTYPE) if truth_slot else None
        self._rec = np.zeros(1, SRM_TRUTH_DTYPE)
        cam.keep_truth = self._slot is not None

    def open(self) -> None:
        self.cam.open()

    def read(self) -> tuple[int, Array] | None:
        frame = self.cam.read()
        if self._slot is not None and self.cam.truth:
            stamp, delta, contact = self.cam.truth[-1]
            self._rec["stamp_ns"], self._rec["delta_true"], self._rec["in_contact"] = stamp, delta, contact
            self._slot.write(self._rec)
            self.cam.truth.clear()
        return frame

    def close(self) -> None:
        self.cam.close()
        self._close_reader()
        if self._slot is not None:
            self._slot.close()


@dataclass(frozen=True)
class SimSrmSource:
    """The simulated SRM camera as the tactile process builds it (a picklable frame-source factory).

    ``wall`` (n, 2) and ``free`` describe the seam wall in the plane
    ``T_base_plane``, or ``wall`` is a :class:`WallSurface` (the wall at the
    tip's height); ``robot_host`` is the simulated controller whose true
    flange pose drives the finger; ``tool`` the finger's geometry in the
    flange frame (the tool as built, in the simulated cell). ``params`` with
    ``fps`` 0 takes the camera's configured rate. With ``truth_slot`` (a
    :data:`SRM_TRUTH_DTYPE` slot the caller created) each frame's true
    deformation is shared there, for benchmarks; the estimator never reads it.
    ``far_wall``: the joint's other wall (:class:`SimSrm`).
    """

    robot_host: str
    wall: Array | WallSurface
    free: float
    T_base_plane: Array
    tool: ToolConfig = ToolConfig()
    params: SrmSimParams | None = None
    truth_slot: str = ""
    far_wall: WallSurface | None = None
    camera: SrmCamera | None = None

    def __call__(self, cfg: TactileConfig) -> _TruthSharingCamera:
        from dataclasses import replace

        from celld.sim.robot.truth import TruthReader

        reader = TruthReader(self.robot_host)
        wall = self.wall if isinstance(self.wall, WallSurface) else Wall(np.asarray(self.wall), self.free)
        params = self.params or SrmSimParams(fps=cfg.fps)
        if params.fps <= 0.0:
            params = replace(params, fps=cfg.fps)
        srm = SimSrm(cfg, self.tool, wall, self.T_base_plane, params, self.far_wall, self.camera)
        return _TruthSharingCamera(SimSrmCamera(srm, _pose_at(reader.history)), reader.close, self.truth_slot)
