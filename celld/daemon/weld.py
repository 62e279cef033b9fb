"""The weld job: scan, find the seam, touch it, track it with Algorithm 2, retract.

Steps, each published as a progress event:

1. **scan**: the arm goes to ``weld.scan_pose`` (out of the scanner's view)
   and the scanner captures the part;
2. **seam**: the seam finder registers the part model in the scan and places
   its seam in the base frame with the *current* calibration (an accepted
   calibrate job); a weld without one is refused. The tool's tip is the
   current tool calibration's (an accepted tool-calibrate job), which
   overrides ``tool.tip_tcp_mm``; without one the weld is refused unless
   ``tool.measured = "nominal"`` says the typed tip may be used. A calibration with a
   range bias on metal (time-of-flight scanner) has the scan's points moved
   back along their rays by it first: the part and the table are metal;
3. **approach**: the finger's wall line at ``weld.tip_height`` above the seam
   (:mod:`celld.seam.weldpath`) becomes the servo's plan; the tool comes down
   ``approach_height`` above its start, then onto it, ``clearance`` off the
   wall on the free side; the SRM is tared there, free;
4. **track**: Algorithm 2 in the motion process's servo slot touches the wall
   until the deformation settles at ``delta_d``, then tracks; the arc is
   switched on (robot digital output ``robot.arc_output``) by the motion loop
   itself while the law tracks and off the cycle a stop begins, so no bus or
   event-loop delay stands between a fault and the arc going out;
5. **retract**: straight up by ``retract_height`` (also after a failed track,
   when the link still stands), then to the scan pose.

Results: the planned wall line, the refined path (the seam as the finger
found it, which the torch followed) and the torch path, in the base frame,
with the tracking figures; the paths are also written to
``jobs/<job>/paths.json`` and logged to the job's recording.
"""

from __future__ import annotations

import asyncio
import hashlib
import math
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from celld import fsutil, polyline, se3
from celld.bus.schema import WeldJob
from celld.calib.mount import Placement, placement_of
from celld.calib.rangebias import correct_range_bias
from celld.config import Config, ServoConfig, ToolConfig, with_overrides
from celld.daemon.devices import CellDevices
from celld.daemon.jobs import CalibrationStore, JobContext, tool_store
from celld.daemon.planning import record_arm, record_cell, record_plan
from celld.errors import CelldError, ConfigError, InputError, JobError, WorkpieceError
from celld.log import get_logger
from celld.motion.algorithm2 import algorithm2_plan
from celld.motion.types import ServoPlan
from celld.recording import layout
from celld.seam.figures import contact_across, track_summary
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
from celld.seam.workpiece import EXAMPLES, Workpiece, example, load_workpiece
from celld.tactile.tool import ToolGeometry, with_measured_torch

log = get_logger(__name__)

# The tool starts this far along the wall line (m) ...
LEAD_IN = 0.005
# ... and this far off the wall on the free side (m); the servo's touch then
# travels it at touch_speed (bounded by servo.touch_distance).
CLEARANCE = 0.004
# A dry run scans only with the arm this close to the scan pose (m, rad).
DRY_RUN_AT_SCAN = 0.002
DRY_RUN_AT_SCAN_ANGLE = 0.01
# A dry run draws the arm at this many configurations along the checked path.
DRY_RUN_ROBOTS = 12
# The weld's path check looks at the tool every this much along the seam, m.
PATH_STEP = 0.01
# Seconds between progress events while tracking.
PROGRESS_PERIOD = 0.5
# Seconds between SRM camera frames logged to the recording while tracking.
PREVIEW_PERIOD = 0.2
# A calibration's range bias beyond this is not a scanner's (mm): refused as corrupt.
MAX_RANGE_BIAS_MM = 100.0
# A measured tip farther than this from the TCP is not a tool's (m): refused as corrupt.
MAX_TIP_DISTANCE = 1.0


