"""Flange detection on ray-cast scenes with known truth, and on bad input."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from celld import se3
from celld.calib.detect import FlangeDetection, detect_flange, to_metres
from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
from celld.calib.flange import FlangeModel, preset
from celld.errors import DetectionError, InputError
from celld.sim.scanner import SCANNER_MODELS, OrganizedCloud, SceneObject, SimScanner, robot_scene
from celld.sim.scene import cylinder

# The paper's Eq. 19: the camera 1 m above the base, looking down.
T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
UR10E = preset("ur10e")


def calibration_pose(i: int) -> np.ndarray:
    """T_base_flange of the i-th seeded calibration pose: flange up, tilted up to 0.3 rad."""
    rng = np.random.default_rng(100 + i)
    xyz = [0.6 + rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), 0.45 + rng.uniform(-0.08, 0.08)]
    return se3.from_xyz_rpy(xyz, rng.uniform(-0.3, 0.3, 3))


def truth_in_camera(T_base_flange: np.ndarray, T_base_cam: np.ndarray = T_BASE_CAM) -> np.ndarray:
    return se3.invert(T_base_cam) @ T_base_flange


def roi_around(model_name: str, T_cam_flange: np.ndarray, half_size: float = 0.07) -> tuple[int, int, int, int]:
    """Pixel window of the full-resolution image around the flange (the scanner's ROI, set by the test)."""
    m = SCANNER_MODELS[model_name]
    x, y, z = T_cam_flange[:3, 3]
    u, v, h = m.fx * x / z + m.cx, m.fy * y / z + m.cy, m.fx * half_size / z
    return (max(int(v - h), 0), min(int(v + h), m.height_px), max(int(u - h), 0), min(int(u + h), m.width_px))


def capture(
    model_name: str,
    T_base_flange: np.ndarray,
    flange: FlangeModel = UR10E,
    seed: int = 0,
    T_base_cam: np.ndarray = T_BASE_CAM,
    clutter: int | None = 3,
) -> OrganizedCloud:
    """A full-resolution capture, ray cast only in a window around the flange (fast)."""
    roi = roi_around(model_name, truth_in_camera(T_base_flange, T_base_cam))
    scanner = SimScanner(model_name, T_base_cam, seed=seed, roi_px=roi)
    return scanner.capture(robot_scene(T_base_flange, flange, clutter_seed=clutter))


def centre_error(det: FlangeDetection, T_cam_flange: np.ndarray) -> float:
    return float(np.linalg.norm(det.center - T_cam_flange[:3, 3]))


@pytest.fixture(scope="module")
def phoxi_m_scenes() -> list[tuple[np.ndarray, OrganizedCloud]]:
    return [(truth_in_camera(calibration_pose(i)), capture("phoxi-m", calibration_pose(i), seed=i)) for i in range(3)]


@pytest.fixture(scope="module")
def full_scene() -> tuple[np.ndarray, OrganizedCloud]:
    """The whole quarter-resolution image: table, arm, clutter and the flange."""
    T = calibration_pose(0)
    cloud = SimScanner("phoxi-m", T_BASE_CAM, seed=1, resolution_scale=0.25).capture(robot_scene(T, UR10E, clutter_seed=5))
    return truth_in_camera(T), cloud


# -- accuracy against the truth ------------------------------------------------


def test_phoxi_m_centre_within_0_1_mm(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]]) -> None:
    for T_cam_flange, cloud in phoxi_m_scenes:
        det = detect_flange(cloud.points, UR10E)
        assert centre_error(det, T_cam_flange) < 1e-4
        # The normal is the flange +z, toward the camera.
        assert math.degrees(math.acos(min(1.0, det.normal @ T_cam_flange[:3, 2]))) < 0.05
        assert det.normal @ det.center < 0
        assert det.radius == pytest.approx(UR10E.circle_radius, abs=5e-4)
        assert det.coverage > 0.9 and det.inliers > 300 and det.residual < UR10E.circle_radius
        assert det.n_input == cloud.points.shape[0] * cloud.points.shape[1]


