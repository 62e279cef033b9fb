"""Deformation from the tag: Eq. 15's sign, tare, contact state with hysteresis, invalid samples."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.errors import InputError, TactileError
from celld.tactile.deformation import (
    DeformationParams,
    confidence,
    contact_state,
    deformation_tool,
    estimate,
    invalid_sample,
    tare,
)
from celld.tactile.sample import ContactState, TactileStatus, from_record, to_record

from .conftest import Scene


def _tare(scene: Scene, n: int = 8):
    return tare(np.array([scene.detect(np.zeros(3)).p_cam for _ in range(n)]), scene.cfg.tare_max_spread, n)


def test_pressing_a_wall_on_the_left_reads_as_positive_normal_delta(scene: Scene) -> None:
    rest = _tare(scene)
    # The wall on the tool's +y side pushes the tip towards -y and drags it back (-x).
    shift = np.array([-0.4e-3, -1.5e-3, 0.0])
    det = scene.detect(shift)
    delta = deformation_tool(det.p_cam, rest, scene.tool.R_tool_cam)
    # Eq. 15: delta = P_r - P_s = -shift.
    np.testing.assert_allclose(delta, -shift, atol=20e-6)


def test_estimate_gives_a_valid_sample_with_contact_and_confidence(scene: Scene) -> None:
    rest = _tare(scene)
    params = DeformationParams.from_config(scene.cfg, scene.tool_cfg)
    det = scene.detect(np.array([0.0, -1.5e-3, 0.0]))
    s = estimate(det, rest, params, stamp_ns=123, seq=4, previous=ContactState.NONE, detect_ns=1000)
    assert s.valid and s.status == TactileStatus.OK
    assert s.contact == ContactState.CONTACT
    assert 0.5 < s.confidence <= 1.0
    assert s.delta_tool[1] == pytest.approx(1.5e-3, abs=20e-6)
    back = from_record(to_record(s))
    assert back.status == TactileStatus.OK and back.stamp_ns == 123
    np.testing.assert_allclose(back.delta_tool, s.delta_tool)


def test_a_failed_detection_never_reads_as_zero_deformation(scene: Scene) -> None:
    rest = _tare(scene)
    params = DeformationParams.from_config(scene.cfg, scene.tool_cfg)
    det = scene.detector.detect(scene.renderer.render(None))
    s = estimate(det, rest, params, 5, 1, ContactState.CONTACT, 0)
    assert not s.valid
    assert s.status == TactileStatus.NO_TAG
    assert np.all(np.isnan(s.delta_tool))
    assert s.confidence == 0.0
    untared = estimate(scene.detect(np.zeros(3)), None, params, 5, 1, ContactState.NONE, 0)
    assert not untared.valid and untared.status == TactileStatus.NOT_TARED
    lost = from_record(to_record(invalid_sample(9, 2, TactileStatus.CAMERA_LOST)))
    assert lost.status == TactileStatus.CAMERA_LOST and np.all(np.isnan(lost.delta_tool))


def test_tare_refuses_a_moving_finger_and_too_few_frames() -> None:
    rng = np.random.default_rng(0)
    still = 0.04 * np.array([0, 0, 1.0]) + rng.normal(0, 2e-6, (20, 3))
    t = tare(still, 2e-5, 10)
    assert t.n_frames == 20
    assert t.spread < 5e-6
    moving = still + np.linspace(0, 1e-3, 20)[:, None] * [1.0, 0, 0]
    with pytest.raises(TactileError, match="moved"):
        tare(moving, 2e-5, 10)
    with pytest.raises(TactileError, match="at least 10"):
        tare(still[:5], 2e-5, 10)
    with pytest.raises(InputError, match="shape"):
        tare(np.zeros((5, 2)), 2e-5)
    # NaN rows (failed detections) are left out, not averaged in.
    with_nan = np.vstack([still, np.full((3, 3), np.nan)])
    assert tare(with_nan, 2e-5, 10).n_frames == 20


@pytest.mark.parametrize(
    ("dn", "previous", "expected"),
    [
        (0.0, ContactState.NONE, ContactState.NONE),
        (0.25e-3, ContactState.NONE, ContactState.NONE),
        (0.31e-3, ContactState.NONE, ContactState.CONTACT),
        # Hysteresis: once in contact, contact holds down to 0.7 x threshold.
        (0.25e-3, ContactState.CONTACT, ContactState.CONTACT),
        (0.2e-3, ContactState.CONTACT, ContactState.NONE),
        (4.0e-3, ContactState.CONTACT, ContactState.OVERLOAD),
        (-2.0e-3, ContactState.NONE, ContactState.CONTACT),
    ],
)
def test_contact_state(dn: float, previous: ContactState, expected: ContactState) -> None:
    assert contact_state(np.array([0.0, dn, 5e-3]), previous, 0.3e-3, 4e-3) == expected


def test_contact_uses_the_in_plane_norm() -> None:
    # 0.2 mm tangential and 0.25 mm normal: 0.32 mm in plane.
    d = np.array([0.2e-3, 0.25e-3, 0.0])
    assert math.hypot(*d[:2]) > 0.3e-3
    assert contact_state(d, ContactState.NONE, 0.3e-3, 4e-3) == ContactState.CONTACT


def test_confidence_falls_with_blur_and_reprojection(scene: Scene) -> None:
    from celld.sim.srm import Imaging

    sharp = scene.detect(np.zeros(3))
    soft = scene.detect(np.zeros(3), Imaging(blur=2.0))
    c_sharp = confidence(sharp, scene.cfg.min_sharpness, scene.cfg.max_reprojection_px)
    c_soft = confidence(soft, scene.cfg.min_sharpness, scene.cfg.max_reprojection_px)
    assert 0.0 <= c_soft < c_sharp <= 1.0
    bad = sharp._replace(reprojection_px=scene.cfg.max_reprojection_px)
    assert confidence(bad, scene.cfg.min_sharpness, scene.cfg.max_reprojection_px) == 0.0
