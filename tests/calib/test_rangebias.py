"""The range bias on metal: its correction, its measurement in one capture, and the joint solve with T_base_cam."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.flange import preset
from celld.calib.metrics import model_cloud_with_normals
from celld.calib.rangebias import (
    FinishStep,
    RangeBiasData,
    bias_from_steps,
    correct_range_bias,
    measure_finish_step,
    solve_range_bias,
    solve_robust_range_bias,
)
from celld.calib.rigid import solve_rigid
from celld.errors import CalibrationError, InputError
from celld.se3 import apply, error, invert, transform_from

# The paper's Eq. 19: the camera 1 m above the base, looking down.
T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
BIAS = 0.008  # the simulated Azure Kinect's, m
WRIST = preset("ur10e-wrist")


def session(
    rng: np.random.Generator, n: int = 20, sigma: float = 0.5e-3, box: float = 0.3, on_metal: bool = False, step_sigma: float | None = 1e-4
) -> tuple[np.ndarray, np.ndarray, RangeBiasData]:
    """Flange centres in a box around (0.6, 0, 0.3) (0.7 m below the camera) as a time-of-flight camera reads them.

    Centres on metal read ``BIAS`` long along their rays; every pair has a
    finish step saying the bias to ``step_sigma`` (none when it is None).
    """
    P_base = rng.uniform(-0.5, 0.5, (n, 3)) * [box, box, 0.2] + [0.6, 0.0, 0.3]
    P_true = apply(invert(T_BASE_CAM), P_base)
    U = P_true / np.linalg.norm(P_true, axis=1, keepdims=True)
    P_cam = P_true + (BIAS * U if on_metal else 0.0) + rng.normal(0.0, sigma, (n, 3))
    if step_sigma is None:
        b, s = np.full(n, np.nan), np.full(n, np.nan)
    else:
        b, s = BIAS + rng.normal(0.0, step_sigma, n), np.full(n, step_sigma)
    return P_base, P_cam, RangeBiasData(on_metal, b, s)


# -- the model ----------------------------------------------------------------------


def test_the_correction_moves_each_point_back_along_its_own_ray() -> None:
    P_true = np.array([[0.1, -0.2, 0.7], [0.0, 0.0, 1.2], [np.nan, np.nan, np.nan]])
    U = P_true / np.linalg.norm(P_true, axis=1, keepdims=True)
    P_meas = P_true + BIAS * U
    before = P_meas.copy()
    out = correct_range_bias(P_meas, BIAS)
    np.testing.assert_allclose(out[:2], P_true[:2], atol=1e-15)
    assert np.isnan(out[2]).all()
    np.testing.assert_array_equal(P_meas, before)  # the input is not modified
    # Not a rigid translation: the two points move in different directions.
    assert np.degrees(np.arccos(np.clip(U[0] @ U[1], -1, 1))) > 10.0
    # Only the points on metal, an organized cloud keeps its shape.
    grid = np.stack([P_meas[:2], P_meas[:2]])
    corrected = correct_range_bias(grid, BIAS, mask=np.array([[True, False], [False, True]]))
    np.testing.assert_allclose(corrected[0, 0], P_true[0], atol=1e-15)
    np.testing.assert_array_equal(corrected[0, 1], P_meas[1])
    with pytest.raises(InputError, match="mask"):
        correct_range_bias(grid, BIAS, mask=np.ones(3, dtype=bool))
    with pytest.raises(InputError, match=r"\(\.\.\., 3\)"):
        correct_range_bias(np.zeros((4, 2)), BIAS)
    with pytest.raises(InputError, match="finite"):
        correct_range_bias(P_meas, math.nan)


def flange_cloud(T_cam_flange: np.ndarray, rng: np.random.Generator, sigma: float = 1.5e-3, flange=WRIST) -> np.ndarray:
    """The flange's surfaces that face the camera, seen by a time-of-flight camera: metal read BIAS long, noise along the rays."""
    P_flange, N_flange = model_cloud_with_normals(flange, 0.0012)
    P_flange = P_flange[N_flange[:, 2] > 0.9]  # face, bore and hole bottoms, shoulder
    metal = np.linalg.norm(P_flange[:, :2], axis=1) < flange.outer_diameter / 2 - 1e-6
    if flange.wrist_finish == "metal":
        metal[:] = True
    P = apply(T_cam_flange, P_flange)
    U = P / np.linalg.norm(P, axis=1, keepdims=True)
    return P + (BIAS * metal + rng.normal(0.0, sigma, len(P)))[:, None] * U


