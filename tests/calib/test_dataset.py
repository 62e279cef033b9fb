"""Calibration sessions on disk: atomic save, load, and the reference toolbox's format."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.dataset import (
    CLOUD_SUFFIX,
    VERSION,
    SessionWriter,
    load_session,
    read_cloud,
    save_session,
    write_cloud,
    write_compact_cloud,
)
from celld.calib.detect import coarse_grid, detect_flange
from celld.calib.detect_params import PARAMS_BY_SCANNER
from celld.calib.flange import preset
from celld.calib.poses import calibration_poses
from celld.errors import DetectionError, InputError
from celld.scanner.depth import depth_to_points, intrinsic_matrix
from celld.se3 import apply, invert, transform_from

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
        np.testing.assert_allclose(rec.T_base_flange, T, atol=1e-15)
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
    doc["pairs"][0]["T_base_flange"][0][0] = 2.0
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"pairs\[0\].T_base_flange"):
        load_session(tmp_path / "s")
    doc["version"] = 7
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="expected version 1 or 2"):
        load_session(tmp_path / "s")
    (tmp_path / "s" / "poses.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_session(tmp_path / "s")


def test_poses_in_millimetres_labelled_metres_are_refused_at_load(tmp_path: Path, rng: np.random.Generator) -> None:
    save_session(tmp_path / "s", [flange_pose(0), flange_pose(1)], [cloud(rng), cloud(rng)], flange="ur10e", scanner="phoxi-m")
    doc = json.loads((tmp_path / "s" / "poses.json").read_text())
    for pair in doc["pairs"]:
        for row in pair["T_base_flange"][:3]:
            row[3] *= 1000.0
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"pairs\[0\].T_base_flange: the flange lies .* m from the robot base.*millimetres"):
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
        np.testing.assert_allclose(rec.T_base_flange, flange_pose(i), atol=1e-12)  # (w, x, y, z) read right
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


# -- compact clouds -------------------------------------------------------------------


def pinhole_scene(rng: np.random.Generator, shape: tuple[int, int] = (90, 120)) -> np.ndarray:
    """(H, W, 3) float32 organized cloud of a tilted plane 0.6-0.9 m away (fx 250, fy 260, cx 59.5, cy 44.5), with holes."""
    H, W = shape
    u = (np.arange(W) - 59.5) / 250.0
    v = (np.arange(H) - 44.5) / 260.0
    z = 0.6 + 0.3 * np.arange(W)[None, :] / W + rng.normal(0.0, 1e-4, (H, W))
    P = np.stack([z * u[None, :], z * v[:, None], np.broadcast_to(z, (H, W))], axis=-1).astype(np.float32)
    P[rng.random((H, W)) < 0.05] = np.nan
    return P


def test_compact_cloud_reads_back_and_opens_in_ordinary_tools(tmp_path: Path, rng: np.random.Generator) -> None:
    P = pinhole_scene(rng)
    name, _ = write_compact_cloud(tmp_path, "c", P, (20, 60, 30, 80), "detection", (0, 90, 0, 120), grid_stride=6)
    assert name == "c" + CLOUD_SUFFIX
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.cloud.json", "c.depth.png", "c.grid.ply", "c.roi.ply"]
    doc = json.loads((tmp_path / name).read_text())
    assert doc["xy"]["model"] == "pinhole" and doc["window"]["window_px"] == [20, 60, 30, 80]
    assert doc["precision_m"] == 5e-5 and doc["valid_points"] == int(np.isfinite(P[..., 2]).sum())
    Q = read_cloud(tmp_path / name, "m")
    np.testing.assert_array_equal(Q[20:60, 30:80], P[20:60, 30:80])
    np.testing.assert_array_equal(Q[::6, ::6], P[::6, ::6])
    valid = np.isfinite(P).all(axis=2)
    assert np.abs(Q - P)[valid].max() <= doc["precision_m"] * (1 + 1e-9)
    # The depth image and the sidecar's intrinsics are all Open3D needs to unproject it.
    depth = cv2.imread(str(tmp_path / doc["depth"]["file"]), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == P.shape[:2]
    xy = doc["xy"]
    K = intrinsic_matrix(xy["fx_px"], xy["fy_px"], xy["cx_px"], xy["cy_px"])
    R = depth_to_points(depth, K, 1.0 / doc["depth"]["unit_m"], 0.0, 10.0)
    np.testing.assert_array_equal(np.isfinite(R[..., 2]), valid)
    assert np.abs(R - P)[valid].max() < 1e-4  # the 50 um of the depth, and Open3D's float32
    # The window is a plain PLY: 40 x 50 points, NaN where there was no return.
    roi = np.asarray(o3d.io.read_point_cloud(str(tmp_path / doc["window"]["file"]), remove_nan_points=False).points)
    np.testing.assert_array_equal(roi.reshape(40, 50, 3), P[20:60, 30:80])


def test_a_malformed_compact_cloud_is_refused_with_the_place(tmp_path: Path, rng: np.random.Generator) -> None:
    name, _ = write_compact_cloud(tmp_path, "c", pinhole_scene(rng), (0, 10, 0, 10), "detection", (0, 90, 0, 120), grid_stride=6)
    good = json.loads((tmp_path / name).read_text())
    for change, match in [
        (lambda d: d["xy"].update(model="magic"), r"c.cloud.json.xy.model"),
        (lambda d: d["depth"].update(unit_m=0), r"c.cloud.json.depth.unit_m: expected a positive"),
        (lambda d: d["depth"].update(file="gone.png"), r"gone.png: image file not found"),
        (lambda d: d["window"].update(window_px=[0, 20, 0, 10]), r"c.cloud.json.window: expected an organized 20 x 10"),
        (lambda d: d.update(shape_px=[45, 120]), r"expected a 16-bit 45 x 120 PNG"),
        (lambda d: d.update(version=9), r"expected a 'celld.calib.cloud' document of version 1 or 2, got 'celld.calib.cloud' 9"),
    ]:
        doc = json.loads(json.dumps(good))
        change(doc)
        (tmp_path / name).write_text(json.dumps(doc))
        with pytest.raises(InputError, match=match):
            read_cloud(tmp_path / name, "m")


@pytest.fixture(scope="module")
def captures() -> tuple[list[tuple[np.ndarray, np.ndarray]], object]:
    """Six captures of the flange by the ray-cast PhoXi M at 0.4 of its resolution, and the scanner's model."""
    from celld.sim.scanner import SimScanner
    from celld.sim.scene import robot_scene

    flange = preset("ur10e")
    scanner = SimScanner("phoxi-m", T_BASE_CAM, seed=2, resolution_scale=0.4)
    poses = calibration_poses(transform_from(np.eye(3), [0.6, 0.0, 0.35]), [0.3, 0.3, 0.2], 6, 0.3, seed=2)
    return [(T, scanner.capture(robot_scene(T, flange)).points) for T in poses], scanner.model


