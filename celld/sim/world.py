"""The simulated cell's world: the nominal cell, the error budget, and the true cell drawn from them (pure).

The controller and the simulator must not share their geometry, or the
simulated cell measures nothing but detector noise. So the simulator owns
its world:

- :class:`NominalCell` is the cell as it was drawn, read from the cell
  config's ``[sim]`` table (never from the controller's sections): the robot
  model, the scanner and where it is mounted, the flange, the welding tool,
  the part and where it lies;
- :class:`ErrorBudget` says how a real cell differs from its drawing, one
  switchable error source at a time (:data:`SOURCES`), each with a
  datasheet-sized default (the comment beside it says where the number comes
  from, or that it is a plausible choice);
- :func:`draw_world` draws a :class:`World` from (nominal cell, budget,
  seed): the true robot kinematics and its noise, the scanner's true pose,
  scale and distortion, the flange as made, the tool as built, the finger's
  mechanics and how its tag follows its tip, the part as placed and as distorted, the timing of captures.
  Each source draws from its own generator (seeded by the world's seed and
  the source's name), so switching one source on or off changes nothing else.

Two presets: :data:`PRESETS` ``"ideal"`` (every source off: the true cell is
its drawing, the world the simulated cell had before it owned one) and
``"realistic"`` (every source on). The ``[sim]`` table::

    [sim]
    preset = "realistic"      # ideal | realistic (default ideal)
    seed = 0                  # the world's seed
    robot = "ur10e"           # the arm's model (its nominal DH table)
    flange = "ur10e"          # the flange preset on the wrist, as drawn
    [sim.scanner]             # model, mount (base | link1-3), T_base_cam or T_link_cam (as mounted by drawing),
                              # resolution_scale, roi_px (a window of the image: only it is cast), seed (noise)
    [sim.tool]                # the welding tool as drawn, flange frame: the keys of [tool]
    [sim.part]                # workpiece ("" for none), pose (UR pose; default the nominal place), bow_mm
    [sim.srm]                 # the SRM camera as drawn: intrinsics_px, width_px, height_px, tag_dictionary,
                              # tag_id, tag_size_mm (its mount is [sim.tool] T_tool_cam)
    [sim.errors]              # <source> = true|false, and magnitudes (ERROR_KEYS) over the preset's
    [sim.power_source]        # the welding power source's rates, ranges and forced schedules over the
                              # preset's (celld.sim.power_source)

Who reads what: the simulated robot process gets :attr:`World.arm`
(:class:`~celld.sim.robot.truearm.ArmTruth`, through its options) and, in a
cell with a ``[power_source]``, :attr:`World.power_source`, the
simulated scanner :attr:`World.scanner` and :attr:`World.flange`, the SRM
camera :attr:`World.srm`, :attr:`World.tool`, :attr:`World.finger` and :attr:`World.camera`,
the part builder (:mod:`celld.sim.workpiece`) :attr:`World.part`; the demo
and the benchmarks score against all of it after the jobs end. The daemon
never sees any of it.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from celld import se3
from celld.calib.flange import FlangeModel
from celld.calib.flange import preset as flange_preset
from celld.config import SCANNER_MOUNTS, ToolConfig
from celld.config.reader import TableReader
from celld.errors import ConfigError, InputError
from celld.robot import dynamics
from celld.robot import kinematics as kin
from celld.sim.power_source import SOURCE_PRESETS, SourceBudget, draw_source, read_source_budget
from celld.sim.robot.source import SourceTruth
from celld.sim.robot.truearm import ArmTruth
from celld.sim.srm import SrmCamera

Array = NDArray[np.float64]

# The error sources, grouped as the issue lists them. Each is switched on or off on its own.
SOURCES: tuple[str, ...] = (
    # robot
    "factory_calibration",  # the controller computes with its own calibrated table, not the published one
    "kinematics",  # true DH table and joint zeros beyond the controller's: pose-dependent absolute error
    "repeatability",  # a new rest error at every stop
    "encoder_noise",  # noise on the joints the controller reports
    "robot2_placement",  # a second robot's base is not exactly where the drawing puts it
    "compliance",  # the joints yield under gravity (the true links and tool): a pose-dependent sag
    "hose_pull",  # the hose package pulls on the torch; the joints yield to it
    "thermal",  # the links grow as the arm warms up
    "lost_motion",  # each joint rests behind where it was sent, on the side it came from
    # time
    "settle",  # the arm rings down after a stop
    "capture_delay",  # the scanner exposes a while after the state was read
    "camera_jitter",  # the SRM camera's stamps and delivery are not exact
    # scanner
    "scanner_mount",  # the scanner is not exactly where the drawing puts it
    "depth_scale",  # a depth scale error
    "distortion",  # a smooth distortion over the measuring volume
    "metal_bias",  # time of flight: the range bias on metal varies per unit
    # flange
    "flange_tolerance",  # diameters and thickness within their ISO fits
    "flange_variant",  # the real part's chamfer, bore and hole depths
    # tool
    "tool_offsets",  # the SRM tip and the torch are not where the tool config says
    "finger",  # the finger's stiffening, hysteresis and stick-slip
    "tag_map",  # the tag inside the finger moves less than the tip, per axis, and less still as the finger bends
    "srm_camera",  # the SRM camera's intrinsics and mount, and the tag's printed size, are not what the controller was told
    # part
    "part_placement",  # the part lies off its place by centimetres and degrees
    "part_shape",  # bow, twist, tack-weld kinks, root-gap variation
)

PRESET_NAMES = ("ideal", "realistic")

# Gaussian draws are cut at this many sigma: a budget's "up to" is this times its sigma.
TRUNCATE = 2.5


@dataclass(frozen=True)
class ErrorBudget:
    """How a real cell differs from its drawing: the sources switched on and their sizes (SI, rad).

    A magnitude matters only while its source is in :attr:`enabled`. Sigmas
    are 1 sigma of a Gaussian cut at :data:`TRUNCATE` sigma; pairs are the
    ends of a uniform range.
    """

    enabled: frozenset[str] = frozenset(SOURCES)

    # -- robot -----------------------------------------------------------------
    # The factory calibration: the controller's table against the published
    # one, each length d_i, a_i, twist alpha_i and joint zero theta_i, 1 sigma.
    # The published table then puts the flange 1-5 mm from where the controller
    # does (3 mm on average over the workspace and 20 seeds,
    # tests/sim/test_world.py): the low end of the UR ROS driver's calibration
    # notes, which say end-effector positions "might be off in the magnitude of
    # centimeters" without it. Plausible; no published spread of the deltas.
    factory_length: float = 1.0e-3  # m
    factory_twist: float = 1.0e-3  # rad
    factory_joint_zero: float = 1.5e-3  # rad
    # Each DH length d_i, a_i, twist alpha_i and joint zero, 1 sigma, beyond the
    # factory calibration (what remains of the arm's error with it). Sized so
    # the flange's absolute position error over the workspace is the 0.3-1 mm
    # of a factory-calibrated UR e-series arm (mean about 0.5 mm on the UR10e;
    # tests/sim/test_world.py measures it). UR publishes no accuracy figure,
    # only repeatability; plausible.
    dh_length: float = 0.15e-3  # m
    dh_twist: float = 0.15e-3  # rad
    joint_offset: float = 0.15e-3  # rad
    # Rest error per joint at each stop, 1 sigma: gives an ISO 9283 pose
    # repeatability (mean + 3 sigma of the spread) near the UR10e datasheet's
    # +-0.05 mm at the flange.
    repeatability: float = 1.0e-5  # rad
    # Noise on the reported joints, 1 sigma; plausible (UR's absolute encoders
    # resolve about 1e-6 rad; the reading jitters by a few of those).
    encoder_noise: float = 2.0e-6  # rad
    # A second robot's base against its drawing, 1 sigma per axis: a base
    # bolted to a floor plate or pedestal, placed by tape and square.
    # Plausible; robot-robot calibration exists because it is not known.
    base_translation: float = 3.0e-3  # m
    base_rotation: float = math.radians(0.3)  # rad
    # Joint stiffness (N m/rad, uniform per joint) of the base and shoulder,
    # the elbow, and the wrists. Sized so the sag under gravity at weld poses
    # (flange down over the table, a 1.6 kg tool) is the 0.2-0.7 mm a study of
    # this cell's arm assumed (../research: arm and weld process);
    # tests/sim/test_world.py measures it. Harmonic drives of these sizes are
    # rated in this range; plausible.
    stiffness_shoulder: tuple[float, float] = (1.2e5, 2.0e5)
    stiffness_elbow: tuple[float, float] = (6.0e4, 1.0e5)
    stiffness_wrist: tuple[float, float] = (1.5e4, 3.0e4)
    # The true links' masses against UR's published ones, and the true tool's
    # mass against its config (relative, 1 sigma), its centre of mass off (m, 1
    # sigma per axis). Plausible: a published mass is a model's, a tool's is weighed.
    link_mass_spread: float = 0.05
    payload_mass_spread: float = 0.10
    payload_com_offset: float = 10.0e-3
    # The hose package's pull on the torch, uniform in size (N), downwards
    # and towards the robot's base within 45 degrees. Plausible for a MIG hose
    # package hung from a boom (a few kg of cable and hose, mostly carried).
    hose_force: tuple[float, float] = (5.0, 20.0)
    # The arm's temperature rise from cold to warm (K, uniform) and the time
    # constant of its warm-up (s): aluminium links (23 um/m/K) over the arm's
    # ~1.3 m give the 0.1-0.3 mm research notes cite for 5-10 K; the weld sits
    # nearer the base, and 8-15 K (joints warm from their motors) gives 0.1-0.25 mm there.
    warm_rise: tuple[float, float] = (8.0, 15.0)
    warmup_tau: float = 1800.0
    # Each joint's lost motion, full width (rad, uniform): with the ISO 9283
    # repeatability near the datasheet's +-0.05 mm (approach from one side),
    # a few arc seconds. Plausible.
    lost_motion: tuple[float, float] = (1.0e-5, 3.0e-5)

    # -- time ------------------------------------------------------------------
    # Settling after a stop: kick per joint (1 sigma; about 0.05 mm at a 1 m
    # lever), decay time and frequency of a UR10e's wrist ringing down. Plausible.
    settle_amplitude: float = 5.0e-5  # rad
    settle_tau: float = 0.08  # s
    settle_hz: float = 8.0  # Hz
    # Delay from the capture request (the daemon has just read the robot's
    # state) to the middle of the exposure, uniform. A PhoXi M scan takes
    # 0.25-2.75 s by its datasheet; the middle of the fastest is 0.1-0.3 s in.
    capture_delay: tuple[float, float] = (0.05, 0.3)  # s
    # SRM camera: error of a frame's capture stamp (1 sigma), and extra
    # delivery latency (uniform from 0). Plausible for a USB camera stamped by
    # its driver.
    camera_stamp_sigma: float = 0.5e-3  # s
    camera_delivery_jitter: float = 4.0e-3  # s

    # -- scanner ---------------------------------------------------------------
    # The scanner's mount against its drawing, 1 sigma per axis; plausible for
    # a bracket on a frame 1 m above the table (calibration does not use it).
    mount_translation: float = 5.0e-3  # m
    mount_rotation: float = math.radians(0.5)  # rad
    # Depth scale error, 1 sigma, and the smooth distortion field's RMS over
    # the measuring volume, for a scanner of the PhoXi M's class (datasheet:
    # calibration accuracy 0.1 mm, 1 sigma); scaled by each model's noise sigma
    # against the PhoXi M's 0.1 mm (a ToF camera's field is mm).
    depth_scale: float = 5.0e-5  # relative
    distortion: float = 0.1e-3  # m, RMS
    # Time of flight only: the unit's range bias on metal about the model's
    # (8 mm; users report 8-15 mm), 1 sigma. Plausible.
    metal_bias: float = 3.0e-3  # m

    # -- flange (ISO 9409-1 fits: d2 h8, d3 H7; the rest plausible) -------------
    # Chamfer leg of the face's outer edge (the drawing's 0.5 mm is not in the
    # standard; a real part's edge break is anywhere here) and the spread of
    # the bore and hole depths (a real CAD model's, not the preset's).
    chamfer: tuple[float, float] = (0.3e-3, 1.0e-3)  # m
    bore_depth: float = 0.5e-3  # m, uniform +-
    hole_depth: float = 1.0e-3  # m, uniform +-

    # -- tool ------------------------------------------------------------------
    # The SRM tip and the torch point against the tool config, 1 sigma per
    # axis (cut at 1.5 mm: the "by up to 1-2 mm"), and the finger's
    # axes (cut at 1 degree). Plausible for a hand-assembled welding tool.
    tip_offset: float = 0.6e-3  # m
    torch_offset: float = 0.6e-3  # m
    tool_rotation: float = math.radians(0.4)  # rad
    # The SRM tip's radius against its drawing, 1 sigma: a printed or turned
    # ball of 2 mm held to a few hundredths. Plausible.
    tip_radius: float = 0.02e-3  # m
    # The SRM camera as built against the values the controller was given
    # ([tactile]), 1 sigma: the focal lengths (relative) and the principal
    # point, what a checkerboard calibration of a small 640 x 480 camera
    # leaves (Zhang's method: a few tenths of a percent and a few pixels;
    # plausible); the tag's printed side (relative: a laser print's scale or a
    # laser-marked tag's tolerance, plausible); the camera's mount in the tool
    # frame (per axis), a camera pressed into the finger's base. Plausible.
    srm_focal: float = 0.005  # relative
    srm_principal_point: float = 2.0  # px
    tag_print: float = 0.0025  # relative
    srm_mount_translation: float = 0.2e-3  # m
    srm_mount_rotation: float = math.radians(0.5)  # rad
    # The finger: deflection at which its stiffness has doubled (F = k d (1 +
    # (d / s)^2)), width of the play between the tip and the tag (a few % of
    # the working deflection), and static over kinetic friction. Plausible
    # for a soft printed metamaterial.
    stiffening: tuple[float, float] = (2.5e-3, 4.0e-3)  # m
    hysteresis: tuple[float, float] = (0.02e-3, 0.06e-3)  # m
    static_friction_ratio: tuple[float, float] = (1.3, 1.7)
    # The tag sits inside the finger, short of its tip: a cantilever loaded at its tip deflects at a fraction x
    # of its length by x^2 (3 - x) / 2 of the tip's (Euler-Bernoulli), so a tag at 90-100 % of the bending length
    # moves 0.85-1.0 times the tip (a gain off by up to 15 %); the printed lattice bends unevenly, 1 sigma per
    # in-plane axis on top; and the tag falls further behind as the lattice's cells close, by (d / s)^2 at a
    # deflection d. Plausible for a printed metamaterial finger, whose own body deformation is estimated to
    # 2.1 % of its length (the SRM family, arXiv 2312.09863).
    tag_position: tuple[float, float] = (0.90, 1.0)  # fraction of the bending length
    tag_anisotropy: float = 0.02  # relative
    tag_softening: tuple[float, float] = (6.0e-3, 12.0e-3)  # m

    # -- part ------------------------------------------------------------------
    # Placement off its place on the table, 1 sigma per axis and in yaw
    # ("centimetres and degrees"; a manual fixture).
    placement_offset: float = 10.0e-3  # m
    placement_yaw: float = math.radians(2.0)  # rad
    # Shape: sideways bow at mid-length (either way, uniform in magnitude),
    # vertical bow, twist end to end (uniform +-), tack-weld kinks (1 sigma
    # each, three tacks) and the root gap's variation along the seam (amplitude,
    # uniform). Plausible for tack-welded 10 mm plates; the whole is the issue's
    # 1-3 mm.
    bow: tuple[float, float] = (0.5e-3, 2.5e-3)  # m
    bow_vertical: tuple[float, float] = (0.0, 1.0e-3)  # m
    twist: float = math.radians(1.0)  # rad
    tack_kink: float = 0.2e-3  # m
    gap_variation: tuple[float, float] = (0.1e-3, 0.3e-3)  # m

    def __post_init__(self) -> None:
        unknown = set(self.enabled) - set(SOURCES)
        if unknown:
            raise InputError(f"error budget: unknown source {sorted(unknown)[0]!r}; known: {', '.join(SOURCES)}")
        object.__setattr__(self, "enabled", frozenset(self.enabled))
        for f in fields(self):
            if f.name == "enabled":
                continue
            v = getattr(self, f.name)
            values = v if isinstance(v, tuple) else (v,)
            if not all(isinstance(x, (int, float)) and math.isfinite(x) and x >= 0.0 for x in values):
                raise InputError(f"error budget: {f.name} must be finite and >= 0, got {v!r}")
            if isinstance(v, tuple) and (len(v) != 2 or v[0] > v[1]):
                raise InputError(f"error budget: {f.name} must be a range (lo, hi) with lo <= hi, got {v!r}")

    def on(self, source: str) -> bool:
        """Whether ``source`` (one of :data:`SOURCES`) is switched on."""
        if source not in SOURCES:
            raise InputError(f"error budget: unknown source {source!r}; known: {', '.join(SOURCES)}")
        return source in self.enabled

    def with_sources(self, on: Sequence[str] = (), off: Sequence[str] = ()) -> ErrorBudget:
        """The same budget with the sources ``on`` switched on and ``off`` switched off."""
        return replace(self, enabled=(self.enabled | frozenset(on)) - frozenset(off))


PRESETS: dict[str, ErrorBudget] = {
    "ideal": ErrorBudget(enabled=frozenset()),
    "realistic": ErrorBudget(),
}

# [sim.errors] keys of the budget's magnitudes: field -> (key, scale from the key's unit to SI, upper bound in the key's unit).
ERROR_KEYS: dict[str, tuple[str, float, float]] = {
    "factory_length": ("factory_length_mm", 1e-3, 20.0),
    "factory_twist": ("factory_twist_deg", math.pi / 180, 2.0),
    "factory_joint_zero": ("factory_joint_zero_deg", math.pi / 180, 2.0),
    "dh_length": ("dh_length_mm", 1e-3, 10.0),
    "dh_twist": ("dh_twist_deg", math.pi / 180, 1.0),
    "joint_offset": ("joint_offset_deg", math.pi / 180, 1.0),
    "repeatability": ("repeatability_deg", math.pi / 180, 0.1),
    "encoder_noise": ("encoder_noise_deg", math.pi / 180, 0.1),
    "base_translation": ("base_translation_mm", 1e-3, 100.0),
    "base_rotation": ("base_rotation_deg", math.pi / 180, 10.0),
    "stiffness_shoulder": ("stiffness_shoulder_nm_rad", 1.0, 1e8),
    "stiffness_elbow": ("stiffness_elbow_nm_rad", 1.0, 1e8),
    "stiffness_wrist": ("stiffness_wrist_nm_rad", 1.0, 1e8),
    "link_mass_spread": ("link_mass_spread", 1.0, 0.5),
    "payload_mass_spread": ("payload_mass_spread", 1.0, 0.5),
    "payload_com_offset": ("payload_com_offset_mm", 1e-3, 100.0),
    "hose_force": ("hose_force_n", 1.0, 100.0),
    "warm_rise": ("warm_rise_k", 1.0, 50.0),
    "warmup_tau": ("warmup_tau_s", 1.0, 1e6),
    "lost_motion": ("lost_motion_deg", math.pi / 180, 0.5),
    "settle_amplitude": ("settle_amplitude_deg", math.pi / 180, 0.5),
    "settle_tau": ("settle_tau_ms", 1e-3, 5000.0),
    "settle_hz": ("settle_hz", 1.0, 200.0),
    "capture_delay": ("capture_delay_ms", 1e-3, 5000.0),
    "camera_stamp_sigma": ("camera_stamp_sigma_ms", 1e-3, 100.0),
    "camera_delivery_jitter": ("camera_delivery_jitter_ms", 1e-3, 100.0),
    "mount_translation": ("mount_translation_mm", 1e-3, 100.0),
    "mount_rotation": ("mount_rotation_deg", math.pi / 180, 10.0),
    "depth_scale": ("depth_scale", 1.0, 0.05),
    "distortion": ("distortion_mm", 1e-3, 20.0),
    "metal_bias": ("metal_bias_mm", 1e-3, 50.0),
    "chamfer": ("chamfer_mm", 1e-3, 5.0),
    "bore_depth": ("bore_depth_mm", 1e-3, 5.0),
    "hole_depth": ("hole_depth_mm", 1e-3, 5.0),
    "tip_offset": ("tip_offset_mm", 1e-3, 20.0),
    "torch_offset": ("torch_offset_mm", 1e-3, 20.0),
    "tool_rotation": ("tool_rotation_deg", math.pi / 180, 10.0),
    "tip_radius": ("tip_radius_mm", 1e-3, 1.0),
    "srm_focal": ("srm_focal", 1.0, 0.1),
    "srm_principal_point": ("srm_principal_point_px", 1.0, 50.0),
    "tag_print": ("tag_print", 1.0, 0.1),
    "srm_mount_translation": ("srm_mount_translation_mm", 1e-3, 10.0),
    "srm_mount_rotation": ("srm_mount_rotation_deg", math.pi / 180, 10.0),
    "stiffening": ("stiffening_mm", 1e-3, 100.0),
    "hysteresis": ("hysteresis_mm", 1e-3, 1.0),
    "static_friction_ratio": ("static_friction_ratio", 1.0, 5.0),
    "tag_position": ("tag_position", 1.0, 1.0),
    "tag_anisotropy": ("tag_anisotropy", 1.0, 0.3),
    "tag_softening": ("tag_softening_mm", 1e-3, 1000.0),
    "placement_offset": ("placement_offset_mm", 1e-3, 100.0),
    "placement_yaw": ("placement_yaw_deg", math.pi / 180, 30.0),
    "bow": ("bow_mm", 1e-3, 10.0),
    "bow_vertical": ("bow_vertical_mm", 1e-3, 10.0),
    "twist": ("twist_deg", math.pi / 180, 10.0),
    "tack_kink": ("tack_kink_mm", 1e-3, 5.0),
    "gap_variation": ("gap_variation_mm", 1e-3, 2.0),
}


# -- the nominal cell ------------------------------------------------------------------

# The scanner's place in the drawing of the default cell: the paper's Eq. 19.
DEFAULT_T_BASE_CAM = ((0.0, -1.0, 0.0, 0.6), (-1.0, 0.0, 0.0, -0.0125), (0.0, 0.0, -1.0, 1.0), (0.0, 0.0, 0.0, 1.0))
SCANNER_MODELS = ("phoxi-s", "phoxi-m", "azure-kinect")
ROBOT_MODELS = tuple(kin.MODELS)


@dataclass(frozen=True)
class NominalCell:
    """The cell as drawn: what the simulator models before its errors (SI)."""

    robot: str = "ur10e"
    flange: str = "ur10e"
    scanner: str = "phoxi-m"
    T_base_cam: tuple[tuple[float, ...], ...] = DEFAULT_T_BASE_CAM
    # On the arm (mount link1-3, celld.calib.mount): the scanner's pose in its link's frame; then T_base_cam is not read.
    scanner_mount: str = "base"
    T_link_cam: tuple[tuple[float, ...], ...] | None = None
    resolution_scale: float = 1.0  # image scale of the simulated scanner (0.01 to 1)
    # The scanner's region of interest (row0, row1, col0, col1) in pixels of its (scaled) image: only it
    # is cast, the rest of each cloud has no return, as on a scanner with an ROI set; None: the whole image.
    scanner_roi_px: tuple[int, int, int, int] | None = None
    scanner_seed: int = 0  # seed of the scanner's noise (mixed with the world's)
    # The welding tool as drawn, in the flange frame (the keys of [tool]).
    tool: ToolConfig = field(default_factory=ToolConfig)
    workpiece: str = ""  # an example part (celld.seam.workpiece.EXAMPLES); "" for a bare table
    # Where the part lies before its placement error (UR pose); () for the simulator's nominal place.
    part_pose: tuple[float, ...] = ()
    # A sideways bow of the part where its model is straight, before the budget's shape errors, m.
    part_bow: float = 0.0
    # A second robot in the scanner's view ([sim.robot2]): its model ("" for
    # none), its base in robot 1's base frame as drawn (UR pose) and its flange.
    robot2: str = ""
    robot2_pose: tuple[float, ...] = ()
    robot2_flange: str = ""
    # The SRM camera and its tag as drawn ([sim.srm]); its mount is the tool's T_tool_cam.
    srm: SrmCamera = field(default_factory=SrmCamera)

    @classmethod
    def read(cls, r: TableReader) -> NominalCell:
        """The nominal cell from the ``[sim]`` table's reader ``r`` (its preset, seed and errors are read elsewhere)."""
        sc = r.table("scanner")
        tool_r = r.table("tool")
        part = r.table("part")
        srm = r.table("srm")
        pose = part.vector("pose", 6) if part.has("pose") else ()
        r2 = r.table("robot2")
        robot2, robot2_flange = "", ""
        robot2_pose: tuple[float, ...] = ()
        if r.has("robot2"):
            if not r2.has("base_pose"):
                raise r2.error("base_pose", "give the second robot's base in robot 1's base frame as drawn (UR pose, m and rad)")
            robot2 = r2.str("robot", "ur10e", choices=ROBOT_MODELS)
            robot2_pose = r2.vector("base_pose", 6)
            robot2_flange = r2.str("flange", "")
        from celld.seam.workpiece import EXAMPLES

        mount = sc.str("mount", "base", choices=SCANNER_MOUNTS)
        T_link_cam = None
        if mount != "base":
            if not sc.has("T_link_cam"):
                raise sc.error("T_link_cam", f"the scanner is on {mount}: give its pose in that link's frame (T_link_cam)")
            T_link_cam = sc.matrix4("T_link_cam")
        elif sc.has("T_link_cam"):
            raise sc.error("T_link_cam", "only a scanner on the arm (mount = link1-3) has a pose on a link")

        scanner = sc.str("model", cls.scanner, choices=SCANNER_MODELS)
        resolution_scale = sc.float("resolution_scale", 1.0, lo=0.01, hi=1.0)
        out = cls(
            robot=r.str("robot", cls.robot, choices=ROBOT_MODELS),
            flange=r.str("flange", cls.flange),
            scanner=scanner,
            T_base_cam=sc.matrix4("T_base_cam", [list(row) for row in DEFAULT_T_BASE_CAM]),
            scanner_mount=mount,
            T_link_cam=T_link_cam,
            resolution_scale=resolution_scale,
            scanner_roi_px=_read_roi(sc, scanner, resolution_scale) if sc.has("roi_px") else None,
            scanner_seed=sc.int("seed", 0, lo=0),
            tool=ToolConfig.read(tool_r),
            workpiece=part.str("workpiece", "", choices=("", *EXAMPLES)),
            part_pose=pose,
            part_bow=part.float("bow_mm", 0.0, lo=-10.0, hi=10.0, scale=1e-3),
            robot2=robot2,
            robot2_pose=robot2_pose,
            robot2_flange=robot2_flange,
            srm=SrmCamera.read(srm),
        )
        for sub in (sc, tool_r, part, r2, srm):
            sub.done()
        try:
            flange_preset(out.flange)
        except InputError as exc:
            raise r.error("flange", str(exc)) from exc
        if out.robot2_flange:
            try:
                flange_preset(out.robot2_flange)
            except InputError as exc:
                raise r2.error("flange", str(exc)) from exc
        if out.part_bow != 0.0 and out.workpiece not in ("v-groove", "curved-groove"):
            raise part.error("bow_mm", f"only a groove can bow, not {out.workpiece or 'no part'!r}")
        return out


