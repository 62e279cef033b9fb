"""The cell config's sections other than the welding tool's and the seam finder's: one frozen dataclass each.

Each section reads its own TOML table through a
:class:`~celld.config.reader.TableReader` (types, ranges, unit suffixes
converted to SI) and refuses keys it does not know, including keys that were
renamed (the reader names the new key).
"""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from celld.config.reader import TableReader
from celld.errors import BusError
from celld.keychunk import check_prefix
from celld.robot.kinematics import MODELS as UR_MODELS

# A cell's workspace, poses and offsets lie within this of the robot base, m.
MAX_CELL_EXTENT = 5.0
# The TCP lies within this of the flange, m (a welding tool is a few tenths).
MAX_TCP_OFFSET = 1.0
# Kernel file systems: no place for a state directory.
_SYSTEM_DIRS = ("proc", "sys", "dev")
# A host name as RFC 1123 allows it: labels of letters, digits and '-'.
_HOSTNAME = re.compile(r"^(?=.{1,253}$)([A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")


def _host(r: TableReader, name: str, default: str) -> str:
    """An IP address or a host name (RFC 1123), else a ConfigError naming the key."""
    host = r.str(name, default)
    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        pass
    if _HOSTNAME.match(host) and not host.replace(".", "").isdigit():
        return host
    raise r.error(name, f"expected an IP address or a host name, got {host!r}")


def _tcp_offset(r: TableReader) -> tuple[float, ...]:
    value = r.vector("tcp_offset", 6, [0.0] * 6)
    if math.hypot(*value[:3]) > MAX_TCP_OFFSET:
        raise r.error("tcp_offset", f"expected the TCP within {MAX_TCP_OFFSET:g} m of the flange (metres), got {list(value[:3])}")
    if math.hypot(*value[3:]) > math.pi + 1e-6:
        raise r.error("tcp_offset", f"expected a rotation vector of at most pi rad, got {list(value[3:])}")
    return value


@dataclass(frozen=True)
class CellConfig:
    """Identity of the cell and where it keeps its state."""

    name: str = "cell"
    state_dir: str = "/var/lib/celld"
    # Below this much free space in state_dir new jobs are refused and queued
    # ones wait, MiB (0: no floor): a weld's recording and clouds take tens of MB.
    min_free_mb: float = 256.0
    # During a storage fault, how often the writes it owes are tried again, s.
    storage_retry_s: float = 5.0
    # The most the state directory may hold, MiB (0: no budget): after each job the oldest recordings,
    # datasets, job files and results go until it fits (celld.daemon.budget).
    storage_budget_mb: float = 0.0
    # Results are kept at least this long whatever the budget, days.
    result_retention_days: float = 30.0

    @classmethod
    def read(cls, r: TableReader) -> CellConfig:
        name = r.str("name", "cell")
        if not name or not all(c.isalnum() or c in "-_" for c in name):
            raise r.error("name", f"expected letters, digits, '-' or '_' (it is a zenoh key part), got {name!r}")
        state_dir = r.str("state_dir", "/var/lib/celld")
        if not state_dir.strip():
            raise r.error("state_dir", "expected a directory for the journal, results and recordings, got an empty path")
        parts = Path(state_dir).resolve().parts
        if len(parts) > 1 and parts[1] in _SYSTEM_DIRS:
            raise r.error("state_dir", f"expected a directory on a disk, got {state_dir!r} (under /{parts[1]}, a kernel file system)")
        return cls(
            name=name,
            state_dir=state_dir,
            min_free_mb=r.float("min_free_mb", cls.min_free_mb, lo=0.0, hi=1e7),
            storage_retry_s=r.float("storage_retry_s", cls.storage_retry_s, lo=0.1, hi=600.0),
            storage_budget_mb=r.float("storage_budget_mb", cls.storage_budget_mb, lo=0.0, hi=1e9),
            result_retention_days=r.float("result_retention_days", cls.result_retention_days, lo=0.0, hi=36500.0),
        )


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
    def read(cls, r: TableReader) -> RobotConfig:
        r.refuse_moved({"connect_timeout": "robot.connect_timeout_s (seconds)"})
        reach = " m (no cell is larger)"
        wmin: tuple[float, ...] = r.vector("workspace_min", 3, list(cls.workspace_min), bound=MAX_CELL_EXTENT, what=reach)
        wmax: tuple[float, ...] = r.vector("workspace_max", 3, list(cls.workspace_max), bound=MAX_CELL_EXTENT, what=reach)
        if not all(a < b for a, b in zip(wmin, wmax)):
            raise r.error("workspace_max", f"expected every value above workspace_min {wmin}, got {wmax}")
        return cls(
            model=r.str("model", "ur10e", choices=tuple(UR_MODELS)),
            host=_host(r, "host", "127.0.0.1"),
            frequency_hz=r.float("frequency_hz", 500.0, lo=1.0, hi=500.0),
            connect_timeout=r.float("connect_timeout_s", 10.0, lo=0.1, hi=120.0),
            workspace_min=wmin,  # type: ignore[arg-type]
            workspace_max=wmax,  # type: ignore[arg-type]
            tcp_offset=_tcp_offset(r),
            home_q=r.vector("home_q", 6, list(cls.home_q), bound=2 * math.pi, what=" rad (a UR joint turns +-360 deg)"),
            arc_output=r.int("arc_output", cls.arc_output, lo=-1, hi=7),
        )


