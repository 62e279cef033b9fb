"""A drawn world as a document: every error source by name, on or off, its budget, what the world drew, its anchor.

``celld sim world --config C [--preset P] [--world-seed N] [--with S] [--without S] [--json]`` prints it
(:func:`world_report`). The budget is in the units of the ``[sim.errors]`` keys (:data:`celld.sim.world.ERROR_KEYS`),
the drawn values in mm, degrees, seconds and their own units as their names say. The anchor says where a size
comes from: a datasheet, a standard, a paper, a measurement, or that it is a plausible choice. The daemon never
reads any of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from celld.calib.flange import preset as flange_preset
from celld.robot import kinematics as kin
from celld.sim.world import ERROR_KEYS, SOURCES, ErrorBudget, World

# Each source's magnitudes in the budget (ErrorBudget's fields; the flange's ISO fits are the standard's, not the budget's).
SOURCE_BUDGET: dict[str, tuple[str, ...]] = {
    "factory_calibration": ("factory_length", "factory_twist", "factory_joint_zero"),
    "kinematics": ("dh_length", "dh_twist", "joint_offset"),
    "repeatability": ("repeatability",),
    "encoder_noise": ("encoder_noise",),
    "robot2_placement": ("base_translation", "base_rotation"),
    "compliance": (
        "stiffness_shoulder",
        "stiffness_elbow",
        "stiffness_wrist",
        "link_mass_spread",
        "payload_mass_spread",
        "payload_com_offset",
    ),
    "hose_pull": ("hose_force",),
    "thermal": ("warm_rise", "warmup_tau"),
    "lost_motion": ("lost_motion",),
    "settle": ("settle_amplitude", "settle_tau", "settle_hz"),
    "capture_delay": ("capture_delay",),
    "camera_jitter": ("camera_stamp_sigma", "camera_delivery_jitter"),
    "scanner_mount": ("mount_translation", "mount_rotation"),
    "depth_scale": ("depth_scale",),
    "distortion": ("distortion",),
    "metal_bias": ("metal_bias",),
    "flange_tolerance": (),
    "flange_variant": ("chamfer", "bore_depth", "hole_depth"),
    "tool_offsets": ("tip_offset", "torch_offset", "tool_rotation", "tip_radius"),
    "finger": ("stiffening", "hysteresis", "static_friction_ratio"),
    "tag_map": ("tag_position", "tag_anisotropy", "tag_softening"),
    "srm_camera": ("srm_focal", "srm_principal_point", "tag_print", "srm_mount_translation", "srm_mount_rotation"),
    "part_placement": ("placement_offset", "placement_yaw"),
    "part_shape": ("bow", "bow_vertical", "twist", "tack_kink", "gap_variation"),
}

# Where each source's size comes from (the budget's comments in celld/sim/world.py say it at length).
ANCHORS: dict[str, str] = {
    "factory_calibration": "the UR ROS driver's calibration notes (positions off by up to centimetres without the "
    "robot's own calibration); sized to 1-5 mm at the flange; plausible",
    "kinematics": "a factory-calibrated UR e-series arm's absolute error, 0.3-1 mm at the flange; UR publishes "
    "repeatability only; plausible",
    "repeatability": "the UR10e datasheet's +-0.05 mm pose repeatability (ISO 9283)",
    "encoder_noise": "UR's absolute encoders resolve about 1e-6 rad; plausible",
    "robot2_placement": "a base placed by tape and square; plausible",
    "compliance": "a 0.2-0.7 mm sag at weld poses with a 1.6 kg tool (research notes: arm and weld process); "
    "harmonic drives of these sizes; plausible",
    "hose_pull": "a MIG hose package hung from a boom; plausible",
    "thermal": "aluminium links, 23 um/m/K: 0.1-0.3 mm between cold and warm (research notes)",
    "lost_motion": "a few arc seconds per joint, within the datasheet's repeatability; plausible",
    "settle": "a UR10e's wrist ringing down after a stop; plausible",
    "capture_delay": "the PhoXi M datasheet's 0.25-2.75 s scan",
    "camera_jitter": "a USB camera stamped by its driver; plausible",
    "scanner_mount": "a bracket on a frame 1 m above the table; plausible",
    "depth_scale": "the PhoXi M datasheet's calibration accuracy, 0.1 mm (1 sigma)",
    "distortion": "the PhoXi M datasheet's calibration accuracy, 0.1 mm (1 sigma), scaled by each model's noise",
    "metal_bias": "time-of-flight users report 8-15 mm on metal; plausible",
    "flange_tolerance": "ISO 9409-1: d2 h8, d3 H7",
    "flange_variant": "a real part's edge break and hole depths, not the preset's; plausible",
    "tool_offsets": "a hand-assembled welding tool, 1-2 mm off its drawing; plausible",
    "finger": "a soft printed metamaterial finger; plausible",
    "tag_map": "Euler-Bernoulli: a tag at 90-100 % of the finger's bending length moves 0.85-1.0 of the tip; the SRM "
    "family's body deformation estimated to 2.1 % of its length (arXiv 2312.09863)",
    "srm_camera": "what a checkerboard calibration (Zhang's method) of a 640 x 480 camera leaves; a tag's print tolerance; plausible",
    "part_placement": "a manual fixture: centimetres and degrees",
    "part_shape": "tack-welded 10 mm plates: 1-3 mm in all; plausible",
}


def _mm(v: Any) -> Any:
    return np.round(np.asarray(v, dtype=np.float64) * 1e3, 4).tolist()


def _deg(v: Any) -> Any:
    return np.round(np.degrees(np.asarray(v, dtype=np.float64)), 5).tolist()


def _pose_off(T: Any, T_drawn: Any) -> dict[str, float]:
    """How far a pose is from its drawing: translation (mm) and rotation angle (deg)."""
    T, T_drawn = np.asarray(T, dtype=np.float64), np.asarray(T_drawn, dtype=np.float64)
    angle = Rotation.from_matrix(T_drawn[:3, :3].T @ T[:3, :3]).magnitude()
    return {
        "translation_mm": round(float(np.linalg.norm(T[:3, 3] - T_drawn[:3, 3])) * 1e3, 4),
        "rotation_deg": round(math.degrees(angle), 5),
    }


def _table_off(table: kin.DH, reference: kin.DH) -> dict[str, Any]:
    return {
        "d_mm": _mm(np.subtract(table.d, reference.d)),
        "a_mm": _mm(np.subtract(table.a, reference.a)),
        "alpha_deg": _deg(np.subtract(table.alpha, reference.alpha)),
        "theta_deg": _deg(np.subtract(table.theta, reference.theta)),
    }


def _drawn(world: World) -> dict[str, Callable[[], dict[str, Any]]]:
    """What the world drew for each source, as a function (some need the part or a second robot)."""
    a, sc, f, t, fi, p, r2 = world.arm, world.scanner, world.flange, world.tool, world.finger, world.part, world.robot2
    published = kin.model(world.nominal.robot).dh
    f0 = flange_preset(world.nominal.flange)
    return {
        "factory_calibration": lambda: {"controller_table_vs_published": _table_off(world.nominal_dh, published)},
        "kinematics": lambda: {
            "true_table_vs_controller": _table_off(a.dh, world.nominal_dh),
            "joint_offsets_deg": _deg(a.joint_offsets),
        },
        "repeatability": lambda: {"rest_error_sigma_deg": _deg(a.repeatability)},
        "encoder_noise": lambda: {"sigma_deg": _deg(a.encoder_noise)},
        "robot2_placement": lambda: {"robot2": None if r2 is None else _pose_off(r2.T_base1_base2, r2.T_base1_base2_drawn)},
        "compliance": lambda: {
            "compliance_rad_per_nm": [float(c) for c in a.compliance],
            "payload_kg": round(float(a.payload_mass), 4),
            "payload_com_mm": _mm(a.payload_com),
        },
        "hose_pull": lambda: {"force_n": np.round(np.asarray(a.hose_force, dtype=np.float64), 3).tolist(), "at_mm": _mm(a.hose_point)},
        "thermal": lambda: {"warm_rise_k": round(float(a.warm_rise), 3), "warmup_tau_s": float(a.warmup_tau)},
        "lost_motion": lambda: {"full_width_deg": _deg(a.lost_motion)},
        "settle": lambda: {"kick_sigma_deg": _deg(a.settle_amplitude), "tau_s": a.settle_tau, "hz": a.settle_hz},
        "capture_delay": lambda: {"range_s": list(sc.capture_delay)},
        "camera_jitter": lambda: {
            "stamp_sigma_ms": world.camera.stamp_sigma * 1e3,
            "delivery_jitter_ms": world.camera.delivery_jitter * 1e3,
        },
        "scanner_mount": lambda: (
            _pose_off(sc.T_mount_cam, world.nominal.T_base_cam)
            if not sc.link
            else {"on_link": sc.link, "T_link_cam_mm": _mm(np.asarray(sc.T_mount_cam)[:3, 3])}
        ),
        "depth_scale": lambda: {"depth_scale": sc.depth_scale},
        "distortion": lambda: {
            "field": sc.field is not None,
            "largest_coefficient_mm": _mm(np.abs(np.asarray(sc.field.coefficients)).max()) if sc.field else 0.0,
        },
        "metal_bias": lambda: {"bias_mm": None if sc.metal_bias is None else _mm(sc.metal_bias)},
        "flange_tolerance": lambda: {
            "outer_diameter_off_drawing_mm": _mm(f.outer_diameter - f0.outer_diameter),
            "bore_diameter_off_drawing_mm": _mm(f.bore_diameter - f0.bore_diameter),
            "thickness_off_drawing_mm": _mm(f.thickness - f0.thickness),
        },
        "flange_variant": lambda: {"chamfer_mm": _mm(f.chamfer), "bore_depth_mm": _mm(f.bore_depth), "hole_depth_mm": _mm(f.hole_depth)},
        "tool_offsets": lambda: {
            "tip_off_drawing_mm": _mm(np.subtract(t.config.tip_tcp, t.nominal.tip_tcp)),
            "torch_off_drawing_mm": _mm(np.subtract(t.p_flange_torch, t.p_flange_torch_nominal)),
            "tip_radius_mm": _mm(t.config.tip_radius),
        },
        "finger": lambda: {
            "stiffening_mm": None if math.isinf(fi.stiffening) else _mm(fi.stiffening),
            "hysteresis_mm": _mm(fi.hysteresis),
            "static_friction_ratio": fi.static_friction_ratio,
        },
        "tag_map": lambda: {
            "tag_gain_xy": [round(g, 5) for g in fi.tag_gain],
            "tag_softening_mm": None if math.isinf(fi.tag_softening) else _mm(fi.tag_softening),
        },
        "srm_camera": lambda: {
            "intrinsics_px": [round(v, 3) for v in world.srm.intrinsics_px],
            "tag_size_mm": _mm(world.srm.tag_size),
            "mount": None if world.srm.T_tool_cam is None else _pose_off(world.srm.T_tool_cam, t.nominal.T_tool_cam),
        },
        "part_placement": lambda: {"part": None} if p is None else {"offset_mm": _mm(p.offset_xy), "yaw_deg": _deg(p.yaw)},
        "part_shape": lambda: (
            {"part": None}
            if p is None
            else {
                "bow_mm": _mm(p.shape.bow),
                "bow_vertical_mm": _mm(p.shape.bow_vertical),
                "twist_deg": _deg(p.shape.twist),
                "tacks_mm": [_mm(k) for _, k in p.shape.tacks],
                "gap_amplitude_mm": _mm(p.shape.gap_amplitude),
            }
        ),
    }


def budget_of(budget: ErrorBudget, source: str) -> dict[str, Any]:
    """A source's magnitudes in the units of their ``[sim.errors]`` keys."""
    out: dict[str, Any] = {}
    for name in SOURCE_BUDGET[source]:
        key, scale, _ = ERROR_KEYS[name]
        v = getattr(budget, name)
        out[key] = [round(x / scale, 9) for x in v] if isinstance(v, tuple) else round(v / scale, 9)
    return out


def world_report(world: World) -> dict[str, Any]:
    """The world as a document (module docstring): its preset and seed, and each source in :data:`SOURCES` order."""
    drawn = _drawn(world)
    return {
        "preset": world.preset,
        "seed": world.seed,
        "sources": [
            {
                "name": s,
                "on": world.budget.on(s),
                "budget": budget_of(world.budget, s),
                "drawn": drawn[s](),
                "anchor": ANCHORS[s],
            }
            for s in SOURCES
        ],
    }


def report_lines(report: dict[str, Any]) -> list[str]:
    """The report as text: one line per source."""
    lines = [f"world: preset {report['preset']}, seed {report['seed']}"]
    for s in report["sources"]:
        state = "on " if s["on"] else "off"
        lines.append(f"  {state} {s['name']}: {s['drawn']}")
        lines.append(f"      budget {s['budget']}; {s['anchor']}")
    return lines
