"""The simulated scanner adapter: the scene is taken at capture time, from the robot's pose."""

from __future__ import annotations

import numpy as np
import pytest

from celld import se3
from celld.calib.flange import preset
from celld.config import ScannerConfig
from celld.errors import DeviceError, InputError
from celld.scanner import OrganizedCloud, Scanner, open_scanner
from celld.scanner.sim import SimulatedScanner, robot_scene_source

# The simulated cell's camera (the paper's Eq. 19) and a small image for speed.
T_BASE_CAM = np.array(ScannerConfig().T_base_cam)
SCALE = 0.1


@pytest.fixture(scope="module")
def flange():  # type: ignore[no-untyped-def]
    return preset("ur10e")


def _flange_centre_in_cloud(cloud: OrganizedCloud) -> np.ndarray:
    on_flange = (cloud.labels == 0) & np.isfinite(cloud.points[..., 2])
    assert on_flange.sum() > 20
    return se3.apply(T_BASE_CAM, cloud.points[on_flange]).mean(axis=0)


def test_each_capture_sees_the_flange_where_the_robot_is_now(flange) -> None:  # type: ignore[no-untyped-def]
    pose = {"T": se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0])}
    scanner = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: pose["T"], flange), seed=1, resolution_scale=SCALE)
    assert isinstance(scanner, Scanner)
    first = scanner.capture()
    assert isinstance(first, OrganizedCloud) and first.points.dtype == np.float32
    assert first.shape == (scanner.info()["height_px"], scanner.info()["width_px"])
    c1 = _flange_centre_in_cloud(first)
    pose["T"] = se3.from_xyz_rpy([0.55, 0.08, 0.40], [0.0, 0.0, 0.0])
    c2 = _flange_centre_in_cloud(scanner.capture())
    # The flange face seen from above: its points' mean moves with the flange, within 2 mm
    # (the face is not fully symmetric in view: holes, the shadowed rim).
    np.testing.assert_allclose(c2[:2] - c1[:2], [-0.05, 0.08], atol=0.002)
    np.testing.assert_allclose(c2[2] - c1[2], -0.05, atol=0.002)
    health = scanner.health()
    assert health["ok"] and health["captures"] == 2 and health["failures"] == 0


def test_the_same_seed_and_scene_give_the_same_cloud(flange) -> None:  # type: ignore[no-untyped-def]
    T = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.1, -0.1, 0.3])
    a = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: T, flange), seed=4, resolution_scale=SCALE).capture()
    b = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: T, flange), seed=4, resolution_scale=SCALE).capture()
    np.testing.assert_array_equal(a.points, b.points)


def test_open_scanner_builds_the_simulated_scanner_from_config(flange) -> None:  # type: ignore[no-untyped-def]
    config = ScannerConfig(kind="sim", model="azure-kinect", seed=2, resolution_scale=0.2)
    T = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0])
    scanner = open_scanner(config, scene=robot_scene_source(lambda: T, flange))
    assert scanner.info()["model"] == "azure-kinect" and scanner.info()["width_px"] == 128
    assert scanner.capture().valid_count() > 0
    scanner.close()
    with pytest.raises(DeviceError, match="after close"):
        scanner.capture()
    with pytest.raises(InputError, match="scene source"):
        open_scanner(config)


def test_a_bad_pose_from_the_source_is_refused(flange) -> None:  # type: ignore[no-untyped-def]
    scanner = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: np.eye(3), flange), resolution_scale=SCALE)
    with pytest.raises(InputError, match="T_base_flange"):
        scanner.capture()
    assert scanner.health()["failures"] == 1
