"""Cell configuration: TOML files loaded once into frozen, validated values.

A config is data. It is read and checked at start-up, before any device is
opened; a bad file is refused with a :class:`~celld.errors.ConfigError` that
names the file, the dotted key and the reason. Unknown keys are refused too, so
a typo never silently falls back to a default.

Sections (one frozen dataclass each) are split by axis, as in
``configs/``: the cell, the robot, motion limits, the scanner, the calibration,
the tactile sensor, the bus and the recording. Lengths are metres, angles
radians, times seconds, unless the key carries a unit suffix (``_mm``,
``_deg``, ``_hz``, ``_ms``), which is converted here, once.

A file may ``include = ["robots/ur10e.toml", ...]`` other files (paths relative
to it); later values override earlier ones, table by table.
"""

from __future__ import annotations

import ipaddress
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Sequence, TypeVar

import numpy as np

from celld.errors import ConfigError

T = TypeVar("T")


class TableReader:
    """Reads typed values out of one TOML table and tracks which keys were used.

    Every getter checks the type and range and raises ConfigError with the file
    and the dotted key. :meth:`done` refuses any key that no getter asked for.
    """

    def __init__(self, table: dict[str, Any], source: str, prefix: str = "") -> None:
        if not isinstance(table, dict):
            raise ConfigError(source, prefix, f"expected a table, got {type(table).__name__}")
        self._table = table
        self.source = source
        self.prefix = prefix
        self._used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def error(self, name: str, reason: str) -> ConfigError:
        return ConfigError(self.source, self.key(name), reason)

    def has(self, name: str) -> bool:
        return name in self._table

    def _get(self, name: str, default: Any) -> Any:
        self._used.add(name)
        if name in self._table:
            return self._table[name]
        if default is _REQUIRED:
            raise self.error(name, "required key is missing")
        return default

    def str(self, name: str, default: Any = None, choices: Sequence[str] | None = None) -> str:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, str):
            raise self.error(name, f"expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise self.error(name, f"expected one of {', '.join(choices)}, got {value!r}")
        return value

    def bool(self, name: str, default: Any = None) -> bool:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, bool):
            raise self.error(name, f"expected true or false, got {value!r}")
        return value

    def int(self, name: str, default: Any = None, lo: float = -math.inf, hi: float = math.inf) -> int:
        value = self._get(name, _REQUIRED if default is None else default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(name, f"expected an integer, got {value!r}")
        if not lo <= value <= hi:
            raise self.error(name, f"expected {lo} <= value <= {hi}, got {value}")
        return value

    def float(
        self,
        name: str,
        default: Any = None,
        lo: float = -math.inf,
        hi: float = math.inf,
        scale: float = 1.0,
        open_lo: bool = False,
    ) -> float:
        """A finite number in [lo, hi] (bounds in the file's units), times ``scale``."""
        value = self._get(name, _REQUIRED if default is None else default)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(name, f"expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(name, f"expected a finite number, got {value}")
        if value < lo or value > hi or (open_lo and value <= lo):
            op = "<" if open_lo else "<="
            raise self.error(name, f"expected {lo} {op} value <= {hi}, got {value}")
        return value * scale

    def vector(self, name: str, length: int, default: Any = None, scale: float = 1.0) -> tuple[float, ...]:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, (list, tuple)) or len(value) != length:
            raise self.error(name, f"expected a list of {length} numbers, got {value!r}")
        out = []
        for v in value:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise self.error(name, f"expected finite numbers, got {v!r}")
            out.append(float(v) * scale)
        return tuple(out)

    def matrix4(self, name: str, default: Any = None) -> tuple[tuple[float, ...], ...]:
        """A (4, 4) rigid transform given as 4 rows of 4 numbers (metres)."""
        from celld.errors import InputError
        from celld.se3 import check_transform

        value = self._get(name, _REQUIRED if default is None else default)
        try:
            T = check_transform(value, self.key(name))
        except (InputError, ValueError, TypeError) as exc:
            raise self.error(name, f"expected a 4x4 rigid transform: {exc}") from exc
        return tuple(tuple(float(x) for x in row) for row in T)

    def table(self, name: str, required: bool = False) -> "TableReader":
        value = self._get(name, _REQUIRED if required else {})
        return TableReader(value, self.source, self.key(name))

    def done(self) -> None:
        """Refuse keys that no getter asked for (typos, stale options)."""
        unknown = sorted(set(self._table) - self._used)
        if unknown:
            raise ConfigError(self.source, self.key(unknown[0]), f"unknown key (known here: {', '.join(sorted(self._used)) or 'none'})")


_REQUIRED = object()


# -- sections -----------------------------------------------------------------


@dataclass(frozen=True)
class CellConfig:
    """Identity of the cell and where it keeps its state."""

    name: str = "cell"
    state_dir: str = "/var/lib/celld"

    @classmethod
    def read(cls, r: TableReader) -> "CellConfig":
        name = r.str("name", "cell")
        if not name or not all(c.isalnum() or c in "-_" for c in name):
            raise r.error("name", f"expected letters, digits, '-' or '_' (it is a zenoh key part), got {name!r}")
        return cls(name=name, state_dir=r.str("state_dir", "/var/lib/celld"))


@dataclass(frozen=True)
class RobotConfig:
    """The robot link: where the controller is and what the cell allows it."""

    model: str = "ur10e"
    host: str = "127.0.0.1"
    frequency_hz: float = 500.0
    connect_timeout: float = 10.0
    # Workspace box of the TCP in the base frame, metres.
    workspace_min: tuple[float, float, float] = (-1.2, -1.2, -0.05)
    workspace_max: tuple[float, float, float] = (1.2, 1.2, 1.4)
    # Pose of the TCP in the flange frame, UR pose [x, y, z, rx, ry, rz].
    tcp_offset: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    home_q: tuple[float, ...] = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
    # Standard digital output (0..7) that switches the process (the welding
    # arc), driven by the motion loop; -1: the cell has none.
    arc_output: int = -1

    @classmethod
    def read(cls, r: TableReader) -> "RobotConfig":
        wmin = r.vector("workspace_min", 3, list(cls.workspace_min))
        wmax = r.vector("workspace_max", 3, list(cls.workspace_max))
        if not all(a < b for a, b in zip(wmin, wmax)):
            raise r.error("workspace_max", f"expected every value above workspace_min {wmin}, got {wmax}")
        return cls(
            model=r.str("model", "ur10e", choices=("ur10e", "ur5e", "ur5")),
            host=r.str("host", "127.0.0.1"),
            frequency_hz=r.float("frequency_hz", 500.0, lo=1.0, hi=500.0),
            connect_timeout=r.float("connect_timeout", 10.0, lo=0.1, hi=120.0),
            workspace_min=wmin,  # type: ignore[arg-type]
            workspace_max=wmax,  # type: ignore[arg-type]
            tcp_offset=r.vector("tcp_offset", 6, list(cls.tcp_offset)),
            home_q=r.vector("home_q", 6, list(cls.home_q)),
            arc_output=r.int("arc_output", cls.arc_output, lo=-1, hi=7),
        )


@dataclass(frozen=True)
class MotionLimits:
    """Cartesian limits every command obeys in every cycle (SI)."""

    max_linear_speed: float = 0.25  # m/s
    max_linear_accel: float = 1.0  # m/s^2
    max_linear_jerk: float = 10.0  # m/s^3
    max_angular_speed: float = 1.0  # rad/s
    max_angular_accel: float = 4.0  # rad/s^2
    max_angular_jerk: float = 40.0  # rad/s^3
    # A tactile sample older than this stops a servo, seconds.
    tactile_stale: float = 0.1
    # Robot state older than this many cycles stops the loop.
    state_stale_cycles: int = 3
    # Without fresh robot state for this long the link counts as lost, s.
    link_timeout: float = 0.1
    # RTDE watchdog: the controller stops its program after 1/rate s without a kick.
    rtde_watchdog_hz: float = 10.0

    @classmethod
    def read(cls, r: TableReader) -> "MotionLimits":
        return cls(
            max_linear_speed=r.float("max_linear_speed", cls.max_linear_speed, lo=0.0, hi=1.0, open_lo=True),
            max_linear_accel=r.float("max_linear_accel", cls.max_linear_accel, lo=0.0, hi=10.0, open_lo=True),
            max_linear_jerk=r.float("max_linear_jerk", cls.max_linear_jerk, lo=0.0, hi=1000.0, open_lo=True),
            max_angular_speed=r.float("max_angular_speed", cls.max_angular_speed, lo=0.0, hi=3.14, open_lo=True),
            max_angular_accel=r.float("max_angular_accel", cls.max_angular_accel, lo=0.0, hi=40.0, open_lo=True),
            max_angular_jerk=r.float("max_angular_jerk", cls.max_angular_jerk, lo=0.0, hi=4000.0, open_lo=True),
            tactile_stale=r.float("tactile_stale_ms", cls.tactile_stale * 1e3, lo=1.0, hi=5000.0, scale=1e-3),
            state_stale_cycles=r.int("state_stale_cycles", cls.state_stale_cycles, lo=1, hi=50),
            link_timeout=r.float("link_timeout_ms", cls.link_timeout * 1e3, lo=4.0, hi=5000.0, scale=1e-3),
            rtde_watchdog_hz=r.float("rtde_watchdog_hz", cls.rtde_watchdog_hz, lo=1.0, hi=500.0),
        )


SCANNER_KINDS = ("sim", "replay", "phoxi", "azure-kinect", "realsense")
SCANNER_MODELS = ("phoxi-s", "phoxi-m", "azure-kinect")


@dataclass(frozen=True)
class ScannerConfig:
    """The 3D scanner above the table."""

    kind: str = "sim"
    model: str = "phoxi-m"
    # Nominal pose of the camera in the base frame. For the simulated scanner it
    # is the truth the simulator renders with; celld never reads it as an
    # estimate: calibration starts without it.
    T_base_cam: tuple[tuple[float, ...], ...] = (
        (0.0, -1.0, 0.0, 0.6),
        (-1.0, 0.0, 0.0, -0.0125),
        (0.0, 0.0, -1.0, 1.0),
        (0.0, 0.0, 0.0, 1.0),
    )
    replay_dir: str = ""
    # Length unit of the replayed files ("m" or "mm"); converted once when read.
    replay_units: str = "m"
    # Start again at the first file after the last one (else the replay ends with an error).
    replay_loop: bool = False
    # Serial number (Photoneo), device index (Azure Kinect) or serial (RealSense); "" for the first.
    device: str = ""
    seed: int = 0
    # Image resolution of the simulated scanner relative to the model's (0.01 to 1).
    resolution_scale: float = 1.0
    # GenTL producer (.cti) for the Photoneo driver; "" searches GENICAM_GENTL64_PATH.
    gentl_producer: str = ""
    # Longest wait for one frame from a real scanner, s.
    capture_timeout: float = 10.0
    # Depth-camera intrinsics fx, fy, cx, cy (pixels) where the SDK does not report
    # them (Azure Kinect through Open3D); () when not given.
    depth_intrinsics_px: tuple[float, ...] = ()
    # Depth kept by depth cameras, m: nearer or farther returns become NaN.
    depth_min: float = 0.1
    depth_max: float = 6.0

    @classmethod
    def read(cls, r: TableReader) -> "ScannerConfig":
        depth_min = r.float("depth_min_mm", cls.depth_min * 1e3, lo=0.0, hi=20_000.0, scale=1e-3)
        depth_max = r.float("depth_max_mm", cls.depth_max * 1e3, lo=0.0, hi=20_000.0, scale=1e-3, open_lo=True)
        if not depth_min < depth_max:
            raise r.error("depth_max_mm", f"expected more than depth_min_mm ({depth_min * 1e3}), got {depth_max * 1e3}")
        intrinsics: tuple[float, ...] = ()
        if r.has("depth_intrinsics_px"):
            intrinsics = r.vector("depth_intrinsics_px", 4)
            if intrinsics[0] <= 0.0 or intrinsics[1] <= 0.0:
                raise r.error("depth_intrinsics_px", f"expected positive focal lengths fx, fy, got {intrinsics[:2]}")
        return cls(
            kind=r.str("kind", "sim", choices=SCANNER_KINDS),
            model=r.str("model", "phoxi-m", choices=SCANNER_MODELS),
            T_base_cam=r.matrix4("T_base_cam", [list(row) for row in cls.T_base_cam]),
            replay_dir=r.str("replay_dir", ""),
            replay_units=r.str("replay_units", cls.replay_units, choices=("m", "mm")),
            replay_loop=r.bool("replay_loop", cls.replay_loop),
            device=r.str("device", ""),
            seed=r.int("seed", 0, lo=0),
            resolution_scale=r.float("resolution_scale", cls.resolution_scale, lo=0.01, hi=1.0),
            gentl_producer=r.str("gentl_producer", ""),
            capture_timeout=r.float("capture_timeout", cls.capture_timeout, lo=0.1, hi=600.0),
            depth_intrinsics_px=intrinsics,
            depth_min=depth_min,
            depth_max=depth_max,
        )


@dataclass(frozen=True)
class CalibrationConfig:
    """Flange-based hand-eye calibration (Algorithm 1)."""

    flange: str = "ur10e"
    e_required: float = 0.0005  # m, cost target of Algorithm 1
    k_max: int = 30
    n_poses: int = 20
    cost: str = "translation"  # or "se3" (the 6-vector with the work radius)
    work_radius: float = 0.5  # m, r of the se3 cost
    settle: float = 0.3  # s after a move before capture
    auto_accept: bool = False
    # Pose generation box around the verification pose, metres, and max tilt.
    pose_box: tuple[float, float, float] = (0.3, 0.3, 0.2)
    max_tilt: float = 0.3  # rad
    verification_pose: tuple[float, ...] = (0.6, 0.0, 0.45, 0.0, 0.0, 0.0)
    # Estimator of T_base_cam: robust (every consistent pair), svd (all pairs,
    # Eq. 9-12) or algorithm1 (the optimum pool of Algorithm 1).
    method: str = "robust"
    compensate: bool = False  # also report Eq. 21's compensated estimate
    # e_icp (Eq. 13): ICP correspondence distance (m; about 3x the scanner's
    # point noise or more), verification points used, model point spacing (m).
    icp_max_distance: float = 0.003
    icp_points: int = 1000
    model_spacing: float = 0.002
    # Retention of the calibrate jobs' datasets (<state_dir>/jobs/<job>/dataset,
    # about 59 MB for 20 PhoXi M poses): keep the newest keep_sessions, and any
    # younger than keep_days days; 0 turns a rule off, both 0 keep everything.
    # The current calibration's dataset is always kept (celld.daemon.retention).
    keep_sessions: int = 10
    keep_days: float = 0.0

    @classmethod
    def read(cls, r: TableReader) -> "CalibrationConfig":
        return cls(
            flange=r.str("flange", cls.flange),
            e_required=r.float("e_required_mm", cls.e_required * 1e3, lo=0.0, hi=100.0, scale=1e-3),
            k_max=r.int("k_max", cls.k_max, lo=1, hi=10_000),
            n_poses=r.int("n_poses", cls.n_poses, lo=4, hi=1000),
            cost=r.str("cost", cls.cost, choices=("translation", "se3")),
            work_radius=r.float("work_radius", cls.work_radius, lo=0.0, hi=10.0, open_lo=True),
            settle=r.float("settle", cls.settle, lo=0.0, hi=10.0),
            auto_accept=r.bool("auto_accept", False),
            pose_box=r.vector("pose_box", 3, list(cls.pose_box)),  # type: ignore[arg-type]
            max_tilt=r.float("max_tilt_deg", math.degrees(cls.max_tilt), lo=0.0, hi=60.0, scale=math.pi / 180),
            verification_pose=r.vector("verification_pose", 6, list(cls.verification_pose)),
            method=r.str("method", cls.method, choices=("robust", "svd", "algorithm1")),
            compensate=r.bool("compensate", False),
            icp_max_distance=r.float(
                "icp_max_distance_mm", cls.icp_max_distance * 1e3, lo=0.0, hi=100.0, scale=1e-3, open_lo=True
            ),
            icp_points=r.int("icp_points", cls.icp_points, lo=10, hi=1_000_000),
            model_spacing=r.float("model_spacing_mm", cls.model_spacing * 1e3, lo=0.1, hi=10.0, scale=1e-3),
            keep_sessions=r.int("keep_sessions", cls.keep_sessions, lo=0, hi=100_000),
            keep_days=r.float("keep_days", cls.keep_days, lo=0.0, hi=36_500.0),
        )


@dataclass(frozen=True)
class TactileConfig:
    """The SRM finger camera, its tool geometry and the deformation servo (Algorithm 2).

    The tool frame, the SRM tip and the torch are described in
    :mod:`celld.tactile.tool`: the tool frame sits at the undeformed SRM tip
    (the paper's P_r), x along t_d (from the torch to the tip), z along the
    finger towards the flange (the welding-plane normal), y = n_d.
    """

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
    # -- tool geometry (celld.tactile.tool) --
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
    # -- detection quality gates --
    min_sharpness: float = 0.16  # edge slope / contrast (1/px) below which a frame is blurred (~ sigma 2.5 px)
    max_reprojection_px: float = 0.5  # RMS corner reprojection error above which a pose is refused
    tare_frames: int = 30
    tare_max_spread: float = 2e-5  # m, RMS spread of the rest pose allowed during a tare
    # -- Algorithm 2 --
    delta_d: float = 0.0015  # m, desired normal deformation
    k_p: float = 5.0  # 1/s, normal gain of Eq. 16
    v_const: float = 0.010  # m/s, tangential speed
    torch_offset: float = 0.03  # m, |d| of Eq. 14
    k_torch: float = 2.0  # 1/s, torch lateral gain added to Eq. 18 (0: the paper's law)
    max_correction_speed: float = 0.01  # m/s, bound of the normal correction of Eq. 16
    omega_max: float = 0.5  # rad/s, bound of line 13
    guard_cos: float = 0.25  # |n_d . n_t| below which line 13 is damped
    plan_smoothing: float = 0.012  # m, window of the planned path's smoothing
    refine_window: float = 0.002  # m, chord of the refined path's tangent
    contact_threshold: float = 0.0003  # m
    overload: float = 0.004  # m
    contact_loss_samples: int = 3  # consecutive no-contact samples that mean contact is lost
    search_distance: float = 0.005  # m, travel after contact loss before a stop
    touch_speed: float = 0.003  # m/s, approach speed towards the wall
    touch_distance: float = 0.012  # m, approach travel without contact before a stop

    def R_tool_cam(self) -> np.ndarray:
        return np.array(self.T_tool_cam, dtype=np.float64)[:3, :3]

    @classmethod
    def read(cls, r: TableReader) -> "TactileConfig":
        def unit(name: str, default: tuple[float, float, float]) -> tuple[float, float, float]:
            v = np.array(r.vector(name, 3, list(default)))
            if np.linalg.norm(v) < 1e-9:
                raise r.error(name, f"expected a non-zero direction, got {v.tolist()}")
            return tuple(float(x) for x in v / np.linalg.norm(v))  # type: ignore[return-value]

        tool_x = unit("tool_x_tcp", cls.tool_x_tcp)
        tool_z = unit("tool_z_tcp", cls.tool_z_tcp)
        if abs(float(np.dot(tool_x, tool_z))) > 1e-6:
            raise r.error("tool_z_tcp", f"expected a direction perpendicular to tool_x_tcp {tool_x}, got {tool_z}")
        delta_d = r.float("delta_d_mm", cls.delta_d * 1e3, lo=0.0, hi=20.0, scale=1e-3, open_lo=True)
        contact = r.float("contact_threshold_mm", cls.contact_threshold * 1e3, lo=0.0, hi=20.0, scale=1e-3)
        overload = r.float("overload_mm", cls.overload * 1e3, lo=0.0, hi=50.0, scale=1e-3)
        if not contact < delta_d < overload:
            raise r.error(
                "delta_d_mm",
                f"expected contact_threshold < delta_d < overload, got {contact * 1e3} / {delta_d * 1e3} / {overload * 1e3} mm",
            )
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
            tool_x_tcp=tool_x,
            tool_z_tcp=tool_z,
            tip_tcp=r.vector("tip_tcp_mm", 3, [x * 1e3 for x in cls.tip_tcp], scale=1e-3),  # type: ignore[arg-type]
            tip_radius=r.float("tip_radius_mm", cls.tip_radius * 1e3, lo=0.0, hi=20.0, scale=1e-3),
            T_tool_cam=r.matrix4("T_tool_cam", [list(row) for row in cls.T_tool_cam]),
            wall_side=r.str("wall_side", cls.wall_side, choices=("left", "right")),
            min_sharpness=r.float("min_sharpness", cls.min_sharpness, lo=0.0, hi=1.0),
            max_reprojection_px=r.float("max_reprojection_px", cls.max_reprojection_px, lo=0.0, hi=20.0, open_lo=True),
            tare_frames=r.int("tare_frames", cls.tare_frames, lo=1, hi=10_000),
            tare_max_spread=r.float("tare_max_spread_mm", cls.tare_max_spread * 1e3, lo=0.0, hi=5.0, scale=1e-3, open_lo=True),
            delta_d=delta_d,
            k_p=r.float("k_p", cls.k_p, lo=0.0, hi=1000.0, open_lo=True),
            v_const=r.float("v_const_mm_s", cls.v_const * 1e3, lo=0.0, hi=500.0, scale=1e-3),
            torch_offset=r.float("torch_offset_mm", cls.torch_offset * 1e3, lo=0.0, hi=500.0, scale=1e-3, open_lo=True),
            k_torch=r.float("k_torch", cls.k_torch, lo=0.0, hi=100.0),
            max_correction_speed=r.float(
                "max_correction_speed_mm_s", cls.max_correction_speed * 1e3, lo=0.0, hi=500.0, scale=1e-3, open_lo=True
            ),
            omega_max=r.float("omega_max", cls.omega_max, lo=0.0, hi=3.14, open_lo=True),
            guard_cos=r.float("guard_cos", cls.guard_cos, lo=0.0, hi=0.9, open_lo=True),
            plan_smoothing=r.float("plan_smoothing_mm", cls.plan_smoothing * 1e3, lo=0.0, hi=200.0, scale=1e-3),
            refine_window=r.float("refine_window_mm", cls.refine_window * 1e3, lo=0.0, hi=50.0, scale=1e-3, open_lo=True),
            contact_threshold=contact,
            overload=overload,
            contact_loss_samples=r.int("contact_loss_samples", cls.contact_loss_samples, lo=1, hi=1000),
            search_distance=r.float("search_distance_mm", cls.search_distance * 1e3, lo=0.0, hi=500.0, scale=1e-3),
            touch_speed=r.float("touch_speed_mm_s", cls.touch_speed * 1e3, lo=0.0, hi=100.0, scale=1e-3, open_lo=True),
            touch_distance=r.float("touch_distance_mm", cls.touch_distance * 1e3, lo=0.0, hi=500.0, scale=1e-3, open_lo=True),
        )


