"""The weld's plan from a scan: the path the tool takes, the height probe's reading, the refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import se3
from celld.bus.checker import validate
from celld.config import ToolConfig, WeldConfig
from celld.config.seam import SeamParams
from celld.errors import WorkpieceError
from celld.seam.weldpath import joint_width, weld_geometry
from celld.seam.workpiece import example
from celld.sim import workpiece as simscene
from celld.sim.scanner import SimScanner
from celld.tactile.tool import ToolGeometry
from celld.weld.plan import (
    LEAD_IN,
    PROBED_SCHEMA,
    WeldPlan,
    for_torch,
    judged,
    plan_weld,
    precorrected,
    prepare_part,
    probe_across,
    probe_targets,
    probed_height,
    touch_check,
)

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
WELD = WeldConfig()
TOOL = ToolConfig()

# A finger's gain as a weld's touches read it (celld.weld.plan.measured_finger): the probe carries it in its reading.
FINGER = {
    "measured": True,
    "gain": 1.12,
    "gain_sigma": 0.004,
    "cubic_per_mm2": 0.02,
    "residual_rms_um": 1.8,
    "frames": 31,
    "span_mm": [0.4, 1.5],
}


@pytest.fixture(scope="module")
def plan() -> WeldPlan:
    wp = example("v-groove")
    T_true = simscene.random_pose(wp, np.random.default_rng(4), math.radians(10.0), 0.02)
    scan = SimScanner("phoxi-m", T_BASE_CAM, seed=1, resolution_scale=0.5).capture(simscene.workpiece_scene(wp, T_true)).points
    weld = WeldConfig(nominal_pose=tuple(se3.to_ur_pose(simscene.nominal_pose(wp)).tolist()))
    part = prepare_part(wp, SeamParams(), weld.tip_height)
    return plan_weld(
        scan, T_BASE_CAM, part, weld, SeamParams(), ToolGeometry.from_config(TOOL).T_tcp_tool, se3.from_ur_pose(weld.scan_pose)
    )


def test_the_path_comes_down_onto_the_start_runs_along_the_seam_and_goes_back_to_the_scan_pose(plan: WeldPlan) -> None:
    path = plan.path
    np.testing.assert_allclose(path[0], plan.T_above)
    np.testing.assert_allclose(path[1], plan.T_start)
    np.testing.assert_allclose(path[-1], se3.from_ur_pose(WELD.scan_pose))
    np.testing.assert_allclose(plan.T_above[:3, 3] - plan.T_start[:3, 3], WELD.approach_height * plan.up, atol=1e-12)
    # Along the seam: one pose every PATH_STEP of the wall line, then up by the retract height.
    along = path[2:-2, :3, 3]
    assert len(along) >= 10 and np.all(np.linalg.norm(np.diff(along, axis=0), axis=1) < 0.0105)
    np.testing.assert_allclose(path[-2, :3, 3] - path[-3, :3, 3], WELD.retract_height * plan.up, atol=1e-9)


def test_a_probe_that_finds_the_planned_width_leaves_the_plan_and_a_wider_joint_brings_it_down(plan: WeldPlan) -> None:
    targets, why = probe_targets(plan, TOOL)
    assert [t.name for t in targets] == ["far", "finger"] and why == ""
    assert targets[0].tool.wall_side != TOOL.wall_side and targets[1].tool == TOOL
    tool = ToolGeometry.from_config(TOOL)
    i = int(plan.geometry.stations([LEAD_IN])[0])
    finger, far = plan.seam.wall_across[i], plan.seam.far_wall_across[i]
    planned = joint_width(finger, far, plan.geometry.tip_height)

    def touches(width: float) -> dict[str, float]:  # where the tip's centre stood at each wall, across the joint
        return {"far": 0.0, "finger": width - 2.0 * tool.tip_radius}

    found, same = probed_height(plan, touches(planned), FINGER, tool, tool.T_tcp_tool, WELD.max_height_correction)
    assert found["probed"] and abs(found["height_correction_mm"]) < 1e-6
    validate(PROBED_SCHEMA, found)  # the shape the weld's result promises
    np.testing.assert_allclose(same.T_start, plan.T_start, atol=1e-9)
    opening = finger[1] + far[1]
    found, lifted = probed_height(plan, touches(planned + opening * 0.001), FINGER, tool, tool.T_tcp_tool, WELD.max_height_correction)
    # The joint is wider than planned: the tip stands 1 mm higher than the plan says, and the plan comes down by it.
    assert found["height_correction_mm"] == pytest.approx(-1.0, abs=1e-6)
    assert (plan.T_start[:3, 3] - lifted.T_start[:3, 3]) @ plan.up == pytest.approx(0.001, abs=1e-6)
    with pytest.raises(WorkpieceError, match="check the calibration and the tool"):
        probed_height(plan, touches(planned + opening * 0.003), FINGER, tool, tool.T_tcp_tool, WELD.max_height_correction)


def test_the_touch_check_reads_how_far_the_touched_joint_is_from_the_scanned_one_across_and_in_height(plan: WeldPlan) -> None:
    tool = ToolGeometry.from_config(TOOL)
    i = int(plan.geometry.stations([LEAD_IN])[0])
    finger, far = plan.seam.wall_across[i], plan.seam.far_wall_across[i]
    origin, across = probe_across(plan)
    h = plan.geometry.tip_height
    y_seam = float((plan.geometry.seam_base[i] - origin) @ across)

    def touches(shift: float, lower: float = 0.0) -> dict[str, float]:
        # The tip's centre a radius inside each wall, the walls as the scan measured them but the joint moved
        # ``shift`` towards the finger wall and its root ``lower`` down (the tip, at the planned height over the
        # scanned root, meets the walls where they are ``h + lower`` over the true one).
        finger_wall = y_seam + finger[0] + finger[1] * (h + lower) + shift
        far_wall = y_seam - (far[0] + far[1] * (h + lower)) + shift
        return {"finger": finger_wall - tool.tip_radius, "far": far_wall + tool.tip_radius}

    # Where the scan put it: no error.
    found, _ = probed_height(plan, touches(0.0), FINGER, tool, tool.T_tcp_tool, WELD.max_height_correction)
    check = found["touch_check"]
    assert check["across_mm"] == pytest.approx(0.0, abs=1e-4) and check["height_mm"] == pytest.approx(0.0, abs=1e-4)
    np.testing.assert_allclose(check["at_base"], plan.geometry.seam_base[i], atol=1e-6)
    # The joint 0.3 mm further towards the finger wall than scanned: +0.3 mm across, none in height.
    check = touch_check(plan, touches(0.3e-3), h)
    assert check["across_mm"] == pytest.approx(0.3, abs=1e-4) and check["error_mm"] == pytest.approx(0.3, abs=1e-4)
    # The root 0.5 mm lower than scanned and the joint 0.2 mm towards the far wall: the tip stands 0.5 mm higher
    # than planned, and the plan comes down by it.
    found, _ = probed_height(plan, touches(-0.2e-3, 0.5e-3), FINGER, tool, tool.T_tcp_tool, WELD.max_height_correction)
    check = found["touch_check"]
    assert check["across_mm"] == pytest.approx(-0.2, abs=1e-4), check
    assert check["height_mm"] == pytest.approx(-0.5, abs=1e-4) and found["height_correction_mm"] == pytest.approx(-0.5, abs=1e-4)
    assert check["error_mm"] == pytest.approx(math.hypot(0.2, 0.5), abs=1e-4)
    # The job adds the calibration's own bound at the weld: covered, exceeded, or none stored.
    assert judged(check, 1e-3)["verdict"] == "ok" and judged(check, 1e-3)["within_bound"] is True
    beyond = judged(check, 0.4e-3)
    assert beyond["verdict"] == "beyond_bound" and beyond["bound_mm"] == pytest.approx(0.4) and beyond["within_bound"] is False
    assert judged(check, None)["verdict"] == "no_bound" and judged(check, None)["bound_mm"] is None
    for bound in (1e-3, 0.4e-3, None):
        validate(PROBED_SCHEMA, {**found, "touch_check": judged(check, bound)})


def test_a_torch_measured_off_the_tips_height_moves_the_tip_so_the_torch_welds_at_the_planned_height() -> None:
    # The wire's end 0.7 mm above the tip (cut short): the tip rides 0.7 mm lower, the torch at weld.tip_height.
    assert for_torch(WELD, 0.7e-3).tip_height == pytest.approx(WELD.tip_height - 0.7e-3)
    assert for_torch(WELD, -0.4e-3).tip_height == pytest.approx(WELD.tip_height + 0.4e-3)
    assert for_torch(WELD, 0.0) == WELD
    # Beyond what the tip's height can make up: refused, with what to do.
    with pytest.raises(WorkpieceError, match=r"2\.50 mm above the tip .*weld\.max_height_correction_mm \(2\).*trim the wire"):
        for_torch(WELD, 2.5e-3)
    with pytest.raises(WorkpieceError, match="not a number"):
        for_torch(WELD, math.nan)


def test_a_plan_pre_corrected_moves_each_pose_and_the_lines_with_the_tool_beside_them(plan: WeldPlan) -> None:
    # A correction that grows along x (as the arm's own error grows away from where it was calibrated):
    # 1 mm per metre along x, and a turn of 1 mrad about z.
    turn = se3.from_ur_pose([0.0, 0.0, 0.0, 0.0, 0.0, 1e-3])

    def correct(T: np.ndarray) -> np.ndarray:
        D = turn.copy()
        D[:3, 3] = [0.0, 1e-3 * T[0, 3], 0.0]
        return D @ T

    tool = ToolGeometry.from_config(TOOL)
    got = precorrected(plan, correct, tool.T_tcp_tool)
    for a, b in ((got.T_start, plan.T_start), (got.T_above, plan.T_above)):
        np.testing.assert_allclose(a, correct(b), atol=1e-12)
    np.testing.assert_allclose(got.path[:-1], np.array([correct(T) for T in plan.path[:-1]]), atol=1e-12)
    np.testing.assert_array_equal(got.path[-1], plan.path[-1])  # the scan pose: the controller's, as configured
    g0, g1 = plan.geometry, got.geometry
    # Each wall point moved by the correction of the tool's pose there: the tool's own x is 0.1-0.3 mm off the
    # point's, so the shift is the pose's, and the points keep the wall's shape.
    expected = g0.wall_base @ turn[:3, :3].T
    expected[:, 1] += 1e-3 * (g0.wall_base[:, 0] + np.array([T[0, 3] - p[0] for T, p in zip(tool_poses_at(g0, tool), g0.wall_base)]))
    np.testing.assert_allclose(g1.wall_base, expected, atol=1e-9)
    np.testing.assert_allclose(g1.seam_base - g1.wall_base, (g0.seam_base - g0.wall_base) @ turn[:3, :3].T, atol=1e-12)
    np.testing.assert_allclose(g1.tangents, g0.tangents @ turn[:3, :3].T, atol=1e-12)
    np.testing.assert_allclose(g1.normals, g0.normals @ turn[:3, :3].T, atol=1e-12)
    np.testing.assert_allclose(g1.offsets, g0.offsets)
    # No correction, no change.
    same = precorrected(plan, lambda T: T, tool.T_tcp_tool)
    np.testing.assert_allclose(same.geometry.wall_base, g0.wall_base, atol=1e-12)
    np.testing.assert_allclose(same.path, plan.path, atol=1e-12)


def tool_poses_at(geometry, tool: ToolGeometry) -> np.ndarray:
    """The tool's TCP at every point of the wall line (the poses the pre-correction is taken at)."""
    from celld import polyline
    from celld.seam.weldpath import tool_poses

    return tool_poses(geometry, tool.T_tcp_tool, polyline.arc_length(geometry.wall_base))