def test_the_writer_keeps_exact_what_the_detector_reads(tmp_path: Path, captures) -> None:
    clouds, _ = captures
    T_v, P_v = clouds[0]
    T, P = clouds[1]
    w = SessionWriter(tmp_path, flange="ur10e", scanner="phoxi-m")
    w.set_verification(T_v, P_v)
    w.add_pair(T, P)
    session = load_session(tmp_path)
    assert [r.cloud_path.name for r in (session.verification, *session.pairs)] == ["verification.cloud.json", "p000.cloud.json"]
    det = detect_flange(P, preset("ur10e"), PARAMS_BY_SCANNER["phoxi-m"])
    doc = json.loads((tmp_path / "p000.cloud.json").read_text())
    assert doc["window"]["source"] == "detection" and tuple(doc["window"]["window_px"]) == det.window_px
    assert doc["grid"] == {"file": "p000.grid.ply", "window_px": [0, 618, 0, 826], "stride_px": 7}  # ceil(sqrt(826 x 618 / 12 000))
    Q = session.cloud(session.pairs[0])
    r0, r1, c0, c1 = det.window_px
    np.testing.assert_array_equal(Q[r0:r1, c0:c1], P[r0:r1, c0:c1])
    np.testing.assert_array_equal(Q[::7, ::7], P[::7, ::7])
    again = detect_flange(Q, preset("ur10e"), PARAMS_BY_SCANNER["phoxi-m"])
    np.testing.assert_array_equal(again.center, det.center)
    np.testing.assert_array_equal(again.normal, det.normal)
    # The verification window also holds the flange model as the e_icp crop takes it (55 mm + 10 mm around the centre).
    det_v = detect_flange(P_v, preset("ur10e"), PARAMS_BY_SCANNER["phoxi-m"])
    r0, r1, c0, c1 = json.loads((tmp_path / "verification.cloud.json").read_text())["window"]["window_px"]
    rows, cols = np.nonzero(np.linalg.norm(P_v - det_v.center, axis=2) <= 0.064)
    assert r0 <= rows.min() and rows.max() < r1 and c0 <= cols.min() and cols.max() < c1
    # A compact session is a tenth of the float one at this resolution.
    size = sum(p.stat().st_size for p in tmp_path.iterdir())
    assert size < 0.1 * 2 * P.size * 4


