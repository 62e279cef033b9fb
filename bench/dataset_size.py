"""Calibration datasets on disk: a 20-pose PhoXi M session as float32 PLY and compact, and the solve on each.

The simulated cell of ``configs/sim-cell.toml`` (as ``celld calib demo``):
the ray-cast PhoXi M at full resolution (2064 x 1544) watches the UR10e
flange at the verification pose and at 20 calibration poses. Every capture
is saved twice, by :class:`celld.calib.dataset.SessionWriter` with
``compact=False`` (float32 PLY, 38 MB a cloud, what celld wrote before) and
by default (a 16-bit depth PNG, the detector's window and coarse grid as
float32 PLY, a JSON sidecar), each given the detection the calibrate job
already has, as the daemon does. Then:

- size on disk of each session (MB = 1e6 bytes, every file), and of the
  compact one by kind of file;
- time to write one cloud (encode and files, with fsync) and to read it back,
  median over the captures;
- the rebuild: the stated precision, the largest error measured off the exact
  pixels, and whether x and y came from the pinhole;
- the solve of each session as ``celld calib solve DIR`` does it (robust,
  Algorithm 1, e_icp): the difference between the two T_base_cam (translation
  mm, rotation deg), and each against the simulator's truth.

Target (dataset issue): <= 60 MB per 20-pose session with no change in the solve.

``--quick`` runs 4 poses (20-80 s here, by load) and extrapolates the session
size to 20; ``--json`` prints one JSON object of the figures as the last line.
A full run writes summary.md and dataset_size.png to bench/out/dataset_size/.
The sessions themselves go to a temporary directory and are deleted.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from _common import pyplot

from celld import config as config_mod
from celld import se3
from celld.calib.dataset import SessionWriter, load_session
from celld.calib.detect import detect_flange
from celld.calib.detect_params import PARAMS_BY_SCANNER
from celld.calib.flange import preset
from celld.calib.poses import calibration_poses
from celld.calib.session import calibrate_session
from celld.calib.solve import SolveParams
from celld.errors import DetectionError
from celld.sim.scanner import SimScanner
from celld.sim.scene import robot_scene

OUT = Path(__file__).resolve().parent / "out" / "dataset_size"
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "sim-cell.toml"
TARGET_MB = 60.0
POSES = 20
KINDS = ("float", "compact")


def file_kind(name: str) -> str:
    """depth.png, roi.ply, grid.ply, x/y.png, cloud.json, poses.json, or ply (a float cloud)."""
    for suffix in ("depth.png", "roi.ply", "grid.ply", "x.png", "y.png", "cloud.json"):
        if name.endswith("." + suffix):
            return suffix
    return name if name == "poses.json" else name.rsplit(".", 1)[-1]


def sizes(root: Path) -> dict[str, int]:
    out: dict[str, int] = defaultdict(int)
    for p in root.iterdir():
        out[file_kind(p.name)] += p.stat().st_size
    return dict(out)


def run(n: int, seed: int, work: Path) -> dict[str, Any]:
    cfg = config_mod.load(CONFIG)
    cal = cfg.calibration
    flange = preset(cal.flange)
    dparams = PARAMS_BY_SCANNER[cfg.scanner.model]
    T_true = cfg.T_base_cam_nominal()  # the simulator's truth; the solves never see it
    scanner = SimScanner(cfg.scanner.model, T_true, seed=seed)
    T_v = se3.from_ur_pose(cal.verification_pose)
    poses = calibration_poses(T_v, cal.pose_box, n, cal.max_tilt, seed=seed)
    writers = {k: SessionWriter(work / k, flange=cal.flange, scanner=cfg.scanner.model, compact=k == "compact") for k in KINDS}
    t_write: dict[str, list[float]] = {k: [] for k in KINDS}
    for i, T in enumerate([T_v, *poses]):
        P = scanner.capture(robot_scene(T, flange)).points
        try:
            det = detect_flange(P, flange, dparams)
        except DetectionError as exc:
            det = exc
        for k, w in writers.items():
            t0 = time.perf_counter()
            if i == 0:
                w.set_verification(T, P, detection=None if isinstance(det, DetectionError) else det)
            else:
                w.add_pair(T, P, detection=det)
            t_write[k].append(time.perf_counter() - t0)
        print(f"capture {i:2d}/{n}: " + ", ".join(f"{k} {t_write[k][-1]:.2f} s" for k in KINDS), flush=True)

    out: dict[str, Any] = {"poses": n, "resolution_px": [scanner.model.width_px, scanner.model.height_px]}
    results = {}
    for k in KINDS:
        session = load_session(work / k)
        t_read = []
        for rec in (session.verification, *session.pairs):
            t0 = time.perf_counter()
            session.cloud(rec)
            t_read.append(time.perf_counter() - t0)
        by_kind = sizes(work / k)
        total = sum(by_kind.values())
        out[f"{k}_mb"] = round(total / 1e6, 2)
        out[f"{k}_write_s_median"] = round(float(np.median(t_write[k])), 3)
        out[f"{k}_read_s_median"] = round(float(np.median(t_read)), 3)
        if k == "compact":
            out["compact_mb_by_file"] = {name: round(b / 1e6, 2) for name, b in sorted(by_kind.items())}
            # 20 poses from these: the verification cloud and poses.json once, the pairs' mean 20 times.
            ver = sum(p.stat().st_size for p in (work / k).glob("verification.*"))
            pairs = total - ver - by_kind.get("poses.json", 0)
            out["compact_mb_per_pair_mean"] = round(pairs / n / 1e6, 3)
            out["compact_mb_20_poses"] = round((ver + by_kind.get("poses.json", 0) + pairs / n * POSES) / 1e6, 2)
        t0 = time.perf_counter()
        results[k] = calibrate_session(session, flange, SolveParams.from_config(cal))
        out[f"{k}_solve_s"] = round(time.perf_counter() - t0, 2)
        dt, dr = se3.error(results[k].T_base_cam, T_true)
        out[f"{k}_vs_truth_mm"] = round(dt * 1e3, 4)
        out[f"{k}_vs_truth_deg"] = round(math.degrees(dr), 5)
    out["float_mb_20_poses"] = round(out["float_mb"] / (n + 1) * (POSES + 1), 1)

    sidecars = [json.loads(p.read_text()) for p in sorted((work / "compact").glob("*.cloud.json"))]
    out["compact_clouds"] = len(sidecars)
    out["depth_unit_mm"] = sorted({d["depth"]["unit_m"] * 1e3 for d in sidecars})
    out["precision_mm"] = max(d["precision_m"] for d in sidecars) * 1e3
    out["max_rebuild_error_mm"] = [round(max(d["max_error_m"][a] for d in sidecars) * 1e3, 5) for a in range(3)]
    out["xy_from_pinhole"] = sum(d["xy"]["model"] == "pinhole" for d in sidecars)
    out["pinhole_error_mm_max"] = max(d["xy"]["pinhole_error_m"] for d in sidecars) * 1e3
    out["window_px_median"] = [
        int(np.median([d["window"]["window_px"][1] - d["window"]["window_px"][0] for d in sidecars])),
        int(np.median([d["window"]["window_px"][3] - d["window"]["window_px"][2] for d in sidecars])),
    ]

    a, b = results["float"], results["compact"]
    dt, dr = se3.error(a.T_base_cam, b.T_base_cam)
    out["solve_diff_mm"] = dt * 1e3
    out["solve_diff_deg"] = math.degrees(dr)
    out["same_pairs"] = a.pair_ids == b.pair_ids and [r.id for r in a.rejected] == [r.id for r in b.rejected]
    out["bit_identical_T_base_cam"] = bool(np.array_equal(a.T_base_cam, b.T_base_cam))
    out["target_mb"] = TARGET_MB
    out["target_met"] = bool(out["compact_mb_20_poses"] <= TARGET_MB and out["same_pairs"] and dt < 1e-6)
    out["load_average_1min"] = round(os.getloadavg()[0], 2)
    return out


def write_outputs(figures: dict[str, Any]) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    lines = ["# dataset_size", "", "| figure | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in figures.items()]
    (OUT / "summary.md").write_text("\n".join(lines) + "\n")
    plt = pyplot("dataset_size")
    if plt is None:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].bar(["float32 PLY", "compact"], [figures["float_mb"], figures["compact_mb"]], color=["0.6", "C0"])
    ax[0].axhline(TARGET_MB, color="k", ls="--", lw=0.8, label=f"target {TARGET_MB:.0f} MB")
    ax[0].set_yscale("log")
    ax[0].set_ylabel(f"MB on disk, {figures['poses']}-pose session")
    ax[0].legend(fontsize=8)
    bottom = 0.0
    for name, mb in figures["compact_mb_by_file"].items():
        ax[1].bar(["compact"], [mb], bottom=bottom, label=f"{name} {mb:.1f} MB")
        bottom += mb
    ax[1].axhline(TARGET_MB, color="k", ls="--", lw=0.8)
    ax[1].set_ylabel("MB, by kind of file")
    ax[1].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(OUT / "dataset_size.png", dpi=100)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 poses, the 20-pose size extrapolated")
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object, last line")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="celld-dataset-size-") as tmp:
        figures = run(4 if args.quick else POSES, args.seed, Path(tmp))
    if not args.quick:
        write_outputs(figures)
    for k, v in figures.items():
        print(f"{k}: {v}")
    if args.json:
        print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
