"""UR10e kinematics: known poses, inverse/forward round trips, Jacobian."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.errors import InputError
from celld.robot import kinematics as kin


def test_zero_pose_is_the_stretched_arm() -> None:
    # All joints at zero: the arm lies along -x of the base, offset by d4 + d6 in -y.
    T = kin.forward(np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [-0.6127 - 0.57155, -(0.17415 + 0.11655), 0.1807 - 0.11985], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


def test_home_pose_points_the_tool_down() -> None:
    q_home = [0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0]
    T = kin.forward(q_home)
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)
    # Upper arm up (-a2), forearm and wrist 2 offset along -x (a3, d5), wrist 1 offset d4
    # along -y, flange d6 below wrist 3.
    np.testing.assert_allclose(T[:3, 3], [-0.57155 - 0.11985, -0.17415, 0.1807 + 0.6127 - 0.11655], atol=1e-12)


def test_every_inverse_solution_maps_back_and_contains_the_original(rng: np.random.Generator) -> None:
    for _ in range(300):
        q = rng.uniform(-math.pi, math.pi, 6)
        T = kin.forward(q)
        sols = kin.inverse_all(T, q6_seed=q[5])
        assert len(sols) >= 2
        for s in sols:
            np.testing.assert_allclose(kin.forward(s), T, atol=1e-9)
        wrapped = np.angle(np.exp(1j * (sols - q)))
        assert np.min(np.max(np.abs(wrapped), axis=1)) < 1e-7


def test_inverse_picks_the_seed_configuration_and_whole_turns(rng: np.random.Generator) -> None:
    q = np.array([4.0, -1.2, 1.9, -2.3, -1.5, -5.0])  # base and wrist 3 beyond +-pi
    T = kin.forward(q)
    q_back = kin.inverse(T, q + rng.normal(0, 0.05, 6))
    assert q_back is not None
    np.testing.assert_allclose(q_back, q, atol=1e-9)


def test_tcp_offset_moves_along_the_flange_z() -> None:
    q = [0.3, -1.4, 1.6, -1.8, -1.5, 0.7]
    T_flange_tcp = np.eye(4)
    T_flange_tcp[2, 3] = 0.2
    T_flange = kin.forward(q)
    T_tcp = kin.forward(q, T_flange_tcp=T_flange_tcp)
    np.testing.assert_allclose(T_tcp[:3, 3], T_flange[:3, 3] + 0.2 * T_flange[:3, 2], atol=1e-12)


def test_out_of_reach_has_no_solution() -> None:
    T = np.eye(4)
    T[:3, 3] = [1.6, 0.0, 0.3]  # beyond a2 + a3 + wrist from the shoulder
    assert len(kin.inverse_all(T)) == 0
    assert kin.inverse(T, np.zeros(6)) is None


def test_wrist_singularity_keeps_the_seed_q6() -> None:
    q = np.array([0.2, -1.3, 1.5, -1.7, 0.0, 0.4])  # q5 = 0: q4 and q6 share an axis
    sols = kin.inverse_all(kin.forward(q), q6_seed=0.4)
    for s in sols:
        np.testing.assert_allclose(kin.forward(s), kin.forward(q), atol=1e-9)
    assert any(abs(s[5] - 0.4) < 1e-12 for s in sols)


def test_jacobian_matches_finite_differences(rng: np.random.Generator) -> None:
    q = rng.uniform(-2.0, 2.0, 6)
    J = kin.jacobian(q)
    eps = 1e-7
    T0 = kin.forward(q)
    for j in range(6):
        dq = q.copy()
        dq[j] += eps
        T1 = kin.forward(dq)
        np.testing.assert_allclose(J[:3, j], (T1[:3, 3] - T0[:3, 3]) / eps, atol=1e-6)
        w = Rotation.from_matrix(T1[:3, :3] @ T0[:3, :3].T).as_rotvec() / eps
        np.testing.assert_allclose(J[3:, j], w, atol=1e-6)


def test_limits_and_validation() -> None:
    assert kin.within_limits(np.zeros(6))
    assert not kin.within_limits([0, 0, 0, 0, 0, 6.5])
    with pytest.raises(InputError, match="6 joint angles"):
        kin.forward([0.0, 1.0])
    with pytest.raises(InputError, match="NaN"):
        kin.forward([0, 0, math.nan, 0, 0, 0])
