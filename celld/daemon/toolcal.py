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
direction from the torch to the tip (:func:`celld.daemon.store.current_tool`):
on a real tool the torch is bent, clamped and trimmed independently of the
finger, and a torch a millimetre off the tip's line welds a millimetre off the
seam that the finger tracks exactly. The poses, the points found and why a
capture showed none are written to
``jobs/<job>/toolcal.json``, so the solve can be repeated offline.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from celld import fsutil, se3
from celld.bus.requests import ToolCalibrateJob
from celld.calib.toolcal import tool_calibration_poses
from celld.calib.toolsession import TOOL_SCHEMA, ToolCalibrationSession
from celld.config import Config
from celld.daemon.devices import CellDevices
from celld.daemon.jobs import JobContext
from celld.daemon.planning import REFUSED_SCHEMA, record_arm, record_cell, record_plan, report_plan
from celld.daemon.store import current_calibration, for_controller
from celld.errors import CalibrationError, JobError
from celld.log import get_logger
from celld.schemadoc import array, const, integer, obj, one_of, string, vector

log = get_logger(__name__)

# Defaults of a job's parameters: orientations, their largest tilt (rad).
N_POSES = 12
MAX_TILT = math.radians(20.0)

# The JSON shape of a tool-calibrate job's result (run_tool_calibrate).
RESULT_SCHEMA = one_of(
    "A tool-calibrate job's result: the tool measured, or a dry run's plan.",
    obj(
        "A dry run: the plan, nothing moved.",
        {
            "dry_run": const(True),
            "plan": obj(
                "The poses that present the tip to the scanner, checked against the cell with the tool on, the joints at each, "
                "and the candidates left out.",
                {
                    "tip_position": vector("Where the tip is presented, base frame, m.", 3),
                    "poses": array(vector("A TCP pose [x, y, z, rx, ry, rz], m and rad, base frame.", 6)),
                    "joints": array(vector("Joint positions, rad.", 6)),
                    "refused": REFUSED_SCHEMA,
                },
                ("tip_position", "poses", "joints", "refused"),
            ),
        },
        ("dry_run", "plan"),
    ),
    obj(
        "The tool measured: the tool calibration (a candidate until accepted), the poses planned, those that showed the tip "
        "and the torch, the dataset.",
        {
            "dry_run": const(False),
            "tool": TOOL_SCHEMA,
            "poses_planned": integer(lo=0),
            "poses_detected": integer("Captures that showed the tip.", lo=0),
            "torch_detected": integer("Captures that showed the welding wire's end.", lo=0),
            "dataset": string("Path of the saved captures (toolcal.json), to solve again offline."),
        },
        ("dry_run", "tool", "poses_planned", "poses_detected", "torch_detected", "dataset"),
    ),
)


@dataclass(frozen=True)
class ToolCalibrationOutcome:
    """A tool-calibrate job's result (:data:`RESULT_SCHEMA`): the tool it measured, or its dry run's plan (``tool`` None)."""

    plan: dict[str, Any]  # the checked plan, as the dry run's "plan"
    tool: dict[str, Any] | None = None  # the candidate an accept stores (celld.calib.toolsession.TOOL_SCHEMA)
    poses_detected: int = 0  # poses whose tip was found
    torch_detected: int = 0  # poses whose torch was found
    dataset: Path | None = None

    def as_dict(self) -> dict[str, Any]:
        if self.tool is None:
            return {"dry_run": True, "plan": self.plan}
        return {
            "dry_run": False,
            "tool": self.tool,
            "poses_planned": len(self.plan["poses"]),
            "poses_detected": self.poses_detected,
            "torch_detected": self.torch_detected,
            "dataset": str(self.dataset),
        }


