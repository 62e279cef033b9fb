"""Calibration datasets on disk: save a session, load it again, read the reference format.

Owns the files of a calibration session, so that it can be solved again
offline (``celld calib solve DIR``). A session directory holds::

    poses.json            what was captured: flange poses, cloud files, units
    verification.ply      the verification cloud (optional)
    p000.ply, p001.ply    one cloud per calibration pose, camera frame

``poses.json``::

    {"format": "celld.calib.session", "version": 1, "units": "m",
     "flange": "ur10e", "scanner": "phoxi-m", "created": "...Z",
     "verification": {"id": "verification", "cloud": "verification.ply",
                      "T_base_flan": [[...4 x 4, metres...]]},
     "pairs": [{"id": "p000", "cloud": "p000.ply", "T_base_flan": [[...]]}, ...]}

Every file is written atomically (:mod:`celld.fsutil`: temporary file,
fsync, rename, fsync of the directory); ``poses.json`` is rewritten after
each cloud, so a session interrupted at any point is a valid session of the
pairs captured so far. Clouds are binary little-endian PLY, float32 x y z.
An organized cloud (H, W, 3) keeps its image layout: every pixel is written,
NaN where there is no return, and a header comment ``celld organized H W``
lets the reader restore the (H, W, 3) array (the detector works on the image
grid); other readers see an ordinary PLY with NaN points.

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
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike

from celld.calib.detect import to_metres
from celld.calib.rigid import Array
from celld.cloudfile import check_cloud_file
from celld.errors import InputError
from celld.fsutil import atomic_open, write_json
from celld.se3 import check_transform, from_xyz_quat_wxyz

# Name and version of the session format written here.
FORMAT = "celld.calib.session"
VERSION = 1
POSES_FILE = "poses.json"
REFERENCE_FILE = "calib_data.json"
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
    T_base_flan : (4, 4) array | None
        The flange pose, when the session has it.
    cloud_path : Path | None
        The cloud file, if any.
    p_cam : (3,) array | None
        A flange centre recorded with the session (reference format), metres.
    """

    id: str
    p_base: Array
    T_base_flan: Array | None
    cloud_path: Path | None
    p_cam: Array | None = None


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

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(p.id for p in self.pairs)

    def cloud(self, record: PairRecord) -> Array:
        """The cloud of ``record`` in the camera frame, metres, (n, 3)."""
        if record.cloud_path is None:
            raise InputError(f"pair {record.id!r}: the session has no cloud for it")
        return read_cloud(record.cloud_path, self.units)


def _organized_shape(path: Path) -> tuple[int, int] | None:
    """The (H, W) of a cloud written organized by :func:`write_cloud`, from its PLY header."""
    if path.suffix.lower() != ".ply":
        return None
    with path.open("rb") as f:
        head = f.read(_HEADER_BYTES)
    end = head.find(b"end_header")
    for line in head[: end if end >= 0 else len(head)].decode("ascii", "replace").splitlines():
        parts = line.split()
        if parts[:3] == ["comment", "celld", "organized"] and len(parts) == 5 and parts[3].isdigit() and parts[4].isdigit():
            return int(parts[3]), int(parts[4])
    return None


def read_cloud(path: str | Path, units: str) -> Array:
    """Read a PLY or PCD cloud (Open3D) and convert it to metres.

    Returns
    -------
    array
        (H, W, 3) with NaN for no return when the file was written organized
        by :func:`write_cloud`, else (n, 3) finite points; float64, metres.

    Raises
    ------
    InputError
        Missing or unreadable file, no points, or data that do not look like ``units``.
    """
    path = Path(path)
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


def _ply_bytes(P: Array, organized: tuple[int, int] | None) -> bytes:
    layout = "" if organized is None else f"comment celld organized {organized[0]} {organized[1]}\n"
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


def _matrix(T: ArrayLike) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(T)]


