"""``celld demo``: the simulated cell end to end, driven over the bus like an MES.

1. starts the simulated cell of ``configs/sim-cell.toml`` (the UR10e behind
   real ur-rtde, in real time) and the daemon on it as its own process
   (``celld sim run``: ``celld run`` on the simulated scanner and camera);
2. submits a calibrate job over zenoh, shows its progress, accepts the result;
3. submits a weld job: scan, seam, touch, Algorithm 2 with the arc, retract;
4. prints the calibration error against the simulator's truth, the seam
   tracking error (the torch path against the true seam) and the paths of
   the jobs' ``.rrd`` recordings.

Only this script reads the truth (the config's ``[scanner] T_base_cam`` and
``[sim]`` part), after the jobs have ended; the daemon never sees it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from celld import config as config_mod
from celld import se3

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "sim-cell.toml"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the simulated cell and its daemon: calibrate, then weld, over the bus")
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="a cell config whose devices are simulated")
    p.add_argument("--poses", type=int, default=None, help="calibration poses (default: the config's n_poses)")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object last")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from celld.errors import CelldError
    from celld.seam.figures import lateral_error
    from celld.sim.cell import run_cell, sim_workpiece

    cfg = config_mod.load(args.config)
    part = sim_workpiece(cfg)
    if cfg.scanner.kind != "sim" or cfg.tactile.kind != "sim" or part is None:
        print("celld demo: the config must simulate the scanner and the SRM and name a [sim] workpiece", file=sys.stderr)
        return 2
    state = Path(cfg.cell.state_dir)
    state.mkdir(parents=True, exist_ok=True)
    log_path = state / "demo-daemon.log"
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if args.json else (lambda text: print(text, flush=True))
    figures: dict[str, Any] = {}
    say(f"celld demo: simulated cell {cfg.cell.name!r} on {cfg.robot.host}; daemon log {log_path}")
    t0 = time.monotonic()
    try:
        with run_cell(args.config, log_path) as cell:
            say(f"daemon up, robot link up ({time.monotonic() - t0:.0f} s)")
            calibrate: dict[str, Any] = {"kind": "calibrate"}
            if args.poses:
                calibrate["n_poses"] = args.poses
            cal = _job(cell.client, calibrate, say)
            if cal["state"] != "succeeded":
                return _failed(cal, say)
            accepted = cell.client.accept(cal["id"])
            T_est = np.array(accepted["calibration"]["T_base_cam"])
            dt, dr = se3.error(T_est, cfg.T_base_cam_nominal())
            cal_result = json.loads(Path(cal["result"]).read_text())
            figures["calibration"] = {"job": cal["id"], "translation_error_mm": dt * 1e3, "rotation_error_deg": math.degrees(dr),
                                      "pairs": cal_result["calibration"]["pairs"], "recording": cal_result.get("recording")}
            say(f"calibration {cal['id']} accepted: error against the simulator's truth {dt * 1e3:.3f} mm, {math.degrees(dr):.4f} deg")
            weld = _job(cell.client, {"kind": "weld"}, say)
            if weld["state"] != "succeeded":
                return _failed(weld, say)
            res = json.loads(Path(weld["result"]).read_text())  # the record names the result file
            g = part.wall
            torch = lateral_error(np.array(res["torch_path"]), g.seam_base, g.T_base_plane)
            refined = lateral_error(np.array(res["refined_path"]), g.seam_base, g.T_base_plane)
            planned = lateral_error(np.array(res["planned_path"]), g.seam_base, g.T_base_plane)
            figures["weld"] = {"job": weld["id"], "torch_error": torch, "refined_error": refined, "planned_error": planned,
                               "figures": res["figures"], "recording": res.get("recording"), "paths": res.get("paths")}
    except CelldError as exc:
        say(f"celld demo failed: {exc}")
        return 1
    f = figures["weld"]
    say("")
    say(f"calibration: {figures['calibration']['translation_error_mm']:.3f} mm, {figures['calibration']['rotation_error_deg']:.4f} deg from the truth "
        f"({figures['calibration']['pairs']} pairs)")
    say(f"seam plan from the scan: {f['planned_error']['rms_mm']:.3f} mm RMS, {f['planned_error']['max_mm']:.3f} mm max from the true seam")
    say(f"torch path (tactile tracking): {f['torch_error']['rms_mm']:.3f} mm RMS, {f['torch_error']['max_mm']:.3f} mm max from the true seam "
        f"over {f['figures']['tracked_mm']:.0f} mm, arc on {f['figures']['arc_on_s']:.1f} s")
    say(f"delta_n tracking error: {f['figures']['delta_n_error_rms_mm']} mm RMS")
    say("recordings (open with: rerun FILE.rrd):")
    say(f"  {figures['calibration']['recording']}")
    say(f"  {f['recording']}")
    say(f"weld paths: {f['paths']}   total {time.monotonic() - t0:.0f} s")
    if args.json:
        print(json.dumps(figures))
    return 0


def _job(client: Any, message: dict[str, Any], say: Any) -> dict[str, Any]:
    from celld.bus.cli import ProgressBar

    bar = ProgressBar(sys.stderr)
    try:
        with client.watch_progress() as events:
            reply = client.submit(message)
            say(f"{message['kind']} job {reply['job']} {reply['state']}")
            record = events.wait(reply["job"], bar.update, 1800.0)
    finally:
        bar.close()
    return record


def _failed(record: dict[str, Any], say: Any) -> int:
    say(f"job {record['id']} {record['state']}: {record.get('reason') or record}")
    return 1