def _read_roi(sc: TableReader, model: str, resolution_scale: float) -> tuple[int, int, int, int]:
    """``[sim.scanner] roi_px``: (row0, row1, col0, col1), whole pixels of the scanner's image at its resolution_scale."""
    from celld.sim.scanner import scanner_model

    m = scanner_model(model).scaled(resolution_scale)
    value = sc.vector("roi_px", 4)
    if not all(v == int(v) for v in value):
        raise sc.error("roi_px", f"expected whole pixels [row0, row1, col0, col1], got {list(value)}")
    r0, r1, c0, c1 = (int(v) for v in value)
    if not (0 <= r0 < r1 <= m.height_px and 0 <= c0 < c1 <= m.width_px):
        raise sc.error(
            "roi_px",
            f"expected 0 <= row0 < row1 <= {m.height_px} and 0 <= col0 < col1 <= {m.width_px} "
            f"(the {model}'s image at resolution_scale {resolution_scale:g}), got {[r0, r1, c0, c1]}",
        )
    return r0, r1, c0, c1


@dataclass(frozen=True)
class WorldOptions:
    """What a command line may change of the ``[sim]`` table: preset, seed, sources on and off."""

    preset: str | None = None
    seed: int | None = None
    on: tuple[str, ...] = ()
    off: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.preset is not None and self.preset not in PRESET_NAMES:
            raise InputError(f"preset: expected one of {', '.join(PRESET_NAMES)}, got {self.preset!r}")
        if self.seed is not None and not (isinstance(self.seed, int) and self.seed >= 0):
            raise InputError(f"seed: expected an integer >= 0, got {self.seed!r}")
        for s in (*self.on, *self.off):
            if s not in SOURCES:
                raise InputError(f"unknown error source {s!r}; known: {', '.join(SOURCES)}")

    def to_argv(self) -> list[str]:
        """The arguments :func:`add_world_arguments` reads back into these options."""
        argv: list[str] = []
        if self.preset is not None:
            argv += ["--preset", self.preset]
        if self.seed is not None:
            argv += ["--world-seed", str(self.seed)]
        if self.on:
            argv += ["--with", ",".join(self.on)]
        if self.off:
            argv += ["--without", ",".join(self.off)]
        return argv


