"""The calibrate job: the robot shows its flange to the scanner, pose after pose, and the session decides.

The runner is the shell around a :class:`~celld.calib.session.CalibrationSession`
(which holds the pairs, Algorithm 1 online with its range-bias restart, the
early stop's quality gate and the final solve): it plans the poses and checks
them against the cell, moves, settles, captures, hands each capture to the
session, publishes what the session answered, records and stores.

1. **plan**: the verification pose, then ``n_poses`` generated poses in the
   calibration box (refused ones replaced) or the job's given poses (a refused
   one refuses the job); a dry run stops here and returns the plan;
2. **verify**: the verification cloud, which scores every estimate (Eq. 13);
3. **pair** (each): move, settle, capture, the flange pose and joints the
   robot reports; the session finds the flange, feeds Algorithm 1 and says
   whether to stop early (only when the pairs so far pass the quality gate);
4. **solve**: the session's result with Algorithm 1's history, the e_icp of
   Eq. 13 and the quality gate's verdict (accept refuses a failed one unless
   forced); with ``compensate`` the calibration stored is Eq. 21's
   compensated estimate, and ``stored`` says so.

The dataset is saved as it is captured, so the session can be solved again
offline (``celld calib solve``); old datasets are then pruned by the config's
retention rules (:mod:`celld.daemon.retention`). With
``calibration.range_bias = "estimate"`` (time-of-flight scanners) the
scanner's range bias on metal is estimated with the transform and stored with
it (``range_bias_mm`` and its 1-sigma): every scan placed with this
calibration is corrected by it. With the scanner on the arm
(``scanner.mount`` = link1-3, eye-on-arm, Eq. 8) each capture's flange pose
is moved into the scanner's link frame by the joints of that capture, and the
same session gives ``T_linkN_cam``; the calibration stores it with the mount
and the DH table (:mod:`celld.calib.mount`). A job with ``robot2`` runs this
for each robot (:mod:`celld.daemon.two_robots`).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from celld import fsutil, se3
from celld.bus.requests import CalibrateJob
from celld.calib.algorithm1 import Algorithm1Result
from celld.calib.dataset import SessionWriter
from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
from celld.calib.flange import preset
from celld.calib.kinematic import ARM_ENTRY_SCHEMA, KINEMATICS_FILE, ArmPairs, arm_entry, kinematics_doc, wide_poses
from celld.calib.mount import MOUNT_ENTRY_PROPERTIES, ScannerMount, in_any_frame, in_frame, mount_entry
from celld.calib.pairs import Detections
from celld.calib.poses import calibration_poses
from celld.calib.quality import QUALITY_SCHEMA
from celld.calib.rangebias import MODES as RANGE_BIAS_MODES
from celld.calib.rangebias import correct_range_bias
from celld.calib.session import CalibrationSession, CaptureStep
from celld.calib.solve import METHODS, REPORT_SCHEMA, STORED, CalibrationResult, SolveParams
from celld.config import Config
from celld.daemon.arm import Arm
from celld.daemon.devices import CellDevices
from celld.daemon.jobs import JobContext
from celld.daemon.planning import REFUSED_SCHEMA, CalibrationPlan, record_arm, record_cell, record_plan, report_plan
from celld.daemon.retention import prune_sessions
from celld.daemon.store import CalibrationStore
from celld.errors import CalibrationError, DamagedStateError, InputError, JobError
from celld.log import get_logger
from celld.recording import layout
from celld.robot import dynamics
from celld.scanner.base import OrganizedCloud
from celld.schemadoc import array, boolean, const, enum, integer, number, obj, one_of, string, vector

if TYPE_CHECKING:
    from celld.recording.job import JobRecording

log = get_logger(__name__)

# Fewest wide poses an arm calibration takes (it fits the scanner's pose and some 20 of the arm's parameters).
ARM_MIN_POSES = 8
# The wide poses' generator seed, beside the job's: apart from the hand-eye poses'.
ARM_SEED = 7919


def calibration_entry(
    job: str,
    mount: ScannerMount,
    result: CalibrationResult,
    report: Mapping[str, Any],
    params: SolveParams,
    dataset: Path,
    a1: Algorithm1Result | None,
) -> dict[str, Any]:
    """The calibration a calibrate job ``job`` offers for accept (CALIBRATION_SCHEMA): ``result`` solved from the
    session saved in ``dataset``, ``report`` its report in the mount's frame, ``a1`` Algorithm 1 as it ran."""
    return {
        "job": job,
        **mount_entry(mount, result.T_base_cam_stored),
        "stored": result.stored,
        "cost_mm": a1.cost * 1e3 if a1 is not None and math.isfinite(a1.cost) else None,
        "pairs": len(result.pair_ids),
        "dataset": str(dataset),
        "method": result.method,
        "quality": report["quality"],
        # The scanner's range bias on metal, to apply with T_base_cam (0 with mode none).
        "range_bias": params.range_bias,
        "range_bias_mm": result.bias * 1e3,
        "range_bias_std_mm": None if result.range_bias is None else report["range_bias"]["std_mm"],
    }


