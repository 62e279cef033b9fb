"""Job runners: what each job kind does with the cell's devices.

A runner is a coroutine ``runner(ctx) -> result dict``. It raises a
:class:`~celld.errors.CelldError` to fail; the job manager then stops the
robot and records the reason. Heavy maths (detection, ICP, solves) runs in
worker threads so the event loop keeps answering the bus.

- **calibrate**: :mod:`celld.daemon.calibrate` (with ``robot2``:
  :mod:`celld.daemon.two_robots`);
- **move**: a jerk-limited straight move of the TCP to a pose, or a
  jerk-limited joint move (straight in joint space, sent as speedJ) to joint
  positions; both checked against the cell first (planning module); of robot
  1, or of robot 2 (``robot: 2``) checked against robot 1 where it stands;
- **health**: the robot link and loop timing, the scanner (one capture), the
  tactile sensor;
- **weld**: :mod:`celld.daemon.weld`;
- **tool-calibrate**: :mod:`celld.daemon.toolcal`.

Every job that moves robot 1 is checked against robot 2 where it stands on a
cell with two robots (:meth:`~celld.daemon.devices.CellDevices.beside_robot2`).

Each runner's result has its JSON Schema beside the runner (here
:data:`MOVE_RESULT_SCHEMA` and :data:`HEALTH_RESULT_SCHEMA`);
:mod:`celld.daemon.results` gathers them by job kind for the bus.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from celld import se3
from celld.bus.requests import CalibrateJob, HealthJob, MoveJob
from celld.config import Config
from celld.daemon.arm import Arm
from celld.daemon.calibrate import run_calibrate
from celld.daemon.devices import INTERLOCK_SCHEMA, CellDevices
from celld.daemon.jobs import JobContext, Runner
from celld.daemon.toolcal import run_tool_calibrate
from celld.daemon.two_robots import run_calibrate_two
from celld.daemon.verify import ensure_verified, run_verify
from celld.daemon.weld import run_weld
from celld.errors import CelldError, DeviceError, JobError
from celld.journal import utc_now
from celld.motion.handle import HEALTH_SCHEMA
from celld.motion.source_io import BIT_ROLES, source_problem, source_state
from celld.robot.dashboard import CONDITION_SCHEMA
from celld.schemadoc import boolean, const, integer, number, obj, one_of, string, texts, vector, with_properties


def build_runners(config: Config, devices: CellDevices) -> dict[str, Runner]:
    """The runners of every job kind this cell can run."""

    async def calibrate(ctx: JobContext) -> Mapping[str, Any]:
        if isinstance(ctx.job, CalibrateJob) and ctx.job.robot2:
            return await run_calibrate_two(ctx, config, devices, ctx.job)
        return await run_calibrate(ctx, config, devices)

    async def move(ctx: JobContext) -> Mapping[str, Any]:
        if isinstance(ctx.job, MoveJob) and ctx.job.robot == 2:
            return await run_move_robot2(ctx, devices)
        async with devices.beside_robot2():
            return await run_move(ctx, devices.robot)

    async def health(ctx: JobContext) -> Mapping[str, Any]:
        return await run_health(ctx, devices)

    weld_cache: dict[str, Any] = {}  # prepared part models, by name

    started = utc_now()  # a weld verifies the calibration first once after a start (celld.daemon.verify)

    async def weld(ctx: JobContext) -> Mapping[str, Any]:
        if config.calibration.verify_before_weld and not getattr(ctx.job, "dry_run", False):
            await ensure_verified(ctx, config, devices, started)
        return await run_weld(ctx, config, devices, weld_cache)

    async def verify(ctx: JobContext) -> Mapping[str, Any]:
        return await run_verify(ctx, config, devices)

    async def tool_calibrate(ctx: JobContext) -> Mapping[str, Any]:
        return await run_tool_calibrate(ctx, config, devices)

    def beside_robot2(run: Runner) -> Runner:
        """A job that moves robot 1, its moves checked against robot 2 where it stands (a two-robot cell;
        a calibrate job with robot2 puts robot 2 where it parks it, celld.daemon.two_robots)."""

        async def checked(ctx: JobContext) -> Mapping[str, Any]:
            async with devices.beside_robot2():
                return await run(ctx)

        return checked

    moving = {"calibrate": calibrate, "weld": weld, "tool-calibrate": tool_calibrate, "verify": verify}
    return {"health": health, "move": move, **{kind: beside_robot2(run) for kind, run in moving.items()}}


# -- move ----------------------------------------------------------------------------

_UR_POSE = vector("The TCP pose [x, y, z, rx, ry, rz] the robot reports, m and rad, base frame.", 6)
# The JSON shape of a move job's result (run_move).
MOVE_RESULT_SCHEMA = one_of(
    "Where the move ended.",
    obj(
        "A joint move: the joints the robot reports, their error from the target, and the TCP there.",
        {
            "space": const("joint"),
            "q": vector("Joint positions, rad.", 6),
            "joint_error_deg": vector("|q - target| of each joint.", 6),
            "tcp_pose": _UR_POSE,
        },
        ("space", "q", "joint_error_deg", "tcp_pose"),
    ),
    obj(
        "A Cartesian move: the TCP pose the robot reports and its error from the target.",
        {
            "space": const("cartesian"),
            "tcp_pose": _UR_POSE,
            "error_mm": number("Distance from the target position.", lo=0.0),
            "error_deg": number("Rotation from the target orientation.", lo=0.0),
        },
        ("space", "tcp_pose", "error_mm", "error_deg"),
    ),
)


async def run_move_robot2(ctx: JobContext, devices: CellDevices) -> Mapping[str, Any]:
    """A move job of robot 2: its target in its own base frame, checked against robot 1's arm and tool where
    they stand (nothing moves robot 1 meanwhile)."""
    arm2 = devices.robot2
    if arm2 is None:
        raise JobError("$.robot", "this cell has no second robot ([robot2] in its config)")
    try:
        q1 = await devices.robot.current_q()
    except DeviceError as exc:
        raise DeviceError(f"robot 1's place is unknown ({exc}); robot 2 does not move beside it") from exc
    with arm2.avoiding(devices.robot1_obstacles(q1)):
        return await run_move(ctx, arm2, tool=False)


async def run_move(ctx: JobContext, arm: Arm, *, tool: bool = True) -> Mapping[str, Any]:
    """A move job of ``arm`` (``tool``: its moves are checked with the welding tool on its flange)."""
    job = ctx.job
    if not isinstance(job, MoveJob):
        raise JobError("$.kind", "not a move job")
    target = np.asarray(job.target, dtype=np.float64)
    who = "" if job.robot == 1 else f"robot {job.robot}: "
    if job.space == "joint":
        ctx.progress("move", 0.0, f"{who}joint move to {np.round(target, 4).tolist()} rad")
        state = await arm.move_joints(target, speed_scale=job.speed_scale, tool=tool)
        err = np.degrees(np.abs(np.asarray(state.q) - target))
        return {
            "space": "joint",
            "q": np.asarray(state.q).tolist(),
            "joint_error_deg": err.tolist(),
            "tcp_pose": se3.to_ur_pose(state.T_base_tcp).tolist(),
        }
    T = se3.from_ur_pose(target)
    ctx.progress("move", 0.0, f"{who}moving to {np.round(target, 4).tolist()}")
    state = await arm.move_to(T, speed_scale=job.speed_scale, tool=tool)
    dt, dr = se3.error(state.T_base_tcp, T)
    return {
        "space": "cartesian",
        "tcp_pose": se3.to_ur_pose(state.T_base_tcp).tolist(),
        "error_mm": dt * 1e3,
        "error_deg": math.degrees(dr),
    }


# -- health ----------------------------------------------------------------------------

# The JSON shape of a health job's result (run_health): what was checked, and every problem found.
HEALTH_RESULT_SCHEMA = obj(
    "A health check: the robot link and the loop's timing with the robot's condition (and the second robot's link), the "
    "arc interlock, the welding power source, the scanner (one capture), the tactile sensor: each checked one, and every problem found "
    "(check all reports them here and succeeds; a single check fails the job on one). Null where a figure is not finite.",
    {
        "robot": with_properties(HEALTH_SCHEMA, {"condition": CONDITION_SCHEMA}, ("condition",)),
        "robot2": {**HEALTH_SCHEMA, "description": "The second robot's link and loop, on a cell with one."},
        "arc_interlock": INTERLOCK_SCHEMA,
        "power_source": obj(
            "The welding power source's inputs as the motion loop last read them (a cell with a [power_source]).",
            {
                **{role: boolean() for role in BIT_ROLES},
                "current_a": number("Welding current.", null=True),
                "voltage_v": number("Welding voltage.", null=True),
            },
            (*BIT_ROLES, "current_a", "voltage_v"),
        ),
        "scanner": obj(
            "One capture.",
            {
                "ok": boolean("It returned points."),
                "valid_points": integer(lo=0),
                "shape": vector("Rows and columns of the organized cloud.", 2),
                "error": string("Why the capture failed."),
            },
            ("ok",),
        ),
        "tactile": obj(
            "The tactile process and the SRM: running, seeing its tag, tared.",
            {
                "ok": boolean(),
                "running": boolean(),
                "valid": boolean("The latest sample saw the tag."),
                "tared": boolean(),
                "tare_offset_mm": number("The finger's offset from its reference rest at the tare.", null=True),
                "error": string("Why the sensor is not there or its process ended, empty when none."),
            },
            ("ok", "error"),
        ),
        "problems": texts("Every problem found, empty when none."),
    },
    ("problems",),
)


async def run_health(ctx: JobContext, devices: CellDevices) -> Mapping[str, Any]:
    job = ctx.job
    if not isinstance(job, HealthJob):
        raise JobError("$.kind", "not a health job")
    out: dict[str, Any] = {}
    problems: list[str] = []
    if job.check in ("all", "robot"):
        h = devices.robot.require_motion().health()
        out["robot"] = h._asdict()
        condition = devices.robot_condition()
        out["robot"]["condition"] = condition.as_dict()
        if h.link != "running":
            problems.append(f"robot link {h.link}")
        if not condition.ready:
            problems.append(f"robot {condition.state}: {condition.reason} ({condition.remedy})")
        if devices.robot2 is not None:
            h2 = devices.robot2.require_motion().health()
            out["robot2"] = h2._asdict()
            if h2.link != "running":
                problems.append(f"robot 2 link {h2.link}")
        out["arc_interlock"] = devices.interlock_report()
        if out["arc_interlock"]["missing_seen"]:
            problems.append(out["arc_interlock"]["detail"])
        source = source_state(devices.robot.require_motion().last_record())
        if source is not None:
            out["power_source"] = source
            if problem := source_problem(source):
                problems.append(problem)
    if job.check in ("all", "scanner"):
        try:
            cloud = await devices.scanner.capture()
            n = int(np.count_nonzero(np.all(np.isfinite(cloud.points), axis=-1)))
            out["scanner"] = {"ok": n > 0, "valid_points": n, "shape": list(cloud.points.shape[:2])}
            if n == 0:
                problems.append("the scanner returned no points")
        except CelldError as exc:
            out["scanner"] = {"ok": False, "error": str(exc)}
            problems.append(f"scanner: {exc}")
    if job.check in ("all", "tactile"):
        sample = devices.tactile.sample()
        process = devices.tactile.process
        if process is None:
            out["tactile"] = {"ok": False, "error": "no tactile sensor configured"}
        else:
            running = process.running()
            counters = process.read_counters()
            tared = bool(counters is not None and counters["tared"])
            refused = bool(counters is not None and counters["tare_refused"])
            offset = float(counters["tare_offset"]) if counters is not None else math.nan
            out["tactile"] = {
                "ok": running and tared and sample is not None and sample.valid,
                "running": running,
                "valid": bool(sample and sample.valid),
                "tared": tared,
                "tare_offset_mm": offset * 1e3,
                "error": devices.tactile.error,
            }
            if not running:
                problems.append(f"the tactile process is not running: {devices.tactile.error or 'it ended'}")
            elif not tared and refused:
                problems.append(f"the SRM is not tared: the finger is not free ({offset * 1e3:.2f} mm from its reference rest)")
            elif not tared:
                problems.append("the SRM is not tared yet")
            elif sample is None or not sample.valid:
                problems.append("the tactile sensor sees no tag")
    if problems and job.check != "all":
        raise CelldError("; ".join(problems))
    out["problems"] = problems
    return _json_safe(out)


def _json_safe(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _json_safe(value.item())
    return value
