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
   (lower by as much as a measured torch's end stands above the tip, so the
   torch is at that height: :func:`celld.weld.plan.for_torch`;
   :mod:`celld.seam.weldpath`) becomes the servo's plan; the tool comes down
   ``approach_height`` above its start, then onto it, ``clearance`` off the
   wall on the free side; the SRM is tared there, free;
4. **track**: Algorithm 2 in the motion process's servo slot touches the wall
   until the deformation settles at ``delta_d``, then tracks; the arc is
   switched on (robot digital output ``robot.arc_output``) by the motion loop
   itself while the law tracks and off the cycle a stop begins, so no bus or
   event-loop delay stands between a fault and the arc going out;
5. **retract**: straight up by ``retract_height``, then back to the scan pose by a joint
   move to the joints the arm scanned from.
   After a fault stopped the weld the arm moves only as
   ``weld.retract_after_fault`` says: ``none`` (it stays), ``clear`` (straight
   out of the joint, slowly) or ``full`` (that, then to the scan pose); never
   after a protective stop or with the link down. What it did is added to the
   job's reason and logged in its recording.

Results: the planned wall line, the refined path (the seam as the finger
found it, which the torch followed) and the torch path, in the base frame,
with the tracking figures; the paths are also written to
``jobs/<job>/paths.json`` and logged to the job's recording. The result's
shape: :data:`RESULT_SCHEMA`.

