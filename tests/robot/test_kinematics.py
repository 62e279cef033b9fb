"""UR kinematics: known poses, inverse/forward round trips, Jacobian, every model and its limits."""

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


# -- every UR model ----------------------------------------------------------------

# Universal Robots' published DH lengths (d1, a2, a3, d4, d5, d6), m, typed here
# apart from the module's table so that a typo in either shows.
PUBLISHED = {
    "ur3": (0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819),
    "ur5": (0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
    "ur10": (0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922),
    "ur3e": (0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    "ur5e": (0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "ur10e": (0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    "ur16e": (0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
    "ur20": (0.2363, -0.862, -0.7287, 0.201, 0.1593, 0.1543),
    "ur30": (0.2363, -0.637, -0.5037, 0.201, 0.1593, 0.1543),
}
# Joint speeds from the user manuals, deg/s: base, shoulder, elbow, wrists.
SPEEDS_DEG_S = {
    "ur3": (180, 180, 180, 360), "ur3e": (180, 180, 180, 360),
    "ur5": (180, 180, 180, 180), "ur5e": (180, 180, 180, 180),
    "ur10": (120, 120, 180, 180), "ur10e": (120, 120, 180, 180), "ur16e": (120, 120, 180, 180),
    "ur20": (120, 120, 150, 210), "ur30": (120, 120, 150, 210),
}  # fmt: skip


def test_every_model_the_config_accepts_is_known() -> None:
    for name in ("ur10e", "ur5e", "ur5"):
        assert kin.model(name).name == name
    assert set(kin.MODELS) == set(PUBLISHED)
    with pytest.raises(InputError, match="expected one of ur3, .*got 'ur11'"):
        kin.model("ur11")


def test_defaults_stay_the_ur10e() -> None:
    assert kin.UR10E == kin.model("ur10e").dh
    assert kin.UR10E_LIMITS == kin.model("ur10e").limits


@pytest.mark.parametrize("name", sorted(PUBLISHED))
def test_zero_joints_stretch_the_arm_by_the_published_lengths(name: str) -> None:
    d1, a2, a3, d4, d5, d6 = PUBLISHED[name]
    T = kin.forward(np.zeros(6), kin.model(name).dh)
    # Along -x by the two link lengths, offset by d4 + d6 in -y, wrist 2 down by d5.
    np.testing.assert_allclose(T[:3, 3], [a2 + a3, -(d4 + d6), d1 - d5], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize("name", sorted(PUBLISHED))
def test_round_trip_for_every_model(name: str, rng: np.random.Generator) -> None:
    dh = kin.model(name).dh
    done = 0
    while done < 100:
        q = rng.uniform(-math.pi, math.pi, 6)
        if abs(math.sin(q[2])) < 0.1 or abs(math.sin(q[4])) < 0.1:
            continue  # near the elbow or wrist singularity the joints are not defined to 1e-7 by the pose
        done += 1
        T = kin.forward(q, dh)
        sols = kin.inverse_all(T, dh, q6_seed=q[5])
        for s in sols:
            np.testing.assert_allclose(kin.forward(s, dh), T, atol=1e-9)
        q_back = kin.inverse(T, q + rng.normal(0.0, 0.02, 6), dh, kin.model(name).limits)
        assert q_back is not None
        np.testing.assert_allclose(q_back, q, atol=1e-7)


@pytest.mark.parametrize("name", sorted(PUBLISHED))
def test_limits_of_every_model(name: str) -> None:
    limits = kin.model(name).limits
    np.testing.assert_allclose(limits.q_min, [-2 * math.pi] * 6)
    np.testing.assert_allclose(limits.q_max, [2 * math.pi] * 6)
    base, shoulder, elbow, wrist = SPEEDS_DEG_S[name]
    np.testing.assert_allclose(np.degrees(limits.qd_max), [base, shoulder, elbow, wrist, wrist, wrist])
    assert kin.within_limits([6.2, 0, 0, 0, 0, -6.2], limits)
    assert not kin.within_limits([0, 0, 0, 0, 6.3, 0], limits)


def test_forward_agrees_with_ur_analytic_ik(rng: np.random.Generator) -> None:
    # An independent implementation with its own copy of the published tables.
    ur_analytic_ik = pytest.importorskip("ur_analytic_ik")
    for name in PUBLISHED:
        dh = kin.model(name).dh
        for q in rng.uniform(-math.pi, math.pi, (50, 6)):
            np.testing.assert_allclose(kin.forward(q, dh), getattr(ur_analytic_ik, name).forward_kinematics(*q), atol=1e-12)


def test_batched_jacobian_matches_the_single_one(rng: np.random.Generator) -> None:
    Q = rng.uniform(-2.0, 2.0, (5, 6))
    frames = np.array([kin.forward_all_rows(q) for q in Q.tolist()]).reshape(5, 6, 3, 4)
    J = kin.jacobian_from_frames(frames)
    for i, q in enumerate(Q):
        np.testing.assert_allclose(J[i], kin.jacobian(q), atol=1e-12)
    with pytest.raises(InputError, match=r"expected \(n, 6, 3, 4\)"):
        kin.jacobian_from_frames(np.zeros((5, 6, 4, 4)))


def test_forward_batch_is_forward_all_rows_pose_by_pose() -> None:
    rng = np.random.default_rng(7)
    Q = rng.uniform(-math.pi, math.pi, (5, 6))
    dh = kin.DH(tuple(np.add(kin.UR10E.d, 1e-4)), kin.UR10E.a, tuple(np.add(kin.UR10E.alpha, 2e-4)))  # twists off pi/2 too
    F = kin.forward_batch(Q, dh)
    for i, q in enumerate(Q):
        rows = np.asarray(kin.forward_all_rows(q.tolist(), dh)).reshape(6, 3, 4)
        np.testing.assert_allclose(F[i, :, :3, :], rows, atol=1e-14)
        np.testing.assert_array_equal(F[i, :, 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (6, 4)))


def _controller_table(rng: np.random.Generator) -> kin.DH:
    """A controller's calibrated UR10e table: every length, twist and joint zero a millimetre or milliradian off."""
    rows = [np.asarray(row) + rng.normal(0.0, 1.5e-3, 6) for row in kin.UR10E[:3]]
    return kin.DH(*(tuple(r.tolist()) for r in rows), tuple(rng.normal(0.0, 2e-3, 6).tolist()))  # type: ignore[arg-type]


def _away_from_singularities(rng: np.random.Generator) -> np.ndarray:
    """Joints with the elbow bent, the wrist not straight and the wrist centre off the shoulder's cylinder."""
    while True:
        q = rng.uniform(-math.pi, math.pi, 6)
        p5 = kin.forward_all_rows(q.tolist())[4]
        if abs(math.sin(q[2])) > 0.2 and abs(math.sin(q[4])) > 0.2 and math.hypot(p5[3], p5[7]) > kin.UR10E.d[3] + 0.05:
            return q


def test_a_controllers_calibrated_table_is_solved_exactly_by_newton_from_its_ur_form(rng: np.random.Generator) -> None:
    dh = _controller_table(rng)
    assert kin.ur_form(dh) != dh and kin.ur_form(kin.UR10E) == kin.UR10E
    # The joint zeros turn each joint: theta is q's offset.
    q = rng.uniform(-math.pi, math.pi, 6)
    shifted = kin.DH(dh.d, dh.a, dh.alpha)
    np.testing.assert_allclose(kin.forward(q, dh), kin.forward(q + np.asarray(dh.theta), shifted), atol=1e-12)
    np.testing.assert_allclose(kin.forward_batch(q[None], dh)[0, 5], kin.forward(q, dh), atol=1e-12)
    for _ in range(100):
        q = _away_from_singularities(rng)
        T = kin.forward(q, dh)
        sols = kin.inverse_all(T, dh, float(q[5]))
        # Every solution is exact on the table itself (the closed form of its UR form is millimetres off) ...
        for s in sols:
            np.testing.assert_allclose(kin.forward(s, dh), T, atol=1e-9)
        assert np.linalg.norm(kin.forward(kin.inverse_all(T, kin.ur_form(dh), float(q[5]))[0], dh)[:3, 3] - T[:3, 3]) > 1e-4
        # ... the original is among them, and inverse() picks it from its neighbourhood.
        assert min(np.abs((s - q + math.pi) % (2 * math.pi) - math.pi).max() for s in sols) < 1e-8
        q_near = kin.inverse(T, q + 0.05, dh)
        assert q_near is not None and np.abs(q_near - q).max() < 1e-8
