"""Benchmark: seeded simulated cells end to end through the daemon, scored against each cell's own truth.

For each seed the simulator draws a world (``--preset``, default
``realistic``: the robot's kinematic error, repeatability and noise, capture
timing, the scanner's mount, scale and distortion, the flange as made, the
tool as built, the finger's mechanics, the part's placement and shape;
celld/sim/world.py) and runs the cell of ``configs/sim-cell.toml`` in it:
the simulated UR10e behind real ur-rtde and ``celld sim run``, driven over
the bus (:func:`celld.sim.demo.run_jobs`):

1. calibrate (the cell's 20 poses, Algorithm 1 may stop earlier; then the
   arm's kinematic calibration from ``--arm-poses`` wide poses, 40 by
   default as in the demo, 0 for the hand-eye calibration alone) and accept;
2. tool-calibrate and accept: the SRM tip and the torch's wire end measured
   with the scanner (the realistic world's tool misses the configured one by
   up to 1-2 mm); the weld then uses the measured tip and torch (``--no-tool-calibrate`` welds with the
   configured one, ``--without tool_offsets`` as if the tool were drawn
   exactly);
3. weld the V-groove: scan, seam (both walls measured beside it), the
   height probe (the finger touches both walls at the start; the joint's
   width gives the tip's height in it), touch, Algorithm 2 with the arc.

Per seed, against the world's truth (read after the jobs):

- tool calibration: the measured tip against the tool as built (and how far
  the config's tip is off it), with the job's own 1-sigma and verdict;
- calibration targeting error: where the flange truly lands when sent, through
  the accepted T_base_cam and the controller's nominal kinematics, to points
  the scanner saw (celld.sim.score.targeting): mean and max over the
  calibration box (the flange facing the scanner, as calibrated) and over the
  table (the flange facing down, as when welding);
- plan alone: the torch following the weld plan from scan and calibration
  without the tactile correction (open loop through the true arm and tool):
  lateral RMS / max from the true seam, with the tool as typed
  (``plan_alone_rms_mm``) and as its calibration measured it, as the weld
  used it (``plan_alone_measured_tool_rms_mm``): touch's own gain is the
  difference between the second and the torch;
- torch: the torch's true path while the arc was on: lateral RMS / max;
- torch height: the same path's height over the true root (contact tip to
  work), mean, min and max, and its largest distance from weld.tip_height,
  the height the cell welds at (``ctwd_err_max_mm``);
- touch check: the calibration's error at the weld's start as the height
  probe's two touches read it (the joint's centre across and its root in
  height, as touched against as scanned; the whole chain of calibration, arm
  and tool calibration), beside what it should have read
  (``celld.sim.score.touch_check_truth``: the point where the arm truly put
  it, from the simulated arm's states near it, the controller's belief against
  the truth, against the part's true root), and how far apart
  (``touch_check_disagree_mm``; target 0.10 mm);
- finger gain: the tip's deflection over the tag's along the joint's normal
  as the probe's touches measured it (``celld.tactile.fingermap``), beside the
  world's tag (``finger_gain``, ``finger_gain_true``, ``finger_gain_error``);
- success: the weld job succeeded, tracked at least 120 of the 150 mm, and the
  torch stayed within 0.5 mm of the seam (it did not weld off the seam).

Targets (the issue): targeting mean <= 0.25 mm; torch RMS <= 0.2 mm and max
<= 0.5 mm in every seed; the torch's height within +-1.0 mm of the height
welded at in every seed (issue 25); no seed that welds off the seam. The plan alone is
expected off by 0.5-3 mm in the realistic preset.

``--quick``: one seed, 6 calibration poses, the scanner at full resolution
(at half resolution the tool calibration finds the SRM's tip in too few
poses and is refused); a cell's start, the three jobs and the weld take a
few minutes even so.
``--json`` prints one JSON object of the figures last. A full run writes
results.json and results.md to bench/out/realistic_cell/<preset>/.

Exit code 1 when a seed failed: the cell did not come up, a job (calibrate,
tool-calibrate, weld) did not succeed, or the weld laid no bead (the arc never
on along the seam); each named on stderr and in the JSON's ``failed``. A seed
that welds but misses a target is a figure (``success``, ``targets``). 0
otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Failures  # noqa: E402

from celld.errors import CelldError  # noqa: E402
from celld.log import read_events  # noqa: E402
from celld.sim.demo import DEMO_ARM_POSES, run_jobs  # noqa: E402
from celld.sim.world import SOURCES, WorldOptions  # noqa: E402
from celld.tactile.fingermap import FingerGain  # noqa: E402

OUT = ROOT / "bench" / "out" / "realistic_cell"
# The benchmark's own loopback address (the demo uses 127.0.0.2, the tests from 127.0.0.12 up).
HOST = "127.0.0.7"
# Targets, mm.
TARGETING_MEAN = 0.25
TORCH_RMS, TORCH_MAX = 0.2, 0.5
# Contact tip to work: the torch's height over the true root within this of weld.tip_height, mm (issue 25).
CTWD_MAX = 1.0
# The touch check (the calibration's error at the weld, as the finger finds it) against its truth, mm (issue 24).
TOUCH_CHECK_AGREE = 0.10
TRACKED_MIN = 120.0  # of the 150 mm seam


def cell_config(work: Path, quick: bool) -> Path:
    """The simulated cell of configs/sim-cell.toml on the benchmark's address, its state in ``work``."""
    path = work / "cell.toml"
    extra = "[calibration]\nn_poses = 6\n" if quick else ""
    path.write_text(
        f'include = ["{ROOT / "configs" / "sim-cell.toml"}"]\n[cell]\nname = "bench-realistic"\nstate_dir = "{work / "state"}"\n'
        f'[robot]\nhost = "{HOST}"\n[bus]\nlisten = ["tcp/{HOST}:7447"]\n{extra}'
    )
    return path


