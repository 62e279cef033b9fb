"""The simulated cell's scanner device: the scene is taken at capture time, from the robot's pose."""

from __future__ import annotations

import numpy as np
import pytest

from celld import se3
from celld.calib.flange import preset
from celld.config import ScannerConfig
from celld.errors import DeviceError, InputError
from celld.scanner import OrganizedCloud, Scanner
from celld.sim.scanner import SimScanner, SimulatedScanner, robot_scene, robot_scene_source

# The simulated cell's camera (the paper's Eq. 19) and a small image for speed.
T_BASE_CAM = np.array(ScannerConfig().T_base_cam)
SCALE = 0.1


@pytest.fixture(scope="module")
def flange():  # type: ignore[no-untyped-def]
    return preset("ur10e")


def test_each_capture_sees_the_flange_where_the_robot_is_now(flange) -> None:  # type: ignore[no-untyped-def]
    pose = {"T": se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0])}
    scanner = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: pose["T"], flange), seed=1, resolution_scale=SCALE)
    assert isinstance(scanner, Scanner)
    # The same scanner model and seed, given the scene at each pose by hand.
    reference = SimScanner("phoxi-m", T_BASE_CAM, seed=1, resolution_scale=SCALE)
    first = scanner.capture()
    assert isinstance(first, OrganizedCloud) and first.points.dtype == np.float32
    assert first.shape == (scanner.info()["height_px"], scanner.info()["width_px"])
    np.testing.assert_array_equal(first.points, reference.capture(robot_scene(pose["T"], flange)).points)
    pose["T"] = se3.from_xyz_rpy([0.55, 0.08, 0.40], [0.0, 0.0, 0.0])
    second = scanner.capture()
    np.testing.assert_array_equal(second.points, reference.capture(robot_scene(pose["T"], flange)).points)
    assert not np.array_equal(np.isfinite(first.points), np.isfinite(second.points))
    health = scanner.health()
    assert health["ok"] and health["captures"] == 2 and health["failures"] == 0
    scanner.close()
    with pytest.raises(DeviceError, match="after close"):
        scanner.capture()


def test_the_same_seed_and_scene_give_the_same_cloud(flange) -> None:  # type: ignore[no-untyped-def]
    T = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.1, -0.1, 0.3])
    a = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: T, flange), seed=4, resolution_scale=SCALE).capture()
    b = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: T, flange), seed=4, resolution_scale=SCALE).capture()
    np.testing.assert_array_equal(a.points, b.points)


def test_a_region_of_interest_casts_only_its_window(flange) -> None:  # type: ignore[no-untyped-def]
    T = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0])
    whole = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: T, flange), seed=2, resolution_scale=SCALE).capture()
    roi = (60, 100, 80, 130)  # around the flange, in pixels of the scaled image
    part = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: T, flange), seed=2, resolution_scale=SCALE, roi_px=roi)
    cloud = part.capture()
    assert cloud.shape == whole.shape and part.info()["width_px"] == whole.points.shape[1]
    inside = np.zeros(cloud.shape, dtype=bool)
    inside[roi[0] : roi[1], roi[2] : roi[3]] = True
    seen = np.isfinite(cloud.points[..., 2])
    assert not seen[~inside].any()
    # Inside the window it sees what the whole image sees there: the same pixels but for the random dropouts
    # at grazing angles, at the same depths but for the noise (two draws of it: 0.24 mm each on the table,
    # 1 m away, 0.1 mm on the flange).
    seen_whole = np.isfinite(whole.points[..., 2])
    assert seen[inside].sum() > 1000 and np.mean(seen[inside] != seen_whole[inside]) < 0.02
    both = seen & seen_whole
    assert float(np.sqrt(np.mean((cloud.points[both, 2] - whole.points[both, 2]) ** 2))) < 0.4e-3


def test_a_bad_pose_from_the_source_is_refused(flange) -> None:  # type: ignore[no-untyped-def]
    scanner = SimulatedScanner("phoxi-m", T_BASE_CAM, robot_scene_source(lambda: np.eye(3), flange), resolution_scale=SCALE)
    with pytest.raises(InputError, match="T_base_flange"):
        scanner.capture()
    assert scanner.health()["failures"] == 1


def test_the_units_own_error_and_exposure_delay(flange) -> None:  # type: ignore[no-untyped-def]
    import time

    from celld.sim.world import PRESETS, NominalCell, draw_world

    T = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0])
    exact = SimScanner("phoxi-m", T_BASE_CAM, seed=2, resolution_scale=SCALE).capture(robot_scene(T, flange)).points
    # The realistic world's unit: a depth scale and a smooth distortion, tenths of a millimetre.
    sc = draw_world(NominalCell(), PRESETS["realistic"], 3).scanner
    off = SimScanner("phoxi-m", T_BASE_CAM, seed=2, resolution_scale=SCALE, measure=sc.measure).capture(robot_scene(T, flange)).points
    ok = np.isfinite(exact[..., 2])
    np.testing.assert_array_equal(ok, np.isfinite(off[..., 2]))
    d = np.linalg.norm(off[ok] - exact[ok], axis=1)
    np.testing.assert_allclose(off[ok], sc.measure(exact[ok].astype(np.float64)), atol=2e-7)
    assert 1e-6 < np.median(d) < 0.5e-3
    # The exposure comes a while after the capture is asked for: the scene is what is in view then.
    pose = {"T": T}
    scanner = SimulatedScanner(
        "phoxi-m", T_BASE_CAM, robot_scene_source(lambda: pose["T"], flange), seed=1, resolution_scale=SCALE, capture_delay=(0.2, 0.2)
    )
    timer = __import__("threading").Timer(0.1, lambda: pose.__setitem__("T", se3.from_xyz_rpy([0.55, 0.08, 0.40], [0.0, 0.0, 0.0])))
    t0 = time.monotonic()
    timer.start()
    cloud = scanner.capture()
    assert time.monotonic() - t0 >= 0.2
    reference = SimScanner("phoxi-m", T_BASE_CAM, seed=1, resolution_scale=SCALE).capture(robot_scene(pose["T"], flange)).points
    np.testing.assert_array_equal(cloud.points, reference)
