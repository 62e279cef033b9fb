"""The current calibration held against the cell before it welds (:mod:`celld.calib.verify`): the verify job and gate.

A calibration that no longer matches the cell (the scanner knocked, the table
moved, a calibration file from another cell) reads as valid. A verification
(:func:`verify_calibration`) shows the flange to the scanner at
``calibration.verify_poses`` poses, with the tool on: the calibration's
verification pose, captured twice, then poses drawn around it in the
calibration's pose box, facing the scanner as there (checked against the
cell before the robot moves; as many spares, for views where the detector
does not find the flange), and compares what the scanner sees with where the
calibration puts it. Poses apart show a turn of the scanner as well as a
shift: its error differs from pose to pose. The worst pose decides, so the
arm stops looking once two poses are seen and one is beyond the bound.

When it runs:

- ``celld submit verify`` (a ``verify`` job): now;
- before a weld (:func:`ensure_verified`), when the current calibration was
  never verified (a new one accepted, the file changed), not since the daemon
  started, or longer ago than ``calibration.verify_interval_h`` (8 h, a
  shift, by default: parts do not pay for it).

Its record, ``<state_dir>/verification.json``, is sealed (:mod:`celld.sealed`)
and names the calibration it held (by its checksum). While the current
calibration's last verification failed, welds are refused with its figure
until a new calibration is accepted; a verify job that passes clears it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any

import numpy as np

from celld import se3, sealed
from celld.bus.requests import VerifyJob
from celld.calib.detect import detect_flange
from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
from celld.calib.flange import preset
from celld.calib.poses import calibration_poses
from celld.calib.rangebias import correct_range_bias
from celld.calib.verify import SCHEMA, Sighting, Verification, calibration_bound, verify_placement
from celld.config import Config
from celld.daemon.devices import CellDevices
from celld.daemon.jobs import JobContext
from celld.daemon.store import (
    VERIFICATION,
    VERIFICATION_KIND,
    failed_verification,
    for_controller,
    last_verification,
    placed,
    required_calibration,
)
from celld.errors import CalibrationError, CelldError, JobError
from celld.journal import utc_now
from celld.log import get_logger
from celld.schemadoc import string, with_properties

log = get_logger(__name__)

# Seed of the poses drawn around the verification pose: the same poses each time.
POSE_SEED = 7919
# The verify job's result: the verification, and the calibration it held.
RESULT_SCHEMA = with_properties(
    SCHEMA,
    {"calibration": string("The calibrate job whose calibration was verified."), "at": string("When, UTC ISO 8601.")},
    ("calibration", "at"),
)


def due(record: Mapping[str, Any] | None, calibration: Mapping[str, Any], started: str, interval_s: float, now: datetime) -> str:
    """Why the current calibration must be verified before a weld, "" when its last verification stands.

    Raises
    ------
    JobError
        Its last verification failed: welds are refused with its figure until a new calibration is accepted.
    """
    if record is None or record.get("calibration_sha256") != calibration.get(sealed.CHECKSUM_KEY):
        return "the current calibration has not been verified"
    failed = failed_verification(record, calibration)
    if failed:
        raise JobError("$", failed)
    at = str(record.get("at", ""))
    if at < started:
        return "not verified since the daemon started"
    try:
        age = (now - datetime.fromisoformat(at.replace("Z", "+00:00"))).total_seconds()
    except ValueError:
        return "its last verification's time is unreadable"
    if interval_s > 0 and age > interval_s:
        return f"last verified {age / 3600:.1f} h ago (calibration.verify_interval_h = {interval_s / 3600:g})"
    return ""


async def ensure_verified(ctx: JobContext, config: Config, devices: CellDevices, started: str) -> None:
    """Verify the current calibration first when :func:`due` says so; refused when it fails (or failed before)."""
    calibration = required_calibration(ctx.state_dir)
    why = due(last_verification(ctx.state_dir), calibration, started, config.calibration.verify_interval, datetime.now(UTC))
    if not why:
        return
    ctx.progress("verify", 0.0, f"verifying the calibration first: {why}")
    await verify_calibration(ctx, config, devices, calibration)


async def run_verify(ctx: JobContext, config: Config, devices: CellDevices) -> Mapping[str, Any]:
    """The verify job: the current calibration verified now; failed (with the figure) when it does not hold."""
    if not isinstance(ctx.job, VerifyJob):
        raise JobError("$.kind", "not a verify job")
    calibration = required_calibration(ctx.state_dir)
    done = await verify_calibration(ctx, config, devices, calibration)
    return {**done.as_dict(), "calibration": str(calibration.get("job", "")), "at": utc_now()}


async def verify_calibration(ctx: JobContext, config: Config, devices: CellDevices, calibration: Mapping[str, Any]) -> Verification:
    """Show the flange at the verification poses, compare, and keep the record (module docstring); the
    verification when it passed.

    Raises
    ------
    JobError
        It failed (the record kept says so too), or the calibration cannot be verified here.
    """
    cal = config.calibration
    if any(abs(v) > 1e-12 for v in config.robot.tcp_offset):
        raise JobError("$", "a verification reads the flange pose: set robot.tcp_offset to zero")
    placement, bias = placed(calibration, config.scanner.mount)
    for_controller(placement, devices.robot.require_kinematics)
    try:
        own_bound = calibration_bound(calibration)
    except CalibrationError as exc:
        raise JobError("$", str(exc)) from exc
    arm = devices.robot
    motion = arm.require_motion()
    flange = preset(cal.flange)
    dparams = PARAMS_BY_SCANNER.get(config.scanner.model, DetectParams())

    # The verification pose, then poses drawn around it: checked with the tool on before the robot moves.
    T_v = se3.from_ur_pose(cal.verification_pose)
    q_now = await arm.current_q()  # first: it waits for the controller's kinematics
    planner = arm.planner
    to_v = await asyncio.to_thread(planner.check_move, q_now, T_v, True)
    n = cal.verify_poses - 1

    # Shifted in the pose box, facing the scanner as at the verification pose (with the tool on, a tilted flange
    # is partly hidden): poses apart show a turn of the scanner as errors that differ from pose to pose.
    def more(count: int, rnd: int) -> np.ndarray:  # the generator draws four at least
        return calibration_poses(T_v, cal.pose_box, max(count, 4), 0.0, seed=POSE_SEED + 1000 * (rnd + 1))

    # As many spares: a view where the detector does not find the flange is left out, as a calibration leaves it.
    candidates = calibration_poses(T_v, cal.pose_box, max(2 * n, 4), 0.0, seed=POSE_SEED)
    plan = await asyncio.to_thread(planner.plan_calibration, to_v.q_end, candidates, 2 * n, more, True)
    targets = [T_v, *plan.poses]

    async def look(T_reported: np.ndarray, q: np.ndarray, name: str) -> tuple[Sighting, np.ndarray | None]:
        T_base_cam = placement.T_base_cam(q)
        # Where the calibration puts the flange: the controller's report, through the arm's calibration if any.
        T_bf = placement.modelled(T_reported, q)
        predicted = se3.invert(T_base_cam) @ np.append(T_bf[:3, 3], 1.0)
        cloud = await devices.scanner.capture()
        points = correct_range_bias(cloud.points, bias) if bias else np.asarray(cloud.points)
        try:
            det = await asyncio.to_thread(detect_flange, points, flange, dparams, predicted[:3])
        except CelldError as near:
            try:  # far from where the calibration puts it: looked for in the whole cloud, for the figure
                det = await asyncio.to_thread(detect_flange, points, flange, dparams)
            except CelldError:
                return Sighting(name, T_bf, T_base_cam, None, None, str(near)), None
        return Sighting(name, T_bf, T_base_cam, np.asarray(det.center), np.asarray(det.normal)), np.asarray(det.center)

    sightings: list[Sighting] = []
    repeat: np.ndarray | None = None
    for i, T in enumerate(targets):
        ctx.progress("verify", i / len(targets), f"verification pose {i + 1} (of {cal.verify_poses}, and {n} spares)")
        await arm.move_to(T, tool=True)
        await asyncio.sleep(cal.settle)
        state = motion.state()
        if state is None:
            raise JobError("$", "no robot state after a verification move")
        T_bf, q = state.T_base_tcp, np.asarray(state.q, dtype=np.float64)
        sighting, _ = await look(T_bf, q, f"v{i}")
        sightings.append(sighting)
        if i == 0:
            _, repeat = await look(T_bf, q, "v0-again")  # the verification's own repeatability
        seen = sum(s.center_cam is not None for s in sightings)
        if seen >= cal.verify_poses:
            break
        # Two poses seen and one beyond the bound: the verdict (the worst pose's) is failed whatever comes next.
        if seen >= 2 and not verify_placement(sightings, repeat, own_bound, cal.verify_bound).passed:
            break
    done = verify_placement(sightings, repeat, own_bound, cal.verify_bound)
    record = {
        **done.as_dict(),
        "calibration_sha256": calibration.get(sealed.CHECKSUM_KEY),
        "calibration_job": calibration.get("job"),
        "at": utc_now(),
    }
    sealed.write_sealed(ctx.state_dir / VERIFICATION, record, VERIFICATION_KIND, ctx.job_id)
    (log.info if done.passed else log.error)(
        "calibration verified" if done.passed else "calibration failed its verification",
        calibration=calibration.get("job"),
        error_mm=None if not np.isfinite(done.error) else round(done.error * 1e3, 3),
        bound_mm=round(done.bound * 1e3, 3),
        reason=done.reason,
    )
    if ctx.recording is not None:
        ctx.recording.event_later(
            f"calibration {'verified' if done.passed else 'failed its verification'}: "
            + (done.reason or f"{done.error * 1e3:.2f} mm within {done.bound * 1e3:.2f} mm"),
            "INFO" if done.passed else "WARN",
        )
    if not done.passed:
        raise JobError("$", f"the current calibration failed its verification: {done.reason}; calibrate again and accept the result")
    return done
