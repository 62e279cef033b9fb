"""Depth image to organized cloud (pinhole unprojection through Open3D)."""

from __future__ import annotations

import numpy as np
import pytest

from celld.errors import InputError
from celld.scanner.depth import depth_to_points, intrinsic_matrix

K = intrinsic_matrix(500.0, 520.0, 31.5, 23.5)


def test_a_flat_depth_image_unprojects_to_the_pinhole_grid() -> None:
    depth = np.full((48, 64), 1200, dtype=np.uint16)  # 1.2 m in millimetres
    P = depth_to_points(depth, K, 1000.0, 0.1, 6.0)
    assert P.shape == (48, 64, 3) and P.dtype == np.float32
    np.testing.assert_allclose(P[..., 2], 1.2, rtol=1e-6)
    v, u = 10, 50
    np.testing.assert_allclose(P[v, u], [(u - 31.5) * 1.2 / 500.0, (v - 23.5) * 1.2 / 520.0, 1.2], rtol=1e-5)


def test_no_return_and_out_of_range_pixels_are_nan() -> None:
    depth = np.full((4, 5), 1000, dtype=np.uint16)
    depth[0, 0] = 0  # no return
    depth[1, 1] = 7000  # beyond depth_max
    depth[2, 2] = 50  # nearer than depth_min
    P = depth_to_points(depth, K, 1000.0, 0.1, 6.0)
    for v, u in ((0, 0), (1, 1), (2, 2)):
        assert np.isnan(P[v, u]).all()
    assert np.isfinite(P[3]).all()
    # A zero depth stays "no return" even with depth_min = 0.
    assert np.isnan(depth_to_points(depth, K, 1000.0, 0.0, 6.0)[0, 0]).all()


def test_float_metres_work_with_a_unit_scale() -> None:
    depth = np.full((3, 3), 0.8, dtype=np.float32)
    np.testing.assert_allclose(depth_to_points(depth, K, 1.0, 0.1, 6.0)[..., 2], 0.8)


def test_bad_images_and_intrinsics_are_refused() -> None:
    with pytest.raises(InputError, match="depth image"):
        depth_to_points(np.zeros((3, 3, 2), np.uint16), K, 1000.0, 0.1, 6.0)
    with pytest.raises(InputError, match="intrinsics"):
        depth_to_points(np.zeros((3, 3), np.uint16), np.eye(3) * 0.0, 1000.0, 0.1, 6.0)
    with pytest.raises(InputError, match="intrinsics"):
        intrinsic_matrix(-1.0, 500.0, 0.0, 0.0)
