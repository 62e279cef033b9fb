"""What a weld did along its seam: the refined and torch paths and the tracking figures (pure).

:func:`track_summary` reads the motion loop's records of one Algorithm 2 run
(:data:`celld.motion.channels.STATE_DTYPE`) and returns the paths (base
frame, m) and the figures a weld job reports: how far it tracked, how long
the arc was on, the deformation's error from ``delta_d``, how far the refined
path lies from the planned seam (the tactile correction), the loop's timing
and the frame-to-command latency. :func:`lateral_error` scores a path
against a seam in the welding plane (the demo and benchmarks score the torch
path against the simulator's true seam with it).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from celld import polyline, se3
from celld.errors import CelldError
from celld.schemadoc import integer, number, obj
from celld.seam.weldpath import WeldGeometry, in_plane
from celld.tactile.fingermap import FingerGain, Press
from celld.tactile.tool import ToolGeometry

Array = NDArray[np.float64]

# Torch path points are kept at least this far apart (m).
TORCH_STEP = 0.0005


class TrackSummary(NamedTuple):
    """The paths (base frame, m) and the figures of one track."""

    refined: Array  # (n, 3) the refined path, as Algorithm 2 recorded it
    torch: Array  # (m, 3) the torch while the arc was on (or while tracking, on a dry run)
    figures: dict[str, Any]  # TRACK_FIGURES_SCHEMA


# The JSON shape of TrackSummary.figures (null: nothing to measure it on).
TRACK_FIGURES_SCHEMA = obj(
    "The figures of one track.",
    {
        "duration_s": number("How long the servo ran.", lo=0.0),
        "tracked_mm": number("Length of the refined path.", lo=0.0),
        "arc_on_s": number("How long the arc was on.", lo=0.0),
        "delta_n_error_rms_mm": number("RMS of |delta_n| - delta_d while tracking.", null=True),
        "correction_rms_mm": number("RMS in-plane distance of the refined path from the planned seam (the tactile correction).", null=True),
        "correction_max_mm": number("Its largest.", null=True),
        "omega_peak": number("Largest angular speed commanded, rad/s.", lo=0.0),
        "loop_late_p99_ms": number("The motion loop's wake-up lateness while the servo ran, 99th percentile."),
        "loop_late_max_ms": number("Its largest."),
        "loop_cycles_late_2ms": integer("Cycles woken more than 2 ms late.", lo=0),
        "loop_cycles": integer("Cycles the servo ran.", lo=0),
        "frame_to_command_median_ms": number("From a camera frame to the command that first used it, median.", null=True),
        "frame_to_command_p99_ms": number("Its 99th percentile.", null=True),
    },
    (
        "duration_s",
        "tracked_mm",
        "arc_on_s",
        "delta_n_error_rms_mm",
        "correction_rms_mm",
        "correction_max_mm",
        "omega_peak",
        "loop_late_p99_ms",
        "loop_late_max_ms",
        "loop_cycles_late_2ms",
        "loop_cycles",
        "frame_to_command_median_ms",
        "frame_to_command_p99_ms",
    ),
)


def lateral_offsets(geometry: WeldGeometry, P_base: Array, line_base: Array) -> Array:
    """Signed in-plane distance (m) of points from a polyline, positive towards the finger wall."""
    d, _ = polyline.signed_offset(in_plane(geometry, P_base), in_plane(geometry, line_base))
    # Plane y is left of the first tangent; the normals point to the finger wall.
    side = 1.0 if float(geometry.normals[0] @ geometry.T_base_plane[:3, 1]) > 0.0 else -1.0
    return side * d


def lateral_error(P_base: Array, seam_base: Array, T_base_plane: Array) -> dict[str, float]:
    """Distance (mm) of path points from a seam in the welding plane ``T_base_plane``: RMS and max.

    Heights along the plane normal are left out; only points alongside the
    seam count (a point beyond either end of it has no lateral error), and
    ``outside`` says how many were left out.
    """
    R, o = T_base_plane[:3, :3], T_base_plane[:3, 3]

    def flat(P: Array) -> Array:
        return ((np.asarray(P, dtype=np.float64).reshape(-1, 3) - o) @ R)[:, :2]

    Q = flat(P_base)
    d, inside = polyline.signed_offset(Q, flat(seam_base))
    e = np.abs(d[inside])
    if len(e) == 0:
        return {"rms_mm": float("nan"), "max_mm": float("nan"), "points": 0, "outside": int(len(Q))}
    return {
        "rms_mm": float(np.sqrt(np.mean(e**2))) * 1e3,
        "max_mm": float(e.max()) * 1e3,
        "points": int(len(e)),
        "outside": int(len(Q) - len(e)),
    }


def height_over_root(P_base: Array, seam_base: Array, T_base_plane: Array) -> dict[str, float]:
    """Height (mm) of path points over a seam's root line along the welding plane's normal: mean, min, max.

    The root's height is taken where each point lies alongside it (its foot
    in the plane); points beyond either end are left out, as by
    :func:`lateral_error`.
    """
    R, o = T_base_plane[:3, :3], T_base_plane[:3, 3]
    Q = (np.asarray(P_base, dtype=np.float64).reshape(-1, 3) - o) @ R
    S = (np.asarray(seam_base, dtype=np.float64).reshape(-1, 3) - o) @ R
    proj = polyline.project(Q[:, :2], S[:, :2])
    root = np.interp(proj.arc, polyline.arc_length(S[:, :2]), S[:, 2])
    h = (Q[:, 2] - root)[proj.inside]
    if len(h) == 0:
        return {"mean_mm": float("nan"), "min_mm": float("nan"), "max_mm": float("nan"), "points": 0}
    return {"mean_mm": float(h.mean()) * 1e3, "min_mm": float(h.min()) * 1e3, "max_mm": float(h.max()) * 1e3, "points": int(len(h))}


def torch_positions(records: np.ndarray, tool: ToolGeometry) -> np.ndarray:
    """The torch's position (n, 3), base frame, m, at each of the motion loop's ``records`` (their TCP poses)."""
    T_tool = se3.from_ur_poses(records["tcp_pose"]) @ tool.T_tcp_tool
    return np.einsum("nij,j->ni", T_tool[:, :3, :3], tool.torch_tool()) + T_tool[:, :3, 3]


def refined_of(records: np.ndarray) -> np.ndarray:
    """The refined path (k, 3), base frame, m, in the motion loop's ``records``: each point once, as it was found."""
    refined = records["refined_base"]
    refined = refined[np.all(np.isfinite(refined), axis=1)]
    if len(refined):
        refined = refined[np.concatenate([[True], np.any(np.diff(refined, axis=0) != 0.0, axis=1)])]
    return refined