def test_phoxi_s_centre_within_0_1_mm() -> None:
    # PhoXi S sees 0.384-0.520 m over a narrow field: the camera 0.45 m above
    # the flange and over it, near the 0.442 m sweet spot.
    for i in (1, 2):
        T = calibration_pose(i)
        T_base_cam = T_BASE_CAM.copy()
        T_base_cam[:3, 3] = [T[0, 3] + 0.02, T[1, 3] - 0.03, T[2, 3] + 0.45]
        cloud = capture("phoxi-s", T, seed=i, T_base_cam=T_base_cam)
        det = detect_flange(cloud.points, UR10E)
        assert centre_error(det, truth_in_camera(T, T_base_cam)) < 1e-4


def test_full_scene_without_hints_finds_the_flange(full_scene: tuple[np.ndarray, OrganizedCloud]) -> None:
    T_cam_flange, cloud = full_scene
    det = detect_flange(cloud.points, UR10E)
    # Quarter resolution: 1 mm pixels at this range.
    assert centre_error(det, T_cam_flange) < 6e-4


def test_a_user_cropped_unorganized_cloud_works(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]]) -> None:
    T_cam_flange, cloud = phoxi_m_scenes[0]
    P = cloud.valid()
    crop = P[np.linalg.norm(P - T_cam_flange[:3, 3], axis=1) < 0.06]
    det = detect_flange(crop, UR10E)
    # Without the pixel grid the rim is cut with a plain slab: a little less accurate.
    assert centre_error(det, T_cam_flange) < 2e-4
    assert det.n_input == len(crop) and det.n_dropped == 0


def test_roi_center_restricts_the_search(full_scene: tuple[np.ndarray, OrganizedCloud]) -> None:
    T_cam_flange, cloud = full_scene
    near = detect_flange(cloud.points, UR10E, roi_center=T_cam_flange[:3, 3] + [0.01, -0.01, 0.005])
    assert centre_error(near, T_cam_flange) < 6e-4
    with pytest.raises(DetectionError):
        detect_flange(cloud.points, UR10E, roi_center=T_cam_flange[:3, 3] + [0.3, 0.0, 0.0])


def test_crop_box_that_misses_the_flange_fails_at_the_crop_or_later(full_scene: tuple[np.ndarray, OrganizedCloud]) -> None:
    _, cloud = full_scene
    params = DetectParams(crop_min=(-1.0, -1.0, 0.9), crop_max=(1.0, 1.0, 1.2))  # only the table
    with pytest.raises(DetectionError):
        detect_flange(cloud.points, UR10E, params)


def test_wrist_circle_preset_gives_the_face_centre(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]]) -> None:
    # The 90 mm circle lies 6.5 mm behind the face; the centre returned is still the face's.
    T_cam_flange, cloud = phoxi_m_scenes[1]
    det = detect_flange(cloud.points, preset("ur10e-wrist"))
    assert det.radius == pytest.approx(0.045, abs=1e-3)
    np.testing.assert_allclose(det.circle_center, T_cam_flange[:3, 3] - 0.0065 * T_cam_flange[:3, 2], atol=3e-4)
    assert centre_error(det, T_cam_flange) < 3e-4