# Job failures that are the shared machine's, not the cell's: the RTDE watchdog
# stopped the robot program, or the motion loop stopped on a stale robot state,
# because a process was starved (other real-time processes on the same two
# cores). A run that ends so is run again, and the table says so.
INFRASTRUCTURE = ("robot program stopped", "robot link", "stale state")


def run_seed(
    seed: int,
    options: WorldOptions,
    quick: bool,
    force_accept: bool,
    say: Any,
    retries: int = 1,
    tool_calibrate: bool = True,
    arm_poses: int = DEMO_ARM_POSES,
) -> dict[str, Any]:
    """One seeded cell end to end, run again (up to ``retries`` times) after a starved robot link; its figures."""
    lost: list[str] = []
    while True:
        r = _run_seed(seed, options, quick, force_accept, say, tool_calibrate, arm_poses)
        reason = str(r.get("failed", {}).get("reason", ""))
        if "failed" not in r or not any(k in reason for k in INFRASTRUCTURE) or len(lost) >= retries:
            if lost:
                r["retried_after"] = lost
            return r
        lost.append(reason)
        say(f"seed {seed}: {reason}; running it again")


def _run_seed(
    seed: int,
    options: WorldOptions,
    quick: bool,
    force_accept: bool,
    say: Any,
    tool_calibrate: bool = True,
    arm_poses: int = DEMO_ARM_POSES,
) -> dict[str, Any]:
    """One seeded cell end to end; its figures (or why it failed)."""
    with tempfile.TemporaryDirectory(prefix="celld-realistic-") as tmp:
        work = Path(tmp)
        t0 = time.monotonic()
        try:
            figures = run_jobs(
                cell_config(work, quick),
                work / "daemon.log",
                WorldOptions(options.preset, seed, options.on, options.off),
                say,
                calibrate_seed=seed,
                force_accept=force_accept,
                tool_calibrate=tool_calibrate,
                arm_poses=arm_poses,
            )
        except CelldError as exc:
            log = (work / "daemon.log").read_text(errors="replace")[-2000:] if (work / "daemon.log").exists() else ""
            return {"seed": seed, "success": False, "failed": {"reason": str(exc), "log_tail": log}, "seconds": time.monotonic() - t0}
        stops = stops_in((work / "daemon.log").read_text(errors="replace"))
    out: dict[str, Any] = {
        "seed": seed,
        "seconds": round(time.monotonic() - t0, 1),
        # Motion stopped for a hung daemon (none hung here: each is spurious) or a stale robot state.
        **stops,
        "tool_calibration": figures.get("tool", "not run (--no-tool-calibrate)" if not tool_calibrate else "failed"),
        # How late the daemon's event loop ran over the three jobs (celld.daemon.loopwatch).
        "loop": figures.get("loop"),
    }
    if "calibration" in figures:
        c = figures["calibration"]
        out["calibration"] = {k: c[k] for k in ("translation_error_mm", "rotation_error_deg", "pairs", "verdict", "forced", "targeting")}
        out["calibration"]["targeting_hand_eye"] = c.get("targeting_hand_eye")  # None without the arm's calibration
        out["calibration"]["arm"] = c.get("arm")
    if "failed" in figures:
        out.update(success=False, failed=figures["failed"])
        return out
    w = figures["weld"]
    out["weld"] = {
        k: w[k] for k in ("plan_alone_error", "plan_error", "torch_error", "torch_believed_error", "torch_height", "plan_alone_height")
    }
    out["weld"]["plan_alone_measured_tool_error"] = w.get("plan_alone_measured_tool_error")
    out["weld"]["tracked_mm"] = w["figures"]["tracked_mm"]
    out["weld"]["height_probe"] = w.get("height_probe")
    out["weld"]["touch_check"] = touch_check_figures(w.get("height_probe"), w.get("touch_check_truth"))
    out["weld"]["finger"] = finger_figures(w.get("height_probe"), w.get("finger_truth"))
    out["weld"]["wall_offset_used_mm"] = w["figures"].get("wall_offset_used_mm")
    out["weld"]["arc_on_s"] = w["figures"]["arc_on_s"]
    # The calibration held against the cell before the weld (celld.daemon.verify): a drift caught, noise not.
    out["verification"] = figures.get("verification")
    torch = w["torch_error"]
    out["success"] = bool(w["figures"]["tracked_mm"] >= TRACKED_MIN and torch["points"] > 0 and torch["max_mm"] <= TORCH_MAX)
    return out