class SessionWriter:
    """Writes a session directory one capture at a time (the daemon's online use).

    Parameters
    ----------
    root : path
        The session directory; created if absent. An existing ``poses.json``
        is refused unless ``resume`` (then its pairs are kept and appended to).
    flange, scanner : str
        Preset names recorded for the offline solve.
    """

    def __init__(self, root: str | Path, *, flange: str, scanner: str, resume: bool = False) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
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
        existing = self.root / POSES_FILE
        if existing.exists():
            if not resume:
                raise InputError(f"{existing}: a session is already there (resume it, or choose another directory)")
            self._doc = _read_json(existing)
            _check_header(self._doc, existing)

    @property
    def ids(self) -> list[str]:
        return [p["id"] for p in self._doc["pairs"]]

    def set_verification(self, T_base_flan: ArrayLike, P_cam: ArrayLike) -> None:
        """Save the verification cloud and its flange pose."""
        T = check_transform(T_base_flan, "T_base_flan")
        write_cloud(self.root / "verification.ply", P_cam)
        self._doc["verification"] = {"id": "verification", "cloud": "verification.ply", "T_base_flan": _matrix(T)}
        write_json(self.root / POSES_FILE, self._doc)

    def add_pair(self, T_base_flan: ArrayLike, P_cam: ArrayLike, pair_id: str | None = None) -> str:
        """Save one calibration capture; return its id."""
        T = check_transform(T_base_flan, "T_base_flan")
        pid = pair_id if pair_id is not None else f"p{len(self._doc['pairs']):03d}"
        if not _ID.match(pid) or pid == "verification":
            raise InputError(f"pair id: expected 1-64 letters, digits, '_', '.' or '-' (not 'verification'), got {pid!r}")
        if pid in self.ids:
            raise InputError(f"pair id {pid!r}: already in the session")
        write_cloud(self.root / f"{pid}.ply", P_cam)
        self._doc["pairs"].append({"id": pid, "cloud": f"{pid}.ply", "T_base_flan": _matrix(T)})
        write_json(self.root / POSES_FILE, self._doc)
        return pid


def save_session(
    root: str | Path,
    T_base_flan: Sequence[ArrayLike],
    clouds: Sequence[ArrayLike],
    *,
    flange: str,
    scanner: str,
    ids: Sequence[str] | None = None,
    verification: tuple[ArrayLike, ArrayLike] | None = None,
) -> Session:
    """Save a whole session (poses, clouds, optional ``(T_base_flan_v, P_v_cam)``) and read it back."""
    if len(T_base_flan) != len(clouds):
        raise InputError(f"T_base_flan and clouds: expected the same number, got {len(T_base_flan)} and {len(clouds)}")
    if ids is not None and len(ids) != len(clouds):
        raise InputError(f"ids: expected {len(clouds)} pair ids, got {len(ids)}")
    writer = SessionWriter(root, flange=flange, scanner=scanner)
    if verification is not None:
        writer.set_verification(*verification)
    for i, (T, P) in enumerate(zip(T_base_flan, clouds)):
        writer.add_pair(T, P, None if ids is None else ids[i])
    return load_session(root)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON: {exc}") from exc


def _check_header(doc: Any, path: Path) -> None:
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"{path}: expected a {FORMAT!r} document, got format {doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}")
    if doc.get("version") != VERSION:
        raise InputError(f"{path}: expected version {VERSION}, got {doc.get('version')!r}")
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


def _record(entry: Any, root: Path, where: str) -> PairRecord:
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected an object, got {type(entry).__name__}")
    pid = entry.get("id")
    if not isinstance(pid, str) or not _ID.match(pid):
        raise InputError(f"{where}.id: expected a pair id string, got {pid!r}")
    raw_T = entry.get("T_base_flan")
    if raw_T is None:
        raise InputError(f"{where}.T_base_flan: missing (the flange pose, a 4x4 transform in metres)")
    try:
        T = check_transform(raw_T, f"{where}.T_base_flan")
    except (ValueError, TypeError) as exc:
        raise InputError(f"{where}.T_base_flan: expected a 4x4 rigid transform: {exc}") from exc
    check_reach(T[:3, 3], f"{where}.T_base_flan")
    cloud = entry.get("cloud")
    if cloud is not None and (not isinstance(cloud, str) or Path(cloud).name != cloud):
        raise InputError(f"{where}.cloud: expected a file name in the session directory, got {cloud!r}")
    return PairRecord(id=pid, p_base=T[:3, 3].copy(), T_base_flan=T, cloud_path=None if cloud is None else root / cloud)


def _load_celld(root: Path) -> Session:
    path = root / POSES_FILE
    doc = _read_json(path)
    _check_header(doc, path)
    pairs = tuple(_record(e, root, f"{path.name}: pairs[{i}]") for i, e in enumerate(doc["pairs"]))
    ids = [p.id for p in pairs]
    if len(set(ids)) != len(ids):
        raise InputError(f"{path}: pair ids must be unique")
    ver = doc.get("verification")
    verification = None if ver is None else _record(ver, root, f"{path.name}: verification")
    return Session(root, "celld", pairs, verification, doc.get("flange"), doc.get("scanner"), doc["units"])


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
    doc = _read_json(path)
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{path}: expected an object of entries keyed by index")
    try:
        keys = sorted(doc, key=int)
    except ValueError as exc:
        raise InputError(f"{path}: expected integer keys, got {sorted(doc)[:5]}") from exc
    numbered = sorted(
        ((int(m.group(1)), p) for p in root.iterdir() if (m := _REFERENCE_CLOUD.match(p.name))), key=lambda x: x[0]
    )
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
                T_base_flan=T,
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