def test_azure_kinect_on_a_painted_wrist_finds_the_true_centre_and_measures_the_metal_bias() -> None:
    # The simulated Azure Kinect reads metal 8 mm long. The 90 mm circle lies on the
    # painted wrist: its centre is not biased, and the metal face reads 8 mm lower
    # against the shoulder than the drawing's 6.5 mm, which is what measures the bias.
    T = se3.from_xyz_rpy([0.6, 0.0, 0.42], [0.1, -0.05, 0.2])
    cloud = SimScanner("azure-kinect", T_BASE_CAM, seed=0).capture(robot_scene(T, UR10E))
    det = detect_flange(cloud.points, preset("ur10e-wrist"), PARAMS_BY_SCANNER["azure-kinect"])
    truth = truth_in_camera(T)[:3, 3]
    assert np.linalg.norm(det.center - truth) < 1e-3
    step = det.finish_step
    assert step is not None and step.nominal == pytest.approx(0.0065)
    assert step.measured == pytest.approx(0.0065 - 0.008 * step.cos_incidence, abs=5e-4)
    assert step.bias == pytest.approx(SCANNER_MODELS["azure-kinect"].metal_bias, abs=5e-4)
    assert 0.0 < step.bias_std < 3e-4 and step.n_metal > 200 and step.n_painted > 200


def test_azure_kinect_on_a_bare_metal_wrist_reads_long_by_the_metal_bias() -> None:
    T = se3.from_xyz_rpy([0.6, 0.0, 0.42], [0.1, -0.05, 0.2])
    metal_wrist = replace(preset("ur10e-wrist"), wrist_finish="metal")
    cloud = SimScanner("azure-kinect", T_BASE_CAM, seed=0).capture(robot_scene(T, metal_wrist))
    det = detect_flange(cloud.points, metal_wrist, PARAMS_BY_SCANNER["azure-kinect"])
    truth = truth_in_camera(T)[:3, 3]
    ray = truth / np.linalg.norm(truth)
    err = det.center - truth
    along = float(err @ ray)
    # 8 mm of range bias on all of it: the detector sees it, it cannot remove it, and no step says it.
    assert 0.004 < along < 0.011
    assert np.linalg.norm(err - along * ray) < 0.003
    assert det.finish_step is None


def test_structured_light_measures_no_finish_step_bias(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]]) -> None:
    _, cloud = phoxi_m_scenes[1]
    det = detect_flange(cloud.points, UR10E)
    assert det.finish_step is not None
    assert det.finish_step.bias == pytest.approx(0.0, abs=2e-4)


def test_detection_is_deterministic(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]]) -> None:
    _, cloud = phoxi_m_scenes[2]
    a, b = detect_flange(cloud.points, UR10E), detect_flange(cloud.points, UR10E)
    np.testing.assert_array_equal(a.center, b.center)
    assert a.inliers == b.inliers


# -- a flange that is not there -------------------------------------------------


@pytest.mark.parametrize("name", ["iso9409-1-80-6-m8", "iso9409-1-31.5-4-m5"])
def test_a_preset_that_does_not_match_the_flange_is_refused(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]], name: str) -> None:
    _, cloud = phoxi_m_scenes[0]
    with pytest.raises(DetectionError):
        detect_flange(cloud.points, preset(name))


def test_a_scene_without_a_flange_is_refused() -> None:
    objects = [o for o in robot_scene(calibration_pose(0), UR10E, clutter_seed=2) if o.name not in ("flange", "wrist", "wrist3")]
    cloud = SimScanner("phoxi-m", T_BASE_CAM, resolution_scale=0.25).capture(objects)
    with pytest.raises(DetectionError):
        detect_flange(cloud.points, UR10E)


def test_a_solid_disc_of_the_flange_radius_is_not_a_flange() -> None:
    # A 31 mm cylinder top has the right rim but no centring bore.
    T = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.1, 0.0, 0.0])
    disc = SceneObject("puck", cylinder(UR10E.circle_radius, 0.03), T, "metal")
    cloud = SimScanner("phoxi-m", T_BASE_CAM, roi_px=roi_around("phoxi-m", truth_in_camera(T))).capture([disc])
    with pytest.raises(DetectionError, match="hollow"):
        detect_flange(cloud.points, UR10E)