@dataclass(frozen=True)
class BusUser:
    """A user the bus accepts (zenoh user/password authentication) and its role."""

    name: str
    password: str
    role: str  # operator: may submit, cancel and accept, and read | viewer: may only read


BUS_ROLES = ("operator", "viewer")


@dataclass(frozen=True)
class BusConfig:
    """The zenoh bus: mode, endpoints and access control (see :mod:`celld.bus.session`).

    With no ``users`` the bus is open (loopback development and the simulated
    cell). With users, every link must authenticate with one of them and
    zenoh's access control gives each its role's rights.
    """

    mode: str = "peer"  # peer | client | router
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    connect: tuple[str, ...] = ()
    prefix: str = "celld"
    state_rate_hz: float = 20.0
    users: tuple[BusUser, ...] = ()
    # The credentials this process presents when it connects (clients, the CLI,
    # a daemon in client mode or linking to peers that require authentication).
    user: str = ""
    password: str = ""
    # Multicast and gossip scouting: off keeps a loopback bus to the configured endpoints.
    multicast_scouting: bool = False
    # How long a client waits for a link to the cell, and for a reply, s.
    connect_timeout: float = 3.0
    query_timeout: float = 5.0

    @classmethod
    def read(cls, r: TableReader) -> "BusConfig":
        from celld.bus.keys import check_prefix
        from celld.errors import BusError

        listen = r._get("listen", list(cls.listen))
        connect = r._get("connect", list(cls.connect))
        for key, value in (("listen", listen), ("connect", connect)):
            if not isinstance(value, list) or not all(isinstance(v, str) and "/" in v for v in value):
                raise r.error(key, f"expected a list of zenoh endpoints such as \"tcp/127.0.0.1:7447\", got {value!r}")
        users_raw = r._get("users", [])
        if not isinstance(users_raw, list):
            raise r.error("users", "expected an array of tables [[bus.users]]")
        users: list[BusUser] = []
        for i, u in enumerate(users_raw):
            ur = TableReader(u, r.source, r.key(f"users[{i}]"))
            user = BusUser(ur.str("name"), ur.str("password"), ur.str("role", choices=BUS_ROLES))
            if not user.name or any(c in user.name for c in ": \t\r\n"):
                raise ur.error("name", f"expected a name without ':' or white space, got {user.name!r}")
            if not user.password or any(c in user.password for c in "\r\n"):
                raise ur.error("password", "expected a non-empty password on one line")
            if any(u.name == user.name for u in users):
                raise ur.error("name", f"user {user.name!r} is given twice")
            ur.done()
            users.append(user)
        prefix = r.str("prefix", cls.prefix)
        try:
            check_prefix(prefix)
        except BusError as exc:
            raise r.error("prefix", str(exc)) from exc
        user, password = r.str("user", ""), r.str("password", "")
        if bool(user) != bool(password):
            raise r.error("password" if user else "user", "expected user and password together, or neither")
        return cls(
            mode=r.str("mode", cls.mode, choices=("peer", "client", "router")),
            listen=tuple(listen),
            connect=tuple(connect),
            prefix=prefix,
            state_rate_hz=r.float("state_rate_hz", cls.state_rate_hz, lo=0.1, hi=500.0),
            users=tuple(users),
            user=user,
            password=password,
            multicast_scouting=r.bool("multicast_scouting", False),
            connect_timeout=r.float("connect_timeout", cls.connect_timeout, lo=0.05, hi=120.0),
            query_timeout=r.float("query_timeout", cls.query_timeout, lo=0.05, hi=600.0),
        )


