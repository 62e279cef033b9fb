"""Robot-robot calibration by Eq. 6 (a), (b), (c)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.comanip import point_std, robots_through_camera, solve_comanipulation, solve_shared_camera
from celld.calib.rigid import Uncertainty, perturb
from celld.errors import CalibrationError, InputError
from celld.se3 import apply, error, invert, transform_from

# Robot 1 carries the camera on its flange; robot 2's base sits 1.2 m away, turned.
T_FLAN1_CAM = transform_from(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), [0.03, -0.05, 0.08])
T_BASE1_BASE2 = transform_from(Rotation.from_euler("z", np.pi - 0.1).as_matrix(), [1.2, 0.1, 0.02])
# Robot 2's flange during (a), face up, in its own base.
T_BASE2_FLAN2_A = transform_from(np.eye(3), [0.6, 0.05, 0.3])


def scene(rng: np.random.Generator, sigma: float, n_a: int = 10, n_b: int = 15):
    p_base1 = (T_BASE1_BASE2 @ T_BASE2_FLAN2_A)[:3, 3]
    Ta, Pa = [], []
    for _ in range(n_a):  # (a): robot 1 moves over robot 2's still flange
        R = Rotation.from_rotvec(rng.normal(0.0, 0.25, 3)).as_matrix() @ Rotation.from_euler("x", np.pi).as_matrix()
        T = transform_from(R, p_base1 + [0.0, 0.0, 0.5] + rng.uniform(-0.1, 0.1, 3))
        T_cb = invert(T @ T_FLAN1_CAM)
        Ta.append(T)
        Pa.append(T_cb[:3, :3] @ p_base1 + T_cb[:3, 3] + rng.normal(0.0, sigma, 3))
    T_fixed = Ta[0]
    T_base2_cam = invert(T_BASE1_BASE2) @ T_fixed @ T_FLAN1_CAM
    Tb, Pb = [], []
    for _ in range(n_b):  # (b): robot 1 still, robot 2 moves its flange under the camera
        F = transform_from(Rotation.from_rotvec(rng.normal(0.0, 0.2, 3)).as_matrix(), T_BASE2_FLAN2_A[:3, 3] + rng.uniform(-0.1, 0.1, 3))
        Tb.append(F)
        Pb.append((invert(T_base2_cam) @ F)[:3, 3] + rng.normal(0.0, sigma, 3))
    return np.array(Ta), np.array(Pa), T_fixed, np.array(Tb), np.array(Pb), T_base2_cam


def test_exact_data_give_the_three_transforms_and_a_closed_loop(rng: np.random.Generator) -> None:
    Ta, Pa, T_fixed, Tb, Pb, T_base2_cam = scene(rng, 0.0)
    fit = solve_comanipulation(Ta, Pa, T_fixed, Tb, Pb, T_base2_flan2_fixed_a=T_BASE2_FLAN2_A)
    for est, true in ((fit.T_flan1_cam, T_FLAN1_CAM), (fit.T_base2_cam, T_base2_cam), (fit.T_base1_base2, T_BASE1_BASE2)):
        dt, dr = error(est, true)
        assert dt < 1e-8 and dr < 1e-8
    assert fit.closure is not None and fit.closure < 1e-8


def test_noisy_data_stay_within_the_propagated_uncertainty() -> None:
    rng = np.random.default_rng(11)
    Ta, Pa, T_fixed, Tb, Pb, _ = scene(rng, 0.0002, n_a=15, n_b=25)
    fit = solve_comanipulation(Ta, Pa, T_fixed, Tb, Pb, T_base2_flan2_fixed_a=T_BASE2_FLAN2_A)
    dt, dr = error(fit.T_base1_base2, T_BASE1_BASE2)
    assert dt < 4 * fit.uncertainty.translation_error
    assert dr < 4 * fit.uncertainty.rotation_error
    # (c) composes two estimates: its uncertainty exceeds that of (b) alone.
    assert fit.uncertainty.translation_error > fit.eye_on_base.fit.uncertainty.translation_error
    assert fit.closure is not None and fit.closure < 0.002


def test_a_false_detection_in_b_is_rejected(rng: np.random.Generator) -> None:
    Ta, Pa, T_fixed, Tb, Pb, _ = scene(rng, 0.0001)
    Pb[4] += [0.03, 0.0, 0.0]
    fit = solve_comanipulation(Ta, Pa, T_fixed, Tb, Pb, ids_b=[f"b{i}" for i in range(len(Pb))])
    assert [r.id for r in fit.eye_on_base.rejected] == ["b4"]
    assert error(fit.T_base1_base2, T_BASE1_BASE2)[0] < 0.002
    assert fit.closure is None


def test_bad_input_is_refused(rng: np.random.Generator) -> None:
    Ta, Pa, T_fixed, Tb, Pb, _ = scene(rng, 0.0)
    with pytest.raises(CalibrationError, match="at least 4 pairs"):
        solve_comanipulation(Ta, Pa, T_fixed, Tb[:3], Pb[:3])
    with pytest.raises(InputError, match=r"\(m, 4, 4\)"):
        solve_comanipulation(Ta, Pa, T_fixed, Tb[:, :3], Pb)
    with pytest.raises(InputError, match="T_base1_flan1_fixed"):
        solve_comanipulation(Ta, Pa, np.eye(3), Tb, Pb)


def test_fixed_camera_seeing_both_flanges() -> None:
    rng = np.random.default_rng(2)
    T_base1_cam = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
    T_base2_cam = invert(T_BASE1_BASE2) @ T_base1_cam
    box = np.array([0.3, 0.3, 0.2])
    P1 = rng.uniform(-0.5, 0.5, (15, 3)) * box + [0.5, -0.2, 0.4]
    P2_b1 = rng.uniform(-0.5, 0.5, (15, 3)) * box + [0.7, 0.2, 0.4]  # robot 2's flange, seen in base 1
    P2 = (invert(T_BASE1_BASE2) @ np.c_[P2_b1, np.ones(15)].T).T[:, :3]
    cam1 = (invert(T_base1_cam) @ np.c_[P1, np.ones(15)].T).T[:, :3] + rng.normal(0.0, 0.0002, (15, 3))
    cam2 = (invert(T_base1_cam) @ np.c_[P2_b1, np.ones(15)].T).T[:, :3] + rng.normal(0.0, 0.0002, (15, 3))
    cam2[6] += [0.0, 0.04, 0.0]  # one false detection on robot 2
    fit = solve_shared_camera(P1, cam1, P2, cam2)
    assert [r.index for r in fit.robot2.rejected] == [6]
    dt, dr = error(fit.T_base1_base2, T_BASE1_BASE2)
    assert dt < 4 * fit.uncertainty.translation_error and dr < 4 * fit.uncertainty.rotation_error
    assert error(fit.T_base2_cam, T_base2_cam)[0] < 0.002


def test_a_point_where_the_robots_meet_takes_the_rotation_error_times_its_lever() -> None:
    # Monte Carlo of the composition's covariance, against point_std's first order.
    rng = np.random.default_rng(4)
    T_base1_cam = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
    T_base2_cam = invert(T_BASE1_BASE2) @ T_base1_cam
    cov = np.diag([3e-4, 2e-4, 1e-4, 1e-4, 2e-4, 1e-4]) ** 2
    unc = Uncertainty(cov, 1e-4, 30)
    T_b1b2, both = robots_through_camera(T_base1_cam, unc, T_base2_cam, unc)
    np.testing.assert_allclose(T_b1b2, T_BASE1_BASE2, atol=1e-12)
    p2 = np.array([0.65, 0.0, 0.45])
    samples = []
    for _ in range(4000):
        T1 = perturb(T_base1_cam, rng.multivariate_normal(np.zeros(6), cov))
        T2 = perturb(T_base2_cam, rng.multivariate_normal(np.zeros(6), cov))
        samples.append(apply(T1 @ invert(T2), p2[None])[0])
    np.testing.assert_allclose(point_std(T_b1b2, both, p2), np.std(samples, axis=0), rtol=0.08)