def resolve_workpiece(name: str, config: Config) -> Workpiece:
    """The part ``name`` (or the cell's default part): an example or a model in ``weld.workpiece_dir``."""
    wc = config.weld
    name = name or wc.workpiece
    if not name:
        raise JobError("$.workpiece", "no workpiece named and the cell has no default (weld.workpiece in the config)")
    if name in EXAMPLES:
        return example(name)
    if not wc.workpiece_dir:
        raise JobError(
            "$.workpiece", f"unknown workpiece {name!r}: not an example ({', '.join(EXAMPLES)}) and weld.workpiece_dir is not set"
        )
    if "/" in name or name.startswith("."):
        raise JobError("$.workpiece", f"expected a plain model name, got {name!r}")
    d = Path(wc.workpiece_dir)
    meshes = [d / f"{name}{ext}" for ext in (".stl", ".ply", ".obj") if (d / f"{name}{ext}").exists()]
    seams = [d / f"{name}.seam{ext}" for ext in (".json", ".csv") if (d / f"{name}.seam{ext}").exists()]
    if not meshes or not seams:
        raise JobError("$.workpiece", f"unknown workpiece {name!r}: {d} holds no {name}.stl|ply|obj with a {name}.seam.json|csv")
    try:
        return load_workpiece(meshes[0], seams[0], mesh_units=wc.workpiece_units, name=name)
    except WorkpieceError as exc:
        raise JobError("$.workpiece", f"workpiece {name!r} cannot be used: {exc}") from exc


def current_calibration(state_dir: Path, mount: str = "base") -> tuple[Placement, float, str]:
    """The accepted calibration: the scanner's placement (``T_base_cam``, or its pose on its link of the
    arm), the scanner's range bias on metal (m) and the job that made it.

    Refused without one, when either value is unusable, or when it was made
    for a scanner mounted elsewhere than the config's ``mount``. A calibration
    without a range bias (structured light, or written before it existed)
    has none: 0.
    """
    cal = CalibrationStore(state_dir).current()
    if cal is None:
        raise JobError("$", "the cell has no current calibration: run a calibrate job and accept it first")
    try:
        placement = placement_of(cal)
    except InputError as exc:
        raise JobError("$", f"the current calibration is unusable: {exc}") from exc
    if placement.mount.name != mount:
        raise JobError(
            "$",
            f"the current calibration is of a scanner on {placement.mount.name}, and scanner.mount is {mount!r}: "
            "calibrate the scanner where it is mounted now",
        )
    bias_mm = cal.get("range_bias_mm", 0.0)
    if isinstance(bias_mm, bool) or not isinstance(bias_mm, (int, float)) or not abs(bias_mm) <= MAX_RANGE_BIAS_MM:
        raise JobError(
            "$", f"the current calibration is unusable: range_bias_mm must be a number within +-{MAX_RANGE_BIAS_MM:g} mm, got {bias_mm!r}"
        )
    return placement, float(bias_mm) * 1e-3, str(cal.get("job", ""))


class CurrentTool(NamedTuple):
    """The tool a weld runs with (:func:`current_tool`)."""

    tool: ToolConfig
    job: str  # the tool-calibrate job that measured it, "" for none
    sensor_yaw: float = 0.0  # rad, Algorithm2Params.sensor_yaw
    torch_measured: bool = False


def current_tool(state_dir: Path, tool: ToolConfig) -> CurrentTool:
    """``tool`` with the current tool calibration's tip and, when it measured it, its torch.

    A measured torch sets the tool's x axis (from the torch to the tip, across
    the configured finger axis) and ``torch_offset``
    (:func:`celld.tactile.tool.with_measured_torch`). Refused without a current
    tool calibration unless ``tool.measured`` is ``"nominal"``, and when the
    stored tip or torch is unusable.
    """
    current = tool_store(state_dir).current()
    if current is None:
        if tool.measured == "nominal":
            return CurrentTool(tool, "")
        raise JobError(
            "$",
            "the tool's tip is not measured: run a tool-calibrate job and accept it first, or set "
            'tool.measured = "nominal" in the config to weld with tool.tip_tcp_mm as typed',
        )
    job = str(current.get("job", ""))
    tip = _stored_point(current, "tip_tcp_mm")
    tool = replace(tool, tip_tcp=(float(tip[0]), float(tip[1]), float(tip[2])))
    if current.get("torch_measured") is not True:
        return CurrentTool(tool, job)  # a calibration of the tip alone: the torch as configured
    try:
        measured = with_measured_torch(tool, _stored_point(current, "torch_tcp_mm"))
    except InputError as exc:
        raise JobError("$", f"the current tool calibration {job} is unusable: {exc}") from exc
    return CurrentTool(measured.tool, job, measured.sensor_yaw, True)


