"""The tool-calibrate job: measure the SRM tip and the torch in the TCP frame with the scanner.

Steps, each published as a progress event:

1. **plan**: ``n_poses`` TCP poses that present the tip where the scanner
   sees it (``tip_position``, by default the position of
   ``calibration.verification_pose``), turned about it by up to
   ``max_tilt_deg`` about axes across the finger and spun about it
   (:func:`celld.calib.toolcal.tool_calibration_poses`), checked against the
   cell *with the tool on*; refused ones are replaced. A dry run stops here
   and returns the plan.
2. **pose** (each): move, settle (``calibration.settle_s``), capture, read
   the TCP pose from the robot, find the tip ball in the cloud near where the
   tool config puts it (:mod:`celld.calib.tooltip`, the cloud placed with the
   *current* calibration, its range bias taken off), and the end of the
   welding wire near where the config puts the torch (``torch_offset`` behind
   the tip, :func:`celld.calib.tooltip.detect_wire_end`); a capture without
   the tip or the wire is reported and skipped for that point.
3. **solve**: the tip and the torch, each by linear least squares
   (:mod:`celld.calib.toolcal`, T1-T2), with per-pose residuals, outliers,
   1-sigma and a verdict; the job's verdict is the first of the two that is
   not ``ok`` (the torch's reasons prefixed ``torch:``).

The job needs a current calibration (an accepted calibrate job). Its result
``tool`` is a candidate: an ``accept`` of the job makes it the current tool
calibration (``<state_dir>/tool.json``), refused when the verdict is not
``ok`` unless forced; a weld then uses its tip in place of
``tool.tip_tcp_mm``, and its torch for the configured torch offset and the
direction from the torch to the tip (:func:`celld.daemon.weld.current_tool`):
on a real tool the torch is bent, clamped and trimmed independently of the
finger, and a torch a millimetre off the tip's line welds a millimetre off the
seam that the finger tracks exactly. The poses, the points found and why a
capture showed none are written to
``jobs/<job>/toolcal.json``, so the solve can be repeated offline.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import numpy as np

from celld import fsutil, se3
from celld.bus.schema import ToolCalibrateJob
from celld.calib.mount import mount_entry
from celld.calib.rangebias import correct_range_bias
from celld.calib.toolcal import ToolCalParams, ToolTipFit, solve_tool_tip, tool_calibration_poses
from celld.calib.tooltip import TipDetection, TipDetectParams, WireDetectParams, detect_tip, detect_wire_end
from celld.config import Config
from celld.daemon.devices import CellDevices
from celld.daemon.jobs import JobContext
from celld.daemon.planning import record_arm, record_cell, record_plan, report_plan
from celld.daemon.weld import current_calibration
from celld.errors import CalibrationError, JobError
from celld.log import get_logger

log = get_logger(__name__)

# Defaults of a job's parameters: orientations, their largest tilt (rad).
N_POSES = 12
MAX_TILT = math.radians(20.0)


async def run_tool_calibrate(ctx: JobContext, config: Config, devices: CellDevices) -> Mapping[str, Any]:
    job = ctx.job
    if not isinstance(job, ToolCalibrateJob):
        raise JobError("$.kind", "not a tool-calibrate job")
    placement, range_bias, cal_job = current_calibration(ctx.state_dir, config.scanner.mount)
    tool = config.tool
    p_tcp_nominal = np.asarray(tool.tip_tcp, dtype=np.float64)
    z_tcp = np.asarray(tool.tool_z_tcp, dtype=np.float64)
    x_tcp = np.asarray(tool.tool_x_tcp, dtype=np.float64)
    n = job.n_poses if job.n_poses is not None else N_POSES
    max_tilt = job.max_tilt if job.max_tilt is not None else MAX_TILT
    seed = job.seed or 0
    T_v = se3.from_ur_pose(config.calibration.verification_pose)
    p_tip = np.asarray(job.tip_position, dtype=np.float64) if job.tip_position is not None else T_v[:3, 3]

    def more(count: int, rnd: int) -> np.ndarray:
        return tool_calibration_poses(T_v[:3, :3], p_tip, p_tcp_nominal, z_tcp, count + 1, max_tilt, seed + 1000 * (rnd + 1))[1:]

    candidates = tool_calibration_poses(T_v[:3, :3], p_tip, p_tcp_nominal, z_tcp, n, max_tilt, seed)
    planner = devices.planner
    plan = await asyncio.to_thread(planner.plan_calibration, await devices.current_q(), candidates, n, more, True)
    poses = np.array(plan.poses)
    report_plan(ctx, plan, "tool calibration")
    if job.dry_run:
        record_plan(ctx.recording, planner.with_tool, list(plan.q))
        return {
            "dry_run": True,
            "plan": {
                "tip_position": p_tip.tolist(),
                "poses": [se3.to_ur_pose(T).tolist() for T in plan.poses],
                "joints": [list(q) for q in plan.q],
                "refused": [{"pose": list(r.target), "reason": r.reason, "message": r.message} for r in plan.refused],
            },
        }
    rec = ctx.recording
    if rec is not None:
        record_cell(rec, planner.with_tool)
        if not placement.mount.on_arm:
            rec.log_camera_pose(placement.T_ref_cam, static=True)
    dparams, wparams = TipDetectParams(), WireDetectParams()
    p_tcp_torch_nominal = p_tcp_nominal - tool.torch_offset * x_tcp  # Eq. 14, as configured
    tip, torch = _Points("tip"), _Points("torch")
    for i, T in enumerate(poses):
        pid = f"{i:03d}"
        await devices.move_to(T, tool=True)
        await asyncio.sleep(config.calibration.settle)
        state = devices.require_motion().state()
        if state is None:
            raise CalibrationError("no robot state after the move")
        T_bt = state.T_base_tcp
        cloud = await devices.capture()
        points = correct_range_bias(cloud.points, range_bias) if range_bias else np.asarray(cloud.points)
        T_base_cam = placement.T_base_cam(state.q)  # a scanner on the arm moves with its link (Eq. 8)
        if rec is not None and placement.mount.on_arm:
            rec.log_camera_pose(T_base_cam)
        T_cam_tcp = se3.invert(T_base_cam) @ T_bt
        u_cam = T_cam_tcp[:3, :3] @ z_tcp  # along the finger and the wire, towards the flange
        tip_pred, torch_pred = se3.apply(T_cam_tcp, np.array([p_tcp_nominal, p_tcp_torch_nominal]))
        found_tip = await tip.detect(pid, T_bt, T_base_cam, partial(detect_tip, points, tip_pred, u_cam, tool.tip_radius, dparams))
        found_torch = await torch.detect(
            pid, T_bt, T_base_cam, partial(detect_wire_end, points, torch_pred, u_cam, tool.wire_diameter / 2.0, wparams)
        )
        if rec is not None and (found_tip is not None or found_torch is not None):
            rec.log_tcp(T_bt)
            record_arm(rec, planner.with_tool, state.q)
        ctx.progress(
            "pose",
            (i + 1) / len(poses),
            f"pose {pid}: {tip.summary(found_tip)}, {torch.summary(found_torch)}",
            pose=pid,
            detected=found_tip is not None,
            torch_detected=found_torch is not None,
            **(
                {"points": found_tip.n_points, "fit_rms_mm": round(found_tip.rms * 1e3, 4), "offset_mm": round(found_tip.offset * 1e3, 3)}
                if found_tip is not None
                else {}
            ),
        )

    dataset = ctx.result_dir() / "toolcal.json"
    await asyncio.to_thread(
        fsutil.write_json,
        dataset,
        {
            "frame": "base",
            "units": "m",
            "calibration_job": cal_job,
            **mount_entry(placement.mount, placement.T_ref_cam),
            "range_bias_m": range_bias,
            "tip_tcp_config": p_tcp_nominal.tolist(),
            "tip_radius": tool.tip_radius,
            "torch_tcp_config": p_tcp_torch_nominal.tolist(),
            "wire_diameter": tool.wire_diameter,
            "detections": tip.detections,
            "missed": tip.missed,
            "torch_detections": torch.detections,
            "torch_missed": torch.missed,
        },
    )
    ctx.progress("solve", None, f"solving the tip from {len(tip.ids)} and the torch from {len(torch.ids)} of {len(poses)} poses")
    fit = await asyncio.to_thread(tip.solve)
    torch_fit = await asyncio.to_thread(torch.solve)
    if fit is None:
        raise CalibrationError(
            f"only {len(tip.ids)} of {len(poses)} captures showed the tip; at least 3 are needed"
            + (f" (first miss: {tip.missed[0]['reason']})" if tip.missed else "")
        )
    quality = fit.as_dict()
    quality["missed"] = tip.missed
    if tip.missed:
        quality["warnings"].append(f"{len(tip.missed)} of {len(poses)} captures showed no tip")
    quality["torch"] = _torch_quality(torch_fit, torch, len(poses))
    if quality["torch"]["verdict"] != "ok" and quality["verdict"] == "ok":
        # The job's verdict: the first of the tip's and the torch's that is not ok.
        quality["verdict"], quality["passed"] = quality["torch"]["verdict"], False
        quality["reasons"] = ["torch: " + r for r in quality["torch"]["reasons"]]
    if rec is not None:
        rec.log_residuals(*tip.residual_points(fit))
    p_tip = fit.p_tcp_tip
    result_tool: dict[str, Any] = {
        "job": ctx.job_id,
        "tip_tcp_mm": (p_tip * 1e3).tolist(),
        "tip_std_mm": quality["tip_std_mm"],
        "nominal_tip_tcp_mm": (p_tcp_nominal * 1e3).tolist(),
        "delta_mm": ((p_tip - p_tcp_nominal) * 1e3).tolist(),
        "calibration_job": cal_job,
        "poses": len(tip.ids),
        "quality": quality,
    }
    if torch_fit is not None:
        p_torch = torch_fit.p_tcp_tip
        result_tool |= {
            "torch_measured": True,
            "torch_tcp_mm": (p_torch * 1e3).tolist(),
            "torch_std_mm": quality["torch"]["tip_std_mm"],
            "nominal_torch_tcp_mm": (p_tcp_torch_nominal * 1e3).tolist(),
            "torch_delta_mm": ((p_torch - p_tcp_torch_nominal) * 1e3).tolist(),
        }
    else:
        # No torch measured: it follows the tip as configured (Eq. 14).
        result_tool |= {"torch_measured": False, "torch_tcp_mm": ((p_tip - tool.torch_offset * x_tcp) * 1e3).tolist()}
    log.info(
        "tool calibration solved",
        job=ctx.job_id,
        poses=len(tip.ids),
        verdict=quality["verdict"],
        tip_mm=np.round(p_tip * 1e3, 3).tolist(),
        delta_mm=np.round((p_tip - p_tcp_nominal) * 1e3, 3).tolist(),
        torch_delta_mm=np.round(result_tool["torch_delta_mm"], 3).tolist() if torch_fit is not None else None,
    )
    return {
        "tool": result_tool,
        "poses_planned": len(poses),
        "poses_detected": len(tip.ids),
        "torch_detected": len(torch.ids),
        "dataset": str(dataset),
    }


class _Points:
    """One point of the tool (the tip or the torch) as the captures found it: poses, points, misses."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.missed: list[dict[str, Any]] = []
        self.detections: list[dict[str, Any]] = []

    async def detect(
        self, pid: str, T_base_tcp: np.ndarray, T_base_cam: np.ndarray, find: Callable[[], TipDetection]
    ) -> TipDetection | None:
        """Run the detector ``find`` in a thread; keep its point (base frame) or the reason it found none."""
        try:
            det = await asyncio.to_thread(find)
        except CalibrationError as exc:
            self.missed.append({"id": pid, "reason": str(exc)})
            return None
        p_base = se3.apply(T_base_cam, det.p_cam[None])[0]
        self.detections.append(
            {
                "id": pid,
                "T_base_tcp": T_base_tcp.tolist(),
                f"p_base_{self.name}": p_base.tolist(),
                "points": det.n_points,
                "rms_mm": det.rms * 1e3,
                "offset_mm": det.offset * 1e3,
            }
        )
        return det

    def summary(self, det: TipDetection | None) -> str:
        if det is None:
            return f"no {self.name} ({self.missed[-1]['reason']})"
        return f"{self.name} {det.offset * 1e3:.2f} mm from the configured one"

    @property
    def ids(self) -> list[str]:
        return [d["id"] for d in self.detections]

    def _arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The TCP poses (n, 4, 4) and the points found (n, 3), base frame."""
        T = np.array([d["T_base_tcp"] for d in self.detections], dtype=np.float64).reshape(-1, 4, 4)
        P = np.array([d[f"p_base_{self.name}"] for d in self.detections], dtype=np.float64).reshape(-1, 3)
        return T, P

    def solve(self) -> ToolTipFit | None:
        """T1-T2 on the points found; None when fewer than 3 leave it unsolved."""
        fit = solve_tool_tip(*self._arrays(), self.ids, ToolCalParams())
        return fit if np.all(np.isfinite(fit.p_tcp_tip)) else None

    def residual_points(self, fit: ToolTipFit) -> tuple[list[str], np.ndarray, np.ndarray, list[bool]]:
        """Ids, the fitted point through each pose (plus the fit's base offset), the found points, and which are used."""
        T, P = self._arrays()
        P_robot = np.einsum("nij,j->ni", T[:, :3, :3], fit.p_tcp_tip) + T[:, :3, 3] + fit.offset_base
        out = set(fit.inliers)
        return self.ids, P_robot, P, [i not in out for i in range(len(T))]


def _torch_quality(fit: ToolTipFit | None, torch: _Points, n_poses: int) -> dict[str, Any]:
    """The torch's report: its fit's, or a ``poor_data`` verdict saying why there is none."""
    if fit is None:
        first = f" (first miss: {torch.missed[0]['reason']})" if torch.missed else ""
        return {
            "verdict": "poor_data",
            "passed": False,
            "reasons": [f"only {len(torch.ids)} of {n_poses} captures showed the welding wire's end; at least 3 are needed{first}"],
            "warnings": [],
            "missed": torch.missed,
        }
    quality = fit.as_dict()
    quality["missed"] = torch.missed
    if torch.missed:
        quality["warnings"].append(f"{len(torch.missed)} of {n_poses} captures showed no wire end")
    return quality
