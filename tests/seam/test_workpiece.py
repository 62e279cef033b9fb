"""Workpiece models: generated geometry, seam files, user meshes and their refusals."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from celld.errors import WorkpieceError
from celld.seam import workpiece as wpm
from celld.seam.workpiece import LEFT_WALL, RIGHT_WALL, Workpiece


@pytest.mark.parametrize("name", list(wpm.EXAMPLES))
def test_examples_are_closed_solids_with_both_walls_and_the_seam_on_them(name: str) -> None:
    wp = wpm.example(name)
    V, F = wp.vertices, wp.triangles
    signed_volume = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0
    assert signed_volume > 0  # outward normals
    assert wp.has_walls
    assert wp.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)  # lies on z = 0
    d = wpm.seam_distance_to_mesh(wp.seam, V, F)
    assert d.max() < 1.5e-3  # the seam runs along the joint (root gap centre: 1 mm off the faces)


def test_v_groove_follows_iso_9692_parameters() -> None:
    t, alpha, b, c = 0.012, math.radians(50.0), 0.003, 0.0015
    wp = wpm.v_groove_butt(thickness=t, groove_angle=alpha, root_gap=b, root_face=c)
    np.testing.assert_allclose(wp.seam[:, 1:], [[0.0, c], [0.0, c]], atol=1e-12)
    top = wp.vertices[np.isclose(wp.vertices[:, 2], t)]
    groove_top_width = 2.0 * np.abs(top[:, 1]).min()
    assert groove_top_width == pytest.approx(b + 2.0 * (t - c) * math.tan(alpha / 2.0), abs=1e-12)
    # Left wall (bevel of the +y plate) faces -y and up, at half the groove angle from vertical.
    m = wp.mesh()
    N = np.asarray(m.triangle_normals)
    left = N[wp.wall_labels == LEFT_WALL]
    np.testing.assert_allclose(left, np.tile([0.0, -math.cos(alpha / 2.0), math.sin(alpha / 2.0)], (len(left), 1)), atol=1e-12)


def test_fillet_seam_is_the_web_flange_corner() -> None:
    wp = wpm.fillet_t_joint(flange_thickness=0.01, web_thickness=0.008, web_offset=0.02)
    np.testing.assert_allclose(wp.seam[:, 1:], [[0.016, 0.01], [0.016, 0.01]], atol=1e-12)
    N = np.asarray(wp.mesh().triangle_normals)
    np.testing.assert_allclose(N[wp.wall_labels == LEFT_WALL], [[0.0, -1.0, 0.0]] * 2, atol=1e-12)
    np.testing.assert_allclose(N[wp.wall_labels == RIGHT_WALL], [[0.0, 0.0, 1.0]] * 2, atol=1e-12)


def test_curved_groove_seam_is_the_arc() -> None:
    R = 0.2
    wp = wpm.curved_groove(radius=R, arc_angle=math.radians(40.0))
    r = np.linalg.norm(wp.seam[:, :2] - [0.0, R], axis=1)
    np.testing.assert_allclose(r, R, atol=1e-12)
    assert wp.seam_length == pytest.approx(R * math.radians(40.0), rel=1e-4)


def _write_mesh_mm(wp: Workpiece, path: Path) -> None:
    m = wp.mesh()
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) * 1e3)
    assert o3d.io.write_triangle_mesh(str(path), m)


def test_user_mesh_and_json_seam_in_millimetres_load_with_walls(tmp_path: Path) -> None:
    ref = wpm.v_groove_butt()
    _write_mesh_mm(ref, tmp_path / "part.stl")
    (tmp_path / "seam.json").write_text(json.dumps({"units": "mm", "points": (ref.seam * 1e3).tolist(), "wall_band": [2.0, 9.0]}))
    wp = wpm.load_workpiece(tmp_path / "part.stl", tmp_path / "seam.json", mesh_units="mm")
    np.testing.assert_allclose(wp.seam, ref.seam, atol=1e-9)
    assert wp.wall_band == pytest.approx((0.002, 0.009))
    assert wp.has_walls
    # The walls found on the mesh are the bevels: left faces -y, right faces +y.
    N = np.asarray(wp.mesh().triangle_normals)
    assert np.all(N[wp.wall_labels == LEFT_WALL][:, 1] < -0.8)
    assert np.all(N[wp.wall_labels == RIGHT_WALL][:, 1] > 0.8)


def test_csv_seam_states_its_units_in_the_header(tmp_path: Path) -> None:
    (tmp_path / "a.csv").write_text("x_mm,y_mm,z_mm\n-75,0,1\n75,0,1\n")
    (tmp_path / "b.csv").write_text("x_m,y_m,z_m\n-0.075,0,0.001\n0.075,0,0.001\n")
    a, b = wpm.read_seam_file(tmp_path / "a.csv"), wpm.read_seam_file(tmp_path / "b.csv")
    np.testing.assert_allclose(a.points, b.points, atol=1e-12)
    (tmp_path / "c.csv").write_text("x,y,z\n-75,0,1\n75,0,1\n")
    with pytest.raises(WorkpieceError, match="unit"):
        wpm.read_seam_file(tmp_path / "c.csv")


def test_model_with_no_seam_is_refused(tmp_path: Path) -> None:
    (tmp_path / "seam.json").write_text(json.dumps({"units": "mm", "points": []}))
    with pytest.raises(WorkpieceError, match="no seam"):
        wpm.read_seam_file(tmp_path / "seam.json")
    ref = wpm.v_groove_butt()
    with pytest.raises(WorkpieceError, match="no seam"):
        Workpiece("p", ref.vertices, ref.triangles, np.zeros((0, 3)), ref.approach, ref.wall_labels)


def test_seam_outside_the_mesh_is_refused() -> None:
    ref = wpm.v_groove_butt()
    off = ref.seam + [0.0, 0.0, 0.02]  # 20 mm above the plates
    with pytest.raises(WorkpieceError, match="outside the mesh"):
        Workpiece("p", ref.vertices, ref.triangles, off, ref.approach, ref.wall_labels)


def test_units_mixed_up_are_named(tmp_path: Path) -> None:
    ref = wpm.v_groove_butt()
    _write_mesh_mm(ref, tmp_path / "part.ply")
    (tmp_path / "seam_mm.json").write_text(json.dumps({"units": "mm", "points": (ref.seam * 1e3).tolist()}))
    (tmp_path / "seam_m_as_mm.json").write_text(json.dumps({"units": "mm", "points": ref.seam.tolist()}))
    # A millimetre mesh read as metres spans 150 m.
    with pytest.raises(WorkpieceError, match="millimetres read as metres"):
        wpm.load_workpiece(tmp_path / "part.ply", tmp_path / "seam_mm.json", mesh_units="m")
    # A seam in metres declared as millimetres is 1000 times too small.
    with pytest.raises(WorkpieceError, match="units|outside the mesh|long"):
        wpm.load_workpiece(tmp_path / "part.ply", tmp_path / "seam_m_as_mm.json", mesh_units="mm")


def test_unreadable_inputs_say_what_was_expected(tmp_path: Path) -> None:
    with pytest.raises(WorkpieceError, match=r"\.stl, \.ply or \.obj"):
        wpm.read_mesh(tmp_path / "part.step")
    with pytest.raises(WorkpieceError, match="not found"):
        wpm.read_mesh(tmp_path / "missing.stl")
    (tmp_path / "s.json").write_text(json.dumps({"units": "inch", "points": [[0, 0, 0], [1, 0, 0]]}))
    with pytest.raises(WorkpieceError, match="'units' must be one of m, mm"):
        wpm.read_seam_file(tmp_path / "s.json")
    with pytest.raises(WorkpieceError, match="unknown example"):
        wpm.example("lap-joint")


def test_workpiece_arrays_are_read_only_copies() -> None:
    wp = wpm.v_groove_butt()
    with pytest.raises(ValueError):
        wp.seam[0, 0] = 1.0
    seam = np.array(wp.seam)
    other = Workpiece("copy", wp.vertices, wp.triangles, seam, wp.approach, wp.wall_labels)
    seam[0, 0] = 5.0
    assert other.seam[0, 0] == wp.seam[0, 0]