@pytest.mark.parametrize("tilt", [0.0, 0.25, 0.45])
def test_one_capture_measures_the_bias_from_the_face_over_the_painted_shoulder(rng: np.random.Generator, tilt: float) -> None:
    T_cam_flange = invert(T_BASE_CAM) @ transform_from(Rotation.from_rotvec([tilt, -0.5 * tilt, 0.3]).as_matrix(), [0.65, 0.1, 0.3])
    P = flange_cloud(T_cam_flange, rng)
    step = measure_finish_step(P, T_cam_flange[:3, 3], -T_cam_flange[:3, 2], WRIST)  # either sign of the axis
    assert isinstance(step, FinishStep)
    assert step.nominal == pytest.approx(0.0065)
    # The face reads b cos(theta) lower against the shoulder than the drawing's 6.5 mm.
    assert step.measured == pytest.approx(0.0065 - BIAS * step.cos_incidence, abs=4 * step.std + 5e-5)
    assert step.bias == pytest.approx(BIAS, abs=4 * step.bias_std + 5e-5)
    assert 0.0 < step.bias_std < 2e-4 and step.n_metal > 100 and step.n_painted > 100
    assert step.as_dict()["bias_mm"] == pytest.approx(step.bias * 1e3)


def test_no_finish_step_without_a_painted_shoulder_or_from_a_grazing_view(rng: np.random.Generator) -> None:
    T_cam_flange = invert(T_BASE_CAM) @ transform_from(np.eye(3), [0.6, 0.0, 0.3])
    bare = replace(WRIST, wrist_finish="metal")
    assert (
        bare.finish_step is None
        and measure_finish_step(flange_cloud(T_cam_flange, rng, flange=bare), T_cam_flange[:3, 3], T_cam_flange[:3, 2], bare) is None
    )
    flush = preset("iso9409-1-50-4-m6")  # the wrist no wider than the flange: no shoulder in view
    assert flush.finish_step is None
    grazing = invert(T_BASE_CAM) @ transform_from(Rotation.from_rotvec([1.35, 0.0, 0.0]).as_matrix(), [0.6, 0.0, 0.3])
    assert measure_finish_step(flange_cloud(grazing, rng), grazing[:3, 3], grazing[:3, 2], WRIST) is None
    # Too few points on a band (a capture that holds only the face).
    P = flange_cloud(T_cam_flange, rng)
    face_only = P[np.linalg.norm(P - T_cam_flange[:3, 3], axis=1) < 0.03]
    assert measure_finish_step(face_only, T_cam_flange[:3, 3], T_cam_flange[:3, 2], WRIST) is None


# -- the joint solve ------------------------------------------------------------------


def test_centres_on_paint_solve_as_eq9_and_the_steps_give_the_bias(rng: np.random.Generator) -> None:
    P_base, P_cam, data = session(rng)
    fit = solve_range_bias(P_base, P_cam, data)
    rigid = solve_rigid(P_base, P_cam)
    dt, dr = error(fit.T_base_cam, rigid.T_dst_src)
    assert dt < 1e-9 and dr < 1e-9  # the pairs say nothing about b: Eq. 9-12 as they are
    assert fit.bias == pytest.approx(BIAS, abs=4 * fit.bias_std)
    assert fit.bias_std == pytest.approx(1e-4 / math.sqrt(20), rel=0.35)
    assert math.isinf(fit.sigma_from_pairs) and fit.source == "steps"
    np.testing.assert_array_equal(fit.P_cam_corrected, P_cam)
    assert fit.as_dict()["std_mm"] == pytest.approx(fit.bias_std * 1e3)


def unbiased(P_base: np.ndarray, P_cam: np.ndarray) -> np.ndarray:
    """The oracle: Eq. 9-12 on the centres with the true bias taken out (the noise alone)."""
    return solve_rigid(P_base, correct_range_bias(P_cam, BIAS)).T_dst_src


def test_centres_on_metal_the_joint_solve_removes_the_bias_the_rigid_fit_absorbs(rng: np.random.Generator) -> None:
    P_base, P_cam, data = session(rng, on_metal=True)
    rigid = solve_rigid(P_base, P_cam).T_dst_src
    fit = solve_range_bias(P_base, P_cam, data)
    # Without the bias the camera lands about b off along its axis; with it, where the
    # noise alone puts it (the steps fix b to 0.02 mm).
    assert error(rigid, T_BASE_CAM)[0] > 0.6 * BIAS
    assert error(fit.T_base_cam, unbiased(P_base, P_cam))[0] < 0.1e-3
    assert fit.bias == pytest.approx(BIAS, abs=4 * fit.bias_std)
    assert fit.source == "steps+pairs"
    # Both kinds of information add: 1 / sigma^2 = 1 / sigma_pairs^2 + 1 / sigma_steps^2.
    combined = 1.0 / math.sqrt(fit.sigma_from_pairs**-2 + fit.sigma_from_steps**-2)
    assert fit.bias_std == pytest.approx(combined, rel=0.05)
    np.testing.assert_allclose(fit.P_cam_corrected, correct_range_bias(P_cam, fit.bias), atol=1e-15)


