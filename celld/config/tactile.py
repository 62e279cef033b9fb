"""The welding tool's config: the SRM sensor (``[tactile]``), the tool (``[tool]``) and the servo (``[servo]``).

- :class:`TactileConfig`: the finger camera, its tag and detection gates, the
  tare, and the deformation levels that classify contact;
- :class:`ToolConfig`: the tool's geometry on the flange (frames, the SRM
  tip, the torch, the camera's mount, the wall side); see
  :mod:`celld.tactile.tool` for the frames;
- :class:`ServoConfig`: Algorithm 2's gains and the touch and search moves
  (:class:`celld.motion.algorithm2.Algorithm2Params` is derived from it).

Every bound of a servo value a job may override is stated once, in
:data:`SERVO_BOUNDS` (SI): the config reader, the job schema
(:mod:`celld.bus.messages`) and the plan check in the motion process all use
it. :func:`check_servo` holds the rules that tie the sections together
(``contact_threshold < delta_d < overload``); the config, a weld job's
overrides and the plan are all checked by it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any, NamedTuple

import numpy as np

from celld.config.reader import TableReader
from celld.errors import ConfigError

# Keys that moved out of [tactile] when it was split, and where they went.
_MOVED_FROM_TACTILE = {
    **{k: f"[tool] {k}" for k in ("tool_x_tcp", "tool_z_tcp", "tip_tcp_mm", "tip_radius_mm", "T_tool_cam", "wall_side", "torch_offset_mm")},
    **{
        k: f"[servo] {k}"
        for k in (
            "delta_d_mm",
            "k_p",
            "v_const_mm_s",
            "k_torch",
            "max_correction_speed_mm_s",
            "omega_max",
            "guard_cos",
            "plan_smoothing_mm",
            "refine_window_mm",
            "contact_loss_samples",
            "search_distance_mm",
            "touch_speed_mm_s",
            "touch_distance_mm",
        )
    },
}

# A welding tool's tip, and its camera, lie within this of the TCP (m): a kilometre is a unit slip.
MAX_TOOL_REACH = 1.0
# The heaviest payload of any UR arm (the UR30), kg.
MAX_PAYLOAD = 30.0


def _point_mm(r: TableReader, name: str, default: tuple[float, float, float], what: str, origin: str) -> tuple[float, float, float]:
    """A point given in millimetres (``name``), in metres, within :data:`MAX_TOOL_REACH` of ``origin``."""
    v = r.vector(name, 3, [x * 1e3 for x in default], scale=1e-3)
    if np.linalg.norm(v) > MAX_TOOL_REACH:
        raise r.error(name, f"expected {what} within {MAX_TOOL_REACH * 1e3:g} mm of the {origin} (millimetres), got {[x * 1e3 for x in v]}")
    return (float(v[0]), float(v[1]), float(v[2]))


@dataclass(frozen=True)
class TactileConfig:
    """The SRM sensor: the finger camera, the tag it watches, detection, tare and contact levels."""

    kind: str = "sim"  # sim | opencv | none (the cell has no finger camera: no weld jobs)
    device: str = "0"
    width_px: int = 640
    height_px: int = 480
    fps: float = 60.0
    # Time from the start of exposure to the return of a grab (real camera), s.
    capture_latency: float = 0.008
    # SCHED_FIFO priority of the camera process, below the motion loop's (0:
    # best effort at nice -10). A frame then waits for no best-effort work.
    rt_priority: int = 40
    tag_id: int = 7
    tag_dictionary: str = "DICT_4X4_50"
    tag_size: float = 0.008  # m, side of the tag's black square
    # Camera intrinsics: fx, fy, cx, cy in pixels, and distortion k1 k2 p1 p2 k3.
    intrinsics_px: tuple[float, float, float, float] = (600.0, 600.0, 320.0, 240.0)
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    # -- detection quality gates --
    min_sharpness: float = 0.16  # edge slope / contrast (1/px) below which a frame is blurred (~ sigma 2.5 px)
    max_reprojection_px: float = 0.5  # RMS corner reprojection error above which a pose is refused
    tare_frames: int = 30
    tare_max_spread: float = 2e-5  # m, RMS spread of the rest pose allowed during a tare
    # m: a tare whose rest lies farther than this from the finger's reference
    # rest (the first tare, kept in state_dir) is refused: the finger is not free.
    tare_max_offset: float = 0.3e-3
    # -- contact levels of the normal deformation --
    contact_threshold: float = 0.0003  # m
    overload: float = 0.004  # m

    @classmethod
    def read(cls, r: TableReader) -> TactileConfig:
        r.refuse_moved(_MOVED_FROM_TACTILE)
        return cls(
            kind=r.str("kind", cls.kind, choices=("sim", "opencv", "none")),
            device=r.str("device", cls.device),
            width_px=r.int("width_px", cls.width_px, lo=16, hi=8192),
            height_px=r.int("height_px", cls.height_px, lo=16, hi=8192),
            fps=r.float("fps", cls.fps, lo=1.0, hi=1000.0),
            capture_latency=r.float("capture_latency_ms", cls.capture_latency * 1e3, lo=0.0, hi=500.0, scale=1e-3),
            rt_priority=r.int("rt_priority", cls.rt_priority, lo=0, hi=79),
            tag_id=r.int("tag_id", cls.tag_id, lo=0, hi=999),
            tag_dictionary=r.str("tag_dictionary", cls.tag_dictionary),
            tag_size=r.float("tag_size_mm", cls.tag_size * 1e3, lo=0.5, hi=200.0, scale=1e-3),
            intrinsics_px=r.vector("intrinsics_px", 4, list(cls.intrinsics_px)),  # type: ignore[arg-type]
            distortion=r.vector("distortion", 5, list(cls.distortion)),
            min_sharpness=r.float("min_sharpness", cls.min_sharpness, lo=0.0, hi=1.0),
            max_reprojection_px=r.float("max_reprojection_px", cls.max_reprojection_px, lo=0.0, hi=20.0, open_lo=True),
            tare_frames=r.int("tare_frames", cls.tare_frames, lo=1, hi=10_000),
            tare_max_spread=r.float("tare_max_spread_mm", cls.tare_max_spread * 1e3, lo=0.0, hi=5.0, scale=1e-3, open_lo=True),
            tare_max_offset=r.float("tare_max_offset_mm", cls.tare_max_offset * 1e3, lo=0.0, hi=10.0, scale=1e-3, open_lo=True),
            contact_threshold=r.float("contact_threshold_mm", cls.contact_threshold * 1e3, lo=0.0, hi=20.0, scale=1e-3),
            overload=r.float("overload_mm", cls.overload * 1e3, lo=0.0, hi=50.0, scale=1e-3),
        )


# tool.measured: a weld needs a measured tip, or may use the configured one.
TOOL_MEASURED = ("required", "nominal")


@dataclass(frozen=True)
class ToolConfig:
    """The welding tool on the flange: the SRM finger, its camera's mount and the torch.

    The tool frame sits at the undeformed SRM tip (the paper's P_r), x along
    t_d (from the torch to the tip), z along the finger towards the flange
    (the welding-plane normal), y = n_d (:mod:`celld.tactile.tool`).
    """

    # Tool axes in the TCP frame: x = t_d (torch -> tip), z = finger axis up.
    tool_x_tcp: tuple[float, float, float] = (1.0, 0.0, 0.0)
    tool_z_tcp: tuple[float, float, float] = (0.0, 0.0, -1.0)
    # Undeformed SRM tip centre in the TCP frame, m.
    tip_tcp: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tip_radius: float = 0.001  # m, radius of the SRM tip
    # Pose of the finger camera in the tool frame (camera up the finger, looking at the tag).
    T_tool_cam: tuple[tuple[float, ...], ...] = (
        (1.0, 0.0, 0.0, 0.0),
        (0.0, -1.0, 0.0, 0.0),
        (0.0, 0.0, -1.0, 0.04),
        (0.0, 0.0, 0.0, 1.0),
    )
    # Which side of the tool the seam wall is on: "left" (+n_d) or "right" (-n_d).
    wall_side: str = "left"
    torch_offset: float = 0.03  # m, |d| of Eq. 14: the torch trails the tip by this much
    # Diameter of the welding wire: the torch point is the centre of the
    # wire's cut end, which a tool-calibrate job finds in the scanner's cloud.
    wire_diameter: float = 0.0012  # m
    # Whether a weld needs the tip measured by an accepted tool-calibrate job
    # ("required": the measured tip overrides tip_tcp; a weld without one is
    # refused) or may run on tip_tcp as typed ("nominal": a tool known to be as
    # drawn; a measured tip, when there is one, still overrides it).
    measured: str = "required"
    # The tool's mass and its centre of mass in the flange frame, as the
    # controller's payload setting: the arm's calibration models the joints'
    # sag under it (celld.calib.kinematic). 0 kg: not known.
    mass: float = 0.0  # kg
    com_flange: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m

    def R_tool_cam(self) -> np.ndarray:
        return np.array(self.T_tool_cam, dtype=np.float64)[:3, :3]

    @classmethod
    def read(cls, r: TableReader) -> ToolConfig:
        def unit(name: str, default: tuple[float, float, float]) -> tuple[float, float, float]:
            v: np.ndarray = np.array(r.vector(name, 3, list(default)))
            if np.linalg.norm(v) < 1e-9:
                raise r.error(name, f"expected a non-zero direction, got {v.tolist()}")
            return tuple(float(x) for x in v / np.linalg.norm(v))  # type: ignore[return-value]

        tool_x = unit("tool_x_tcp", cls.tool_x_tcp)
        tool_z = unit("tool_z_tcp", cls.tool_z_tcp)
        if abs(float(np.dot(tool_x, tool_z))) > 1e-6:
            raise r.error("tool_z_tcp", f"expected a direction perpendicular to tool_x_tcp {tool_x}, got {tool_z}")
        lo, hi = SERVO_BOUNDS["torch_offset"].lo * 1e3, SERVO_BOUNDS["torch_offset"].hi * 1e3
        tip = _point_mm(r, "tip_tcp_mm", cls.tip_tcp, "the tip", "TCP")
        T_tool_cam = r.matrix4("T_tool_cam", [list(row) for row in cls.T_tool_cam])
        if np.linalg.norm(np.asarray(T_tool_cam)[:3, 3]) > MAX_TOOL_REACH:
            raise r.error(
                "T_tool_cam",
                f"expected the camera within {MAX_TOOL_REACH:g} m of the tool frame (metres), got {np.asarray(T_tool_cam)[:3, 3].tolist()}",
            )
        return cls(
            tool_x_tcp=tool_x,
            tool_z_tcp=tool_z,
            tip_tcp=tip,
            tip_radius=r.float("tip_radius_mm", cls.tip_radius * 1e3, lo=0.0, hi=20.0, scale=1e-3),
            T_tool_cam=T_tool_cam,
            wall_side=r.str("wall_side", cls.wall_side, choices=("left", "right")),
            torch_offset=r.float("torch_offset_mm", cls.torch_offset * 1e3, lo=lo, hi=hi, scale=1e-3, open_lo=True),
            wire_diameter=r.float("wire_diameter_mm", cls.wire_diameter * 1e3, lo=0.2, hi=5.0, scale=1e-3),
            measured=r.str("measured", cls.measured, choices=TOOL_MEASURED),
            mass=r.float("mass_kg", cls.mass, lo=0.0, hi=MAX_PAYLOAD),
            com_flange=_point_mm(r, "com_flange_mm", cls.com_flange, "the centre of mass", "flange"),
        )


class Bound(NamedTuple):
    """A value's range in SI; ``open_lo``: the lower end itself is refused."""

    lo: float
    hi: float
    open_lo: bool = False

    def holds(self, value: float) -> bool:
        return (value > self.lo if self.open_lo else value >= self.lo) and value <= self.hi

    def text(self, scale: float = 1.0) -> str:
        return f"{self.lo * scale:g} {'<' if self.open_lo else '<='} value <= {self.hi * scale:g}"


# The range of every servo value (and the tool's torch offset), SI. The config
# file's keys carry the unit named beside each (a job's fields too).
SERVO_BOUNDS: dict[str, Bound] = {
    "delta_d": Bound(0.0, 0.020, True),  # m (_mm)
    "k_p": Bound(0.0, 1000.0, True),  # 1/s
    "v_const": Bound(0.0, 0.5, True),  # m/s (_mm_s)
    "k_torch": Bound(0.0, 100.0),  # 1/s
    "max_correction_speed": Bound(0.0, 0.5, True),  # m/s (_mm_s)
    "omega_max": Bound(0.0, 3.14, True),  # rad/s
    "guard_cos": Bound(0.0, 0.9, True),
    "plan_smoothing": Bound(0.0, 0.2),  # m (_mm)
    "refine_window": Bound(0.0, 0.05, True),  # m (_mm)
    "contact_loss_samples": Bound(1, 1000),
    "search_distance": Bound(0.0, 0.5),  # m (_mm)
    "touch_speed": Bound(0.0, 0.1, True),  # m/s (_mm_s)
    "touch_distance": Bound(0.0, 0.5, True),  # m (_mm)
    "torch_offset": Bound(0.0, 0.5, True),  # m (_mm), [tool]
}


@dataclass(frozen=True)
class ServoConfig:
    """Algorithm 2 (the deformation servo) and the moves around it, SI units."""

    delta_d: float = 0.0015  # m, desired normal deformation
    k_p: float = 5.0  # 1/s, normal gain of Eq. 16
    v_const: float = 0.010  # m/s, tangential speed
    k_torch: float = 2.0  # 1/s, torch lateral gain added to Eq. 18 (0: the paper's law)
    max_correction_speed: float = 0.01  # m/s, bound of the normal correction of Eq. 16
    omega_max: float = 0.5  # rad/s, bound of line 13
    guard_cos: float = 0.25  # |n_d . n_t| below which line 13 is damped
    plan_smoothing: float = 0.012  # m, window of the planned path's smoothing
    refine_window: float = 0.002  # m, chord of the refined path's tangent
    contact_loss_samples: int = 3  # consecutive no-contact samples that mean contact is lost
    search_distance: float = 0.005  # m, travel after contact loss before a stop
    touch_speed: float = 0.003  # m/s, approach speed towards the wall
    touch_distance: float = 0.012  # m, approach travel without contact before a stop

    @classmethod
    def read(cls, r: TableReader) -> ServoConfig:
        values: dict[str, Any] = {}
        for f in fields(cls):
            key, scale = _SERVO_KEYS[f.name]
            b = SERVO_BOUNDS[f.name]
            default = getattr(cls, f.name)
            if f.name == "contact_loss_samples":
                values[f.name] = r.int(key, default, lo=b.lo, hi=b.hi)
            else:
                values[f.name] = r.float(key, default / scale, lo=b.lo / scale, hi=b.hi / scale, scale=scale, open_lo=b.open_lo)
        return cls(**values)


# The config key of each servo value and the factor from the key's unit to SI.
_SERVO_KEYS: dict[str, tuple[str, float]] = {
    "delta_d": ("delta_d_mm", 1e-3),
    "k_p": ("k_p", 1.0),
    "v_const": ("v_const_mm_s", 1e-3),
    "k_torch": ("k_torch", 1.0),
    "max_correction_speed": ("max_correction_speed_mm_s", 1e-3),
    "omega_max": ("omega_max", 1.0),
    "guard_cos": ("guard_cos", 1.0),
    "plan_smoothing": ("plan_smoothing_mm", 1e-3),
    "refine_window": ("refine_window_mm", 1e-3),
    "contact_loss_samples": ("contact_loss_samples", 1.0),
    "search_distance": ("search_distance_mm", 1e-3),
    "touch_speed": ("touch_speed_mm_s", 1e-3),
    "touch_distance": ("touch_distance_mm", 1e-3),
}


def servo_key(name: str) -> tuple[str, float]:
    """The config (and job) key of a servo or tool value and its scale to SI: ``("delta_d_mm", 1e-3)``."""
    if name == "torch_offset":
        return "torch_offset_mm", 1e-3
    return _SERVO_KEYS[name]


def check_servo(
    servo: ServoConfig, tactile: TactileConfig, tool: ToolConfig, source: str = "<config>", max_linear_speed: float = math.inf
) -> None:
    """The rules that tie the servo to the sensor, the tool and the motion limits; raises ConfigError naming the servo key.

    Every value in its :data:`SERVO_BOUNDS`; ``contact_threshold < delta_d <
    overload``: the servo must ask for a deformation the sensor reads as
    contact and not as overload; its speeds at most ``max_linear_speed``
    (``[motion] max_linear_speed``), which every command obeys.
    """
    for name, bound in SERVO_BOUNDS.items():
        value = tool.torch_offset if name == "torch_offset" else getattr(servo, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and bound.holds(value)):
            key, scale = servo_key(name)
            section = "tool" if name == "torch_offset" else "servo"
            raise ConfigError(source, f"{section}.{key}", f"expected {bound.text(1.0 / scale)}, got {value / scale:g}")
    if not tactile.contact_threshold < servo.delta_d < tactile.overload:
        raise ConfigError(
            source,
            "servo.delta_d_mm",
            f"expected tactile.contact_threshold_mm < delta_d_mm < tactile.overload_mm, got "
            f"{tactile.contact_threshold * 1e3:g} / {servo.delta_d * 1e3:g} / {tactile.overload * 1e3:g} mm",
        )
    for name in ("v_const", "max_correction_speed", "touch_speed"):
        v = getattr(servo, name)
        if v > max_linear_speed:
            raise ConfigError(
                source,
                f"servo.{name}_mm_s",
                f"expected at most motion.max_linear_speed ({max_linear_speed * 1e3:g} mm/s), got {v * 1e3:g} mm/s",
            )


def with_overrides(
    servo: ServoConfig, tactile: TactileConfig, tool: ToolConfig, source: str, max_linear_speed: float = math.inf, **overrides: float | None
) -> tuple[ServoConfig, ToolConfig]:
    """The servo and tool with a job's overrides (None: keep), checked as the config is (:func:`check_servo`)."""
    given: dict[str, Any] = {k: v for k, v in overrides.items() if v is not None}
    tool_new = replace(tool, torch_offset=given.pop("torch_offset")) if "torch_offset" in given else tool
    servo_new = replace(servo, **given)
    check_servo(servo_new, tactile, tool_new, source, max_linear_speed)
    return servo_new, tool_new
