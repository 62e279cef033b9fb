"""The cell model: shapes and their signed distances, the [cell_model] TOML table, allowed contacts."""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from celld import se3
from celld.config import TableReader
from celld.config.cell_model import read_cell_model
from celld.errors import ConfigError, InputError
from celld.robot.cellmodel import (
    ARM_LINKS,
    Box,
    CellModel,
    CellObject,
    Cylinder,
    Mesh,
    Rod,
    Sphere,
    ToolPart,
)

EXAMPLE = Path(__file__).resolve().parents[2] / "configs" / "cell-models" / "sim-cell.toml"


def read(table: dict[str, Any], source: str = "cell.toml") -> CellModel:
    r = TableReader(table, source, "cell_model")
    model = read_cell_model(r)
    r.done()
    return model


def test_box_signed_distance() -> None:
    box = Box((2.0, 1.0, 0.5))
    P = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 0.0, -0.35], [1.3, 0.9, 0.25], [0.9, 0.0, 0.0]])
    # Inside the centre: the nearest face is z at 0.25; a corner is reached diagonally.
    np.testing.assert_allclose(box.signed_distance(P), [-0.25, 0.5, 0.1, math.hypot(0.3, 0.4), -0.1], atol=1e-12)


def test_cylinder_and_sphere_signed_distance() -> None:
    cyl = Cylinder(radius=0.1, length=0.4)
    P = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.5], [0.4, 0.0, 0.6], [0.05, 0.0, 0.15]])
    np.testing.assert_allclose(cyl.signed_distance(P), [-0.1, 0.2, 0.3, math.hypot(0.3, 0.4), -0.05], atol=1e-12)
    np.testing.assert_allclose(Sphere(0.2).signed_distance(np.array([[0.0, 0.3, 0.4], [0.0, 0.0, 0.1]])), [0.3, -0.1])


def test_rod_signed_distance_is_a_capsules() -> None:
    # Beside the segment, past its ends (round, not flat like a cylinder's), on its axis; length 0 is a sphere.
    rod = Rod(radius=0.1, length=0.4)
    P = np.array([[0.3, 0.0, 0.1], [0.0, 0.0, 0.5], [0.3, 0.0, 0.6], [0.0, 0.0, 0.0], [0.0, 0.0, 0.25]])
    np.testing.assert_allclose(rod.signed_distance(P), [0.2, 0.2, math.hypot(0.3, 0.4) - 0.1, -0.1, -0.05], atol=1e-12)
    np.testing.assert_allclose(Rod(0.2, 0.0).signed_distance(np.array([[0.0, 0.3, 0.4]])), [0.3])
    with pytest.raises(InputError, match="rod length"):
        Rod(0.1, -0.1)


def test_object_distance_uses_its_pose() -> None:
    # A box turned 90 degrees about z: its long x side now runs along the base y axis.
    T = se3.from_ur_pose([1.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2])
    obj = CellObject("bar", Box((1.0, 0.1, 0.1)), T)
    np.testing.assert_allclose(obj.signed_distance(np.array([[1.0, 0.45, 0.0], [1.45, 0.0, 0.0]])), [-0.05, 0.4], atol=1e-12)


def test_mesh_from_a_file_in_mm_matches_the_box(tmp_path: Path, rng: np.random.Generator) -> None:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(200.0, 100.0, 50.0)  # mm, corner at the origin
    mesh.translate([-100.0, -50.0, -25.0])
    mesh.compute_triangle_normals()
    path = tmp_path / "block.stl"
    o3d.io.write_triangle_mesh(str(path), mesh)
    loaded = Mesh.load(path, "mm")
    np.testing.assert_allclose(np.ptp(loaded.vertices, axis=0), [0.2, 0.1, 0.05], atol=1e-9)
    P = rng.uniform(-0.3, 0.3, (500, 3))
    np.testing.assert_allclose(loaded.signed_distance(P), Box((0.2, 0.1, 0.05)).signed_distance(P), atol=1e-6)


def test_an_open_mesh_is_refused(tmp_path: Path) -> None:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    mesh.triangles = o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[:-2])  # one face off
    mesh.compute_triangle_normals()
    path = tmp_path / "open.stl"
    o3d.io.write_triangle_mesh(str(path), mesh)
    with pytest.raises(InputError, match="not closed"):
        Mesh.load(path, "m")
    table = {"objects": [{"name": "clamp", "shape": "mesh", "path": "open.stl", "units": "m", "pose": [0, 0, 0, 0, 0, 0]}]}
    with pytest.raises(ConfigError, match=r"cell_model\.objects\[0\]\.path: .*not closed"):
        read(table, str(tmp_path / "cell.toml"))