def test_the_finger_s_gain_is_measured_from_the_touches_or_said_why_not_and_a_broken_finger_stops_the_weld() -> None:
    from celld.tactile.fingermap import FingerGain, FingerRefused, Press
    from celld.weld.plan import FINGER_SCHEMA, measured_finger

    tip = np.linspace(0.4e-3, 1.6e-3, 15)
    # Two touches of a finger whose tag moves 0.9 times its tip, walls 6 mm apart (the far one towards -y).
    presses = [Press(0.003 + tip, 0.9 * tip, 1.0), Press(-0.003 - tip, -0.9 * tip, 1.0)]
    finger, reading = measured_finger(presses, 1.5e-3)
    assert finger.gain == pytest.approx(1 / 0.9, rel=1e-6) and abs(finger.cubic) < 1.0 and reading["frames"] == 30
    validate(FINGER_SCHEMA, reading)
    validate(FINGER_SCHEMA, FINGER)
    # Touches that came on too fast for the camera: Eq. 15 as it is, and why.
    finger, reading = measured_finger([Press(tip[:3], 0.9 * tip[:3], 1.0)], 1.5e-3)
    assert finger == FingerGain() and reading["measured"] is False and "span" in reading["why"]
    validate(FINGER_SCHEMA, reading)
    with pytest.raises(FingerRefused, match="check the finger and its tag"):
        measured_finger([Press(0.003 + tip, 0.4 * tip, 1.0)], 1.5e-3)