def add_world_arguments(parser: Any) -> None:
    """``--preset``, ``--world-seed``, ``--with`` and ``--without`` on an argparse parser."""
    parser.add_argument("--preset", choices=PRESET_NAMES, default=None, help="the error budget (default: the config's [sim] preset)")
    parser.add_argument("--world-seed", type=int, default=None, help="the world's seed (default: the config's [sim] seed)")
    parser.add_argument(
        "--with",
        dest="with_sources",
        default="",
        metavar="SOURCES",
        help=f"error sources to switch on, comma-separated ({', '.join(SOURCES)})",
    )
    parser.add_argument("--without", dest="without_sources", default="", metavar="SOURCES", help="error sources to switch off")


def options_from_args(args: Any) -> WorldOptions:
    """:class:`WorldOptions` of parsed :func:`add_world_arguments` arguments."""

    def names(text: str) -> tuple[str, ...]:
        return tuple(s.strip() for s in text.split(",") if s.strip())

    try:
        return WorldOptions(args.preset, args.world_seed, names(args.with_sources), names(args.without_sources))
    except InputError as exc:
        raise ConfigError("command line", "world", str(exc)) from exc


# -- the true cell -----------------------------------------------------------------------


@dataclass(frozen=True)
class DepthField:
    """A smooth distortion of a scanner's measurements: a quadratic field in camera coordinates.

    A point ``p`` (camera frame, m) is measured at ``p + C @ basis(p)`` with
    the basis ``[u, v, w, u^2, v^2, w^2, uv, uw, vw]`` of its normalised
    coordinates ``u = (x / z) / u_half``, ``v = (y / z) / v_half``, ``w = (z -
    z_mid) / z_half`` (each about [-1, 1] over the measuring volume).
    """

    coefficients: tuple[tuple[float, ...], ...]  # (3, 9), m
    u_half: float
    v_half: float
    z_mid: float
    z_half: float

    def basis(self, P: Array) -> Array:
        """The (n, 9) basis at points (n, 3), filled in place (a capture has millions of points)."""
        z = P[:, 2]
        B = np.empty((len(P), 9), dtype=np.float64)
        u, v, w = B[:, 0], B[:, 1], B[:, 2]
        np.divide(P[:, 0], z, out=u)
        u /= self.u_half
        np.divide(P[:, 1], z, out=v)
        v /= self.v_half
        np.subtract(z, self.z_mid, out=w)
        w /= self.z_half
        for k, (a, b) in enumerate(((u, u), (v, v), (w, w), (u, v), (u, w), (v, w)), start=3):
            np.multiply(a, b, out=B[:, k])
        return B

    def displacement(self, P_cam: Array) -> Array:
        """The field's displacement (n, 3) at points (n, 3), m."""
        return self.basis(np.asarray(P_cam, dtype=np.float64)) @ np.asarray(self.coefficients).T


