"""Job runners: what each job kind does with the cell's devices.

A runner is a coroutine ``runner(ctx) -> result dict``. It raises a
:class:`~celld.errors.CelldError` to fail; the job manager then stops the
robot and records the reason. Heavy maths (detection, ICP, solves) runs in
worker threads so the event loop keeps answering the bus.

- **calibrate** (eye-on-base, Algorithm 1 online): the verification pose
  first, then one calibration pose after another: move, settle, capture,
  read the flange pose from the robot, detect the flange, feed Algorithm 1,
  publish a progress event, stop early once the cost reaches
  ``e_required``. The dataset is saved as it is captured, so the session can
  be solved again offline (``celld calib solve``). The final estimate is the
  robust solve over every consistent pair, reported with Algorithm 1's
  history, the e_icp of Eq. 13 and the quality gate's verdict (accept
  refuses a failed one unless forced). With ``compensate`` the calibration
  stored is Eq. 21's compensated estimate, and ``stored`` says so.
  The early stop waits until the gate has its minimum of pairs. Old
  datasets are then pruned by the config's retention rules
  (:mod:`celld.daemon.retention`).
  With ``calibration.range_bias = "estimate"`` (time-of-flight scanners)
  the scanner's range bias on metal is estimated with the transform
  (:mod:`celld.calib.rangebias`) and stored with it (``range_bias_mm`` and
  its 1-sigma): every scan placed with this calibration is corrected by it.
  Algorithm 1 starts with the bias its first four captures' finish steps
  say (the verification cloud's metal points, and the centres when they lie
  on metal, corrected by it).
  With the scanner on the arm (``scanner.mount`` = link1-3, eye-on-arm,
  Eq. 8) each capture's flange pose is moved into the scanner's link frame
  by the joints of that capture, and the same solve, Algorithm 1, e_icp and
  quality gate give ``T_linkN_cam``; the calibration stores it with the
  mount and the DH table (:mod:`celld.calib.mount`).
- **move**: a jerk-limited straight move of the TCP to a pose, or a
  jerk-limited joint move (straight in joint space, sent as speedJ) to joint
  positions; both checked against the cell first (planning module).
- **health**: the robot link and loop timing, the scanner (one capture), the
  tactile sensor.
- **weld**: :mod:`celld.daemon.weld`.
- **tool-calibrate**: :mod:`celld.daemon.toolcal`.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from celld import se3
from celld.bus.schema import CalibrateJob, HealthJob, MoveJob
from celld.calib.algorithm1 import Algorithm1
from celld.calib.dataset import SessionWriter
from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
from celld.calib.flange import FlangeModel, preset
from celld.calib.metrics import IcpVerifier, cost_function
from celld.calib.mount import ScannerMount, in_frame, mount_entry
from celld.calib.pairs import Detections, PairCollector
from celld.calib.poses import calibration_poses
from celld.calib.rangebias import bias_from_steps, correct_range_bias
from celld.calib.session import CalibrationResult, SolveParams, range_bias_data, solve_pairs, verifier_from_cloud
from celld.config import Config
from celld.daemon.devices import Arm, CellDevices
from celld.daemon.jobs import CalibrationStore, JobContext, Runner
from celld.daemon.planning import record_arm, record_cell, record_plan, report_plan
from celld.daemon.retention import prune_sessions
from celld.errors import CalibrationError, CelldError, JobError
from celld.log import get_logger
from celld.recording import layout
from celld.scanner.base import OrganizedCloud

log = get_logger(__name__)


def build_runners(config: Config, devices: CellDevices) -> dict[str, Runner]:
    """The runners of every job kind this cell can run."""

    async def calibrate(ctx: JobContext) -> Mapping[str, Any]:
        return await run_calibrate(ctx, config, devices)

    async def move(ctx: JobContext) -> Mapping[str, Any]:
        return await run_move(ctx, devices)

    async def health(ctx: JobContext) -> Mapping[str, Any]:
        return await run_health(ctx, devices)

    weld_cache: dict[str, Any] = {}  # prepared part models, by name

    async def weld(ctx: JobContext) -> Mapping[str, Any]:
        from celld.daemon.weld import run_weld

        return await run_weld(ctx, config, devices, weld_cache)

    async def tool_calibrate(ctx: JobContext) -> Mapping[str, Any]:
        from celld.daemon.toolcal import run_tool_calibrate

        return await run_tool_calibrate(ctx, config, devices)

    def beside_robot2(run: Runner) -> Runner:
        """A job that moves robot 1, its moves checked against robot 2 where it stands (a two-robot cell;
        a calibrate job with robot2 puts robot 2 where it parks it, celld.daemon.two_robots)."""

        async def checked(ctx: JobContext) -> Mapping[str, Any]:
            async with devices.beside_robot2():
                return await run(ctx)

        return checked

    moving = {"calibrate": calibrate, "move": move, "weld": weld, "tool-calibrate": tool_calibrate}
    return {"health": health, **{kind: beside_robot2(run) for kind, run in moving.items()}}


# -- calibrate ---------------------------------------------------------------------


async def _settled_flange_pose(arm: Arm, T_target: np.ndarray, settle: float) -> tuple[np.ndarray, np.ndarray]:
    """Move to ``T_target`` (the tool is off: the scanner must see the flange), let the arm settle, and
    return the flange pose the robot reports and its joints."""
    motion = arm.require_motion()
    await arm.move_to(T_target, tool=False)
    await asyncio.sleep(settle)
    state = motion.state()
    if state is None:
        raise CalibrationError("no robot state after the move")
    return state.T_base_tcp, np.asarray(state.q, dtype=np.float64)


async def run_calibrate(ctx: JobContext, config: Config, devices: CellDevices) -> Mapping[str, Any]:
    job = ctx.job
    if not isinstance(job, CalibrateJob):
        raise JobError("$.kind", "not a calibrate job")
    if job.robot2:
        from celld.daemon.two_robots import run_calibrate_two

        return await run_calibrate_two(ctx, config, devices, job)
    done = await calibrate_arm(ctx, config, devices, devices.capture, job)
    await prune_calibrations(ctx, config)
    return done.output


async def prune_calibrations(ctx: JobContext, config: Config) -> None:
    """Old calibration datasets pruned by the config's retention rules, never this job's or the current calibration's."""
    cal = config.calibration
    current = CalibrationStore(ctx.state_dir).current() or {}
    await asyncio.to_thread(prune_sessions, ctx.state_dir / "jobs", cal.keep_sessions, cal.keep_days, (ctx.job_id, current.get("job")))