@dataclass(frozen=True)
class Robot2Config:
    """A second robot in view of the cell's scanner, calibrated to robot 1 through it (Eq. 5-6).

    It has its own link (``robot``: host, model, workspace box in its own
    base frame, ``home_q``) and no welding tool or arc: a calibrate job with
    ``robot2`` set calibrates the scanner to both robots and gives
    ``T_base1_base2`` (:mod:`celld.calib.comanip`). While one robot works the
    other waits at its ``home_q``, which must keep its flange out of the
    scanner's view and clear of the other arm (celld does not check arm
    against arm).

    Attributes
    ----------
    robot : RobotConfig
        Its link, in the keys of ``[robot]`` (``arc_output`` -1, ``tcp_offset`` zero).
    base_pose : tuple of 6 float
        Its base in robot 1's base frame as drawn (UR pose, m and rad): places
        the cell model for its moves and is compared with the calibration.
    flange : str
        Its flange model; "" for ``calibration.flange``.
    verification_pose : tuple of 6 float
        Its calibration's verification pose, its own base frame (UR pose).
    """

    robot: RobotConfig
    base_pose: tuple[float, ...]
    flange: str = ""
    verification_pose: tuple[float, ...] = (0.6, 0.0, 0.45, 0.0, 0.0, 0.0)

    @classmethod
    def read(cls, r: TableReader) -> Robot2Config:
        if not r.has("base_pose"):
            raise r.error("base_pose", "give the second robot's base in robot 1's base frame as drawn (UR pose, m and rad)")
        base_pose = r.vector("base_pose", 6, bound=MAX_CELL_EXTENT, what=" m (no cell is larger)")
        flange = r.str("flange", "")
        verification_pose = r.vector("verification_pose", 6, list(cls.verification_pose))
        robot = RobotConfig.read(r)
        if robot.arc_output != -1:
            raise r.error("arc_output", "the second robot carries no welding tool: leave arc_output out")
        if any(abs(v) > 0.0 for v in robot.tcp_offset):
            raise r.error("tcp_offset", "the second robot is calibrated by its flange: its tcp_offset must be zero")
        lo, hi = robot.workspace_min, robot.workspace_max
        if not all(lo[i] <= verification_pose[i] <= hi[i] for i in range(3)):
            raise r.error(
                "verification_pose",
                f"expected a position inside its workspace box {list(lo)} .. {list(hi)} m, got {list(verification_pose[:3])}",
            )
        return cls(robot=robot, base_pose=base_pose, flange=flange, verification_pose=verification_pose)


# motion.hang_stop's ceiling, s: the arc off within 0.3 s of a frozen daemon (its 20 ms beat, the loop's
# 10 ms look and two cycles inside it).
HANG_STOP_MAX = 0.27