def touch_check_figures(probe: dict[str, Any] | None, truth: dict[str, float] | None) -> dict[str, Any] | None:
    """The weld's touch check (the calibration's error at the weld's start, from the height probe's touches) beside
    what it should have read (celld.sim.score.touch_check_truth), and how far apart they are (``disagree_mm``, the
    norm over across and height); None when the joint was not probed."""
    if not (probe or {}).get("probed"):
        return None
    check = probe["touch_check"]
    out: dict[str, Any] = {k: check.get(k) for k in ("across_mm", "height_mm", "error_mm", "bound_mm", "verdict")}
    if truth is not None:
        out["true"] = {k: round(v, 4) if isinstance(v, float) else v for k, v in truth.items()}
        out["disagree_mm"] = round(math.hypot(check["across_mm"] - truth["across_mm"], check["height_mm"] - truth["height_mm"]), 4)
    return out


def finger_figures(probe: dict[str, Any] | None, truth: dict[str, Any] | None) -> dict[str, Any] | None:
    """The finger's gain the weld's touches measured (celld.tactile.fingermap) beside the world's tag: the tip's
    deflection over the tag's along the joint's normal, and the measured one's error relative to it; None when
    the joint was not probed."""
    finger = (probe or {}).get("finger")
    if finger is None:
        return None
    out: dict[str, Any] = {**finger, "true_gain": None if truth is None else round(truth["tip_over_tag"], 5)}
    if truth is not None and finger["measured"]:
        out["gain_error"] = round(finger["gain"] / truth["tip_over_tag"] - 1.0, 5)
        # Where the servo holds the tag (delta_d): the tip's deflection over the tag's, measured and true.
        held = FingerGain.of_reading(finger).over(truth["delta_d_mm"] * 1e-3)
        out["held_error"] = round(held / truth["tip_over_tag_held"] - 1.0, 5)
        out["held_error_um"] = round((held - truth["tip_over_tag_held"]) * truth["delta_d_mm"] * 1e3, 2)
    return out


def stops_in(log: str) -> dict[str, int]:
    """How often the daemon's log says motion stopped because the daemon seemed hung (its motion process's
    exit: the heartbeat too old) or the robot state went stale; the run hangs no daemon, so every hang stop
    is spurious."""
    ends = list(read_events(log, "motion_loop_ended"))
    failed = list(read_events(log, "job_failed"))
    return {
        "spurious_hang_stops": sum(1 for e in ends if "(it hangs)" in str(e.get("reason", ""))),
        "stale_stops": sum(1 for e in ends if "stale state" in str(e.get("reason", "")))
        + sum(1 for e in failed if "stale state" in str(e.get("error", ""))),
    }


