"""The finger's wall line beside a seam, and the weld's start pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import se3
from celld.errors import WorkpieceError
from celld.seam.weldpath import height_from_width, in_plane, measured_offsets, model_geometry, start_pose, wall_offset, weld_geometry
from celld.seam.workpiece import curved_groove, fillet_t_joint, v_groove_butt


def nominal_pose(wp) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The part on the table at (0.6, 0), its seam along base y."""
    return se3.from_xyz_rpy([0.6, 0.0, -float(wp.vertices[:, 2].min())], [0.0, 0.0, np.pi / 2])


@pytest.mark.parametrize("h", [0.0, 0.002, 0.005])
def test_v_groove_wall_offset_is_half_the_gap_plus_the_bevel_at_the_tip_height(h: float) -> None:
    wp = v_groove_butt(groove_angle=math.radians(60.0), root_gap=0.002)
    expected = 0.001 + h * math.tan(math.radians(30.0))
    assert wall_offset(wp, h, "left") == pytest.approx(expected, abs=1e-6)
    assert wall_offset(wp, h, "right") == pytest.approx(expected, abs=1e-6)


def test_fillet_web_stands_on_the_seam_and_curved_groove_matches_the_straight_one() -> None:
    assert wall_offset(fillet_t_joint(), 0.004, "left") == pytest.approx(0.0, abs=1e-6)
    assert wall_offset(curved_groove(), 0.004) == pytest.approx(wall_offset(v_groove_butt(), 0.004), abs=2e-5)


def test_a_wall_out_of_reach_or_a_flange_side_finger_is_refused() -> None:
    # The fillet's right wall is the flange top: a ray across the joint at the tip height never meets it.
    with pytest.raises(WorkpieceError, match="not beside it"):
        wall_offset(fillet_t_joint(), 0.004, "right")
    with pytest.raises(WorkpieceError, match="finger_wall"):
        wall_offset(v_groove_butt(), 0.004, "up")


def test_start_pose_puts_the_tip_off_the_wall_on_the_free_side_facing_along_the_seam() -> None:
    wp = v_groove_butt()
    g = model_geometry(wp, nominal_pose(wp), 0.004)
    T_tcp_tool = se3.transform_from(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.2])
    T = start_pose(g, T_tcp_tool, lead=0.005, clearance=0.004)
    T_tool = T @ T_tcp_tool
    tip = in_plane(g, T_tool[None, :3, 3])[0]
    assert tip[0] == pytest.approx(0.005, abs=1e-3)
    assert tip[1] == pytest.approx(-0.004, abs=1e-9)  # 4 mm right of the (left) wall
    assert np.allclose(T_tool[:3, 2], g.T_base_plane[:3, 2], atol=1e-9)  # finger up along the plane normal
    assert np.allclose(T_tool[:3, 0], g.tangents[5], atol=1e-9)
    with pytest.raises(WorkpieceError, match="shorter than the lead-in"):
        start_pose(g, T_tcp_tool, lead=1.0, clearance=0.004)


def test_weld_geometry_refuses_mismatched_arrays() -> None:
    with pytest.raises(WorkpieceError, match="matching"):
        weld_geometry(np.zeros((3, 3)), np.zeros((2, 3)), np.zeros((3, 3)), np.array([0, 0, 1.0]), 0.001, 0.004)


def test_a_bowed_groove_keeps_its_wall_beside_its_seam() -> None:
    straight, bowed = v_groove_butt(), v_groove_butt(bow=0.002)
    mid = bowed.seam[len(bowed.seam) // 2]
    assert mid[1] == pytest.approx(0.002, abs=1e-9) and bowed.seam[0][1] == pytest.approx(0.0, abs=1e-9)
    assert len(straight.seam) == 2  # the straight part is unchanged
    assert wall_offset(bowed, 0.004) == pytest.approx(wall_offset(straight, 0.004), abs=2e-5)
    with pytest.raises(WorkpieceError, match="bow"):
        v_groove_butt(bow=0.1)


def test_the_scan_measured_wall_sets_the_offset_per_point_and_fills_what_it_missed() -> None:
    # Rows (t0, slope): a V's bevel at tan(30 deg), its gap opening from 2.0 to 2.4 mm along the seam.
    n = 11
    t0 = np.linspace(0.0010, 0.0012, n)
    rows = np.column_stack([t0, np.full(n, math.tan(math.radians(30.0)))])
    rows[3:5] = np.nan  # not measured there: its neighbours' between
    got = measured_offsets(rows, 0.004, 0.0033)
    expected = np.linspace(0.0010, 0.0012, n) + 0.004 * math.tan(math.radians(30.0))
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # Nothing measured: the model's offset everywhere.
    np.testing.assert_allclose(measured_offsets(np.full((n, 2), np.nan), 0.004, 0.0033), 0.0033)
    # A wall far off the model's is a different joint, not a correction.
    with pytest.raises(WorkpieceError, match="off the model"):
        measured_offsets(rows, 0.004, 0.0033 + 0.0012)
    # The plan's wall line follows the offsets.
    P = np.column_stack([np.linspace(0, 0.1, n), np.zeros(n), np.zeros(n)])
    T = np.tile([1.0, 0.0, 0.0], (n, 1))
    N = np.tile([0.0, 1.0, 0.0], (n, 1))
    g = weld_geometry(P, T, N, np.array([0.0, 0.0, 1.0]), got, 0.004)
    np.testing.assert_allclose(g.wall_base[:, 1], got, atol=1e-15)
    assert g.offset == pytest.approx(float(np.median(got)))


@pytest.mark.parametrize("h", [0.003, 0.004, 0.0055])
def test_a_v_grooves_width_tells_the_height_and_a_fillets_does_not(h: float) -> None:
    slope = math.tan(math.radians(30.0))
    finger, far = np.array([0.0011, slope]), np.array([0.0009, slope])  # an off-centre gap of 2 mm
    width = 0.002 + 2.0 * slope * h
    assert height_from_width(width, finger, far) == pytest.approx(h, abs=1e-12)
    with pytest.raises(WorkpieceError, match="open by"):
        height_from_width(0.004, np.array([0.0, 0.0]), np.array([0.004, 0.1]))  # an upright web
    with pytest.raises(WorkpieceError, match="both walls"):
        height_from_width(width, finger, np.array([np.nan, slope]))