@dataclass(frozen=True)
class ScannerTruth:
    """The scanner as it is: where it is, how it measures, when it exposes.

    A scanner on the arm (``link`` 1-3) is fixed on that link: ``T_mount_cam``
    is its true pose in the link's frame, and its pose in the base frame
    follows the arm's true joints (:meth:`T_base_cam_at`).
    """

    model: str
    T_mount_cam: Array  # (4, 4) the true pose in the frame it is fixed in (the base, or its link)
    depth_scale: float  # relative: a range r is measured as r (1 + depth_scale)
    field: DepthField | None
    metal_bias: float | None  # m, the unit's bias on metal (None: the model's)
    capture_delay: tuple[float, float]  # s, uniform range from the request to the exposure
    resolution_scale: float
    noise_seed: int
    link: int = 0  # 0: fixed in the base frame; k: on the frame after joint k
    roi_px: tuple[int, int, int, int] | None = None  # the window of the (scaled) image that is cast; None: all of it

    @property
    def T_base_cam(self) -> Array:
        """The true pose in the base frame of a scanner fixed there."""
        if self.link:
            raise InputError(f"the scanner is on link {self.link}: its pose in the base frame follows the joints (T_base_cam_at)")
        return self.T_mount_cam

    def T_base_cam_at(self, q_true: Sequence[float] | Array, dh_true: kin.DH) -> Array:
        """The true pose in the base frame with the arm's true joints ``q_true`` and DH table."""
        if not self.link:
            return self.T_mount_cam
        T_base_link = kin.matrix_from_rows(kin.forward_all_rows(list(q_true), dh_true)[self.link - 1])
        return np.asarray(T_base_link @ self.T_mount_cam, dtype=np.float64)

    def measure(self, P_cam: Array) -> Array:
        """Where the scanner measures true points (n, 3) of its camera frame, m: scale and distortion (no noise)."""
        P = np.asarray(P_cam, dtype=np.float64)
        out = P * (1.0 + self.depth_scale)
        if self.field is not None:
            out += self.field.displacement(P)
        return out

    @property
    def ideal(self) -> bool:
        return self.depth_scale == 0.0 and self.field is None


