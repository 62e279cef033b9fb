"""Collision checks before motion: time to check a calibration plan and a weld line.

The simulated cell of configs/cell-models/sim-cell.toml (table, PhoXi M and its
mount, the SRM finger and torch on the flange) with a UR10e at the simulated
robot's home (configs/sim-cell.toml), through celld.robot.collision.Checker:

- calibration plan: the verification pose (0.6, 0, 0.45) m, flange up, then
  20 poses of ``celld.calib.poses.calibration_poses`` in the 0.3 x 0.3 x 0.2 m
  box with tilts up to 0.3 rad, one plan per seed; ``check_plan`` from the
  home joints, wall clock, the tool on. Each move is a straight TCP line
  solved and checked at most 5 mm of motion of any point of the arm apart;
- weld line: a 150 mm straight line of the SRM tip (the TCP 200 mm out along
  the flange axis), tool down, 50 mm above the table, over a plate the finger
  may touch; ``check_cartesian_path`` from the joints at its start.

Target (collision-model issue): a 20-pose calibration plan checked in under
1 s on this 2-core machine.

``--quick`` runs 3 plans and 3 weld lines (< 1 min); ``--json`` prints one
JSON object of the figures as the last line. Exit code 1 when a job failed:
a plan that refused a pose, a weld line that was refused or whose start is
out of reach (the cell is drawn so that every one is accepted), each named
on stderr and in the JSON's ``failed``; 0 otherwise. A full run (20 plans, 10 weld
lines) writes results.csv, summary.md and plan_times.png to
bench/out/collision_check/.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _common import Failures, pyplot

from celld import se3
from celld.calib.poses import calibration_poses
from celld.config import TableReader, load
from celld.config.cell_model import read_cell_model
from celld.robot import kinematics as kin
from celld.robot.cellmodel import Box, CellModel, CellObject
from celld.robot.collision import Checker

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "collision_check"
# The simulated cell: its robot's home and its calibration set-up (20 poses).
SIM_CELL = load(ROOT / "configs" / "sim-cell.toml")
SIM_HOME = np.array(SIM_CELL.robot.home_q)
N_POSES = SIM_CELL.calibration.n_poses
# The weld line: 150 mm along y at x = 0.6 m, the tip 50 mm above the table.
WELD_LENGTH = 0.150
WELD_HEIGHT = 0.05
TARGET_PLAN_S = 1.0


@dataclass
class Row:
    kind: str  # "plan" or "weld"
    seed: int
    seconds: float
    samples: int
    accepted: int
    refused: str


def cell_model() -> CellModel:
    table = tomllib.loads((ROOT / "configs" / "cell-models" / "sim-cell.toml").read_text())["cell_model"]
    return read_cell_model(TableReader(table, "cell-models/sim-cell.toml", "cell_model"))


def run_plan(checker: Checker, seed: int) -> Row:
    cal = SIM_CELL.calibration
    T_v = se3.from_ur_pose(cal.verification_pose)
    targets = np.concatenate([T_v[None], calibration_poses(T_v, cal.pose_box, N_POSES, cal.max_tilt, seed=seed)])
    t0 = time.perf_counter()
    plan = checker.check_plan(SIM_HOME, targets)
    seconds = time.perf_counter() - t0
    refused = "; ".join(f"{p.index}: {p.refusal}" for p in plan.refused)
    return Row("plan", seed, seconds, sum(p.samples for p in plan.poses), len(plan.accepted), refused)


def run_weld(cell: CellModel, seed: int) -> Row:
    # The part: a 20 mm plate whose top is 20 mm below the tip (the tip rides in its groove, which a box does not show).
    plate = CellObject("workpiece", Box((0.3, 0.3, 0.02)), se3.transform_from(np.eye(3), [0.6, 0.0, WELD_HEIGHT - 0.03]))
    T_flange_tcp = se3.transform_from(np.eye(3), [0.0, 0.0, 0.2])
    checker = Checker(kin.model("ur10e"), cell.with_object(plate), T_flange_tcp)
    # Each seed shifts the line a little along x so the runs are not identical.
    x = 0.6 + 0.01 * (seed - 5)
    start = se3.from_ur_pose([x, -WELD_LENGTH / 2, WELD_HEIGHT, math.pi, 0.0, 0.0])
    end = se3.from_ur_pose([x, WELD_LENGTH / 2, WELD_HEIGHT, math.pi, 0.0, 0.0])
    seed_q = np.array([math.pi, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])
    q_start = kin.inverse(start @ se3.invert(T_flange_tcp), seed_q)
    if q_start is None:
        return Row("weld", seed, math.nan, 0, 0, "start pose unreachable")
    t0 = time.perf_counter()
    check = checker.check_cartesian_path(q_start, end)
    seconds = time.perf_counter() - t0
    return Row("weld", seed, seconds, len(check.q), int(check.ok), "" if check.ok else str(check.refusal))


def summarise(rows: list[Row], build_s: float) -> dict[str, Any]:
    plans = [r for r in rows if r.kind == "plan"]
    welds = [r for r in rows if r.kind == "weld"]
    plan_s = np.array([r.seconds for r in plans])
    weld_s = np.array([r.seconds for r in welds])
    return {
        "checker_build_s": round(build_s, 4),
        "plans": len(plans),
        "plan_median_s": round(float(np.median(plan_s)), 4),
        "plan_max_s": round(float(plan_s.max()), 4),
        "plan_target_s": TARGET_PLAN_S,
        "plan_target_met": bool(plan_s.max() < TARGET_PLAN_S),
        "plan_samples_median": int(np.median([r.samples for r in plans])),
        "plan_accepted_min": min(r.accepted for r in plans),
        "plan_poses": N_POSES + 1,
        "weld_lines": len(welds),
        "weld_median_s": round(float(np.median(weld_s)), 4),
        "weld_max_s": round(float(weld_s.max()), 4),
        "weld_samples_median": int(np.median([r.samples for r in welds])),
        "weld_accepted": sum(r.accepted for r in welds),
    }


def write_outputs(rows: list[Row], figures: dict[str, Any]) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    with open(OUT / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["kind", "seed", "seconds", "samples", "accepted", "refused"])
        for r in rows:
            w.writerow([r.kind, r.seed, f"{r.seconds:.4f}", r.samples, r.accepted, r.refused])
    lines = ["# collision_check", "", "| figure | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in figures.items()]
    (OUT / "summary.md").write_text("\n".join(lines) + "\n")
    plt = pyplot("collision_check")
    if plt is None:
        return
    plans = [r for r in rows if r.kind == "plan"]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.bar([r.seed for r in plans], [r.seconds for r in plans], color="tab:blue")
    ax.axhline(TARGET_PLAN_S, color="tab:red", linestyle="--", label=f"target {TARGET_PLAN_S:.0f} s")
    ax.set_xlabel("plan seed")
    ax.set_ylabel(f"check_plan of {N_POSES + 1} poses, s")
    ax.set_title("Calibration plan collision check, UR10e in the simulated cell")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / "plan_times.png", dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 plans and 3 weld lines")
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object, last line")
    args = ap.parse_args(argv)
    n_plans, n_welds = (3, 3) if args.quick else (20, 10)
    cell = cell_model()
    t0 = time.perf_counter()
    checker = Checker(kin.model("ur10e"), cell)
    build_s = time.perf_counter() - t0
    rows: list[Row] = []
    failures = Failures("collision_check")
    for seed in range(n_plans):
        row = run_plan(checker, seed)
        rows.append(row)
        print(
            f"plan seed {seed:2d}: {row.seconds:6.3f} s, {row.samples:5d} samples, {row.accepted}/{N_POSES + 1} accepted {row.refused}",
            flush=True,
        )
        if row.refused:
            failures.add(f"plan seed {seed}", f"{N_POSES + 1 - row.accepted} pose(s) refused: {row.refused}")
    for seed in range(n_welds):
        row = run_weld(cell, seed)
        rows.append(row)
        print(f"weld line {seed:2d}: {row.seconds:6.3f} s, {row.samples:5d} samples, {'ok' if row.accepted else row.refused}", flush=True)
        if not row.accepted:
            failures.add(f"weld line {seed}", row.refused)
    figures = summarise(rows, build_s)
    figures["failed"] = failures.jobs
    if not args.quick:
        write_outputs(rows, figures)
    for k, v in figures.items():
        print(f"{k}: {v}")
    if args.json:
        print(json.dumps(figures))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
