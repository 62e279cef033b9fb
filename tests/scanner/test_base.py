"""The organized cloud value and the unit and no-return conversion at the driver boundary."""

from __future__ import annotations

import numpy as np
import pytest

from celld.errors import InputError
from celld.scanner import OrganizedCloud, check_organized


def test_millimetres_become_metres_and_zero_triplets_become_nan() -> None:
    raw = np.array([[[100.0, -50.0, 650.0], [0.0, 0.0, 0.0]], [[0.0, 0.0, 700.0], [np.nan, 1.0, 2.0]]])
    P = check_organized(raw, "test", scale=1e-3)
    assert P.dtype == np.float32 and P.shape == (2, 2, 3)
    np.testing.assert_allclose(P[0, 0], [0.1, -0.05, 0.65], rtol=1e-6)
    np.testing.assert_allclose(P[1, 0], [0.0, 0.0, 0.7], rtol=1e-6)  # one zero coordinate is a real point
    assert np.isnan(P[0, 1]).all() and np.isnan(P[1, 1]).all()
    assert raw[0, 1, 2] == 0.0  # the input is not modified


def test_shapes_types_and_infinities_are_refused_with_the_source_name() -> None:
    with pytest.raises(InputError, match=r"cam0: expected an organized \(H, W, 3\) cloud, got shape \(10, 3\)"):
        check_organized(np.zeros((10, 3)), "cam0")
    with pytest.raises(InputError, match="numeric"):
        check_organized(np.zeros((2, 2, 3), dtype=bool), "cam0")
    bad = np.ones((2, 2, 3))
    bad[1, 1, 2] = np.inf
    with pytest.raises(InputError, match="cam0: 1 pixels hold infinite"):
        check_organized(bad, "cam0")


def test_valid_points_are_the_finite_pixels_in_row_major_order() -> None:
    P = np.full((2, 3, 3), np.nan, dtype=np.float32)
    P[0, 2] = [1.0, 2.0, 3.0]
    P[1, 0] = [4.0, 5.0, 6.0]
    cloud = OrganizedCloud(points=P, stamp_ns=7)
    assert cloud.shape == (2, 3) and cloud.valid_count() == 2
    np.testing.assert_array_equal(cloud.valid(), [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
