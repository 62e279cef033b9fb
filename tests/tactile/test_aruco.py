"""Tag detection on rendered finger images: the configured id only, sub-pixel pose, quality gates."""

from __future__ import annotations

import numpy as np
import pytest

from celld.config import TactileConfig
from celld.errors import ConfigError, InputError
from celld.sim.srm import Imaging
from celld.tactile.aruco import TagDetector
from celld.tactile.sample import TactileStatus

from .conftest import Scene


def test_pose_of_the_rest_tag_matches_the_rendered_one(scene: Scene) -> None:
    det = scene.detect(np.zeros(3))
    assert det.status == TactileStatus.OK
    truth = scene.T_cam_tag(np.zeros(3))[:3, 3]
    # Lateral position to a few micrometres; depth to 0.05 mm (0.1 % at 40 mm).
    assert np.abs(det.p_cam[:2] - truth[:2]).max() < 1e-5
    assert abs(det.p_cam[2] - truth[2]) < 5e-5
    assert det.reprojection_px < 0.1
    assert det.other_ids == 0


def test_displacements_read_back_to_micrometres(scene: Scene) -> None:
    rng = np.random.default_rng(3)
    rest = np.mean([scene.detect(np.zeros(3)).p_cam for _ in range(5)], axis=0)
    err = []
    for _ in range(25):
        shift = np.array([rng.uniform(-1e-3, 1e-3), rng.uniform(-3e-3, 0.5e-3), rng.uniform(-1e-4, 1e-4)])
        det = scene.detect(shift)
        assert det.status == TactileStatus.OK
        err.append(scene.tool.R_tool_cam @ (det.p_cam - rest) - shift)
    err = np.abs(np.array(err))
    assert np.sqrt(np.mean(err[:, :2] ** 2)) < 12e-6
    assert err[:, :2].max() < 30e-6
    assert err[:, 2].max() < 40e-6


def test_another_tag_id_is_rejected_and_counted(cfg: TactileConfig) -> None:
    foreign = Scene(cfg, tag_id=17)
    det = foreign.detector.detect(foreign.image(np.zeros(3)))
    assert det.status == TactileStatus.WRONG_ID
    assert det.other_ids == 1
    assert np.all(np.isnan(det.p_cam))


def test_a_frame_without_the_tag_reports_no_tag(scene: Scene) -> None:
    det = scene.detector.detect(scene.renderer.render(None))
    assert det.status == TactileStatus.NO_TAG
    assert np.all(np.isnan(det.p_cam))


def test_sharpness_falls_with_blur_and_heavy_blur_is_flagged(scene: Scene) -> None:
    sharp = [scene.detect(np.zeros(3), Imaging(blur=b)).sharpness for b in (0.8, 1.5, 2.5)]
    assert sharp[0] > sharp[1] > sharp[2]
    # About 0.4 / sigma for a Gaussian blur of sigma px (plus the pixel's own width).
    assert sharp[1] == pytest.approx(0.4 / 1.5, rel=0.25)
    blurred = scene.detect(np.zeros(3), Imaging(blur=5.0))
    assert blurred.status in (TactileStatus.BLURRED, TactileStatus.NO_TAG)
    assert blurred.status != TactileStatus.OK


def test_lighting_changes_leave_the_position_alone(scene: Scene) -> None:
    shift = np.array([3e-4, 1.5e-3, 0.0])
    ref = scene.detect(shift).p_cam
    for imaging in (Imaging(gain=0.6), Imaging(gain=1.2, offset=10.0), Imaging(gradient=0.4, gradient_angle=0.7)):
        det = scene.detect(shift, imaging)
        assert det.status == TactileStatus.OK
        assert np.abs(det.p_cam[:2] - ref[:2]).max() < 15e-6


def test_translation_is_stable_where_the_face_on_rotation_flips(scene: Scene) -> None:
    # Tiny tilts either side of face-on: the IPPE rotation may jump, the
    # translation must not.
    from scipy.spatial.transform import Rotation

    from celld.se3 import transform_from

    positions = []
    for angle in (-0.004, 0.0, 0.004):
        T = scene.T_cam_tag(np.zeros(3)) @ transform_from(Rotation.from_rotvec([angle, angle, 0.0]).as_matrix(), np.zeros(3))
        det = scene.detector.detect(scene.renderer.render(T))
        assert det.status == TactileStatus.OK
        positions.append(det.p_cam)
    assert np.ptp(np.array(positions)[:, :2], axis=0).max() < 20e-6


def test_detector_refuses_bad_images_and_bad_config(scene: Scene) -> None:
    with pytest.raises(InputError, match="uint8"):
        scene.detector.detect(np.zeros((480, 640), np.float32))
    with pytest.raises(InputError, match="shape"):
        scene.detector.detect(np.zeros((480, 640, 4), np.uint8))
    with pytest.raises(ConfigError, match="dictionary"):
        TagDetector("DICT_NOPE", 7, 0.008, (600.0, 600.0, 320.0, 240.0))
    with pytest.raises(ConfigError, match="tag_id"):
        TagDetector("DICT_4X4_50", 60, 0.008, (600.0, 600.0, 320.0, 240.0))
    # A colour frame is accepted.
    bgr = np.repeat(scene.image(np.zeros(3))[:, :, None], 3, axis=2)
    assert scene.detector.detect(bgr).status == TactileStatus.OK