@dataclass(frozen=True)
class RecordingConfig:
    """rerun recordings: one .rrd per job, and optional live viewing."""

    enabled: bool = True
    serve_grpc_port: int = 0  # 0: no live server
    # Address the live server binds; loopback unless viewers elsewhere must reach it.
    serve_grpc_host: str = "127.0.0.1"
    connect_url: str = ""  # a viewer to stream to, e.g. rerun+http://127.0.0.1:9876/proxy
    # Clouds are thinned to this many points when logged (0: all); the full
    # clouds belong in the job's dataset, not in the recording.
    max_cloud_points: int = 200_000
    # JPEG quality of logged SRM camera frames (0: raw pixels).
    image_jpeg_quality: int = 85

    @classmethod
    def read(cls, r: TableReader) -> "RecordingConfig":
        host = r.str("serve_grpc_host", cls.serve_grpc_host)
        try:
            ipaddress.ip_address(host)
        except ValueError as exc:
            raise r.error("serve_grpc_host", f"expected an IP address such as 127.0.0.1, got {host!r}") from exc
        url = r.str("connect_url", "")
        if url and not (url.startswith(("rerun://", "rerun+http://", "rerun+https://")) and url.endswith("/proxy")):
            raise r.error("connect_url", f"expected rerun+http://<host>:<port>/proxy (or rerun://, rerun+https://), got {url!r}")
        return cls(
            enabled=r.bool("enabled", True),
            serve_grpc_port=r.int("serve_grpc_port", 0, lo=0, hi=65535),
            serve_grpc_host=host,
            connect_url=url,
            max_cloud_points=r.int("max_cloud_points", cls.max_cloud_points, lo=0),
            image_jpeg_quality=r.int("image_jpeg_quality", cls.image_jpeg_quality, lo=0, hi=100),
        )


