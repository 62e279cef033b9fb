"""The daemon's move planning: the cell, the workspace box, the TCP's Cartesian limits and the joints' speed limit."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld import se3
from celld.config import load
from celld.daemon.planning import MotionPlanner, joint_move_scale
from celld.errors import PathRefused
from celld.robot import kinematics as kin

ROOT = Path(__file__).resolve().parents[2]
CONFIG = load(ROOT / "configs" / "sim-cell.toml")
HOME = np.array(CONFIG.robot.home_q)


@pytest.fixture(scope="module")
def planner() -> MotionPlanner:
    return MotionPlanner(CONFIG)


def _tcp_peaks(planner: MotionPlanner, q0: np.ndarray, q1: np.ndarray, scale: float) -> tuple[float, float]:
    """The TCP's largest linear and angular speed along a synchronised joint move at ``scale``, sampled finely.

    The path parameter's speed is at most ``scale * v_joint / max|dq|`` (reached
    in the cruise, or not at all on a short move): the bound is tight on the
    cruise, so this samples the TCP speed along the line at that path speed.
    """
    s = np.linspace(0.0, 1.0, 2001)
    T = np.array([kin.forward(q0 + si * (q1 - q0), planner.arm.dh, planner.T_flange_tcp) for si in s])
    sd = scale * CONFIG.motion.max_joint_speed / float(np.abs(q1 - q0).max())
    lin = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / np.diff(s) * sd
    R = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    ang = np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)) / np.diff(s) * sd
    return float(lin.max()), float(ang.max())


def test_a_large_joint_move_is_slowed_so_the_tcp_keeps_its_cartesian_limits(planner: MotionPlanner) -> None:
    # Half a turn of the base with the arm stretched out: at full joint speed
    # the TCP would sweep far faster than 0.25 m/s.
    q1 = HOME + np.array([-0.9, 0.1, -0.2, 0.1, 0.0, 0.3])
    plan = planner.plan_joint_move(HOME, q1)
    lin_full, _ = _tcp_peaks(planner, HOME, q1, 1.0)
    assert lin_full > 2 * CONFIG.motion.max_linear_speed
    assert plan.speed_scale < 0.5
    lin, ang = _tcp_peaks(planner, HOME, q1, plan.speed_scale)
    assert lin <= CONFIG.motion.max_linear_speed * 1.01 and ang <= CONFIG.motion.max_angular_speed * 1.01
    # Not slowed more than the bound needs (the speed or the acceleration bound decides).
    assert lin > 0.3 * CONFIG.motion.max_linear_speed
    assert plan.tcp_speed >= lin * 0.99
    np.testing.assert_allclose(plan.T_base_tcp_goal, kin.forward(q1, planner.arm.dh, planner.T_flange_tcp))


def test_a_wrist_turn_keeps_the_asked_scale_when_the_tcp_stays_slow(planner: MotionPlanner) -> None:
    # Only the last joint turns: the flange turns in place.
    q1 = HOME + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.3])
    k, v, w = joint_move_scale(np.array([HOME, q1]), np.array([0.0, 1.0]), planner.arm.dh, np.eye(4), CONFIG.motion)
    assert k == pytest.approx(1.0, rel=1e-6) and v < 1e-9 and w == pytest.approx(CONFIG.motion.max_joint_speed, rel=1e-6)
    assert planner.plan_joint_move(HOME, q1, speed_scale=0.5).speed_scale <= 0.5


def test_a_joint_move_to_where_the_arm_stands_keeps_the_asked_scale(planner: MotionPlanner) -> None:
    # The arm parked at a home position it already holds (to rounding): no move, not a move slowed to nothing.
    for nudge in (0.0, 1e-12, 1e-9, 1e-6):
        plan = planner.plan_joint_move(HOME, HOME + nudge, speed_scale=0.5)
        assert plan.speed_scale == 0.5, (nudge, plan.speed_scale)
    # A short real move gets a bound it keeps, not one that grows without end as the move shrinks.
    for span in (0.002, 0.05):
        q1 = HOME + np.array([0.0, span, -span, span, 0.0, 0.0])
        plan = planner.plan_joint_move(HOME, q1)
        assert 0.05 < plan.speed_scale < 1.0, (span, plan.speed_scale)
        lin, ang = _tcp_peaks(planner, HOME, q1, plan.speed_scale)
        assert lin <= CONFIG.motion.max_linear_speed * 1.01 and ang <= CONFIG.motion.max_angular_speed * 1.01


def _joint_peaks(planner: MotionPlanner, T0: np.ndarray, T1: np.ndarray, limits, scale: float) -> np.ndarray:
    """Each joint's largest speed (6,) along the straight TCP move from ``T0`` to ``T1`` at ``scale`` of ``limits``,
    its line sampled finely (position straight, rotation vector about the base frame growing linearly)."""
    s = np.linspace(0.0, 1.0, 4001)
    dphi = Rotation.from_matrix(T1[:3, :3] @ T0[:3, :3].T).as_rotvec()
    T_tcp_flange = se3.invert(planner.T_flange_tcp)
    q, Q = HOME.copy(), []
    for si in s:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(si * dphi).as_matrix() @ T0[:3, :3]
        T[:3, 3] = T0[:3, 3] + si * (T1[:3, 3] - T0[:3, 3])
        q = kin.inverse(T @ T_tcp_flange, q, planner.arm.dh)
        assert q is not None
        Q.append(q)
    dp, dang = se3.error(T1, T0)
    sd = scale * min(limits.max_linear_speed / dp, limits.max_angular_speed / dang)
    return np.abs(np.diff(np.array(Q), axis=0)).max(axis=0) / (s[1] - s[0]) * sd


def test_a_cartesian_move_that_would_turn_a_joint_too_fast_is_slowed_to_the_joint_limit() -> None:
    # At a UR10e's production speeds (0.75 m/s, 2 rad/s about the TCP) a straight move that turns the tool
    # spun wrist 1 at 3.2 rad/s on the simulated controller, beyond its safety limit: a protective stop.
    fast = dataclasses.replace(CONFIG.motion, max_linear_speed=0.75, max_angular_speed=2.0, max_joint_speed=2.0)
    planner = MotionPlanner(dataclasses.replace(CONFIG, motion=fast))
    T0 = kin.forward(HOME, planner.arm.dh, planner.T_flange_tcp)
    T1 = T0.copy()
    T1[:3, 3] += [-0.051, 0.087, -0.059]
    T1[:3, :3] = Rotation.from_rotvec([-0.074, -0.586, -0.155]).as_matrix() @ T0[:3, :3]
    plan = planner.plan_move(HOME, T1)
    full = _joint_peaks(planner, T0, T1, fast, 1.0)
    assert full.max() > 1.2 * fast.max_joint_speed  # unslowed, a joint would be past its limit
    assert plan.speed_scale < 0.85
    slowed = _joint_peaks(planner, T0, T1, fast, plan.speed_scale)
    # Every joint within the limit, and the move not slowed more than that needs.
    assert slowed.max() <= fast.max_joint_speed * 1.01 and slowed.max() >= fast.max_joint_speed * 0.97, slowed
    assert plan.joint_speed == pytest.approx(slowed.max(), rel=0.02)
    # A short move that turns no joint near its limit keeps the scale it was asked for.
    T2 = T0.copy()
    T2[:3, 3] += [0.02, 0.0, 0.0]
    assert planner.plan_move(HOME, T2, speed_scale=0.5).speed_scale == 0.5
    assert planner.plan_move(HOME, T0).speed_scale == 1.0  # where it stands


def test_joint_moves_out_of_the_box_into_the_table_or_past_a_joint_limit_are_refused(planner: MotionPlanner) -> None:
    with pytest.raises(PathRefused, match="table"):
        planner.plan_joint_move(HOME, np.array([2.9, -0.3, 2.2, -2.4, 1.5, -1.1]))
    narrow = dataclasses.replace(CONFIG, robot=dataclasses.replace(CONFIG.robot, workspace_max=(1.0, 1.0, 0.5)))
    up = HOME + np.array([0.0, -0.2, -0.2, 0.0, 0.0, 0.0])
    assert kin.forward(up, planner.arm.dh, planner.T_flange_tcp)[2, 3] > 0.5
    with pytest.raises(PathRefused, match=r"leaves the workspace box .* at \d+% of the move"):
        MotionPlanner(narrow).plan_joint_move(HOME, up)
    past = HOME.copy()
    past[0] = 7.0
    with pytest.raises(PathRefused, match="joint limits"):
        planner.plan_joint_move(HOME, past)


def test_a_second_robot_where_it_waits_is_an_obstacle_of_the_first() -> None:
    from celld import se3
    from celld.calib.poses import calibration_poses
    from celld.daemon.arm import robot2_config
    from celld.daemon.planning import ARM_CLEARANCE, arm_obstacles

    cfg = load(ROOT / "configs" / "sim-cell-two-robots.toml")
    assert cfg.robot2 is not None
    one, two = MotionPlanner(cfg), MotionPlanner(robot2_config(cfg))
    T_b1b2 = se3.from_ur_pose(cfg.robot2.base_pose)
    home1, home2 = np.asarray(cfg.robot.home_q), np.asarray(cfg.robot2.robot.home_q)

    # Robot 2's capsules, named for it, in robot 1's base frame, swollen by the clearance.
    waiting = arm_obstacles(two.bare, home2, T_b1b2, "robot2")
    names, ends, radii = two.bare.segments(home2)
    assert [o.name for o in waiting] == [f"robot2-{n}" for n in names]
    for obj, (p0, p1), r in zip(waiting, ends, radii, strict=True):
        on_axis = se3.apply(T_b1b2, np.array([p0, (p0 + p1) / 2, p1]))
        np.testing.assert_allclose(obj.signed_distance(on_axis), -(r + ARM_CLEARANCE), atol=1e-9)

    # Objects given again replace those given before (a job's block inside another's), never pile up.
    again = one.with_objects(waiting).with_objects(waiting)
    assert len(again.bare.cell.objects) == len(one.bare.cell.objects) + len(waiting)

    # The shipped cell's homes are clear: robot 1's calibration plan loses no pose to robot 2 at its home.
    T_v = se3.from_ur_pose(cfg.calibration.verification_pose)
    candidates = calibration_poses(T_v, cfg.calibration.pose_box, 12, cfg.calibration.max_tilt, seed=1)
    plan = one.with_objects(waiting).plan_calibration(home1, candidates, 12)
    assert len(plan.poses) == 12 and not [r for r in plan.refused if "robot2-" in r.message], plan.refused

    # Robot 2 at its verification pose, where the robots meet (robot 1's verification flange goes to the
    # same point): robot 1's move there, accepted with robot 2 at home, is refused naming robot 2's part.
    q2 = two.check_move(home2, se3.from_ur_pose(cfg.robot2.verification_pose), tool=False).q_end
    one.with_objects(waiting).check_move(home1, T_v, tool=False)
    with pytest.raises(PathRefused, match="robot2-"):
        one.with_objects(arm_obstacles(two.bare, q2, T_b1b2, "robot2")).check_move(home1, T_v, tool=False)