@dataclass(frozen=True)
class ToolTruth:
    """The welding tool as drawn and as built, in the flange frame.

    ``config`` is the tool as built, in the keys of :class:`ToolConfig` with
    the flange as its TCP (the SRM tip, the finger's axes, the camera mount);
    ``p_flange_torch`` the true torch point (the wire's tip), m.
    """

    nominal: ToolConfig
    config: ToolConfig
    p_flange_torch: Array  # (3,)
    p_flange_torch_nominal: Array  # (3,)


@dataclass(frozen=True)
class FingerTruth:
    """The SRM finger's mechanics beyond its linear stiffness (celld.sim.srm.ContactParams)."""

    stiffening: float = math.inf  # m, deflection at which the stiffness has doubled (inf: linear)
    hysteresis: float = 0.0  # m, width of the play between the tip and the tag
    static_friction_ratio: float = 1.0  # static over kinetic friction (1: no stick-slip)
    # The tag's shift over the tip's along the tool's x and y, and the deflection s at which it has fallen
    # behind by a further (d / s)^2 (inf: none): celld.sim.srm.tag_of_tip.
    tag_gain: tuple[float, float] = (1.0, 1.0)
    tag_softening: float = math.inf  # m


@dataclass(frozen=True)
class CameraTiming:
    """The SRM camera's timing errors and its image noise seed."""

    stamp_sigma: float = 0.0  # s
    delivery_jitter: float = 0.0  # s
    seed: int = 0


@dataclass(frozen=True)
class PartShape:
    """How the part differs from its model (m, rad), applied along its seam (celld.sim.workpiece)."""

    bow: float = 0.0  # sideways at mid-length
    bow_vertical: float = 0.0  # upwards at mid-length
    twist: float = 0.0  # of the joint about the seam, end against start
    tacks: tuple[tuple[float, float], ...] = ()  # (position along the seam 0..1, sideways kink m)
    gap_amplitude: float = 0.0  # root gap variation
    gap_waves: float = 1.0  # half-waves of the variation over the seam
    gap_phase: float = 0.0  # rad

    @property
    def bow_only(self) -> bool:
        """True when the shape is at most the model's own sideways bow (celld.seam.workpiece.v_groove_butt)."""
        return not (self.bow_vertical or self.twist or self.tacks or self.gap_amplitude)


@dataclass(frozen=True)
class PartTruth:
    """The part as placed and as made."""

    workpiece: str
    T_base_place: Array  # (4, 4) where it would lie without placement error (before it is set down)
    offset_xy: tuple[float, float]  # m, placement error on the table
    yaw: float  # rad, placement error about the table's normal
    shape: PartShape


@dataclass(frozen=True)
class Robot2Truth:
    """A second robot as installed: its physical arm, its flange as made, its base in robot 1's base frame.

    ``T_base1_base2`` is the truth a robot-robot calibration estimates;
    ``T_base1_base2_drawn`` is where the drawing puts it.
    """

    model: str
    arm: ArmTruth
    flange: FlangeModel
    T_base1_base2: Array
    T_base1_base2_drawn: Array
    kinematics: kin.DH | None = None  # the table its controller computes with; None: the published one

    @property
    def nominal_dh(self) -> kin.DH:
        """The DH table its controller believes (its factory calibration's)."""
        return self.kinematics or kin.model(self.model).dh


