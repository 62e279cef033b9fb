"""Simulated scanner: geometry of the rays, each noise effect, determinism, the robot scene."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest

from celld import se3
from celld.calib.flange import preset
from celld.errors import InputError
from celld.sim.scanner import SCANNER_MODELS, ScannerModel, SceneObject, SimScanner, robot_scene
from celld.sim.scene import box, flange_objects

# The paper's Eq. 19: the camera 1 m above the base, looking down.
T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])

# A small ideal camera for the geometry tests: 160 x 120, no noise, no shadows.
IDEAL = ScannerModel(
    name="ideal",
    kind="structured-light",
    width_px=160,
    height_px=120,
    fx=200.0,
    fy=200.0,
    cx=79.5,
    cy=59.5,
    min_range=0.2,
    max_range=2.0,
    sigma=0.0,
    sigma_range=1.0,
    sigma_exponent=2.0,
    max_incidence=math.radians(89.9),
    dropout_incidence=math.radians(89.9),
)


def plate(depth: float, tilt: float = 0.0, material: str = "matte", size: float = 2.0) -> SceneObject:
    """A thin square plate facing the camera at ``depth`` (camera frame = base frame here)."""
    T = se3.from_xyz_rpy([0.0, 0.0, depth + 0.005], [0.0, tilt, 0.0])
    return SceneObject("plate", box((size, size, 0.01)), T, material)


def test_ideal_scanner_sees_a_plane_at_its_depth_with_pinhole_spacing() -> None:
    cloud = SimScanner(IDEAL, np.eye(4)).capture([plate(0.8)])
    P = cloud.points
    assert P.shape == (120, 160, 3) and P.dtype == np.float32
    np.testing.assert_allclose(P[..., 2], 0.8, atol=1e-6)
    # Neighbouring pixels are depth / f apart: 4 mm here.
    np.testing.assert_allclose(np.diff(P[..., 0], axis=1), 0.8 / 200.0, rtol=1e-4)
    np.testing.assert_allclose(P[60, 80, :2], [0.8 * 0.5 / 200.0, 0.8 * 0.5 / 200.0], atol=1e-6)


def test_the_flange_points_lie_on_the_flange_mesh() -> None:
    flange = preset("ur10e")
    T_base_flange = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.2, -0.1, 0.5])
    objects = robot_scene(T_base_flange, flange)
    model = replace(SCANNER_MODELS["phoxi-m"], sigma=0.0)
    cloud, labels = SimScanner(model, T_BASE_CAM, resolution_scale=0.25).capture_labelled(objects)
    on_flange = (labels == 0) & np.isfinite(cloud.points[..., 2])
    assert on_flange.sum() > 2000
    P_flange = se3.apply(se3.invert(T_base_flange) @ T_BASE_CAM, cloud.points[on_flange])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(flange.mesh()))
    dist = scene.compute_distance(o3d.core.Tensor(P_flange.astype(np.float32))).numpy()
    assert np.max(dist) < 2e-6


@pytest.mark.parametrize(("name", "sigma"), [("phoxi-m", 1e-4), ("phoxi-s", 5e-5), ("azure-kinect", 1.5e-3)])
def test_depth_noise_at_the_reference_range_matches_the_model(name: str, sigma: float) -> None:
    model = SCANNER_MODELS[name]
    scanner = SimScanner(model, np.eye(4), seed=3, resolution_scale=0.1)
    cloud = scanner.capture([plate(model.sigma_range)])
    P = cloud.valid()
    # Range error along each ray: |p| against the exact range of that ray.
    exact = model.sigma_range * np.linalg.norm(P / P[:, 2:3], axis=1)
    err = np.linalg.norm(P, axis=1) - exact
    # sigma grows with the range, so off-axis rays (longer) are noisier.
    z = err / (sigma * (exact / model.sigma_range) ** model.sigma_exponent)
    assert len(P) > 3000
    assert np.std(z) == pytest.approx(1.0, rel=0.05)
    assert abs(np.mean(z)) < 4 / math.sqrt(len(P))


def test_time_of_flight_reads_metal_long_and_matte_true() -> None:
    model = replace(SCANNER_MODELS["azure-kinect"], flying_probability=0.0)
    scanner = SimScanner(model, np.eye(4), seed=1, resolution_scale=0.25)
    for material, bias in (("metal", model.metal_bias), ("matte", 0.0)):
        P = scanner.capture([plate(1.0, material=material)]).valid()
        err = np.linalg.norm(P, axis=1) - np.linalg.norm(P / P[:, 2:3], axis=1)
        assert np.mean(err) == pytest.approx(bias, abs=3e-4)


def test_time_of_flight_puts_flying_pixels_on_depth_steps() -> None:
    step = [plate(0.8, size=0.3), plate(1.2)]
    model = SCANNER_MODELS["azure-kinect"]
    quiet = replace(model, sigma=0.0, flying_probability=0.0)
    Z_clean = SimScanner(quiet, np.eye(4), resolution_scale=0.5).capture(step).points[..., 2]
    Z_fly = SimScanner(replace(model, sigma=0.0), np.eye(4), resolution_scale=0.5).capture(step).points[..., 2]
    between = (Z_fly > 0.81) & (Z_fly < 1.19)
    assert not np.any((Z_clean > 0.81) & (Z_clean < 1.19))
    # The square's outline is about 4 * 0.3 / (0.8 / 252) = 380 pixels long on each side of the step.
    assert 150 < between.sum() < 800


def test_grazing_surfaces_return_nothing() -> None:
    model = replace(SCANNER_MODELS["phoxi-m"], baseline=0.0)
    scanner = SimScanner(model, np.eye(4), resolution_scale=0.05)
    assert np.isfinite(scanner.capture([plate(0.8)]).points[..., 2]).mean() == 1.0
    assert np.isfinite(scanner.capture([plate(0.8, tilt=math.radians(85))]).points[..., 2]).sum() == 0
    # Between dropout_incidence (65 deg) and max_incidence (80 deg) returns thin out.
    frac = np.isfinite(scanner.capture([plate(0.8, tilt=math.radians(72.5))]).points[..., 2]).mean()
    assert 0.05 < frac < 0.95


def test_out_of_range_surfaces_return_nothing() -> None:
    scanner = SimScanner("phoxi-s", np.eye(4), resolution_scale=0.05)
    assert np.isfinite(scanner.capture([plate(0.45)]).points[..., 2]).all()
    assert not np.isfinite(scanner.capture([plate(0.60)]).points[..., 2]).any()


def test_structured_light_projector_casts_shadows_away_from_itself() -> None:
    # A 10 cm square 20 cm above a plane; the projector sits 0.35 m along +x.
    occluder = SceneObject("block", box((0.1, 0.1, 0.01)), se3.transform_from(np.eye(3), [0, 0, 0.6]), "matte")
    scanner = SimScanner(replace(SCANNER_MODELS["phoxi-m"], sigma=0.0), np.eye(4), resolution_scale=0.25)
    cloud, labels = scanner.capture_labelled([occluder, plate(0.8)])
    missing = ~np.isfinite(cloud.points[..., 2]) & (labels == 1)
    cols = np.nonzero(missing)[1]
    centre_col = cloud.points.shape[1] / 2
    # The shadow lies on -x of the block, the side away from the projector.
    assert len(cols) > 500 and np.all(cols < centre_col)


def test_captures_are_deterministic_per_seed() -> None:
    objects = robot_scene(se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0]), preset("ur10e"), clutter_seed=2)
    a = SimScanner("phoxi-m", T_BASE_CAM, seed=5, resolution_scale=0.1).capture(objects).points
    b = SimScanner("phoxi-m", T_BASE_CAM, seed=5, resolution_scale=0.1).capture(objects).points
    c = SimScanner("phoxi-m", T_BASE_CAM, seed=6, resolution_scale=0.1).capture(objects).points
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c, equal_nan=True)


def test_resolution_scale_scales_the_image_and_intrinsics() -> None:
    scanner = SimScanner("phoxi-m", T_BASE_CAM, resolution_scale=0.25)
    assert (scanner.model.width_px, scanner.model.height_px) == (516, 386)
    assert scanner.model.fx == pytest.approx(2270.0 / 4)
    with pytest.raises(InputError, match="resolution_scale"):
        SimScanner("phoxi-m", T_BASE_CAM, resolution_scale=2.0)


def test_valid_returns_only_finite_points() -> None:
    cloud = SimScanner(IDEAL, np.eye(4)).capture([plate(0.8, size=0.5)])
    P = cloud.valid()
    assert P.ndim == 2 and P.shape[1] == 3 and np.isfinite(P).all()
    assert len(P) == np.isfinite(cloud.points[..., 2]).sum() < 160 * 120


def test_robot_scene_puts_the_flange_first_and_the_table_top_at_base_z0() -> None:
    T_base_flange = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0])
    objects = robot_scene(T_base_flange, preset("ur10e"), clutter_seed=4)
    assert objects[0].name == "flange" and objects[0].material == "metal"
    np.testing.assert_array_equal(objects[0].T_base_obj, T_base_flange)
    assert objects[1].name == "wrist" and objects[1].material == "matte"
    table = next(o for o in objects if o.name == "table")
    top = se3.apply(table.T_base_obj, np.asarray(table.mesh.vertices))[:, 2].max()
    assert top == pytest.approx(0.0, abs=1e-12)
    assert any(o.name.startswith("clutter") for o in objects)
    assert not any(o.name.startswith("clutter") for o in robot_scene(T_base_flange, preset("ur10e")))
    # Nothing of the arm stands in front of the flange face.
    T_flange_base = se3.invert(T_base_flange)
    for obj in objects[1:]:
        z = se3.apply(T_flange_base @ obj.T_base_obj, np.asarray(obj.mesh.vertices))[:, 2]
        assert z.max() <= 1e-9 or obj.name in ("table", "base") or obj.name.startswith("clutter")


def test_bad_scene_objects_are_refused() -> None:
    with pytest.raises(InputError, match="material"):
        SceneObject("x", box((0.1, 0.1, 0.1)), np.eye(4), "glass")
    with pytest.raises(InputError, match="T_base_obj"):
        SceneObject("x", box((0.1, 0.1, 0.1)), np.eye(3), "matte")
    with pytest.raises(InputError, match="known: phoxi-m, phoxi-s"):
        SimScanner("phoxi-x", np.eye(4))


def test_roi_casts_only_its_window_of_the_full_size_cloud() -> None:
    quiet = replace(SCANNER_MODELS["phoxi-m"], sigma=0.0)
    full = SimScanner(quiet, np.eye(4), resolution_scale=0.1).capture([plate(0.8)])
    part, labels = SimScanner(quiet, np.eye(4), resolution_scale=0.1, roi_px=(10, 60, 20, 90)).capture_labelled([plate(0.8)])
    assert part.points.shape == full.points.shape
    np.testing.assert_array_equal(part.points[10:60, 20:90], full.points[10:60, 20:90])
    outside = np.ones(part.points.shape[:2], dtype=bool)
    outside[10:60, 20:90] = False
    assert not np.isfinite(part.points[outside]).any() and (labels[outside] == -1).all()
    with pytest.raises(InputError, match="roi_px"):
        SimScanner(quiet, np.eye(4), resolution_scale=0.1, roi_px=(10, 5, 0, 10))


def test_the_tool_flange_is_metal_and_the_wrist_body_has_its_finish() -> None:
    flange = preset("ur10e")
    T = se3.from_xyz_rpy([0.6, 0.0, 0.45], [0.0, 0.0, 0.0])
    tool, wrist = flange_objects(T, flange)
    z_tool = np.asarray(tool.mesh.vertices)[:, 2]
    z_wrist = np.asarray(wrist.mesh.vertices)[:, 2]
    r_wrist = np.linalg.norm(np.asarray(wrist.mesh.vertices)[:, :2], axis=1)
    # The flange stands 6.5 mm proud: everything from its face down to the shoulder (and its
    # 8 mm threaded holes) is the machined flange; the shoulder out to the 90 mm wrist and the
    # wrist behind it are painted.
    assert z_tool.min() == pytest.approx(-flange.hole_depth) and z_tool.max() == pytest.approx(0.0)
    assert np.linalg.norm(np.asarray(tool.mesh.vertices)[:, :2], axis=1).max() == pytest.approx(flange.outer_diameter / 2, rel=1e-6)
    assert z_wrist.max() == pytest.approx(-flange.thickness) and r_wrist.max() == pytest.approx(flange.wrist_diameter / 2, rel=1e-6)
    assert (tool.material, wrist.material) == ("metal", "matte")
    assert len(tool.mesh.triangles) + len(wrist.mesh.triangles) == len(flange.mesh().triangles)
    bare = replace(flange, wrist_finish="metal")
    assert [o.material for o in flange_objects(T, bare)] == ["metal", "metal"]


def test_the_tool_is_drawn_as_built_a_thin_finger_ending_in_the_tip_ball() -> None:
    from celld.config import ToolConfig
    from celld.sim.scene import tool_objects

    T = se3.from_xyz_rpy([0.6, 0.0, 0.25], [0.2, -0.1, 0.3])
    built = ToolConfig(tip_tcp=(0.0008, -0.0011, 0.2009), tip_radius=0.001)
    finger, ball = tool_objects(T, built)
    assert (finger.name, ball.name) == ("srm_finger", "srm_tip")
    p_tip = se3.apply(T, np.array([built.tip_tcp]))[0]
    V_ball = se3.apply(ball.T_base_obj, np.asarray(ball.mesh.vertices))
    assert np.allclose(np.linalg.norm(V_ball - p_tip, axis=1), built.tip_radius, atol=1e-9)
    V = se3.apply(finger.T_base_obj, np.asarray(finger.mesh.vertices))
    axis = T[:3, :3] @ np.asarray(built.tool_z_tcp)
    along = (V - p_tip) @ axis
    across = np.linalg.norm((V - p_tip) - np.outer(along, axis), axis=1)
    assert along.min() == pytest.approx(0.0, abs=1e-9) and along.max() == pytest.approx(np.linalg.norm(built.tip_tcp) - 1e-3, abs=1e-9)
    assert across.max() < built.tip_radius  # thinner than the ball: the ball's end stands out


def test_the_torch_is_drawn_as_built_the_wire_ending_at_the_torch_point_out_of_a_metal_nozzle() -> None:
    from celld.config import ToolConfig
    from celld.sim.scene import tool_objects

    T = se3.from_xyz_rpy([0.6, 0.0, 0.25], [0.2, -0.1, 0.3])
    built = ToolConfig(tip_tcp=(0.0008, -0.0011, 0.2009), wire_diameter=0.0012)
    p_torch = np.array([-0.0296, -0.0019, 0.2004])
    objects = tool_objects(T, built, p_torch)
    assert [(o.name, o.material) for o in objects[2:]] == [("torch_wire", "metal"), ("torch_nozzle", "metal")]
    wire, nozzle = objects[2:]
    end = se3.apply(T, p_torch[None])[0]
    axis = T[:3, :3] @ np.asarray(built.tool_z_tcp)  # along the finger, towards the flange
    for obj, radius, first, last in ((wire, 0.0006, 0.0, 0.015), (nozzle, 0.008, 0.015, 0.055)):
        V = se3.apply(obj.T_base_obj, np.asarray(obj.mesh.vertices))
        along = (V - end) @ axis
        across = np.linalg.norm((V - end) - np.outer(along, axis), axis=1)
        assert along.min() == pytest.approx(first, abs=1e-9) and along.max() == pytest.approx(last, abs=1e-9)
        assert across.max() == pytest.approx(radius, abs=1e-9)
    # Without a torch point, the finger alone.
    assert len(tool_objects(T, built)) == 2