@dataclass(frozen=True)
class MotionLimits:
    """The limits every command obeys in every cycle (SI): Cartesian for the TCP, per joint for joint moves."""

    max_linear_speed: float = 0.25  # m/s
    max_linear_accel: float = 1.0  # m/s^2
    max_linear_jerk: float = 10.0  # m/s^3
    max_angular_speed: float = 1.0  # rad/s
    max_angular_accel: float = 4.0  # rad/s^2
    max_angular_jerk: float = 40.0  # rad/s^3
    # Every joint in a joint move (the move is also slowed so the TCP keeps
    # the Cartesian limits above). UR's own movej defaults: 1.05 rad/s, 1.4 rad/s^2.
    max_joint_speed: float = 1.0  # rad/s
    max_joint_accel: float = 2.0  # rad/s^2
    max_joint_jerk: float = 20.0  # rad/s^3
    # A tactile sample older than this stops a servo, seconds.
    tactile_stale: float = 0.1
    # Robot state older than this many cycles stops the loop.
    state_stale_cycles: int = 3
    # Without fresh robot state for this long the link counts as lost, s.
    link_timeout: float = 0.1
    # RTDE watchdog: the controller stops its program after 1/rate s without a kick.
    rtde_watchdog_hz: float = 10.0
    # The motion and camera processes stop the robot and end when the daemon's
    # heartbeat is older than this (the daemon hangs), s; a dead daemon is seen
    # at once. Above the event loop's worst hold-ups (a scan holding the GIL on a
    # loaded PC: about 1 s measured) and above systemd's WatchdogSec.
    parent_timeout: float = 3.0
    # While the arm moves or the arc is on, the motion process stops them both once the heartbeat is this
    # old, s (a daemon stopped by a signal or a debugger at once, by its /proc state): a hung daemon can
    # cancel nothing. The heartbeat beats every 20 ms from a thread that stands still only when the whole
    # process does or its event loop has not run for a second; the loop looks every 10 ms: the arc is off
    # within 0.3 s of a freeze.
    hang_stop: float = 0.25
    # ur-rtde's receive threads, after the watchdog handshake (which they run at SCHED_FIFO, below the
    # loop): best effort at this niceness. They poll (about a fifth of a core each, idle or not) and every
    # command waits on the state they take in; -10 keeps them ahead of a cell PC's other work. The
    # simulated cell, whose controller and scanner share two cores with them, runs them at 0.
    link_nice: int = -10

    @classmethod
    def read(cls, r: TableReader) -> MotionLimits:
        return cls(
            max_linear_speed=r.float("max_linear_speed", cls.max_linear_speed, lo=0.0, hi=1.0, open_lo=True),
            max_linear_accel=r.float("max_linear_accel", cls.max_linear_accel, lo=0.0, hi=10.0, open_lo=True),
            max_linear_jerk=r.float("max_linear_jerk", cls.max_linear_jerk, lo=0.0, hi=1000.0, open_lo=True),
            max_angular_speed=r.float("max_angular_speed", cls.max_angular_speed, lo=0.0, hi=3.14, open_lo=True),
            max_angular_accel=r.float("max_angular_accel", cls.max_angular_accel, lo=0.0, hi=40.0, open_lo=True),
            max_angular_jerk=r.float("max_angular_jerk", cls.max_angular_jerk, lo=0.0, hi=4000.0, open_lo=True),
            max_joint_speed=r.float("max_joint_speed", cls.max_joint_speed, lo=0.0, hi=3.14, open_lo=True),
            max_joint_accel=r.float("max_joint_accel", cls.max_joint_accel, lo=0.0, hi=40.0, open_lo=True),
            max_joint_jerk=r.float("max_joint_jerk", cls.max_joint_jerk, lo=0.0, hi=4000.0, open_lo=True),
            tactile_stale=r.float("tactile_stale_ms", cls.tactile_stale * 1e3, lo=1.0, hi=5000.0, scale=1e-3),
            state_stale_cycles=r.int("state_stale_cycles", cls.state_stale_cycles, lo=1, hi=50),
            link_timeout=r.float("link_timeout_ms", cls.link_timeout * 1e3, lo=4.0, hi=5000.0, scale=1e-3),
            rtde_watchdog_hz=r.float("rtde_watchdog_hz", cls.rtde_watchdog_hz, lo=1.0, hi=500.0),
            parent_timeout=r.float("parent_timeout_ms", cls.parent_timeout * 1e3, lo=HANG_STOP_MAX * 1e3, hi=5000.0, scale=1e-3),
            hang_stop=r.float("hang_stop_ms", cls.hang_stop * 1e3, lo=60.0, hi=HANG_STOP_MAX * 1e3, scale=1e-3),
            link_nice=r.int("link_nice", cls.link_nice, lo=-20, hi=19),
        )