def track_summary(records: np.ndarray, geometry: WeldGeometry, tool: ToolGeometry, delta_d: float) -> TrackSummary:
    """The paths and figures of a finished track from the motion loop's records of it.

    Parameters
    ----------
    records : structured array
        The state records of the servo's command, in order (at least one).
    geometry : WeldGeometry
        The planned weld (the seam line the torch should follow).
    tool : ToolGeometry
        Where the torch is on the tool.
    delta_d : float
        The deformation the servo held, m.
    """
    torch = torch_positions(records, tool)
    refined = refined_of(records)
    tracking = records["servo_phase"] == 1
    torch_weld = polyline.thin(torch[records["process_on"]] if records["process_on"].any() else torch[tracking], TORCH_STEP)
    delta_n = records["delta_n"][tracking]
    delta_n = delta_n[np.isfinite(delta_n)]
    e_delta = np.abs(np.abs(delta_n) - delta_d) if len(delta_n) else np.zeros(0)
    corr = lateral_offsets(geometry, refined, geometry.seam_base) if len(refined) > 1 else np.zeros(0)
    t = (records["t_ns"] - records["t_ns"][0]) * 1e-9
    # Frame to command: the cycle that first used a frame sent its command work_ns after
    # waking, and the frame was tactile_age_ns old at the wake-up.
    fresh = np.concatenate([[False], np.diff(records["tactile_seq"]) != 0]) & (records["tactile_age_ns"] >= 0)
    latency_ms = (records["tactile_age_ns"][fresh] + records["work_ns"][fresh]) * 1e-6
    omega = np.abs(records["twist"][:, 3:]).max()
    figures = {
        "duration_s": round(float(t[-1]), 3),
        "tracked_mm": round(float(polyline.arc_length(refined)[-1]) * 1e3, 2) if len(refined) > 1 else 0.0,
        "arc_on_s": round(float(records["process_on"].sum()) * float(np.median(np.diff(t))) if len(t) > 1 else 0.0, 3),
        "delta_n_error_rms_mm": round(float(np.sqrt(np.mean(e_delta**2))) * 1e3, 4) if len(e_delta) else None,
        "correction_rms_mm": round(float(np.sqrt(np.mean(corr**2))) * 1e3, 4) if len(corr) else None,
        "correction_max_mm": round(float(np.abs(corr).max()) * 1e3, 4) if len(corr) else None,
        "omega_peak": round(float(omega), 5),
        # The motion loop while the servo ran: wake-up lateness (ms) and cycles more than 2 ms late.
        "loop_late_p99_ms": round(float(np.percentile(records["late_ns"], 99)) * 1e-6, 3),
        "loop_late_max_ms": round(float(records["late_ns"].max()) * 1e-6, 3),
        "loop_cycles_late_2ms": int(np.count_nonzero(records["late_ns"] > 2_000_000)),
        "loop_cycles": int(len(records)),
        "frame_to_command_median_ms": round(float(np.median(latency_ms)), 3) if len(latency_ms) else None,
        "frame_to_command_p99_ms": round(float(np.percentile(latency_ms, 99)), 3) if len(latency_ms) else None,
    }
    return TrackSummary(refined, torch_weld, figures)


