"""Eye-in-hand (Eq. 1, 3, 7) and eye-on-arm (Eq. 8) from flange centres and normals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.handeye import solve_eye_in_hand, solve_eye_on_arm
from celld.errors import CalibrationError, InputError
from celld.se3 import error, invert, transform_from

# The camera on the flange: 80 mm out, looking along the tool axis, tilted.
T_FLAN_CAM = transform_from(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), [0.03, -0.05, 0.08])
# A fixed feature (another robot's flange centre) in the base frame, facing up.
P_FEATURE = np.array([0.6, 0.1, 0.05])
N_FEATURE = np.array([0.0, 0.0, 1.0])


def eye_in_hand_data(rng: np.random.Generator, n: int, sigma: float, axes: str = "xyz") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flange poses around the feature and the feature seen from the camera (centre and normal)."""
    T, P, N = [], [], []
    for _ in range(n):
        rv = rng.normal(0.0, 0.3, 3) * [a in axes for a in "xyz"]
        R = Rotation.from_rotvec(rv).as_matrix() @ Rotation.from_euler("x", np.pi).as_matrix()
        T_bf = transform_from(R, P_FEATURE + [0.0, 0.0, 0.4] + rng.uniform(-0.1, 0.1, 3))
        T_cb = invert(T_bf @ T_FLAN_CAM)
        T.append(T_bf)
        P.append(T_cb[:3, :3] @ P_FEATURE + T_cb[:3, 3] + rng.normal(0.0, sigma, 3))
        N.append(T_cb[:3, :3] @ N_FEATURE)
    return np.array(T), np.array(P), np.array(N)


def test_eye_in_hand_recovers_exact_data(rng: np.random.Generator) -> None:
    T, P, _ = eye_in_hand_data(rng, 8, 0.0)
    fit = solve_eye_in_hand(T, P)
    dt, dr = error(fit.T_link_cam, T_FLAN_CAM)
    assert dt < 1e-9 and dr < 1e-9
    np.testing.assert_allclose(fit.p_base, P_FEATURE, atol=1e-9)
    # The closed form alone is already exact on exact data.
    assert error(fit.T_closed_form, T_FLAN_CAM)[0] < 1e-8
    np.testing.assert_allclose(fit.residuals, 0.0, atol=1e-9)


def test_eye_in_hand_with_noise_is_within_its_uncertainty() -> None:
    rng = np.random.default_rng(4)
    T, P, _N = eye_in_hand_data(rng, 15, 0.0002)
    fit = solve_eye_in_hand(T, P)
    dt, dr = error(fit.T_link_cam, T_FLAN_CAM)
    # Within 4 sigma of the predicted RMS errors, and the noise scale recovered.
    assert dt < 4 * fit.uncertainty.translation_error
    assert dr < 4 * fit.uncertainty.rotation_error
    assert fit.uncertainty.sigma == pytest.approx(0.0002, rel=0.4)
    assert len(fit.residuals) == 15 and fit.normal_residuals is None


def test_eye_in_hand_normals_let_four_poses_suffice(rng: np.random.Generator) -> None:
    T, P, N = eye_in_hand_data(rng, 4, 0.0)
    with pytest.raises(CalibrationError, match="at least 5 poses without normals"):
        solve_eye_in_hand(T, P)
    fit = solve_eye_in_hand(T, P, N)
    assert error(fit.T_link_cam, T_FLAN_CAM)[0] < 1e-8
    np.testing.assert_allclose(fit.n_base, N_FEATURE, atol=1e-8)
    np.testing.assert_allclose(fit.normal_residuals, 0.0, atol=1e-6)


def test_eye_in_hand_refuses_rotations_about_one_axis(rng: np.random.Generator) -> None:
    T, P, _ = eye_in_hand_data(rng, 10, 0.0, axes="z")
    with pytest.raises(CalibrationError, match="fewer than two axes"):
        solve_eye_in_hand(T, P)


