"""Calibration datasets on disk: save a session, load it again, read the reference format.

Owns the files of a calibration session, so that it can be solved again
offline (``celld calib solve DIR``). A session directory holds::

    poses.json                 what was captured: flange poses, cloud files, units
    verification.cloud.json    the verification cloud (optional), as a pair's
    p000.cloud.json ...        one cloud per calibration pose, camera frame:
    p000.depth.png               the whole image as 16-bit depth
    p000.roi.ply                 the window around the flange, float32, exact
    p000.grid.ply                the detector's coarse grid, float32, exact
    (p000.x.png, p000.y.png)     x and y, when the depth does not rebuild them

``poses.json``::

    {"format": "celld.calib.session", "version": 4, "units": "m",
     "flange": "ur10e", "scanner": "phoxi-m", "created": "...Z",
     "verification": {"id": "verification", "cloud": "verification.cloud.json",
                      "T_base_flange": [[...4 x 4, metres...]]},
     "pairs": [{"id": "p000", "cloud": "p000.cloud.json", "T_base_flange": [[...]]}, ...]}

Each capture keeps the robot's joints when its writer is given them (``"q"``,
6 joints in rad): the arm's kinematic calibration solves from them
(``celld calib solve DIR --arm``). A scanner on the arm (eye-on-arm,
:mod:`celld.calib.mount`) moves with the joints: its session must have them,
and adds the mount and the robot's DH table to the header, so that the
flange is placed in the scanner's link frame as the daemon placed it::

    {..., "version": 4, "mount": "link1",
     "dh": {"d": [...], "a": [...], "alpha": [...]},
     "pairs": [{"id": "p000", ..., "T_base_flange": [[...]], "q": [6 joints, rad]}, ...]}

Every file is written atomically (:mod:`celld.fsutil`: temporary file,
fsync, rename, fsync of the directory); a cloud's sidecar JSON after its
images, ``poses.json`` after each cloud, so a session interrupted at any
point is a valid session of the pairs captured so far.

Compact clouds (the default for organized clouds, :mod:`celld.calib.compact`):
the sidecar ``pNNN.cloud.json`` (format ``celld.calib.cloud``) names the
files and states the units, the precision and the projection::

    {"format": "celld.calib.cloud", "version": 2, "units": "m", "frame": "camera",
     "shape_px": [H, W], "valid_points": n, "precision_m": 5e-05,
     "max_error_m": [ex, ey, ez],            measured off the window and the grid
     "depth": {"file": "p000.depth.png", "unit_m": 0.0001, "offset_m": 0.0},
     "xy": {"model": "pinhole", "fx_px": ..., "fy_px": ..., "cx_px": ..., "cy_px": ...,
            "pinhole_error_m": ...},
         or {"model": "pinhole+residual", "fx_px": ..., ..., "x": {"file": ..., "unit_m": ..., "offset_m": ...},
             "y": {...}, ...}       x = z (col - cx) / fx + the x image's value, y likewise
         or {"model": "images", "x": {"file": ..., "unit_m": ..., "offset_m": ...}, "y": {...}, ...},
     "window": {"file": "p000.roi.ply", "window_px": [row0, row1, col0, col1],
                "source": "detection" | "expected"},
     "grid": {"file": "p000.grid.ply", "window_px": [row0, row1, col0, col1], "stride_px": s}}

The depth PNG is an ordinary 16-bit depth image: z = count x ``unit_m``
(Open3D: ``depth_scale = 1 / unit_m``), 0 for no return, with the pinhole
intrinsics of the sidecar. The two PLY files are organized pieces of the
cloud as the scanner gave it (NaN for no return; any PLY reader opens them):
the window the flange detector's fine pass read
(:attr:`~celld.calib.detect.FlangeDetection.window_px`), and the grid
``[row0:row1:s, col0:col1:s]`` its coarse pass reads (:func:`~celld.calib.detect.coarse_grid`),
so that ``celld calib solve`` finds the same centres, to the bit, in the
compact cloud as in the original. The verification cloud's window also
covers the flange model as the e_icp crop takes it; when the flange is not
found, the window is around where the session's pairs so far put it. A
capture without any window (no detection and no estimate yet), an
unorganized cloud, or a writer asked for ``compact=False`` gets the float32
PLY below.

Float clouds are binary little-endian PLY, float32 x y z (the only format
of version-1 sessions). An organized cloud (H, W, 3) keeps its image layout:
every pixel is written, NaN where there is no return, and a header comment
``celld organized H W`` lets the reader restore the (H, W, 3) array (the
detector works on the image grid); other readers see an ordinary PLY with
NaN points.

The reader also takes the session format of the authors' public toolbox:
``calib_data.json`` (a dict keyed by index: ``p_cam`` in millimetres,
``p_robot`` in metres, ``robot_pose`` as ``[x, y, z, qw, qx, qy, qz]``, metres
and a (w, x, y, z) quaternion) next to numbered ``NN_tool.ply`` clouds in
millimetres. In the toolbox's sample the clouds are numbered with gaps
(01, 02, 04, ...), and the n-th entry goes with the n-th cloud in numeric
order (each cloud's centroid lies next to its entry's ``p_cam``); that is
the rule here, applied only when the counts match.

Clouds are converted to metres where they are read (:func:`~celld.calib.detect.to_metres`).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike

from celld.calib.compact import DEPTH_UNIT, CompactCloud, Image16, Pinhole, Quantizer, check_window, decode, encode, fit_pinhole
from celld.calib.detect import FlangeDetection, coarse_grid, detect_flange, to_metres
from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
from celld.calib.flange import FlangeModel, preset
from celld.calib.mount import ScannerMount, mount_from
from celld.calib.rigid import Array, solve_rigid
from celld.cloudfile import check_cloud_file
from celld.errors import CelldError, InputError
from celld.fsutil import atomic_open, write_bytes, write_json
from celld.log import get_logger
from celld.robot.kinematics import check_q
from celld.se3 import apply, check_transform, from_xyz_quat_wxyz, invert

log = get_logger(__name__)

# Name and version of the session format written here; the versions read.
# Version 2 adds the compact clouds (a version-1 reader would not open them);
# version 3 the scanner's mount on the arm and the joints of each capture (a
# version-2 reader would solve it in the wrong frame); version 4 names each
# flange pose T_base_flange (earlier versions: T_base_flan), one spelling of
# the frame with the code's. Every session is written as version 4.
FORMAT = "celld.calib.session"
VERSION = 4
VERSION_ON_ARM = 3  # the first version that can hold a scanner on the arm
_VERSIONS_READ = (1, 2, 3, 4)
# The flange pose's key by version: its spelling before version 4.
_POSE_KEY = "T_base_flange"
_POSE_KEY_BEFORE_4 = "T_base_flan"
POSES_FILE = "poses.json"
REFERENCE_FILE = "calib_data.json"
# Name and version of a compact cloud's sidecar, and the end of its file name.
CLOUD_FORMAT = "celld.calib.cloud"
# Version 2 adds the x and y images of what the pinhole misses ("pinhole+residual"); version 1 is read too.
CLOUD_VERSION = 2
_CLOUD_VERSIONS_READ = (1, 2)
CLOUD_SUFFIX = ".cloud.json"
# The verification window holds the flange model's extent plus this margin
# around the centre, m: at least sqrt(2) x the 5 mm margin of the e_icp crop
# (a cylinder about the flange axis) so that the crop lies inside it.
_VERIFICATION_MARGIN = 0.010
# A flange that is not found is kept exact within this radius of where the
# session's own estimate puts it, m: the flange and the error of an estimate
# from a few pairs.
_EXPECTED_RADIUS = 0.06
# Pairs found before the writer predicts where a missing flange is (Eq. 9-12 need four).
_MIN_PAIRS_TO_PREDICT = 4
# zlib level and strategy of the PNG images: on a PhoXi M depth image level 3
# is within 1 % of level 9's size at a twentieth of its time (0.3 s), and
# OpenCV's default strategy (run lengths only) is 5 % larger.
_PNG_OPTIONS = [cv2.IMWRITE_PNG_COMPRESSION, 3, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_DEFAULT]
# Numbered clouds of the reference toolbox: "01_tool.ply" (not "01_tool_valid.ply").
_REFERENCE_CLOUD = re.compile(r"^(\d+)_tool\.ply$")
_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
# A PLY header is read from at most this many bytes.
_HEADER_BYTES = 4096


@dataclass(frozen=True)
class PairRecord:
    """One capture of a session.

    Attributes
    ----------
    id : str
    p_base : (3,) array
        The flange centre (TCP) in the base frame, metres.
    T_base_flange : (4, 4) array | None
        The flange pose, when the session has it.
    cloud_path : Path | None
        The cloud file, if any.
    p_cam : (3,) array | None
        A flange centre recorded with the session (reference format), metres.
    q : (6,) array | None
        The robot's joints at the capture, rad (sessions of a scanner on the arm).
    """

    id: str
    p_base: Array
    T_base_flange: Array | None
    cloud_path: Path | None
    p_cam: Array | None = None
    q: Array | None = None


@dataclass(frozen=True)
class Session:
    """A calibration session read from disk (clouds are loaded on demand)."""

    root: Path
    kind: str  # "celld" or "reference"
    pairs: tuple[PairRecord, ...]
    verification: PairRecord | None
    flange: str | None
    scanner: str | None
    units: str  # units of the cloud files
    mount: ScannerMount = ScannerMount()  # where the scanner was fixed

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(p.id for p in self.pairs)

    def flange_position(self, record: PairRecord) -> Array:
        """The flange centre of ``record`` in the frame the scanner is fixed in (the base, or its link), m."""
        if not self.mount.on_arm:
            return record.p_base
        return self.flange_pose(record)[:3, 3].copy()

    def flange_pose(self, record: PairRecord) -> Array:
        """The flange pose of ``record`` in the frame the scanner is fixed in (``T_base_flange`` or ``T_link_flange``)."""
        if record.T_base_flange is None:
            raise InputError(f"pair {record.id!r}: the session has no flange pose for it")
        return self.mount.to_link(record.T_base_flange, record.q)

    def cloud(self, record: PairRecord) -> Array:
        """The cloud of ``record`` in the camera frame, metres, (n, 3)."""
        if record.cloud_path is None:
            raise InputError(f"pair {record.id!r}: the session has no cloud for it")
        return read_cloud(record.cloud_path, self.units)


def _ply_comments(path: Path) -> list[list[str]]:
    """The ``comment`` lines of a PLY header, split into words."""
    with path.open("rb") as f:
        head = f.read(_HEADER_BYTES)
    end = head.find(b"end_header")
    lines = head[: end if end >= 0 else len(head)].decode("ascii", "replace").splitlines()
    return [line.split()[1:] for line in lines if line.startswith("comment ")]


def _organized_shape(path: Path) -> tuple[int, int] | None:
    """The (H, W) of a cloud written organized by :func:`write_cloud`, from its PLY header."""
    if path.suffix.lower() != ".ply":
        return None
    for words in _ply_comments(path):
        if words[:2] == ["celld", "organized"] and len(words) == 4 and words[2].isdigit() and words[3].isdigit():
            return int(words[2]), int(words[3])
    return None


def read_cloud(path: str | Path, units: str) -> Array:
    """Read a cloud and convert it to metres: a compact cloud's sidecar, or a PLY or PCD file (Open3D).

    A compact cloud (``*.cloud.json``, :func:`read_compact_cloud`) states its
    own units; ``units`` is that of the other files.

    Returns
    -------
    array
        (H, W, 3) with NaN for no return when the file was written organized
        (:func:`write_cloud`, :func:`write_compact_cloud`), else (n, 3) finite
        points; float64, metres.

    Raises
    ------
    InputError
        Missing or unreadable file, no points, or data that do not look like ``units``.
    """
    path = Path(path)
    if path.is_file() and path.name.endswith(CLOUD_SUFFIX):
        return read_compact_cloud(path)
    check_cloud_file(path)  # the header against the file's size, before Open3D allocates what it declares
    shape = _organized_shape(path)
    cloud = o3d.io.read_point_cloud(str(path), remove_nan_points=shape is None, remove_infinite_points=shape is None)
    P = np.asarray(cloud.points, dtype=np.float64)
    if len(P) == 0:
        raise InputError(f"{path}: no points read (not a PLY/PCD cloud, or empty)")
    if shape is not None and len(P) == shape[0] * shape[1]:
        P = P.reshape(shape[0], shape[1], 3)
    else:
        P = P[np.all(np.isfinite(P), axis=1)]
    try:
        return np.asarray(to_metres(P, units), dtype=np.float64)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from exc


def _ply_bytes(P: Array, organized: tuple[int, int] | None, comments: Sequence[str] = ()) -> bytes:
    layout = "" if organized is None else f"comment celld organized {organized[0]} {organized[1]}\n"
    layout += "".join(f"comment {c}\n" for c in comments)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment celld calibration cloud, camera frame, metres\n"
        f"{layout}element vertex {len(P)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    return header.encode("ascii") + np.ascontiguousarray(P, dtype="<f4").tobytes()


def write_cloud(path: str | Path, P_cam: ArrayLike) -> int:
    """Atomically write a cloud, metres, as PLY; return the number of points with a return.

    An (n, 3) cloud loses its non-finite points; an organized (H, W, 3) cloud
    is written whole (NaN for no return) with its layout in the header.
    """
    P = np.asarray(P_cam, dtype=np.float64)
    organized = None
    if P.ndim == 3 and P.shape[2] == 3:
        organized = (P.shape[0], P.shape[1])
        P = P.reshape(-1, 3)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"P_cam: expected an (n, 3) or (H, W, 3) cloud, got shape {P.shape}")
    finite = np.all(np.isfinite(P), axis=1)
    if organized is None:
        P = P[finite]
    else:
        P = np.where(finite[:, None], P, np.nan)
    with atomic_open(path) as f:
        f.write(_ply_bytes(P, organized))
    return int(finite.sum())


def _png_bytes(image: np.ndarray, path: Path) -> bytes:
    ok, buf = cv2.imencode(".png", image, _PNG_OPTIONS)
    if not ok:
        raise InputError(f"{path}: OpenCV could not encode the {image.dtype} {image.shape} image as PNG")
    return buf.tobytes()


def _image_doc(image: Image16, file: str) -> dict[str, Any]:
    return {"file": file, "unit_m": image.q.unit, "offset_m": image.q.offset, "no_return": 0}


def write_compact_cloud(
    root: str | Path,
    stem: str,
    P_cam: ArrayLike,
    window_px: ArrayLike,
    source: str,
    grid_px: ArrayLike,
    grid_stride: int,
    depth_unit: float = DEPTH_UNIT,
) -> tuple[str, CompactCloud]:
    """Atomically write an organized cloud in the compact form; return the sidecar's file name and the encoding.

    Files ``<stem>.depth.png``, ``<stem>.roi.ply`` (the window, float32, with
    its place in the image in a header comment), ``<stem>.grid.ply`` (the
    pixels ``[row0:row1:grid_stride, col0:col1:grid_stride]`` of ``grid_px``,
    float32), ``<stem>.x.png`` and ``<stem>.y.png`` when the pinhole does not
    rebuild x and y within the precision, and last the sidecar
    ``<stem>.cloud.json``. ``source`` says where the window came from
    (``detection``, ``expected``).

    Raises
    ------
    InputError
        What :func:`celld.calib.compact.encode` refuses (shape, window, a
        return at or behind the camera).
    """
    root = Path(root)
    c = encode(P_cam, window_px, grid_px, grid_stride, depth_unit)
    H, W = c.shape
    r0, r1, c0, c1 = c.window_px
    depth_file = f"{stem}.depth.png"
    write_bytes(root / depth_file, _png_bytes(c.depth.counts, root / depth_file))
    xy: dict[str, Any] = {"model": "images"}
    if c.pinhole is not None:  # encode leaves x, y out only when the pinhole rebuilds them
        model = "pinhole+residual" if c.xy_residual else "pinhole"
        xy = {"model": model, "fx_px": c.pinhole.fx, "fy_px": c.pinhole.fy, "cx_px": c.pinhole.cx, "cy_px": c.pinhole.cy}
    if c.xy is not None:
        for axis, image in zip("xy", c.xy):
            name = f"{stem}.{axis}.png"
            write_bytes(root / name, _png_bytes(image.counts, root / name))
            xy[axis] = _image_doc(image, name)
    xy["pinhole_error_m"] = c.pinhole_error
    window_file = f"{stem}.roi.ply"
    comment = f"celld window rows {r0}:{r1} cols {c0}:{c1} of a {H} x {W} image, float32 as captured"
    with atomic_open(root / window_file) as f:
        f.write(_ply_bytes(c.window.reshape(-1, 3), (r1 - r0, c1 - c0), [comment]))
    grid_file = f"{stem}.grid.ply"
    g0, g1, h0, h1 = c.grid_px
    comment = f"celld grid rows {g0}:{g1}:{c.grid_stride} cols {h0}:{h1}:{c.grid_stride} of a {H} x {W} image, float32 as captured"
    with atomic_open(root / grid_file) as f:
        f.write(_ply_bytes(c.grid.reshape(-1, 3), c.grid.shape[:2], [comment]))
    doc = {
        "format": CLOUD_FORMAT,
        "version": CLOUD_VERSION,
        "units": "m",
        "frame": "camera",
        "shape_px": [H, W],
        "valid_points": c.valid_count,
        "precision_m": c.precision,
        "max_error_m": [float(e) for e in c.max_error],
        "depth": {**_image_doc(c.depth, depth_file), "quantity": "z along the optical axis"},
        "xy": xy,
        "window": {"file": window_file, "window_px": [r0, r1, c0, c1], "source": source},
        "grid": {"file": grid_file, "window_px": [g0, g1, h0, h1], "stride_px": c.grid_stride},
    }
    name = f"{stem}{CLOUD_SUFFIX}"
    write_json(root / name, doc)
    return name, c


# What each JSON type of a sidecar is called in a message.
_JSON_NAMES = {dict: "an object", list: "a list", str: "a string", int: "an integer", (int, float): "a number"}


def _get(doc: Any, key: str, kind: type | tuple[type, ...], where: str) -> Any:
    value = doc.get(key) if isinstance(doc, dict) else None
    if not isinstance(value, kind) or isinstance(value, bool):
        raise InputError(f"{where}.{key}: expected {_JSON_NAMES[kind]}, got {value!r}")
    return value


def _number(doc: Any, key: str, where: str, positive: bool = False) -> float:
    value = float(_get(doc, key, (int, float), where))
    if not math.isfinite(value) or (positive and value <= 0):
        raise InputError(f"{where}.{key}: expected a {'positive' if positive else 'finite'} number, got {value!r}")
    return value


def _read_png(root: Path, entry: Any, shape: tuple[int, int], where: str) -> Image16:
    name = _get(entry, "file", str, where)
    path = root / Path(name).name
    if not path.is_file():
        raise InputError(f"{path}: image file not found")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint16 or image.shape != shape:
        got = "nothing readable" if image is None else f"{image.dtype} {image.shape}"
        raise InputError(f"{path}: expected a 16-bit {shape[0]} x {shape[1]} PNG, got {got}")
    return Image16(image, Quantizer(_number(entry, "unit_m", where, positive=True), _number(entry, "offset_m", where)))


def read_compact_cloud(path: str | Path) -> Array:
    """Read a compact cloud from its sidecar: (H, W, 3) float64, metres, NaN for no return.

    Exact (float32) in the window and on the grid, within the sidecar's ``precision_m`` elsewhere.

    Raises
    ------
    InputError
        Missing files, a malformed sidecar (the message names the key), or
        images or a window that do not fit it.
    """
    path = Path(path)
    root, where = path.parent, path.name
    doc = read_json(path)
    if _get(doc, "format", str, where) != CLOUD_FORMAT or doc.get("version") not in _CLOUD_VERSIONS_READ:
        raise InputError(
            f"{path}: expected a {CLOUD_FORMAT!r} document of version {' or '.join(map(str, _CLOUD_VERSIONS_READ))}, "
            f"got {doc.get('format')!r} {doc.get('version')!r}"
        )
    if doc.get("units") != "m":
        raise InputError(f"{path}: units: expected 'm', got {doc.get('units')!r}")
    shape_doc = _get(doc, "shape_px", list, where)
    if len(shape_doc) != 2 or not all(isinstance(v, int) and v > 0 for v in shape_doc):
        raise InputError(f"{where}.shape_px: expected [H, W], got {shape_doc!r}")
    shape = (shape_doc[0], shape_doc[1])
    depth = _read_png(root, _get(doc, "depth", dict, where), shape, f"{where}.depth")
    xy_doc = _get(doc, "xy", dict, where)
    model = xy_doc.get("model")
    pinhole, xy = None, None
    models = ("pinhole", "images") if doc["version"] == 1 else ("pinhole", "pinhole+residual", "images")
    if model not in models:
        raise InputError(f"{where}.xy.model: expected {' or '.join(map(repr, models))}, got {model!r}")
    if model != "images":
        fx, fy, cx, cy = (_number(xy_doc, k, f"{where}.xy", positive=k[0] == "f") for k in ("fx_px", "fy_px", "cx_px", "cy_px"))
        pinhole = Pinhole(fx, fy, cx, cy)
    if model != "pinhole":
        x, y = (_read_png(root, _get(xy_doc, a, dict, f"{where}.xy"), shape, f"{where}.xy.{a}") for a in "xy")
        xy = (x, y)
    window_doc = _get(doc, "window", dict, where)
    window_px = check_window(_get(window_doc, "window_px", list, f"{where}.window"), shape)
    r0, r1, c0, c1 = window_px
    window = _read_piece(root, window_doc, (r1 - r0, c1 - c0), f"{where}.window")
    grid_doc = _get(doc, "grid", dict, where)
    g0, g1, h0, h1 = grid_px = check_window(_get(grid_doc, "window_px", list, f"{where}.grid"), shape)
    stride = _get(grid_doc, "stride_px", int, f"{where}.grid")
    if stride < 1:
        raise InputError(f"{where}.grid.stride_px: expected a positive integer, got {stride}")
    grid = _read_piece(root, grid_doc, (len(range(g0, g1, stride)), len(range(h0, h1, stride))), f"{where}.grid")
    compact = CompactCloud(depth, pinhole, xy, None, window_px, window, grid_px, stride, grid, np.zeros(3), model == "pinhole+residual")
    return decode(compact)


def _read_piece(root: Path, entry: dict[str, Any], shape: tuple[int, int], where: str) -> Array:
    """An organized PLY piece of a compact cloud, checked against the (h, w) it must have."""
    piece = read_cloud(root / Path(_get(entry, "file", str, where)).name, "m")
    if piece.shape != (*shape, 3):
        raise InputError(f"{where}: expected an organized {shape[0]} x {shape[1]} cloud, the file holds shape {piece.shape}")
    return piece


def _union(a: tuple[int, int, int, int], b: tuple[int, int, int, int] | None) -> tuple[int, int, int, int]:
    if b is None:
        return a
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])


def _ball_window(P: np.ndarray, centre: np.ndarray, radius: float) -> tuple[int, int, int, int] | None:
    """The bounding window of the pixels of P (H, W, 3) within ``radius`` of ``centre`` (None: no such pixel)."""
    with np.errstate(invalid="ignore"):
        inside = np.sum((P - centre) ** 2, axis=-1) <= radius**2
    rows, cols = np.nonzero(inside)
    if len(rows) == 0:
        return None
    return int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1


def _matrix(T: ArrayLike) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(T)]


class SessionWriter:
    """Writes a session directory one capture at a time (the daemon's online use).

    Organized clouds are written compact (:func:`write_compact_cloud`), exact
    on the detector's coarse grid and in a window around the flange: the
    window the detector's fine pass read (its
    :attr:`~celld.calib.detect.FlangeDetection.window_px`), for the
    verification cloud grown to the flange model's extent as the e_icp crop
    takes it, and for a capture where the flange is not found the
    neighbourhood of where the pairs found so far (four or more, in this
    writer) put it. The writer runs the detector itself, with the session's
    flange and the scanner's parameters (those of the offline solve), unless
    the caller gives its own detection. A capture without a window, and every
    unorganized cloud, is written as a float32 PLY.

    Parameters
    ----------
    root : path
        The session directory; created if absent. An existing ``poses.json``
        is refused unless ``resume`` (then its pairs are kept and appended to;
        the prediction of missing flanges starts afresh).
    flange, scanner : str
        Preset names recorded for the offline solve.
    compact : bool
        Write organized clouds in the compact form (False: float32 PLY).
    depth_unit : float
        Metres per count of the depth images.
    mount : ScannerMount
        Where the scanner is fixed; on the arm, every capture needs its joints.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        flange: str,
        scanner: str,
        resume: bool = False,
        compact: bool = True,
        depth_unit: float = DEPTH_UNIT,
        mount: ScannerMount = ScannerMount(),
    ) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.compact = compact
        self.depth_unit = depth_unit
        self._doc: dict[str, Any] = {
            "format": FORMAT,
            "version": VERSION,
            "units": "m",
            "flange": flange,
            "scanner": scanner,
            "created": datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
            "verification": None,
            "pairs": [],
        }
        self.mount = mount
        if mount.on_arm:
            self._doc |= {"mount": mount.name, "dh": mount.dh_entry()}
        existing = self.root / POSES_FILE
        if existing.exists():
            if not resume:
                raise InputError(f"{existing}: a session is already there (resume it, or choose another directory)")
            self._doc = read_json(existing)
            _check_header(self._doc, existing)
            if mount_from(self._doc, str(existing)) != mount:
                raise InputError(f"{existing}: the session's scanner mount is not this writer's ({mount.name})")
            # An older session goes on in this version: its poses take this version's key.
            for entry in [*self._doc["pairs"], self._doc.get("verification") or {}]:
                if _POSE_KEY_BEFORE_4 in entry:
                    entry[_POSE_KEY] = entry.pop(_POSE_KEY_BEFORE_4)
            self._doc["version"] = VERSION
        self._flange: FlangeModel | None
        try:
            self._flange = preset(flange)
        except InputError:
            self._flange = None  # an unknown preset: no detection, clouds written whole
        self._detect_params = PARAMS_BY_SCANNER.get(scanner)
        self._found: list[tuple[Array, Array]] = []  # (p_base, p_cam) of every flange found

    @property
    def ids(self) -> list[str]:
        return [p["id"] for p in self._doc["pairs"]]

    def set_verification(
        self, T_base_flange: ArrayLike, P_cam: ArrayLike, *, detection: FlangeDetection | None = None, q: ArrayLike | None = None
    ) -> None:
        """Save the verification cloud and its flange pose (``detection``: the caller's, if it has one; ``q``: the joints)."""
        T = check_transform(T_base_flange, "T_base_flange")
        joints = self._joints(q, "verification")
        name = self._write_cloud("verification", self.mount.to_link(T, joints), P_cam, detection, verification=True)
        self._doc["verification"] = {"id": "verification", "cloud": name, _POSE_KEY: _matrix(T)} | self._q_entry(joints)
        write_json(self.root / POSES_FILE, self._doc)

    def _joints(self, q: ArrayLike | None, what: str) -> Array | None:
        """The joints of a capture, required when the scanner is on the arm (kept whenever given: the arm's
        calibration solves from them, :mod:`celld.calib.kinematic`)."""
        if q is None:
            if self.mount.on_arm:
                raise InputError(f"{what}: the scanner is on {self.mount.name}: the capture needs the robot's joints")
            return None
        return check_q(q, f"{what}.q")

    @staticmethod
    def _q_entry(q: Array | None) -> dict[str, Any]:
        return {} if q is None else {"q": [float(v) for v in q]}

    def add_pair(
        self,
        T_base_flange: ArrayLike,
        P_cam: ArrayLike,
        pair_id: str | None = None,
        *,
        detection: FlangeDetection | CelldError | None = None,
        q: ArrayLike | None = None,
    ) -> str:
        """Save one calibration capture; return its id.

        ``detection`` is the caller's detection of the flange in ``P_cam`` (or
        the error it failed with), to spare the writer its own; ``q`` the
        robot's joints (required when the scanner is on the arm).
        """
        T = check_transform(T_base_flange, "T_base_flange")
        pid = pair_id if pair_id is not None else f"p{len(self._doc['pairs']):03d}"
        if not _ID.match(pid) or pid == "verification":
            raise InputError(f"pair id: expected 1-64 letters, digits, '_', '.' or '-' (not 'verification'), got {pid!r}")
        if pid in self.ids:
            raise InputError(f"pair id {pid!r}: already in the session")
        joints = self._joints(q, f"pair {pid}")
        name = self._write_cloud(pid, self.mount.to_link(T, joints), P_cam, detection, verification=False)
        self._doc["pairs"].append({"id": pid, "cloud": name, _POSE_KEY: _matrix(T)} | self._q_entry(joints))
        write_json(self.root / POSES_FILE, self._doc)
        return pid

    def _write_cloud(
        self, stem: str, T: Array, P_cam: ArrayLike, detection: FlangeDetection | CelldError | None, verification: bool
    ) -> str:
        """Write one cloud, compact where it can be; return its file name.

        ``T`` is the flange pose in the frame the scanner is fixed in (the base, or its link).
        """
        P = np.asarray(P_cam)
        if self.compact and P.ndim == 3 and P.shape[2] == 3:
            found = self._window(P, T, detection, verification)
            if found is None:
                log.info("calibration_cloud_whole_no_flange", cloud=stem)
            else:
                grid_px, stride = coarse_grid(P, self._detect_params or DetectParams())
                try:
                    name, c = write_compact_cloud(self.root, stem, P, found[0], found[1], grid_px, stride, self.depth_unit)
                except InputError as exc:
                    log.warning("calibration_cloud_whole_no_compact_form", cloud=stem, reason=str(exc))
                else:
                    log.debug(
                        "calibration_cloud_written_compact",
                        cloud=stem,
                        window_px=c.window_px,
                        source=found[1],
                        xy="pinhole" if c.xy is None else "pinhole+residual" if c.xy_residual else "images",
                        max_error_mm=np.round(c.max_error * 1e3, 4).tolist(),
                    )
                    return name
        write_cloud(self.root / f"{stem}.ply", P)
        return f"{stem}.ply"

    def _window(
        self, P: np.ndarray, T: Array, detection: FlangeDetection | CelldError | None, verification: bool
    ) -> tuple[tuple[int, int, int, int], str] | None:
        """The window to keep exact and where it came from, or None."""
        if detection is None and self._flange is not None:
            try:
                detection = detect_flange(P, self._flange, self._detect_params)
            except CelldError as exc:  # not found, or a cloud the detector refuses: kept all the same
                detection = exc
        if isinstance(detection, FlangeDetection) and detection.window_px is not None:
            self._found.append((T[:3, 3].copy(), np.asarray(detection.center, dtype=np.float64)))
            window = detection.window_px
            if verification and self._flange is not None:
                reach = float(np.max(np.linalg.norm(self._flange.model_cloud(0.002), axis=1))) + _VERIFICATION_MARGIN
                window = _union(window, _ball_window(P, detection.center, reach))
            return window, "detection"
        expected = self._expected_window(P, T)
        return None if expected is None else (expected, "expected")

    def _expected_window(self, P: np.ndarray, T: Array) -> tuple[int, int, int, int] | None:
        """Around the flange centre that the scanner's pose in its frame (``T_base_cam``, or ``T_link_cam``
        on the arm), fitted to the flanges found so far, predicts; ``T`` is the flange in that frame."""
        if len(self._found) < _MIN_PAIRS_TO_PREDICT:
            return None
        P_ref, P_cam = (np.array(v) for v in zip(*self._found))
        try:
            T_ref_cam = solve_rigid(P_ref, P_cam).T_dst_src
        except CelldError:
            return None
        p = apply(invert(T_ref_cam), T[:3, 3][None])[0]
        pinhole = fit_pinhole(P)
        if pinhole is None or p[2] <= _EXPECTED_RADIUS:
            return None
        col, row = pinhole.fx * p[0] / p[2] + pinhole.cx, pinhole.fy * p[1] / p[2] + pinhole.cy
        # Half the width of the ball's image, bounded with its nearest depth.
        half_c, half_r = (f * _EXPECTED_RADIUS / (p[2] - _EXPECTED_RADIUS) for f in (pinhole.fx, pinhole.fy))
        H, W = P.shape[:2]
        r0, r1 = max(math.floor(row - half_r), 0), min(math.ceil(row + half_r) + 1, H)
        c0, c1 = max(math.floor(col - half_c), 0), min(math.ceil(col + half_c) + 1, W)
        return (r0, r1, c0, c1) if r0 < r1 and c0 < c1 else None