def test_the_pairs_alone_fix_the_bias_only_through_the_spread_of_the_rays() -> None:
    # Monte Carlo of the pairs-only solve (a bare-metal wrist: no finish step), 1 mm
    # centres, 20 pairs: the predicted 1-sigma is the spread of the estimates, and it
    # halves when the workspace is twice as wide (twice the spread of ray directions).
    axis_base = T_BASE_CAM[:3, 2]

    def run(box: float, seed: int) -> tuple[float, float, float]:
        rng = np.random.default_rng(seed)
        P_base, P_cam, data = session(rng, sigma=1e-3, box=box, on_metal=True, step_sigma=None)
        fit = solve_range_bias(P_base, P_cam, data)
        # The camera's error along its own axis, against where the noise alone puts it.
        along = float((fit.T_base_cam[:3, 3] - unbiased(P_base, P_cam)[:3, 3]) @ axis_base)
        return fit.bias, fit.sigma_from_pairs, along

    narrow = np.array([run(0.3, s) for s in range(150)])
    wide = np.array([run(0.6, 1000 + s) for s in range(150)])
    for runs in (narrow, wide):
        assert np.mean(runs[:, 0]) == pytest.approx(BIAS, abs=3 * np.std(runs[:, 0]) / math.sqrt(len(runs)))
        assert np.std(runs[:, 0]) == pytest.approx(np.mean(runs[:, 1]), rel=0.2)
    # Over a 0.3 m workspace at 0.7 m, about 1.2 mm: more than the 1 mm of a centre.
    assert 0.8e-3 < np.mean(narrow[:, 1]) < 1.6e-3
    assert np.mean(wide[:, 1]) / np.mean(narrow[:, 1]) == pytest.approx(0.5, abs=0.1)
    # The camera moves along its axis by the bias's error: a range offset left in the
    # centres is, near the axis, a shift of the camera.
    assert np.corrcoef(narrow[:, 0] - BIAS, narrow[:, 2])[0, 1] > 0.95
    assert np.std(narrow[:, 2]) == pytest.approx(np.std(narrow[:, 0]), rel=0.15)


def test_an_outlying_step_is_left_out_and_named(rng: np.random.Generator) -> None:
    P_base, P_cam, data = session(rng)
    data.step_bias[3] = BIAS + 0.004  # an occluded shoulder
    fit = solve_range_bias(P_base, P_cam, data, ids=[f"p{i}" for i in range(20)])
    assert [r.id for r in fit.rejected_steps] == ["p3"] and "p3" not in fit.step_ids
    assert fit.bias == pytest.approx(BIAS, abs=4 * fit.bias_std)


def test_the_robust_solve_leaves_a_false_detection_out(rng: np.random.Generator) -> None:
    P_base, P_cam, data = session(rng, on_metal=True)
    P_cam[5] += [0.03, -0.02, 0.01]  # another part of the arm taken for the flange
    rob, fit = solve_robust_range_bias(P_base, P_cam, data)
    assert [r.index for r in rob.rejected] == [5] and fit.n_pairs == 19
    keep = np.arange(20) != 5
    assert error(fit.T_base_cam, unbiased(P_base[keep], P_cam[keep]))[0] < 0.1e-3
    assert fit.bias == pytest.approx(BIAS, abs=4 * fit.bias_std)


def test_a_bias_nothing_observes_is_refused_and_bad_data_named(rng: np.random.Generator) -> None:
    P_base, P_cam, data = session(rng, step_sigma=None)
    with pytest.raises(CalibrationError, match="cannot be observed"):
        solve_range_bias(P_base, P_cam, data)
    with pytest.raises(InputError, match="steps"):
        solve_range_bias(P_base, P_cam, data.subset(range(10)))
    with pytest.raises(InputError, match="ids"):
        solve_range_bias(P_base, P_cam, session(rng)[2], ids=["a"])


def test_the_online_estimate_is_the_steps_median() -> None:
    steps = [FinishStep(0.0065 - 0.008 * 0.9, 0.0065, 1e-4, 0.9, 500, 700), None, FinishStep(-0.0016, 0.0065, 1e-4, 1.0, 500, 700)]
    assert bias_from_steps(steps) == pytest.approx((0.008 + 0.0081) / 2)
    assert bias_from_steps([None, None]) is None
