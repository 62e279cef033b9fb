"""Cloud file headers (PLY, PCD), checked against the file's size before any reader allocates.

A reader trusts the point count a header declares: Open3D allocates it
before it reads a byte of the body, so a 245-byte PLY that declares 5e8
points takes tens of gigabytes. :func:`check_cloud_file` reads only the
header and refuses a file whose declared points cannot fit in its body, or
that declares more than :data:`MAX_POINTS`, with an InputError naming the
file and the figures. :func:`ply_header` is the PLY header parser the
replay scanner builds its organized-cloud reader on. :func:`load_npy` does
the same for a ``.npy`` array: numpy allocates the shape its header
declares before it reads the data.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from celld.errors import InputError

# More points than any scanner of the cell gives in one capture (a PhoXi XL: 3.2 M).
MAX_POINTS = 50_000_000
# A header longer than this is not a header.
MAX_HEADER_BYTES = 64 * 1024
# PLY scalar types and their numpy codes.
PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
# The smallest ASCII value and its separator ("0 "): a row of k values takes at least 2 k bytes.
_MIN_ASCII_BYTES = 2
_GRID_RE = re.compile(r"^(?:comment|obj_info)\s+(width|height)\s*[:=]?\s*(\d+)\s*$", re.IGNORECASE)


class PlyHeader(NamedTuple):
    """What a PLY header declares."""

    fmt: str  # "ascii", "binary_little_endian", "binary_big_endian"
    n_vertex: int
    vertex_dtype: np.dtype  # structured dtype of one vertex (binary byte order; native for ascii)
    data_offset: int  # bytes before the body
    grid: dict[str, int]  # "width" / "height" from comments, when given
    other_elements: bool  # elements besides the vertices (faces, ...)


def _read_head(path: Path) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc}") from exc


def ply_header(path: str | Path) -> PlyHeader:
    """Parse and check a PLY header, and that the body can hold the vertices it declares."""
    path = Path(path)
    head = _read_head(path)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header' in the first {MAX_HEADER_BYTES} bytes)")
    nl = head.find(b"\n", end)
    data_offset = (nl + 1) if nl >= 0 else len(head)
    fmt = ""
    grid: dict[str, int] = {}
    n_vertex = -1
    fields: list[tuple[str, str]] = []
    element = ""
    elements: list[str] = []
    for raw in head[:end].decode("ascii", errors="replace").splitlines()[1:]:
        line = raw.strip()
        words = line.split()
        if not words:
            continue
        m = _GRID_RE.match(line)
        if m:
            grid[m.group(1).lower()] = int(m.group(2))
        elif words[0] == "format":
            fmt = words[1] if len(words) > 1 else ""
        elif words[0] == "element":
            element = words[1] if len(words) > 1 else ""
            elements.append(element)
            if element == "vertex":
                n_vertex = int(words[2]) if len(words) > 2 and words[2].isdigit() else -1
        elif words[0] == "property" and element == "vertex":
            if len(words) != 3 or words[1] not in PLY_TYPES:
                raise InputError(f"{path}: vertex property {line!r} is not a scalar PLY type (lists are not supported)")
            fields.append((words[2], PLY_TYPES[words[1]]))
    if fmt not in PLY_FORMATS:
        raise InputError(f"{path}: PLY format {fmt!r} not supported (ascii, binary_little_endian, binary_big_endian)")
    if n_vertex < 0:
        raise InputError(f"{path}: no 'element vertex <count>' in the header")
    if elements[0] != "vertex":
        raise InputError(f"{path}: the vertex element must come first in the file")
    names = [n for n, _ in fields]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        raise InputError(f"{path}: expected vertex properties x, y, z once each, got {names}")
    order = PLY_FORMATS[fmt]
    dtype = np.dtype([(n, (order or "<") + t) for n, t in fields])
    _check_count(path, n_vertex, fmt != "ascii", dtype.itemsize if fmt != "ascii" else _MIN_ASCII_BYTES * len(fields), data_offset)
    return PlyHeader(fmt, n_vertex, dtype, data_offset, grid, len(elements) > 1)


def _check_count(path: Path, n: int, binary: bool, bytes_per_point: int, data_offset: int) -> None:
    if n > MAX_POINTS:
        raise InputError(f"{path}: the header declares {n} points, more than the {MAX_POINTS} any capture has")
    body = path.stat().st_size - data_offset
    need = n * bytes_per_point
    if need > body:
        what = f"{bytes_per_point} bytes each" if binary else f"at least {bytes_per_point} characters each"
        raise InputError(
            f"{path}: the header declares {n} points ({what}, {need} bytes) but the file holds {max(body, 0)} bytes after "
            "its header: truncated or a forged header"
        )


def pcd_points(path: str | Path) -> int:
    """Check a PCD header against the file's size; return its point count."""
    path = Path(path)
    head = _read_head(path)
    fields: dict[str, list[str]] = {}
    offset = 0
    data = ""
    for raw in head.split(b"\n"):
        offset += len(raw) + 1
        line = raw.decode("ascii", errors="replace").strip()
        if not line or line.startswith("#"):
            continue
        words = line.split()
        fields[words[0].upper()] = words[1:]
        if words[0].upper() == "DATA":
            data = words[1].lower() if len(words) > 1 else ""
            break
    else:
        raise InputError(f"{path}: not a PCD file (no DATA line in the first {MAX_HEADER_BYTES} bytes)")
    try:
        if "POINTS" in fields:
            n = int(fields["POINTS"][0])
        else:
            n = int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
        sizes = [int(s) for s in fields.get("SIZE", [])]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(sizes))]
    except (KeyError, IndexError, ValueError) as exc:
        raise InputError(f"{path}: unreadable PCD header ({exc})") from exc
    if n < 0 or not sizes or len(counts) != len(sizes) or min(sizes + counts) < 1:
        raise InputError(f"{path}: PCD header with {n} points, sizes {sizes}, counts {counts}")
    if data == "binary":
        _check_count(path, n, True, sum(s * c for s, c in zip(sizes, counts, strict=True)), offset)
    elif data == "ascii":
        _check_count(path, n, False, _MIN_ASCII_BYTES * sum(counts), offset)
    elif data == "binary_compressed":
        if n > MAX_POINTS:
            raise InputError(f"{path}: the header declares {n} points, more than the {MAX_POINTS} any capture has")
    else:
        raise InputError(f"{path}: PCD DATA {data!r} not supported (ascii, binary, binary_compressed)")
    return n