@dataclass(frozen=True)
class World:
    """One true cell: drawn from a nominal cell and a budget by a seed (see :func:`draw_world`)."""

    preset: str
    seed: int
    budget: ErrorBudget
    nominal: NominalCell
    arm: ArmTruth
    scanner: ScannerTruth
    flange: FlangeModel
    tool: ToolTruth
    finger: FingerTruth
    camera: CameraTiming
    part: PartTruth | None
    robot2: Robot2Truth | None = None
    srm: SrmCamera = field(default_factory=SrmCamera)  # the SRM camera as built, its mount in the tool frame set
    kinematics: kin.DH | None = None  # the table the controller computes with; None: the published one
    # The welding power source's behaviour (celld.sim.power_source); it runs only where the cell wires one.
    power_source: SourceTruth = field(default_factory=SourceTruth)

    @property
    def nominal_dh(self) -> kin.DH:
        """The DH table the controller believes (its factory calibration's)."""
        return self.kinematics or kin.model(self.nominal.robot).dh

    def describe(self) -> str:
        """One line: the preset, the seed and the sources that are off or on."""
        on = sorted(self.budget.enabled)
        if not on:
            what = "no error source"
        elif len(on) == len(SOURCES):
            what = "every error source"
        elif len(on) > len(SOURCES) / 2:
            what = "every error source but " + ", ".join(sorted(set(SOURCES) - set(on)))
        else:
            what = "error sources " + ", ".join(on)
        return f"world: preset {self.preset}, seed {self.seed}, {what}"


def _rng(seed: int, source: str) -> np.random.Generator:
    """The generator of one source: independent of every other source's."""
    return np.random.default_rng([int(seed), zlib.crc32(source.encode())])


def _tnormal(rng: np.random.Generator, sigma: float, size: int | tuple[int, ...]) -> Array:
    """Gaussian draws cut at :data:`TRUNCATE` sigma (drawn again beyond it)."""
    x = rng.standard_normal(size)
    bad = np.abs(x) > TRUNCATE
    while np.any(bad):
        x[bad] = rng.standard_normal(int(bad.sum()))
        bad = np.abs(x) > TRUNCATE
    return np.asarray(x * sigma, dtype=np.float64)


def _seed_of(seed: int, source: str) -> int:
    return int(_rng(seed, source).integers(0, 2**31 - 1))


def _draw_arm(
    model: str,
    b: ErrorBudget,
    seed: int,
    tag: str = "",
    payload: dynamics.Payload = dynamics.Payload(),
    hose_at: tuple[float, float, float] = (0.0, 0.0, 0.0),
    believed: kin.DH | None = None,
) -> ArmTruth:
    """The physical arm of a robot ``model`` whose controller computes with ``believed`` (:func:`_draw_factory`);
    ``tag`` names a second robot's own draws; ``payload`` the tool as drawn and ``hose_at`` where its hose
    package pulls (flange frame, m)."""
    believed = believed or kin.model(model).dh
    dh = kin.DH(believed.d, believed.a, believed.alpha)
    offsets = believed.theta
    if b.on("kinematics"):
        r = _rng(seed, "kinematics" + tag)
        d = np.asarray(dh.d) + _tnormal(r, b.dh_length, 6)
        a = np.asarray(dh.a) + _tnormal(r, b.dh_length, 6)
        alpha = np.asarray(dh.alpha) + _tnormal(r, b.dh_twist, 6)
        dh = kin.DH(tuple(d.tolist()), tuple(a.tolist()), tuple(alpha.tolist()))
        offsets = tuple((np.asarray(offsets) + _tnormal(r, b.joint_offset, 6)).tolist())
    settle = b.on("settle")
    bends: dict[str, Any] = {}
    published = dynamics.links(model)
    if (b.on("compliance") or b.on("hose_pull")) and published is not None:
        r = _rng(seed, "compliance" + tag)
        ranges = (b.stiffness_shoulder,) * 2 + (b.stiffness_elbow,) + (b.stiffness_wrist,) * 3
        compliance = tuple(1.0 / float(r.uniform(*k)) for k in ranges)
        if b.on("compliance"):
            mass = np.asarray(published.mass) * (1.0 + _tnormal(r, b.link_mass_spread, 6))
            m_tool = payload.mass * (1.0 + float(_tnormal(r, b.payload_mass_spread, 1)[0])) if payload.mass else 0.0
            com_tool = np.asarray(payload.com) + (_tnormal(r, b.payload_com_offset, 3) if payload.mass else 0.0)
            bends.update(link_mass=tuple(mass.tolist()), link_com=published.com, payload_mass=m_tool, payload_com=tuple(com_tool.tolist()))
        if b.on("hose_pull"):
            h = _rng(seed, "hose_pull" + tag)
            # Down and towards the base (-x of a tool over the table), within 45 degrees of that.
            axis = np.array([-1.0, 0.0, -1.0]) / math.sqrt(2.0)
            tilt = Rotation.from_rotvec(h.uniform(-1.0, 1.0, 3) * math.radians(45.0) / math.sqrt(3.0)).as_matrix()
            bends.update(hose_force=tuple((tilt @ axis * h.uniform(*b.hose_force)).tolist()), hose_point=hose_at)
        bends["compliance"] = compliance
    if b.on("thermal"):
        bends.update(warm_rise=float(_rng(seed, "thermal" + tag).uniform(*b.warm_rise)), warmup_tau=b.warmup_tau)
    if b.on("lost_motion"):
        bends["lost_motion"] = tuple(_rng(seed, "lost_motion" + tag).uniform(*b.lost_motion, 6).tolist())
    return ArmTruth(
        dh=dh,
        joint_offsets=offsets,
        encoder_noise=b.encoder_noise if b.on("encoder_noise") else 0.0,
        repeatability=b.repeatability if b.on("repeatability") else 0.0,
        settle_amplitude=b.settle_amplitude if settle else 0.0,
        settle_tau=b.settle_tau if settle and b.settle_tau > 0.0 else ArmTruth.settle_tau,
        settle_hz=b.settle_hz if settle else ArmTruth.settle_hz,
        seed=_seed_of(seed, "arm-noise" + tag),
        **bends,
    )


def _draw_factory(model: str, b: ErrorBudget, seed: int, tag: str = "") -> kin.DH | None:
    """The table a robot ``model``'s controller computes with: the published one and its factory calibration's
    deltas on every length, twist and joint zero; None (the published table) with the source off."""
    if not b.on("factory_calibration"):
        return None
    dh, r = kin.model(model).dh, _rng(seed, "factory_calibration" + tag)

    def drawn(row: tuple[float, ...], sigma: float) -> Any:
        return tuple((np.asarray(row) + _tnormal(r, sigma, 6)).tolist())

    d, a, alpha = drawn(dh.d, b.factory_length), drawn(dh.a, b.factory_length), drawn(dh.alpha, b.factory_twist)
    return kin.DH(d, a, alpha, drawn((0.0,) * 6, b.factory_joint_zero))


def _depth_field(model_name: str, rms: float, rng: np.random.Generator) -> DepthField:
    from celld.sim.scanner import scanner_model  # the intrinsics and range of the model (no Open3D use)

    m = scanner_model(model_name)
    u_half = (m.width_px / 2.0) / m.fx
    v_half = (m.height_px / 2.0) / m.fy
    z_mid, z_half = (m.min_range + m.max_range) / 2.0, (m.max_range - m.min_range) / 2.0
    unit = DepthField(tuple(map(tuple, rng.standard_normal((3, 9)).tolist())), u_half, v_half, z_mid, z_half)
    g = np.linspace(-1.0, 1.0, 7)
    U, V, W = np.meshgrid(g, g, g, indexing="ij")
    z = z_mid + z_half * W.ravel()
    P = np.column_stack([U.ravel() * u_half * z, V.ravel() * v_half * z, z])
    k = rms / float(np.sqrt(np.mean(np.sum(unit.displacement(P) ** 2, axis=1))))
    return replace(unit, coefficients=tuple(tuple(float(c) * k for c in row) for row in unit.coefficients))


