"""Calibration pose generation: inside the box, within the tilt, never degenerate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.calib.poses import calibration_poses
from celld.calib.rigid import geometry_defect
from celld.errors import InputError
from celld.se3 import transform_from

T_V = transform_from(np.eye(3), [0.6, 0.0, 0.45])


def test_poses_fill_the_box_within_the_tilt_bound() -> None:
    T = calibration_poses(T_V, [0.3, 0.3, 0.2], 20, 0.3, seed=1)
    assert T.shape == (20, 4, 4)
    offset = T[:, :3, 3] - T_V[:3, 3]
    assert np.all(np.abs(offset) <= np.array([0.15, 0.15, 0.1]) + 1e-12)
    tilt = np.degrees(np.arccos(np.clip(T[:, 2, 2], -1, 1)))
    assert tilt.max() <= math.degrees(0.3) + 1e-9
    assert geometry_defect(T[:, :3, 3]) is None
    for Ti in T:
        np.testing.assert_allclose(Ti[:3, :3] @ Ti[:3, :3].T, np.eye(3), atol=1e-12)


def test_poses_are_deterministic_for_a_seed() -> None:
    a = calibration_poses(T_V, [0.3, 0.3, 0.2], 8, 0.3, seed=4)
    b = calibration_poses(T_V, [0.3, 0.3, 0.2], 8, 0.3, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, calibration_poses(T_V, [0.3, 0.3, 0.2], 8, 0.3, seed=5))


@pytest.mark.parametrize(
    ("box", "n", "tilt", "match"),
    [([0.3, 0.3], 8, 0.3, "edge lengths"), ([0.3, 0.3, 0.2], 3, 0.3, "at least 4"), ([0.3, 0.3, 0.2], 8, 2.0, "max_tilt")],
)
def test_bad_arguments_are_refused(box: list, n: int, tilt: float, match: str) -> None:
    with pytest.raises(InputError, match=match):
        calibration_poses(T_V, box, n, tilt)