def test_eye_in_hand_refuses_bad_input(rng: np.random.Generator) -> None:
    T, P, N = eye_in_hand_data(rng, 6, 0.0)
    with pytest.raises(InputError, match=r"expected shape \(6, 3\)"):
        solve_eye_in_hand(T, P[:5])
    P_nan = P.copy()
    P_nan[3, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        solve_eye_in_hand(T, P_nan)
    with pytest.raises(InputError, match=r"\(n, 4, 4\)"):
        solve_eye_in_hand(T[0], P)
    T_bad = T.copy()
    T_bad[2, :3, :3] *= 1.1
    with pytest.raises(InputError, match="not a rotation"):
        solve_eye_in_hand(T_bad, P)
    with pytest.raises(InputError, match="zero-length normals"):
        solve_eye_in_hand(T, P, np.zeros_like(N))


# -- Eq. 8: camera on an arm link, looking at the robot's own flange -------------

T_ARM_CAM = transform_from(Rotation.from_rotvec([1.0, 0.2, -0.3]).as_matrix(), [0.1, 0.0, 0.2])


def eye_on_arm_data(rng: np.random.Generator, n: int, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    Ta, Tf, P, N = [], [], [], []
    for _ in range(n):
        A = transform_from(Rotation.from_rotvec(rng.normal(0.0, 0.5, 3)).as_matrix(), rng.uniform(-0.2, 0.2, 3))
        F = A @ transform_from(
            Rotation.from_rotvec(rng.normal(0.0, 0.3, 3)).as_matrix(), np.array([0.4, 0.0, 0.0]) + rng.uniform(-0.1, 0.1, 3)
        )
        T_cf = invert(A @ T_ARM_CAM) @ F
        Ta.append(A)
        Tf.append(F)
        P.append(T_cf[:3, 3] + rng.normal(0.0, sigma, 3))
        N.append(T_cf[:3, 2])
    return np.array(Ta), np.array(Tf), np.array(P), np.array(N)


def test_eye_on_arm_recovers_exact_data(rng: np.random.Generator) -> None:
    Ta, Tf, P, N = eye_on_arm_data(rng, 6, 0.0)
    for normals in (None, N):
        fit = solve_eye_on_arm(Ta, Tf, P, normals)
        dt, dr = error(fit.T_link_cam, T_ARM_CAM)
        assert dt < 1e-9 and dr < 1e-9
        assert fit.p_base is None


def test_eye_on_arm_with_noise_is_within_its_uncertainty() -> None:
    rng = np.random.default_rng(8)
    Ta, Tf, P, _N = eye_on_arm_data(rng, 20, 0.0002)
    fit = solve_eye_on_arm(Ta, Tf, P)
    dt, dr = error(fit.T_link_cam, T_ARM_CAM)
    assert dt < 4 * fit.uncertainty.translation_error
    assert dr < 4 * fit.uncertainty.rotation_error


def test_eye_on_arm_solves_coplanar_and_refuses_collinear_flange_positions(rng: np.random.Generator) -> None:
    Ta, Tf, _, _ = eye_on_arm_data(rng, 6, 0.0)
    Ta[:] = np.eye(4)
    Tf[:, 2, 3] = 0.3  # every flange at the same height in the (fixed) arm frame: a plane fixes the rotation
    P = np.array([(invert(T_ARM_CAM) @ F)[:3, 3] for F in Tf])
    fit = solve_eye_on_arm(Ta, Tf, P)
    dt, dr = error(fit.T_link_cam, T_ARM_CAM)
    assert dt < 1e-9 and dr < 1e-9
    Tf[:, 1, 3] = 0.05  # and on one line: the rotation about it is undetermined
    P = np.array([(invert(T_ARM_CAM) @ F)[:3, 3] for F in Tf])
    with pytest.raises(CalibrationError, match="collinear"):
        solve_eye_on_arm(Ta, Tf, P)
    with pytest.raises(InputError, match="same number of poses"):
        solve_eye_on_arm(Ta[:5], Tf, P)
