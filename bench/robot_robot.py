"""Robot-robot calibration (Eq. 5-6 with the camera fixed) on realistic simulated cells, scored against the truth.

The cell is ``configs/sim-cell-two-robots.toml``: a second UR10e across the
table from the welding robot, both in view of the fixed scanner. For each
world seed the real daemon (``celld sim run``) runs one calibrate job with
``robot2`` over the bus: robot 1's eye-on-base calibration, then robot 2's,
then ``T_base1_base2 = T_base1_cam T_base2_cam^-1``. The realistic preset
puts in every error source: each arm's own kinematic error, repeatability
and settling, the capture timing, the scanner's mount, scale and
distortion, each flange as made, and robot 2's base off its drawing by
millimetres and tenths of a degree. Only after the job is the result
compared with the simulator's truth:

- ``at meet``: robot 2's base as calibrated against the truth, at robot 2's
  verification position (where the two robots meet), mm, and in rotation,
  deg; with the job's own 1-sigma there;
- ``hand-over``: where robot 1's flange lands when sent, face to face, to
  meet robot 2's flange over robot 2's calibration box (75 points; both
  arms' kinematic errors count, as on a real cell:
  :func:`celld.sim.score.handover_errors`), mean and max, mm; the same with
  the true ``T_base1_base2`` (what the arms alone cost) and with the drawn
  one (no calibration);
- each robot's quality verdict.

Targets (the cell's; the issue names none for this configuration): the
hand-over mean <= 0.5 mm (two robots each within the calibration's 0.25 mm
targeting), every seed; both verdicts ok.

``--seeds`` (default 1-5; about 3 minutes each at 12 poses per robot, full
resolution); ``--quick``: seed 1, 6 poses per robot at half resolution
(about 2 minutes). ``--json`` prints the figures as one JSON object on the
last line. Exit code 1 when a seed's calibrate job did not succeed (named
on stderr and in the JSON's ``failed``); a missed target is a figure
(``met``), not a failure: 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Failures  # noqa: E402

from celld import se3  # noqa: E402
from celld.sim.cell import run_cell  # noqa: E402
from celld.sim.demo import robot2_figures  # noqa: E402
from celld.sim.score import box_grid, handover_errors  # noqa: E402

HOST, HOST2 = "127.0.0.8", "127.0.0.9"
TARGET_HANDOVER_MM = 0.5


def _config(workdir: Path, seed: int, n_poses: int, resolution: float) -> Path:
    path = workdir / f"cell-{seed}.toml"
    path.write_text(
        f"""
