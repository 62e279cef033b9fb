"""Scan to seam path through the ray-cast scanner: known-truth scenes and refusals.

The PhoXi M runs at half resolution (0.9 mm point spacing at 1 m) to keep the
tests short; the full-resolution figures are the benchmark's.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from celld import polyline, se3
from celld.cli import main as celld_main
from celld.config.seam import SeamParams
from celld.errors import GrooveError, RegistrationError, ScanError, SeamError
from celld.seam import workpiece as wpm
from celld.seam.pipeline import find_seam, prepare
from celld.seam.workpiece import Workpiece, example
from celld.sim import workpiece as simscene
from celld.sim.scanner import SimScanner
from celld.sim.scene import box

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
SCALE = 0.5


def _scan(wp: Workpiece, T_base_obj: np.ndarray, seed: int = 0) -> np.ndarray:
    return SimScanner("phoxi-m", T_BASE_CAM, seed=seed, resolution_scale=SCALE).capture(simscene.workpiece_scene(wp, T_base_obj)).points


def _pose(wp: Workpiece, seed: int, angle_deg: float = 15.0) -> np.ndarray:
    return simscene.random_pose(wp, np.random.default_rng(seed), math.radians(angle_deg), 0.04)


def _error(path, wp: Workpiece, T_true: np.ndarray) -> np.ndarray:
    truth = se3.apply(T_true, polyline.resample(wp.seam, 2e-4)[0])
    return polyline.distance(path.points_base, truth)


@pytest.mark.parametrize("name", ["v-groove", "curved-groove", "fillet-t"])
def test_known_truth_scene_gives_the_seam_in_the_base_frame(name: str) -> None:
    wp = example(name)
    T_true = _pose(wp, seed=11)
    if name == "fillet-t":
        # Tilted 35 degrees about its seam (toward the PA welding position), so
        # the camera above sees the web face; lying flat, see the next test.
        T_true = simscene.set_down(wp, T_true @ se3.from_xyz_rpy([0.0, 0.0, 0.0], [math.radians(-35.0), 0.0, 0.0]))
    path = find_seam(_scan(wp, T_true), wp, T_BASE_CAM, SeamParams(), T_base_obj_nominal=simscene.nominal_pose(wp))
    err = _error(path, wp, T_true)
    assert math.sqrt(np.mean(err**2)) < 1e-4
    assert err.max() < 0.3e-3
    # Ordered from the model's start to its end, 1 mm apart.
    true_start, true_end = se3.apply(T_true, wp.seam[[0, -1]])
    assert np.linalg.norm(path.points_base[0] - true_start) < 2e-3
    assert np.linalg.norm(path.points_base[-1] - true_end) < 2e-3
    np.testing.assert_allclose(np.linalg.norm(np.diff(path.points_base, axis=0), axis=1), path.spacing, rtol=0.05)
    assert path.spacing == pytest.approx(1e-3, rel=0.01)
    # Frames: unit tangents along travel, normals in the seam plane toward the left wall.
    np.testing.assert_allclose(np.linalg.norm(path.tangents, axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.einsum("ij,ij->i", path.tangents, path.normals), 0.0, atol=1e-9)
    np.testing.assert_allclose(path.normals @ path.plane_normal, 0.0, atol=0.02)
    np.testing.assert_allclose(path.plane_normal, T_true[:3, :3] @ wp.approach, atol=0.005)
    left_true = T_true[:3, :3] @ np.cross(wp.approach, np.gradient(wp.seam, axis=0)[0] / np.linalg.norm(np.gradient(wp.seam, axis=0)[0]))
    assert path.normals[0] @ left_true > 0.99
    q = path.quality
    assert q.fitness > 0.97 and q.coverage > 0.95
    assert q.source in ("groove", "model")


def test_fillet_lying_flat_is_refused_not_guessed() -> None:
    # Under a camera straight above, the web faces are seen at grazing angles
    # by a few dozen points: the seam's sideways position is not fixed.
    wp = example("fillet-t")
    T_true = simscene.nominal_pose(wp)
    with pytest.raises(ScanError, match="across"):
        find_seam(_scan(wp, T_true), wp, T_BASE_CAM, SeamParams(), T_base_obj_nominal=T_true)


def _bowed_v_groove(bow: float) -> Workpiece:
    """The shipped V-groove as built with its joint bowed sideways (welding
    distortion): the seam runs y = bow * (1 - (2x / L)^2) instead of y = 0."""
    ref = example("v-groove")
    p = ref.params
    x = np.linspace(-p["length"] / 2.0, p["length"] / 2.0, 41)
    path = np.column_stack([x, bow * (1.0 - (2.0 * x / p["length"]) ** 2), np.zeros_like(x)])
    lat = np.tile([0.0, 1.0, 0.0], (len(x), 1))
    up = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    left, right = wpm._v_profiles(p["thickness"], p["groove_angle"], p["root_gap"], p["root_face"], p["plate_width"])
    V, F, L = wpm._merge(
        wpm._sweep(left, path, lat, up, labels={3: wpm.LEFT_WALL}), wpm._sweep(right, path, lat, up, labels={0: wpm.RIGHT_WALL})
    )
    return Workpiece("bowed", V, F, path + [0.0, 0.0, p["root_face"]], ref.approach, L, ref.wall_band)


def test_groove_finds_the_actual_seam_where_the_part_differs_from_its_model() -> None:
    model = example("v-groove")
    built = _bowed_v_groove(0.0008)  # bowed 0.8 mm at mid-length
    T_true = _pose(model, seed=5, angle_deg=10.0)
    cloud = _scan(built, T_true)
    nominal = simscene.nominal_pose(model)
    path = find_seam(cloud, model, T_BASE_CAM, SeamParams(seam_source="groove"), T_base_obj_nominal=nominal)
    truth = se3.apply(T_true, polyline.resample(built.seam, 2e-4)[0])
    err_groove = polyline.distance(path.points_base, truth)
    err_model = polyline.distance(path.model_points_base, truth)
    assert path.quality.source == "groove"
    assert math.sqrt(np.mean(err_groove**2)) < 0.06e-3
    # A rigid fit of the straight model cannot follow the bow.
    assert math.sqrt(np.mean(err_model**2)) > 0.15e-3
    assert path.quality.model_groove_max > 0.3e-3
    # "auto" takes the groove too: the deviation is far beyond its uncertainty.
    auto = find_seam(cloud, model, T_BASE_CAM, SeamParams(), T_base_obj_nominal=nominal)
    assert auto.quality.source == "groove"


@pytest.fixture(scope="module")
def vgroove_scan() -> tuple[Workpiece, np.ndarray, np.ndarray]:
    wp = example("v-groove")
    T_true = _pose(wp, seed=2, angle_deg=10.0)
    return wp, T_true, _scan(wp, T_true)


def test_empty_scan_is_refused() -> None:
    with pytest.raises(ScanError, match="empty"):
        find_seam(np.full((40, 50, 3), np.nan, np.float32), example("v-groove"), T_BASE_CAM)


def test_partial_scan_is_refused(vgroove_scan) -> None:
    wp, T_true, cloud = vgroove_scan
    # Blank the image rows that hold the second half of the seam.
    cut = np.array(cloud)
    end_cam = se3.apply(se3.invert(T_BASE_CAM), se3.apply(T_true, wp.seam[[-1]]))[0]
    start_cam = se3.apply(se3.invert(T_BASE_CAM), se3.apply(T_true, wp.seam[[0]]))[0]
    mid_cam = (start_cam + end_cam) / 2.0
    axis = int(np.argmax(np.abs(end_cam[:2] - start_cam[:2])))  # 0: image x, 1: image y
    coord = cut[..., axis] / cut[..., 2]
    beyond = (coord - mid_cam[axis] / mid_cam[2]) * np.sign(end_cam[axis] - start_cam[axis]) > 0
    cut[beyond] = np.nan
    with pytest.raises(ScanError, match="partial scan"):
        find_seam(cut, wp, T_BASE_CAM, SeamParams(), T_base_obj_nominal=simscene.nominal_pose(wp))


def test_scan_of_a_different_part_is_refused() -> None:
    fillet = example("fillet-t")
    cloud = _scan(fillet, _pose(fillet, seed=3, angle_deg=10.0))
    with pytest.raises((RegistrationError, GrooveError)):
        find_seam(cloud, example("v-groove"), T_BASE_CAM, SeamParams(), T_base_obj_nominal=simscene.nominal_pose(example("v-groove")))


def test_flat_plate_without_a_groove_is_refused() -> None:
    from celld.sim.scene import SceneObject

    plate = SceneObject("plate", box((0.15, 0.122, 0.01)), se3.from_xyz_rpy([0.6, 0.0, 0.005], [0.0, 0.0, 0.1]), "metal")
    table = simscene.workpiece_scene(example("v-groove"), np.eye(4))[1]
    cloud = SimScanner("phoxi-m", T_BASE_CAM, seed=0, resolution_scale=SCALE).capture([plate, table]).points
    wp = example("v-groove")
    with pytest.raises(SeamError) as info:
        find_seam(cloud, wp, T_BASE_CAM, SeamParams(), T_base_obj_nominal=simscene.nominal_pose(wp))
    assert isinstance(info.value, (RegistrationError, GrooveError))


def test_cloud_in_millimetres_is_refused(vgroove_scan) -> None:
    wp, _, cloud = vgroove_scan
    with pytest.raises(ScanError, match="millimetres"):
        find_seam(cloud * 1000.0, wp, T_BASE_CAM)


def test_malformed_cloud_is_refused() -> None:
    with pytest.raises(ScanError, match=r"\(H, W, 3\) or \(n, 3\)"):
        find_seam(np.zeros((10, 4)), example("v-groove"), T_BASE_CAM)


def test_same_seed_same_path(vgroove_scan) -> None:
    wp, _, cloud = vgroove_scan
    prepared = prepare(wp, SeamParams())
    a = find_seam(cloud, prepared, T_BASE_CAM, T_base_obj_nominal=simscene.nominal_pose(wp))
    b = find_seam(cloud, prepared, T_BASE_CAM, T_base_obj_nominal=simscene.nominal_pose(wp))
    assert np.abs(a.points_base - b.points_base).max() < 1e-6
    assert a.quality.attempts == b.quality.attempts


def test_cli_prints_one_json_object(vgroove_scan, tmp_path, capsys) -> None:
    wp, _, cloud = vgroove_scan
    np.save(tmp_path / "scan.npy", cloud)
    (tmp_path / "T_base_cam.json").write_text(json.dumps(T_BASE_CAM.tolist()))
    (tmp_path / "nominal.json").write_text(json.dumps(simscene.nominal_pose(wp).tolist()))
    code = celld_main(
        [
            "seam",
            "find",
            str(tmp_path / "scan.npy"),
            "--model",
            "v-groove",
            "--T-base-cam",
            str(tmp_path / "T_base_cam.json"),
            "--nominal",
            str(tmp_path / "nominal.json"),
            "--json",
        ]
    )
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["ok"] is True
    seam = out["seam"]
    assert seam["frame"] == "base" and seam["units"] == "m"
    assert len(seam["points_base"]) == len(seam["normals"]) == len(seam["tangents"]) == 151
    assert seam["quality"]["fitness"] > 0.97

    np.save(tmp_path / "mm.npy", cloud * 1000.0)
    code = celld_main(
        ["seam", "find", str(tmp_path / "mm.npy"), "--model", "v-groove", "--T-base-cam", str(tmp_path / "T_base_cam.json"), "--json"]
    )
    out = json.loads(capsys.readouterr().out)
    assert code == 2 and out["ok"] is False
    assert out["error"]["type"] == "ScanError" and "millimetres" in out["error"]["reason"]
    # Read back in its own units, the same cloud is fine again.
    code = celld_main(
        [
            "seam",
            "find",
            str(tmp_path / "mm.npy"),
            "--cloud-units",
            "mm",
            "--model",
            "v-groove",
            "--T-base-cam",
            str(tmp_path / "T_base_cam.json"),
            "--nominal",
            str(tmp_path / "nominal.json"),
            "--json",
        ]
    )
    assert code == 0 and json.loads(capsys.readouterr().out)["ok"] is True


def test_cli_applies_the_range_bias_of_a_calibration_file(vgroove_scan, tmp_path, capsys) -> None:
    wp, _, cloud = vgroove_scan
    np.save(tmp_path / "scan.npy", cloud)
    (tmp_path / "nominal.json").write_text(json.dumps(simscene.nominal_pose(wp).tolist()))

    def seam(calibration: dict, *extra: str) -> np.ndarray:
        (tmp_path / "cal.json").write_text(json.dumps(calibration))
        code = celld_main(
            [
                "seam",
                "find",
                str(tmp_path / "scan.npy"),
                "--model",
                "v-groove",
                "--T-base-cam",
                str(tmp_path / "cal.json"),
                "--nominal",
                str(tmp_path / "nominal.json"),
                "--json",
                *extra,
            ]
        )
        out = json.loads(capsys.readouterr().out)
        assert code == 0 and out["ok"] is True, out
        return np.array(out["seam"]["points_base"])

    plain = seam({"T_base_cam": T_BASE_CAM.tolist()})
    # A calibrate job's result: its range bias moves the scan 8 mm back along the rays
    # (toward the camera above the part), and the seam with it.
    job = {"calibration": {"T_base_cam": T_BASE_CAM.tolist(), "range_bias_mm": 8.0}}
    shift = seam(job) - plain
    assert np.median(shift[:, 2]) == pytest.approx(0.008, abs=0.0015)
    # The option wins over the file.
    np.testing.assert_allclose(seam(job, "--range-bias-mm", "0"), plain, atol=1e-4)


def test_cli_refuses_a_range_bias_that_is_no_scanner_s(tmp_path, capsys) -> None:
    (tmp_path / "cal.json").write_text(json.dumps({"T_base_cam": T_BASE_CAM.tolist(), "range_bias_mm": "8"}))
    for extra in ([], ["--range-bias-mm", "800"]):
        code = celld_main(
            [
                "seam",
                "find",
                str(tmp_path / "scan.npy"),
                "--model",
                "v-groove",
                "--T-base-cam",
                str(tmp_path / "cal.json"),
                "--json",
                *extra,
            ]
        )
        out = json.loads(capsys.readouterr().out)
        assert code == 2 and out["ok"] is False and "range bias" in out["error"]["reason"], out


def test_seam_config_table_is_read_and_checked() -> None:
    from celld.config import TableReader
    from celld.config.seam import read_seam
    from celld.errors import ConfigError

    r = TableReader({"preset": "azure-kinect", "spacing_mm": 2, "seam_source": "groove"}, "cell.toml", "seam")
    params = read_seam(r, "phoxi-m", "right")
    r.done()
    assert params.spacing == pytest.approx(0.002)
    assert (params.seam_source, params.finger_wall, params.table_z) == ("groove", "right", None)
    assert params.registration.voxel == SeamParams.for_scanner("azure-kinect").registration.voxel
    with pytest.raises(ConfigError, match="seam.seam_source"):
        read_seam(TableReader({"seam_source": "cad"}, "cell.toml", "seam"), "phoxi-m", "left")


def _wall_error(part, W_base: np.ndarray, surface) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Signed distances (m) across the seam of points from a simulated part's true wall at their heights."""
    W = se3.apply(se3.invert(part.T_base_plane), W_base)
    out = []
    for p in W:
        line = surface.at(p).P
        o = np.argsort(line[:, 0])
        out.append(p[1] - np.interp(p[0], line[o, 0], line[o, 1]))
    return np.array(out)


