"""The tool tip's least squares (T1, T2): recovered within noise, outliers named, degenerate turns refused by the verdict."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.bus.checker import validate
from celld.calib.toolcal import FIT_SCHEMA, ToolCalParams, orientation_spread, solve_tool_tip, tool_calibration_poses
from celld.errors import InputError

TIP_TRUE = np.array([0.0009, -0.0012, 0.2011])  # m, TCP frame: the tool as built
TIP_CONFIG = np.array([0.0, 0.0, 0.2])  # what the config says
R_FACE = np.eye(3)  # flange z up, towards the scanner
P_TIP = np.array([0.6, 0.0, 0.45])
Z_FINGER = np.array([0.0, 0.0, -1.0])
OFFSET = np.array([0.3e-3, -0.2e-3, 0.5e-3])  # the scanner's and the arm's disagreement at the tool's place, m


def _measure(T: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    P = np.einsum("nij,j->ni", T[:, :3, :3], TIP_TRUE) + T[:, :3, 3] + OFFSET
    return P + rng.normal(0.0, sigma, P.shape)


def test_the_tip_is_recovered_within_its_stated_uncertainty() -> None:
    rng = np.random.default_rng(1)
    T = tool_calibration_poses(R_FACE, P_TIP, TIP_CONFIG, Z_FINGER, 12, math.radians(20), seed=0)
    sigma = 0.05e-3
    fit = solve_tool_tip(T, _measure(T, rng, sigma))
    assert fit.verdict == "ok", fit.reasons
    err = fit.p_tcp_tip - TIP_TRUE
    # Within 3 sigma of its own 1-sigma on every axis, and that 1-sigma is tens of microns.
    assert np.all(np.abs(err) <= 3.0 * fit.tip_std), (err, fit.tip_std)
    assert np.all(fit.tip_std < 0.1e-3), fit.tip_std
    assert np.linalg.norm(err) < 0.1e-3
    assert np.allclose(fit.offset_base, OFFSET, atol=0.1e-3)
    assert abs(fit.sigma - sigma) < 0.5 * sigma  # noise per axis from the residuals
    assert fit.rejected == () and len(fit.inliers) == 12
    assert fit.spread > math.radians(8)


def test_exact_data_give_the_tip_exactly_and_the_floor_as_noise() -> None:
    T = tool_calibration_poses(R_FACE, P_TIP, TIP_CONFIG, Z_FINGER, 8, math.radians(15), seed=2)
    fit = solve_tool_tip(T, _measure(T, np.random.default_rng(0), 0.0))
    assert np.allclose(fit.p_tcp_tip, TIP_TRUE, atol=1e-9)
    assert fit.sigma_source == "floor" and fit.verdict == "ok"


def test_outliers_are_named_with_their_residual_and_threshold() -> None:
    rng = np.random.default_rng(3)
    T = tool_calibration_poses(R_FACE, P_TIP, TIP_CONFIG, Z_FINGER, 14, math.radians(20), seed=1)
    P = _measure(T, rng, 0.05e-3)
    P[4] += [0.0, 0.0, 2.0e-3]  # the table's edge taken for the tip
    P[9] += [1.5e-3, 1.0e-3, 0.0]
    fit = solve_tool_tip(T, P, ids=[f"p{i}" for i in range(14)])
    assert sorted(r.id for r in fit.rejected) == ["p4", "p9"]
    assert all("exceeds the inlier threshold" in r.reason for r in fit.rejected)
    assert np.linalg.norm(fit.p_tcp_tip - TIP_TRUE) < 0.1e-3
    assert fit.verdict == "ok" and any("outliers" in w for w in fit.warnings)
    report = fit.as_dict()
    validate(FIT_SCHEMA, report)
    assert report["outliers"] == ["p4", "p9"]
    assert [p["outlier"] for p in report["poses"]].count(True) == 2


def test_too_many_outliers_are_poor_data() -> None:
    rng = np.random.default_rng(4)
    T = tool_calibration_poses(R_FACE, P_TIP, TIP_CONFIG, Z_FINGER, 8, math.radians(20), seed=1)
    P = _measure(T, rng, 0.05e-3)
    P[[1, 3, 5]] += rng.normal(0.0, 3e-3, (3, 3))
    fit = solve_tool_tip(T, P)
    assert fit.verdict == "poor_data", fit.reasons
    assert any("outliers" in r for r in fit.reasons)


def test_turns_about_one_axis_give_the_poor_spread_verdict() -> None:
    rng = np.random.default_rng(5)
    angles = np.linspace(-0.4, 0.4, 9)
    R = Rotation.from_rotvec(np.outer(angles, [1.0, 0.0, 0.0])).as_matrix()  # tilts about base x only
    T = np.tile(np.eye(4), (9, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = P_TIP - R @ TIP_CONFIG
    fit = solve_tool_tip(T, _measure(T, rng, 0.05e-3))
    assert fit.verdict == "poor_orientation_spread", fit.reasons
    assert fit.spread < 1e-9
    assert abs(abs(fit.spread_axis_tcp[0]) - 1.0) < 1e-6  # the free direction is the turning axis
    assert "two axes" in fit.reasons[0]


def test_one_orientation_moved_in_a_plane_gives_the_poor_spread_verdict() -> None:
    rng = np.random.default_rng(6)
    T = np.tile(np.eye(4), (8, 1, 1))
    T[:, :2, 3] = rng.uniform(-0.1, 0.1, (8, 2))  # coplanar positions, the same orientation
    T[:, 2, 3] = 0.25
    fit = solve_tool_tip(T, _measure(T, rng, 0.05e-3))
    assert fit.verdict == "poor_orientation_spread"
    assert not np.all(np.isfinite(fit.tip_std))


def test_too_few_poses() -> None:
    T = tool_calibration_poses(R_FACE, P_TIP, TIP_CONFIG, Z_FINGER, 4, math.radians(20), seed=0)
    fit = solve_tool_tip(T, _measure(T, np.random.default_rng(7), 0.05e-3))
    assert fit.verdict == "too_few_poses" and "at least 6" in fit.reasons[0]
    two = solve_tool_tip(T[:2], _measure(T[:2], np.random.default_rng(7), 0.0))
    assert two.verdict == "too_few_poses" and not np.any(np.isfinite(two.p_tcp_tip))


def test_inputs_are_checked_where_they_enter() -> None:
    T = tool_calibration_poses(R_FACE, P_TIP, TIP_CONFIG, Z_FINGER, 6, math.radians(20), seed=0)
    P = _measure(T, np.random.default_rng(8), 0.0)
    with pytest.raises(InputError, match="one tip per pose"):
        solve_tool_tip(T, P[:5])
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        solve_tool_tip(T, P[:, :2])
    bad = T.copy()
    bad[2, :3, :3] *= 2.0
    with pytest.raises(InputError, match=r"T_base_tcp\[2\]"):
        solve_tool_tip(bad, P)
    P[1, 0] = np.nan
    with pytest.raises(InputError, match="finite"):
        solve_tool_tip(T, P)
    with pytest.raises(InputError, match="min_poses"):
        ToolCalParams(min_poses=2)


def test_generated_poses_keep_the_tip_in_place_and_turn_about_three_axes() -> None:
    T = tool_calibration_poses(R_FACE, P_TIP, TIP_CONFIG, Z_FINGER, 12, math.radians(20), seed=9)
    tips = np.einsum("nij,j->ni", T[:, :3, :3], TIP_CONFIG) + T[:, :3, 3]
    assert np.allclose(tips, P_TIP, atol=1e-12)
    tilt = np.degrees(np.arccos(np.clip(T[:, 2, 2], -1.0, 1.0)))  # the finger's angle from vertical
    assert tilt[0] == pytest.approx(0.0, abs=1e-9) and tilt.max() == pytest.approx(20.0, abs=1e-6)
    assert orientation_spread(T[:, :3, :3])[0] > math.radians(8)
