"""Replay of recorded organized clouds from a directory, in file-name order.

A replay directory holds one capture per file, ``.npy`` or ``.ply``, taken in
sorted file-name order (name them ``0000.npy``, ``0001.npy``, ...); other
files (poses, notes) are left alone. The length unit of the files is declared
(``"m"`` or ``"mm"``) and converted once, where a file is read.

- ``.npy``: an (H, W, 3) float array, written by :func:`numpy.save` (no pickles).
- ``.ply``: ``element vertex`` of H * W points in row-major pixel order with
  ``property float x``, ``y``, ``z`` (other vertex properties are skipped), and
  the grid size in the header, as ``comment width W`` / ``comment height H``
  or ``obj_info width W`` / ``obj_info height H``. ASCII and binary.

Every file's header is checked when the scanner opens, so a malformed file is
refused before the first capture with its name and the reason; the data
itself (length, values) is checked when it is read.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from celld import fsutil
from celld.cloudfile import ply_header
from celld.errors import DeviceError, InputError
from celld.scanner.base import CaptureStats, OrganizedCloud, check_organized

# File suffixes a replay reads.
SUFFIXES = (".npy", ".ply")
# Metres per declared unit.
UNITS = {"m": 1.0, "mm": 1e-3}


class PlyHeader(NamedTuple):
    """What a PLY header declares about an organized cloud."""

    fmt: str  # "ascii", "binary_little_endian", "binary_big_endian"
    width: int
    height: int
    vertex_dtype: np.dtype  # structured dtype of one vertex
    data_offset: int  # bytes before the body


def read_ply_header(path: Path) -> PlyHeader:
    """Parse and check the header of an organized PLY file; InputError names the file and the reason."""
    h = ply_header(path)
    if "width" not in h.grid or "height" not in h.grid:
        raise InputError(
            f"{path}: an organized PLY needs its grid in the header ('comment width W' and 'comment height H'); "
            f"it has {h.n_vertex} vertices and no grid size"
        )
    width, height = h.grid["width"], h.grid["height"]
    if width < 1 or height < 1 or width * height != h.n_vertex:
        raise InputError(f"{path}: header grid {width} x {height} does not match its {h.n_vertex} vertices")
    return PlyHeader(h.fmt, width, height, h.vertex_dtype, h.data_offset)


def _read_ply(path: Path) -> np.ndarray:
    """The (H, W, 3) x, y, z of an organized PLY, in the file's unit."""
    h = read_ply_header(path)
    n = h.width * h.height
    # The body is read with numpy rather than Open3D: Open3D reports a short
    # or garbled body only as a warning and still returns a cloud of the
    # declared size, which would let a damaged file through unseen.
    if h.fmt == "ascii":
        with open(path, "rb") as f:
            f.seek(h.data_offset)
            try:
                table = np.loadtxt(f, dtype=np.float64, max_rows=n, ndmin=2)
            except ValueError as exc:
                raise InputError(f"{path}: unreadable ASCII vertex data: {exc}") from exc
        names = h.vertex_dtype.names or ()
        if table.shape != (n, len(names)):
            raise InputError(f"{path}: expected {n} vertex rows of {len(names)} values, got {table.shape}")
        cols = {name: table[:, i] for i, name in enumerate(names)}
        xyz = np.column_stack([cols["x"], cols["y"], cols["z"]])
    else:
        need = n * h.vertex_dtype.itemsize
        have = path.stat().st_size - h.data_offset
        if have < need:
            raise InputError(f"{path}: truncated: the header declares {need} bytes of vertices, the file has {have}")
        body = np.fromfile(path, dtype=h.vertex_dtype, count=n, offset=h.data_offset)
        xyz = np.column_stack([body["x"], body["y"], body["z"]]).astype(np.float64)
    return xyz.reshape(h.height, h.width, 3)


def _check_npy_header(path: Path) -> tuple[int, int]:
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npy array: {exc}") from exc
    if not isinstance(arr, np.ndarray) or arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"{path}: expected an organized (H, W, 3) array, got shape {getattr(arr, 'shape', None)}")
    if arr.dtype.kind != "f":
        raise InputError(f"{path}: expected float coordinates, got dtype {arr.dtype}")
    return int(arr.shape[0]), int(arr.shape[1])


def _read_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npy array: {exc}") from exc


def read_cloud_file(path: str | Path, units: str = "m") -> np.ndarray:
    """Read one organized cloud file (.npy or .ply) and return (H, W, 3) float32 metres, NaN for no return.

    Raises
    ------
    InputError
        The file is malformed; the message names it and says why.
    """
    path = Path(path)
    if units not in UNITS:
        raise InputError(f"units: expected one of {', '.join(UNITS)}, got {units!r}")
    if path.suffix.lower() == ".npy":
        _check_npy_header(path)
        raw = _read_npy(path)
    elif path.suffix.lower() == ".ply":
        raw = _read_ply(path)
    else:
        raise InputError(f"{path}: expected a .npy or .ply file")
    return check_organized(raw, str(path), UNITS[units])