SCANNER_KINDS = ("sim", "replay", "phoxi", "azure-kinect", "realsense")
SCANNER_MODELS = ("phoxi-s", "phoxi-m", "azure-kinect")
# Where a scanner can be fixed: in the base frame, or on the frame after joint 1, 2 or 3 (celld.calib.mount).
SCANNER_MOUNTS = ("base", "link1", "link2", "link3")
# calibration.range_bias: estimate the range bias on metal with T_base_cam, or not.
RANGE_BIAS_MODES = ("estimate", "none")
# Scanners that read bare metal long (time of flight, and the RealSense
# family, whose L515 is a lidar): the range bias is estimated unless the config says "none".
_BIASED_KINDS = ("azure-kinect", "realsense")
_BIASED_MODELS = ("azure-kinect",)


def range_bias_default(kind: str, model: str) -> str:
    """``calibration.range_bias`` when the config does not set it: ``estimate`` for a time-of-flight scanner, else ``none``.

    ``kind`` and ``model`` are the scanner's (``scanner.kind``, ``scanner.model``);
    a simulated or replayed scanner goes by its model.
    """
    return "estimate" if kind in _BIASED_KINDS or model in _BIASED_MODELS else "none"


@dataclass(frozen=True)
class ScannerConfig:
    """The 3D scanner above the table."""

    kind: str = "sim"
    model: str = "phoxi-m"
    # Where the scanner is fixed: "base" (over the cell, eye-on-base) or on the
    # arm after joint 1, 2 or 3 ("link1", "link2", "link3": eye-on-arm, Eq. 8;
    # celld.calib.mount). A calibration is made for one mount and used only with it.
    mount: str = "base"
    # Nominal pose of the camera in the base frame, as the cell was drawn (the
    # offline seam tools place a scan with it). celld never reads it as an
    # estimate: calibration starts without it. A simulated scanner is placed
    # by the simulator's own [sim.scanner], not by this.
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
    def read(cls, r: TableReader) -> ScannerConfig:
        r.refuse_moved(
            {
                "capture_timeout": "scanner.capture_timeout_s (seconds)",
                "seed": "[sim.scanner] seed (the simulated scanner belongs to the simulator's world)",
                "resolution_scale": "[sim.scanner] resolution_scale (the simulated scanner belongs to the simulator's world)",
            }
        )
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
            mount=r.str("mount", cls.mount, choices=SCANNER_MOUNTS),
            T_base_cam=r.matrix4("T_base_cam", [list(row) for row in cls.T_base_cam]),
            replay_dir=r.str("replay_dir", ""),
            replay_units=r.str("replay_units", cls.replay_units, choices=("m", "mm")),
            replay_loop=r.bool("replay_loop", cls.replay_loop),
            device=r.str("device", ""),
            gentl_producer=r.str("gentl_producer", ""),
            capture_timeout=r.float("capture_timeout_s", cls.capture_timeout, lo=0.1, hi=600.0),
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
    compensate: bool = False  # store Eq. 21's compensated estimate as the calibration
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
    # The scanner's range bias on bare metal: "estimate" it with T_base_cam
    # (time of flight) or "none" (structured light). None until the config is
    # parsed: it then takes the scanner's default (range_bias_default).
    range_bias: str | None = None
    # Verification of the current calibration (celld.calib.verify): before the first weld after a start or
    # after the calibration changed, then every verify_interval (s; 0: only then), at verify_poses poses.
    # The bound is the calibration's own plus the measured repeatability, or verify_bound (m) when > 0.
    # verify_before_weld = false leaves it to verify jobs (a cell that verifies by a procedure of its own).
    verify_before_weld: bool = True
    verify_interval: float = 8 * 3600.0
    verify_poses: int = 3
    verify_bound: float = 0.0
    # The arm's own error away from the calibration poses, m: a hand-eye calibration cannot see it (the fit
    # absorbs it where the pairs are), so the bound the calibration reports away from its poses carries it
    # (celld.calib.quality). The prior of the arm's class: a real industrial arm calibrated hand-eye only
    # from a 3-D scanner misses by 0.81 mm mean, 1.04 mm max (Sensors 2025, 25(15):4661).
    arm_error_prior: float = 1.0e-3
    # The robust estimator's and the gate's outlier threshold never go below this, m (celld.calib.quality
    # OUTLIER_FLOOR, which says why: an arm's error is never an outlier, a false detection lies millimetres off).
    outlier_floor: float = 1.0e-3
    # The arm's kinematic calibration after the hand-eye one (celld.calib.kinematic): this many wide poses
    # (0: none, the hand-eye calibration alone). 80 took the weld site's error over the table from
    # 0.69 to 0.33 mm mean in the simulated cell's realistic worlds (bench/arm_calibration.py).
    arm_poses: int = 0

    @classmethod
    def read(cls, r: TableReader) -> CalibrationConfig:
        r.refuse_moved({"settle": "calibration.settle_s (seconds)"})
        return cls(
            flange=r.str("flange", cls.flange),
            e_required=r.float("e_required_mm", cls.e_required * 1e3, lo=0.0, hi=100.0, scale=1e-3),
            k_max=r.int("k_max", cls.k_max, lo=1, hi=10_000),
            n_poses=r.int("n_poses", cls.n_poses, lo=4, hi=1000),
            cost=r.str("cost", cls.cost, choices=("translation", "se3")),
            work_radius=r.float("work_radius", cls.work_radius, lo=0.0, hi=10.0, open_lo=True),
            settle=r.float("settle_s", cls.settle, lo=0.0, hi=10.0),
            auto_accept=r.bool("auto_accept", False),
            pose_box=r.vector("pose_box", 3, list(cls.pose_box)),  # type: ignore[arg-type]
            max_tilt=r.float("max_tilt_deg", math.degrees(cls.max_tilt), lo=0.0, hi=60.0, scale=math.pi / 180),
            verification_pose=r.vector("verification_pose", 6, list(cls.verification_pose)),
            method=r.str("method", cls.method, choices=("robust", "svd", "algorithm1")),
            compensate=r.bool("compensate", False),
            icp_max_distance=r.float("icp_max_distance_mm", cls.icp_max_distance * 1e3, lo=0.0, hi=100.0, scale=1e-3, open_lo=True),
            icp_points=r.int("icp_points", cls.icp_points, lo=10, hi=1_000_000),
            model_spacing=r.float("model_spacing_mm", cls.model_spacing * 1e3, lo=0.1, hi=10.0, scale=1e-3),
            keep_sessions=r.int("keep_sessions", cls.keep_sessions, lo=0, hi=100_000),
            keep_days=r.float("keep_days", cls.keep_days, lo=0.0, hi=36_500.0),
            range_bias=r.str("range_bias", choices=RANGE_BIAS_MODES) if r.has("range_bias") else None,
            verify_before_weld=r.bool("verify_before_weld", True),
            verify_interval=r.float("verify_interval_h", cls.verify_interval / 3600.0, lo=0.0, hi=24.0 * 366, scale=3600.0),
            verify_poses=r.int("verify_poses", cls.verify_poses, lo=2, hi=10),
            verify_bound=r.float("verify_bound_mm", 0.0, lo=0.0, hi=100.0, scale=1e-3),
            arm_error_prior=r.float("arm_error_prior_mm", cls.arm_error_prior * 1e3, lo=0.0, hi=50.0, scale=1e-3),
            outlier_floor=r.float("outlier_floor_mm", cls.outlier_floor * 1e3, lo=0.0, hi=50.0, scale=1e-3, open_lo=True),
            arm_poses=r.int("arm_poses", cls.arm_poses, lo=0, hi=1000),
        )


