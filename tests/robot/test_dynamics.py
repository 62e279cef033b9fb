"""Static joint torques against two independent rules: the potential energy's slope, and J^T F."""

from __future__ import annotations

import numpy as np
import pytest

from celld.robot import dynamics
from celld.robot import kinematics as kin

Q = np.array([[2.847, -1.401, 2.311, -2.481, 1.571, -1.276], [0.3, -2.0, 1.2, -0.4, -1.1, 0.7], [-1.0, -0.6, -1.9, 2.2, 0.4, 3.0]])
ARM = dynamics.links("ur10e")
PAYLOAD = dynamics.Payload(1.6, (0.01, -0.02, 0.09))


def _frames(q: np.ndarray) -> np.ndarray:
    return np.asarray(kin.forward_all_rows(q.tolist(), kin.UR10E)).reshape(1, 6, 3, 4)


def _potential(q: np.ndarray) -> float:
    """Gravity's potential energy of the links and the payload at joints ``q``, J."""
    F = [kin.matrix_from_rows(r) for r in kin.forward_all_rows(q.tolist(), kin.UR10E)]
    assert ARM is not None
    v = sum(m * dynamics.GRAVITY * (T @ [*c, 1.0])[2] for m, c, T in zip(ARM.mass, ARM.com, F))
    return float(v + PAYLOAD.mass * dynamics.GRAVITY * (F[5] @ [*PAYLOAD.com, 1.0])[2])


@pytest.mark.parametrize("q", Q)
def test_gravity_torque_is_minus_the_slope_of_the_potential(q: np.ndarray) -> None:
    tau = dynamics.joint_torques(_frames(q), ARM, PAYLOAD)[0]
    h = 1e-6
    slope = [(_potential(q + h * e) - _potential(q - h * e)) / (2 * h) for e in np.eye(6)]
    np.testing.assert_allclose(tau, -np.asarray(slope), atol=1e-5)
    assert abs(tau[0]) < 1e-9  # the base turns about the vertical: gravity has no say


@pytest.mark.parametrize("q", Q)
def test_a_force_on_the_tool_loads_the_joints_by_the_jacobian_transpose(q: np.ndarray) -> None:
    f, p = np.array([-6.0, 2.0, -11.0]), np.array([0.0, 0.0, 0.2])
    tau = dynamics.joint_torques(_frames(q), None, force=f, force_point=p)[0]
    T_flange_tcp = np.eye(4)
    T_flange_tcp[:3, 3] = p
    J = kin.jacobian(q, kin.UR10E, T_flange_tcp)
    np.testing.assert_allclose(tau, J[:3].T @ f, atol=1e-12)


def test_a_batch_is_its_poses_one_by_one() -> None:
    F = np.concatenate([_frames(q) for q in Q])
    batch = dynamics.joint_torques(F, ARM, PAYLOAD, [1.0, 2.0, 3.0], [0.0, 0.0, 0.1])
    for i, q in enumerate(Q):
        np.testing.assert_allclose(batch[i], dynamics.joint_torques(_frames(q), ARM, PAYLOAD, [1.0, 2.0, 3.0], [0.0, 0.0, 0.1])[0])
    assert dynamics.links("ur10") is None
