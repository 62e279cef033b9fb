"""A calibrate job with ``robot2``: the scanner calibrated to both robots of the cell, and robot 2's base in robot 1's.

The paper's co-manipulation (Eq. 5) has robot 1 hold the camera and robot 2
show the mark; Eq. 6 splits it into an eye-in-hand problem (a), an
eye-on-base problem (b) and a composition (c). This cell's scanner is fixed
above the table and sees either robot's flange, so (a) is not needed: each
robot is an eye-on-base problem of its own (Eq. 9-12, Algorithm 1, the ICP
metric and the quality gate, exactly as a calibrate job), and (c) becomes
``T_base1_base2 = T_base1_cam T_base2_cam^-1``
(:func:`celld.calib.comanip.robots_through_camera`).

The job, one robot at a time:

1. robot 2 to its ``home_q`` (a checked joint move): out of the scanner's view;
2. robot 1's calibration, as a calibrate job without ``robot2`` (recorded,
   its dataset in ``dataset/``);
3. robot 1 to its ``home_q``;
4. robot 2's calibration from its ``[robot2]`` verification pose with its
   flange, its moves checked against the cell model seen from its base (its
   dataset in ``dataset-robot2/``; the job's recording gets its clouds and
   circles in the camera's frame, named ``robot2-*``);
5. robot 2 back to its ``home_q``;
6. ``T_base1_base2`` with its 1-sigma at robot 2's verification position
   (where the two robots work together) and its distance from the drawn
   ``robot2.base_pose``; the recording draws robot 2's base there.

Every move of either robot, and each robot's plan, is checked against the
other robot's arm where it waits (its capsules at its joints, placed by the
drawn ``robot2.base_pose`` and swollen by
:data:`~celld.daemon.planning.ARM_CLEARANCE`); a dry run plans each robot
with the other at its ``home_q``.

The calibration it leaves is robot 1's (``T_base_cam``, made current by an
accept as any calibrate job's) with a ``robot2`` entry: ``T_base2_cam``,
``T_base1_base2`` and robot 2's quality report (:data:`ROBOT2_ENTRY_SCHEMA`);
accept refuses it when either verdict failed, unless forced. The job's result
is robot 1's with robot 2's calibration beside it (``robot2``:
:data:`ROBOT2_OUTPUT_SCHEMA`), or on a dry run robot 2's plan
(``robot2_plan``). A fault at any step stops both arms
(jerk-limited: the job manager's stop reaches every robot of the cell).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from celld import se3
from celld.bus.requests import CalibrateJob
from celld.calib.comanip import point_std, robots_through_camera
from celld.calib.quality import QUALITY_SCHEMA
from celld.calib.solve import STORED
from celld.config import Config
from celld.daemon.arm import Arm
from celld.daemon.calibrate import OUTPUT_SCHEMA, ArmCalibration, calibrate_arm, prune_calibrations
from celld.daemon.devices import CellDevices
from celld.daemon.jobs import JobContext
from celld.errors import JobError
from celld.log import get_logger
from celld.schemadoc import enum, integer, matrix4, number, obj, string, vector

log = get_logger(__name__)


async def _park(ctx: JobContext, arm: Arm, who: str) -> None:
    """A checked, jerk-limited joint move of ``arm`` to its ``home_q``, out of the scanner's view."""
    ctx.progress("park", None, f"{who} to its home position")
    await arm.move_joints(np.asarray(arm.config.robot.home_q, dtype=np.float64), tool=False)


async def run_calibrate_two(ctx: JobContext, config: Config, devices: CellDevices, job: CalibrateJob) -> Mapping[str, Any]:
    """The calibrate job with ``robot2`` (module docstring)."""
    r2 = config.robot2
    arm2 = devices.robot2
    if r2 is None or arm2 is None:
        raise JobError("$.robot2", "this cell has no second robot ([robot2] in its config)")
    if job.poses:
        raise JobError("$.poses", "a job with robot2 generates both robots' poses: give n_poses, not poses")
    job2 = replace(job, verification_pose=None)  # robot 2's comes from [robot2]
    # Each robot's moves are checked against the other's arm where it waits, placed by the drawn base.
    home1, home2 = (np.asarray(c.robot.home_q, dtype=np.float64) for c in (config, arm2.config))
    if job.dry_run:  # each robot planned with the other where the job parks it
        with devices.robot.avoiding(devices.robot2_obstacles(home2)):
            one = await calibrate_arm(ctx, config, devices.robot, devices.scanner.capture, job)
        with arm2.avoiding(devices.robot1_obstacles(home1)):
            two = await calibrate_arm(ctx, arm2.config, arm2, devices.scanner.capture, job2, robot=2)
        return {**one.output, "robot2_plan": two.output["plan"]}

    with arm2.avoiding(devices.robot1_obstacles(await devices.robot.current_q())):
        await _park(ctx, arm2, "robot 2")
    with devices.robot.avoiding(devices.robot2_obstacles(await arm2.current_q())):
        one = await calibrate_arm(ctx, config, devices.robot, devices.scanner.capture, job)
        await _park(ctx, devices.robot, "robot 1")
    with arm2.avoiding(devices.robot1_obstacles(await devices.robot.current_q())):
        two = await calibrate_arm(ctx, arm2.config, arm2, devices.scanner.capture, job2, dataset_name="dataset-robot2", robot=2)
        await _park(ctx, arm2, "robot 2")
    entry = robot2_entry(one, two, r2.base_pose, r2.verification_pose)
    if ctx.recording is not None:
        ctx.recording.log_robot2_base(np.asarray(entry["T_base1_base2"]))
    await prune_calibrations(ctx, config)
    out = dict(one.output)
    out["calibration"] = {**out["calibration"], "robot2": entry}
    out["robot2"] = {key: two.output[key] for key in _ROBOT2_KEYS}
    log.info(
        "robots_calibrated",
        job=ctx.job_id,
        from_drawing_mm=round(entry["from_drawing_mm"], 3),
        translation_std_mm=[round(v, 3) for v in entry["translation_std_mm"]],
        verdict=entry["quality"].get("verdict"),
    )
    return out