async def run_calibrate(ctx: JobContext, config: Config, devices: CellDevices) -> Mapping[str, Any]:
    """A calibrate job of robot 1 (a job with ``robot2``: :func:`celld.daemon.two_robots.run_calibrate_two`)."""
    job = ctx.job
    if not isinstance(job, CalibrateJob):
        raise JobError("$.kind", "not a calibrate job")
    done = await calibrate_arm(ctx, config, devices.robot, devices.scanner.capture, job)
    await prune_calibrations(ctx, config)
    return done.output


async def prune_calibrations(ctx: JobContext, config: Config) -> None:
    """Old calibration datasets pruned by the config's retention rules, never this job's or the current calibration's."""
    cal = config.calibration
    try:
        current = CalibrationStore(ctx.state_dir).current() or {}
    except DamagedStateError as exc:  # its job is unknown: its dataset may be one to keep
        log.warning("calibration_datasets_not_pruned", reason=str(exc))
        return
    await asyncio.to_thread(prune_sessions, ctx.state_dir / "jobs", cal.keep_sessions, cal.keep_days, (ctx.job_id, current.get("job")))


@dataclass(frozen=True)
class ArmCalibration:
    """One robot's calibration as a job made it, or its dry run's plan (``result`` None).

    :attr:`output` is the job's result for this robot: :data:`OUTPUT_SCHEMA`,
    or :data:`DRY_RUN_SCHEMA` for a dry run.
    """

    plan: dict[str, Any]  # the checked plan, as DRY_RUN_SCHEMA's "plan"
    result: CalibrationResult | None = None  # the solve
    calibration: dict[str, Any] = field(default_factory=dict)  # the candidate an accept stores (calibration_entry)
    report: dict[str, Any] = field(default_factory=dict)  # the solve's report in the scanner mount's frame
    early_stop: bool = False  # Algorithm 1 and the quality gate were satisfied before the last planned pose
    poses_captured: int = 0
    dataset: Path | None = None

    @property
    def output(self) -> dict[str, Any]:
        if self.result is None:
            return {"dry_run": True, "plan": self.plan}
        return {
            "dry_run": False,
            "calibration": self.calibration,
            "report": self.report,
            "early_stop": self.early_stop,
            "poses_captured": self.poses_captured,
            "poses_planned": len(self.plan["poses"]),
            "dataset": str(self.dataset),
        }


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