@dataclass(frozen=True)
class ArmCalibration:
    """One robot's calibration as a job made it: the job's output, and the solve (None for a dry run)."""

    output: dict[str, Any]
    result: CalibrationResult | None


async def calibrate_arm(
    ctx: JobContext,
    config: Config,
    arm: Arm,
    capture: Callable[[], Awaitable[OrganizedCloud]],
    job: CalibrateJob,
    *,
    dataset_name: str = "dataset",
    robot: int = 1,
) -> ArmCalibration:
    """Calibrate the scanner to the flange of ``arm``, whose view of the cell is ``config``.

    Robot 1 (the cell's) records into the job's recording; another robot
    (``robot`` 2) saves its dataset under ``dataset_name`` and tags its
    progress events with its number.
    """
    tag = {} if robot == 1 else {"robot": robot}
    who = "" if robot == 1 else f"robot {robot}: "

    def progress(stage: str, fraction: float | None, message: str = "", **data: Any) -> None:
        ctx.progress(stage, fraction, who + message, **tag, **data)

    cal = config.calibration
    if any(abs(v) > 1e-12 for v in config.robot.tcp_offset):
        raise JobError("$", "calibration reads the flange pose: set robot.tcp_offset to zero for a calibrate job")
    flange = preset(cal.flange)
    dparams = PARAMS_BY_SCANNER.get(config.scanner.model, DetectParams())
    overrides: dict[str, Any] = {}
    if job.e_required is not None:
        overrides["e_required"] = job.e_required
    if job.k_max is not None:
        overrides["k_max"] = job.k_max
    if job.compensate:
        overrides["compensate"] = True
    params = SolveParams.from_config(cal, **overrides)
    T_v = se3.from_ur_pose(job.verification_pose if job.verification_pose is not None else cal.verification_pose)
    # The plan, checked against the cell before the robot moves: the verification
    # pose, then the poses; generated ones that fail are replaced, given ones refuse the job.
    planner = arm.planner
    to_v = await asyncio.to_thread(planner.check_move, await arm.current_q(), T_v, False)
    seed = job.seed or 0
    if job.poses:
        candidates = np.array([se3.from_ur_pose(p) for p in job.poses])
        plan = await asyncio.to_thread(planner.plan_calibration, to_v.q_end, candidates, len(candidates))
    else:
        n = job.n_poses if job.n_poses is not None else cal.n_poses

        def more(count: int, rnd: int) -> np.ndarray:
            return calibration_poses(T_v, cal.pose_box, count, cal.max_tilt, seed=seed + 1000 * (rnd + 1))

        candidates = calibration_poses(T_v, cal.pose_box, n, cal.max_tilt, seed=seed)
        plan = await asyncio.to_thread(planner.plan_calibration, to_v.q_end, candidates, n, more)
    poses = np.array(plan.poses)
    report_plan(ctx, plan, who + "calibration")
    # Robot 1's calibration draws the cell, its arm and its solution in the job's recording (base 1's
    # frame); another robot's adds what the scanner saw of it, named for it, in the camera's frame.
    rec = ctx.recording if robot == 1 else None
    seen = ctx.recording
    seen_as = "" if robot == 1 else f"robot{robot}-"
    if job.dry_run:
        record_plan(rec, planner.bare, [tuple(to_v.q_end), *plan.q])
        return ArmCalibration(
            {
                "dry_run": True,
                "plan": {
                    "verification_pose": se3.to_ur_pose(T_v).tolist(),
                    "poses": [se3.to_ur_pose(T).tolist() for T in plan.poses],
                    "joints": [list(to_v.q_end), *[list(q) for q in plan.q]],
                    "refused": [{"pose": list(r.target), "reason": r.reason, "message": r.message} for r in plan.refused],
                },
            },
            None,
        )
    dataset = ctx.result_dir() / dataset_name
    # A scanner on the arm: every pair's robot side is the flange in the scanner's link frame (Eq. 8).
    mount = ScannerMount.of(config.scanner.mount, config.robot.model)
    writer = SessionWriter(dataset, flange=cal.flange, scanner=config.scanner.model, mount=mount)
    if rec is not None:
        # The cell, and the flange model carried by the TCP (the flange: tcp_offset is zero here) at each pose.
        record_cell(rec, planner.bare)
        mesh = await asyncio.to_thread(flange.mesh)
        rec.log_mesh(layout.FLANGE, np.asarray(mesh.vertices), np.asarray(mesh.triangles), static=True)

    # Verification pose first: its cloud scores every estimate (Eq. 13).
    progress("verify", 0.0, "verification pose")
    T_v_robot, q_v = await _settled_flange_pose(arm, T_v, cal.settle)
    cloud_v = await capture()
    await asyncio.to_thread(partial(writer.set_verification, T_v_robot, cloud_v.points, q=q_v))
    if seen is not None:
        seen.log_cloud_cam(seen_as + "verification", cloud_v.points)
    verifier = await asyncio.to_thread(verifier_from_cloud, cloud_v.points, mount.to_link(T_v_robot, q_v), flange, params, dparams)
    alg = Algorithm1(
        verifier, cost_function(params.cost, params.work_radius), e_required=params.e_required, k_max=params.k_max or len(poses)
    )
    estimate_bias = params.range_bias == "estimate"
    bias_online = 0.0  # the range bias Algorithm 1 runs with, m

    pairs = PairCollector(flange, dparams, writer)
    early = False
    result: CalibrationResult | None = None  # solved at an early stop
    q_of: dict[str, np.ndarray] = {}  # each capture's joints, by pair id
    for i, T in enumerate(poses):
        T_bf, q = await _settled_flange_pose(arm, T, cal.settle)
        cloud = await capture()
        got = await asyncio.to_thread(pairs.capture, T_bf, cloud.points, q)
        q_of[got.id] = q
        pid, det = got.id, got.detection
        if got.rejected is not None or det is None:
            reason = got.rejected.reason if got.rejected is not None else "no detection"
            progress("pair", (i + 1) / len(poses), f"pair {pid}: no flange ({reason})", pair=pid, detected=False)
            continue
        if seen is not None:
            seen.log_cloud_cam(seen_as + "pair", cloud.points)
            seen.log_circle_cam(seen_as + "flange", det.center, det.normal, det.radius)
        if rec is not None:
            rec.log_tcp(T_bf)
            here = arm.require_motion().state()
            if here is not None:
                record_arm(rec, planner.bare, here.q)
        data: dict[str, Any] = {"pair": pid, "detected": True, "radius_mm": det.radius * 1e3, "inliers": det.inliers}
        if det.finish_step is not None:
            data["range_bias_mm"] = det.finish_step.bias * 1e3
        found = pairs.detections()
        if pairs.n_pairs == 4:
            if estimate_bias:
                # The first four finish steps fix the bias to about 0.1 mm: Algorithm 1
                # scores with the verification cloud's metal corrected by it.
                bias_online = bias_from_steps(found.steps) or 0.0
                corrected = await asyncio.to_thread(verifier.with_range_bias, bias_online)
                alg = Algorithm1(
                    corrected,
                    cost_function(params.cost, params.work_radius),
                    e_required=params.e_required,
                    k_max=params.k_max or len(poses),
                )
            P_cam = correct_range_bias(found.P_cam, bias_online) if flange.circle_on_metal else found.P_cam
            step = await asyncio.to_thread(alg.start, list(found.ids), found.P_base, P_cam)
        elif pairs.n_pairs > 4 and not alg.done:
            p_cam = correct_range_bias(found.P_cam[-1:], bias_online)[0] if flange.circle_on_metal else found.P_cam[-1]
            step = await asyncio.to_thread(alg.add, pid, found.P_base[-1], p_cam)
        else:
            step = None
        if step is not None:
            data["cost_mm"] = step.cost_optimal * 1e3 if math.isfinite(step.cost_optimal) else None
            data["pool"] = list(step.pool_ids)
            if rec is not None:
                rec.log_e_icp(step.k, step.cost_optimal)
        progress("pair", (i + 1) / len(poses), f"pair {pid}", **data)
        if alg.started and alg.done and pairs.n_pairs >= params.quality.min_pairs and i + 1 < len(poses):
            # Algorithm 1 is done; stop early only when the pairs so far make a calibration that
            # passes its quality gate (a realistic arm's pose-dependent error can leave a handful
            # of pairs disagreeing although the cost is low): else the remaining poses go on.
            result, why = await asyncio.to_thread(_gated_solve, pairs.detections(), params, verifier, flange, pairs.n_captures)
            if result is not None:
                early = alg.reached
                break
            progress("pair", (i + 1) / len(poses), f"Algorithm 1 is done but {why}: capturing more", pair=pid, detected=True)

    found = pairs.detections()
    if pairs.n_pairs < 4:
        raise CalibrationError(f"only {pairs.n_pairs} of {len(poses)} captures showed the flange; at least 4 are needed")
    progress("solve", None, f"solving from {pairs.n_pairs} pairs")
    if result is None:  # not solved already at an early stop
        result = await asyncio.to_thread(
            solve_pairs,
            found.ids,
            found.P_base,
            found.P_cam,
            params,
            verifier,
            found.rejected,
            pairs.n_captures,
            range_bias_data(params, flange, found),
        )
    report = in_frame(result.as_dict(), mount)
    if rec is not None:
        T_base_link = [mount.T_base_link(q_of[pid]) for pid in found.ids]
        _record_solution(
            rec, result.T_base_cam, result.bias, found, report["quality"], flange.circle_on_metal, T_base_link, mount.T_base_link(q_v)
        )
    a1 = alg.result() if alg.started else None
    cost_mm = a1.cost * 1e3 if a1 is not None and math.isfinite(a1.cost) else None
    calibration = {
        "job": ctx.job_id,
        **mount_entry(mount, result.T_base_cam_stored),
        "stored": result.stored,
        "cost_mm": cost_mm,
        "pairs": len(result.pair_ids),
        "dataset": str(dataset),
        "method": result.method,
        "quality": report["quality"],
        # The scanner's range bias on metal, to apply with T_base_cam (0 with mode none).
        "range_bias": params.range_bias,
        "range_bias_mm": result.bias * 1e3,
        "range_bias_std_mm": None if result.range_bias is None else report["range_bias"]["std_mm"],
    }
    log.info(
        "calibration solved",
        job=ctx.job_id,
        robot=robot,
        pairs=len(result.pair_ids),
        cost_mm=cost_mm,
        early_stop=early,
        verdict=result.quality.verdict,
        stored=result.stored,
        range_bias_mm=round(result.bias * 1e3, 3),
    )
    output = {
        "calibration": calibration,
        "report": report,
        "early_stop": early,
        "poses_captured": pairs.n_captures,
        "poses_planned": len(poses),
        "dataset": str(dataset),
    }
    return ArmCalibration(output, result)