def _draw_scanner(nominal: NominalCell, b: ErrorBudget, seed: int) -> ScannerTruth:
    from celld.sim.scanner import scanner_model

    model = scanner_model(nominal.scanner)
    # The scanner's errors are sized for the PhoXi M's 0.1 mm class and scale with each model's noise.
    klass = model.sigma / 1e-4
    link = SCANNER_MOUNTS.index(nominal.scanner_mount)
    T = np.array(nominal.T_base_cam if nominal.T_link_cam is None else nominal.T_link_cam, dtype=np.float64)
    if b.on("scanner_mount"):
        r = _rng(seed, "scanner_mount")
        dT = se3.transform_from(Rotation.from_rotvec(_tnormal(r, b.mount_rotation, 3)).as_matrix(), _tnormal(r, b.mount_translation, 3))
        T = T @ dT
    scale = float(_tnormal(_rng(seed, "depth_scale"), b.depth_scale * klass, 1)[0]) if b.on("depth_scale") else 0.0
    dfield = (
        _depth_field(nominal.scanner, b.distortion * klass, _rng(seed, "distortion")) if b.on("distortion") and b.distortion > 0 else None
    )
    bias = None
    if b.on("metal_bias") and model.metal_bias > 0.0:
        bias = max(0.0, model.metal_bias + float(_tnormal(_rng(seed, "metal_bias"), b.metal_bias, 1)[0]))
    delay = b.capture_delay if b.on("capture_delay") else (0.0, 0.0)
    noise_seed = nominal.scanner_seed + 1_000_003 * seed
    return ScannerTruth(nominal.scanner, T, scale, dfield, bias, delay, nominal.resolution_scale, noise_seed, link, nominal.scanner_roi_px)


# ISO 9409-1 fits of the 50-4-M6 face as a ratio of the nominal: d2 h8 on 63 mm is -46..0 um, d3 H7 on 31.5 mm 0..+25 um.
_H8_63 = 46e-6 / 0.063
_H7_31 = 25e-6 / 0.0315
# Pitch-circle and thickness tolerances (plausible: a turned and drilled part), m.
_PITCH_TOL = 20e-6
_THICKNESS_TOL = 50e-6


def _draw_flange(name: str, b: ErrorBudget, seed: int, tag: str = "") -> FlangeModel:
    """The flange ``name`` as made; ``tag`` names a second robot's own draws."""
    f = flange_preset(name)
    face_circle = abs(f.circle_radius - f.face_radius) < 1e-12 and f.circle_z == 0.0
    changes: dict[str, Any] = {}
    if b.on("flange_tolerance"):
        r = _rng(seed, "flange_tolerance" + tag)
        changes.update(
            outer_diameter=f.outer_diameter * (1.0 - _H8_63 * r.uniform()),
            bore_diameter=f.bore_diameter * (1.0 + _H7_31 * r.uniform()),
            pitch_diameter=f.pitch_diameter + r.uniform(-_PITCH_TOL, _PITCH_TOL),
            thickness=f.thickness + r.uniform(-_THICKNESS_TOL, _THICKNESS_TOL),
        )
    if b.on("flange_variant"):
        r = _rng(seed, "flange_variant" + tag)
        changes.update(
            chamfer=r.uniform(*b.chamfer),
            bore_depth=f.bore_depth + r.uniform(-b.bore_depth, b.bore_depth),
            hole_depth=f.hole_depth + r.uniform(-b.hole_depth, b.hole_depth),
            dowel_depth=f.dowel_depth + r.uniform(-b.hole_depth, b.hole_depth),
        )
    if not changes:
        return f
    outer = changes.get("outer_diameter", f.outer_diameter)
    chamfer = changes.get("chamfer", f.chamfer)
    if face_circle:
        changes["circle_radius"] = outer / 2.0 - chamfer
    if outer > f.wrist_diameter:
        changes["wrist_diameter"] = outer
    return replace(f, name=f"{f.name} (as made)", **changes)


def _tool_point(cfg: ToolConfig, p_tool: Array) -> Array:
    """A point given in the tool frame of ``cfg``, in its TCP frame."""
    x, z = np.asarray(cfg.tool_x_tcp), np.asarray(cfg.tool_z_tcp)
    R = np.column_stack([x, np.cross(z, x), z])
    return np.asarray(cfg.tip_tcp) + R @ p_tool


def _draw_tool(nominal: NominalCell, b: ErrorBudget, seed: int) -> ToolTruth:
    cfg = nominal.tool
    torch_nominal = _tool_point(cfg, np.array([-cfg.torch_offset, 0.0, 0.0]))
    if not b.on("tool_offsets"):
        return ToolTruth(cfg, cfg, torch_nominal, torch_nominal)
    r = _rng(seed, "tool_offsets")
    dR = Rotation.from_rotvec(_tnormal(r, b.tool_rotation, 3)).as_matrix()
    tip = np.asarray(cfg.tip_tcp) + _tnormal(r, b.tip_offset, 3)
    torch = torch_nominal + _tnormal(r, b.torch_offset, 3)
    x = dR @ np.asarray(cfg.tool_x_tcp)
    z = dR @ np.asarray(cfg.tool_z_tcp)
    radius = max(cfg.tip_radius + float(_tnormal(r, b.tip_radius, 1)[0]), 0.1 * cfg.tip_radius)
    true_cfg = replace(
        cfg,
        tool_x_tcp=tuple(x.tolist()),
        tool_z_tcp=tuple(z.tolist()),
        tip_tcp=tuple(tip.tolist()),
        tip_radius=radius,
        torch_offset=float(np.linalg.norm(torch - tip)),
    )
    return ToolTruth(cfg, true_cfg, torch, torch_nominal)


def _draw_finger(b: ErrorBudget, seed: int) -> FingerTruth:
    finger = FingerTruth()
    if b.on("finger"):
        r = _rng(seed, "finger")
        finger = FingerTruth(r.uniform(*b.stiffening), r.uniform(*b.hysteresis), r.uniform(*b.static_friction_ratio))
    if not b.on("tag_map"):
        return finger
    r = _rng(seed, "tag_map")
    x = r.uniform(*b.tag_position)
    bent = x * x * (3.0 - x) / 2.0  # the cantilever's deflection at x over the tip's
    gain = bent * (1.0 + _tnormal(r, b.tag_anisotropy, 2))
    return replace(finger, tag_gain=(float(gain[0]), float(gain[1])), tag_softening=float(r.uniform(*b.tag_softening)))


def _draw_camera(b: ErrorBudget, seed: int) -> CameraTiming:
    srm_seed = _seed_of(seed, "srm-image") if seed else 0  # seed 0: the image noise of the cell before it had a world
    if not b.on("camera_jitter"):
        return CameraTiming(seed=srm_seed)
    return CameraTiming(b.camera_stamp_sigma, b.camera_delivery_jitter, srm_seed)