_POSE = vector("A UR pose [x, y, z, rx, ry, rz], m and rad, base frame.", 6)
# The JSON shape of a dry run's plan (calibrate_arm).
PLAN_SCHEMA = obj(
    "The calibration's plan, checked against the cell: the verification pose, then the poses, with the joints at "
    "each (the verification pose's first), and the candidates left out.",
    {
        "verification_pose": _POSE,
        "poses": array(_POSE, "The calibration poses, in order."),
        "joints": array(vector("Joint positions, rad.", 6), "The joints at the verification pose, then at each pose."),
        "refused": REFUSED_SCHEMA,
    },
    ("verification_pose", "poses", "joints", "refused"),
)
# The JSON shape of a dry run's result.
DRY_RUN_SCHEMA = obj("A dry run: the plan, nothing moved.", {"dry_run": const(True), "plan": PLAN_SCHEMA}, ("dry_run", "plan"))
# The JSON shape of a calibration a job made (its candidate; the store adds when it was accepted).
CALIBRATION_SCHEMA = obj(
    "A calibration of the scanner: T_base_cam, the pose of the camera in the robot base frame; for a scanner on "
    "the arm (mount link1-3, Eq. 8) T_linkN_cam, its pose in that link's frame, with the robot's DH table.",
    {
        "job": string("The calibrate job that made it."),
        **MOUNT_ENTRY_PROPERTIES,
        "stored": enum(STORED, "The transform is the estimate, or the estimate compensated by Eq. 21."),
        "cost_mm": number("Final cost of Algorithm 1, null without one.", null=True),
        "pairs": integer("Pairs the transform rests on.", lo=0),
        "dataset": string("Path of the saved dataset."),
        "method": enum(METHODS, "The estimator that gave the transform."),
        "quality": QUALITY_SCHEMA,
        "range_bias": enum(RANGE_BIAS_MODES, "Whether the scanner's range bias on metal was estimated (calibration.range_bias)."),
        "range_bias_mm": number(
            "The scanner's range bias on bare metal, mm (0 when not estimated): every scan placed with this calibration "
            "has its points moved back along their rays by it."
        ),
        "range_bias_std_mm": number("Its 1-sigma; null when not estimated.", null=True),
        "arm": ARM_ENTRY_SCHEMA,
    },
    ("job", "stored", "cost_mm", "pairs", "dataset", "method", "quality", "range_bias", "range_bias_mm", "range_bias_std_mm"),
)
# The JSON shape of a calibration's result (calibrate_arm's output).
OUTPUT_SCHEMA = obj(
    "A calibration: the calibration it made (a candidate until accepted), the solve's report (in the scanner mount's "
    "frame), whether it stopped early, the poses captured and planned, the dataset.",
    {
        "dry_run": const(False),
        "calibration": CALIBRATION_SCHEMA,
        "report": in_any_frame(REPORT_SCHEMA),
        "early_stop": boolean("Algorithm 1 reached e_required and the quality gate passed before the last pose."),
        "poses_captured": integer(lo=0),
        "poses_planned": integer(lo=0),
        "dataset": string("Path of the saved dataset (clouds and poses)."),
    },
    ("dry_run", "calibration", "report", "early_stop", "poses_captured", "poses_planned", "dataset"),
)
# The JSON shape of a calibrate job's result of robot 1 (a job with robot2 adds to it: celld.daemon.two_robots).
RESULT_SCHEMA = one_of("A calibrate job's result: the calibration, or a dry run's plan.", DRY_RUN_SCHEMA, OUTPUT_SCHEMA)


def solve_params(config: Config, job: CalibrateJob) -> SolveParams:
    """How the job's session is solved: the cell's ``[calibration]``, the job's overrides winning."""
    overrides: dict[str, Any] = {}
    if job.e_required is not None:
        overrides["e_required"] = job.e_required
    if job.k_max is not None:
        overrides["k_max"] = job.k_max
    if job.compensate:
        overrides["compensate"] = True
    return SolveParams.from_config(config.calibration, **overrides)


class _Plan(NamedTuple):
    """A calibration's plan, checked against the cell: the verification pose, then the poses."""

    T_v: np.ndarray  # the verification pose, base frame
    q_v: tuple[float, ...]  # the joints there
    plan: CalibrationPlan

    def as_dict(self) -> dict[str, Any]:
        return {
            "verification_pose": se3.to_ur_pose(self.T_v).tolist(),
            "poses": [se3.to_ur_pose(T).tolist() for T in self.plan.poses],
            "joints": [list(self.q_v), *[list(q) for q in self.plan.q]],
            "refused": self.plan.refused_entries(),
        }


