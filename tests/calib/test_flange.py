"""Flange models: preset dimensions, a closed mesh with the right volume, the model cloud."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.calib.flange import PRESETS, FlangeModel, preset
from celld.errors import InputError

PRESET_NAMES = (
    "iso9409-1-50-4-m6",
    "iso9409-1-31.5-4-m5",
    "iso9409-1-80-6-m8",
    "ur5",
    "ur10e",
    "franka",
    "aubo-i5",
    "ur10e-wrist",
)


def test_every_preset_named_in_the_issue_exists() -> None:
    assert set(PRESET_NAMES) <= set(PRESETS)
    for name in PRESET_NAMES:
        assert preset(name).name == name


def test_iso_designations_carry_their_standard_dimensions() -> None:
    f = preset("iso9409-1-50-4-m6")
    assert (f.pitch_diameter, f.outer_diameter, f.bore_diameter, f.n_holes) == (0.050, 0.063, 0.0315, 4)
    assert f.hole_diameter == 0.006
    f = preset("iso9409-1-80-6-m8")
    assert (f.pitch_diameter, f.outer_diameter, f.n_holes, f.hole_diameter) == (0.080, 0.100, 6, 0.008)
    f = preset("iso9409-1-31.5-4-m5")
    assert (f.pitch_diameter, f.n_holes, f.hole_diameter) == (0.0315, 4, 0.005)


def test_the_paper_radii_r31_on_the_face_and_45_on_the_ur10e_wrist() -> None:
    # Section 3.2.2: R = 31 mm; section 4.2: the 90 mm wrist circle.
    assert preset("ur10e").circle_radius == pytest.approx(0.031)
    wrist = preset("ur10e-wrist")
    assert wrist.circle_radius == pytest.approx(0.045)
    assert wrist.circle_z == pytest.approx(-0.0065)


def test_unknown_preset_lists_the_known_names() -> None:
    with pytest.raises(InputError, match="known presets: .*ur10e"):
        preset("ur11")


def test_preset_lookup_ignores_case() -> None:
    assert preset("UR10e") is PRESETS["ur10e"]


@pytest.mark.parametrize("name", ["iso9409-1-50-4-m6", "iso9409-1-80-6-m8", "ur10e"])
def test_mesh_is_closed_and_its_volume_matches_the_solid(name: str) -> None:
    f = preset(name)
    mesh = f.mesh()
    assert mesh.is_watertight() and mesh.is_orientable()
    # Volume of the revolved solid minus the bore, the holes and the chamfer ring.
    r_out, r_w = f.outer_diameter / 2, f.wrist_diameter / 2
    solid = math.pi * r_out**2 * f.thickness + math.pi * r_w**2 * f.wrist_depth
    chamfer = 2 * math.pi * (r_out - f.chamfer / 3) * f.chamfer**2 / 2
    bore = math.pi * (f.bore_diameter / 2) ** 2 * f.bore_depth
    holes = float(np.sum(math.pi * f.hole_radii() ** 2 * f.hole_depths()))
    expected = solid - chamfer - bore - holes
    # Positive volume also proves the normals point outwards.
    assert mesh.get_volume() == pytest.approx(expected, rel=2e-3)


def test_mesh_face_is_at_z0_and_points_plus_z() -> None:
    mesh = preset("ur10e").mesh()
    V = np.asarray(mesh.vertices)
    N = np.asarray(mesh.triangle_normals)
    F = np.asarray(mesh.triangles)
    assert V[:, 2].max() == pytest.approx(0.0, abs=1e-12)
    on_face = np.all(np.abs(V[F][:, :, 2]) < 1e-12, axis=1)
    assert on_face.any()
    np.testing.assert_allclose(N[on_face], np.tile([0.0, 0.0, 1.0], (int(on_face.sum()), 1)), atol=1e-9)


def test_model_cloud_lies_on_the_visible_surfaces() -> None:
    f = preset("ur10e")
    P = f.model_cloud(spacing=0.001)
    assert P.shape[1] == 3 and len(P) > 5000
    assert P[:, 2].max() <= 1e-12
    rho = np.hypot(P[:, 0], P[:, 1])
    assert rho.max() <= f.wrist_diameter / 2 + 1e-9
    face = np.abs(P[:, 2]) < 1e-9
    # No face point in the bore, none inside a hole, none beyond the chamfer start.
    assert rho[face].min() >= f.bore_diameter / 2 - 1e-6
    assert rho[face].max() <= f.face_radius + 1e-6
    for (cx, cy), r in zip(f.hole_centres(), f.hole_radii()):
        assert np.hypot(P[face, 0] - cx, P[face, 1] - cy).min() >= r - 1e-6
    # The back cap faces away from the camera and is not sampled.
    assert not np.any(np.abs(P[:, 2] + f.thickness + f.wrist_depth) < 1e-9)


def test_model_cloud_is_deterministic_and_follows_the_spacing() -> None:
    f = preset("iso9409-1-50-4-m6")
    a, b = f.model_cloud(0.001), f.model_cloud(0.001)
    np.testing.assert_array_equal(a, b)
    assert len(f.model_cloud(0.0005)) == pytest.approx(4 * len(a), rel=0.01)


def test_holes_sit_on_the_pitch_circle_half_a_step_from_the_dowel() -> None:
    f = preset("iso9409-1-80-6-m8")
    C = f.hole_centres()
    np.testing.assert_allclose(np.hypot(C[:, 0], C[:, 1]), 0.040, atol=1e-12)
    angles = np.degrees(np.arctan2(C[:, 1], C[:, 0]) - f.dowel_angle) % 360
    np.testing.assert_allclose(np.sort(angles[:-1]), [30, 90, 150, 210, 270, 330], atol=1e-9)
    assert angles[-1] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"pitch_diameter": 0.062}, "must lie between the bore"),
        ({"outer_diameter": float("nan")}, "outer_diameter"),
        ({"n_holes": 0}, "n_holes"),
        ({"wrist_diameter": 0.05}, "wrist_diameter"),
        ({"chamfer": 0.007}, "chamfer"),
    ],
)
def test_impossible_geometry_is_refused(change: dict, message: str) -> None:
    values = dict(
        name="custom",
        pitch_diameter=0.050,
        outer_diameter=0.063,
        bore_diameter=0.0315,
        bore_depth=0.006,
        n_holes=4,
        hole_diameter=0.006,
        dowel_diameter=0.006,
        chamfer=0.0005,
        thickness=0.0065,
    )
    values.update(change)
    with pytest.raises(InputError, match=message):
        FlangeModel(**values)