def _stored_point(current: Mapping[str, Any], key: str) -> np.ndarray:
    value = current.get(key)
    try:
        p = np.asarray(value, dtype=np.float64) * 1e-3
    except (TypeError, ValueError) as exc:
        raise JobError("$", f"the current tool calibration is unusable: {key} {value!r}") from exc
    if p.shape != (3,) or not np.all(np.isfinite(p)) or np.linalg.norm(p) > MAX_TIP_DISTANCE:
        raise JobError(
            "$",
            f"the current tool calibration is unusable: {key} must be 3 finite numbers within "
            f"{MAX_TIP_DISTANCE * 1e3:g} mm of the TCP, got {value!r}",
        )
    return p


class _Collector:
    """Motion state records of one command, gathered from the handle's batches while in a ``with`` block."""

    def __init__(self, motion: Any) -> None:
        self.motion = motion
        self.batches: list[np.ndarray] = []
        self.command_id = 0

    def __enter__(self) -> _Collector:
        self.motion.add_listener(self)
        return self

    def __exit__(self, *exc: object) -> None:
        self.motion.remove_listener(self)

    def __call__(self, batch: np.ndarray) -> None:
        if self.command_id:
            mine = batch[batch["command_id"] == self.command_id]
            if len(mine):
                self.batches.append(mine.copy())

    def records(self) -> np.ndarray | None:
        return np.concatenate(self.batches) if self.batches else None


async def _retract(ctx: JobContext, devices: CellDevices, z: np.ndarray, height: float, T_scan: np.ndarray, speed: float) -> str:
    """Stop, the tool straight up by ``height`` (m, along ``z``) and back to the scan pose; why not, or ""."""
    try:
        await devices.stop_robot()
        state = devices.require_motion().state()
        if state is not None:
            T_up = state.T_base_tcp.copy()
            T_up[:3, 3] += height * z
            ctx.progress("retract", None, "tool up and away")
            await devices.move_to(T_up, speed_scale=min(speed, 0.2))
            await devices.move_to(T_scan, speed_scale=speed)
    except CelldError as exc:
        log.error("retract after the weld failed", job=ctx.job_id, error=str(exc))
        return str(exc)
    return ""


def _start_clearance(geometry: WeldGeometry, seam: Any) -> float:
    """How far off the finger wall the tip starts: mid-way across the joint where the scan measured its
    other wall at the start (as far from either wall as it can be), else :data:`CLEARANCE`."""
    i = int(geometry.stations([LEAD_IN])[0])
    width = geometry.offsets[i] + wall_at_height(seam.far_wall_across[i : i + 1], geometry.tip_height)[0]
    return float(width) / 2.0 if math.isfinite(width) and width > 0.0 else CLEARANCE