@dataclass(frozen=True)
class BusUser:
    """A user the bus accepts (zenoh user/password authentication) and its role.

    Roles (:mod:`celld.bus.security`): *viewer* reads the cell's status, job
    records without their parameters and references, the calibration;
    *operator* also submits, accepts, and cancels its own jobs; *supervisor*
    also cancels any job and sees every job in full. ``job_details`` lets a
    viewer or operator see other users' jobs in full and read their results.
    """

    name: str
    password: str = field(repr=False)
    role: str
    job_details: bool = False


BUS_ROLES = ("viewer", "operator", "supervisor")
# A user name is one zenoh key chunk: its requests go to <prefix>/<cell>/u/<name>/...
_USER_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclass(frozen=True)
class BusTls:
    """zenoh's TLS transport, for ``tls/host:port`` endpoints: PEM files (see :mod:`celld.bus.session`).

    The cell listens with ``listen_certificate`` and ``listen_private_key``
    (the certificate must name the address clients connect to: an IP SAN for
    ``tls/192.0.2.10:7447``). A client verifies it against
    ``root_ca_certificate``. With ``mutual`` both sides present a certificate:
    the cell accepts only clients whose ``connect_certificate`` the same CA
    signed.
    """

    root_ca_certificate: str = ""
    listen_certificate: str = ""
    listen_private_key: str = ""
    mutual: bool = False
    connect_certificate: str = ""
    connect_private_key: str = ""
    # A client checks that the cell's certificate names the host it connects to.
    verify_name_on_connect: bool = True

    @classmethod
    def read(cls, r: TableReader) -> BusTls:
        tls = cls(
            root_ca_certificate=r.str("root_ca_certificate", ""),
            listen_certificate=r.str("listen_certificate", ""),
            listen_private_key=r.str("listen_private_key", ""),
            mutual=r.bool("mutual", False),
            connect_certificate=r.str("connect_certificate", ""),
            connect_private_key=r.str("connect_private_key", ""),
            verify_name_on_connect=r.bool("verify_name_on_connect", True),
        )
        for a, b in (("listen_certificate", "listen_private_key"), ("connect_certificate", "connect_private_key")):
            if bool(getattr(tls, a)) != bool(getattr(tls, b)):
                raise r.error(b if getattr(tls, a) else a, f"expected {a} and {b} together, or neither")
        if tls.mutual and not tls.root_ca_certificate:
            raise r.error("root_ca_certificate", "mutual TLS needs the CA that signs the clients' certificates")
        return tls

    def paths(self) -> dict[str, str]:
        """The configured files by key."""
        keys = ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate", "connect_private_key")
        return {k: getattr(self, k) for k in keys if getattr(self, k)}


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
    password: str = field(default="", repr=False)
    # [bus.tls]: certificates for tls/ endpoints; None: no TLS.
    tls: BusTls | None = None
    # Multicast and gossip scouting: off keeps a loopback bus to the configured endpoints.
    multicast_scouting: bool = False
    # How long a client waits for a link to the cell, and for a reply, s.
    connect_timeout: float = 3.0
    query_timeout: float = 5.0

    @classmethod
    def read(cls, r: TableReader) -> BusConfig:
        r.refuse_moved({"connect_timeout": "bus.connect_timeout_s (seconds)", "query_timeout": "bus.query_timeout_s (seconds)"})
        listen = r._get("listen", list(cls.listen))
        connect = r._get("connect", list(cls.connect))
        for key, value in (("listen", listen), ("connect", connect)):
            if not isinstance(value, list) or not all(isinstance(v, str) and "/" in v for v in value):
                raise r.error(key, f'expected a list of zenoh endpoints such as "tcp/127.0.0.1:7447", got {value!r}')
        users_raw = r._get("users", [])
        if not isinstance(users_raw, list):
            raise r.error("users", "expected an array of tables [[bus.users]]")
        users: list[BusUser] = []
        for i, u in enumerate(users_raw):
            ur = TableReader(u, r.source, r.key(f"users[{i}]"))
            user = BusUser(ur.str("name"), ur.str("password"), ur.str("role", choices=BUS_ROLES), ur.bool("job_details", False))
            if not _USER_NAME.match(user.name):
                raise ur.error("name", f"expected letters, digits, '_', '.' or '-' (a zenoh key chunk), got {user.name!r}")
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
        own_user, password = r.str("user", ""), r.str("password", "")
        if bool(own_user) != bool(password):
            raise r.error("password" if own_user else "user", "expected user and password together, or neither")
        if own_user and not _USER_NAME.match(own_user):
            raise r.error("user", f"expected letters, digits, '_', '.' or '-' (a zenoh key chunk), got {own_user!r}")
        mode = r.str("mode", cls.mode, choices=("peer", "client", "router"))
        tls = None
        if r.has("tls"):
            tr = r.table("tls")
            tls = BusTls.read(tr)
            tr.done()
        tls_listen = [e for e in listen if e.startswith("tls/")] if mode != "client" else []
        if tls_listen and (tls is None or not tls.listen_certificate):
            raise r.error("tls", f"listen endpoints {tls_listen} need bus.tls.listen_certificate and listen_private_key")
        return cls(
            mode=mode,
            listen=tuple(listen),
            connect=tuple(connect),
            prefix=prefix,
            state_rate_hz=r.float("state_rate_hz", cls.state_rate_hz, lo=0.1, hi=500.0),
            users=tuple(users),
            user=own_user,
            password=password,
            multicast_scouting=r.bool("multicast_scouting", False),
            connect_timeout=r.float("connect_timeout_s", cls.connect_timeout, lo=0.05, hi=120.0),
            query_timeout=r.float("query_timeout_s", cls.query_timeout, lo=0.05, hi=600.0),
            tls=tls,
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
    def read(cls, r: TableReader) -> RecordingConfig:
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


# weld.retract_after_fault: what the arm may do by itself after a fault stopped a weld.
RETRACTS_AFTER_FAULT = ("none", "clear", "full")


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
    # What the arm does by itself after a fault stopped a weld: "none" (it stays where it stopped), "clear"
    # (straight out of the joint by retract_height, slowly) or "full" (that, then back to the scan pose).
    # Never after a protective stop or with the robot link down.
    retract_after_fault: str = "clear"
    # Share of the motion limits used by the moves of a weld job.
    speed_scale: float = 0.5
    # The longest a weld may run before it is stopped, s.
    timeout: float = 600.0
    # Before tracking, the finger touches both walls of a groove whose walls open upwards (a V): the
    # joint's width there gives the tip's height in it, and the plan moves to the height it should have.
    probe_height: bool = True
    # A probed height further than this off the plan's is refused (the calibration or the tool is off), m.
    max_height_correction: float = 0.002
    # The weld procedure a cell with a [power_source] welds with when a job names none ("": a job must name one),
    # a file <name>.toml in procedures_dir ("": procedures/ beside the config file).
    procedure: str = ""
    procedures_dir: str = ""

    @classmethod
    def read(cls, r: TableReader) -> WeldConfig:
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
            retract_after_fault=r.str("retract_after_fault", cls.retract_after_fault, choices=RETRACTS_AFTER_FAULT),
            speed_scale=r.float("speed_scale", cls.speed_scale, lo=0.0, hi=1.0, open_lo=True),
            timeout=r.float("timeout_s", cls.timeout, lo=1.0, hi=36_000.0),
            probe_height=r.bool("probe_height", cls.probe_height),
            max_height_correction=r.float(
                "max_height_correction_mm", cls.max_height_correction * 1e3, lo=0.0, hi=20.0, open_lo=True, scale=1e-3
            ),
            procedure=r.str("procedure", cls.procedure),
            procedures_dir=r.str("procedures_dir", cls.procedures_dir),
        )
