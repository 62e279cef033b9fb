"""The seam finder's parameters: registration, groove measurement and the seam, with presets per scanner; and the ``[seam]`` table.

Pure values, no Open3D: the seam finder (:mod:`celld.seam.register`,
:mod:`celld.seam.groove`, :mod:`celld.seam.pipeline`) takes a
:class:`SeamParams`, and the cell config reads its ``[seam]`` table into one
(:func:`read_seam`: the scanner's preset with the table over it) without
loading the point-cloud libraries the finder uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from celld.config.reader import TableReader
from celld.errors import InputError

SEAM_SOURCES = ("auto", "groove", "model")


@dataclass(frozen=True)
class RegistrationParams:
    """Tuning of the registration (SI units).

    ``voxel`` sets the scale of the global step: FPFH radius ``5 voxel``,
    normals ``2 voxel``, RANSAC correspondences ``1.5 voxel``. ``icp_points``
    (scan points kept) and ``icp_distance`` set the fine ICP; ``gate_distance`` and
    ``min_fitness`` set the gate. RANSAC rejects samples whose matched normals
    differ by more than ``max_normal_angle`` and, given a nominal pose, poses
    turned more than ``max_rotation`` from it about any axis.
    """

    voxel: float = 0.004
    icp_points: int = 20_000
    icp_distance: float = 0.001
    # A part as made is off its model by millimetres (bow, twist, tack welds):
    # the gate takes that; where the part truly is comes from the groove the
    # scan measures (seam_source "auto"), not from the rigid fit.
    gate_distance: float = 0.003
    min_fitness: float = 0.9
    attempts: int = 6
    ransac_iterations: int = 20_000
    max_normal_angle: float = math.radians(30.0)
    max_rotation: float = math.radians(45.0)
    ransac_confidence: float = 0.999
    model_spacing: float = 0.0005
    edge_margin: float = 0.0015
    seed: int = 0


@dataclass(frozen=True)
class GrooveParams:
    """Tuning of the groove measurement (SI units).

    window : seam length per pair of wall fits, m
    max_window : a wall with fewer than ``min_points`` in ``window`` is fitted
        over a window doubled up to this length, m
    step : distance between window centres, m
    min_points : fewest points on each wall in a window
    max_normal_deviation : largest angle (rad) between a fitted wall and the model's
    min_wall_angle : smallest angle (rad) between the two walls for a usable apex
    max_apex_sigma : largest 1-sigma apex uncertainty (m) a window may have
    """

    window: float = 0.010
    max_window: float = 0.040
    step: float = 0.002
    min_points: int = 15
    max_normal_deviation: float = math.radians(12.0)
    min_wall_angle: float = math.radians(20.0)
    max_apex_sigma: float = 0.25e-3


@dataclass(frozen=True)
class SeamParams:
    """Everything :func:`find_seam` can be tuned by (SI units).

    Attributes
    ----------
    registration, groove : parameters of the two stages
    spacing : output point spacing along the seam, m
    table_z : height of the table top in the base frame, m, or None to
        measure the table plane in each scan (the largest near-horizontal
        plane in the region of interest); points up to ``table_margin``
        above the table are the table and are dropped
    table_tolerance : inlier distance of the table plane fit, m
    outlier_radius, outlier_neighbours : a point with fewer neighbours than
        this within the radius (m) is dropped; radius 0 keeps all
    roi_min, roi_max : base-frame box where the part may be, m
    max_range : a camera-frame range beyond this is taken as wrong units, m
    min_points : fewest part points a usable scan has
    label_distance : a scan point within this of a model wall sample counts
        as on that wall, m
    view_cos : a model wall sample facing the camera more than this cosine
        should be seen by it
    support_distance : such a sample is seen when a scan point lies this close, m
    min_coverage : share of seam stations that must have scan points near them
    min_wall_support : share of the should-be-seen wall samples that must be seen
    min_across_support : share of the scan points near the seam that must lie
        on faces facing across it (else the registration cannot place it sideways)
    min_visible_wall : fewest wall samples (0.5 mm apart) the camera must be
        able to see for the joint to count as visible
    seam_source : ``"auto"`` (groove where measured, else the registered
        model), ``"groove"`` (refuse unless measured) or ``"model"``
    min_groove_coverage : share of stations the groove must be measured at
        for it to be the seam
    max_gap : longest stretch (m) of seam without a groove window that is
        bridged by interpolation
    max_contradicting : share of groove windows that may contradict the
        model before the scan is refused
    max_model_deviation : largest distance between the measured and the
        registered seam accepted, m
    deviation_span : the groove's offsets from the model are smoothed along
        the seam over this length, m
    deviation_sigmas : in ``"auto"``, the measured seam replaces the model's
        only where somewhere it differs by more than this many of its own
        standard errors; otherwise the (more precise) registered seam stands,
        confirmed by the groove
    tangent_span : length over which tangents are taken, m
    finger_wall : ``"left"`` or ``"right"`` of travel; the normals point to it
    """

    registration: RegistrationParams = field(default_factory=RegistrationParams)
    groove: GrooveParams = field(default_factory=GrooveParams)
    spacing: float = 0.001
    table_z: float | None = None
    table_margin: float = 0.002
    table_tolerance: float = 0.001
    outlier_radius: float = 0.0
    outlier_neighbours: int = 8
    roi_min: tuple[float, float, float] = (-0.2, -1.0, -0.1)
    roi_max: tuple[float, float, float] = (1.4, 1.0, 0.6)
    max_range: float = 4.0
    min_points: int = 500
    label_distance: float = 0.002
    view_cos: float = 0.34  # cos 70 deg: the scanners return up to 75-80 deg of incidence
    support_distance: float = 0.0015
    min_coverage: float = 0.95
    min_wall_support: float = 0.5
    min_across_support: float = 0.02
    min_visible_wall: int = 200
    seam_source: str = "auto"
    min_groove_coverage: float = 0.9
    max_gap: float = 0.010
    max_contradicting: float = 0.2
    max_model_deviation: float = 0.003
    deviation_span: float = 0.030
    deviation_sigmas: float = 3.5
    tangent_span: float = 0.004
    finger_wall: str = "left"

    def __post_init__(self) -> None:
        if self.seam_source not in SEAM_SOURCES:
            raise InputError(f"seam_source: expected one of {', '.join(SEAM_SOURCES)}, got {self.seam_source!r}")
        if self.finger_wall not in ("left", "right"):
            raise InputError(f"finger_wall: expected 'left' or 'right', got {self.finger_wall!r}")
        if not 0.0 < self.spacing <= 0.05:
            raise InputError(f"spacing: expected 0 < spacing <= 0.05 m, got {self.spacing}")
        if self.registration.attempts < 1:
            raise InputError(f"registration.attempts: expected at least 1, got {self.registration.attempts}")
        if not all(a < b for a, b in zip(self.roi_min, self.roi_max)):
            raise InputError(f"roi_min {self.roi_min} must be below roi_max {self.roi_max} on every axis")

    @classmethod
    def for_scanner(cls, model: str, **overrides: Any) -> SeamParams:
        """Defaults tuned for a scanner model (``phoxi-s``, ``phoxi-m``, ``azure-kinect``)."""
        if model not in PRESETS:
            raise InputError(f"no seam preset for scanner {model!r}; known: {', '.join(PRESETS)}")
        return replace(PRESETS[model], **overrides)


PRESETS: dict[str, SeamParams] = {
    "phoxi-s": SeamParams(),
    "phoxi-m": SeamParams(),
    # Millimetres of noise and flying pixels: coarser voxels, wider gates, long
    # groove windows; the groove is used only where its apex is measured well.
    "azure-kinect": SeamParams(
        registration=RegistrationParams(voxel=0.005, icp_points=10_000, icp_distance=0.008, gate_distance=0.008, min_fitness=0.8),
        groove=GrooveParams(window=0.040, step=0.005, min_points=25, max_normal_deviation=math.radians(20.0), max_apex_sigma=0.8e-3),
        table_margin=0.006,
        table_tolerance=0.006,
        outlier_radius=0.008,
        outlier_neighbours=10,
        label_distance=0.006,
        support_distance=0.008,
        min_wall_support=0.3,
        max_gap=0.04,
        max_model_deviation=0.006,
        tangent_span=0.010,
    ),
}


# A seam region of interest beyond this from the base is not a cell's, m.
_ROI_BOUND = 5.0


def read_seam(r: TableReader, scanner_model: str, finger_wall: str) -> SeamParams:
    """Read the ``[seam]`` table: the scanner's preset with ``seam_source``,
    ``spacing_mm``, ``table_z`` (omit to measure the table),
    ``max_model_deviation_mm``, ``seed`` and the region of interest
    ``roi_min`` / ``roi_max`` (base frame, m: where the part may be; a
    wide-angle camera such as the Azure Kinect sees the robot's base inside
    the default box) over it. The finger's wall is the tool's (``[tool] wall_side``)."""
    r.refuse_moved({"finger_wall": "[tool] wall_side (the seam's normals point to the finger's wall)"})
    base = SeamParams.for_scanner(r.str("preset", scanner_model, choices=tuple(PRESETS)))
    table_z = r.float("table_z", 0.0, lo=-2.0, hi=2.0) if r.has("table_z") else None
    x0, y0, z0 = r.vector("roi_min", 3, list(base.roi_min), bound=_ROI_BOUND, what=" m (base frame)")
    x1, y1, z1 = r.vector("roi_max", 3, list(base.roi_max), bound=_ROI_BOUND, what=" m (base frame)")
    roi_min, roi_max = (x0, y0, z0), (x1, y1, z1)
    if not all(a < b for a, b in zip(roi_min, roi_max)):
        raise r.error("roi_max", f"expected above roi_min {list(roi_min)} on every axis, got {list(roi_max)}")
    return replace(
        base,
        roi_min=roi_min,
        roi_max=roi_max,
        seam_source=r.str("seam_source", base.seam_source, choices=SEAM_SOURCES),
        spacing=r.float("spacing_mm", base.spacing * 1e3, lo=0.1, hi=50.0, scale=1e-3),
        finger_wall=finger_wall,
        table_z=table_z,
        max_model_deviation=r.float("max_model_deviation_mm", base.max_model_deviation * 1e3, lo=0.0, hi=50.0, open_lo=True, scale=1e-3),
        registration=replace(base.registration, seed=r.int("seed", base.registration.seed, lo=0)),
    )