def write_cloud_file(path: str | Path, points: ArrayLike, units: str = "m") -> Path:
    """Write an (H, W, 3) organized cloud in metres to ``.npy`` or binary ``.ply`` in ``units``.

    NaN (no return) is kept as NaN; the file appears whole or not at all
    (:func:`celld.fsutil.atomic_open`). The inverse of :func:`read_cloud_file`.
    """
    path = Path(path)
    if units not in UNITS:
        raise InputError(f"units: expected one of {', '.join(UNITS)}, got {units!r}")
    P = np.asarray(points, dtype=np.float32)
    if P.ndim != 3 or P.shape[2] != 3:
        raise InputError(f"write_cloud_file: expected an (H, W, 3) cloud, got shape {P.shape}")
    P = P / np.float32(UNITS[units])
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(f"{path}: expected a .npy or .ply file name")
    with fsutil.atomic_open(path) as f:
        if suffix == ".npy":
            np.save(f, P, allow_pickle=False)
        else:
            h, w = P.shape[:2]
            header = (
                "ply\nformat binary_little_endian 1.0\n"
                f"comment celld organized cloud, units {units}\ncomment width {w}\ncomment height {h}\n"
                f"element vertex {h * w}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
            )
            f.write(header.encode("ascii"))
            f.write(P.astype("<f4").tobytes())
    return path


class ReplayScanner:
    """A scanner that replays the organized clouds of a directory.

    Parameters
    ----------
    directory : str or Path
        The replay directory.
    units : str
        Length unit of the files, ``"m"`` or ``"mm"``.
    loop : bool
        Start over after the last file; otherwise a capture past the end
        raises :class:`~celld.errors.DeviceError`.
    clock : callable
        Source of capture stamps, ``time.monotonic_ns`` by default.

    Raises
    ------
    DeviceError
        The directory does not exist or holds no ``.npy`` / ``.ply`` file.
    InputError
        A file's header is malformed (named in the message).
    """

    def __init__(self, directory: str | Path, units: str = "m", loop: bool = False, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.directory = Path(directory)
        if units not in UNITS:
            raise InputError(f"replay units: expected one of {', '.join(UNITS)}, got {units!r}")
        if not self.directory.is_dir():
            raise DeviceError(f"replay directory {self.directory}: not a directory")
        self.units = units
        self.loop = loop
        self._clock = clock
        self.files = sorted(p for p in self.directory.iterdir() if p.suffix.lower() in SUFFIXES and p.is_file())
        if not self.files:
            raise DeviceError(f"replay directory {self.directory}: no {' or '.join(SUFFIXES)} clouds in it")
        self._shapes = [self._check_header(p) for p in self.files]
        self._next = 0
        self._lock = threading.Lock()
        self._stats = CaptureStats()
        self._open = True

    @staticmethod
    def _check_header(path: Path) -> tuple[int, int]:
        if path.suffix.lower() == ".npy":
            return _check_npy_header(path)
        h = read_ply_header(path)
        return h.height, h.width

    @property
    def position(self) -> int:
        """Index of the file the next capture reads."""
        return self._next

    def capture(self) -> OrganizedCloud:
        """Read the next file; see the class for the errors."""
        with self._lock:
            if not self._open:
                raise DeviceError(f"replay {self.directory}: capture after close")
            started = time.monotonic_ns()
            try:
                if self._next >= len(self.files):
                    if not self.loop:
                        raise DeviceError(f"replay {self.directory}: all {len(self.files)} clouds were replayed")
                    self._next = 0
                path = self.files[self._next]
                self._next += 1
                points = read_cloud_file(path, self.units)
            except (DeviceError, InputError) as exc:
                self._stats.failure(exc)
                raise
            stamp = int(self._clock())
            self._stats.success(stamp, started)
            return OrganizedCloud(points=points, stamp_ns=stamp)

    def info(self) -> dict[str, Any]:
        h, w = self._shapes[0]
        return {
            "kind": "replay",
            "model": "replay",
            "device": str(self.directory),
            "width_px": w,
            "height_px": h,
            "files": len(self.files),
            "units": self.units,
            "loop": self.loop,
        }

    def health(self) -> dict[str, Any]:
        out = self._stats.as_dict(self._open)
        out["remaining"] = None if self.loop else len(self.files) - self._next
        return out

    def close(self) -> None:
        self._open = False