def _gated_solve(
    found: Detections, params: SolveParams, verifier: IcpVerifier | None, flange: FlangeModel, n_captures: int
) -> tuple[CalibrationResult | None, str]:
    """The calibration from the pairs found so far if it passes its quality gate, else None and why not."""
    try:
        result = solve_pairs(
            found.ids, found.P_base, found.P_cam, params, verifier, found.rejected, n_captures, range_bias_data(params, flange, found)
        )
    except CalibrationError as exc:
        return None, str(exc)
    if result.quality.verdict != "ok":
        return None, f"the quality gate says {result.quality.verdict} ({'; '.join(result.quality.reasons)})"
    if result.gated:
        # An early stop wants a session the gate passes as the estimator left it; the
        # final solve may still leave the gate's outliers out (solve_pairs).
        return None, f"the quality gate found the pairs {', '.join(result.gated)} to be outliers"
    return result, ""


def _record_solution(
    rec: Any,
    T_ref_cam: np.ndarray,
    bias: float,
    found: Detections,
    quality: Mapping[str, Any],
    circle_on_metal: bool,
    T_base_ref: list[np.ndarray],
    T_base_ref_v: np.ndarray,
) -> None:
    """The solved calibration in its recording: the camera placed for the whole
    recording (every capture then lies in the base frame; a scanner on the arm
    is placed where it was at the verification pose) and each pair's residual,
    robot centre to scanner centre (the centre corrected by the range bias where
    the circle lies on metal, as the solve used it). ``T_ref_cam`` is the
    scanner in the frame it is fixed in, ``T_base_ref`` that frame at each
    pair (the identity on the base) and ``T_base_ref_v`` at the verification pose."""
    rec.log_camera_pose(T_base_ref_v @ T_ref_cam, static=True)
    P_cam = correct_range_bias(found.P_cam, bias) if (bias and circle_on_metal) else found.P_cam
    left_out = {str(p["id"]): bool(p["outlier"] or not p["used"]) for p in quality.get("pairs", [])}
    P_robot = np.array([se3.apply(T, p[None])[0] for T, p in zip(T_base_ref, found.P_base)]).reshape(-1, 3)
    P_scanner = np.array([se3.apply(T @ T_ref_cam, p[None])[0] for T, p in zip(T_base_ref, P_cam)]).reshape(-1, 3)
    rec.log_residuals(list(found.ids), P_robot, P_scanner, [left_out.get(i, False) for i in found.ids])