# The JSON shape of robot2_entry: the calibration's robot2 entry.
ROBOT2_ENTRY_SCHEMA = obj(
    "The cell's second robot calibrated through the same scanner (a calibrate job with robot2): Eq. 6b for each "
    "robot with the camera fixed, and Eq. 6c, T_base1_base2 = T_base1_cam T_base2_cam^-1.",
    {
        "T_base2_cam": matrix4("The scanner in robot 2's base frame."),
        "T_base1_base2": matrix4("Robot 2's base in robot 1's."),
        "quality": QUALITY_SCHEMA,
        "translation_std_mm": vector(
            "1-sigma of robot 2's verification position placed in base 1 by T_base1_base2 (where the robots meet), along "
            "robot 1's base axes, mm: the scanner's noise through both calibrations, not the arms' absolute error.",
            3,
        ),
        "rotation_std_deg": vector("Its rotation 1-sigma about robot 1's base axes, deg.", 3),
        "from_drawing_mm": number("How far the calibrated base 2 lies from robot2.base_pose, mm."),
        "from_drawing_deg": number("The angle between them, deg."),
        "cost_mm": number("Final cost of robot 2's Algorithm 1, mm.", null=True),
        "pairs": integer("Robot 2's pairs in the final pool.", lo=0),
        "dataset": string("Path of robot 2's saved dataset."),
        "stored": enum(STORED, "T_base2_cam is the estimate or Eq. 21's."),
    },
    (
        "T_base2_cam",
        "T_base1_base2",
        "quality",
        "translation_std_mm",
        "rotation_std_deg",
        "from_drawing_mm",
        "from_drawing_deg",
        "cost_mm",
        "pairs",
        "dataset",
        "stored",
    ),
)
# The keys of robot 2's own calibration the job's result keeps (robot2), and their JSON shape.
_ROBOT2_KEYS = ("report", "early_stop", "poses_captured", "poses_planned", "dataset")
ROBOT2_OUTPUT_SCHEMA = obj(
    "Robot 2's calibration as the job made it: its solve's report, early stop, poses and dataset.",
    {key: OUTPUT_SCHEMA["properties"][key] for key in _ROBOT2_KEYS},
    _ROBOT2_KEYS,
)


def robot2_entry(
    one: ArmCalibration, two: ArmCalibration, base_pose: tuple[float, ...], verification_pose: tuple[float, ...]
) -> dict[str, Any]:
    """The calibration's ``robot2`` entry from both robots' solves (Eq. 6c with the camera fixed; :data:`ROBOT2_ENTRY_SCHEMA`)."""
    if one.result is None or two.result is None:
        raise JobError("$.dry_run", "a dry run has no calibration to compose")
    r1, r2 = one.result, two.result
    T_b1b2, unc = robots_through_camera(r1.T_base_cam_stored, r1.uncertainty, r2.T_base_cam_stored, r2.uncertainty)
    # The 1-sigma where the robots meet: robot 2's verification position, in base 1.
    std = point_std(T_b1b2, unc, np.asarray(verification_pose[:3]))
    off, angle = se3.error(T_b1b2, se3.from_ur_pose(base_pose))
    cal2 = two.output["calibration"]
    return {
        "T_base2_cam": cal2["T_base_cam"],
        "T_base1_base2": T_b1b2.tolist(),
        "quality": cal2["quality"],
        "translation_std_mm": (std * 1e3).tolist(),
        "rotation_std_deg": np.degrees(unc.rotation_std).tolist(),
        "from_drawing_mm": off * 1e3,
        "from_drawing_deg": math.degrees(angle),
        "cost_mm": cal2["cost_mm"],
        "pairs": cal2["pairs"],
        "dataset": cal2["dataset"],
        "stored": cal2["stored"],
    }
