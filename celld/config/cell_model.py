"""The ``[cell_model]`` table: the cell's objects, the tool on the flange, the margin.

The shape of the table is documented in :mod:`celld.robot.cellmodel`, which
holds the model itself (pure geometry, no config); this module reads and
checks the table into it. A mesh's ``path`` is relative to the config file.
"""

from __future__ import annotations

from pathlib import Path

from celld import se3
from celld.config.reader import TableReader
from celld.errors import InputError
from celld.robot.cellmodel import DEFAULT_MARGIN, MESH_UNITS, Box, CellModel, CellObject, Cylinder, Mesh, Shape, Sphere, ToolPart


def read_cell_model(r: TableReader) -> CellModel:
    """Validate a ``[cell_model]`` table; ConfigError names the key and the reason.

    Without ``objects`` the objects of :meth:`CellModel.default` are used (a
    table top at base z = 0 all around the base); without ``tool`` the flange
    carries none.
    """
    margin = r.float("margin_mm", DEFAULT_MARGIN * 1e3, lo=0.0, hi=500.0, scale=1e-3)
    objects = tuple(_read_object(sub) for sub in r.tables("objects")) if r.has("objects") else CellModel.default().objects
    tool = tuple(_read_tool_part(sub) for sub in r.tables("tool"))
    try:
        return CellModel(objects=objects, tool=tool, margin=margin)
    except InputError as exc:
        raise r.error("objects", str(exc)) from exc


def _length(r: TableReader, key: str) -> float:
    return r.float(key, lo=0.0, hi=100.0, open_lo=True)


def _name(r: TableReader) -> str:
    name = r.str("name")
    if not name or any(c.isspace() for c in name):
        raise r.error("name", f"expected a name without white space, got {name!r}")
    return name


def _read_object(r: TableReader) -> CellObject:
    name = _name(r)
    kind = r.str("shape", choices=("box", "cylinder", "sphere", "mesh"))
    shape: Shape
    if kind == "box":
        size = r.vector("size", 3)
        if not all(v > 0.0 for v in size):
            raise r.error("size", f"expected 3 positive edge lengths (m), got {list(size)}")
        shape = Box(size)  # type: ignore[arg-type]
    elif kind == "cylinder":
        shape = Cylinder(_length(r, "radius"), _length(r, "length"))
    elif kind == "sphere":
        shape = Sphere(_length(r, "radius"))
    else:
        units = r.str("units", choices=tuple(MESH_UNITS))
        path = Path(r.str("path"))
        if not path.is_absolute():
            path = Path(r.source).parent / path
        try:
            shape = Mesh.load(path, units)
        except InputError as exc:
            raise r.error("path", str(exc)) from exc
    pose = r.vector("pose", 6)
    allow = r.names("allow")
    r.done()
    return CellObject(name, shape, se3.from_ur_pose(pose), allow)


def _read_tool_part(r: TableReader) -> ToolPart:
    part = ToolPart(_name(r), r.vector("from", 3), r.vector("to", 3), _length(r, "radius"), r.names("allow"))  # type: ignore[arg-type]
    r.done()
    return part
