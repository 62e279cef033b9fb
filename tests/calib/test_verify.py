"""A calibration held against the cell: the flange seen where the calibration puts it passes, a moved or turned
scanner fails with its figure, and the bound is the calibration's own plus the measured repeatability."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld import se3
from celld.calib.verify import Sighting, calibration_bound, verify_placement
from celld.daemon.verify import due
from celld.errors import CalibrationError, JobError

T_TRUE = se3.from_ur_pose([0.6, 0.0, 1.2, math.pi, 0.0, 0.0])  # the scanner as it is, looking down


def _sightings(T_calibrated: np.ndarray, rng: np.random.Generator, noise: float = 2e-5) -> tuple[list[Sighting], np.ndarray]:
    """Three flange poses tilted apart, seen by the scanner where it truly is, held to ``T_calibrated``."""
    out = []
    for i, (p, rv) in enumerate([([0.6, 0.0, 0.45], [0, 0, 0]), ([0.75, 0.12, 0.5], [0.25, 0, 0]), ([0.5, -0.1, 0.4], [0, -0.25, 0.1])]):
        T_bf = np.eye(4)
        T_bf[:3, :3] = Rotation.from_rotvec(rv).as_matrix()
        T_bf[:3, 3] = p
        T_cam_flange = se3.invert(T_TRUE) @ T_bf
        center = T_cam_flange[:3, 3] + rng.normal(0, noise, 3)
        out.append(Sighting(f"v{i}", T_bf, T_calibrated, center, T_cam_flange[:3, 2]))
    repeat = out[0].center_cam + rng.normal(0, noise, 3)
    return out, repeat


def test_the_flange_where_the_calibration_puts_it_passes(rng: np.random.Generator) -> None:
    sightings, repeat = _sightings(T_TRUE, rng)
    done = verify_placement(sightings, repeat, 0.3e-3)
    assert done.passed and done.reason == ""
    assert done.error < 1e-4 and 0 < done.repeatability < 1e-4
    assert done.bound == pytest.approx(0.3e-3 + done.repeatability)  # its own bound plus the repeatability
    d = done.as_dict()
    assert d["passed"] and [p["id"] for p in d["poses"]] == ["v0", "v1", "v2"] and all(p["normal_deg"] < 0.1 for p in d["poses"])


def test_a_scanner_moved_50_mm_and_turned_fails_with_its_figure(rng: np.random.Generator) -> None:
    moved = T_TRUE.copy()
    moved[:3, 3] += [0.05, 0.0, 0.0]
    sightings, repeat = _sightings(moved, rng)
    done = verify_placement(sightings, repeat, 0.3e-3)
    assert not done.passed and done.error == pytest.approx(0.05, abs=1e-4)
    assert "the flange is 50.0" in done.reason and "beyond the bound of 0.3" in done.reason
    # Turned 1 degree about its own axis, not moved: the poses away from the axis show it.
    turned = T_TRUE @ se3.from_ur_pose([0, 0, 0, 0, 0, math.radians(1.0)])
    done = verify_placement(*_sightings(turned, rng), 0.3e-3)
    assert not done.passed and 1e-3 < done.error < 1e-2


def test_a_flange_seen_at_fewer_than_two_poses_fails_and_a_configured_bound_replaces_the_rule(rng: np.random.Generator) -> None:
    sightings, repeat = _sightings(T_TRUE, rng)
    lost = [Sighting(s.id, s.T_base_flange, T_TRUE, None, None, "no hollow rim circle") for s in sightings]
    # A view where the detector finds no flange at all is left out, as a calibration leaves it out ...
    done = verify_placement([sightings[0], lost[1], sightings[2]], repeat, 0.3e-3)
    assert done.passed and done.as_dict()["poses"][1] == {
        "id": "v1",
        "error_mm": None,
        "normal_deg": None,
        "seen": False,
        "why": "no hollow rim circle",
    }
    # ... but one seen pose cannot show a turn.
    done = verify_placement([sightings[0], lost[1], lost[2]], repeat, 0.3e-3)
    assert not done.passed and "seen at 1 of 3 poses, too few to verify (v1: no hollow rim circle; v2: no hollow rim circle)" in done.reason
    done = verify_placement(lost, None, 0.3e-3)
    assert not done.passed and done.error == math.inf and done.as_dict()["error_mm"] is None
    nudged = T_TRUE.copy()
    nudged[:3, 3] += [0.0, 0.0005, 0.0]  # 0.5 mm
    assert not verify_placement(*_sightings(nudged, rng), 0.3e-3).passed
    assert verify_placement(*_sightings(nudged, rng), 0.3e-3, bound=1e-3).passed
    with pytest.raises(CalibrationError, match="two poses or more"):
        verify_placement(sightings[:1], repeat, 0.3e-3)


def test_the_calibrations_own_bound_is_its_largest_used_residual_and_its_reported_uncertainty() -> None:
    pairs = [{"residual_mm": 0.12, "used": True}, {"residual_mm": 0.31, "used": True}, {"residual_mm": 4.0, "used": False}]
    assert calibration_bound({"quality": {"pairs": pairs, "rms_mm": 0.2}}) == pytest.approx(0.31e-3)
    assert calibration_bound({"quality": {"pairs": [], "rms_mm": 0.1}}) == pytest.approx(0.3e-3)
    # ... plus three times its reported 1-sigma at the workspace centre: how far the fit itself may be off.
    std = {"translation_std_mm": [0.02, 0.0, 0.0]}
    assert calibration_bound({"quality": {"pairs": pairs, **std}}) == pytest.approx(0.37e-3)
    assert calibration_bound({"quality": {"pairs": pairs, "translation_std_mm": [None, 0.0, 0.0]}}) == pytest.approx(0.31e-3)
    with pytest.raises(CalibrationError, match="no pair residuals"):
        calibration_bound({"quality": {}})


def test_a_weld_verifies_when_due_and_is_refused_after_a_failure() -> None:
    now = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
    at = (now - timedelta(hours=2)).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    started = (now - timedelta(hours=3)).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    cal = {"job": "c1", "sha256": "aa"}
    ok = {"calibration_sha256": "aa", "passed": True, "at": at, "job": "v1", "reason": ""}
    assert due(None, cal, started, 8 * 3600, now) == "the current calibration has not been verified"
    assert due({**ok, "calibration_sha256": "bb"}, cal, started, 8 * 3600, now) == "the current calibration has not been verified"
    assert due(ok, cal, started, 8 * 3600, now) == ""
    assert "since the daemon started" in due(ok, cal, now.isoformat().replace("+00:00", "Z"), 8 * 3600, now)
    assert "last verified 2.0 h ago" in due(ok, cal, started, 3600, now)
    assert due(ok, cal, started, 0, now) == ""  # no interval: only after a start or a change
    failed = {**ok, "passed": False, "reason": "the flange is 50.02 mm (at v1) from where the calibration puts it"}
    with pytest.raises(JobError, match="failed its verification by job v1 .*50.02 mm.*calibrate again"):
        due(failed, cal, started, 8 * 3600, now)