@dataclass(frozen=True)
class WeldConfig:
    """The weld job: which part, where the arm waits while the scanner looks,
    and how the SRM finger meets the seam.

    Poses are UR poses of the TCP ``[x, y, z, rx, ry, rz]`` (m, rad). Heights
    are measured along the seam plane's normal (the approach direction).
    """

    # The part the cell welds when a job names none: an example name
    # (v-groove, fillet-t, curved-groove) or a model in workpiece_dir.
    workpiece: str = ""
    # Directory of user parts: <name>.stl|.ply|.obj with <name>.seam.json|.csv.
    workpiece_dir: str = ""
    workpiece_units: str = "mm"  # units of the user meshes
    # Where the fixture holds the part (the registration's window is around it);
    # empty: anywhere the scan shows it.
    nominal_pose: tuple[float, ...] = ()
    # TCP pose while the scanner looks at the part: the arm out of its view.
    scan_pose: tuple[float, ...] = (0.45, -0.35, 0.5, 1.5708, 0.0, 0.0)
    # SRM tip centre above the seam while tracking, m.
    tip_height: float = 0.004
    # The tool comes down onto the seam from this far above the tracking height, m.
    approach_height: float = 0.03
    # ... and leaves it this far up when the weld ends (or fails), m.
    retract_height: float = 0.05
    # Share of the motion limits used by the moves of a weld job.
    speed_scale: float = 0.5
    # The longest a weld may run before it is stopped, s.
    timeout: float = 600.0

    @classmethod
    def read(cls, r: TableReader) -> "WeldConfig":
        nominal = r.vector("nominal_pose", 6, list(cls.nominal_pose)) if r.has("nominal_pose") else ()
        return cls(
            workpiece=r.str("workpiece", cls.workpiece),
            workpiece_dir=r.str("workpiece_dir", cls.workpiece_dir),
            workpiece_units=r.str("workpiece_units", cls.workpiece_units, choices=("mm", "m")),
            nominal_pose=nominal,
            scan_pose=r.vector("scan_pose", 6, list(cls.scan_pose)),
            tip_height=r.float("tip_height_mm", cls.tip_height * 1e3, lo=0.0, hi=50.0, scale=1e-3),
            approach_height=r.float("approach_height_mm", cls.approach_height * 1e3, lo=1.0, hi=500.0, scale=1e-3),
            retract_height=r.float("retract_height_mm", cls.retract_height * 1e3, lo=1.0, hi=500.0, scale=1e-3),
            speed_scale=r.float("speed_scale", cls.speed_scale, lo=0.0, hi=1.0, open_lo=True),
            timeout=r.float("timeout_s", cls.timeout, lo=1.0, hi=36_000.0),
        )


