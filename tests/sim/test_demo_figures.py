"""The demo's figures: the calibrated base 2 against the truth where the robots meet; the calibration's own bounds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import se3
from celld.sim.demo import _bound_lines, _robot2_lines, robot2_figures


def test_robot2_figures_measure_the_miss_where_the_robots_meet() -> None:
    T_true = se3.from_ur_pose([1.25, 0.0, 0.0, 0.0, 0.0, math.pi])
    # The estimate turned 1 mrad about the vertical through base 2's origin: 1 mm off per metre of lever.
    T_est = se3.transform_from(se3.from_xyz_rpy([0, 0, 0], [0, 0, 1e-3])[:3, :3] @ T_true[:3, :3], T_true[:3, 3])
    entry = {
        "T_base1_base2": T_est.tolist(),
        "translation_std_mm": [0.03, 0.04, 0.0],
        "from_drawing_mm": 3.2,
        "quality": {"verdict": "ok"},
    }
    verification = (0.65, 0.0, 0.45, 0.0, 0.0, 0.0)
    f = robot2_figures(entry, T_true, verification)
    lever = se3.apply(T_true, np.array([verification[:3]]))[0] - T_true[:3, 3]  # 0.65 m across, 0.45 m up
    assert f["meet_mm"] == pytest.approx(1e-3 * np.hypot(*lever[:2]) * 1e3, rel=1e-3)
    assert f["meet_std_mm"] == pytest.approx(0.05) and f["rotation_deg"] == pytest.approx(math.degrees(1e-3), rel=1e-6)
    assert "0.650 mm where the robots meet" in _robot2_lines(f)[0] and _robot2_lines(None) == []


def test_the_calibrations_own_bounds_are_printed_as_it_reported_them() -> None:
    bound = {"confidence": 0.95, "calibration_box_mm": 0.2041, "work_radius_mm": 1.2563, "arm_error_prior_mm": 1.0}
    (line,) = _bound_lines(bound)
    assert "(95%): 0.204 mm in the box, 1.256 mm elsewhere in reach" in line and "taken as 1.0 mm" in line
    # A calibration stored before the bounds existed, or one whose bounds are not finite, prints nothing.
    assert _bound_lines(None) == [] and _bound_lines({**bound, "work_radius_mm": None}) == []


def test_the_torch_height_is_printed_beside_the_plan_alones() -> None:
    from celld.sim.demo import _height_lines

    torch = {"mean_mm": 3.912, "min_mm": 3.51, "max_mm": 4.27, "points": 80, "error_mean_mm": -0.088, "error_max_mm": 0.49}
    plan = {**torch, "mean_mm": 3.4, "error_max_mm": 1.2}
    first, second = _height_lines(torch, plan)
    assert "mean 3.912 mm (3.510 to 4.270)" in first and "at most 0.490 mm from the height welded at" in first
    assert "plan alone: mean 3.400 mm, at most 1.200 mm" in second
    assert _height_lines({**torch, "points": 0}, plan) == [] and _height_lines(torch, None) == [first]


def test_the_plan_alone_with_the_measured_tool_is_built_from_the_tool_calibrations_result() -> None:
    from celld.config import ToolConfig
    from celld.sim.score import measured_tool

    typed = ToolConfig(tip_tcp=(0.0, 0.0, 0.2), torch_offset=0.03)
    # Measured: the tip 0.8 mm off in x, the torch 0.9 mm to the side and its end 0.5 mm nearer the flange.
    tool = measured_tool(typed, {"tip_tcp_mm": [0.8, 0.0, 200.0], "torch_tcp_mm": [-29.2, 0.9, 199.5]})
    assert tool.tip_tcp == pytest.approx((0.8e-3, 0.0, 0.2))
    assert tool.torch_offset == pytest.approx(np.hypot(30.0, 0.9) * 1e-3)
    np.testing.assert_allclose(tool.tool_x_tcp, np.array([30.0, -0.9, 0.0]) / np.hypot(30.0, 0.9))


def test_the_touch_checks_truth_carries_its_point_by_the_arms_error_there_against_the_true_root() -> None:
    from types import SimpleNamespace

    from celld.sim.robot.truth import TRUTH_DTYPE
    from celld.sim.score import touch_check_truth

    # The true root along x in the plane z = 0; the check at x = 50 mm, 3 mm up, across along +y.
    part = SimpleNamespace(T_base_plane=np.eye(4), seam_base=np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]))
    check = {"at_base": [0.05, 0.0, 0.003], "across": [0.0, 1.0, 0.0], "tip_height_mm": 3.0}
    tip_believed, tip_true = np.array([0.0, 0.0, 0.2]), np.array([0.0, 1e-4, 0.2])  # the tool as built 0.1 mm off
    recs = np.zeros(30, TRUTH_DTYPE)
    for k, r in enumerate(recs):
        wobble = 1e-3 * np.array([0.0, (k % 3) - 1.0, 0.0])  # the touches move the tip across
        model = se3.transform_from(np.eye(3), np.array(check["at_base"]) - tip_believed + wobble)
        r["T_base_tcp_model"] = model
        # The arm truly 0.4 mm to -y and 0.2 mm low; after the arc lit (the last 10), 5 mm off: not the check's.
        off = np.array([0.0, -4e-4, -2e-4]) if k < 20 else np.array([0.0, 5e-3, 0.0])
        r["T_base_tcp"] = se3.transform_from(np.eye(3), model[:3, 3] + off)
        r["arc_on"] = k >= 20
    got = touch_check_truth(part, check, recs, tip_believed, tip_true, -1)  # the arc as a power source burns it
    assert got is not None and got["states"] == 20
    # The point truly at y = -0.3 mm, z = 2.8 mm: the root 0.3 mm across towards +y, and 0.2 mm higher than planned.
    assert got["across_mm"] == pytest.approx(0.3, abs=1e-6) and got["height_mm"] == pytest.approx(0.2, abs=1e-6)
    assert got["error_mm"] == pytest.approx(math.hypot(0.3, 0.2), abs=1e-6)
    # No state near the point: no truth.
    far = {**check, "at_base": [0.08, 0.0, 0.003]}
    assert touch_check_truth(part, far, recs, tip_believed, tip_true, -1) is None
    # The arc on a digital output (bit 0) from the same record: the same states before it.
    recs["digital_out"] = recs["arc_on"]
    assert touch_check_truth(part, check, recs, tip_believed, tip_true, 0) == got