def failure(r: dict[str, Any]) -> tuple[str, str] | None:
    """``(job, reason)`` of a seed's run that failed, or None when it welded (well or not)."""
    if "failed" in r:
        f = r["failed"]
        job = f"seed {r['seed']} " + (f"{f.get('kind') or ''} job {f['job']}".lstrip() if "job" in f else "cell")
        return job, f"{f.get('state', 'failed')}: {f.get('reason')}"
    w = r.get("weld")
    if w is None:
        return f"seed {r['seed']} weld", "no weld figures"
    if not w["torch_error"]["points"]:
        return f"seed {r['seed']} weld", f"no bead laid: the arc was never on along the seam (tracked {w['tracked_mm']} mm)"
    return None


def summarise(preset: str, sources: list[str], runs: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in runs if "weld" in r]
    cal = [r for r in runs if "calibration" in r]

    def col(rows: list[dict[str, Any]], *keys: str) -> list[float]:
        vals = []
        for r in rows:
            v: Any = r
            for k in keys:
                v = v[k]
            vals.append(float(v))
        return vals

    tmean = col(cal, "calibration", "targeting", "calibration", "mean_mm")
    trms, tmax = col(ok, "weld", "torch_error", "rms_mm"), col(ok, "weld", "torch_error", "max_mm")
    ctwd = col(ok, "weld", "torch_height", "error_max_mm")
    summary = {
        "preset": preset,
        "sources": sources,
        "seeds": [r["seed"] for r in runs],
        # Each seed's tool calibration: its verdict, or why there is none.
        "tool_calibration": [tc["verdict"] if isinstance(tc := r.get("tool_calibration"), dict) else tc for r in runs],
        "targeting_mean_mm": float(np.mean(tmean)) if tmean else None,
        "targeting_mean_worst_mm": max(tmean) if tmean else None,
        "targeting_max_mm": max(col(cal, "calibration", "targeting", "calibration", "max_mm")) if cal else None,
        "targeting_table_mean_mm": float(np.mean(col(cal, "calibration", "targeting", "table", "mean_mm"))) if cal else None,
        # The same over the table with the hand-eye calibration alone (the arm calibration's gain), per seed.
        "targeting_table_hand_eye_mean_mm": [
            None if (he := r["calibration"].get("targeting_hand_eye")) is None else round(he["table"]["mean_mm"], 3) for r in cal
        ],
        "targeting_table_mean_per_seed_mm": [round(v, 3) for v in col(cal, "calibration", "targeting", "table", "mean_mm")],
        "plan_alone_rms_mm": [round(v, 3) for v in col(ok, "weld", "plan_alone_error", "rms_mm")],
        "plan_alone_max_mm": [round(v, 3) for v in col(ok, "weld", "plan_alone_error", "max_mm")],
        # The plan alone with the tool as its calibration measured it (None: the torch not measured): touch's own gain.
        "plan_alone_measured_tool_rms_mm": [
            None if (m := (r["weld"].get("plan_alone_measured_tool_error") or {}).get("rms_mm")) is None else round(m, 3) for r in ok
        ],
        "torch_rms_mm": [round(v, 3) for v in trms],
        "torch_max_mm": [round(v, 3) for v in tmax],
        # The torch's height over the true root against weld.tip_height: the largest distance from it, per seed.
        "ctwd_err_max_mm": [round(v, 3) for v in ctwd],
        # The touch check at the weld's start (the calibration's error there, as the finger found it), its truth,
        # and how far apart they are (issue 24's target: within 0.10 mm), per seed (None: not probed).
        "touch_check_error_mm": [(r["weld"].get("touch_check") or {}).get("error_mm") for r in ok],
        "touch_check_true_error_mm": [
            None if (t := (r["weld"].get("touch_check") or {}).get("true")) is None else t["error_mm"] for r in ok
        ],
        "touch_check_disagree_mm": [(r["weld"].get("touch_check") or {}).get("disagree_mm") for r in ok],
        "touch_check_verdict": [(r["weld"].get("touch_check") or {}).get("verdict") for r in ok],
        # The finger's gain as the weld's touches measured it (None: not measured), the world's, and the relative error.
        "finger_gain": [(r["weld"].get("finger") or {}).get("gain") for r in ok],
        "finger_gain_true": [(r["weld"].get("finger") or {}).get("true_gain") for r in ok],
        "finger_gain_error": [(r["weld"].get("finger") or {}).get("gain_error") for r in ok],
        # ... and at the deformation the servo holds: the tip's deflection there off by this (um).
        "finger_held_error_um": [(r["weld"].get("finger") or {}).get("held_error_um") for r in ok],
        "successes": sum(1 for r in runs if r.get("success")),
        "failures": [{"seed": r["seed"], **r["failed"]} for r in runs if "failed" in r],
    }
    summary["targets"] = {
        "targeting_mean": bool(tmean) and float(np.mean(tmean)) <= TARGETING_MEAN,
        "torch_every_seed": len(ok) == len(runs) and all(a <= TORCH_RMS and b <= TORCH_MAX for a, b in zip(trms, tmax)),
        "no_seed_off_the_seam": summary["successes"] == len(runs),
        "ctwd_within_1_0_every_seed": len(ok) == len(runs) and all(v <= CTWD_MAX for v in ctwd),
        "touch_check_within_0_10": bool(ok) and all(d is not None and d <= TOUCH_CHECK_AGREE for d in summary["touch_check_disagree_mm"]),
    }
    return summary