@dataclass(frozen=True)
class SimConfig:
    """The simulated cell's truth: what the simulated devices show.

    Read only by the simulated devices (the scanner's scene, the SRM's wall);
    no estimator sees it. ``workpiece`` empty: the table is bare.
    """

    workpiece: str = ""
    # The part's true pose on the table (model frame in base), UR pose; empty:
    # the simulator's nominal place (celld.seam.simscene).
    workpiece_pose: tuple[float, ...] = ()
    # The true V-groove bows sideways by this much at mid-length (tack-weld
    # distortion) where its model is straight, m.
    workpiece_bow: float = 0.0

    @classmethod
    def read(cls, r: TableReader) -> "SimConfig":
        pose = r.vector("workpiece_pose", 6, []) if r.has("workpiece_pose") else ()
        return cls(
            workpiece=r.str("workpiece", cls.workpiece),
            workpiece_pose=pose,
            workpiece_bow=r.float("workpiece_bow_mm", 0.0, lo=-10.0, hi=10.0, scale=1e-3),
        )


@dataclass(frozen=True)
class Config:
    """The whole cell configuration; every section validated."""

    source: str = "<defaults>"
    cell: CellConfig = field(default_factory=CellConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    motion: MotionLimits = field(default_factory=MotionLimits)
    scanner: ScannerConfig = field(default_factory=ScannerConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    tactile: TactileConfig = field(default_factory=TactileConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    weld: WeldConfig = field(default_factory=WeldConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    # The seam finder's parameters (celld.seam.pipeline.SeamParams) when the
    # file has a [seam] table; None: the scanner's preset.
    seam: Any = None

    def T_base_cam_nominal(self) -> np.ndarray:
        return np.array(self.scanner.T_base_cam, dtype=np.float64)


_SECTIONS: dict[str, Callable[[TableReader], Any]] = {
    "cell": CellConfig.read,
    "robot": RobotConfig.read,
    "motion": MotionLimits.read,
    "scanner": ScannerConfig.read,
    "calibration": CalibrationConfig.read,
    "tactile": TactileConfig.read,
    "bus": BusConfig.read,
    "recording": RecordingConfig.read,
    "weld": WeldConfig.read,
    "sim": SimConfig.read,
}


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _read_toml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    source = str(path)
    if path in seen:
        raise ConfigError(source, "include", "include cycle: " + " -> ".join(str(p) for p in seen + (path,)))
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ConfigError(source, "", "file not found") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(source, "", f"cannot read: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(source, "", f"not valid TOML: {exc}") from exc
    includes = data.pop("include", [])
    if not isinstance(includes, list) or not all(isinstance(i, str) for i in includes):
        raise ConfigError(source, "include", f"expected a list of file paths, got {includes!r}")
    merged: dict[str, Any] = {}
    for inc in includes:
        merged = _merge(merged, _read_toml((path.parent / inc).resolve(), seen + (path,)))
    return _merge(merged, data)


def parse(data: dict[str, Any], source: str = "<dict>") -> Config:
    """Validate a TOML-shaped dict into a :class:`Config`."""
    top = TableReader(data, source)
    values: dict[str, Any] = {"source": source}
    for name, reader in _SECTIONS.items():
        sub = top.table(name)
        values[name] = reader(sub)
        sub.done()
    if top.has("seam"):
        from celld.seam.pipeline import SeamParams  # heavy (Open3D): only when asked for

        sub = top.table("seam")
        values["seam"] = SeamParams.read(sub, values["scanner"].model)
        sub.done()
    top.done()
    return Config(**values)


def load(path: str | Path) -> Config:
    """Load and validate a config file (and its includes).

    Raises
    ------
    ConfigError
        The file, the dotted key and the reason of the first problem found.
    """
    path = Path(path).resolve()
    return parse(_read_toml(path), str(path))


def section_names() -> list[str]:
    return [f.name for f in fields(Config) if f.name != "source"]
