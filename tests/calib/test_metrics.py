"""e_icp (Eq. 13), the cost metrics of section 4.2 and the compensation of Eq. 21."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.flange import preset
from celld.calib.metrics import (
    IcpMetric,
    IcpParams,
    IcpVerifier,
    compensate,
    cost_function,
    model_cloud_with_normals,
    se3_cost,
    translation_cost,
)
from celld.errors import CalibrationError, InputError
from celld.se3 import apply, error, invert, transform_from

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
# Verification pose: flange face up towards the camera, slightly tilted.
T_BASE_FLAN_V = transform_from(Rotation.from_rotvec([0.1, -0.05, 0.3]).as_matrix(), [0.6, 0.02, 0.45])


def metric(rotvec: list[float], t: list[float]) -> IcpMetric:
    return IcpMetric(transform_from(Rotation.from_rotvec(rotvec).as_matrix(), t), True, 1.0, 0.0)


def test_translation_cost_is_the_norm_of_the_translation() -> None:
    e = metric([0.01, 0.0, 0.0], [0.003, 0.004, 0.0])
    assert translation_cost(e) == pytest.approx(0.005, abs=1e-15)


def test_se3_cost_weighs_roll_pitch_yaw_with_the_work_radius() -> None:
    # (dx, dy, dz) = (3, 4, 0) mm and a yaw of 0.01 rad at r = 0.5 m: 5 mm of
    # the rotation, so |(3, 4, 0, 0, 0, 5)| = sqrt(50) mm.
    e = metric([0.0, 0.0, 0.01], [0.003, 0.004, 0.0])
    np.testing.assert_allclose(e.rpy, [0.0, 0.0, 0.01], atol=1e-15)
    assert se3_cost(e, 0.5) == pytest.approx(math.sqrt(50) * 1e-3, rel=1e-12)
    assert cost_function("se3", 0.5)(e) == se3_cost(e, 0.5)
    assert cost_function("translation")(e) == translation_cost(e)


def test_failed_icp_costs_infinity() -> None:
    e = IcpMetric.failed("no correspondences")
    assert translation_cost(e) == math.inf
    assert se3_cost(e, 0.5) == math.inf
    assert np.all(np.isinf(e.translation)) and np.all(np.isinf(e.rpy))
    assert e.as_dict() == {"ok": False, "reason": "no correspondences", "fitness": 0.0}


def test_cost_function_refuses_unknown_names_and_bad_radius() -> None:
    with pytest.raises(InputError, match="translation, se3"):
        cost_function("rotation")
    with pytest.raises(InputError, match="work_radius"):
        cost_function("se3", 0.0)


def test_eq21_compensation_is_the_product_of_the_estimate_and_e_icp() -> None:
    H = transform_from(Rotation.from_rotvec([0.0, 0.0, 0.002]).as_matrix(), [0.601, -0.012, 1.0]) @ T_BASE_CAM
    e = metric([0.001, -0.002, 0.0], [0.0005, 0.0, -0.001])
    np.testing.assert_allclose(compensate(H, e), H @ e.T_camhat_cam, atol=1e-15)
    with pytest.raises(CalibrationError, match="e_icp is infinite"):
        compensate(H, IcpMetric.failed("fitness 0.1"))


@pytest.fixture(scope="module")
def ur10e_model() -> tuple[np.ndarray, np.ndarray]:
    return model_cloud_with_normals(preset("ur10e"), 0.001)


@pytest.fixture(scope="module")
def verification_cloud(ur10e_model: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The flange surface seen by the camera at the verification pose (independent samples, 0.05 mm noise)."""
    rng = np.random.default_rng(5)
    surface = preset("ur10e").model_cloud(0.0007)
    pts = surface[rng.choice(len(surface), 4000, replace=False)]
    return apply(invert(T_BASE_CAM) @ T_BASE_FLAN_V, pts) + rng.normal(0.0, 5e-5, (4000, 3))


def test_e_icp_of_the_true_transform_is_near_identity(ur10e_model, verification_cloud) -> None:
    P, N = ur10e_model
    verifier = IcpVerifier(verification_cloud, P, T_BASE_FLAN_V, IcpParams(max_points=3000), normals_flange=N)
    e = verifier(T_BASE_CAM)
    assert e.ok and e.fitness > 0.9
    # The registration of one small flange: about 0.1 mm at the camera origin
    # and a few hundredths of a degree, mostly about the flange axis (only the
    # holes fix that rotation).
    assert translation_cost(e) < 2e-4
    assert np.degrees(np.linalg.norm(e.rpy)) < 0.1


def test_e_icp_measures_the_error_of_an_estimate_and_eq21_removes_it(ur10e_model, verification_cloud) -> None:
    P, N = ur10e_model
    verifier = IcpVerifier(verification_cloud, P, T_BASE_FLAN_V, IcpParams(max_points=3000).strict(), normals_flange=N)
    # The estimate's camera frame {Cam'} is off by 1 mm and 0.21 deg.
    T_cam_camhat = transform_from(Rotation.from_rotvec(np.radians([0.15, -0.15, 0.0])).as_matrix(), [0.0006, -0.0008, 0.0])
    estimate = T_BASE_CAM @ T_cam_camhat
    assert error(estimate, T_BASE_CAM)[0] == pytest.approx(0.001)
    e = verifier(estimate)
    assert e.ok
    # e_icp = T_cam'_cam = inverse of the error put in, to ICP's accuracy.
    dt, dr = error(e.T_camhat_cam, invert(T_cam_camhat))
    assert dt < 2e-4 and np.degrees(dr) < 0.02
    dt, dr = error(compensate(estimate, e), T_BASE_CAM)
    assert dt < 2e-4 and np.degrees(dr) < 0.02


def test_icp_fails_when_the_estimate_misplaces_the_model(ur10e_model, verification_cloud) -> None:
    P, N = ur10e_model
    verifier = IcpVerifier(verification_cloud, P, T_BASE_FLAN_V, normals_flange=N)
    e = verifier(T_BASE_CAM @ transform_from(np.eye(3), [0.05, 0.0, 0.0]))
    assert not e.ok
    assert translation_cost(e) == math.inf
    assert "mm of the placed model" in e.reason or "fitness" in e.reason
    assert not verifier(np.full((4, 4), np.nan)).ok


def test_verifier_refuses_bad_clouds(ur10e_model) -> None:
    P, N = ur10e_model
    with pytest.raises(InputError, match="P_v_cam"):
        IcpVerifier(np.zeros((5, 3)), P, T_BASE_FLAN_V)
    with pytest.raises(InputError, match="normals_flange"):
        IcpVerifier(P[:100], P, T_BASE_FLAN_V, normals_flange=N[:10])
    with pytest.raises(InputError, match="T_base_flange_v"):
        IcpVerifier(P[:100], P, np.eye(3))
    with pytest.raises(InputError, match="max_distances"):
        IcpParams(max_distances=())


def test_model_normals_are_unit_and_outward_on_the_face(ur10e_model) -> None:
    P, N = ur10e_model
    np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-6)
    on_face = (np.abs(P[:, 2]) < 1e-6) & (np.linalg.norm(P[:, :2], axis=1) < 0.029) & (np.linalg.norm(P[:, :2], axis=1) > 0.017)
    assert on_face.sum() > 100
    assert np.mean(N[on_face, 2] > 0.99) > 0.95
