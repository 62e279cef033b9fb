"""``celld seam``: find a seam in a saved scan, offline.

``celld seam find CLOUD --model MODEL [--json]`` reads one scanner cloud
(camera frame), registers the part model, measures the groove and prints the
seam in the robot base frame with its quality figures. With ``--json`` it
prints exactly one JSON object: ``{"ok": true, "seam": {...}}`` or
``{"ok": false, "error": {"type", "reason", "figures"}}``; lengths in metres.

CLOUD: ``.npy`` ((H, W, 3) organized or (n, 3), NaN for no return), ``.npz``
(array ``points``), or ``.ply`` / ``.pcd``; ``--cloud-units`` says its unit.
MODEL: a shipped example (``v-groove``, ``fillet-t``, ``curved-groove``) or a
mesh file (STL, PLY, OBJ; ``--mesh-units``) with ``--seam`` (JSON or CSV).
The hand-eye transform comes from ``--T-base-cam`` (a JSON 4x4, metres, or
``.npy``; or a calibration JSON with ``T_base_cam``) or from a cell config's
``[scanner] T_base_cam`` (``--config``). A time-of-flight scanner's range bias
on metal (``--range-bias-mm``, default: the calibration file's
``range_bias_mm``, else 0) moves the scan's points back along their rays
first, as the daemon does.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from celld.errors import InputError, ScanError, SeamError, WorkpieceError

if TYPE_CHECKING:
    import numpy as np

# Cloud units accepted at this boundary, to metres.
_UNITS = {"m": 1.0, "mm": 1e-3}
# A range bias beyond this is not a scanner's, mm.
_MAX_RANGE_BIAS_MM = 100.0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("seam", help="seam finding from a workpiece scan")
    psub = p.add_subparsers(dest="seam_command", metavar="ACTION", required=True)
    find = psub.add_parser("find", help="find the seam of a part in a saved scan")
    find.add_argument("cloud", help="scan: .npy, .npz, .ply or .pcd, camera frame")
    find.add_argument("--model", required=True, help="shipped example name, or a mesh file (with --seam)")
    find.add_argument("--seam", help="seam file (JSON or CSV) of a mesh model")
    find.add_argument("--mesh-units", default="mm", choices=tuple(_UNITS), help="units of a mesh model (default mm)")
    find.add_argument("--cloud-units", default="m", choices=tuple(_UNITS), help="units of the cloud (default m)")
    find.add_argument("--T-base-cam", dest="T_base_cam", help="hand-eye transform: JSON 4x4 (m) or .npy")
    find.add_argument("--config", help="cell config whose [scanner] T_base_cam to use")
    find.add_argument(
        "--range-bias-mm",
        dest="range_bias_mm",
        type=float,
        help="the scanner's range bias on metal, mm (default: the --T-base-cam calibration file's range_bias_mm, else 0)",
    )
    find.add_argument("--nominal", help="expected part pose T_base_obj: JSON 4x4 (m) or .npy (orders the seam, limits the search)")
    find.add_argument("--scanner", default="phoxi-m", help="parameter preset: phoxi-s, phoxi-m, azure-kinect")
    find.add_argument("--seam-source", default="auto", choices=("auto", "groove", "model"))
    find.add_argument("--seed", type=int, default=0, help="registration seed")
    find.add_argument("--json", action="store_true", help="print one JSON object")
    find.set_defaults(func=_find)


def _find(args: argparse.Namespace) -> int:
    try:
        path = _run(args)
    except SeamError as exc:
        if args.json:
            print(json.dumps({"ok": False, "error": {"type": type(exc).__name__, "reason": exc.reason, "figures": _finite(exc.figures)}}))
            return 2
        raise
    except InputError as exc:
        if args.json:
            print(json.dumps({"ok": False, "error": {"type": type(exc).__name__, "reason": str(exc), "figures": {}}}))
            return 2
        raise
    if args.json:
        print(json.dumps({"ok": True, "seam": path.to_dict()}))
    else:
        import numpy as np

        q = path.quality
        print(
            f"seam: {len(path.points_base)} points over {path.length * 1e3:.1f} mm ({q.source}), "
            f"start {np.round(path.points_base[0] * 1e3, 2).tolist()} mm, end {np.round(path.points_base[-1] * 1e3, 2).tolist()} mm (base)"
        )
        print(
            f"quality: fitness {q.fitness:.3f}, coverage {q.coverage:.2f}, groove coverage {q.groove_coverage:.2f}, "
            f"groove vs model {q.model_groove_rms * 1e3:.3f} mm RMS, {q.duration:.2f} s"
            + (f" ({q.source_reason})" if q.source_reason else "")
        )
    return 0


def _run(args: argparse.Namespace) -> Any:
    from celld.config.seam import SeamParams
    from celld.seam.pipeline import find_seam
    from celld.seam.workpiece import EXAMPLES, example, load_workpiece

    if args.model in EXAMPLES:
        model = example(args.model)
    else:
        if not args.seam:
            raise WorkpieceError(f"--model {args.model!r} is not a shipped example ({', '.join(EXAMPLES)}): give a mesh file with --seam")
        model = load_workpiece(args.model, args.seam, mesh_units=args.mesh_units)
    from celld.calib.rangebias import correct_range_bias

    T_base_cam = _hand_eye(args)
    bias = _range_bias(args)
    nominal = _matrix_file(args.nominal, "--nominal") if args.nominal else None
    params = SeamParams.for_scanner(args.scanner, seam_source=args.seam_source)
    params = replace(params, registration=replace(params.registration, seed=args.seed))
    cloud = read_cloud(args.cloud, args.cloud_units)
    if bias:
        cloud = correct_range_bias(cloud, bias)
    return find_seam(cloud, model, T_base_cam, params, T_base_obj_nominal=nominal)


def _range_bias(args: argparse.Namespace) -> float:
    """The range bias on metal, m: ``--range-bias-mm``, else the calibration file's ``range_bias_mm``, else 0."""
    value: Any = args.range_bias_mm
    where = "--range-bias-mm"
    if value is None and args.T_base_cam and Path(args.T_base_cam).suffix.lower() != ".npy":
        try:
            doc = json.loads(Path(args.T_base_cam).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            doc = None  # _hand_eye has read it already, or said why not
        if isinstance(doc, dict):
            doc = doc.get("calibration", doc)
            value = doc.get("range_bias_mm") if isinstance(doc, dict) else None
            where = f"range_bias_mm of {args.T_base_cam}"
    if value is None:
        return 0.0
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not abs(value) <= _MAX_RANGE_BIAS_MM:
        raise InputError(f"{where}: expected a range bias within +-{_MAX_RANGE_BIAS_MM:g} mm, got {value!r}")
    return float(value) * 1e-3


def _hand_eye(args: argparse.Namespace) -> np.ndarray:
    if args.T_base_cam:
        return _matrix_file(args.T_base_cam, "--T-base-cam")
    if args.config:
        from celld import config

        return config.load(args.config).T_base_cam_nominal()
    raise InputError("no hand-eye transform: give --T-base-cam FILE or --config CELL.toml")


def _matrix_file(path: str, what: str) -> np.ndarray:
    from celld import se3
    from celld.cloudfile import load_npy

    p = Path(path)
    try:
        if p.suffix.lower() == ".npy":
            value: Any = load_npy(p, max_items=16)
        else:
            value = json.loads(p.read_text(encoding="utf-8"))
            if isinstance(value, dict):
                value = value.get("calibration", value) if isinstance(value.get("calibration"), dict) else value
                value = next((value[k] for k in ("T_base_cam", "T_base_obj", "matrix") if k in value), value)
    except (OSError, ValueError) as exc:
        raise InputError(f"{what} {path}: cannot read a 4x4 matrix: {exc}") from exc
    return se3.check_transform(value, f"{what} {path}")


def read_cloud(path: str | Path, units: str = "m") -> np.ndarray:
    """Read a saved scan as an (H, W, 3) or (n, 3) float array in metres."""
    import numpy as np

    from celld.cloudfile import check_cloud_file, load_npy

    p = Path(path)
    if not p.is_file():
        raise ScanError(f"{p}: cloud file not found")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npy":
            P = load_npy(p)  # the header checked before anything is allocated
        elif suffix == ".npz":
            with np.load(p) as data:
                if "points" not in data:
                    raise ScanError(f"{p}: expected an array named 'points', found {', '.join(data.files) or 'none'}")
                P = data["points"]
        elif suffix in (".ply", ".pcd"):
            import open3d as o3d

            check_cloud_file(p)  # the header against the file's size, before Open3D allocates
            P = np.asarray(o3d.io.read_point_cloud(str(p)).points)
        else:
            raise ScanError(f"{p}: cloud must be .npy, .npz, .ply or .pcd, got {suffix or 'no extension'!r}")
    except (OSError, ValueError, InputError) as exc:
        raise ScanError(f"{p}: cannot read the cloud: {exc}") from exc
    P = np.asarray(P, dtype=np.float32 if np.asarray(P).dtype == np.float32 else np.float64)
    return P * _UNITS[units] if units != "m" else P


def _finite(figures: dict[str, float]) -> dict[str, float | None]:
    return {k: (v if math.isfinite(v) else None) for k, v in figures.items()}
