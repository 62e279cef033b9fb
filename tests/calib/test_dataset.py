"""Calibration sessions on disk: atomic save, load, and the reference toolbox's format."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.dataset import SessionWriter, load_session, read_cloud, save_session, write_cloud
from celld.errors import InputError
from celld.se3 import transform_from

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])


def flange_pose(i: int) -> np.ndarray:
    return transform_from(Rotation.from_rotvec([0.05 * i, -0.03, 0.1]).as_matrix(), [0.5 + 0.02 * i, -0.1 + 0.03 * i, 0.4 + 0.01 * i])


def cloud(rng: np.random.Generator, n: int = 500) -> np.ndarray:
    return rng.uniform(-0.05, 0.05, (n, 3)) + [0.0, 0.0, 0.55]


def test_save_and_load_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    clouds = [cloud(rng) for _ in range(3)]
    poses = [flange_pose(i) for i in range(3)]
    P_v = cloud(rng)
    session = save_session(tmp_path / "s", poses, clouds, flange="ur10e", scanner="phoxi-m", verification=(flange_pose(9), P_v))
    assert session.kind == "celld" and session.ids == ("p000", "p001", "p002")
    assert session.flange == "ur10e" and session.scanner == "phoxi-m" and session.units == "m"
    for rec, T, P in zip(session.pairs, poses, clouds):
        np.testing.assert_allclose(rec.T_base_flan, T, atol=1e-15)
        np.testing.assert_allclose(rec.p_base, T[:3, 3], atol=1e-15)
        # float32 on disk: 0.1 um at half a metre.
        np.testing.assert_allclose(session.cloud(rec), P, atol=1e-7)
    np.testing.assert_allclose(session.cloud(session.verification), P_v, atol=1e-7)
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["p000.ply", "p001.ply", "p002.ply", "poses.json", "verification.ply"]


def test_organized_clouds_keep_their_image_layout(tmp_path: Path, rng: np.random.Generator) -> None:
    P = cloud(rng, 12).reshape(3, 4, 3)
    P[1, 2] = np.nan
    assert write_cloud(tmp_path / "c.ply", P) == 11
    back = read_cloud(tmp_path / "c.ply", "m")
    assert back.shape == (3, 4, 3)
    assert np.all(np.isnan(back[1, 2]))
    np.testing.assert_allclose(back[0], P[0], atol=1e-7)
    # Any other PLY reader sees the 12 points, one of them NaN.
    import open3d as o3d

    other = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "c.ply"), remove_nan_points=False).points)
    assert other.shape == (12, 3) and np.isnan(other).any(axis=1).sum() == 1


def test_unorganized_clouds_lose_their_missing_returns(tmp_path: Path, rng: np.random.Generator) -> None:
    P = cloud(rng, 12)
    P[5] = np.nan
    assert write_cloud(tmp_path / "c.ply", P) == 11
    assert read_cloud(tmp_path / "c.ply", "m").shape == (11, 3)


def test_writer_appends_and_every_step_is_a_valid_session(tmp_path: Path, rng: np.random.Generator) -> None:
    w = SessionWriter(tmp_path, flange="ur10e", scanner="phoxi-m")
    assert w.add_pair(flange_pose(0), cloud(rng)) == "p000"
    assert load_session(tmp_path).ids == ("p000",)
    w.add_pair(flange_pose(1), cloud(rng), pair_id="extra-1")
    assert load_session(tmp_path).ids == ("p000", "extra-1")
    with pytest.raises(InputError, match="already in the session"):
        w.add_pair(flange_pose(2), cloud(rng), pair_id="extra-1")
    with pytest.raises(InputError, match="pair id"):
        w.add_pair(flange_pose(2), cloud(rng), pair_id="../evil")
    with pytest.raises(InputError, match="already there"):
        SessionWriter(tmp_path, flange="ur10e", scanner="phoxi-m")
    resumed = SessionWriter(tmp_path, flange="ur10e", scanner="phoxi-m", resume=True)
    assert resumed.add_pair(flange_pose(3), cloud(rng)) == "p002"
    assert not list(tmp_path.glob(".*celld-tmp"))  # no temporaries left behind


def test_malformed_sessions_are_refused_with_the_place(tmp_path: Path, rng: np.random.Generator) -> None:
    with pytest.raises(InputError, match="no poses.json nor calib_data.json"):
        load_session(tmp_path)
    save_session(tmp_path / "s", [flange_pose(0)], [cloud(rng)], flange="ur10e", scanner="phoxi-m")
    doc = json.loads((tmp_path / "s" / "poses.json").read_text())
    doc["pairs"][0]["T_base_flan"][0][0] = 2.0
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"pairs\[0\].T_base_flan"):
        load_session(tmp_path / "s")
    doc["version"] = 7
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="expected version 1"):
        load_session(tmp_path / "s")
    (tmp_path / "s" / "poses.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_session(tmp_path / "s")


def test_poses_in_millimetres_labelled_metres_are_refused_at_load(tmp_path: Path, rng: np.random.Generator) -> None:
    save_session(tmp_path / "s", [flange_pose(0), flange_pose(1)], [cloud(rng), cloud(rng)], flange="ur10e", scanner="phoxi-m")
    doc = json.loads((tmp_path / "s" / "poses.json").read_text())
    for pair in doc["pairs"]:
        for row in pair["T_base_flan"][:3]:
            row[3] *= 1000.0
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"pairs\[0\].T_base_flan: the flange lies .* m from the robot base.*millimetres"):
        load_session(tmp_path / "s")


def test_a_cloud_in_the_wrong_units_is_refused(tmp_path: Path, rng: np.random.Generator) -> None:
    write_cloud(tmp_path / "c.ply", cloud(rng) * 1e3)  # millimetres in a metre file
    with pytest.raises(InputError, match="millimetres"):
        read_cloud(tmp_path / "c.ply", "m")
    assert read_cloud(tmp_path / "c.ply", "mm").max() < 1.0


def write_reference(root: Path, rng: np.random.Generator, n: int = 5, numbers: list[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A session in the reference toolbox's format: p_cam mm, p_robot m, [x y z qw qx qy qz], NN_tool.ply in mm."""
    root.mkdir(parents=True, exist_ok=True)
    doc, P_base, P_cam = {}, [], []
    for i in range(n):
        T = flange_pose(i)
        q_xyzw = Rotation.from_matrix(T[:3, :3]).as_quat()
        p_cam = np.linalg.inv(T_BASE_CAM) @ np.append(T[:3, 3], 1.0)
        doc[str(i)] = {
            "p_cam": (p_cam[:3] * 1e3).tolist(),
            "p_robot": T[:3, 3].tolist(),
            "robot_pose": T[:3, 3].tolist() + [q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]],
        }
        P_base.append(T[:3, 3])
        P_cam.append(p_cam[:3])
    (root / "calib_data.json").write_text(json.dumps(doc, indent=4))
    for k, num in enumerate(numbers or list(range(1, n + 1))):
        write_cloud(root / f"{num:02d}_tool.ply", (cloud(rng, 50) + P_cam[k] - [0, 0, 0.55]) * 1e3)
    return np.array(P_base), np.array(P_cam)