def table(runs: list[dict[str, Any]]) -> list[str]:
    lines = [
        "| seed | cal. vs truth mm / deg | targeting mean / max mm (cal. box) | (over the table) | plan alone RMS / max mm "
        "| height probed, corrected mm | touch check across / height mm (true) | torch RMS / max mm "
        "| torch height over the root mean (min-max) mm | tracked mm | success |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        c = r.get("calibration")
        w = r.get("weld")
        cal = f"{c['translation_error_mm']:.3f} / {c['rotation_error_deg']:.4f}" if c else "-"
        if c and c.get("forced"):
            cal += f" ({c['verdict']}, forced)"
        tc = f"{c['targeting']['calibration']['mean_mm']:.3f} / {c['targeting']['calibration']['max_mm']:.3f}" if c else "-"
        tt = f"{c['targeting']['table']['mean_mm']:.3f} / {c['targeting']['table']['max_mm']:.3f}" if c else "-"
        pa = f"{w['plan_alone_error']['rms_mm']:.3f} / {w['plan_alone_error']['max_mm']:.3f}" if w else "-"
        to = f"{w['torch_error']['rms_mm']:.3f} / {w['torch_error']['max_mm']:.3f}" if w else "-"
        tr = f"{w['tracked_mm']:.0f}" if w else "-"
        th = w["torch_height"] if w else {}
        ht = f"{th['mean_mm']:.2f} ({th['min_mm']:.2f}-{th['max_mm']:.2f})" if th.get("points") else "-"
        hp = (w or {}).get("height_probe") or {}
        hc = f"{hp['height_correction_mm']:+.3f}" if hp.get("probed") else "-"
        tk = (w or {}).get("touch_check") or {}
        tcs = f"{tk['across_mm']:+.3f} / {tk['height_mm']:+.3f}" if tk else "-"
        if tk.get("true"):
            tcs += f" ({tk['true']['across_mm']:+.3f} / {tk['true']['height_mm']:+.3f})"
        ok = "yes" if r.get("success") else "no" + (f" ({r['failed'].get('reason', '')[:80]})" if "failed" in r else "")
        if r.get("retried_after"):
            ok += f" (run {len(r['retried_after']) + 1}: the robot link was starved before)"
        lines.append(f"| {r['seed']} | {cal} | {tc} | {tt} | {pa} | {hc} | {tcs} | {to} | {ht} | {tr} | {ok} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, 6 calibration poses")
    ap.add_argument("--json", action="store_true", help="print one JSON object of the figures last")
    ap.add_argument("--preset", default="realistic", choices=("ideal", "realistic"))
    ap.add_argument("--seeds", type=int, default=10, help="how many seeded cells (N)")
    ap.add_argument("--seed0", type=int, default=1, help="the first seed")
    ap.add_argument("--with", dest="with_sources", default="", help=f"error sources to switch on ({', '.join(SOURCES)})")
    ap.add_argument("--without", dest="without_sources", default="", help="error sources to switch off")
    ap.add_argument("--force-accept", action="store_true", help="accept calibrations that fail the daemon's quality gate")
    ap.add_argument("--no-tool-calibrate", action="store_true", help="weld with the configured tool, no tool-calibrate job")
    ap.add_argument(
        "--arm-poses",
        type=int,
        default=DEMO_ARM_POSES,
        help=f"wide poses of the arm's kinematic calibration (default {DEMO_ARM_POSES}, as the demo; 0: hand-eye only)",
    )
    ap.add_argument("--retries", type=int, default=1, help="runs again of a seed whose robot link was starved by the machine")
    ap.add_argument("--out", default=None, help="directory of a full run's results (default bench/out/realistic_cell/<preset>)")
    args = ap.parse_args(argv)

    def names(text: str) -> tuple[str, ...]:
        return tuple(s.strip() for s in text.split(",") if s.strip())

    options = WorldOptions(args.preset, None, names(args.with_sources), names(args.without_sources))
    seeds = [args.seed0] if args.quick else list(range(args.seed0, args.seed0 + args.seeds))
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if args.json else (lambda text: print(text, flush=True))
    label = args.preset + "".join(f" +{s}" for s in options.on) + "".join(f" -{s}" for s in options.off)
    say(f"realistic_cell: preset {label}, seeds {seeds}; tool calibration: {'not run' if args.no_tool_calibrate else 'run and accepted'}")
    runs = []
    failures = Failures("realistic_cell")
    quiet = lambda text: None  # noqa: E731  (the jobs' own progress lines)
    for seed in seeds:
        say(f"seed {seed} ...")
        r = run_seed(seed, options, args.quick, args.force_accept, quiet, args.retries, not args.no_tool_calibrate, args.arm_poses)
        runs.append(r)
        say("\n".join(table([r])[2:]) + f"   ({r.get('seconds', 0):.0f} s)")
        if (failed := failure(r)) is not None:
            failures.add(*failed)
        tc = r.get("tool_calibration")
        if isinstance(tc, dict):
            say(
                f"  tool calibration: tip {tc['tip_error_mm']:.3f} mm from the true tip (config {tc['config_error_mm']:.3f} mm), "
                f"torch {tc['torch_error_mm']:.3f} mm from the true torch (config {tc['torch_config_error_mm']:.3f} mm, "
                f"across the tool (TCP y) {tc['torch_error_xyz_mm'][1]:+.3f} mm), "
                f"1-sigma {tc['tip_std_mm']} mm, RMS {tc['rms_mm']} mm, {tc['poses']} poses, verdict {tc['verdict']}"
            )
    sources = sorted(((set(SOURCES) if args.preset == "realistic" else set()) | set(options.on)) - set(options.off))
    summary = summarise(label, sources, runs)
    measured = [r["tool_calibration"] for r in runs if isinstance(r.get("tool_calibration"), dict)]
    summary["tool_tip_error_mm"] = [tc["tip_error_mm"] for tc in measured]
    summary["tool_torch_error_mm"] = [tc["torch_error_mm"] for tc in measured]
    say("")
    say(f"preset: {label} (sources on: {', '.join(sources) or 'none'})")
    for line in table(runs):
        say(line)
    say(
        f"targeting mean {summary['targeting_mean_mm']} mm (target <= {TARGETING_MEAN}): "
        f"{'met' if summary['targets']['targeting_mean'] else 'missed'}; torch within {TORCH_RMS} / {TORCH_MAX} mm in every seed: "
        f"{'met' if summary['targets']['torch_every_seed'] else 'missed'}; torch height within {CTWD_MAX} mm of the height "
        f"welded at in every seed: {'met' if summary['targets']['ctwd_within_1_0_every_seed'] else 'missed'} "
        f"({summary['ctwd_err_max_mm']} mm); successes {summary['successes']} of {len(runs)}"
    )
    if not args.quick:
        out = Path(args.out) if args.out else OUT / label.replace(" ", "_")
        out.mkdir(parents=True, exist_ok=True)
        (out / "results.json").write_text(json.dumps({"summary": summary, "runs": runs}, indent=1))
        (out / "results.md").write_text("\n".join([f"preset {label}", "", *table(runs), ""]))
        say(f"results in {out}")
    if args.json:
        print(
            json.dumps(
                {"summary": summary, "runs": runs, "failed": failures.jobs},
                default=lambda o: None if isinstance(o, float) and not math.isfinite(o) else str(o),
            )
        )
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