def test_the_example_is_the_simulated_cell() -> None:
    model = read(tomllib.loads(EXAMPLE.read_text())["cell_model"], str(EXAMPLE))
    assert [o.name for o in model.objects] == ["table", "scanner", "scanner_mount"]
    assert [p.name for p in model.tool] == ["srm_finger", "srm_tip", "torch"]
    assert model.margin == pytest.approx(0.005)
    objects = {o.name: o for o in model.objects}
    # The table top is z = 0 over x in [0, 1.2], y in [-0.5, 0.5].
    d = objects["table"].signed_distance(np.array([[0.6, 0.0, 0.01], [0.6, 0.0, -0.01], [1.25, 0.0, -0.01]]))
    np.testing.assert_allclose(d, [0.01, -0.01, 0.05], atol=1e-12)
    # The scanner's optics (T_base_cam) sit just inside its body, the glass below them.
    d = objects["scanner"].signed_distance(np.array([[0.6, -0.0125, 1.001], [0.6, -0.0125, 0.99]]))
    np.testing.assert_allclose(d, [-0.001, 0.01], atol=1e-12)
    assert model.allows("base", "table") and not model.allows("wrist3", "table")
    assert model.allows("srm_tip", "workpiece") and model.allows("srm_tip", "table")
    assert not model.allows("srm_finger", "workpiece") and not model.allows("torch", "workpiece")


def test_no_table_means_the_default_cell() -> None:
    model = read({})
    assert [o.name for o in model.objects] == ["table"] and model.tool == ()
    table = model.objects[0]
    # Its top is z = 0 around the base, as far as any UR reaches.
    np.testing.assert_allclose(table.signed_distance(np.array([[1.5, -1.5, 0.002], [0.0, 0.0, -0.002]])), [0.002, -0.002], atol=1e-12)
    assert model.allows("base", "table")
    with_tool = read({"tool": [{"name": "finger", "from": [0, 0, 0], "to": [0, 0, 0.1], "radius": 0.01}]})
    assert [o.name for o in with_tool.objects] == ["table"] and with_tool.tool[0].name == "finger"


@pytest.mark.parametrize(
    "objects, key, reason",
    [
        ([{"name": "a", "shape": "cone", "pose": [0] * 6}], "objects[0].shape", "expected one of box"),
        ([{"name": "a", "shape": "box", "size": [1, 0, 1], "pose": [0] * 6}], "objects[0].size", "positive"),
        ([{"name": "a", "shape": "box", "size": [1, 1, 1]}], "objects[0].pose", "missing"),
        ([{"name": "a", "shape": "sphere", "radius": 0.1, "pose": [0] * 6, "colour": "red"}], "objects[0].colour", "unknown key"),
        ([{"name": "a", "shape": "sphere", "radius": 0.1, "pose": [0] * 6, "allow": ["elbowz"]}], "objects", "allow names \\['elbowz'\\]"),
        ([{"name": "forearm", "shape": "sphere", "radius": 0.1, "pose": [0] * 6}], "objects", "'forearm' is used twice"),
        ([{"name": "m", "shape": "mesh", "path": "nowhere.stl", "units": "mm", "pose": [0] * 6}], "objects[0].path", "file not found"),
        ([{"name": "m", "shape": "mesh", "path": "x.stl", "units": "inch", "pose": [0] * 6}], "objects[0].units", "expected one of m, mm"),
    ],
)
def test_bad_tables_are_refused_with_the_key(objects: list[dict[str, Any]], key: str, reason: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(f"cell_model.{key}: ") + f".*{reason}"):
        read({"objects": objects})


def test_values_are_frozen_and_validated() -> None:
    with pytest.raises(InputError, match="positive length"):
        Cylinder(radius=-0.1, length=1.0)
    with pytest.raises(InputError, match="3 finite coordinates"):
        ToolPart("t", (0.0, 0.0), (0.0, 0.0, 0.1), 0.01)  # type: ignore[arg-type]
    obj = CellObject("box", Box((1.0, 1.0, 1.0)), np.eye(4))
    with pytest.raises(ValueError):
        obj.T_base_obj[0, 3] = 1.0
    model = CellModel.default()
    workpiece = CellObject("workpiece", Box((0.2, 0.1, 0.02)), se3.transform_from(np.eye(3), [0.6, 0.0, 0.01]))
    assert [o.name for o in model.with_object(workpiece).objects] == ["table", "workpiece"]
    assert [o.name for o in model.objects] == ["table"]
    assert set(ARM_LINKS) >= {"base", "forearm", "wrist3"}