def test_reference_format_is_read_with_its_units_and_quaternion_order(tmp_path: Path, rng: np.random.Generator) -> None:
    # Numbered with gaps, as the toolbox's sample: the n-th entry takes the n-th cloud.
    _P_base, P_cam = write_reference(tmp_path, rng, 5, numbers=[1, 2, 4, 6, 7])
    session = load_session(tmp_path)
    assert session.kind == "reference" and session.units == "mm"
    assert session.ids == ("0", "1", "2", "3", "4")
    for i, rec in enumerate(session.pairs):
        np.testing.assert_allclose(rec.p_cam, P_cam[i], atol=1e-12)  # mm -> m
        np.testing.assert_allclose(rec.T_base_flan, flange_pose(i), atol=1e-12)  # (w, x, y, z) read right
    assert [r.cloud_path.name for r in session.pairs] == ["01_tool.ply", "02_tool.ply", "04_tool.ply", "06_tool.ply", "07_tool.ply"]
    # Each cloud lies around its own entry's centre, in metres once read.
    for i, rec in enumerate(session.pairs):
        assert np.linalg.norm(session.cloud(rec).mean(axis=0) - P_cam[i]) < 0.01


def test_reference_clouds_are_not_guessed_when_the_counts_differ(tmp_path: Path, rng: np.random.Generator) -> None:
    write_reference(tmp_path, rng, 5, numbers=[1, 2, 3])
    session = load_session(tmp_path)
    assert all(rec.cloud_path is None for rec in session.pairs)
    assert all(rec.p_cam is not None for rec in session.pairs)


def test_reference_entries_without_a_pose_are_refused(tmp_path: Path, rng: np.random.Generator) -> None:
    write_reference(tmp_path, rng, 4)
    doc = json.loads((tmp_path / "calib_data.json").read_text())
    del doc["2"]["robot_pose"], doc["2"]["p_robot"]
    (tmp_path / "calib_data.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="2: neither robot_pose nor p_robot"):
        load_session(tmp_path)
    doc["2"]["p_robot"] = [0.1, "x", 0.2]
    (tmp_path / "calib_data.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"2.p_robot"):
        load_session(tmp_path)