def test_the_scan_measures_both_walls_beside_the_seam_where_a_distorted_part_moves_them() -> None:
    from celld.seam.weldpath import wall_offset
    from celld.sim.world import PartShape

    model = example("v-groove")
    shape = PartShape(bow=1.0e-3, twist=math.radians(1.0), gap_amplitude=0.25e-3, gap_waves=2.0, tacks=((0.3, 0.2e-3),))
    built, stations = simscene.distorted_groove("v-groove", shape)
    T_true = _pose(model, seed=5, angle_deg=10.0)
    part = simscene.on_table(built, stations, T_true, "left")
    assert part.far_wall is not None
    path = find_seam(_scan(built, T_true), model, T_BASE_CAM, SeamParams(), T_base_obj_nominal=simscene.nominal_pose(model))
    h = 0.004
    up = path.points_base + h * path.plane_normal
    t = path.wall_across[:, 0] + path.wall_across[:, 1] * h
    t_far = path.far_wall_across[:, 0] + path.far_wall_across[:, 1] * h
    assert np.mean(np.isfinite(t)) > 0.9 and np.mean(np.isfinite(t_far)) > 0.9
    ok = np.isfinite(t) & np.isfinite(t_far)
    measured = _wall_error(part, up[ok] + t[ok, None] * path.normals[ok], part.wall)
    far = _wall_error(part, up[ok] - t_far[ok, None] * path.normals[ok], part.far_wall)
    model_wall = _wall_error(part, up + wall_offset(model, h) * path.normals, part.wall)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    # The gap's variation and the twist move the wall by up to ~0.2 mm from the model's constant
    # offset; the scan's wall fits, smoothed along the seam, follow them (half-resolution PhoXi M).
    assert rms(model_wall) > 0.08e-3
    assert rms(measured) < 0.05e-3 and rms(far) < 0.05e-3, (rms(measured), rms(far), rms(model_wall))
