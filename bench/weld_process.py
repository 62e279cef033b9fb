"""Benchmark: welds with a power source that fails, scored against the simulator's truth.

One simulated cell (``configs/sim-cell.toml`` with the control-box wiring of
``configs/power-source-io.toml``, the procedure ``steel-1.0mm-mag-short``), in
the world of ``--preset`` (default realistic) and ``--seed``, driven over the
bus: calibrate and accept, tool-calibrate and accept, then ``--welds`` welds
of the world's V-groove (10; 3 with ``--quick``). The world's power source
fails every weld's first start, puts the arc out once in every weld after
``--loss-after`` s of arc, and sticks the wire at the end of every third weld
(``[sim.power_source]``: ``fail_first_start``, ``arc_loss_after_s``,
``stuck_every``); the operator cuts it 3 s later, the arm is then moved up
50 mm and the next weld starts. The daemon sees only the source's signals.

Per weld, against the truth (``celld.sim.score.arc_truth``, the truth stream's
true arc and torch):

- completed by re-strike (welded to the seam's end), or reported short: the
  result's (or the failed job's ``arc.json``) unwelded length; with the
  truth's welded length along the true seam they must make the seam's length
  within 1 mm (``unwelded_truth_mismatch_mm``). The seam before the point
  where the finger first touched it is never welded (the arc lights there):
  ``unwelded_at_start_mm``, reported, not counted as short;
- travel along the seam from each weld's first start to a stable arc, in
  cycles of the procedure's travel speed (target: at most one, 2 ms); each
  re-strike is a scratch start, whose travel to a stable arc is its scratch
  (target: at most a few millimetres, the procedure's 2 mm and the arm's stop:
  3 mm), against the arc report's own figure of it;
- arc-on samples more than 5 mm across the seam (target 0), moves of more
  than 0.1 mm while the wire was stuck (target 0);
- the torch's true lateral error while the arc burned (targets: RMS <= 0.2 mm,
  max <= 0.5 mm), arc-on time, the cycle time (the weld job's wall time) and
  the arc-on ratio.

``--json`` prints one JSON object last with the keys the issue names.
Exit code 1 when a job failed other than as scheduled (a weld whose only
failure is its scheduled stuck wire counts as reported, not failed), or the
cell did not come up; a missed target is a figure.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Failures, JobFailed  # noqa: E402

from celld.errors import JobError  # noqa: E402
from celld.sim.cell import run_cell, sim_part  # noqa: E402
from celld.sim.score import TruthRecorder, arc_truth, lateral, true_torch_path  # noqa: E402
from celld.weld.procedure import load_procedure  # noqa: E402

HOST = "127.0.0.11"
OUT = ROOT / "bench" / "out" / "weld_process"
PROCEDURE = "steel-1.0mm-mag-short"
ARC_START_BIT = 0  # configs/power-source-io.toml: arc_start = "do0"
STUCK_EVERY = 3
STUCK_CLEAR = 3.0  # s
PERIOD = 0.002  # s, the motion loop's cycle
# A weld refused because the robot link was down (the machine starved the simulated robot) is submitted again.
LINK_RETRIES = 3
# Targets.
MISMATCH_MAX = 1.0  # mm
START_CYCLES_MAX = 1.0
SCRATCH_MAX = 3.0  # mm
TORCH_RMS, TORCH_MAX = 0.2, 0.5  # mm


def cell_config(work: Path, preset: str, seed: int, loss_after: float, quick: bool) -> Path:
    path = work / "cell.toml"
    cal = "[calibration]\nn_poses = 8\n" if quick else ""
    path.write_text(
        f'include = ["{ROOT / "configs" / "sim-cell.toml"}", "{ROOT / "configs" / "power-source-io.toml"}"]\n'
        f'[cell]\nname = "bench-weld-process"\nstate_dir = "{work / "state"}"\n'
        f'[robot]\nhost = "{HOST}"\n[bus]\nlisten = ["tcp/{HOST}:7447"]\n{cal}'
        f'[weld]\nprocedure = "{PROCEDURE}"\nprocedures_dir = "{ROOT / "configs" / "procedures"}"\n'
        f'[sim]\npreset = "{preset}"\nseed = {seed}\n'
        f"[sim.power_source]\nfail_first_start = true\narc_loss_after_s = {loss_after}\nstuck_every = {STUCK_EVERY}\n"
        f"stuck_clear_s = [{STUCK_CLEAR}, {STUCK_CLEAR}]\nfault_rate_per_h = 0.0\nfailed_start_rate = 0.0\n"
        "arc_loss_rate_per_s = 0.0\nstuck_wire_rate = 0.0\n"
    )
    return path


def _accept(client: Any, record: dict[str, Any], what: str) -> None:
    if record["state"] != "succeeded":
        raise JobFailed(what, record.get("reason", record["state"]))
    try:
        client.accept(record["id"])
    except Exception:  # noqa: BLE001 (a quality gate refused it: weld with it anyway, and say so)
        client.accept(record["id"], force=True)
        print(f"weld_process: {what} {record['id']} accepted past its quality gate", file=sys.stderr)


def weld_once(cell: Any, k: int, say: Any) -> dict[str, Any]:
    """Weld ``k`` (from 1) and its figures against the truth."""
    client, cfg, world = cell.client, cell.config, cell.world
    part = sim_part(world)
    travel_speed = load_procedure(ROOT / "configs" / "procedures", PROCEDURE).travel_speed
    for attempt in range(LINK_RETRIES + 1):
        t0 = time.monotonic()
        try:
            with TruthRecorder(cfg.robot.host) as truth:
                _, record = client.submit_and_wait({"kind": "weld", "ref": f"weld {k}"}, timeout=900)
            break
        except JobError as exc:
            # Refused at submit while the robot link is down (a starved machine): the daemon reconnects by itself.
            if "robot link down" not in str(exc) or attempt == LINK_RETRIES:
                raise JobFailed(f"weld {k}", str(exc)) from exc
            say(f"weld {k} refused ({exc}); again in 5 s")
            time.sleep(5.0)
    seconds = time.monotonic() - t0
    state_dir = Path(cfg.cell.state_dir)
    if record["state"] == "succeeded":
        result = json.loads(Path(record["result"]).read_text())
        arc = result["arc"]
    else:
        path = state_dir / "jobs" / record["id"] / "arc.json"
        if not path.exists():
            return {"weld": k, "failed": record.get("reason", record["state"]), "seconds": seconds}
        arc = json.loads(path.read_text())
    recs = truth.records()
    t = arc_truth(world, part, recs, ARC_START_BIT)
    # The torch's true path while an arc burned: lateral from the true seam.
    torch = true_torch_path(world, recs, -1) if recs["arc_on"].any() else np.zeros((0, 3))
    lat = lateral(part, torch) if len(torch) > 1 else {"rms_mm": math.nan, "max_mm": math.nan}
    arc_s = float(np.count_nonzero(recs["arc_on"])) * PERIOD
    # The weld's first start (at rest), then its re-strikes (scratch starts).
    start_cycles = [m / travel_speed / PERIOD for m in t["start_travel_m"][:1]]
    scratches = [m * 1e3 for m in t["start_travel_m"][1:]]
    stretches = arc["unwelded_stretches_mm"]
    # Before the point where the finger first touched the seam is not welded (the arc lights there): the
    # stretch from 0; any other is seam the weld left (a retract or an end short of the seam's).
    at_start = stretches[0][1] if stretches and stretches[0][0] == 0.0 else 0.0
    left = [g for g in stretches if g[0] > 0.0]
    out = {
        "weld": k,
        "job": record["id"],
        "state": record["state"],
        "ended_in": arc["ended_in"],
        # The seam welded to its end (through re-strikes), the sequence closed (done) or the wire stuck after it.
        "completed": arc["ended_in"] in ("done", "stuck") and not left,
        "reported_short": bool(left),
        "unwelded_at_start_mm": at_start,
        "unwelded_mm": arc["unwelded_mm"],
        "unwelded_stretches_mm": arc["unwelded_stretches_mm"],
        "seam_true_mm": round(t["seam_length_m"] * 1e3, 2),
        "welded_true_mm": round(t["welded_m"] * 1e3, 2),
        "unwelded_truth_mismatch_mm": round(abs(t["welded_m"] * 1e3 + arc["unwelded_mm"] - t["seam_length_m"] * 1e3), 3),
        "failed_starts": arc["failed_starts"],
        "restrikes": arc["restrikes"],
        "arc_losses": arc["arc_losses"],
        "stuck_wire": arc["ended_in"] == "stuck",
        "starts": len(start_cycles),
        "travel_without_arc_cycles_max": round(max(start_cycles), 3) if start_cycles else 0.0,
        "scratch_true_mm_max": round(max(scratches), 3) if scratches else 0.0,
        "scratch_reported_mm_max": arc["scratch_max_mm"],
        "arc_on_off_seam_samples": t["arc_on_off_seam_samples"],
        "stuck_windows": t["stuck_windows"],
        "stuck_wire_moves": t["stuck_wire_moves"],
        "torch_rms_mm": round(lat["rms_mm"], 4),
        "torch_max_mm": round(lat["max_mm"], 4),
        "arc_on_s": round(arc_s, 2),
        "cycle_time_s": round(seconds, 1),
        "weld_data": arc["weld_data"],
        "reason": record.get("reason", ""),
    }
    say(
        f"weld {k}: {record['state']} ({arc['ended_in']}), {arc['failed_starts']} failed starts, {arc['restrikes']} re-strikes, "
        f"{arc['arc_losses']} arc losses; unwelded {arc['unwelded_mm']:.2f} mm, truth mismatch {out['unwelded_truth_mismatch_mm']:.3f} mm; "
        f"travel to a stable arc <= {out['travel_without_arc_cycles_max']:.2f} cycles, scratches <= "
        f"{out['scratch_true_mm_max']:.2f} mm (reported {arc['scratch_max_mm']:.2f}); torch {out['torch_rms_mm']:.3f} / "
        f"{out['torch_max_mm']:.3f} mm; arc {arc_s:.1f} s of {seconds:.0f} s"
    )
    return out


def _move_up(cell: Any) -> None:
    """After a stuck wire is cut: the tool 50 mm straight up (a move job), so the next weld starts clear of the part."""
    pose = list(cell.robot.status()["tcp_pose"])
    pose[2] += 0.05
    _, moved = cell.client.submit_and_wait(
        {"kind": "move", "target": {"space": "cartesian", "pose": pose}, "speed_scale": 0.1}, timeout=120
    )
    if moved["state"] != "succeeded":
        raise JobFailed("move up after the stuck wire", moved.get("reason", moved["state"]))


def summarise(welds: list[dict[str, Any]]) -> dict[str, Any]:
    done = [w for w in welds if "failed" not in w]
    arc_on = sum(w["arc_on_s"] for w in done)
    cycle = sum(w["cycle_time_s"] for w in done)
    mismatch = max((w["unwelded_truth_mismatch_mm"] for w in done), default=math.nan)
    start_cycles = max((w["travel_without_arc_cycles_max"] for w in done), default=math.nan)
    scratch = max((w["scratch_true_mm_max"] for w in done), default=math.nan)
    scratch_reported = max((w["scratch_reported_mm_max"] for w in done), default=math.nan)
    rms = max((w["torch_rms_mm"] for w in done), default=math.nan)
    tmax = max((w["torch_max_mm"] for w in done), default=math.nan)
    out = {
        "seams": len(welds),
        "seams_completed": sum(1 for w in done if w["completed"]),
        "seams_reported_short": sum(1 for w in done if w["reported_short"]),
        "unwelded_at_start_mm_max": max((w["unwelded_at_start_mm"] for w in done), default=math.nan),
        "unwelded_truth_mismatch_mm_max": mismatch,
        "failed_starts": sum(w["failed_starts"] for w in done),
        "restrikes": sum(w["restrikes"] for w in done),
        "arc_losses": sum(w["arc_losses"] for w in done),
        "stuck_wires": sum(1 for w in done if w["stuck_wire"]),
        "travel_without_arc_ms_max": round(start_cycles * PERIOD * 1e3, 3) if math.isfinite(start_cycles) else math.nan,
        "restrike_scratch_mm_max": scratch,
        "restrike_scratch_reported_mm_max": scratch_reported,
        "arc_on_off_seam_samples": sum(w["arc_on_off_seam_samples"] for w in done),
        "stuck_wire_moves": sum(w["stuck_wire_moves"] for w in done),
        "torch_rms_mm_max": rms,
        "torch_max_mm": tmax,
        "cycle_time_s": round(cycle / len(done), 1) if done else math.nan,
        "arc_on_ratio": round(arc_on / cycle, 3) if cycle else math.nan,
    }
    out["targets"] = {
        "truth_mismatch_within_1mm": bool(mismatch <= MISMATCH_MAX),
        "travel_without_arc_at_most_one_cycle": bool(start_cycles <= START_CYCLES_MAX),
        "scratch_within_a_few_mm": bool(scratch <= SCRATCH_MAX and scratch_reported <= SCRATCH_MAX),
        "no_arc_off_seam": out["arc_on_off_seam_samples"] == 0,
        "no_stuck_wire_moves": out["stuck_wire_moves"] == 0,
        "torch_rms_and_max": bool(rms <= TORCH_RMS and tmax <= TORCH_MAX),
    }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 welds, 8 calibration poses")
    ap.add_argument("--json", action="store_true", help="print one JSON object of the figures last")
    ap.add_argument("--preset", default="realistic", choices=("ideal", "realistic"))
    ap.add_argument("--seed", type=int, default=1, help="the world's seed")
    ap.add_argument("--welds", type=int, default=10)
    ap.add_argument("--loss-after", type=float, default=8.0, help="s of arc after which every weld loses its arc once")
    args = ap.parse_args(argv)
    n = 3 if args.quick else args.welds
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if args.json else (lambda text: print(text, flush=True))
    failures = Failures("weld_process")
    welds: list[dict[str, Any]] = []
    say(f"weld_process: preset {args.preset}, seed {args.seed}, {n} welds with {PROCEDURE}")
    with tempfile.TemporaryDirectory(prefix="celld-weld-process-") as tmp:
        work = Path(tmp)
        try:
            with run_cell(cell_config(work, args.preset, args.seed, args.loss_after, args.quick), work / "daemon.log") as cell:
                _, cal = cell.client.submit_and_wait({"kind": "calibrate", "seed": args.seed}, timeout=1800)
                _accept(cell.client, cal, "calibrate")
                say(f"calibration {cal['id']} accepted")
                _, tc = cell.client.submit_and_wait({"kind": "tool-calibrate", "seed": args.seed}, timeout=1800)
                _accept(cell.client, tc, "tool-calibrate")
                say(f"tool calibration {tc['id']} accepted")
                for k in range(1, n + 1):
                    w = weld_once(cell, k, say)
                    welds.append(w)
                    # A wire stuck after a seam welded to its end is the world's schedule (its every third weld,
                    # counted by the source's own process-active episodes: a weld that stopped before its arc
                    # was not one), reported, not failed.
                    if "failed" in w:
                        failures.add(f"weld {k}", w["failed"])
                    elif w["state"] != "succeeded" and not (w["stuck_wire"] and w["completed"]):
                        failures.add(f"weld {k}", w["reason"])
                    if w.get("stuck_wire"):
                        time.sleep(STUCK_CLEAR + 0.5)
                        _move_up(cell)
        except JobFailed as exc:
            failures.add(exc.job, exc.reason)
        except Exception as exc:  # noqa: BLE001 (the cell did not come up, or a job's transport failed: named, not a traceback)
            failures.add("cell", f"{type(exc).__name__}: {exc}")
        if failures and (work / "daemon.log").exists():
            OUT.mkdir(parents=True, exist_ok=True)
            kept = OUT / f"daemon-seed{args.seed}.log"
            shutil.copyfile(work / "daemon.log", kept)
            say(f"the daemon's log of the failed run: {kept}")
    summary = summarise(welds)
    say(json.dumps(summary, indent=1))
    if args.json:
        print(json.dumps({**summary, "welds": welds, "failed": failures.jobs}, default=lambda o: None))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