async def _plan(arm: Arm, config: Config, job: CalibrateJob) -> _Plan:
    """The verification pose, then the poses, checked against the cell before the robot moves; generated
    poses that fail are replaced, given ones refuse the job."""
    cal = config.calibration
    T_v = se3.from_ur_pose(job.verification_pose if job.verification_pose is not None else cal.verification_pose)
    q_now = await arm.current_q()  # first: it waits for the controller's kinematics, which the planner takes up
    planner = arm.planner
    to_v = await asyncio.to_thread(planner.check_move, q_now, T_v, False)
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
    return _Plan(T_v, tuple(to_v.q_end), plan)


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
    params = solve_params(config, job)
    planned = await _plan(arm, config, job)
    T_v, poses, planner = planned.T_v, np.array(planned.plan.poses), arm.planner
    report_plan(ctx, planned.plan, who + "calibration")
    # Robot 1's calibration draws the cell, its arm and its solution in the job's recording (base 1's
    # frame); another robot's adds what the scanner saw of it, named for it, in the camera's frame.
    rec = ctx.recording if robot == 1 else None
    seen = ctx.recording
    seen_as = "" if robot == 1 else f"robot{robot}-"
    if job.dry_run:
        await asyncio.to_thread(record_plan, rec, planner.bare, [planned.q_v, *planned.plan.q])
        return ArmCalibration(planned.as_dict())
    dataset = ctx.result_dir() / dataset_name
    # A scanner on the arm: every pair's robot side is the flange in the scanner's link frame (Eq. 8).
    table = arm.require_kinematics().dh if config.scanner.mount != "base" else None
    mount = ScannerMount.of(config.scanner.mount, config.robot.model, table)
    writer = SessionWriter(dataset, flange=cal.flange, scanner=config.scanner.model, mount=mount)
    if arm.kinematics is not None:
        # The table the pairs' poses were reported with, for an arm fit from the dataset (celld calib solve --arm).
        await asyncio.to_thread(fsutil.write_json, dataset / KINEMATICS_FILE, kinematics_doc(arm.kinematics.dh))
    dparams = PARAMS_BY_SCANNER.get(config.scanner.model, DetectParams())
    session = CalibrationSession(flange, params, dparams, planned=len(poses), mount=mount, writer=writer)
    if rec is not None:
        # The cell, and the flange model carried by the TCP (the flange: tcp_offset is zero here) at each pose.
        await asyncio.to_thread(record_cell, rec, planner.bare)
        mesh = await asyncio.to_thread(flange.mesh)
        await asyncio.to_thread(rec.log_mesh, layout.FLANGE, np.asarray(mesh.vertices), np.asarray(mesh.triangles), static=True)

    # Verification pose first: its cloud scores every estimate (Eq. 13).
    progress("verify", 0.0, "verification pose")
    T_v_robot, q_v = await _settled_flange_pose(arm, T_v, cal.settle)
    cloud_v = await capture()
    if seen is not None:
        await asyncio.to_thread(seen.log_cloud_cam, seen_as + "verification", cloud_v.points)
    await asyncio.to_thread(session.verify, T_v_robot, cloud_v.points, q_v)

    q_of: dict[str, np.ndarray] = {}  # each capture's joints, by pair id
    for i, T in enumerate(poses):
        T_bf, q = await _settled_flange_pose(arm, T, cal.settle)
        cloud = await capture()
        step = await asyncio.to_thread(session.capture, T_bf, cloud.points, q)
        q_of[step.pair.id] = q
        message, data = step.progress()
        det = step.pair.detection
        if det is not None:
            if seen is not None:
                await asyncio.to_thread(seen.log_cloud_cam, seen_as + "pair", cloud.points)
                seen.later(seen.log_circle_cam, seen_as + "flange", det.center, det.normal, det.radius, time.monotonic_ns())
            if rec is not None:
                await _record_pair(rec, arm, T_bf, step)
        progress("pair", (i + 1) / len(poses), message, **data)
        if step.stop:
            break
        if step.held:
            progress("pair", (i + 1) / len(poses), f"Algorithm 1 is done but {step.held}: capturing more", pair=step.pair.id, detected=True)

    progress("solve", None, f"solving from {session.n_pairs} pairs")
    result = await asyncio.to_thread(session.finish)
    found = session.detections()
    report = in_frame(result.as_dict(), mount)
    if rec is not None:
        T_base_link = [mount.T_base_link(q_of[pid]) for pid in found.ids]
        await asyncio.to_thread(
            _record_solution,
            rec,
            result.T_base_cam,
            result.bias,
            found,
            report["quality"],
            flange.circle_on_metal,
            T_base_link,
            mount.T_base_link(q_v),
        )
    early = session.stopped_early and session.reached
    calibration = calibration_entry(ctx.job_id, mount, result, report, params, dataset, session.algorithm1())
    n_arm = _arm_poses(config, job, mount, robot)
    if n_arm:
        calibration["arm"] = await _calibrate_kinematics(
            ctx, config, arm, capture, planned.T_v, result.T_base_cam, n_arm, job.seed or 0, dataset
        )
    log.info(
        "calibration_solved",
        job=ctx.job_id,
        robot=robot,
        pairs=len(result.pair_ids),
        cost_mm=calibration["cost_mm"],
        early_stop=early,
        verdict=result.quality.verdict,
        stored=result.stored,
        range_bias_mm=round(result.bias * 1e3, 3),
    )
    return ArmCalibration(planned.as_dict(), result, calibration, report, early, session.n_captures, dataset)


def _arm_poses(config: Config, job: CalibrateJob, mount: ScannerMount, robot: int) -> int:
    """How many wide poses the job's arm calibration takes (0: none); refused where it cannot run."""
    n = job.arm_poses if job.arm_poses is not None else config.calibration.arm_poses
    if not n:
        return 0
    if mount.on_arm:
        raise JobError("$.arm_poses", f"the arm's kinematic calibration needs a fixed scanner, and this one is on {mount.name}")
    if robot != 1 or job.robot2:
        raise JobError("$.arm_poses", "the arm's kinematic calibration is robot 1's: give arm_poses 0 with robot2")
    if n < ARM_MIN_POSES:
        raise JobError("$.arm_poses", f"the arm's kinematic calibration needs at least {ARM_MIN_POSES} wide poses, got {n}")
    return n


