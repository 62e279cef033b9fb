"""The loop's rotation-vector maps agree with scipy, near 0 and near pi too."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.motion import so3


def _rotvecs(rng: np.random.Generator) -> np.ndarray:
    axes = rng.normal(size=(300, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [
            rng.uniform(0.0, np.pi, 100),
            rng.uniform(0.0, 1e-5, 50),  # the small-angle series
            np.pi - rng.uniform(0.0, 1e-6, 50),  # next to pi: the symmetric-part branch
            np.pi - rng.uniform(0.0, 0.5, 100),
        ]
    )
    return axes * angles[:, None]


def test_exp_matches_scipy(rng: np.random.Generator) -> None:
    for r in _rotvecs(rng):
        np.testing.assert_allclose(so3.exp(r), Rotation.from_rotvec(r).as_matrix(), atol=1e-12)


def test_log_inverts_exp_and_matches_scipy(rng: np.random.Generator) -> None:
    for r in _rotvecs(rng):
        R = Rotation.from_rotvec(r).as_matrix()
        got = so3.log(R)
        # Near pi, r and -r describe nearly the same rotation: compare rotations, and
        # compare vectors where the angle leaves no ambiguity.
        assert np.linalg.norm(got) <= np.pi + 1e-12
        np.testing.assert_allclose(so3.exp(got), R, atol=1e-9)
        if np.linalg.norm(r) < np.pi - 1e-3:
            np.testing.assert_allclose(got, Rotation.from_matrix(R).as_rotvec(), atol=1e-9)


@pytest.mark.parametrize("axis", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0]])
def test_log_at_exactly_pi(axis: list[float]) -> None:
    k = np.asarray(axis) / np.linalg.norm(axis)
    R = Rotation.from_rotvec(np.pi * k).as_matrix()
    got = so3.log(R)
    assert np.linalg.norm(got) == pytest.approx(np.pi, abs=1e-9)
    assert abs(abs(got @ k) - np.pi) < 1e-9


def test_identity_is_zero() -> None:
    np.testing.assert_array_equal(so3.log(np.eye(3)), np.zeros(3))
    np.testing.assert_array_equal(so3.exp(np.zeros(3)), np.eye(3))
