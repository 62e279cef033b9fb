"""Calibration subcommands: ``celld calib solve DIR`` and ``celld calib detect CLOUD``.

``celld calib solve DIR [--json] [--flange PRESET] [--method robust|svd|algorithm1]``
solves a saved session again, offline (this project's ``poses.json`` or the
reference toolbox's ``calib_data.json``). With ``--json`` it prints one JSON
object with ``T_base_cam`` (4 x 4, metres; the compensated one of Eq. 21 with
``--compensate``, as ``stored`` says), ``residuals_mm`` (one per used pair,
aligned with ``pairs``), ``rejected`` (ids), ``pairs`` (ids used) and
``quality`` (the gate's verdict, reasons, warnings, per-pair residuals and
outliers, uncertainty at the workspace centre, e_icp), ``range_bias``
(the scanner's range bias on metal, ``bias_mm`` and ``std_mm``, estimated
with ``--range-bias estimate``, the default for a time-of-flight session),
plus the details of
:meth:`~celld.calib.solve.CalibrationResult.as_dict`. A session of a
scanner on the arm (:mod:`celld.calib.mount`) is solved in its link's frame,
and its transforms are named so (``T_link1_cam``, ...) with ``mount`` beside
them. A failed verdict is a result, not an error: the exit code stays 0.

``celld calib detect CLOUD --flange PRESET --units mm|m [--json]`` finds the
flange in one cloud (PLY or PCD, a ``.npy`` array (n, 3) or (H, W, 3), or a
session's compact ``*.cloud.json``, whose sidecar states its units) and
prints ``center`` and ``radius`` in the cloud's units, the unit ``normal``
and the ``inliers`` count, or ``error`` with the reason.

In ``--json`` mode every failure prints ``{"error": "..."}`` and exits 2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from celld.errors import CelldError, InputError

if TYPE_CHECKING:
    import numpy as np

# Exit code of a refused input or a failed solve (celld.cli's convention).
_EXIT_ERROR = 2


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calib", help="flange-based hand-eye calibration tools")
    psub = p.add_subparsers(dest="calib_command", metavar="ACTION", required=True)

    s = psub.add_parser("solve", help="solve a saved calibration session again, offline")
    s.add_argument("dir", help="session directory (poses.json, or the reference calib_data.json)")
    s.add_argument("--json", action="store_true", help="print the result as one JSON object")
    s.add_argument("--flange", help="flange preset (default: the session's); needed to detect centres in clouds")
    s.add_argument("--method", choices=("robust", "svd", "algorithm1"), help="estimator (default: the config's, robust)")
    s.add_argument("--config", help="cell config whose [calibration] section sets the method, e_icp and Algorithm 1")
    s.add_argument(
        "--compensate", action="store_true", help="report the estimate compensated by Eq. 21 as T_base_cam (needs a verification cloud)"
    )
    s.add_argument("--redetect", action="store_true", help="detect every centre in its cloud, ignoring recorded centres")
    s.add_argument("--scale", action="store_true", help="estimate the scale c of Eq. 11")
    s.add_argument(
        "--range-bias",
        choices=("estimate", "none"),
        help="estimate the scanner's range bias on metal with T_base_cam (default: the config's, else by the session's scanner: "
        "estimate for time of flight)",
    )
    s.add_argument(
        "--arm",
        action="store_true",
        help="also fit the arm's kinematic corrections with T_base_cam from the pairs' joints (celld.calib.kinematic); "
        "needs --config for the robot model and the tool's weight",
    )
    s.set_defaults(func=_solve)

    d = psub.add_parser("detect", help="find the flange centre and normal in one cloud")
    d.add_argument("cloud", help="PLY / PCD file, .npy (n, 3) or (H, W, 3), or a session's compact *.cloud.json")
    d.add_argument("--flange", required=True, help="flange preset, e.g. ur10e or ur10e-wrist")
    d.add_argument("--units", required=True, choices=("mm", "m"), help="units of the cloud")
    d.add_argument("--scanner", help="scanner model whose detection tolerances to use (phoxi-s, phoxi-m, azure-kinect)")
    d.add_argument("--json", action="store_true", help="print the detection as one JSON object")
    d.set_defaults(func=_detect)


def _fail(args: argparse.Namespace, exc: Exception) -> int:
    if not args.json:
        raise exc
    print(json.dumps({"error": str(exc)}))
    return _EXIT_ERROR


def _solve(args: argparse.Namespace) -> int:
    try:
        out = _solve_dict(args)
    except CelldError as exc:
        return _fail(args, exc)
    if args.json:
        print(json.dumps(out, allow_nan=False))
        return 0
    key = "T_base_cam" if "mount" not in out else f"T_{out['mount']}_cam"
    print(f"{key} ({out['method']}, {out['stored']}, {len(out['pairs'])} of {out['n_pairs']} pairs, rms {out['rms_mm']:.3f} mm):")
    for row in out[key]:
        print("  " + "  ".join(f"{x:+.6f}" for x in row))
    for r in out["rejected_detail"]:
        print(f"rejected {r['id']}: {r['reason']}")
    q = out["quality"]
    t = ", ".join("-" if x is None else f"{x:.3f}" for x in q["translation_std_mm"])
    r = ", ".join("-" if x is None else f"{x:.3f}" for x in q["rotation_std_deg"])
    print(f"uncertainty (1 sigma): translation ({t}) mm at the workspace centre, rotation about x, y, z ({r}) deg")
    rb = out["range_bias"]
    if rb["mode"] == "estimate":
        std = "-" if rb["std_mm"] is None else f"{rb['std_mm']:.3f}"
        print(f"range bias on metal: {rb['bias_mm']:.3f} +- {std} mm (1 sigma, from {rb['source']})")
    if out["e_icp"] is not None:
        print(f"e_icp: {json.dumps(out['e_icp'])}")
    print(f"quality: {q['verdict']}")
    for reason in q["reasons"]:
        print(f"  fails: {reason}")
    for warning in q["warnings"]:
        print(f"  warning: {warning}")
    if "arm" in out:
        a = out["arm"]
        print(
            f"arm: {a['pairs']} pairs, rank {a['rank']} of {a['parameters']} (condition {a['condition']:.0f}; held {', '.join(a['held'])}), "
            f"residuals {a['residual_rms_before_mm']:.3f} -> {a['residual_rms_mm']:.3f} mm RMS, "
            f"bounds {a['bound']['poses_mm']:.3f} mm where the poses went, {a['bound']['away_mm']:.3f} mm away from them"
        )
    return 0


def _solve_dict(args: argparse.Namespace) -> dict[str, Any]:
    from celld import config
    from celld.calib.dataset import load_session
    from celld.calib.flange import preset
    from celld.calib.mount import in_frame
    from celld.calib.session import calibrate_session
    from celld.calib.solve import SolveParams

    if args.arm and not args.config:
        raise InputError("--arm: give the cell's --config (its robot model and the tool's weight, tool.mass_kg)")
    session = load_session(args.dir)
    name = args.flange or session.flange
    flange = preset(name) if name else None
    cal = config.load(args.config).calibration if args.config else config.CalibrationConfig()
    overrides: dict[str, Any] = {"with_scale": args.scale}
    if args.range_bias is not None:
        overrides["range_bias"] = args.range_bias
    elif not args.config:
        overrides["range_bias"] = "none" if args.scale else config.range_bias_default("", session.scanner or "")
    if args.method is not None:
        overrides["method"] = args.method
    if args.compensate:
        overrides["compensate"] = True
    params = SolveParams.from_config(cal, **overrides)
    result = calibrate_session(session, flange, params, redetect=args.redetect)
    out = in_frame(result.as_dict(), session.mount)
    out.update({"source": str(Path(args.dir)), "format": session.kind, "flange": name})
    if session.mount.on_arm:
        out["mount"] = session.mount.name
    if args.arm:
        out["arm"] = _arm_fit(session, flange, result.T_base_cam, config.load(args.config), Path(args.dir))
    return out


def _arm_fit(session: Any, flange: Any, T_base_cam: np.ndarray, cfg: Any, where: Path) -> dict[str, Any]:
    """The arm's kinematic calibration from a session's pairs: each flange found again in its cloud (centre and
    face normal, near where ``T_base_cam`` puts it), fitted with the controller's joints of the capture, on the
    controller's own table where the dataset holds it (``kinematics.json``; else the published one)."""
    from celld.calib.dataset import read_json
    from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
    from celld.calib.kinematic import KINEMATICS_FILE, ArmPairs, table_of
    from celld.robot import dynamics

    stored = where / KINEMATICS_FILE
    table = table_of(read_json(stored), cfg.robot.model, str(stored)) if stored.is_file() else None

    if session.mount.on_arm:
        raise InputError(f"--arm: the scanner is on {session.mount.name}; the arm's calibration needs a fixed scanner")
    if flange is None:
        raise InputError("--arm: the flange must be found in each cloud again: give --flange")
    pairs = ArmPairs(flange, PARAMS_BY_SCANNER.get(session.scanner or "", DetectParams()), T_base_cam)
    for rec in session.pairs:
        if rec.q is None or rec.cloud_path is None:
            pairs.skipped.append(f"{rec.id}: no joints or no cloud")
            continue
        pairs.add(rec.id, session.cloud(rec), rec.p_base, rec.q)
    fit = pairs.fit(cfg.robot.model, dynamics.Payload(cfg.tool.mass, cfg.tool.com_flange), table, cfg.calibration.arm_error_prior)
    out = {**fit.report(), "T_base_cam": fit.T_base_cam.tolist(), "pairs": len(pairs.q), "skipped": pairs.skipped}
    return out | ({"kinematics": stored.name} if table is not None else {})


