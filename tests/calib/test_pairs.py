"""The pair collector: captures become pairs, or rejections that say why; the dataset keeps both."""

from __future__ import annotations

import json

import numpy as np
import pytest

from celld import se3
from celld.calib.dataset import SessionWriter
from celld.calib.flange import preset
from celld.calib.pairs import PairCollector
from celld.errors import InputError
from celld.sim.scanner import SimScanner, robot_scene

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
UR10E = preset("ur10e")


def test_captures_become_pairs_or_rejections_and_all_are_stored(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scanner = SimScanner("phoxi-m", T_BASE_CAM, seed=2, resolution_scale=0.25)
    writer = SessionWriter(tmp_path / "s", flange="ur10e", scanner="phoxi-m")
    pairs = PairCollector(UR10E, writer=writer)
    T_seen = se3.from_xyz_rpy([0.6, 0.02, 0.45], [0.1, -0.05, 0.2])
    # The flange far outside the camera's view: the table alone.
    T_unseen = se3.from_xyz_rpy([-1.5, 1.5, 0.45], [0.0, 0.0, 0.0])
    seen = pairs.capture(T_seen, scanner.capture(robot_scene(T_seen, UR10E)).points)
    unseen = pairs.capture(T_unseen, scanner.capture(robot_scene(T_unseen, UR10E)).points)
    assert seen.kept and seen.detection is not None
    assert not unseen.kept and unseen.rejected is not None and unseen.rejected.reason.startswith("detection failed at ")
    assert (unseen.rejected.id, unseen.rejected.index) == (unseen.id, 1)
    found = pairs.detections()
    assert found.ids == (seen.id,) and [r.id for r in found.rejected] == [unseen.id]
    np.testing.assert_allclose(found.P_base[0], T_seen[:3, 3])
    # The centre found is the flange's, seen from the camera, within the detector's tolerance at quarter resolution.
    p_true_cam = (se3.invert(T_BASE_CAM) @ T_seen)[:3, 3]
    assert np.linalg.norm(found.P_cam[0] - p_true_cam) < 1e-3
    assert (pairs.n_pairs, pairs.n_captures) == (1, 2)
    # The writer named both pairs and stored both captures, found or not.
    doc = json.loads((tmp_path / "s" / "poses.json").read_text())
    assert [p["id"] for p in doc["pairs"]] == [seen.id, unseen.id]


def test_recorded_centres_need_no_cloud_and_a_pair_with_neither_is_rejected() -> None:
    pairs = PairCollector(None)
    kept = pairs.add("a", [0.5, 0.0, 0.4], p_cam=[0.01, 0.02, 0.6])
    none = pairs.add("b", [0.5, 0.1, 0.4])
    assert kept.kept and kept.detection is None
    assert none.rejected is not None and "no flange centre recorded and no cloud" in none.rejected.reason
    np.testing.assert_allclose(pairs.detections().P_cam, [[0.01, 0.02, 0.6]])
    with pytest.raises(InputError, match="flange preset"):
        pairs.add("c", [0.5, 0.0, 0.4], cloud=np.zeros((10, 10, 3)))