def check_cloud_file(path: str | Path) -> int:
    """Check a .ply or .pcd file's header against its size before a reader allocates; return its point count.

    Raises
    ------
    InputError
        Not found, another format, a malformed header, or more points declared than the file holds.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: cloud file not found")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return ply_header(path).n_vertex
    if suffix == ".pcd":
        return pcd_points(path)
    raise InputError(f"{path}: expected a .ply or .pcd cloud, got {suffix or 'no suffix'}")


def load_npy(path: str | Path, max_items: int = 3 * MAX_POINTS) -> np.ndarray:
    """A ``.npy`` array of numbers, its header checked before anything is allocated.

    Refused with an InputError naming the file: not a ``.npy`` file, an
    object or non-numeric dtype, a shape whose data the file cannot hold, or
    more than ``max_items`` values.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _fortran, dtype = np.lib.format.read_array_header_1_0(f)
            elif version in ((2, 0), (3, 0)):
                shape, _fortran, dtype = np.lib.format.read_array_header_2_0(f)
            else:
                raise InputError(f"{p}: .npy format version {version} is not supported")
            offset = f.tell()
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: not a readable .npy array: {exc}") from exc
    if dtype.hasobject or dtype.kind not in "biuf":
        raise InputError(f"{p}: expected an array of numbers, the header declares dtype {dtype}")
    items = int(np.prod(shape, dtype=np.float64)) if shape else 1
    if items > max_items:
        raise InputError(f"{p}: the header declares {items} values (shape {shape}); at most {max_items} are read")
    body = p.stat().st_size - offset
    if items * dtype.itemsize > body:
        raise InputError(f"{p}: the header declares shape {shape} of {dtype} ({items * dtype.itemsize} bytes), the file holds {body}")
    try:
        return np.array(np.load(p, mmap_mode="r", allow_pickle=False))
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: not a readable .npy array: {exc}") from exc