async def _probe_height(
    ctx: JobContext,
    devices: CellDevices,
    config: Config,
    geometry: WeldGeometry,
    seam: Any,
    servo: ServoConfig,
    tool_cfg: ToolConfig,
    sensor_yaw: float,
    T_start: np.ndarray,
    speed: float,
) -> tuple[dict[str, Any], WeldGeometry, np.ndarray]:
    """Touch the far wall and the finger wall at the start; from the joint's width there and the scan's
    walls (:func:`height_from_width`), the tip's height in the joint. Returns what was found, the
    geometry moved to the planned height and the start pose on it (unchanged when not probed)."""
    wc = config.weld
    i = int(geometry.stations([LEAD_IN])[0])
    finger, far = seam.wall_across[i], seam.far_wall_across[i]
    if not wc.probe_height:
        return {"probed": False, "why": "weld.probe_height is off"}, geometry, T_start
    try:
        height_from_width(float(finger[0] + far[0]), finger, far)  # the joint can tell a height
    except WorkpieceError as exc:
        return {"probed": False, "why": str(exc)}, geometry, T_start
    motion = devices.require_motion()
    tool = ToolGeometry.from_config(tool_cfg)
    z = geometry.T_base_plane[:3, 2]
    N = geometry.normals[i] - float(geometry.normals[i] @ z) * z
    N /= np.linalg.norm(N)
    # The far wall at the tip's height, where the scan measured it (its neighbours' between).
    far_line = geometry.seam_base - wall_at_height(seam.far_wall_across, geometry.tip_height)[:, None] * geometry.normals
    other = replace(tool_cfg, wall_side="right" if tool_cfg.wall_side == "left" else "left")
    touches = {}
    for name, line, cfg in (("far", far_line, other), ("finger", geometry.wall_base, tool_cfg)):
        ctx.progress("probe", None, f"touching the {name} wall of the joint")
        plan = algorithm2_plan(line, servo, cfg, config.motion, T_base_plane=geometry.T_base_plane, touch_only=True, sensor_yaw=sensor_yaw)
        records = await _run_servo(motion, plan, wc.timeout)
        touches[name] = contact_across(records, tool, geometry.T_base_plane[:3, 3], N, tool.side, servo.delta_d)
        await devices.move_to(T_start, speed_scale=speed)
    width = touches["finger"] - touches["far"] + 2.0 * tool.tip_radius
    height = height_from_width(width, finger, far)
    dh = height - geometry.tip_height
    found = {
        "probed": True,
        "joint_width_mm": round(width * 1e3, 4),
        "scan_width_mm": round(joint_width(finger, far, geometry.tip_height) * 1e3, 4),
        "height_mm": round(height * 1e3, 4),
        "height_correction_mm": round(-dh * 1e3, 4),
    }
    if abs(dh) > wc.max_height_correction:
        raise WorkpieceError(
            f"the tip stands {height * 1e3:.2f} mm above the seam where the plan puts it at {geometry.tip_height * 1e3:.2f} mm "
            f"(the joint is {width * 1e3:.2f} mm wide there; at most {wc.max_height_correction * 1e3:.1f} mm off is corrected): "
            "check the calibration and the tool"
        )
    log.info("tip height probed", job=ctx.job_id, **found)
    moved = weld_geometry(seam.points_base, seam.tangents, seam.normals, seam.plane_normal, geometry.offsets, geometry.tip_height - dh)
    T_start = start_pose(moved, tool.T_tcp_tool, LEAD_IN, _start_clearance(geometry, seam))
    await devices.move_to(T_start, speed_scale=speed)
    return found, moved, T_start


async def _run_servo(motion: Any, plan: ServoPlan, timeout: float) -> np.ndarray:
    """Run a servo plan to its end; the motion records of it."""
    with _Collector(motion) as collector:
        collector.command_id = await motion.start_servo(plan)
        await motion.wait(collector.command_id, timeout=timeout)
    records = collector.records()
    if records is None:
        raise CelldError("a touch ran but no motion record of it was read")
    return records