async def run_tool_calibrate(ctx: JobContext, config: Config, devices: CellDevices) -> Mapping[str, Any]:
    """The tool-calibrate job (module docstring); its result's shape: :data:`RESULT_SCHEMA`."""
    job = ctx.job
    if not isinstance(job, ToolCalibrateJob):
        raise JobError("$.kind", "not a tool-calibrate job")
    placement, range_bias, cal_job, _ = current_calibration(ctx.state_dir, config.scanner.mount)
    for_controller(placement, devices.robot.require_kinematics)
    tool = config.tool
    p_tcp_nominal = np.asarray(tool.tip_tcp, dtype=np.float64)
    z_tcp = np.asarray(tool.tool_z_tcp, dtype=np.float64)
    n = job.n_poses if job.n_poses is not None else N_POSES
    max_tilt = job.max_tilt if job.max_tilt is not None else MAX_TILT
    seed = job.seed or 0
    T_v = se3.from_ur_pose(config.calibration.verification_pose)
    p_tip = np.asarray(job.tip_position, dtype=np.float64) if job.tip_position is not None else T_v[:3, 3]

    def more(count: int, rnd: int) -> np.ndarray:
        return tool_calibration_poses(T_v[:3, :3], p_tip, p_tcp_nominal, z_tcp, count + 1, max_tilt, seed + 1000 * (rnd + 1))[1:]

    candidates = tool_calibration_poses(T_v[:3, :3], p_tip, p_tcp_nominal, z_tcp, n, max_tilt, seed)
    q_now = await devices.robot.current_q()  # first: it waits for the controller's kinematics
    planner = devices.robot.planner
    plan = await asyncio.to_thread(planner.plan_calibration, q_now, candidates, n, more, True)
    poses = np.array(plan.poses)
    report_plan(ctx, plan, "tool calibration")
    planned = {
        "tip_position": p_tip.tolist(),
        "poses": [se3.to_ur_pose(T).tolist() for T in plan.poses],
        "joints": [list(q) for q in plan.q],
        "refused": plan.refused_entries(),
    }
    if job.dry_run:
        await asyncio.to_thread(record_plan, ctx.recording, planner.with_tool, list(plan.q))
        return ToolCalibrationOutcome(planned).as_dict()
    rec = ctx.recording
    if rec is not None:
        await asyncio.to_thread(record_cell, rec, planner.with_tool)
        if not placement.mount.on_arm:
            rec.later(rec.log_camera_pose, placement.T_ref_cam, None, True)
    session = ToolCalibrationSession(config.tool, placement, range_bias)
    for i, T in enumerate(poses):
        await devices.robot.move_to(T, tool=True)
        await asyncio.sleep(config.calibration.settle)
        state = devices.robot.require_motion().state()
        if state is None:
            raise CalibrationError("no robot state after the move")
        cloud = await devices.scanner.capture()
        step = await asyncio.to_thread(session.capture, state.T_base_tcp, state.q, cloud.points)
        if rec is not None and placement.mount.on_arm:
            rec.later(rec.log_camera_pose, step.T_base_cam, time.monotonic_ns())
        if rec is not None and (step.tip is not None or step.torch is not None):
            rec.later(rec.log_tcp, step.T_base_tcp, time.monotonic_ns())
            await asyncio.to_thread(record_arm, rec, planner.with_tool, state.q)
        ctx.progress("pose", (i + 1) / len(poses), step.message, **step.progress())

    dataset = ctx.result_dir() / "toolcal.json"
    await asyncio.to_thread(fsutil.write_json, dataset, session.dataset(cal_job))
    n_tip, n_torch = session.counts()
    ctx.progress("solve", None, f"solving the tip from {n_tip} and the torch from {n_torch} of {len(poses)} poses")
    done = await asyncio.to_thread(session.finish, ctx.job_id, cal_job)
    if rec is not None:
        ids, P_robot, P_found, outlier = done.residuals
        await asyncio.to_thread(rec.log_residuals, ids, P_robot, P_found, outlier)
    measured = done.tool
    log.info(
        "tool_calibration_solved",
        job=ctx.job_id,
        poses=measured["poses"],
        verdict=measured["quality"]["verdict"],
        tip_mm=np.round(done.tip_fit.p_tcp_tip * 1e3, 3).tolist(),
        delta_mm=np.round(measured["delta_mm"], 3).tolist(),
        torch_delta_mm=np.round(measured["torch_delta_mm"], 3).tolist() if done.torch_fit is not None else None,
    )
    return ToolCalibrationOutcome(planned, measured, n_tip, n_torch, dataset).as_dict()
