"""Eq. 9-12 (SVD / Umeyama): hand-computed cases, the uncertainty, refused input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.rigid import (
    geometry_defect,
    pair_residuals,
    perturb,
    perturbation,
    propagate,
    solve_rigid,
    umeyama,
)
from celld.errors import CalibrationError, InputError
from celld.se3 import apply, error, invert, transform_from

# Eq. 19, the paper's simulated camera.
T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])

# A tetrahedron of flange centres in the camera frame, metres.
TETRA_CAM = np.array([[0.0, 0.0, 0.5], [0.1, 0.0, 0.5], [0.0, 0.1, 0.5], [0.0, 0.0, 0.6]])


def test_eq10_to_12_on_a_hand_computed_tetrahedron() -> None:
    # Base = Eq. 19 applied to the tetrahedron, worked by hand:
    # (x, y, z) -> (0.6 - y, -0.0125 - x, 1 - z).
    P_base = np.array([[0.6, -0.0125, 0.5], [0.6, -0.1125, 0.5], [0.5, -0.0125, 0.5], [0.6, -0.0125, 0.4]])
    fit = solve_rigid(P_base, TETRA_CAM)
    np.testing.assert_allclose(fit.T_dst_src, T_BASE_CAM, atol=1e-12)
    assert fit.scale == 1.0
    np.testing.assert_allclose(fit.residuals, 0.0, atol=1e-12)
    assert fit.n_pairs == 4


def test_eq11_centroids_and_eq10b_translation() -> None:
    # Translation only: R = I, and t = mu_base - mu_cam (Eq. 10b with c = 1).
    t = np.array([0.3, -0.2, 0.1])
    R, t_hat, c = umeyama(TETRA_CAM + t, TETRA_CAM)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-12)
    assert c == 1.0


def test_eq11_scale_recovered_only_when_asked() -> None:
    R_true = Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix()
    P_base = 1.02 * TETRA_CAM @ R_true.T + [0.1, 0.2, 0.3]
    fit = solve_rigid(P_base, TETRA_CAM, with_scale=True)
    assert fit.scale == pytest.approx(1.02, abs=1e-12)
    np.testing.assert_allclose(fit.T_dst_src[:3, :3], R_true, atol=1e-12)
    np.testing.assert_allclose(fit.residuals, 0.0, atol=1e-12)
    rigid = solve_rigid(P_base, TETRA_CAM)
    assert rigid.scale == 1.0
    assert rigid.residuals.max() > 1e-4  # a 2 % scale error cannot be absorbed by a rigid fit


def test_eq12_sign_correction_never_returns_a_reflection() -> None:
    mirror = np.diag([1.0, 1.0, -1.0])
    P_base = TETRA_CAM @ mirror.T
    fit = solve_rigid(P_base, TETRA_CAM)
    assert np.linalg.det(fit.T_dst_src[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    assert fit.residuals.max() > 1e-3  # a mirror image is not a rigid motion


def test_residuals_are_per_pair_in_pair_order(rng: np.random.Generator) -> None:
    P_cam = rng.uniform(-0.15, 0.15, (10, 3)) + [0.0, 0.0, 0.55]
    P_base = apply(T_BASE_CAM, P_cam)
    P_base[7] += [0.0, 0.0, 0.01]
    fit = solve_rigid(P_base, P_cam)
    assert int(np.argmax(fit.residuals)) == 7
    np.testing.assert_allclose(fit.residuals, pair_residuals(fit.T_dst_src, P_base, P_cam))


def test_inputs_are_not_modified(rng: np.random.Generator) -> None:
    P_cam = rng.uniform(-0.1, 0.1, (6, 3)) + [0, 0, 0.5]
    P_base = apply(T_BASE_CAM, P_cam)
    a, b = P_base.copy(), P_cam.copy()
    solve_rigid(P_base, P_cam, with_scale=True)
    np.testing.assert_array_equal(P_base, a)
    np.testing.assert_array_equal(P_cam, b)


def test_covariance_predicts_the_spread_of_the_estimate() -> None:
    rng = np.random.default_rng(1)
    sigma = 0.001
    P_base = rng.uniform(-0.15, 0.15, (20, 3)) * [1, 1, 0.66] + [0.6, 0.0, 0.45]
    P_cam_true = apply(invert(T_BASE_CAM), P_base)
    xis, predicted = [], []
    for _ in range(400):
        fit = solve_rigid(P_base, P_cam_true + rng.normal(0.0, sigma, P_base.shape))
        xis.append(perturbation(fit.T_dst_src, T_BASE_CAM))
        predicted.append(np.sqrt(np.diag(fit.uncertainty.covariance)))
    empirical = np.std(xis, axis=0)
    # Per-axis std of rotation and translation within 15 % of the prediction
    # (400 samples: the sampling error of a std is about 4 %).
    np.testing.assert_allclose(empirical, np.mean(predicted, axis=0), rtol=0.15)
    assert fit.uncertainty.sigma == pytest.approx(sigma, rel=0.25)
    assert fit.uncertainty.dof == 3 * 20 - 6


def test_four_exact_pairs_have_no_redundancy_left_for_the_noise_estimate() -> None:
    # 12 equations, 6 unknowns: dof 6, the estimate exists but the residual is zero.
    fit = solve_rigid(apply(T_BASE_CAM, TETRA_CAM), TETRA_CAM)
    assert fit.uncertainty.dof == 6
    assert fit.uncertainty.sigma == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_fewer_than_four_pairs_are_refused(n: int) -> None:
    with pytest.raises(CalibrationError, match="at least 4 pairs"):
        solve_rigid(apply(T_BASE_CAM, TETRA_CAM[:n]), TETRA_CAM[:n])


def test_coplanar_positions_are_solved_exactly() -> None:
    # Eq. 10-12 with the determinant correction: Sigma has rank 2, and the sign
    # of its third direction is fixed by det(U) det(V), not left to chance.
    P_cam = np.array([[0.0, 0.0, 0.5], [0.1, 0.0, 0.5], [0.0, 0.1, 0.5], [0.1, 0.1, 0.5], [0.05, 0.02, 0.5]])
    assert geometry_defect(P_cam) is None
    fit = solve_rigid(apply(T_BASE_CAM, P_cam), P_cam)
    np.testing.assert_allclose(fit.T_dst_src, T_BASE_CAM, atol=1e-12)
    np.testing.assert_allclose(fit.residuals, 0.0, atol=1e-12)


def test_three_distinct_points_off_a_line_are_enough() -> None:
    P_cam = np.array([[0.0, 0.0, 0.5], [0.1, 0.0, 0.5], [0.0, 0.1, 0.5], [0.1, 0.0, 0.5]])  # one point twice
    fit = solve_rigid(apply(T_BASE_CAM, P_cam), P_cam)
    np.testing.assert_allclose(fit.T_dst_src, T_BASE_CAM, atol=1e-12)


def test_covariance_predicts_the_spread_of_a_coplanar_estimate() -> None:
    # A strip in a plane, 300 x 60 mm: rotation about the strip's long axis is
    # fixed five times worse than the others, and the covariance says so.
    rng = np.random.default_rng(2)
    sigma = 0.0002
    P_base = np.column_stack([rng.uniform(0.45, 0.75, 12), rng.uniform(-0.03, 0.03, 12), np.full(12, 0.45)])
    P_cam_true = apply(invert(T_BASE_CAM), P_base)
    xis, predicted = [], []
    for _ in range(400):
        fit = solve_rigid(P_base, P_cam_true + rng.normal(0.0, sigma, P_base.shape))
        xis.append(perturbation(fit.T_dst_src, T_BASE_CAM))
        predicted.append(np.sqrt(np.diag(fit.uncertainty.covariance)))
    empirical = np.std(xis, axis=0)
    np.testing.assert_allclose(empirical, np.mean(predicted, axis=0), rtol=0.15)
    rot = np.mean(predicted, axis=0)[:3]
    assert rot[0] > 3 * rot[1] and rot[0] > 3 * rot[2]  # about base x, the strip's long axis


def test_collinear_positions_are_refused_with_the_reason() -> None:
    P_cam = np.outer(np.linspace(0.0, 0.2, 5), [1.0, 0.5, 0.2]) + [0, 0, 0.5]
    with pytest.raises(CalibrationError, match="collinear.*rotation about the line is undetermined"):
        solve_rigid(apply(T_BASE_CAM, P_cam), P_cam)
    # Two distinct points are a line too.
    P_two = np.array([[0.0, 0.0, 0.5], [0.1, 0.0, 0.5], [0.0, 0.0, 0.5], [0.1, 0.0, 0.5]])
    with pytest.raises(CalibrationError, match="collinear"):
        solve_rigid(apply(T_BASE_CAM, P_two), P_two)


def test_a_set_a_few_microns_off_a_line_is_solved_with_its_true_conditioning(rng: np.random.Generator) -> None:
    # 5 um across a 200 mm line is not a rank defect: it solves, and the
    # covariance puts the rotation about the line tens of degrees loose.
    P_cam = np.outer(np.linspace(-0.1, 0.1, 6), [1.0, 0.0, 0.0]) + [0.0, 0.0, 0.5]
    P_cam[:, 1] += rng.uniform(-5e-6, 5e-6, 6)
    P_base = apply(T_BASE_CAM, P_cam) + rng.normal(0.0, 1e-4, (6, 3))
    fit = solve_rigid(P_base, P_cam)
    assert np.degrees(fit.uncertainty.rotation_error) > 5.0


def test_coincident_positions_are_refused() -> None:
    P = np.tile([0.6, 0.0, 0.4], (5, 1))
    with pytest.raises(CalibrationError, match="coincide"):
        solve_rigid(P, P)


def test_nearly_planar_but_thick_enough_sets_are_solved(rng: np.random.Generator) -> None:
    # 1 % out-of-plane spread is far above the 0.1 % refusal ratio.
    P_cam = np.column_stack([rng.uniform(-0.1, 0.1, (8, 2)), 0.5 + rng.uniform(-0.002, 0.002, 8)])
    assert geometry_defect(P_cam) is None
    fit = solve_rigid(apply(T_BASE_CAM, P_cam), P_cam)
    dt, dr = error(fit.T_dst_src, T_BASE_CAM)
    assert dt < 1e-9 and dr < 1e-9


def test_nan_is_refused_naming_the_pair() -> None:
    P_cam = TETRA_CAM.copy()
    P_cam[2, 1] = np.nan
    with pytest.raises(InputError, match=r"P_cam: pairs \[2\]"):
        solve_rigid(apply(T_BASE_CAM, TETRA_CAM), P_cam)


def test_mismatched_lengths_are_refused() -> None:
    with pytest.raises(InputError, match="same number of pairs, got 4 and 5"):
        solve_rigid(apply(T_BASE_CAM, TETRA_CAM), np.vstack([TETRA_CAM, [0, 0, 0.7]]))


def test_wrong_shape_is_refused() -> None:
    with pytest.raises(InputError, match=r"expected an \(n, 3\) array"):
        solve_rigid(np.zeros((4, 2)), TETRA_CAM)


def test_propagate_matches_sampling_for_a_composition(rng: np.random.Generator) -> None:
    A = transform_from(Rotation.from_rotvec([0.3, 0.1, -0.2]).as_matrix(), [0.2, 0.1, 0.5])
    B = transform_from(Rotation.from_rotvec([-0.1, 0.4, 0.2]).as_matrix(), [0.0, 0.3, 0.1])
    cov_a = np.diag([1e-6, 2e-6, 1e-6, 1e-8, 4e-8, 1e-8])
    cov_b = np.diag([3e-6, 1e-6, 1e-6, 2e-8, 1e-8, 9e-8])

    def f(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        return X @ invert(Y)

    cov = propagate(f, [A, B], [cov_a, cov_b])
    C = f(A, B)
    samples = [
        perturbation(f(perturb(A, rng.multivariate_normal(np.zeros(6), cov_a)), perturb(B, rng.multivariate_normal(np.zeros(6), cov_b))), C)
        for _ in range(1200)
    ]
    # Each entry within 0.12 of sqrt(C_ii C_jj) (1200 samples: sampling error about 0.03-0.04).
    scale = np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.max(np.abs(np.cov(np.array(samples).T) - cov) / scale) < 0.12