def _draw_srm(nominal: NominalCell, b: ErrorBudget, seed: int) -> SrmCamera:
    drawn = replace(nominal.srm, T_tool_cam=nominal.tool.T_tool_cam)
    if not b.on("srm_camera"):
        return drawn
    r = _rng(seed, "srm_camera")
    fx, fy, cx, cy = drawn.intrinsics_px
    f = 1.0 + _tnormal(r, b.srm_focal, 1)[0]
    dc = _tnormal(r, b.srm_principal_point, 2)
    size = drawn.tag_size * (1.0 + _tnormal(r, b.tag_print, 1)[0])
    T = np.asarray(drawn.T_tool_cam, dtype=np.float64)
    dR = Rotation.from_rotvec(_tnormal(r, b.srm_mount_rotation, 3)).as_matrix()
    T_built = se3.transform_from(dR @ T[:3, :3], T[:3, 3] + _tnormal(r, b.srm_mount_translation, 3))
    return replace(
        drawn,
        intrinsics_px=(float(fx * f), float(fy * f), float(cx + dc[0]), float(cy + dc[1])),
        tag_size=float(size),
        T_tool_cam=tuple(tuple(float(v) for v in row) for row in T_built),
    )


def _draw_robot2(nominal: NominalCell, b: ErrorBudget, seed: int) -> Robot2Truth | None:
    if not nominal.robot2:
        return None
    T_drawn = se3.from_ur_pose(nominal.robot2_pose)
    T_true = T_drawn
    if b.on("robot2_placement"):
        r = _rng(seed, "robot2_placement")
        dp = _tnormal(r, b.base_translation, 3)
        dR = Rotation.from_rotvec(_tnormal(r, b.base_rotation, 3)).as_matrix()
        T_true = se3.transform_from(dR @ T_drawn[:3, :3], T_drawn[:3, 3] + dp)
    tag = "/robot2"
    factory = _draw_factory(nominal.robot2, b, seed, tag)
    return Robot2Truth(
        model=nominal.robot2,
        kinematics=factory,
        arm=_draw_arm(nominal.robot2, b, seed, tag, believed=factory),
        flange=_draw_flange(nominal.robot2_flange or nominal.flange, b, seed, tag),
        T_base1_base2=T_true,
        T_base1_base2_drawn=T_drawn,
    )


def _draw_part(nominal: NominalCell, b: ErrorBudget, seed: int) -> PartTruth | None:
    if not nominal.workpiece:
        return None
    from celld.sim.workpiece import NOMINAL_XY, NOMINAL_YAW

    if nominal.part_pose:
        T_place = se3.from_ur_pose(nominal.part_pose)
    else:
        T_place = se3.from_xyz_rpy([NOMINAL_XY[0], NOMINAL_XY[1], 0.0], [0.0, 0.0, NOMINAL_YAW])
    offset, yaw = (0.0, 0.0), 0.0
    if b.on("part_placement"):
        r = _rng(seed, "part_placement")
        dx, dy = _tnormal(r, b.placement_offset, 2)
        offset, yaw = (float(dx), float(dy)), float(_tnormal(r, b.placement_yaw, 1)[0])
    shape = PartShape(bow=nominal.part_bow)
    if b.on("part_shape") and nominal.workpiece in ("v-groove", "curved-groove"):
        r = _rng(seed, "part_shape")
        bow = nominal.part_bow + float(r.choice([-1.0, 1.0]) * r.uniform(*b.bow))
        tacks = tuple((float(x + r.uniform(-0.05, 0.05)), float(_tnormal(r, b.tack_kink, 1)[0])) for x in (0.15, 0.5, 0.85))
        shape = PartShape(
            bow=bow,
            bow_vertical=float(r.uniform(*b.bow_vertical)),
            twist=float(r.uniform(-b.twist, b.twist)),
            tacks=tacks,
            gap_amplitude=float(r.uniform(*b.gap_variation)),
            gap_waves=float(r.choice([1.0, 2.0, 3.0])),
            gap_phase=float(r.uniform(0.0, 2.0 * math.pi)),
        )
    return PartTruth(nominal.workpiece, T_place, offset, yaw, shape)


def draw_world(nominal: NominalCell, budget: ErrorBudget, seed: int, preset: str = "", source: SourceBudget | None = None) -> World:
    """The true cell of ``nominal`` under ``budget`` for ``seed`` (deterministic); its power source drawn from
    ``source`` (None: the source preset of the budget's preset, the ideal one for a budget of neither)."""
    if not (isinstance(seed, int) and seed >= 0):
        raise InputError(f"world seed: expected an integer >= 0, got {seed!r}")
    factory = _draw_factory(nominal.robot, budget, seed)
    payload = dynamics.Payload(nominal.tool.mass, nominal.tool.com_flange)
    return World(
        preset=preset or _preset_name(budget),
        seed=seed,
        budget=budget,
        nominal=nominal,
        kinematics=factory,
        arm=_draw_arm(nominal.robot, budget, seed, payload=payload, hose_at=nominal.tool.tip_tcp, believed=factory),
        scanner=_draw_scanner(nominal, budget, seed),
        flange=_draw_flange(nominal.flange, budget, seed),
        tool=_draw_tool(nominal, budget, seed),
        finger=_draw_finger(budget, seed),
        camera=_draw_camera(budget, seed),
        part=_draw_part(nominal, budget, seed),
        robot2=_draw_robot2(nominal, budget, seed),
        srm=_draw_srm(nominal, budget, seed),
        power_source=draw_source(
            source if source is not None else SOURCE_PRESETS.get(_preset_name(budget), SOURCE_PRESETS["ideal"]),
            _rng(seed, "power_source"),
            _seed_of(seed, "power-source-events"),
        ),
    )


def _preset_name(budget: ErrorBudget) -> str:
    for name, b in PRESETS.items():
        if b == budget:
            return name
    return "custom"


def read_budget(r: TableReader, preset: str) -> ErrorBudget:
    """The preset's budget with the ``[sim.errors]`` table (reader ``r``) over it."""
    b = PRESETS[preset]
    on = [s for s in SOURCES if r.has(s) and r.bool(s)]
    off = [s for s in SOURCES if r.has(s) and not r.bool(s)]
    changes: dict[str, Any] = {}
    for name, (key, scale, hi) in ERROR_KEYS.items():
        if not r.has(key):
            continue
        if isinstance(getattr(b, name), tuple):
            lo_v, hi_v = r.vector(key, 2)
            if not 0.0 <= lo_v <= hi_v <= hi:
                raise r.error(key, f"expected [lo, hi] with 0 <= lo <= hi <= {hi}, got {[lo_v, hi_v]}")
            changes[name] = (lo_v * scale, hi_v * scale)
        else:
            changes[name] = r.float(key, lo=0.0, hi=hi, scale=scale)
    return replace(b, **changes).with_sources(on, off)


def world_from_table(table: Mapping[str, Any], source: str = "<sim>", options: WorldOptions = WorldOptions()) -> World:
    """The world of a cell config's ``[sim]`` table, with the command line's ``options`` over it.

    Raises
    ------
    ConfigError
        A key of ``[sim]`` is unknown, of the wrong type or out of range.
    """
    r = TableReader(dict(table), source, "sim")
    preset = options.preset or r.str("preset", "ideal", choices=PRESET_NAMES)
    seed = options.seed if options.seed is not None else r.int("seed", 0, lo=0, hi=2**31 - 1)
    if options.preset is not None:
        r.str("preset", "ideal", choices=PRESET_NAMES)  # still checked
    if options.seed is not None:
        r.int("seed", 0, lo=0, hi=2**31 - 1)
    nominal = NominalCell.read(r)
    errors = r.table("errors")
    budget = read_budget(errors, preset).with_sources(options.on, options.off)
    errors.done()
    power = r.table("power_source")
    power_budget = read_source_budget(power, preset)
    power.done()
    r.done()
    same = budget == PRESETS[preset] and power_budget == SOURCE_PRESETS[preset]
    return draw_world(nominal, budget, seed, preset if same else f"{preset} (changed)", power_budget)


def world_of(config: Any, options: WorldOptions = WorldOptions()) -> World:
    """The world of a loaded cell config (:class:`celld.config.Config`): its ``[sim]`` table."""
    return world_from_table(config.sim, config.source, options)