# -- move ----------------------------------------------------------------------------


async def run_move(ctx: JobContext, devices: CellDevices) -> Mapping[str, Any]:
    job = ctx.job
    if not isinstance(job, MoveJob):
        raise JobError("$.kind", "not a move job")
    target = np.asarray(job.target, dtype=np.float64)
    if job.space == "joint":
        ctx.progress("move", 0.0, f"joint move to {np.round(target, 4).tolist()} rad")
        state = await devices.move_joints(target, speed_scale=job.speed_scale)
        err = np.degrees(np.abs(np.asarray(state.q) - target))
        return {
            "q": np.asarray(state.q).tolist(),
            "joint_error_deg": err.tolist(),
            "tcp_pose": se3.to_ur_pose(state.T_base_tcp).tolist(),
        }
    T = se3.from_ur_pose(target)
    ctx.progress("move", 0.0, f"moving to {np.round(target, 4).tolist()}")
    state = await devices.move_to(T, speed_scale=job.speed_scale)
    dt, dr = se3.error(state.T_base_tcp, T)
    return {"tcp_pose": se3.to_ur_pose(state.T_base_tcp).tolist(), "error_mm": dt * 1e3, "error_deg": math.degrees(dr)}


# -- health ----------------------------------------------------------------------------


async def run_health(ctx: JobContext, devices: CellDevices) -> Mapping[str, Any]:
    job = ctx.job
    if not isinstance(job, HealthJob):
        raise JobError("$.kind", "not a health job")
    out: dict[str, Any] = {}
    problems: list[str] = []
    if job.check in ("all", "robot"):
        h = devices.require_motion().health()
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
    if job.check in ("all", "scanner"):
        try:
            cloud = await devices.capture()
            n = int(np.count_nonzero(np.all(np.isfinite(cloud.points), axis=-1)))
            out["scanner"] = {"ok": n > 0, "valid_points": n, "shape": list(cloud.points.shape[:2])}
            if n == 0:
                problems.append("the scanner returned no points")
        except CelldError as exc:
            out["scanner"] = {"ok": False, "error": str(exc)}
            problems.append(f"scanner: {exc}")
    if job.check in ("all", "tactile"):
        sample = devices.tactile_sample()
        if devices.tactile is None:
            out["tactile"] = {"ok": False, "error": "no tactile sensor configured"}
        else:
            running = devices.tactile.running()
            counters = devices.tactile.read_counters()
            tared = bool(counters is not None and counters["tared"])
            refused = bool(counters is not None and counters["tare_refused"])
            offset = float(counters["tare_offset"]) if counters is not None else math.nan
            out["tactile"] = {
                "ok": running and tared and sample is not None and sample.valid,
                "running": running,
                "valid": bool(sample and sample.valid),
                "tared": tared,
                "tare_offset_mm": offset * 1e3,
                "error": devices.tactile_error,
            }
            if not running:
                problems.append(f"the tactile process is not running: {devices.tactile_error or 'it ended'}")
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
