"""The simulated part: as made (distorted off its model), as placed, and its true finger wall."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import se3
from celld.seam.workpiece import example
from celld.sim.workpiece import _model_stations, distorted_groove, nominal_pose, on_table, true_part
from celld.sim.world import PartShape, PartTruth


def _in_plane(part, P: np.ndarray) -> np.ndarray:
    T = part.T_base_plane
    return (P - T[:3, 3]) @ T[:3, :3]


def test_the_wall_of_a_straight_groove_leans_with_its_bevel() -> None:
    wp = example("v-groove")
    part = on_table(wp, _model_stations(wp), nominal_pose(wp), "left")
    S = _in_plane(part, part.seam_base)
    half_gap, tan = wp.params["root_gap"] / 2.0, math.tan(wp.params["groove_angle"] / 2.0)
    for k, h in enumerate(part.wall.heights):
        # Left of travel (plane +y), b/2 + h tan(a/2) beside the root line, at every station.
        np.testing.assert_allclose(part.wall.lines[k][:, 1] - S[:, 1], half_gap + h * tan, atol=1e-6)
    np.testing.assert_allclose(part.wall.root_z, 0.0, atol=1e-9)
    assert part.wall.free == -1.0
    # The finger meets the wall at the height of its tip.
    w4 = part.wall.at(np.array([0.05, 0.0, 0.004]))
    np.testing.assert_allclose(w4.P[:, 1] - S[:, 1], half_gap + 0.004 * tan, atol=1e-6)
    w5 = part.wall.at(np.array([0.05, 0.0, 0.00525]))
    np.testing.assert_allclose(w5.P[:, 1] - S[:, 1], half_gap + 0.00525 * tan, atol=1e-6)


def test_an_undistorted_part_is_the_model_at_its_place() -> None:
    T_place = nominal_pose(example("v-groove"))
    part = true_part(PartTruth("v-groove", T_place, (0.0, 0.0), 0.0, PartShape(bow=0.001)), "left")
    np.testing.assert_allclose(part.T_base_obj, T_place)
    seam = se3.apply(part.T_base_obj, part.workpiece.seam)
    # The model's own bow (the shipped generator's), 1 mm at mid-length.
    assert np.ptp(_in_plane(part, seam)[:, 1]) == pytest.approx(0.001, abs=2e-6)


def test_a_distorted_groove_bows_twists_and_varies_its_gap() -> None:
    shape = PartShape(
        bow=0.002, bow_vertical=0.001, twist=math.radians(1.0), tacks=((0.5, 0.0003),), gap_amplitude=0.0003, gap_waves=1.0, gap_phase=0.0
    )
    wp, st = distorted_groove("v-groove", shape)
    mid = len(st.seam) // 2
    # Sideways: the bow plus the tack's kink at mid-length; up: the vertical bow (on top of the root face).
    assert st.seam[mid, 1] == pytest.approx(0.0023, abs=1e-5)
    assert st.seam[mid, 2] - st.seam[0, 2] == pytest.approx(0.001, abs=2e-5)
    # The twist turns the joint by 1 degree from end to end.
    tilt = np.degrees(np.arctan2(st.up[:, 1], st.up[:, 2]))
    assert tilt[-1] - tilt[0] == pytest.approx(-1.0, abs=0.05)
    # Without the twist, the root gap's variation alone: it opens by 0.3 mm at mid-length
    # (one half sine) and the left wall moves out by half of it.
    wp, st = distorted_groove("v-groove", PartShape(bow=0.002, gap_amplitude=0.0003, gap_waves=1.0))
    part = on_table(wp, st, nominal_pose(example("v-groove")), "left")
    S = _in_plane(part, part.seam_base)
    k = int(np.searchsorted(part.wall.heights, 0.004))
    off = np.linalg.norm(part.wall.lines[k] - S[:, :2], axis=1)
    assert off[len(off) // 2] - off[0] == pytest.approx(0.00015, abs=2e-5)


def test_a_placed_part_lies_on_the_table_off_its_place() -> None:
    T_place = nominal_pose(example("v-groove"))
    truth = PartTruth("v-groove", T_place, (0.01, -0.02), math.radians(3.0), PartShape(bow=0.0, bow_vertical=0.001))
    part = true_part(truth, "left")
    np.testing.assert_allclose(part.T_base_obj[:2, 3], T_place[:2, 3] + [0.01, -0.02], atol=1e-12)
    assert se3.error(part.T_base_obj, T_place)[1] == pytest.approx(math.radians(3.0), abs=1e-9)
    assert se3.apply(part.T_base_obj, part.workpiece.vertices)[:, 2].min() == pytest.approx(0.0, abs=1e-12)