# Records of a touch averaged for its contact: the last this many settled cycles (50 ms at 500 Hz).
_CONTACT_RECORDS = 25
# A touch's cycle counts as settled with |delta_n| within this share of delta_d.
_SETTLED = 0.2


def contact_across(
    records: np.ndarray, tool: ToolGeometry, origin: Array, across: Array, side: float, delta_d: float, finger: FingerGain = FingerGain()
) -> float:
    """Where a touch found its wall: the deformed tip centre's coordinate (m) along ``across`` from ``origin``.

    ``records`` are the motion loop's records of a touch-only Algorithm 2 plan
    (:func:`celld.motion.algorithm2.algorithm2_plan`); the contact is the
    undeformed tip of the TCP pose minus the deformation the law used (Eq. 15,
    ``P_s = P_r - delta``), averaged over the last settled cycles of the touch.
    ``across`` (3,) is unit, in the welding plane, towards the finger wall;
    ``side`` the finger wall's side (+1 left of the travel, as the law's
    ``delta_n`` is signed), whichever wall was touched; ``finger`` the tip's
    deflection for the tag's (:mod:`celld.tactile.fingermap`; the touches' own
    :func:`touch_press` measure it).

    Raises
    ------
    CelldError
        The touch never settled on a wall.
    """
    touch = records[(records["servo_phase"] == 0) & np.isfinite(records["delta_n"])]
    settled = touch[np.abs(np.abs(touch["delta_n"]) - delta_d) < _SETTLED * delta_d][-_CONTACT_RECORDS:]
    if len(settled) == 0:
        raise CelldError("the touch ended without settling on a wall")
    T_tool = se3.from_ur_poses(settled["tcp_pose"]) @ tool.T_tcp_tool
    y = (T_tool[:, :3, 3] - np.asarray(origin, dtype=np.float64)) @ np.asarray(across, dtype=np.float64)
    return float(np.mean(y - side * np.asarray(finger.tip(settled["delta_n"]))))


# A touch's frames that measure the finger's gain: the tag's deformation within these shares of delta_d (below,
# the tip may not yet bear on the wall through the finger's play; above, the approach has overshot).
_PRESS_BAND = (0.25, 1.15)


def touch_press(records: np.ndarray, tool: ToolGeometry, origin: Array, across: Array, side: float, delta_d: float) -> Press:
    """A touch's frames while it came onto its wall, for the finger's gain (:func:`celld.tactile.fingermap.fit_finger_gain`).

    Each new frame of the touch's approach, up to its deepest deformation (after it, the servo settles back and
    the finger's play turns round): the undeformed tip centre's position along ``across`` at the frame's capture
    (the motion records interpolated to it) and the tag's normal deformation that frame showed (the law's
    ``delta_n`` less what it predicted from the tip's motion since the capture). ``origin``, ``across``,
    ``side`` as for :func:`contact_across`.
    """
    touch = records[(records["servo_phase"] == 0) & np.isfinite(records["delta_n"])]
    if len(touch) < 2:
        return Press(np.zeros(0), np.zeros(0), side)
    T_tool = se3.from_ur_poses(touch["tcp_pose"]) @ tool.T_tcp_tool
    y = (T_tool[:, :3, 3] - np.asarray(origin, dtype=np.float64)) @ np.asarray(across, dtype=np.float64)
    t = touch["t_ns"].astype(np.float64)
    y_cap = np.interp(t - touch["tactile_age_ns"], t, y)
    d = touch["delta_n"] - side * (y - y_cap)
    fresh = np.concatenate([[True], np.diff(touch["tactile_seq"]) != 0]) & (touch["tactile_seq"] >= 0)
    deepest = int(np.argmax(np.abs(d)))
    band = (np.abs(d) >= _PRESS_BAND[0] * delta_d) & (np.abs(d) <= _PRESS_BAND[1] * delta_d)
    keep = fresh & band & (np.arange(len(touch)) <= deepest)
    return Press(y_cap[keep], d[keep], side)