def save_session(
    root: str | Path,
    T_base_flange: Sequence[ArrayLike],
    clouds: Sequence[ArrayLike],
    *,
    flange: str,
    scanner: str,
    ids: Sequence[str] | None = None,
    verification: tuple[ArrayLike, ArrayLike] | None = None,
    compact: bool = True,
) -> Session:
    """Save a whole session (poses, clouds, optional ``(T_base_flange_v, P_v_cam)``) and read it back.

    ``compact``: organized clouds in the compact form where a window is found
    (:class:`SessionWriter`), else float32 PLY.
    """
    if len(T_base_flange) != len(clouds):
        raise InputError(f"T_base_flange and clouds: expected the same number, got {len(T_base_flange)} and {len(clouds)}")
    if ids is not None and len(ids) != len(clouds):
        raise InputError(f"ids: expected {len(clouds)} pair ids, got {len(ids)}")
    writer = SessionWriter(root, flange=flange, scanner=scanner, compact=compact)
    if verification is not None:
        writer.set_verification(*verification)
    for i, (T, P) in enumerate(zip(T_base_flange, clouds)):
        writer.add_pair(T, P, None if ids is None else ids[i])
    return load_session(root)


def read_json(path: Path) -> Any:
    """A JSON file of a dataset; InputError naming the file when it cannot be read or is not JSON."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON: {exc}") from exc


def _check_header(doc: Any, path: Path) -> None:
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(
            f"{path}: expected a {FORMAT!r} document, got format {doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}"
        )
    if doc.get("version") not in _VERSIONS_READ:
        raise InputError(f"{path}: expected version {' or '.join(map(str, _VERSIONS_READ))}, got {doc.get('version')!r}")
    if doc.get("units") not in ("m", "mm"):
        raise InputError(f"{path}: units: expected 'm' or 'mm', got {doc.get('units')!r}")
    if not isinstance(doc.get("pairs"), list):
        raise InputError(f"{path}: pairs: expected a list")


# No arm reaches farther from its base than this (a UR16e: 0.9 m, a UR20: 1.75 m), m.
MAX_FLANGE_DISTANCE = 3.0
# Nor does a cell's scanner sit farther from the robot's base, m.
MAX_CAMERA_DISTANCE = 10.0


def check_reach(p_base: Any, where: str) -> Array:
    """``p_base`` (3,) metres, or InputError when no arm could put its flange there (a unit mix-up)."""
    p = np.asarray(p_base, dtype=np.float64)
    d = float(np.linalg.norm(p))
    if d > MAX_FLANGE_DISTANCE:
        raise InputError(
            f"{where}: the flange lies {d:.3g} m from the robot base, beyond any arm's reach "
            f"(at most {MAX_FLANGE_DISTANCE:g} m): are the poses in millimetres? They must be in metres"
        )
    return p


def _record(entry: Any, root: Path, where: str, on_arm: bool = False, key: str = _POSE_KEY) -> PairRecord:
    """One capture of a session; its flange pose under ``key`` (:data:`_POSE_KEY`, or its spelling before version 4)."""
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected an object, got {type(entry).__name__}")
    pid = entry.get("id")
    if not isinstance(pid, str) or not _ID.match(pid):
        raise InputError(f"{where}.id: expected a pair id string, got {pid!r}")
    raw_T = entry.get(key)
    if raw_T is None:
        raise InputError(f"{where}.{key}: missing (the flange pose, a 4x4 transform in metres)")
    try:
        T = check_transform(raw_T, f"{where}.{key}")
    except (ValueError, TypeError) as exc:
        raise InputError(f"{where}.{key}: expected a 4x4 rigid transform: {exc}") from exc
    check_reach(T[:3, 3], f"{where}.{key}")
    cloud = entry.get("cloud")
    if cloud is not None and (not isinstance(cloud, str) or Path(cloud).name != cloud):
        raise InputError(f"{where}.cloud: expected a file name in the session directory, got {cloud!r}")
    q = _vector(entry.get("q"), 6, f"{where}.q")
    if on_arm and q is None:
        raise InputError(f"{where}.q: missing (the robot's joints, rad: the scanner is on the arm)")
    return PairRecord(id=pid, p_base=T[:3, 3].copy(), T_base_flange=T, cloud_path=None if cloud is None else root / cloud, q=q)


def _load_celld(root: Path) -> Session:
    path = root / POSES_FILE
    doc = read_json(path)
    _check_header(doc, path)
    mount = mount_from(doc, str(path))
    if mount.on_arm and doc["version"] < VERSION_ON_ARM:
        raise InputError(f"{path}: a session of a scanner on {mount.name} is version {VERSION_ON_ARM} or later, got {doc['version']}")
    key = _POSE_KEY if doc["version"] >= 4 else _POSE_KEY_BEFORE_4
    pairs = tuple(_record(e, root, f"{path.name}: pairs[{i}]", mount.on_arm, key) for i, e in enumerate(doc["pairs"]))
    ids = [p.id for p in pairs]
    if len(set(ids)) != len(ids):
        raise InputError(f"{path}: pair ids must be unique")
    ver = doc.get("verification")
    verification = None if ver is None else _record(ver, root, f"{path.name}: verification", mount.on_arm, key)
    return Session(root, "celld", pairs, verification, doc.get("flange"), doc.get("scanner"), doc["units"], mount)


def _vector(value: Any, n: int, where: str) -> Array | None:
    if value is None or (isinstance(value, list) and len(value) == 0):
        return None
    ok = isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    arr = np.asarray(value, dtype=np.float64) if ok else None
    if arr is None or arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise InputError(f"{where}: expected {n} finite numbers, got {value!r}")
    return arr


def _load_reference(root: Path) -> Session:
    path = root / REFERENCE_FILE
    doc = read_json(path)
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{path}: expected an object of entries keyed by index")
    try:
        keys = sorted(doc, key=int)
    except ValueError as exc:
        raise InputError(f"{path}: expected integer keys, got {sorted(doc)[:5]}") from exc
    numbered = sorted(((int(m.group(1)), p) for p in root.iterdir() if (m := _REFERENCE_CLOUD.match(p.name))), key=lambda x: x[0])
    by_order = len(numbered) == len(keys)
    pairs = []
    for n, key in enumerate(keys):
        entry = doc[key]
        where = f"{path.name}: {key}"
        if not isinstance(entry, dict):
            raise InputError(f"{where}: expected an object, got {type(entry).__name__}")
        pose = _vector(entry.get("robot_pose"), 7, f"{where}.robot_pose")
        p_robot = _vector(entry.get("p_robot"), 3, f"{where}.p_robot")
        p_cam_mm = _vector(entry.get("p_cam"), 3, f"{where}.p_cam")
        T = None
        if pose is not None:
            T = from_xyz_quat_wxyz(pose[:3], pose[3:])  # [x, y, z, qw, qx, qy, qz], metres
            p_base = check_reach(T[:3, 3], f"{where}.robot_pose").copy()
        elif p_robot is not None:
            p_base = check_reach(p_robot, f"{where}.p_robot")
        else:
            raise InputError(f"{where}: neither robot_pose nor p_robot is given")
        cloud: Path | None = None
        if isinstance(entry.get("point_cloud_dir"), str) and (root / Path(entry["point_cloud_dir"]).name).is_file():
            cloud = root / Path(entry["point_cloud_dir"]).name
        elif by_order:
            cloud = numbered[n][1]
        pairs.append(
            PairRecord(
                id=str(int(key)),
                p_base=p_base,
                T_base_flange=T,
                cloud_path=cloud,
                p_cam=None if p_cam_mm is None else p_cam_mm * 1e-3,  # mm at this boundary
            )
        )
    return Session(root, "reference", tuple(pairs), None, None, None, "mm")


def load_session(root: str | Path) -> Session:
    """Read a session directory: this project's ``poses.json`` or the reference ``calib_data.json``.

    Raises
    ------
    InputError
        No session there, or a malformed file (the message names the file and entry).
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: not a directory")
    if (root / POSES_FILE).is_file():
        return _load_celld(root)
    if (root / REFERENCE_FILE).is_file():
        return _load_reference(root)
    raise InputError(f"{root}: no {POSES_FILE} nor {REFERENCE_FILE} here")