def test_a_finger_whose_gain_moved_beyond_its_scatter_since_the_last_weld_is_said_to_have_changed() -> None:
    from celld.weld.plan import FINGER_SCHEMA, compared_finger

    same = compared_finger(FINGER, 1.11, 0.004, "w1")  # 0.9 % apart: within FINGER_CHANGE
    assert same["previous"] == {"gain": 1.11, "job": "w1", "change": pytest.approx(0.009009, abs=1e-5), "changed": False}
    worn = compared_finger(FINGER, 1.06, 0.004, "w1")  # 5.7 %
    assert worn["previous"]["changed"] is True
    # Two scattered measurements 5.7 % apart: not beyond three of their sigmas.
    assert compared_finger({**FINGER, "gain_sigma": 0.02}, 1.06, 0.02, "w1")["previous"]["changed"] is False
    validate(FINGER_SCHEMA, worn)
    validate(FINGER_SCHEMA, {"measured": False, "why": "not probed", "stored": {"gain": 1.1, "cubic_per_mm2": 0.0, "job": "w1", "at": "x"}})


def test_a_pre_corrected_plan_keeps_its_correction_when_the_probe_moves_it_to_its_height(plan: WeldPlan) -> None:
    # A rigid correction of the arm's calibration at the weld: 0.4 mm down and 0.3 mm across, and a turn of 1 mrad.
    D = se3.from_ur_pose([0.0, 0.3e-3, -0.4e-3, 0.0, 0.0, 1e-3])
    tool = ToolGeometry.from_config(TOOL)
    corrected = precorrected(plan, lambda T: D @ T, tool.T_tcp_tool)
    i = int(plan.geometry.stations([LEAD_IN])[0])
    finger, far = plan.seam.wall_across[i], plan.seam.far_wall_across[i]
    planned = joint_width(finger, far, plan.geometry.tip_height)
    touches = {"far": 0.0, "finger": planned + (finger[1] + far[1]) * 0.0005 - 2.0 * tool.tip_radius}  # 0.5 mm higher
    _, moved = probed_height(corrected, touches, FINGER, tool, tool.T_tcp_tool, WELD.max_height_correction)
    _, plain = probed_height(plan, touches, FINGER, tool, tool.T_tcp_tool, WELD.max_height_correction)
    # Probing the corrected plan is the corrected plan of the probed one: the correction stays, the height moves.
    again = precorrected(plain, lambda T: D @ T, tool.T_tcp_tool)
    for name in ("wall_base", "seam_base", "T_base_plane"):
        np.testing.assert_allclose(getattr(moved.geometry, name), getattr(again.geometry, name), atol=1e-9)
    np.testing.assert_allclose(moved.T_start, again.T_start, atol=1e-9)
    assert moved.geometry.tip_height == pytest.approx(plan.geometry.tip_height - 0.0005, abs=1e-9)
    # And the plain plan moved exactly as one built again from the seam at that height.
    rebuilt = weld_geometry(
        plan.seam.points_base,
        plan.seam.tangents,
        plan.seam.normals,
        plan.seam.plane_normal,
        plan.geometry.offsets,
        plain.geometry.tip_height,
    )
    np.testing.assert_allclose(plain.geometry.wall_base, rebuilt.wall_base, atol=1e-12)
    np.testing.assert_allclose(plain.geometry.T_base_plane, rebuilt.T_base_plane, atol=1e-12)