What the weld is (the seam from the scan, the path, the probe's reading, the
figures) is decided by :mod:`celld.weld.plan`; this runner moves the arm,
captures, reports and records around it.
"""

from __future__ import annotations

import asyncio
import hashlib
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from celld import fsutil, polyline, se3
from celld.bus.requests import WeldJob
from celld.calib.mount import Placement
from celld.calib.rangebias import correct_range_bias
from celld.config import Config, ServoConfig, ToolConfig, WeldConfig, with_overrides
from celld.daemon.devices import CellDevices
from celld.daemon.jobs import JobContext
from celld.daemon.planning import MotionPlanner, record_arm, record_cell, record_plan
from celld.daemon.store import current_calibration, current_tool, for_controller, store_finger, stored_finger
from celld.errors import CelldError, ConfigError, InputError, JobError, SafetyStop, WorkpieceError
from celld.log import get_logger
from celld.motion.algorithm2 import Phase, algorithm2_plan
from celld.motion.arc import plan_keys
from celld.motion.source_io import source_problem, source_state
from celld.motion.types import ServoPlan
from celld.recording import layout
from celld.robot.collision import PathCheck
from celld.schemadoc import array, boolean, const, number, obj, one_of, string, vector
from celld.seam.figures import contact_across, refined_of, torch_positions, touch_press
from celld.seam.workpiece import EXAMPLES, Workpiece, example, load_workpiece
from celld.tactile.fingermap import FingerGain
from celld.tactile.tool import ToolGeometry
from celld.weld.arc_report import ARC_SCHEMA, arc_report, known_seam, sequence_of
from celld.weld.plan import (
    FIGURES_SCHEMA,
    FINGER_SCHEMA,
    PROBED_SCHEMA,
    PreparedPart,
    WeldPlan,
    compared_finger,
    for_torch,
    judged,
    measured_finger,
    plan_weld,
    precorrected,
    prepare_part,
    probe_across,
    probe_targets,
    probed_height,
    summarise,
)
from celld.weld.procedure import PROCEDURE_SCHEMA, WeldProcedure, cell_procedures, list_procedures, load_procedure

if TYPE_CHECKING:
    from celld.recording.job import JobRecording

log = get_logger(__name__)

# A dry run scans only with the arm this close to the scan pose (m, rad).
DRY_RUN_AT_SCAN = 0.002
DRY_RUN_AT_SCAN_ANGLE = 0.01
# A dry run draws the arm at this many configurations along the checked path.
DRY_RUN_ROBOTS = 12
# Algorithm 2's phase once the seam has ended ahead of the finger (celld.motion.algorithm2.Phase.FINISH).
FINISH_PHASE = int(Phase.FINISH)
# Seconds between progress events while tracking.
PROGRESS_PERIOD = 0.5
# Seconds between SRM camera frames logged to the recording while tracking.
PREVIEW_PERIOD = 0.2

_PATH = array(vector("A point, base frame, m.", 3))
# The JSON shape of the height probe's reading (_probe_height): what it found, or why the joint was not probed.
HEIGHT_PROBE_SCHEMA = one_of(
    "The tip's height in the joint, probed by touch at the start; or why it was not.",
    PROBED_SCHEMA,
    obj("Not probed.", {"probed": const(False), "why": string(), "finger": FINGER_SCHEMA}, ("probed", "why")),
)
# The JSON shape of a weld job's result (run_weld).
RESULT_SCHEMA = one_of(
    "A weld job's result: the weld's paths and figures, or a dry run's plan.",
    obj(
        "A dry run: scanned, planned and checked against the cell from the scan pose; nothing moved.",
        {
            "dry_run": const(True),
            "workpiece": string(),
            "calibration_job": string("The calibration the scan was placed with."),
            "tool_calibration_job": string("The tool calibration the tool was taken from (empty: the config's)."),
            "planned_path": {
                **_PATH,
                "description": "The seam as the scan placed it, base frame, m (as the controller was sent it: pre-corrected "
                "through the arm's calibration when the calibration has one).",
            },
            "tcp_path": array(
                vector("A TCP pose [x, y, z, rx, ry, rz], m and rad, base frame.", 6), "Every TCP pose the weld would pass through."
            ),
            "min_clearance_mm": number("The path's least clearance from the cell."),
            "seam_length_mm": number(lo=0.0),
        },
        (
            "dry_run",
            "workpiece",
            "calibration_job",
            "tool_calibration_job",
            "planned_path",
            "tcp_path",
            "min_clearance_mm",
            "seam_length_mm",
        ),
    ),
    obj(
        "A weld: its figures, the refined path (the seam as the finger found it, which the torch followed), the torch "
        "path and the planned seam (base frame, m; also in the file paths), the torch it placed and the height probe.",
        {
            "dry_run": const(False),
            "figures": FIGURES_SCHEMA,
            "paths": string("Path of the job's paths.json (planned, planned wall, refined, torch) on the cell PC."),
            "refined_path": _PATH,
            "torch_path": _PATH,
            "planned_path": _PATH,
            "workpiece": string(),
            "calibration_job": string("The calibration the scan was placed with."),
            "tool_calibration_job": string("The tool calibration the tool was taken from (empty: the config's)."),
            "torch": obj(
                "The torch the weld placed: measured (its offset and the tool's x turned by -sensor_yaw) or as configured; "
                "the tip rides lower by as much as the measured torch's end stands above it, so the torch is at weld.tip_height.",
                {
                    "measured": boolean(),
                    "torch_offset_mm": number(),
                    "yaw_from_config_deg": number(),
                    "height_from_tip_mm": number("The measured torch's end above the tip along the finger (0: not measured)."),
                    "tip_height_mm": number("The tip's height over the seam the weld planned (weld.tip_height less that)."),
                },
                ("measured", "torch_offset_mm", "yaw_from_config_deg", "height_from_tip_mm", "tip_height_mm"),
            ),
            "height_probe": HEIGHT_PROBE_SCHEMA,
            "retract_error": string("Why the retract after the weld failed (absent when it did not)."),
            "procedure": PROCEDURE_SCHEMA,
            "arc": ARC_SCHEMA,
        },
        (
            "dry_run",
            "figures",
            "paths",
            "refined_path",
            "torch_path",
            "planned_path",
            "workpiece",
            "calibration_job",
            "tool_calibration_job",
            "torch",
            "height_probe",
        ),
    ),
)


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


# Share of the motion limits of the move out of the joint after a fault (retract_after_fault = clear).
CLEAR_SPEED = 0.1


async def _retract(
    ctx: JobContext, devices: CellDevices, z: np.ndarray, height: float, q_scan: np.ndarray | None, speed: float, up_speed: float = 0.2
) -> str:
    """Stop, the tool straight up by ``height`` (m, along ``z``) and back to the scan pose (when ``q_scan``, the
    joints the arm scanned from, is given) by a joint move; why not, or "".

    A joint move, not a straight one: the tool along the seam may be turned half a turn about its axis from
    the scan pose, where the shorter way round is a matter of milliradians (of the seam as found, or of the
    arm's calibration) and the longer one takes wrist 3 past its limit."""
    try:
        await devices.stop_robot()
        state = devices.robot.require_motion().state()
        if state is not None:
            T_up = state.T_base_tcp.copy()
            T_up[:3, 3] += height * z
            ctx.progress("retract", None, "tool up and away" if q_scan is not None else "tool straight out of the joint")
            await devices.robot.move_to(T_up, speed_scale=min(speed, up_speed))
            if q_scan is not None:
                await devices.robot.move_joints(q_scan, speed_scale=speed)
    except CelldError as exc:
        log.error("retract_after_weld_failed", job=ctx.job_id, error=str(exc))
        return str(exc)
    return ""


async def _after_fault(
    ctx: JobContext, devices: CellDevices, wc: WeldConfig, fault: CelldError, z: np.ndarray, q_scan: np.ndarray, speed: float
) -> None:
    """Move the arm after ``fault`` stopped the weld only as ``weld.retract_after_fault`` says, and never after a
    protective stop or with the link down; what it did is added to the fault (a note: the job's reason says it)
    and logged in the recording."""
    mode = wc.retract_after_fault
    motion = devices.robot.motion
    if mode == "none":
        note = "the arm was left where it stopped (weld.retract_after_fault = none)"
    elif isinstance(fault, SafetyStop):
        note = "the arm was left where it stopped: no move after a safety stop"
    elif motion is None or not motion.link_running():
        note = "the arm was left where it stopped: the robot link is down"
    else:
        full = mode == "full"
        error = await _retract(ctx, devices, z, wc.retract_height, q_scan if full else None, speed, CLEAR_SPEED)
        moved = f"the tool {wc.retract_height * 1e3:g} mm straight up" + (", then to the scan pose" if full else "")
        note = f"after the fault, {moved} (weld.retract_after_fault = {mode})" + (f", which failed: {error}" if error else "")
    fault.add_note(note)
    log.warning("weld_stopped_by_a_fault", job=ctx.job_id, fault=str(fault), after=note)
    if ctx.recording is not None:
        ctx.recording.event_later(f"weld stopped: {fault}; {note}", "WARN")


async def _probe_height(
    ctx: JobContext,
    devices: CellDevices,
    config: Config,
    plan: WeldPlan,
    servo: ServoConfig,
    tool_cfg: ToolConfig,
    sensor_yaw: float,
    speed: float,
    bound: float | None,
    tool_job: str,
) -> tuple[dict[str, Any], WeldPlan, FingerGain]:
    """Touch the far wall and the finger wall at the start; the finger's gain from the touches
    (:func:`celld.weld.plan.measured_finger`), the tip's height in the joint from the width there
    (:func:`celld.weld.plan.probed_height`), and the calibration's error there against ``bound`` (m, the
    calibration's own; :func:`celld.weld.plan.touch_check`). Returns what was found, the plan moved to that
    height, the tool at its new start (unchanged when not probed), and the finger's gain. A measured gain is kept
    for the welds with the same tool calibration (``tool_job``) that cannot measure it (not probed, or touches
    too fast for the camera), and held against the one kept before it (:func:`celld.weld.plan.compared_finger`)."""
    wc = config.weld
    targets, why = probe_targets(plan, tool_cfg) if wc.probe_height else ([], "weld.probe_height is off")
    if not targets:
        finger, reading = _kept_finger(ctx.state_dir, tool_job, servo.delta_d, f"not probed: {why}")
        log.info("finger_gain", job=ctx.job_id, **reading)
        return {"probed": False, "why": why, "finger": reading}, plan, finger
    motion = devices.robot.require_motion()
    tool = ToolGeometry.from_config(tool_cfg)
    origin, across = probe_across(plan)
    touched = {}
    for target in targets:
        ctx.progress("probe", None, f"touching the {target.name} wall of the joint")
        servo_plan = algorithm2_plan(
            target.line, servo, target.tool, config.motion, T_base_plane=plan.geometry.T_base_plane, touch_only=True, sensor_yaw=sensor_yaw
        )
        touched[target.name] = await _run_servo(motion, servo_plan, wc.timeout)
        await devices.robot.move_to(plan.T_start, speed_scale=speed)
    # The finger's gain from the touches' approaches; the walls where the tip, not the tag, says they are.
    presses = [touch_press(records, tool, origin, across, tool.side, servo.delta_d) for records in touched.values()]
    finger, finger_found = measured_finger(presses, servo.delta_d)
    if finger_found["measured"]:
        finger_found = await asyncio.to_thread(_keep_finger, ctx, tool_job, servo.delta_d, finger_found)
    else:
        finger, finger_found = _kept_finger(ctx.state_dir, tool_job, servo.delta_d, finger_found["why"])
    log.info("finger_gain", job=ctx.job_id, **finger_found)
    touches = {name: contact_across(records, tool, origin, across, tool.side, servo.delta_d, finger) for name, records in touched.items()}
    found, moved = probed_height(plan, touches, finger_found, tool, tool.T_tcp_tool, wc.max_height_correction)
    check = found["touch_check"] = judged(found["touch_check"], bound)
    log.info("tip_height_probed", job=ctx.job_id, **{k: v for k, v in found.items() if k not in ("touch_check", "finger")})
    log.info("touch_check", job=ctx.job_id, **{k: check[k] for k in ("across_mm", "height_mm", "error_mm", "bound_mm", "verdict")})
    if check["verdict"] == "beyond_bound":
        log.warning(
            "calibration_off_at_weld",
            advice="calibrate again",
            job=ctx.job_id,
            error_mm=check["error_mm"],
            bound_mm=check["bound_mm"],
        )
    await devices.robot.move_to(moved.T_start, speed_scale=speed)
    return found, moved, finger


def _kept_finger(state_dir: Path, tool_job: str, delta_d: float, why: str) -> tuple[FingerGain, dict[str, Any]]:
    """The finger's gain a weld that did not measure it (``why``) tracks with: the one kept for its tool calibration
    (:func:`celld.daemon.store.stored_finger`), else the tag's deformation as the tip's; and its reading."""
    stored, none = stored_finger(state_dir, tool_job, delta_d)
    if stored is None:
        return FingerGain(), {"measured": False, "why": f"{why}; none kept to use ({none}): the tag's deformation taken as the tip's"}
    kept = {**stored.finger.reading(), "job": stored.job, "at": stored.at}
    return stored.finger, {"measured": False, "why": why, "stored": kept}


def _keep_finger(ctx: JobContext, tool_job: str, delta_d: float, reading: dict[str, Any]) -> dict[str, Any]:
    """A weld's measured finger gain held against the one kept before it (a warning when the finger has changed),
    then kept in its place."""
    before, _ = stored_finger(ctx.state_dir, tool_job, delta_d)
    if before is not None:
        reading = compared_finger(reading, before.finger.gain, before.gain_sigma, before.job)
        if reading["previous"]["changed"]:
            log.warning(
                "finger_gain_changed",
                advice="check the finger and its tag for wear",
                job=ctx.job_id,
                gain=reading["gain"],
                before=before.finger.gain,
                before_job=before.job,
            )
    store_finger(ctx.state_dir, ctx.job_id, tool_job, reading)
    return reading


async def _run_servo(motion: Any, plan: ServoPlan, timeout: float) -> np.ndarray:
    """Run a servo plan to its end; the motion records of it."""
    with _Collector(motion) as collector:
        collector.command_id = await motion.start_servo(plan)
        await motion.wait(collector.command_id, timeout=timeout)
    records = await asyncio.to_thread(collector.records)  # 7000 records: tens of ms of copying
    if records is None:
        raise CelldError("a touch ran but no motion record of it was read")
    return records


@dataclass(frozen=True)
class WeldSetup:
    """What a weld job welds with, checked before anything moves (:func:`weld_setup`)."""

    servo: ServoConfig  # Algorithm 2's parameters with the job's overrides
    tool_config: ToolConfig  # the tool with the current tool calibration's tip and torch
    tool: ToolGeometry
    tool_job: str  # the tool calibration it came from ("": the config's)
    sensor_yaw: float  # rad: the measured torch turns the tool's x axis by it
    torch_measured: bool
    torch_height: float  # m, the measured torch's end above the tip along the finger (0: not measured)
    weld: WeldConfig  # the weld's settings, the tip's height moved for the torch (celld.weld.plan.for_torch)
    placement: Placement  # the current calibration's scanner
    range_bias: float  # m, the scanner's on metal
    calibration_job: str
    site_bound: float | None  # m, the calibration's own bound on its error at the weld (None: it stores none)
    workpiece: Workpiece
    part: PreparedPart
    # The weld procedure the power source welds with (None: the cell has no [power_source], or the arc is off).
    procedure: WeldProcedure | None = None


@dataclass(frozen=True)
class WeldDryRun:
    """A dry run's result: the weld scanned, planned and checked against the cell; nothing moved."""

    setup: WeldSetup
    plan: WeldPlan
    min_clearance: float  # m, the path's least clearance from the cell

    def as_dict(self) -> dict[str, Any]:
        """The result as :data:`RESULT_SCHEMA` has it."""
        return {
            "dry_run": True,
            "workpiece": self.setup.workpiece.name,
            "calibration_job": self.setup.calibration_job,
            "tool_calibration_job": self.setup.tool_job,
            "planned_path": self.plan.geometry.seam_base.tolist(),
            "tcp_path": [se3.to_ur_pose(T).tolist() for T in self.plan.path],
            "min_clearance_mm": round(self.min_clearance * 1e3, 2),
            "seam_length_mm": round(self.plan.seam.length * 1e3, 2),
        }


@dataclass(frozen=True)
class WeldOutcome:
    """A weld's result: its figures and paths (:func:`celld.weld.plan.summarise`), the torch it placed, the probe."""

    setup: WeldSetup
    figures: dict[str, Any]
    paths: dict[str, Any]  # planned, planned wall, refined, torch: lists of base-frame points, m
    paths_file: Path
    height_probe: dict[str, Any]
    retract_error: str = ""
    arc: dict[str, Any] | None = None  # what the arc did (celld.weld.arc_report), with a power source

    def as_dict(self) -> dict[str, Any]:
        """The result as :data:`RESULT_SCHEMA` has it."""
        setup = self.setup
        out: dict[str, Any] = {
            "dry_run": False,
            "figures": self.figures,
            "paths": str(self.paths_file),
            "refined_path": self.paths["refined"],
            "torch_path": self.paths["torch"],
            "planned_path": self.paths["planned"],
            "workpiece": setup.workpiece.name,
            "calibration_job": setup.calibration_job,
            "tool_calibration_job": setup.tool_job,
            # The torch the weld placed: measured (its offset and the tool's x turned by -sensor_yaw) or as configured.
            "torch": {
                "measured": setup.torch_measured,
                "torch_offset_mm": round(setup.tool_config.torch_offset * 1e3, 4),
                "yaw_from_config_deg": round(-math.degrees(setup.sensor_yaw), 4),
                "height_from_tip_mm": round(setup.torch_height * 1e3, 4),
                "tip_height_mm": round(setup.weld.tip_height * 1e3, 4),
            },
            "height_probe": self.height_probe,
        }
        if self.retract_error:
            out["retract_error"] = self.retract_error
        if setup.procedure is not None:
            out["procedure"] = setup.procedure.as_dict()
        if self.arc is not None:
            out["arc"] = self.arc
        return out


async def weld_setup(ctx: JobContext, config: Config, job: WeldJob, cache: dict[str, Any]) -> WeldSetup:
    """The job's overrides checked against the config, the weld procedure, the current calibration and tool, the
    part prepared (once per model: ``cache`` keeps them by content, so a user's model edited on disk is prepared again)."""
    procedure = weld_procedure(config, job)
    v_const = job.v_const
    if procedure is not None:
        if job.v_const is not None:
            raise JobError(
                "$.v_const_mm_s",
                f"the travel speed is the procedure's ({procedure.ident}: {procedure.travel_speed * 1e3:g} mm/s): leave v_const_mm_s out",
            )
        v_const = procedure.travel_speed
    try:
        servo, tool_cfg = with_overrides(
            config.servo,
            config.tactile,
            config.tool,
            "weld job",
            config.motion.max_linear_speed,
            delta_d=job.delta_d,
            k_p=job.k_p,
            v_const=v_const,
            torch_offset=job.torch_offset,
        )
    except ConfigError as exc:
        # The job's field of the refused value: its key in the section (delta_d_mm, ...).
        raise JobError("$." + exc.key.rsplit(".", 1)[-1], exc.reason) from exc
    placement, range_bias, cal_job, bound = current_calibration(ctx.state_dir, config.scanner.mount)
    tool_cfg, tool_job, sensor_yaw, torch_measured, torch_height = current_tool(ctx.state_dir, tool_cfg)
    try:
        weld = for_torch(config.weld, torch_height)
    except WorkpieceError as exc:
        raise JobError("$", f"the current tool calibration {tool_job}: {exc}") from exc
    if torch_measured and job.torch_offset is not None:
        raise JobError(
            "$.torch_offset_mm",
            f"the torch is measured (tool calibration {tool_job}: {tool_cfg.torch_offset * 1e3:.2f} mm behind the tip); "
            "leave torch_offset_mm out, or measure the tool again",
        )
    workpiece = resolve_workpiece(job.workpiece, config)
    key = hashlib.sha1(
        workpiece.vertices.tobytes() + workpiece.triangles.tobytes() + workpiece.seam.tobytes() + np.float64(weld.tip_height).tobytes()
    ).hexdigest()
    if key not in cache:
        ctx.progress("prepare", None, f"preparing the model of {workpiece.name}")
        cache[key] = await asyncio.to_thread(prepare_part, workpiece, config.seam, weld.tip_height)
    return WeldSetup(
        servo=servo,
        tool_config=tool_cfg,
        tool=ToolGeometry.from_config(tool_cfg),
        tool_job=tool_job,
        sensor_yaw=sensor_yaw,
        torch_measured=torch_measured,
        torch_height=torch_height,
        weld=weld,
        placement=placement,
        range_bias=range_bias,
        calibration_job=cal_job,
        site_bound=bound,
        workpiece=workpiece,
        part=cache[key],
        procedure=procedure,
    )


def weld_procedure(config: Config, job: WeldJob) -> WeldProcedure | None:
    """The procedure a weld runs with: the job's, else ``weld.procedure``; None without a power source or an arc."""
    name = job.procedure or config.weld.procedure
    if not config.power_source.enabled:
        if job.procedure:
            raise JobError("$.procedure", "this cell has no [power_source]: its arc is robot.arc_output alone, with no procedure")
        return None
    if not job.arc:
        return None
    directory = Path(config.weld.procedures_dir) if config.weld.procedures_dir else cell_procedures(Path(config.source))
    if not name:
        known = ", ".join(list_procedures(directory)) or "none"
        raise JobError("$.procedure", f"this cell welds with a power source: name a weld procedure (in {directory}: {known})")
    try:
        return load_procedure(directory, name)
    except ConfigError as exc:
        raise JobError("$.procedure", str(exc)) from exc


def check_source_ready(last: np.void | None) -> None:
    """Refuse a weld at once when the motion loop's latest record says the power source cannot weld."""
    state = source_state(last)
    if state is None:
        return  # no record yet, or no source read: the motion core refuses the servo itself
    problem = source_problem(state)
    if problem:
        raise JobError("$", problem)


async def _scan_and_plan(ctx: JobContext, config: Config, devices: CellDevices, setup: WeldSetup, dry_run: bool) -> WeldPlan:
    """Steps 1 and 2: the scan from the scan pose (a dry run's arm must be there already), the seam and the plan."""
    motion = devices.robot.require_motion()
    T_scan = se3.from_ur_pose(config.weld.scan_pose)
    if dry_run:
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
        await devices.robot.move_to(T_scan, speed_scale=config.weld.speed_scale)
    here = motion.state()
    cloud = await devices.scanner.capture()
    # The scanner where it is now (a scanner on the arm moves with its link, Eq. 8).
    T_base_cam = setup.placement.T_base_cam(None if here is None else here.q)
    # The calibration's range bias on metal: the scan (a metal part on a steel
    # table) moved back along its rays, as the calibration was solved.
    points = correct_range_bias(cloud.points, setup.range_bias) if setup.range_bias else np.asarray(cloud.points)
    rec = ctx.recording
    if rec is not None:
        await asyncio.to_thread(record_cell, rec, devices.robot.planner.with_tool)
        rec.later(rec.log_camera_pose, T_base_cam, time.monotonic_ns())
        await asyncio.to_thread(rec.log_cloud_cam, "scan", points)

    workpiece = setup.workpiece
    ctx.progress("seam", None, f"finding the seam of {workpiece.name} with calibration {setup.calibration_job or '(unnamed)'}")
    plan = await asyncio.to_thread(plan_weld, points, T_base_cam, setup.part, setup.weld, config.seam, setup.tool.T_tcp_tool, T_scan)
    placement = setup.placement
    if placement.arm is not None and here is not None:
        # The plan is in the calibrated arm's base frame (the scan placed by the arm fit's T_base_cam): what
        # the controller is sent, and what touch then measures by its reports, is in its own.
        T_flange_tcp = devices.robot.planner.T_flange_tcp
        q_near = np.asarray(here.q, dtype=np.float64)
        try:
            plan = await asyncio.to_thread(
                precorrected, plan, lambda T: placement.precorrect(T, q_near, T_flange_tcp), setup.tool.T_tcp_tool
            )
        except InputError as exc:
            raise WorkpieceError(f"the weld cannot be pre-corrected through the arm's calibration: {exc}") from exc
    seam = plan.seam
    if rec is not None:
        rec.later(rec.log_path_base, "planned", plan.geometry.seam_base, time.monotonic_ns())
        # The part model where the scan placed it.
        await asyncio.to_thread(rec.log_mesh, layout.WORKPIECE, workpiece.vertices, workpiece.triangles, seam.T_base_obj)
    ctx.progress("seam", None, f"seam found: {seam.length * 1e3:.1f} mm", length_mm=seam.length * 1e3, **_quality(seam))
    return plan


async def _track(
    ctx: JobContext, config: Config, devices: CellDevices, setup: WeldSetup, plan: WeldPlan, finger: FingerGain, process: bool
) -> np.ndarray:
    """Step 4: Algorithm 2 touches the wall and tracks it with the finger's gain, the arc on while it tracks when ``process`` (with a power
    source, in the sequence of the setup's procedure); progress and the finger's camera while it runs. Returns the
    motion records of the track; raises its failure, or the motion loop's own trouble during it (a failed arc
    write: the weld is not good). A failure with a power source says how much of the seam was welded."""
    motion = devices.robot.require_motion()
    geometry = plan.geometry
    servo_plan = algorithm2_plan(
        geometry.wall_base,
        setup.servo,
        setup.tool_config,
        config.motion,
        T_base_plane=geometry.T_base_plane,
        process=process,
        seam_offset=geometry.offsets,
        sensor_yaw=setup.sensor_yaw,
        finger=finger,
    )
    procedure = setup.procedure if process else None
    if procedure is not None:
        servo_plan = servo_plan._replace(params={**servo_plan.params, **plan_keys(sequence_of(procedure))})
        if ctx.recording is not None:
            ctx.recording.event_later(f"weld procedure {procedure.ident} (digest {procedure.digest[:12]})")
    events_before = motion.loop_event_count
    with _Collector(motion) as collector:
        cid = await motion.start_servo(servo_plan)
        collector.command_id = cid
        ctx.progress(
            "track",
            0.0,
            "touching the seam, then tracking" + (" with the arc on" if servo_plan.params.get("process") else " (dry run, arc off)"),
        )
        waiting = asyncio.ensure_future(motion.wait(cid, timeout=config.weld.timeout))
        s_wall = polyline.arc_length(geometry.wall_base)
        try:
            last_progress = 0.0
            last_frame = 0
            while not waiting.done():
                await asyncio.wait({waiting}, timeout=PREVIEW_PERIOD)
                last_frame = await asyncio.to_thread(_log_preview, devices, ctx.recording, last_frame)
                now = asyncio.get_running_loop().time()
                last = motion.last_record()
                if last is not None and not waiting.done() and now - last_progress >= PROGRESS_PERIOD:
                    last_progress = now
                    p = setup.tool.T_base_tool(se3.from_ur_pose(last["tcp_pose"]))[:3, 3]
                    i = int(np.argmin(np.linalg.norm(geometry.wall_base - p, axis=1)))
                    ctx.progress(
                        "track",
                        float(min(1.0, s_wall[i] / s_wall[-1])),
                        f"{s_wall[i] * 1e3:.0f} of {s_wall[-1] * 1e3:.0f} mm",
                        arc=bool(last["process_on"]),
                    )
            try:
                waiting.result()
            except CelldError as exc:
                if procedure is not None:
                    await _report_arc_after_fault(ctx, exc, collector.records(), setup, plan, procedure)
                raise
        finally:
            if not waiting.done():
                waiting.cancel()
    new_events = min(motion.loop_event_count - events_before, len(motion.loop_events))
    trouble = list(motion.loop_events)[-new_events:] if new_events > 0 else []
    if trouble:
        raise CelldError(f"the motion loop reported during the weld: {'; '.join(trouble)}")
    records = await asyncio.to_thread(collector.records)  # 7000 records: tens of ms of copying
    if records is None or len(records) == 0:
        raise CelldError("the servo ran but no motion record of it was read")
    return records


async def run_weld(ctx: JobContext, config: Config, devices: CellDevices, cache: dict[str, Any]) -> Mapping[str, Any]:
    """The weld job (module docstring); its result's shape: :data:`RESULT_SCHEMA`."""
    job = ctx.job
    if not isinstance(job, WeldJob):
        raise JobError("$.kind", "not a weld job")
    srm = devices.tactile.process
    if srm is None:
        raise JobError("$", "the cell has no tactile sensor (tactile.kind); it cannot track a seam")
    if not srm.running():
        raise JobError(
            "$", f"the tactile sensor is not running ({devices.tactile.error or 'its process ended'}); the daemon keeps restarting it"
        )
    devices.robot.require_motion()  # refused at once without a motion process
    wc = config.weld
    setup = await weld_setup(ctx, config, job, cache)
    for_controller(setup.placement, devices.robot.require_kinematics)
    speed = wc.speed_scale
    welding = bool(job.arc) and (config.robot.arc_output >= 0 or config.power_source.enabled)
    if welding and setup.procedure is not None and not job.dry_run:
        check_source_ready(devices.robot.require_motion().last_record())

    # 1, 2. scan, seam and the weld's plan
    plan = await _scan_and_plan(ctx, config, devices, setup, job.dry_run)
    # 3. the whole path, checked against the cell before the tool moves to it:
    # above the start, down, along the seam, up and back to the scan pose.
    rec = ctx.recording
    if rec is not None:
        rec.later(rec.log_path_base, "plan", plan.path[:, :3, 3], time.monotonic_ns())
    # The arm is at the scan pose now (a dry run's too): the weld comes back to these joints (_retract).
    q_scan = await devices.robot.current_q()
    check = await asyncio.to_thread(_check_weld_path, devices.robot.planner, q_scan, plan.path)
    if job.dry_run:
        stations = np.linspace(0, len(check.q) - 1, min(len(check.q), DRY_RUN_ROBOTS)).round().astype(int)
        await asyncio.to_thread(record_plan, rec, devices.robot.planner.with_tool, [tuple(check.q[i]) for i in stations])
        return WeldDryRun(setup, plan, check.min_clearance).as_dict()
    ctx.progress("approach", None, "tool to the seam's start")
    await devices.robot.move_to(plan.T_above, speed_scale=speed)
    await devices.robot.move_to(plan.T_start, speed_scale=min(speed, 0.2))
    ctx.progress("tare", None, "taring the SRM, finger free")
    await asyncio.to_thread(srm.tare)

    # The tip's height in the joint, probed by touch: the plan's height error moves where the finger
    # meets a sloping wall, and so where the torch goes. The plan moves to the height it should have.
    up = plan.up
    try:
        height_probe, plan, finger = await _probe_height(
            ctx, devices, config, plan, setup.servo, setup.tool_config, setup.sensor_yaw, min(speed, 0.2), setup.site_bound, setup.tool_job
        )
    except CelldError as exc:
        await _after_fault(ctx, devices, wc, exc, up, q_scan, speed)
        raise

    # 4. touch and track; 5. retract (also after a failed track, while the robot can still be moved)
    try:
        records = await _track(ctx, config, devices, setup, plan, finger, process=welding)
    except CelldError as exc:
        await _after_fault(ctx, devices, wc, exc, up, q_scan, speed)
        raise
    retract_error = await _retract(ctx, devices, up, wc.retract_height, q_scan, speed)

    figures, paths = await asyncio.to_thread(summarise, records, plan, setup.tool, setup.servo.delta_d)
    arc = None
    if welding and setup.procedure is not None:
        arc = await asyncio.to_thread(_arc_report, records, setup, plan, setup.procedure)
        if arc["flagged"]:
            data = arc["weld_data"]
            log.warning("weld_outside_procedure_window", job=ctx.job_id, procedure=setup.procedure.ident, outside_s=data["outside_s"])
            ctx.progress("track", 1.0, f"flagged: {data['outside_s']:.2f} s outside {setup.procedure.ident}'s current or voltage window")
    path_file = await asyncio.to_thread(fsutil.write_json, ctx.result_dir() / "paths.json", paths)
    if rec is not None:
        for name in ("refined", "torch"):
            if len(paths[name]) > 1:
                rec.later(rec.log_path_base, name, np.asarray(paths[name]), time.monotonic_ns())
    return WeldOutcome(setup, figures, paths, Path(path_file), height_probe, retract_error, arc).as_dict()


def _arc_report(records: np.ndarray, setup: WeldSetup, plan: WeldPlan, procedure: WeldProcedure) -> dict[str, Any]:
    """What the arc did along the seam as the weld found it (the plan to the first touch, then the refined path)."""
    # The law's FINISH phase (3: the seam ended ahead of the finger) means the finger found the joint's end.
    found_end = bool(np.any(records["servo_phase"] == FINISH_PHASE))
    seam = known_seam(plan.geometry.seam_base, refined_of(records), found_end)
    return arc_report(records, torch_positions(records, setup.tool), seam, procedure)


async def _report_arc_after_fault(
    ctx: JobContext, fault: CelldError, records: np.ndarray | None, setup: WeldSetup, plan: WeldPlan, procedure: WeldProcedure
) -> None:
    """What the arc did before ``fault`` ended the weld: written to the job's arc.json and added to the fault."""
    if records is None or len(records) == 0:
        return
    report = await asyncio.to_thread(_arc_report, records, setup, plan, procedure)
    path = await asyncio.to_thread(fsutil.write_json, ctx.result_dir() / "arc.json", report)
    stretches = ", ".join(f"{a:.1f}-{b:.1f}" for a, b in report["unwelded_stretches_mm"]) or "none"
    fault.add_note(
        f"the arc ({procedure.ident}) welded {report['welded_mm']:.1f} of {report['seam_length_mm']:.1f} mm; "
        f"unwelded {report['unwelded_mm']:.1f} mm (mm along the seam: {stretches}); "
        f"{report['failed_starts']} failed starts, {report['arc_losses']} arc losses; {path}"
    )


def _check_weld_path(planner: MotionPlanner, q_scan: np.ndarray, path: np.ndarray) -> PathCheck:
    """The weld's path against the cell from the scan pose's joints ``q_scan``: straight lines through its poses
    up to the tool lifted at the seam's end, then the joint move back to ``q_scan`` (:func:`_retract`)."""
    lines = planner.check_path(q_scan, path[:-1])
    back = planner.check_joint_move(lines.q[-1], q_scan)
    # The path parameter as check_waypoints gives it over the whole path: k / n at its k-th pose.
    n = len(path)
    s = np.concatenate([lines.s * (n - 1) / n, (n - 1 + back.s) / n])
    return PathCheck(np.concatenate([lines.q, back.q]), s, min(lines.min_clearance, back.min_clearance), None)


def _log_preview(devices: CellDevices, rec: JobRecording | None, last_stamp: int) -> int:
    """Log the SRM camera's latest shared frame (with the tag's outline) if it is new; its stamp (in a worker thread:
    an image and the arm's capsules take milliseconds to encode)."""
    srm = devices.tactile.process
    if rec is None or srm is None:
        return last_stamp
    frame = srm.latest_preview()
    if frame is None or frame[0] == last_stamp:
        return last_stamp
    stamp, image, corners = frame
    try:
        rec.log_camera_image(image, corners, stamp_ns=stamp)
        # The arm as it moves, at the rate of the previews.
        here = devices.robot.require_motion().state()
        if here is not None:
            record_arm(rec, devices.robot.planner.with_tool, here.q, stamp_ns=here.stamp_ns)
    except CelldError as exc:
        log.warning("srm_frame_not_recorded", error=str(exc))
    return stamp


def _quality(seam: Any) -> dict[str, Any]:
    q = seam.quality.to_dict()
    return {k: q[k] for k in ("source", "fitness", "inlier_rmse", "coverage") if k in q}