def test_a_solid_disc_of_the_wrist_radius_is_not_a_wrist_under_tof_noise() -> None:
    # With a slab thick enough for ToF noise the bore cannot be seen empty:
    # the face must stand 6.5 mm above the shoulder instead.
    T = se3.from_xyz_rpy([0.6, 0.0, 0.42], [0.1, 0.0, 0.0])
    disc = SceneObject("puck", cylinder(0.045, 0.03), T, "metal")
    cloud = SimScanner("azure-kinect", T_BASE_CAM).capture([disc])
    with pytest.raises(DetectionError):
        detect_flange(cloud.points, preset("ur10e-wrist"), PARAMS_BY_SCANNER["azure-kinect"])


def test_a_cloud_with_no_returns_fails_at_the_crop() -> None:
    with pytest.raises(DetectionError) as info:
        detect_flange(np.full((40, 50, 3), np.nan, dtype=np.float32), UR10E)
    assert info.value.stage == "crop"


# -- bad input --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.empty((0, 3)), "empty"),
        (np.empty((0, 10, 3)), "empty"),
        (np.zeros((10, 2)), r"\(n, 3\)"),
        (np.array([["a", "b", "c"]]), "real numbers"),
        (np.full((5, 3), np.nan), "all 5 points are NaN"),
        (np.array([[0.0, 0.0, 0.5], [np.inf, 0.0, 0.5]]), "infinite"),
    ],
)
def test_malformed_clouds_are_refused(points: np.ndarray, message: str) -> None:
    with pytest.raises(InputError, match=message):
        detect_flange(points, UR10E)


def test_nan_rows_of_an_unorganized_cloud_are_dropped_and_counted(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]]) -> None:
    T_cam_flange, cloud = phoxi_m_scenes[0]
    P = cloud.valid()
    crop = P[np.linalg.norm(P - T_cam_flange[:3, 3], axis=1) < 0.06]
    with_nan = np.vstack([crop, np.full((123, 3), np.nan)])
    det = detect_flange(with_nan, UR10E)
    assert det.n_dropped == 123 and det.n_input == len(with_nan)
    np.testing.assert_allclose(det.center, detect_flange(crop, UR10E).center, atol=1e-12)


def test_millimetres_declared_as_metres_are_refused(phoxi_m_scenes: list[tuple[np.ndarray, OrganizedCloud]]) -> None:
    _, cloud = phoxi_m_scenes[0]
    with pytest.raises(InputError, match="millimetres"):
        detect_flange(cloud.points * 1000.0, UR10E)
    with pytest.raises(InputError, match="millimetres"):
        to_metres(cloud.points * 1000.0, "m")
    with pytest.raises(InputError, match="declared units 'mm'"):
        to_metres(cloud.points, "mm")
    # Converted at the boundary, the same data detect as before (the float32
    # round trip flips a few rim pixels: tens of micrometres, not more).
    P_m = to_metres(cloud.points * 1000.0, "mm")
    assert P_m.dtype == np.float32
    np.testing.assert_allclose(detect_flange(P_m, UR10E).center, detect_flange(cloud.points, UR10E).center, atol=5e-5)


def test_bad_arguments_are_refused() -> None:
    P = np.random.default_rng(0).uniform(0.4, 0.6, (100, 3))
    with pytest.raises(InputError, match="units"):
        to_metres(P, "inch")
    with pytest.raises(InputError, match="roi_center"):
        detect_flange(P, UR10E, roi_center=[0.0, np.nan, 0.5])
    with pytest.raises(InputError, match="FlangeModel"):
        detect_flange(P, "ur10e")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="e_d"):
        DetectParams(e_d=-1.0)
    with pytest.raises(InputError, match="crop_min"):
        DetectParams(crop_min=(0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="below crop_max"):
        DetectParams(crop_min=(0.0, 0.0, 1.0), crop_max=(1.0, 1.0, 0.5))


def test_per_scanner_parameters_cover_every_scanner_model() -> None:
    assert set(PARAMS_BY_SCANNER) == set(SCANNER_MODELS)
    tof = PARAMS_BY_SCANNER["azure-kinect"]
    assert tof.e_d > PARAMS_BY_SCANNER["phoxi-m"].e_d and replace(tof, seed=3).seed == 3