def _read_any_cloud(path: Path, units: str) -> np.ndarray:
    """A cloud file in metres: PLY / PCD (organized if written so by celld), or .npy (n, 3) / (H, W, 3)."""

    from celld.calib.dataset import read_cloud
    from celld.calib.detect import to_metres
    from celld.cloudfile import load_npy

    if path.suffix.lower() != ".npy":
        return read_cloud(path, units)
    if not path.is_file():
        raise InputError(f"{path}: cloud file not found")
    return to_metres(load_npy(path), units)


def _detect(args: argparse.Namespace) -> int:
    from celld.calib.detect import detect_flange
    from celld.calib.detect_params import PARAMS_BY_SCANNER
    from celld.calib.flange import preset

    try:
        flange = preset(args.flange)
        if args.scanner is not None and args.scanner not in PARAMS_BY_SCANNER:
            raise InputError(f"--scanner: expected one of {', '.join(PARAMS_BY_SCANNER)}, got {args.scanner!r}")
        P = _read_any_cloud(Path(args.cloud), args.units)
        det = detect_flange(P, flange, PARAMS_BY_SCANNER.get(args.scanner or ""))
    except CelldError as exc:
        return _fail(args, exc)
    scale = 1e3 if args.units == "mm" else 1.0  # back to the cloud's units at this boundary
    out = {
        "center": (det.center * scale).tolist(),
        "normal": det.normal.tolist(),
        "radius": det.radius * scale,
        "inliers": int(det.inliers),
        "residual": det.residual * scale,
        "coverage": det.coverage,
        "units": args.units,
        "flange": flange.name,
    }
    if args.json:
        print(json.dumps(out))
    else:
        c = ", ".join(f"{x:.4f}" for x in out["center"])
        n = ", ".join(f"{x:.5f}" for x in out["normal"])
        print(
            f"flange {flange.name}: centre ({c}) {args.units}, normal ({n}), radius {out['radius']:.4f} {args.units}, {det.inliers} rim inliers"
        )
    return 0
