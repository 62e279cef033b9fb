"""The finger's wall line beside a seam, and the weld's start pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import se3
from celld.errors import WorkpieceError
from celld.seam.weldpath import in_plane, model_geometry, start_pose, wall_offset, weld_geometry
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