include = ["{ROOT / "configs" / "sim-cell-two-robots.toml"}"]
[cell]
name = "robot-robot-bench"
state_dir = "{workdir / f"state-{seed}"}"
[robot]
host = "{HOST}"
[robot2]
host = "{HOST2}"
[bus]
listen = ["tcp/{HOST}:7447"]
[calibration]
n_poses = {n_poses}
[sim]
preset = "realistic"
seed = {seed}
[sim.scanner]
resolution_scale = {resolution}
"""
    )
    return path


def _stats(e: np.ndarray) -> dict[str, float]:
    ok = e[np.isfinite(e)]
    return {"mean_mm": float(ok.mean()) * 1e3, "max_mm": float(ok.max()) * 1e3, "points": int(len(ok))}


def run_seed(workdir: Path, seed: int, n_poses: int, resolution: float) -> dict[str, Any]:
    cfg_path = _config(workdir, seed, n_poses, resolution)
    t0 = time.monotonic()
    with run_cell(cfg_path, workdir / f"daemon-{seed}.log", timeout=120) as cell:
        _, record = cell.client.submit_and_wait({"kind": "calibrate", "seed": seed, "robot2": True}, timeout=1800)
        cfg, world = cell.config, cell.world
    row: dict[str, Any] = {"seed": seed, "state": record["state"], "seconds": time.monotonic() - t0}
    if record["state"] != "succeeded":
        row["reason"] = record["reason"]
        return row
    assert cfg.robot2 is not None and world.robot2 is not None
    cal = json.loads(Path(record["result"]).read_text())["calibration"]
    entry = cal["robot2"]
    T_est, T_true, T_drawn = np.array(entry["T_base1_base2"]), world.robot2.T_base1_base2, world.robot2.T_base1_base2_drawn
    T_v2 = se3.from_ur_pose(cfg.robot2.verification_pose)
    grid = box_grid(T_v2[:3, 3], cfg.calibration.pose_box)
    q1 = np.array([2.847, -1.401, 2.311, -2.481, 1.571, -1.276])  # robot 1 facing down over the table
    q2 = np.array([2.87, -1.332, 2.218, -2.457, 1.571, -1.3])  # robot 2 at its verification pose
    handover = {
        name: _stats(handover_errors(world, T, grid, T_v2[:3, :3], q1, q2))
        for name, T in (("calibrated", T_est), ("true", T_true), ("drawn", T_drawn))
    }
    row.update(
        robot2_figures(entry, T_true, cfg.robot2.verification_pose),  # meet_mm, meet_std_mm, rotation_deg, from_drawing_mm
        from_drawing_deg=entry["from_drawing_deg"],
        handover=handover,
        verdict1=cal["quality"]["verdict"],
        verdict2=entry["quality"]["verdict"],
        pairs=(cal["pairs"], entry["pairs"]),
    )
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3, 4, 5], help="world seeds (realistic preset)")
    ap.add_argument("--n-poses", type=int, default=12, help="calibration poses per robot")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    seeds, n_poses, resolution = ([1], 6, 0.5) if args.quick else (args.seeds, args.n_poses, 1.0)
    if not seeds or n_poses < 4:
        ap.error("expected at least one seed and 4 poses")
    print(f"robot-robot calibration, realistic worlds {seeds}, {n_poses} poses per robot, resolution x{resolution}")
    head = f"{'seed':>4} {'meet mm':>8} {'1-sigma':>8} {'rot deg':>8} {'drawing mm/deg':>15} {'hand-over mm (mean/max)':>24} {'true T':>12} {'drawn T':>12} {'verdicts':>9} {'s':>5}"
    print(head)
    rows = []
    failures = Failures("robot_robot")
    with tempfile.TemporaryDirectory(prefix="celld-robot-robot-") as tmp:
        for seed in seeds:
            row = run_seed(Path(tmp), seed, n_poses, resolution)
            rows.append(row)
            if row["state"] != "succeeded":
                print(f"{seed:>4} the job {row['state']}: {row['reason']}")
                failures.add(f"seed {seed} calibrate job", f"{row['state']}: {row['reason']}")
                continue
            h = row["handover"]
            print(
                f"{seed:>4} {row['meet_mm']:>8.3f} {row['meet_std_mm']:>8.3f} {row['rotation_deg']:>8.4f} "
                f"{row['from_drawing_mm']:>8.2f}/{row['from_drawing_deg']:<6.2f} "
                f"{h['calibrated']['mean_mm']:>15.3f}/{h['calibrated']['max_mm']:<8.3f} "
                f"{h['true']['mean_mm']:>5.3f}/{h['true']['max_mm']:<6.3f} {h['drawn']['mean_mm']:>5.2f}/{h['drawn']['max_mm']:<6.2f} "
                f"{row['verdict1']}/{row['verdict2']:>4} {row['seconds']:>5.0f}"
            )
    done = [r for r in rows if r["state"] == "succeeded"]
    means = [r["handover"]["calibrated"]["mean_mm"] for r in done]
    met = (
        len(done) == len(rows) and all(m <= TARGET_HANDOVER_MM for m in means) and all(r["verdict1"] == r["verdict2"] == "ok" for r in done)
    )
    if done:
        print(
            f"hand-over mean {min(means):.3f}-{max(means):.3f} mm (median {statistics.median(means):.3f}) against {TARGET_HANDOVER_MM} mm: "
            f"{'met' if met else 'NOT met'}"
        )
    if args.json:
        print(json.dumps({"seeds": rows, "target_handover_mm": TARGET_HANDOVER_MM, "met": met, "failed": failures.jobs}))
    return failures.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
