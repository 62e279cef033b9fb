"""A weld's plan from the scan, the calibration, the tool and the part model; the height probe; the figures.

Pure: arrays and configs in, a plan out. The weld job
(:mod:`celld.daemon.weld`) moves the arm, captures and records around it:

0. :func:`for_torch`: the weld's tip height moved so that the torch, measured
   off the tip's height along the finger (a wire cut short or long), sits
   at ``weld.tip_height``: the finger and the torch are one rigid tool;
1. :func:`prepare_part`: the part model sampled for the seam finder and its
   finger wall's offset from the seam at the tip's height (once per model);
2. :func:`plan_weld`: the seam found in the scan (registration of the model,
   the groove measured) and placed in the base frame with the calibration;
   the finger's wall line at ``weld.tip_height`` above it
   (:mod:`celld.seam.weldpath`, the wall where the scan measured it beside the
   seam); the tool's start pose ``LEAD_IN`` along the line, mid-way across
   the joint; and every TCP pose the weld passes through, for the cell check;
3. :func:`probe_targets` and :func:`probed_height`: where the finger touches
   the joint's two walls at the start, and the tip's height in the joint
   from the width found there (the plan moved to the height it should have);
   :func:`touch_check`: from the same touches, how far the joint is from where
   the scan and the calibration put it, across and in height: the
   calibration's error where the weld happens;
4. :func:`precorrected`: with the arm's kinematic calibration, the plan (in
   the calibrated arm's base frame) as the controller is to be sent it;
5. :func:`summarise`: the refined and torch paths of a finished track and its
   figures.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from celld import polyline, se3
from celld.config import ToolConfig, WeldConfig
from celld.config.seam import SeamParams
from celld.errors import TactileError, WorkpieceError
from celld.schemadoc import boolean, const, enum, integer, nullable, number, obj, one_of, string, vector, with_properties
from celld.seam.figures import TRACK_FIGURES_SCHEMA, track_summary
from celld.seam.pipeline import PreparedWorkpiece, SeamPath, find_seam, prepare
from celld.seam.weldpath import (
    WeldGeometry,
    height_from_width,
    joint_width,
    measured_offsets,
    start_pose,
    tool_poses,
    wall_at_height,
    wall_offset,
    weld_geometry,
)
from celld.seam.workpiece import Workpiece
from celld.tactile.fingermap import FingerGain, FingerRefused, Press, fit_finger_gain
from celld.tactile.tool import ToolGeometry

# The tool starts this far along the wall line (m) ...
LEAD_IN = 0.005
# ... and this far off the wall on the free side where the scan did not measure the joint's width (m);
# the servo's touch then travels it at touch_speed (bounded by servo.touch_distance).
CLEARANCE = 0.004
# The weld's path check looks at the tool every this much along the seam, m.
PATH_STEP = 0.01


@dataclass(frozen=True)
class PreparedPart:
    """A part model ready for the seam finder, and its finger wall's offset from the seam at the tip's height (m)."""

    model: PreparedWorkpiece
    wall_offset: float


def for_torch(weld: WeldConfig, torch_height: float) -> WeldConfig:
    """``weld`` with the tip's height over the seam moved by the torch's measured height above the tip along the
    finger (``torch_height``, m; the wire's end above the tip when it is cut short), so that the torch sits at
    ``weld.tip_height`` as with a torch level with the tip.

    Raises
    ------
    WorkpieceError
        The torch stands more than ``weld.max_height_correction`` off the tip's height: the tip would ride too
        far from where the joint was planned for it (trim the wire, or measure the tool again).
    """
    if not math.isfinite(torch_height):
        raise WorkpieceError(f"the measured torch's height from the tip is not a number ({torch_height})")
    if abs(torch_height) > weld.max_height_correction:
        where = "above" if torch_height > 0 else "below"
        raise WorkpieceError(
            f"the measured torch's end stands {abs(torch_height) * 1e3:.2f} mm {where} the tip along the finger, more than "
            f"weld.max_height_correction_mm ({weld.max_height_correction * 1e3:g}) the tip's height can make up; trim the "
            "wire and measure the tool again"
        )
    return replace(weld, tip_height=weld.tip_height - torch_height)


def prepare_part(workpiece: Workpiece, params: SeamParams, tip_height: float) -> PreparedPart:
    """Sample and describe ``workpiece`` for :func:`plan_weld` (once per model, params and tip height)."""
    return PreparedPart(prepare(workpiece, params), wall_offset(workpiece, tip_height, params.finger_wall))


@dataclass(frozen=True)
class WeldPlan:
    """Where the weld goes, base frame (m).

    Attributes
    ----------
    seam : SeamPath
        The seam as the scan placed it, with the walls it measured beside it.
    geometry : WeldGeometry
        The finger's wall line at the tip's height and its plane.
    wall_offset : float
        The model's finger wall offset from the seam at the tip's height.
    T_start, T_above : (4, 4) arrays
        The TCP at the start of the wall line, and ``approach_height`` above it.
    path : (n, 4, 4) array
        Every TCP pose the weld passes through (:func:`weld_path`).
    """

    seam: SeamPath
    geometry: WeldGeometry
    wall_offset: float
    T_start: np.ndarray
    T_above: np.ndarray
    path: np.ndarray

    @property
    def up(self) -> np.ndarray:
        """The seam plane's normal: the approach and retract direction."""
        return self.geometry.T_base_plane[:3, 2]


def plan_weld(
    points_cam: np.ndarray,
    T_base_cam: np.ndarray,
    part: PreparedPart,
    weld: WeldConfig,
    seam_params: SeamParams,
    T_tcp_tool: np.ndarray,
    T_scan: np.ndarray,
) -> WeldPlan:
    """The weld of ``part`` from one scan (camera frame, m, range bias already taken off) placed by ``T_base_cam``.

    Raises
    ------
    WorkpieceError, SeamError
        The part or its seam is not found in the scan (the seam finder's reasons).
    """
    nominal = se3.from_ur_pose(weld.nominal_pose) if weld.nominal_pose else None
    seam = find_seam(points_cam, part.model, T_base_cam, seam_params, nominal)
    # The finger wall where the scan measured it beside the seam (a part's gap and twist move it; the
    # model's constant offset where it was not measured, or where the config trusts the model alone).
    offset = part.wall_offset
    offsets = offset if seam_params.seam_source == "model" else measured_offsets(seam.wall_across, weld.tip_height, offset)
    geometry = weld_geometry(seam.points_base, seam.tangents, seam.normals, seam.plane_normal, offsets, weld.tip_height)
    # The whole path, to check against the cell before the tool moves to it:
    # above the start, down, along the seam, up and back to the scan pose.
    T_start = start_pose(geometry, T_tcp_tool, LEAD_IN, start_clearance(geometry, seam))
    T_above = T_start.copy()
    T_above[:3, 3] += weld.approach_height * geometry.T_base_plane[:3, 2]
    path = weld_path(geometry, T_tcp_tool, T_above, T_start, T_scan, weld.retract_height)
    return WeldPlan(seam, geometry, offset, T_start, T_above, path)


def precorrected(plan: WeldPlan, correct: Callable[[np.ndarray], np.ndarray], T_tcp_tool: np.ndarray) -> WeldPlan:
    """``plan``, made in the calibrated arm's base frame, as the controller is to be sent it.

    ``correct`` maps a TCP pose (4, 4) the arm is to reach to the pose to send the controller
    (:meth:`celld.calib.mount.Placement.precorrect`). Every pose of the plan goes through it but the scan
    pose the path ends on, which is the controller's own (``weld.scan_pose``). The wall and
    seam lines follow the tool: at each point of the wall line the tool's pose there
    (:func:`~celld.seam.weldpath.tool_poses`) is pre-corrected, and the rigid correction that gives
    (``D = T_cmd T^-1``: a fraction of a millimetre, a few mrad) moves that point of both lines and turns
    its tangent and normal; the welding plane follows the first point's. What touch then finds (the probe,
    Algorithm 2) is measured by the controller's own reports, in the frame the plan is now in.
    """
    g = plan.geometry
    leads = polyline.arc_length(g.wall_base)
    D = np.array([correct(T) @ se3.invert(T) for T in tool_poses(g, T_tcp_tool, leads)])
    R, t = D[:, :3, :3], D[:, :3, 3]

    def points(P: np.ndarray) -> np.ndarray:
        return np.einsum("nij,nj->ni", R, P) + t

    def turned(V: np.ndarray) -> np.ndarray:
        return np.einsum("nij,nj->ni", R, V)

    geometry = g._replace(
        T_base_plane=D[0] @ g.T_base_plane,
        wall_base=points(g.wall_base),
        seam_base=points(g.seam_base),
        tangents=turned(g.tangents),
        normals=turned(g.normals),
    )
    # The path's last pose is the scan pose, the controller's own as configured (weld.scan_pose): as it is.
    path = np.array([*(correct(T) for T in plan.path[:-1]), plan.path[-1]])
    return replace(plan, geometry=geometry, T_start=correct(plan.T_start), T_above=correct(plan.T_above), path=path)


def start_clearance(geometry: WeldGeometry, seam: SeamPath) -> float:
    """How far off the finger wall the tip starts: mid-way across the joint where the scan measured its
    other wall at the start (as far from either wall as it can be), else :data:`CLEARANCE`."""
    i = int(geometry.stations([LEAD_IN])[0])
    width = geometry.offsets[i] + wall_at_height(seam.far_wall_across[i : i + 1], geometry.tip_height)[0]
    return float(width) / 2.0 if math.isfinite(width) and width > 0.0 else CLEARANCE


def weld_path(
    geometry: WeldGeometry, T_tcp_tool: np.ndarray, T_above: np.ndarray, T_start: np.ndarray, T_scan: np.ndarray, retract_height: float
) -> np.ndarray:
    """The TCP poses (n, 4, 4) a weld passes through: above the start, the start, along the wall line
    (every PATH_STEP), up by the retract height at the end, back to the scan pose."""
    length = float(polyline.arc_length(geometry.wall_base)[-1])
    track = tool_poses(geometry, T_tcp_tool, np.arange(LEAD_IN + PATH_STEP, length, PATH_STEP))
    T_up = track[-1].copy() if len(track) else T_start.copy()
    T_up[:3, 3] += retract_height * geometry.T_base_plane[:3, 2]
    return np.concatenate([T_above[None], T_start[None], track, T_up[None], T_scan[None]])


@dataclass(frozen=True)
class ProbeTarget:
    """One wall the finger touches at the start: its name, the line to touch along, and the tool riding it."""

    name: str
    line: np.ndarray
    tool: ToolConfig


def probe_targets(plan: WeldPlan, tool_cfg: ToolConfig) -> tuple[list[ProbeTarget], str]:
    """The joint's far wall, then the finger wall, at the tip's height where the scan measured them; or none
    and why the joint cannot tell a height (its walls do not open upwards, or were not measured)."""
    geometry, seam = plan.geometry, plan.seam
    i = int(geometry.stations([LEAD_IN])[0])
    finger, far = seam.wall_across[i], seam.far_wall_across[i]
    try:
        height_from_width(float(finger[0] + far[0]), finger, far)  # the joint can tell a height
    except WorkpieceError as exc:
        return [], str(exc)
    # The far wall at the tip's height, where the scan measured it (its neighbours' between).
    far_line = geometry.seam_base - wall_at_height(seam.far_wall_across, geometry.tip_height)[:, None] * geometry.normals
    other = replace(tool_cfg, wall_side="right" if tool_cfg.wall_side == "left" else "left")
    return [ProbeTarget("far", far_line, other), ProbeTarget("finger", geometry.wall_base, tool_cfg)], ""


def probe_across(plan: WeldPlan) -> tuple[np.ndarray, np.ndarray]:
    """Where a touch's contact is measured: the plane's origin and the direction across the joint at the start."""
    geometry = plan.geometry
    i = int(geometry.stations([LEAD_IN])[0])
    z = geometry.T_base_plane[:3, 2]
    N = geometry.normals[i] - float(geometry.normals[i] @ z) * z
    return geometry.T_base_plane[:3, 3], N / np.linalg.norm(N)


# The JSON shape of touch_check's reading, with the calibration's bound the weld job sets beside it.
TOUCH_CHECK_SCHEMA = obj(
    "The calibration's error where the weld starts, from the height probe's two touches: where the finger found the "
    "joint against where the scan, placed by the calibration (and the arm's corrections), put it. It holds the whole "
    "chain from the scanner to the finger's tip (calibration, arm, tool calibration), which is what the weld rests on.",
    {
        "across_mm": number("The joint's centre as touched minus as scanned, across the joint (positive towards the finger wall)."),
        "height_mm": number("The joint's root as touched minus as scanned, along the welding plane's normal (positive: higher)."),
        "error_mm": number("The norm of the two.", lo=0.0),
        "tip_height_mm": number("The tip's height over the scanned root the plan touched at."),
        "at_base": vector("Where it was checked: the scan's joint centre at the planned tip height, base frame, m (as sent).", 3),
        "across": vector("The direction across the joint there (unit, base frame, towards the finger wall).", 3),
        "up": vector("The welding plane's normal (unit, base frame).", 3),
        "bound_mm": nullable(
            number("The calibration's own 95 % bound on its error away from the calibration box (null: none stored).", lo=0.0)
        ),
        "within_bound": nullable(boolean("Whether that bound covers the error the touches found (null: no bound).")),
        "verdict": enum(
            ("ok", "beyond_bound", "no_bound"),
            "ok: the bound covers the error; beyond_bound: the calibration is off at the weld by more than it says: calibrate again.",
        ),
    },
    ("across_mm", "height_mm", "error_mm", "tip_height_mm", "at_base", "across", "up"),
)


def judged(check: dict[str, Any], bound: float | None) -> dict[str, Any]:
    """A :func:`touch_check` reading with the calibration's own bound at the weld (m; None: it stores none) and
    the verdict: ``ok`` when the bound covers the error, ``beyond_bound`` when the calibration is off there by more
    than it says, ``no_bound`` without one."""
    within = None if bound is None else check["error_mm"] <= bound * 1e3
    return {
        **check,
        "bound_mm": None if bound is None else round(bound * 1e3, 4),
        "within_bound": within,
        "verdict": "no_bound" if within is None else "ok" if within else "beyond_bound",
    }


# The JSON shape of measured_finger's reading.
FINGER_SCHEMA = one_of(
    "The finger's tip deflection for its tag's along the joint's normal, as the probe's touches measured it while they "
    "came onto the walls (celld.tactile.fingermap): the weld's servo tracks with it.",
    obj(
        "Measured: tip = gain d + cubic d^3 for the tag's deformation d.",
        {
            "measured": const(True),
            "gain": number("The tip's deflection over the tag's, at small deflections."),
            "gain_sigma": number("Its 1 sigma from the fit's scatter.", lo=0.0),
            "cubic_per_mm2": number("The cubic term, 1/mm^2."),
            "residual_rms_um": number("The frames' RMS distance from the fit, um.", lo=0.0),
            "frames": integer("Frames fitted, both touches.", lo=0),
            "span_mm": vector("The least and largest tag deformation fitted, mm.", 2),
            "previous": obj(
                "The gain the last probed weld with this tool calibration measured, and how far this one is from it.",
                {
                    "gain": number(),
                    "job": string("The weld that measured it."),
                    "change": number("This gain over that one, less 1."),
                    "changed": boolean(
                        "Beyond FINGER_CHANGE and three sigmas of the two: the finger has changed (wear, a loosened tag); "
                        "also a warning in the log."
                    ),
                },
                ("gain", "job", "change", "changed"),
            ),
        },
        ("measured", "gain", "gain_sigma", "cubic_per_mm2", "residual_rms_um", "frames", "span_mm"),
    ),
    obj(
        "Not measured by this weld (not probed, or its touches came onto their walls too fast for the camera): the gain "
        "the last probed weld with this tool calibration measured (stored), or without one the tag's deformation taken "
        "as the tip's.",
        {
            "measured": const(False),
            "why": string(),
            "stored": obj(
                "The kept gain the weld tracked with.",
                {"gain": number(), "cubic_per_mm2": number(), "job": string("The weld that measured it."), "at": string()},
                ("gain", "cubic_per_mm2", "job", "at"),
            ),
        },
        ("measured", "why"),
    ),
)

# A finger whose gain moved by more than this share (and three sigmas of the two measurements) since the last
# probed weld has changed: its wear, or its tag working loose.
FINGER_CHANGE = 0.03


def compared_finger(reading: dict[str, Any], gain: float, sigma: float, job: str) -> dict[str, Any]:
    """A measured :data:`FINGER_SCHEMA` reading with the last weld's gain (``gain``, its 1 sigma ``sigma``, from the
    weld ``job``) beside it: how far it moved and whether that is beyond :data:`FINGER_CHANGE` and its scatter."""
    change = reading["gain"] / gain - 1.0
    noise = 3.0 * math.hypot(reading["gain_sigma"], sigma) / gain
    return {
        **reading,
        "previous": {"gain": gain, "job": job, "change": round(change, 5), "changed": abs(change) > max(FINGER_CHANGE, noise)},
    }


def measured_finger(presses: list[Press], delta_d: float) -> tuple[FingerGain, dict[str, Any]]:
    """The finger's gain from the probe's touches (:func:`celld.tactile.fingermap.fit_finger_gain`) and its reading
    (:data:`FINGER_SCHEMA`); Eq. 15 as is, and why, when the touches cannot tell it.

    Raises
    ------
    FingerRefused
        The touches measured a gain no working finger has: the weld does not go on with it.
    """
    try:
        fit = fit_finger_gain(presses, delta_d)
    except FingerRefused:
        raise
    except TactileError as exc:
        return FingerGain(), {"measured": False, "why": str(exc)}
    return fit.finger, {"measured": True, **fit.as_dict()}


# The JSON shape of what probed_height found (a joint that was probed).
PROBED_SCHEMA = obj(
    "The tip's height in the joint, probed by touch at the start: the joint's width where the finger met its two walls, "
    "the height that width gives, and the plan's correction to it; the calibration's error there (touch_check); and the "
    "finger's gain the touches measured (finger).",
    {
        "probed": const(True),
        "joint_width_mm": number("The joint's width at the tip, from the two touches."),
        "scan_width_mm": number("Its width there as the scan measured it, at the planned height."),
        "height_mm": number("The tip's height above the seam that the width gives."),
        "height_correction_mm": number("How far the plan moved up (positive) or down to the height it should have."),
        "touch_check": TOUCH_CHECK_SCHEMA,
        "finger": FINGER_SCHEMA,
    },
    ("probed", "joint_width_mm", "scan_width_mm", "height_mm", "height_correction_mm", "touch_check", "finger"),
)


def touch_check(plan: WeldPlan, touches: dict[str, float], height: float) -> dict[str, Any]:
    """The calibration's error at the weld's start from the probe's two touches (``touches`` as for
    :func:`probed_height`; ``height``, m, the tip's height in the joint they gave): :data:`TOUCH_CHECK_SCHEMA`
    but the bound (:func:`judged`).

    Across: the midpoint of the two walls as touched (each touch is the tip's centre, a radius from its wall on
    either side, so the radii cancel) against the midpoint of the scan's walls at ``height``, both along
    :func:`probe_across`. In height: the plan put the tip ``tip_height`` above the scanned root, the width says it
    stands ``height`` above the true one; the root is higher than scanned by the difference.
    """
    geometry, seam = plan.geometry, plan.seam
    i = int(geometry.stations([LEAD_IN])[0])
    origin, across = probe_across(plan)
    finger, far = seam.wall_across[i], seam.far_wall_across[i]
    y_seam = float((geometry.seam_base[i] - origin) @ across)
    centre_scan = y_seam + 0.5 * (float(finger[0] + finger[1] * height) - float(far[0] + far[1] * height))
    centre_touch = 0.5 * (touches["finger"] + touches["far"])
    d_across, d_height = centre_touch - centre_scan, geometry.tip_height - height
    return {
        "across_mm": round(float(d_across) * 1e3, 4),
        "height_mm": round(float(d_height) * 1e3, 4),
        "error_mm": round(math.hypot(d_across, d_height) * 1e3, 4),
        "tip_height_mm": round(geometry.tip_height * 1e3, 4),
        "at_base": [round(float(v), 7) for v in geometry.seam_base[i]],
        "across": [round(float(v), 7) for v in across],
        "up": [round(float(v), 7) for v in geometry.T_base_plane[:3, 2]],
    }


def probed_height(
    plan: WeldPlan,
    touches: dict[str, float],
    finger_reading: dict[str, Any],
    tool: ToolGeometry,
    T_tcp_tool: np.ndarray,
    max_correction: float,
) -> tuple[dict[str, Any], WeldPlan]:
    """The tip's height in the joint from where the finger met its two walls (``touches``: ``far`` and
    ``finger``, m across the joint, found with the finger's gain whose reading is ``finger_reading``,
    :func:`measured_finger`), and the plan moved to the height it should have.

    Raises
    ------
    WorkpieceError
        The probed height is more than ``max_correction`` off the plan's (the calibration or the tool is off).
    """
    geometry, seam = plan.geometry, plan.seam
    i = int(geometry.stations([LEAD_IN])[0])
    finger, far = seam.wall_across[i], seam.far_wall_across[i]
    width = touches["finger"] - touches["far"] + 2.0 * tool.tip_radius
    height = height_from_width(width, finger, far)
    dh = height - geometry.tip_height
    found = {
        "probed": True,
        "joint_width_mm": round(width * 1e3, 4),
        "scan_width_mm": round(joint_width(finger, far, geometry.tip_height) * 1e3, 4),
        "height_mm": round(height * 1e3, 4),
        "height_correction_mm": round(-dh * 1e3, 4),
        "touch_check": touch_check(plan, touches, height),
        "finger": finger_reading,
    }
    if abs(dh) > max_correction:
        raise WorkpieceError(
            f"the tip stands {height * 1e3:.2f} mm above the seam where the plan puts it at {geometry.tip_height * 1e3:.2f} mm "
            f"(the joint is {width * 1e3:.2f} mm wide there; at most {max_correction * 1e3:.1f} mm off is corrected): "
            "check the calibration and the tool"
        )
    # The plan's lines and plane moved along its normal to the height they should have: the plan as it is, so a
    # plan pre-corrected through the arm's calibration (precorrected) keeps its correction; for one that is not,
    # the same as building it again from the seam at that height (celld.seam.weldpath.weld_geometry).
    shift = -dh * geometry.T_base_plane[:3, 2]
    T_plane = geometry.T_base_plane.copy()
    T_plane[:3, 3] += shift
    moved = geometry._replace(
        T_base_plane=T_plane,
        wall_base=geometry.wall_base + shift,
        seam_base=geometry.seam_base + shift,
        tip_height=geometry.tip_height - dh,
    )
    T_start = start_pose(moved, T_tcp_tool, LEAD_IN, start_clearance(geometry, seam))
    return found, replace(plan, geometry=moved, T_start=T_start)


# The JSON shape of summarise's figures.
FIGURES_SCHEMA = with_properties(
    TRACK_FIGURES_SCHEMA,
    {
        "wall_offset_mm": number("The part model's finger wall offset from the seam at the tip's height."),
        "wall_offset_used_mm": vector("The finger wall's distance from the seam as the weld used it (the scan's), least and most.", 2),
        "seam_length_mm": number("The seam's length.", lo=0.0),
    },
    ("wall_offset_mm", "wall_offset_used_mm", "seam_length_mm"),
    desc="The figures of a finished weld: the track's (celld.seam.figures), the finger wall's offsets and the seam's length.",
)


def summarise(records: np.ndarray, plan: WeldPlan, tool: ToolGeometry, delta_d: float) -> tuple[dict[str, Any], dict[str, Any]]:
    """The figures of a finished track (:data:`FIGURES_SCHEMA`) and its paths (planned, planned wall, refined, torch; base frame, m)."""
    geometry = plan.geometry
    track = track_summary(records, geometry, tool, delta_d)
    paths = {
        "frame": "base",
        "units": "m",
        "planned": geometry.seam_base.tolist(),
        "planned_wall": geometry.wall_base.tolist(),
        "refined": track.refined.tolist(),
        "torch": track.torch.tolist(),
    }
    figures = {
        **track.figures,
        "wall_offset_mm": round(plan.wall_offset * 1e3, 4),
        # The finger wall's distance from the seam as the weld used it (the scan's, where it measured it).
        "wall_offset_used_mm": [round(float(geometry.offsets.min()) * 1e3, 4), round(float(geometry.offsets.max()) * 1e3, 4)],
        "seam_length_mm": round(plan.seam.length * 1e3, 2),
    }
    return figures, paths
