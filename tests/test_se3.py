"""SE(3) helpers against hand-computed cases."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from celld import se3
from celld.errors import InputError


def test_ur_pose_round_trip_and_known_value() -> None:
    T = se3.from_ur_pose([0.1, 0.2, 0.3, 0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(se3.apply(T, [[1.0, 0.0, 0.0]]), [[0.1, 1.2, 0.3]], atol=1e-12)
    np.testing.assert_allclose(se3.to_ur_pose(T), [0.1, 0.2, 0.3, 0.0, 0.0, math.pi / 2], atol=1e-12)


def test_ur_poses_in_one_go_are_each_pose_s_transform(rng: np.random.Generator) -> None:
    poses = np.column_stack([rng.normal(size=(5, 3)), rng.uniform(-2.0, 2.0, size=(5, 3))])
    np.testing.assert_allclose(se3.from_ur_poses(poses), [se3.from_ur_pose(p) for p in poses], atol=1e-12)
    assert se3.from_ur_poses(np.zeros((0, 6))).shape == (0, 4, 4)
    with pytest.raises(InputError, match=r"\(n, 6\)"):
        se3.from_ur_poses(np.zeros((3, 7)))


def test_invert_composes_to_identity(rng: np.random.Generator) -> None:
    T = se3.from_xyz_rpy(rng.normal(size=3), rng.uniform(-3, 3, size=3))
    np.testing.assert_allclose(T @ se3.invert(T), np.eye(4), atol=1e-12)


def test_error_of_a_known_offset() -> None:
    T = se3.from_xyz_rpy([0.6, -0.0125, 1.0], [math.pi, 0, -math.pi / 2])
    T2 = T @ se3.from_xyz_rpy([0.001, 0, 0], [0, 0, math.radians(0.5)])
    dt, dr = se3.error(T2, T)
    assert dt == pytest.approx(0.001)
    assert dr == pytest.approx(math.radians(0.5))


def test_quaternion_order_is_wxyz() -> None:
    T = se3.from_xyz_quat_wxyz([0, 0, 0], [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


@pytest.mark.parametrize(
    ("value", "message"),
    [(np.eye(3), "shape"), (np.full((4, 4), np.nan), "NaN"), (np.diag([2.0, 1, 1, 1]), "rotation")],
)
def test_check_transform_refuses_bad_input(value: np.ndarray, message: str) -> None:
    with pytest.raises(InputError, match=message):
        se3.check_transform(value)


def test_check_points_names_shape_and_nan() -> None:
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        se3.check_points(np.zeros((4, 2)))
    with pytest.raises(InputError, match="1 of 2 points"):
        se3.check_points([[0, 0, 0], [np.nan, 0, 0]])


def test_frame_from_z_is_right_handed() -> None:
    T = se3.frame_from_z([1, 2, 3], [0, 0, -1], x_hint=[1, 0, 0])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1])
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0])


def test_scipy_is_imported_by_the_rotation_functions_and_at_start_by_an_event_loop_user() -> None:
    # celld.se3 imports scipy's Rotation where it is used, so a config loads
    # without it; MotionHandle, whose state() runs in an event loop, imports it
    # when it is imported, not on the first state().
    probe = (
        "import sys\n"
        "import celld.se3, celld.config\n"
        "assert 'scipy' not in sys.modules, 'se3 or config imported scipy'\n"
        "import celld.motion.handle\n"
        "assert 'scipy.spatial.transform' in sys.modules, 'the motion handle did not import scipy'\n"
    )
    subprocess.run([sys.executable, "-c", probe], check=True, timeout=120)