async def run_weld(ctx: JobContext, config: Config, devices: CellDevices, cache: dict[str, Any]) -> Mapping[str, Any]:
    job = ctx.job
    if not isinstance(job, WeldJob):
        raise JobError("$.kind", "not a weld job")
    if devices.tactile is None:
        raise JobError("$", "the cell has no tactile sensor (tactile.kind); it cannot track a seam")
    if not devices.tactile.running():
        raise JobError(
            "$", f"the tactile sensor is not running ({devices.tactile_error or 'its process ended'}); the daemon keeps restarting it"
        )
    motion = devices.require_motion()
    wc = config.weld
    seam_params = config.seam
    from celld.seam.pipeline import find_seam, prepare

    try:
        servo, tool_cfg = with_overrides(
            config.servo,
            config.tactile,
            config.tool,
            "weld job",
            config.motion.max_linear_speed,
            delta_d=job.delta_d,
            k_p=job.k_p,
            v_const=job.v_const,
            torch_offset=job.torch_offset,
        )
    except ConfigError as exc:
        # The job's field of the refused value: its key in the section (delta_d_mm, ...).
        raise JobError("$." + exc.key.rsplit(".", 1)[-1], exc.reason) from exc
    placement, range_bias, cal_job = current_calibration(ctx.state_dir, config.scanner.mount)
    tool_cfg, tool_job, sensor_yaw, torch_measured = current_tool(ctx.state_dir, tool_cfg)
    if torch_measured and job.torch_offset is not None:
        raise JobError(
            "$.torch_offset_mm",
            f"the torch is measured (tool calibration {tool_job}: {tool_cfg.torch_offset * 1e3:.2f} mm behind the tip); "
            "leave torch_offset_mm out, or measure the tool again",
        )
    tool = ToolGeometry.from_config(tool_cfg)
    workpiece = resolve_workpiece(job.workpiece, config)
    # Prepared models by content (a user's model edited on disk is prepared again).
    key = hashlib.sha1(workpiece.vertices.tobytes() + workpiece.triangles.tobytes() + workpiece.seam.tobytes()).hexdigest()
    if key not in cache:
        ctx.progress("prepare", None, f"preparing the model of {workpiece.name}")
        prepared = await asyncio.to_thread(prepare, workpiece, seam_params)
        offset = await asyncio.to_thread(wall_offset, workpiece, wc.tip_height, seam_params.finger_wall)
        cache[key] = (prepared, offset)
    prepared, offset = cache[key]
    rec = ctx.recording
    speed = wc.speed_scale
    T_scan = se3.from_ur_pose(wc.scan_pose)

    # 1. scan
    if job.dry_run:
        # A dry run moves nothing: it scans from the scan pose, so the arm must be there already.
        here = motion.state()
        dt, dr = se3.error(here.T_base_tcp, T_scan) if here is not None else (math.inf, math.inf)
        if dt > DRY_RUN_AT_SCAN or dr > DRY_RUN_AT_SCAN_ANGLE:
            raise JobError(
                "$.dry_run",
                f"a dry run scans from the scan pose and moves nothing: the arm is {dt * 1e3:.1f} mm "
                f"from weld.scan_pose; move it there first (celld submit move --pose ...)",
            )
        ctx.progress("scan", 0.0, "scanning (dry run: the arm stays where it is)")
    else:
        ctx.progress("scan", 0.0, "arm to the scan pose, scanning")
        await devices.move_to(T_scan, speed_scale=speed)
    here = motion.state()
    cloud = await devices.capture()
    # The scanner where it is now (a scanner on the arm moves with its link, Eq. 8).
    T_base_cam = placement.T_base_cam(None if here is None else here.q)
    # The calibration's range bias on metal: the scan (a metal part on a steel
    # table) moved back along its rays, as the calibration was solved.
    points = correct_range_bias(cloud.points, range_bias) if range_bias else np.asarray(cloud.points)
    if rec is not None:
        record_cell(rec, devices.planner.with_tool)
        rec.log_camera_pose(T_base_cam)
        rec.log_cloud_cam("scan", points)

    # 2. seam
    ctx.progress("seam", None, f"finding the seam of {workpiece.name} with calibration {cal_job or '(unnamed)'}")
    nominal = se3.from_ur_pose(wc.nominal_pose) if wc.nominal_pose else None
    seam = await asyncio.to_thread(find_seam, points, prepared, T_base_cam, seam_params, nominal)
    # The finger wall where the scan measured it beside the seam (a part's gap and twist move it; the
    # model's constant offset where it was not measured, or where the config trusts the model alone).
    offsets = offset if seam_params.seam_source == "model" else measured_offsets(seam.wall_across, wc.tip_height, offset)
    geometry = weld_geometry(seam.points_base, seam.tangents, seam.normals, seam.plane_normal, offsets, wc.tip_height)
    if rec is not None:
        rec.log_path_base("planned", geometry.seam_base)
        # The part model where the scan placed it.
        rec.log_mesh(layout.WORKPIECE, workpiece.vertices, workpiece.triangles, seam.T_base_obj)
    ctx.progress("seam", None, f"seam found: {seam.length * 1e3:.1f} mm", length_mm=seam.length * 1e3, **_quality(seam))

    # 3. the whole path, checked against the cell before the tool moves to it:
    # above the start, down, along the seam, up and back to the scan pose.
    T_start = start_pose(geometry, tool.T_tcp_tool, LEAD_IN, _start_clearance(geometry, seam))
    z = geometry.T_base_plane[:3, 2]
    T_above = T_start.copy()
    T_above[:3, 3] += wc.approach_height * z
    path = weld_path(geometry, tool.T_tcp_tool, T_above, T_start, T_scan, wc.retract_height)
    if rec is not None:
        rec.log_path_base("plan", path[:, :3, 3])
    check = await asyncio.to_thread(devices.planner.check_path, await devices.current_q(), path)
    if job.dry_run:
        stations = np.linspace(0, len(check.q) - 1, min(len(check.q), DRY_RUN_ROBOTS)).round().astype(int)
        record_plan(rec, devices.planner.with_tool, [tuple(check.q[i]) for i in stations])
        return {
            "dry_run": True,
            "workpiece": workpiece.name,
            "calibration_job": cal_job,
            "tool_calibration_job": tool_job,
            "planned_path": geometry.seam_base.tolist(),
            "tcp_path": [se3.to_ur_pose(T).tolist() for T in path],
            "min_clearance_mm": round(check.min_clearance * 1e3, 2),
            "seam_length_mm": round(seam.length * 1e3, 2),
        }
    ctx.progress("approach", None, "tool to the seam's start")
    await devices.move_to(T_above, speed_scale=speed)
    await devices.move_to(T_start, speed_scale=min(speed, 0.2))
    ctx.progress("tare", None, "taring the SRM, finger free")
    await asyncio.to_thread(devices.tactile.tare)

    # The tip's height in the joint, probed by touch: the plan's height error moves where the finger
    # meets a sloping wall, and so where the torch goes. The plan moves to the height it should have.
    try:
        height_probe, geometry, T_start = await _probe_height(
            ctx, devices, config, geometry, seam, servo, tool_cfg, sensor_yaw, T_start, min(speed, 0.2)
        )
    except CelldError:
        await _retract(ctx, devices, z, wc.retract_height, T_scan, speed)
        raise

    # 4. touch and track
    plan = algorithm2_plan(
        geometry.wall_base,
        servo,
        tool_cfg,
        config.motion,
        T_base_plane=geometry.T_base_plane,
        process=bool(job.arc) and config.robot.arc_output >= 0,
        seam_offset=geometry.offsets,
        sensor_yaw=sensor_yaw,
    )
    events_before = motion.loop_event_count
    failure: CelldError | None = None
    with _Collector(motion) as collector:
        cid = await motion.start_servo(plan)
        collector.command_id = cid
        ctx.progress(
            "track", 0.0, "touching the seam, then tracking" + (" with the arc on" if plan.params.get("process") else " (dry run, arc off)")
        )
        waiting = asyncio.ensure_future(motion.wait(cid, timeout=wc.timeout))
        s_wall = polyline.arc_length(geometry.wall_base)
        try:
            last_progress = 0.0
            last_frame = 0
            while not waiting.done():
                await asyncio.wait({waiting}, timeout=PREVIEW_PERIOD)
                last_frame = _log_preview(devices, rec, last_frame)
                now = asyncio.get_running_loop().time()
                last = motion.last_record()
                if last is not None and not waiting.done() and now - last_progress >= PROGRESS_PERIOD:
                    last_progress = now
                    p = tool.T_base_tool(se3.from_ur_pose(last["tcp_pose"]))[:3, 3]
                    i = int(np.argmin(np.linalg.norm(geometry.wall_base - p, axis=1)))
                    ctx.progress(
                        "track",
                        float(min(1.0, s_wall[i] / s_wall[-1])),
                        f"{s_wall[i] * 1e3:.0f} of {s_wall[-1] * 1e3:.0f} mm",
                        arc=bool(last["process_on"]),
                    )
            waiting.result()
        except CelldError as exc:
            failure = exc
        finally:
            if not waiting.done():
                waiting.cancel()
    # The loop's own trouble during the track (a failed arc write): the weld is not good.
    new_events = min(motion.loop_event_count - events_before, len(motion.loop_events))
    trouble = list(motion.loop_events)[-new_events:] if new_events > 0 else []
    if trouble and failure is None:
        failure = CelldError(f"the motion loop reported during the weld: {'; '.join(trouble)}")

    # 5. retract (also after a failed track, while the robot can still be moved)
    retract_error = await _retract(ctx, devices, z, wc.retract_height, T_scan, speed) if failure is None or motion.link_running() else ""
    if failure is not None:
        raise failure

    records = collector.records()
    result = _summarise(records, geometry, tool, servo, seam, offset, ctx.result_dir(), rec)
    result["workpiece"] = workpiece.name
    result["calibration_job"] = cal_job
    result["tool_calibration_job"] = tool_job
    # The torch the weld placed: measured (its offset and the tool's x turned by -sensor_yaw) or as configured.
    result["torch"] = {
        "measured": torch_measured,
        "torch_offset_mm": round(tool_cfg.torch_offset * 1e3, 4),
        "yaw_from_config_deg": round(-math.degrees(sensor_yaw), 4),
    }
    result["height_probe"] = height_probe
    if retract_error:
        result["retract_error"] = retract_error
    return result


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


