"""Collision and reachability checks in the simulated cell (configs/cell-models/sim-cell.toml) with a UR10e."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from celld import se3
from celld.calib.poses import calibration_poses
from celld.config import TableReader, load
from celld.config.cell_model import read_cell_model
from celld.errors import InputError
from celld.robot import kinematics as kin
from celld.robot.cellmodel import Box, CellModel, CellObject
from celld.robot.collision import Checker, PathParams, arm_capsules, capsule_spheres

ROOT = Path(__file__).resolve().parents[2]
# The simulated cell: its robot's home and its calibration set-up.
SIM_CELL = load(ROOT / "configs" / "sim-cell.toml")
SIM_HOME = np.array(SIM_CELL.robot.home_q)
# The robot config's default home turned to face the table (q1 = pi): elbow up, the tool pointing down.
HOME_DOWN = np.array([math.pi, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])
VERIFICATION_POSE = SIM_CELL.calibration.verification_pose
# The forearm rising through the scanner: the arm turned towards +x (q1 = pi),
# the upper arm 60 degrees up, the forearm 48 degrees up, so the forearm's
# axis crosses x = 0.6 m at z = 1.04 m, the middle of the scanner's body.
Q_FOREARM_IN_SCANNER = np.array([math.pi, -math.pi / 3, math.pi / 3 - 0.838, -1.0, 1.57, 0.0])


@pytest.fixture(scope="module")
def cell() -> CellModel:
    table = tomllib.loads((ROOT / "configs" / "cell-models" / "sim-cell.toml").read_text())["cell_model"]
    return read_cell_model(TableReader(table, "cell-models/sim-cell.toml", "cell_model"))


@pytest.fixture(scope="module")
def checker(cell: CellModel) -> Checker:
    return Checker(kin.model("ur10e"), cell)


def tool_down(x: float, y: float, z: float) -> np.ndarray:
    """A flange pose at (x, y, z) with the flange z axis (and the tool) pointing down."""
    return se3.from_ur_pose([x, y, z, math.pi, 0.0, 0.0])


def test_capsule_spheres_cover_the_capsule(rng: np.random.Generator) -> None:
    centres, r = capsule_spheres([0.0, 0.0, 0.0], [0.0, 0.0, 0.2], 0.012)
    assert r == pytest.approx(0.012, rel=0.035)
    # Every point of the capsule lies in some sphere.
    P = rng.normal(size=(2000, 3))
    P = P / np.linalg.norm(P, axis=1, keepdims=True) * 0.012 * rng.uniform(0, 1, (2000, 1)) ** (1 / 3)
    P[:, 2] += rng.uniform(0.0, 0.2, 2000)
    assert np.all(np.min(np.linalg.norm(P[:, None] - centres[None], axis=2), axis=1) <= r + 1e-12)


def test_arm_capsules_follow_the_ur10e() -> None:
    # At the home pose the upper arm rises beside the base axis, offset 176 mm towards the wrist.
    arm = kin.model("ur10e")
    q = [0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0]
    frames = [np.eye(4)] + [kin.matrix_from_rows(r) for r in kin.forward_all_rows(q, arm.dh)]
    parts = {c.name: c for c in arm_capsules(arm)}
    upper = parts["upper_arm"]
    ends = [se3.apply(frames[upper.frame], np.array([p]))[0] for p in (upper.p0, upper.p1)]
    np.testing.assert_allclose(ends, [[0.0, -0.1762, 0.1807], [0.0, -0.1762, 0.1807 + 0.6127]], atol=1e-9)
    wrist3 = parts["wrist3"]
    tip = se3.apply(frames[wrist3.frame], np.array([wrist3.p1]))[0]
    np.testing.assert_allclose(tip, kin.forward(q)[:3, 3], atol=1e-12)


def test_the_simulated_robots_home_is_clear(checker: Checker) -> None:
    assert checker.check_configuration(SIM_HOME) is None
    assert checker.check_configuration(HOME_DOWN) is None


def test_a_tool_through_the_table_is_refused_naming_the_tool_and_the_table(checker: Checker) -> None:
    T_goal = tool_down(0.6, 0.0, 0.025)  # flange 25 mm above the table, the 200 mm tool pointing down
    check = checker.check_cartesian_path(SIM_HOME, T_goal)
    assert not check.ok
    r = check.refusal
    assert r is not None and r.reason == "collision" and r.collision is not None
    assert r.collision.part in ("srm_finger", "torch") and r.collision.part_is_tool
    assert r.collision.obstacle == "table" and not r.collision.self_collision
    assert r.collision.clearance < 0.005
    assert r.message.startswith("pose [0.600, 0.000, 0.025, 3.142, 0.000, 0.000] refused: tool part ")
    assert "'table'" in r.message and "% of the path" in r.message
    np.testing.assert_allclose(r.target, se3.to_ur_pose(T_goal), atol=1e-12)
    # It stops where the tool first comes too close, before the goal.
    assert 0.0 < r.fraction < 1.0 and check.s[-1] == r.fraction
    # At the goal itself the finger is 175 mm into the table.
    at_goal = checker.check_configuration(kin.inverse(T_goal, HOME_DOWN))
    assert at_goal is not None and at_goal.obstacle == "table"
    # The tip may touch the table (it works at the part on it); the torch, ending 190 mm out with an 8 mm radius, may not.
    assert at_goal.part == "torch" and at_goal.clearance == pytest.approx(0.025 - 0.19 - 0.008, abs=0.002)


def test_the_forearm_through_the_scanner_is_refused_naming_both(checker: Checker) -> None:
    col = checker.check_configuration(Q_FOREARM_IN_SCANNER)
    assert col is not None and (col.part, col.obstacle) == ("forearm", "scanner")
    # The forearm's axis runs through the middle of the 80 mm body: overlap of about 40 mm + its 50 mm radius.
    assert col.clearance == pytest.approx(-0.09, abs=0.01)
    assert "link 'forearm' hits 'scanner' (clearance -" in col.describe()
    # Rising into it from 20 degrees lower, in joint space and as a straight TCP line.
    q_below = Q_FOREARM_IN_SCANNER + [0.0, 0.35, 0.0, 0.0, 0.0, 0.0]
    assert checker.check_configuration(q_below) is None
    for check in (
        checker.check_joint_path(q_below, Q_FOREARM_IN_SCANNER),
        checker.check_cartesian_path(q_below, kin.forward(Q_FOREARM_IN_SCANNER)),
    ):
        r = check.refusal
        assert r is not None and r.collision is not None
        assert (r.collision.part, r.collision.obstacle) == ("forearm", "scanner")
        assert 0.0 < r.fraction < 1.0


def test_an_unreachable_pose_is_refused_before_any_sample(checker: Checker) -> None:
    T_goal = tool_down(1.6, 0.0, 0.3)  # 1.6 m out: beyond the UR10e's 1.3 m reach
    check = checker.check_cartesian_path(SIM_HOME, T_goal)
    r = check.refusal
    assert r is not None and r.reason == "unreachable" and r.q is None and r.fraction == 1.0
    assert r.message == "pose [1.600, 0.000, 0.300, 3.142, 0.000, 0.000] refused: unreachable: no IK solution at 100 % of the path"
    assert len(check.q) == 1  # only the start was looked at


def test_a_normal_move_is_accepted_and_sampled_finely(checker: Checker) -> None:
    T_goal = se3.from_ur_pose(VERIFICATION_POSE)
    check = checker.check_cartesian_path(SIM_HOME, T_goal)
    assert check.ok and check.refusal is None
    np.testing.assert_allclose(kin.forward(check.q_end), T_goal, atol=1e-9)
    assert check.s[0] == 0.0 and check.s[-1] == 1.0 and np.all(np.diff(check.s) > 0)
    assert check.min_clearance > checker.cell.margin
    # No joint moves more than the joint step, no point of the arm more than the step, between samples.
    assert np.abs(np.diff(check.q, axis=0)).max() <= checker.params.max_joint_step
    frames = np.array([[kin.matrix_from_rows(r) for r in kin.forward_all_rows(q)] for q in check.q.tolist()])
    assert np.linalg.norm(np.diff(frames[:, :, :3, 3], axis=0), axis=2).max() <= checker.params.step
    # The path is the straight line the motion process runs: positions on the segment from start to goal.
    p0, p1 = kin.forward(SIM_HOME)[:3, 3], T_goal[:3, 3]
    P = frames[:, 5, :3, 3]
    np.testing.assert_allclose(P, p0 + check.s[:, None] * (p1 - p0), atol=1e-9)


def test_a_joint_move_through_the_table_is_refused(checker: Checker) -> None:
    # The arm reaches down beside the table (off its 0.5 m half-width, the tool
    # 70 mm below the top), once on each side; the base turns it through the table.
    q_a = np.array([math.pi - 1.31, -0.87, 1.655, -2.356, -math.pi / 2, 0.0])
    q_b = q_a + [2 * 1.31, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert kin.forward(q_a)[2, 3] - 0.2 < -0.05 and abs(kin.forward(q_a)[1, 3]) > 0.8
    assert checker.check_configuration(q_a) is None and checker.check_configuration(q_b) is None
    check = checker.check_joint_path(q_a, q_b)
    r = check.refusal
    assert r is not None and r.collision is not None and r.collision.obstacle == "table"
    assert 0.05 < r.fraction < 0.5
    assert r.message.startswith("joint move to [4.452, -0.870, 1.655, -2.356, -1.571, 0.000] refused: ")
    # Without the table the same move passes.
    no_table = CellModel(objects=checker.cell.objects[1:], tool=checker.cell.tool)
    assert Checker(kin.model("ur10e"), no_table).check_joint_path(q_a, q_b).ok


def test_the_simulated_cells_calibration_plan_is_mostly_accepted(checker: Checker) -> None:
    cal = SIM_CELL.calibration
    T_v = se3.from_ur_pose(cal.verification_pose)
    targets = np.concatenate([T_v[None], calibration_poses(T_v, cal.pose_box, cal.n_poses, cal.max_tilt, seed=0)])
    plan = checker.check_plan(SIM_HOME, targets)
    assert cal.n_poses == 20 and len(plan.poses) == 21 and plan.poses[0].ok
    assert len(plan.accepted) >= 19
    for p in plan.poses:
        if p.ok:
            np.testing.assert_allclose(kin.forward(p.q), targets[p.index], atol=1e-9)


def test_a_refused_plan_pose_is_skipped_and_reported(checker: Checker) -> None:
    T_v = se3.from_ur_pose(VERIFICATION_POSE)
    targets = np.stack([T_v, tool_down(0.6, 0.0, 0.025), tool_down(1.6, 0.0, 0.3), T_v @ se3.from_ur_pose([0.05, 0, 0, 0, 0, 0])])
    plan = checker.check_plan(SIM_HOME, targets)
    assert plan.accepted == (0, 3)
    assert [p.refusal.reason for p in plan.refused if p.refusal] == ["collision", "unreachable"]
    # The fourth move starts from the first pose, not from a pose that was refused.
    direct = checker.check_cartesian_path(plan.poses[0].q, targets[3])
    np.testing.assert_allclose(plan.poses[3].q, direct.q_end, atol=1e-12)


def test_a_passage_by_the_wrist_singularity_is_refused(checker: Checker) -> None:
    q_start = np.array([0.3, -1.4, 1.6, -1.8, 0.3, 0.7])
    T_goal = kin.forward(q_start + [0.0, 0.0, 0.0, 0.0, -0.6, 0.0])  # wrist 2 from +0.3 to -0.3 rad
    r = checker.check_cartesian_path(q_start, T_goal).refusal
    assert r is not None and r.reason == "singular"
    assert r.q is not None and abs(r.q[4]) < 0.1
    assert "singular passage (smallest singular value of the Jacobian 0.0" in r.message


def test_a_turn_past_a_joint_limit_is_refused_naming_the_joint(checker: Checker) -> None:
    # Wrist 3 at 6.0 rad, the TCP turned 0.6 rad about its own axis: wrist 3 would pass 2 pi.
    q_start = HOME_DOWN + [0.0, 0.0, 0.0, 0.0, 0.0, 6.0]
    T_goal = kin.forward(q_start) @ se3.from_ur_pose([0.0, 0.0, 0.0, 0.0, 0.0, 0.6])
    check = checker.check_cartesian_path(q_start, T_goal)
    r = check.refusal
    assert r is not None and r.reason == "joint_limits"
    assert "joint 6 (wrist 3) reaches its limit (6.283 rad)" in r.message
    assert r.fraction == pytest.approx((2 * math.pi - 6.0) / 0.6, abs=0.02)
    assert check.q[:, 5].max() <= 2 * math.pi
    # Turned the other way it is free to go.
    assert checker.check_cartesian_path(q_start, kin.forward(q_start) @ se3.from_ur_pose([0, 0, 0, 0, 0, -0.6])).ok


def test_the_tool_folded_into_the_forearm_is_a_self_collision(checker: Checker) -> None:
    q = np.array([0.0, -math.pi / 2, math.pi / 2, math.pi / 4, -3 * math.pi / 4, 0.0])
    col = checker.check_configuration(q)
    assert col is not None and col.self_collision
    assert (col.part, col.obstacle) == ("forearm", "srm_finger") and col.obstacle_is_tool
    assert col.describe().startswith("link 'forearm' hits tool part 'srm_finger' (clearance -")
    # Checked independently: points of the finger lie within the two radii of the forearm's axis.
    frames = [np.eye(4)] + [kin.matrix_from_rows(r) for r in kin.forward_all_rows(q)]
    finger = se3.apply(frames[6], np.linspace([0.0, 0.0, 0.0], [0.0, 0.0, 0.2], 201))
    forearm = next(c for c in arm_capsules(kin.model("ur10e")) if c.name == "forearm")
    a, b = se3.apply(frames[3], np.array([forearm.p0, forearm.p1]))
    t = np.clip((finger - a) @ (b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    gap = np.linalg.norm(finger - (a + t[:, None] * (b - a)), axis=1).min() - forearm.radius - 0.012
    assert col.clearance == pytest.approx(gap, abs=1e-3)


def test_an_allowed_contact_is_not_a_collision(cell: CellModel) -> None:
    # The finger's tip may touch the workpiece; the torch, whose nozzle ends 10 mm above the tip's centre, may not.
    workpiece = CellObject("workpiece", Box((0.3, 0.2, 0.02)), se3.transform_from(np.eye(3), [0.6, 0.0, 0.01]))
    checker = Checker(kin.model("ur10e"), cell.with_object(workpiece))

    def at(flange_z: float) -> np.ndarray:
        q = kin.inverse(tool_down(0.63, 0.0, flange_z), HOME_DOWN)
        assert q is not None
        return q

    # Lowest points (capsule ends minus their radii): tip flange_z - 0.204, torch flange_z - 0.198; plate top 0.02.
    assert checker.check_configuration(at(0.24)) is None  # both clear of the plate
    assert checker.check_configuration(at(0.2235)) is None  # the tip 0.5 mm into it, the torch 5.5 mm above
    col = checker.check_configuration(at(0.21))  # the torch 8 mm into it
    assert col is not None and (col.part, col.obstacle) == ("torch", "workpiece")
    assert col.clearance == pytest.approx(-0.008, abs=0.001)


def test_a_tcp_offset_moves_the_targets_to_the_tip(cell: CellModel) -> None:
    T_flange_tcp = se3.transform_from(np.eye(3), [0.0, 0.0, 0.2])
    checker = Checker(kin.model("ur10e"), cell, T_flange_tcp)
    # The finger tip 30 mm above the table: the flange 230 mm above it.
    check = checker.check_cartesian_path(HOME_DOWN, tool_down(0.6, 0.0, 0.03))
    assert check.ok
    assert kin.forward(check.q_end)[2, 3] == pytest.approx(0.23, abs=1e-9)
    # The nearest part to the table that may not touch it: the torch, 190 mm out with an 8 mm radius.
    assert check.min_clearance == pytest.approx(0.23 - 0.19 - 0.008, abs=0.001)


def test_a_weld_line_is_checked_through_its_waypoints(cell: CellModel) -> None:
    T_flange_tcp = se3.transform_from(np.eye(3), [0.0, 0.0, 0.2])
    checker = Checker(kin.model("ur10e"), cell, T_flange_tcp)
    line = np.array([tool_down(0.6, y, 0.05) for y in np.linspace(-0.075, 0.075, 7)])
    check = checker.check_waypoints(HOME_DOWN, line)
    assert check.ok and check.s[-1] == 1.0
    np.testing.assert_allclose(kin.forward(check.q_end, T_flange_tcp=T_flange_tcp), line[-1], atol=1e-9)
    # One waypoint 20 mm into the table refuses the path there, naming it.
    low = line.copy()
    low[4, 2, 3] = -0.02
    r = checker.check_waypoints(HOME_DOWN, low).refusal
    assert r is not None and r.collision is not None and r.collision.obstacle == "table"
    assert r.message.startswith("pose 5 of 7 [0.600, 0.025, -0.020, 3.142, 0.000, 0.000] refused: ")
    assert 4 / 7 < r.fraction <= 5 / 7


def test_inputs_are_checked_at_the_boundary(checker: Checker) -> None:
    with pytest.raises(InputError, match="q_start: expected 6 joint angles"):
        checker.check_cartesian_path([0.0] * 5, np.eye(4))
    with pytest.raises(InputError, match="T_base_tcp_goal: expected a .4, 4."):
        checker.check_cartesian_path(SIM_HOME, np.eye(3))
    with pytest.raises(InputError, match="step > 0"):
        Checker(kin.model("ur10e"), checker.cell, params=PathParams(step=0.0))
    r = checker.check_joint_path(SIM_HOME, SIM_HOME + [0, 0, 0, 0, 0, 8.0]).refusal
    assert r is not None and r.reason == "joint_limits" and "goal joints are outside the joint limits" in r.message