def test_behind_a_scanner_roi_the_finer_coarse_grid_is_kept_exact(tmp_path: Path) -> None:
    from celld.sim.scanner import SimScanner
    from celld.sim.scene import robot_scene

    # Returns only in a window of the image: the coarse pass thins its bounding box, finer.
    scanner = SimScanner("phoxi-m", T_BASE_CAM, seed=3, resolution_scale=0.4, roi_px=(200, 420, 300, 530))
    T = transform_from(np.eye(3), [0.6, 0.0, 0.35])
    P = scanner.capture(robot_scene(T, preset("ur10e"))).points
    grid_px, stride = coarse_grid(P, PARAMS_BY_SCANNER["phoxi-m"])
    assert stride < 7 and grid_px[0] >= 190 and grid_px[1] <= 430
    SessionWriter(tmp_path, flange="ur10e", scanner="phoxi-m").add_pair(T, P)
    doc = json.loads((tmp_path / "p000.cloud.json").read_text())
    assert doc["grid"]["window_px"] == list(grid_px) and doc["grid"]["stride_px"] == stride
    Q = load_session(tmp_path).cloud(load_session(tmp_path).pairs[0])
    (r0, r1, c0, c1), s = grid_px, stride
    np.testing.assert_array_equal(Q[r0:r1:s, c0:c1:s], P[r0:r1:s, c0:c1:s])
    det = detect_flange(P, preset("ur10e"), PARAMS_BY_SCANNER["phoxi-m"])
    np.testing.assert_array_equal(detect_flange(Q, preset("ur10e"), PARAMS_BY_SCANNER["phoxi-m"]).center, det.center)


def test_a_missing_flange_is_kept_around_where_the_session_expects_it(tmp_path: Path, captures) -> None:
    clouds, model = captures
    w = SessionWriter(tmp_path / "early", flange="ur10e", scanner="phoxi-m")
    T, P = clouds[5]
    # No pair found yet: nothing to predict from, so the cloud is kept whole.
    assert w.add_pair(T, P, detection=DetectionError("circle", "not found (test)")) == "p000"
    assert (tmp_path / "early" / "p000.ply").is_file()

    w = SessionWriter(tmp_path / "late", flange="ur10e", scanner="phoxi-m")
    for T_i, P_i in clouds[:4]:
        w.add_pair(T_i, P_i)
    w.add_pair(T, P, detection=DetectionError("circle", "not found (test)"))
    doc = json.loads((tmp_path / "late" / "p004.cloud.json").read_text())
    assert doc["window"]["source"] == "expected"
    r0, r1, c0, c1 = doc["window"]["window_px"]
    # The true flange, all of it, lies in the window.
    rows, cols = np.nonzero(np.linalg.norm(P - apply(invert(T_BASE_CAM), T[:3, 3][None])[0], axis=2) <= 0.045)
    assert r0 <= rows.min() and rows.max() < r1 and c0 <= cols.min() and cols.max() < c1
    assert (r1 - r0) * (c1 - c0) < 0.2 * model.width_px * model.height_px


def test_float_sessions_still_load_and_resume(tmp_path: Path, captures) -> None:
    clouds, _ = captures
    (T0, P0), (T1, P1) = clouds[:2]
    session = save_session(tmp_path / "s", [T0], [P0], flange="ur10e", scanner="phoxi-m", compact=False)
    assert session.pairs[0].cloud_path.name == "p000.ply"
    np.testing.assert_array_equal(session.cloud(session.pairs[0]), P0)
    # A version-1 session (float PLY only, its poses under T_base_flan) is read, and resumed as this version.
    doc = json.loads((tmp_path / "s" / "poses.json").read_text())
    doc["version"] = 1
    doc["pairs"][0]["T_base_flan"] = doc["pairs"][0].pop("T_base_flange")
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    assert load_session(tmp_path / "s").ids == ("p000",)
    np.testing.assert_allclose(load_session(tmp_path / "s").pairs[0].T_base_flange, T0)
    SessionWriter(tmp_path / "s", flange="ur10e", scanner="phoxi-m", resume=True).add_pair(T1, P1)
    resumed = json.loads((tmp_path / "s" / "poses.json").read_text())
    assert resumed["version"] == VERSION and all("T_base_flange" in p and "T_base_flan" not in p for p in resumed["pairs"])
    session = load_session(tmp_path / "s")
    assert [r.cloud_path.name for r in session.pairs] == ["p000.ply", "p001.cloud.json"]
    assert session.cloud(session.pairs[1]).shape == P1.shape
    np.testing.assert_allclose(session.pairs[0].T_base_flange, T0)


def test_a_full_resolution_phoxi_m_pair_fits_the_budget(tmp_path: Path) -> None:
    """60 MB for a 20-pose session: 3 MB a pair, against 38 MB as float PLY."""
    from celld.sim.scanner import SimScanner
    from celld.sim.scene import robot_scene

    T = transform_from(np.eye(3), [0.6, 0.0, 0.45])
    P = SimScanner("phoxi-m", T_BASE_CAM, seed=0).capture(robot_scene(T, preset("ur10e"))).points
    SessionWriter(tmp_path, flange="ur10e", scanner="phoxi-m").add_pair(T, P)
    sizes = {p.name: p.stat().st_size for p in tmp_path.iterdir() if p.name != "poses.json"}
    assert sorted(sizes) == ["p000.cloud.json", "p000.depth.png", "p000.grid.ply", "p000.roi.ply"]
    assert sum(sizes.values()) < 3.0e6