def _log_preview(devices: CellDevices, rec: Any, last_stamp: int) -> int:
    """Log the SRM camera's latest shared frame (with the tag's outline) if it is new; its stamp."""
    if rec is None or devices.tactile is None:
        return last_stamp
    frame = devices.tactile.latest_preview()
    if frame is None or frame[0] == last_stamp:
        return last_stamp
    stamp, image, corners = frame
    try:
        rec.log_camera_image(image, corners, stamp_ns=stamp)
        # The arm as it moves, at the rate of the previews.
        here = devices.require_motion().state()
        if here is not None:
            record_arm(rec, devices.planner.with_tool, here.q, stamp_ns=here.stamp_ns)
    except CelldError as exc:
        log.warning("SRM frame not recorded", error=str(exc))
    return stamp


def _quality(seam: Any) -> dict[str, Any]:
    q = seam.quality.to_dict()
    return {k: q[k] for k in ("source", "fitness", "inlier_rmse", "coverage") if k in q}


def _summarise(
    records: np.ndarray | None,
    geometry: WeldGeometry,
    tool: ToolGeometry,
    servo: ServoConfig,
    seam: Any,
    offset: float,
    out_dir: Path,
    rec: Any,
) -> dict[str, Any]:
    """The paths and tracking figures of a finished track, written to paths.json and the recording."""
    if records is None or len(records) == 0:
        raise CelldError("the servo ran but no motion record of it was read")
    track = track_summary(records, geometry, tool, servo.delta_d)
    paths = {
        "frame": "base",
        "units": "m",
        "planned": geometry.seam_base.tolist(),
        "planned_wall": geometry.wall_base.tolist(),
        "refined": track.refined.tolist(),
        "torch": track.torch.tolist(),
    }
    path_file = fsutil.write_json(out_dir / "paths.json", paths)
    if rec is not None:
        if len(track.refined) > 1:
            rec.log_path_base("refined", track.refined)
        if len(track.torch) > 1:
            rec.log_path_base("torch", track.torch)
    figures = {
        **track.figures,
        "wall_offset_mm": round(offset * 1e3, 4),
        # The finger wall's distance from the seam as the weld used it (the scan's, where it measured it).
        "wall_offset_used_mm": [round(float(geometry.offsets.min()) * 1e3, 4), round(float(geometry.offsets.max()) * 1e3, 4)],
        "seam_length_mm": round(seam.length * 1e3, 2),
    }
    return {
        "figures": figures,
        "paths": str(path_file),
        "refined_path": paths["refined"],
        "torch_path": paths["torch"],
        "planned_path": paths["planned"],
    }
