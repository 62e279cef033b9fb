"""The tool-calibrate job: measure the SRM tip in the TCP frame with the scanner.

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
   *current* calibration, its range bias taken off); a capture without the
   tip is reported and skipped.
3. **solve**: the tip by linear least squares (:mod:`celld.calib.toolcal`,
   T1-T2), with per-pose residuals, outliers, 1-sigma and the verdict.

The job needs a current calibration (an accepted calibrate job). Its result
``tool`` is a candidate: an ``accept`` of the job makes it the current tool
calibration (``<state_dir>/tool.json``), refused when the verdict is not
``ok`` unless forced; a weld then uses its tip in place of
``tool.tip_tcp_mm`` (:func:`celld.daemon.weld.current_tool`). The poses,
the tips found and why a capture showed none are written to
``jobs/<job>/toolcal.json``, so the solve can be repeated offline.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from celld import fsutil, se3
from celld.bus.schema import ToolCalibrateJob
from celld.calib.rangebias import correct_range_bias
from celld.calib.toolcal import ToolCalParams, solve_tool_tip, tool_calibration_poses
from celld.calib.tooltip import TipDetectParams, detect_tip
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
    T_base_cam, range_bias, cal_job = current_calibration(ctx.state_dir)
    T_cam_base = se3.invert(T_base_cam)
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
        rec.log_camera_pose(T_base_cam, static=True)
    dparams = TipDetectParams()
    ids: list[str] = []
    T_found: list[np.ndarray] = []
    P_found: list[np.ndarray] = []
    missed: list[dict[str, Any]] = []
    detections: list[dict[str, Any]] = []
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
        p_pred = se3.apply(T_cam_base @ T_bt, p_tcp_nominal[None])[0]
        u_cam = T_cam_base[:3, :3] @ T_bt[:3, :3] @ z_tcp
        try:
            det = await asyncio.to_thread(detect_tip, points, p_pred, u_cam, tool.tip_radius, dparams)
        except CalibrationError as exc:
            missed.append({"id": pid, "reason": str(exc)})
            ctx.progress("pose", (i + 1) / len(poses), f"pose {pid}: no tip ({exc})", pose=pid, detected=False)
            continue
        p_base = se3.apply(T_base_cam, det.p_cam[None])[0]
        ids.append(pid)
        T_found.append(T_bt)
        P_found.append(p_base)
        detections.append(
            {
                "id": pid,
                "T_base_tcp": T_bt.tolist(),
                "p_base_tip": p_base.tolist(),
                "points": det.n_points,
                "rms_mm": det.rms * 1e3,
                "offset_mm": det.offset * 1e3,
            }
        )
        if rec is not None:
            rec.log_tcp(T_bt)
            record_arm(rec, planner.with_tool, state.q)
        ctx.progress(
            "pose",
            (i + 1) / len(poses),
            f"pose {pid}: tip {det.offset * 1e3:.2f} mm from the configured one",
            pose=pid,
            detected=True,
            points=det.n_points,
            fit_rms_mm=round(det.rms * 1e3, 4),
            offset_mm=round(det.offset * 1e3, 3),
        )

    dataset = ctx.result_dir() / "toolcal.json"
    await asyncio.to_thread(
        fsutil.write_json,
        dataset,
        {
            "frame": "base",
            "units": "m",
            "calibration_job": cal_job,
            "T_base_cam": T_base_cam.tolist(),
            "range_bias_m": range_bias,
            "tip_tcp_config": p_tcp_nominal.tolist(),
            "tip_radius": tool.tip_radius,
            "detections": detections,
            "missed": missed,
        },
    )
    ctx.progress("solve", None, f"solving the tip from {len(ids)} of {len(poses)} poses")
    T_arr = np.array(T_found).reshape(-1, 4, 4)
    P_arr = np.array(P_found).reshape(-1, 3)
    fit = await asyncio.to_thread(solve_tool_tip, T_arr, P_arr, ids, ToolCalParams())
    if not np.all(np.isfinite(fit.p_tcp_tip)):
        raise CalibrationError(
            f"only {len(ids)} of {len(poses)} captures showed the tip; at least 3 are needed"
            + (f" (first miss: {missed[0]['reason']})" if missed else "")
        )
    quality = fit.as_dict()
    quality["missed"] = missed
    if len(missed):
        quality["warnings"].append(f"{len(missed)} of {len(poses)} captures showed no tip")
    if rec is not None:
        b = fit.offset_base
        P_robot = np.einsum("nij,j->ni", T_arr[:, :3, :3], fit.p_tcp_tip) + T_arr[:, :3, 3] + b
        out = set(fit.inliers)
        rec.log_residuals(ids, P_robot, P_arr, [i not in out for i in range(len(ids))])
    tip = fit.p_tcp_tip
    torch = tip - tool.torch_offset * x_tcp
    result_tool = {
        "job": ctx.job_id,
        "tip_tcp_mm": (tip * 1e3).tolist(),
        "tip_std_mm": quality["tip_std_mm"],
        "nominal_tip_tcp_mm": (p_tcp_nominal * 1e3).tolist(),
        "delta_mm": ((tip - p_tcp_nominal) * 1e3).tolist(),
        "torch_tcp_mm": (torch * 1e3).tolist(),
        "calibration_job": cal_job,
        "poses": len(ids),
        "quality": quality,
    }
    log.info(
        "tool calibration solved",
        job=ctx.job_id,
        poses=len(ids),
        verdict=fit.verdict,
        tip_mm=np.round(tip * 1e3, 3).tolist(),
        delta_mm=np.round((tip - p_tcp_nominal) * 1e3, 3).tolist(),
    )
    return {"tool": result_tool, "poses_planned": len(poses), "poses_detected": len(ids), "dataset": str(dataset)}