async def _calibrate_kinematics(
    ctx: JobContext,
    config: Config,
    arm: Arm,
    capture: Callable[[], Awaitable[OrganizedCloud]],
    T_v: np.ndarray,
    T_base_cam: np.ndarray,
    n: int,
    seed: int,
    dataset: Path,
) -> dict[str, Any]:
    """The arm's kinematic calibration after the hand-eye one (:mod:`celld.calib.kinematic`): ``n`` wide poses
    around the verification pose ``T_v``, checked against the cell (refused ones replaced), each flange
    found near where ``T_base_cam`` puts it; the DH corrections, joint zeros and the shoulder's and elbow's
    sag (the tool's weight as ``[tool]`` gives it) fitted with the scanner's pose. Returns the calibration's
    ``arm`` entry; the flanges found (joints, centres and normals) are saved in the job's directory
    (``arm.json``) to be fitted again offline."""
    cal = config.calibration
    table = arm.require_kinematics().dh  # the corrections are to the controller's own table
    ctx.progress("arm", 0.0, f"the arm's kinematic calibration: {n} wide poses")

    def more(count: int, rnd: int) -> np.ndarray:
        return wide_poses(T_v, count, seed + ARM_SEED + 1000 * (rnd + 1))

    q_start = await arm.current_q()
    plan = await asyncio.to_thread(arm.planner.plan_calibration, q_start, wide_poses(T_v, n, seed + ARM_SEED), n, more)
    pairs = ArmPairs(preset(cal.flange), PARAMS_BY_SCANNER.get(config.scanner.model, DetectParams()), T_base_cam)
    for i, T in enumerate(plan.poses):
        T_bf, q = await _settled_flange_pose(arm, T, cal.settle)
        cloud = await capture()
        found = await asyncio.to_thread(pairs.add, f"w{i:03d}", cloud.points, T_bf[:3, 3], q)
        ctx.progress(
            "arm", (i + 1) / len(plan.poses), f"wide pose {i + 1} of {len(plan.poses)}: flange {'found' if found else 'not found'}"
        )
    # Back to the joints the wide poses began at, by a joint move: they turn the wrist up to half a turn either
    # way, and a straight move from there to the next job's first pose can take wrist 3 past its limit.
    await arm.move_joints(q_start, tool=False)
    ctx.progress("arm", None, f"fitting the arm from {len(pairs.q)} flanges")
    payload = dynamics.Payload(config.tool.mass, config.tool.com_flange)
    try:
        fit = await asyncio.to_thread(pairs.fit, config.robot.model, payload, table, cal.arm_error_prior)
    except InputError as exc:
        raise CalibrationError(f"the arm's kinematic calibration: {exc}") from exc
    session = {"frame": "camera", "units": "m", "q": np.asarray(pairs.q).tolist(), "p_cam": np.asarray(pairs.p_cam).tolist()}
    session |= {"n_cam": np.asarray(pairs.n_cam).tolist(), "skipped": pairs.skipped, "T_base_cam_hand_eye": T_base_cam.tolist()}
    await asyncio.to_thread(fsutil.write_json, ctx.result_dir() / "arm.json", session)
    entry = arm_entry(fit, config.robot.model, len(pairs.q))
    log.info(
        "arm_calibrated",
        job=ctx.job_id,
        pairs=len(pairs.q),
        rank=fit.rank,
        condition=round(fit.condition, 1),
        residual_rms_mm=round(fit.rms * 1e3, 4),
        residual_rms_before_mm=round(entry["residual_rms_before_mm"], 4),
    )
    return entry


async def _record_pair(rec: JobRecording, arm: Arm, T_base_flange: np.ndarray, step: CaptureStep) -> None:
    """A detected pair in robot 1's recording: the flange pose, the arm where it stands and Algorithm 1's cost."""
    rec.later(rec.log_tcp, T_base_flange, time.monotonic_ns())
    here = arm.require_motion().state()
    if here is not None:
        await asyncio.to_thread(record_arm, rec, arm.planner.bare, here.q)
    if step.algorithm1 is not None:
        rec.later(rec.log_e_icp, step.algorithm1.k, step.algorithm1.cost_optimal, time.monotonic_ns())


def _record_solution(
    rec: JobRecording,
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
