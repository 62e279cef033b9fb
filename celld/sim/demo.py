"""``celld demo``: the simulated cell end to end, driven over the bus like an MES.

1. draws the simulated cell's world from ``configs/sim-cell.toml``'s
   ``[sim]`` table (preset ``realistic`` unless ``--preset ideal``; the robot's
   true kinematics, the scanner's mount, scale and distortion, the flange as
   made, the tool as built, the part as placed and distorted), starts the
   simulated UR10e in it (behind real ur-rtde, in real time) and the daemon on
   its devices as its own process (``celld sim run``);
2. submits a calibrate job over zenoh, shows its progress, accepts the result;
3. submits a tool-calibrate job (the SRM tip and the torch measured by the scanner) and
   accepts it, unless ``--no-tool-calibrate``;
4. submits a weld job: scan, seam, touch, Algorithm 2 with the arc, retract;
5. prints, side by side against the world's truth: the calibration (its
   error and where the robot truly lands when sent to points the scanner
   saw), the weld plan alone (where the torch would go following the plan
   from scan and calibration without the tactile correction) and the torch as
   it truly went with Algorithm 2, and the paths of the jobs' ``.rrd``
   recordings.

Only this script reads the truth, after the jobs have ended (a recorder
keeps the arm's true states while the weld runs, since the robot's shared
history holds two seconds); the daemon never sees it. The ``realistic``
world's tool differs from the configured one by up to 1-2 mm: the
tool-calibrate job measures its tip and torch (``--no-tool-calibrate`` welds with the
configured tip, ``--without tool_offsets`` as if the tool were as drawn).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from celld.cliparse import add_command

if TYPE_CHECKING:
    import numpy as np

# celld --help imports this module to build its parser: the functions import what they run.

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "sim-cell.toml"
# The demo's arm calibration: wide poses after the hand-eye calibration (bench/arm_calibration.py: 40 to 80
# halve the error over the table in the realistic worlds; more poses do not help against the bias that is left).
DEMO_ARM_POSES = 40


def add_parser(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "demo", _arguments, help="run the simulated cell and its daemon: calibrate, tool-calibrate, then weld, over the bus")


def _arguments(p: argparse.ArgumentParser) -> None:
    from celld.sim.world import add_world_arguments

    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="a cell config whose devices are simulated")
    p.add_argument("--poses", type=int, default=None, help="calibration poses (default: the config's n_poses)")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object last")
    p.add_argument("--force-accept", action="store_true", help="accept a calibration that fails the daemon's quality gate")
    p.add_argument("--no-tool-calibrate", action="store_true", help="weld with the configured tool tip, no tool-calibrate job")
    p.add_argument(
        "--arm-poses",
        type=int,
        default=DEMO_ARM_POSES,
        help=f"wide poses of the arm's kinematic calibration after the hand-eye one (default {DEMO_ARM_POSES}; 0: hand-eye only)",
    )
    add_world_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from celld import config as config_mod
    from celld.errors import CelldError
    from celld.sim.world import options_from_args, world_of

    cfg = config_mod.load(args.config)
    options = options_from_args(args)
    world = world_of(cfg, options)
    if cfg.scanner.kind != "sim" or cfg.tactile.kind != "sim" or world.part is None:
        print("celld demo: the config must simulate the scanner and the SRM and name a [sim.part] workpiece", file=sys.stderr)
        return 2
    state = Path(cfg.cell.state_dir)
    state.mkdir(parents=True, exist_ok=True)
    log_path = state / "demo-daemon.log"
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if args.json else (lambda text: print(text, flush=True))
    say(f"celld demo: simulated cell {cfg.cell.name!r} on {cfg.robot.host}; daemon log {log_path}")
    say(world.describe())
    t0 = time.monotonic()
    try:
        figures = run_jobs(
            args.config,
            log_path,
            options,
            say,
            n_poses=args.poses,
            force_accept=args.force_accept,
            tool_calibrate=not args.no_tool_calibrate,
            arm_poses=args.arm_poses,
        )
    except CelldError as exc:
        say(f"celld demo failed: {exc}")
        return 1
    if "failed" in figures:
        return 1
    for line in summary_lines(figures):
        say(line)
    say("recordings (open with: rerun FILE.rrd):")
    say(f"  {figures['calibration']['recording']}")
    say(f"  {figures['weld']['recording']}")
    say(f"weld paths: {figures['weld']['paths']}   total {time.monotonic() - t0:.0f} s")
    if args.json:
        print(json.dumps(figures))
    return 0


def run_jobs(
    config_path: str | Path,
    log_path: str | Path,
    options: Any,
    say: Any,
    n_poses: int | None = None,
    calibrate_seed: int | None = None,
    force_accept: bool = False,
    tool_calibrate: bool = False,
    arm_poses: int = 0,
) -> dict[str, Any]:
    """Start the cell of ``config_path`` in the world of ``options``, calibrate, accept, weld; score against the truth.

    With ``arm_poses`` the calibrate job calibrates the arm's kinematics too from that many wide poses
    (not with a second robot), and the figures score the targeting with the hand-eye calibration alone
    beside it (``targeting_hand_eye``).

    With ``tool_calibrate`` a tool-calibrate job runs (and is accepted) between
    the calibration and the weld, and ``tool`` in the figures scores its tip
    against the tool as built.

    Returns the figures (``world``, ``calibration``, ``weld``), or ``failed``
    with the job's record when a job did not succeed. A calibration that
    fails the daemon's quality gate is accepted only with ``force_accept``
    (and the figures say so); otherwise it ends the run. Raises CelldError
    when the cell does not come up.
    """
    import numpy as np

    from celld import se3
    from celld.calib.mount import placement_of
    from celld.errors import JobError
    from celld.sim.cell import run_cell, sim_part
    from celld.sim.score import (
        TruthRecorder,
        height,
        lateral,
        measured_tool,
        open_loop_torch,
        targeting,
        touch_check_truth,
        true_camera,
        true_torch_path,
    )
    from celld.sim.srm import tip_of_tag

    figures: dict[str, Any] = {}
    t0 = time.monotonic()
    with run_cell(config_path, log_path, world=options) as cell:
        world, cfg = cell.world, cell.config
        part = sim_part(world)
        assert part is not None  # the caller checked the world has a part
        figures["world"] = {"preset": world.preset, "seed": world.seed, "sources": sorted(world.budget.enabled)}
        say(f"daemon up, robot link up ({time.monotonic() - t0:.0f} s)")
        calibrate: dict[str, Any] = {"kind": "calibrate"}
        if n_poses:
            calibrate["n_poses"] = n_poses
        if calibrate_seed is not None:
            calibrate["seed"] = calibrate_seed
        if cfg.robot2 is not None:
            calibrate["robot2"] = True  # a second robot in view: both, and T_base1_base2 (Eq. 5-6)
        elif arm_poses:
            calibrate["arm_poses"] = arm_poses
        cal = _job(cell.client, calibrate, say)
        if cal["state"] != "succeeded":
            return {**figures, "failed": _failed(cal, say), "loop": _loop(cell.client)}
        cal_result = json.loads(Path(cal["result"]).read_text())
        quality = cal_result["calibration"].get("quality") or {}
        forced = False
        try:
            accepted = cell.client.accept(cal["id"])
        except JobError as exc:
            say(f"calibration {cal['id']} refused at accept: {exc}")
            if not force_accept:
                return {
                    **figures,
                    "failed": {
                        "job": cal["id"],
                        "kind": "calibrate",
                        "state": "not accepted",
                        "reason": str(exc),
                        "verdict": quality.get("verdict"),
                    },
                    "loop": _loop(cell.client),
                }
            accepted, forced = cell.client.accept(cal["id"], force=True), True
        # The scanner's pose where it is fixed (on the arm: on its link, scored where the arm holds it at
        # the verification pose, the joints the session recorded there).
        placed = placement_of(accepted["calibration"])
        dt, dr = se3.error(placed.T_ref_cam, world.scanner.T_mount_cam)
        q_v = _verification_joints(cal_result["calibration"]["dataset"]) if placed.mount.on_arm else None
        figures["calibration"] = {
            "job": cal["id"],
            "transform": f"T_{placed.mount.frame}_cam",
            "translation_error_mm": dt * 1e3,
            "rotation_error_deg": math.degrees(dr),
            "pairs": cal_result["calibration"]["pairs"],
            "recording": cal_result.get("recording"),
            "verdict": quality.get("verdict"),
            "forced": forced,
            "bound": quality.get("bound"),  # what the calibration says of its own error (celld.calib.quality)
            "targeting": targeting(world, placed.T_base_cam(q_v), cfg, true_camera(world, q_v) if q_v is not None else None, placed.arm),
        }
        if placed.arm is not None:
            # The same cell with the hand-eye calibration alone, for the arm calibration's gain; and what it fitted.
            hand_eye = np.asarray(cal_result["calibration"]["T_base_cam"])
            figures["calibration"]["targeting_hand_eye"] = targeting(world, hand_eye, cfg)
            arm_entry = cal_result["calibration"]["arm"]
            figures["calibration"]["arm"] = {k: arm_entry[k] for k in ("pairs", "rank", "condition", "held", "residual_rms_mm", "bound")}
        say(
            f"calibration {cal['id']} accepted{' (forced past its quality gate)' if forced else ''}: "
            f"{dt * 1e3:.3f} mm, {math.degrees(dr):.4f} deg from the true T_{placed.mount.frame}_cam"
        )
        entry = cal_result["calibration"].get("robot2")
        if entry is not None and world.robot2 is not None and cfg.robot2 is not None:
            figures["robot2"] = robot2_figures(entry, world.robot2.T_base1_base2, cfg.robot2.verification_pose)
            r2 = figures["robot2"]
            say(
                f"robot 2's base: {r2['meet_mm']:.3f} mm (1-sigma {r2['meet_std_mm']:.3f}) where the robots meet, "
                f"{r2['rotation_deg']:.4f} deg from the truth; the drawing was {r2['from_drawing_mm']:.2f} mm off"
            )
        if tool_calibrate:
            tc = _job(cell.client, {"kind": "tool-calibrate", "seed": calibrate_seed or 0}, say)
            if tc["state"] != "succeeded":
                return {**figures, "failed": _failed(tc, say), "loop": _loop(cell.client)}
            tool = json.loads(Path(tc["result"]).read_text())["tool"]
            tq = tool["quality"]
            tool_forced = False
            try:
                cell.client.accept(tc["id"])
            except JobError as exc:
                say(f"tool calibration {tc['id']} refused at accept: {exc}")
                if not force_accept:
                    return {
                        **figures,
                        "failed": {
                            "job": tc["id"],
                            "kind": "tool-calibrate",
                            "state": "not accepted",
                            "reason": str(exc),
                            "verdict": tq["verdict"],
                        },
                        "loop": _loop(cell.client),
                    }
                cell.client.accept(tc["id"], force=True)
                tool_forced = True
            tip_true = np.asarray(world.tool.config.tip_tcp)
            err = np.asarray(tool["tip_tcp_mm"]) * 1e-3 - tip_true
            torch_true = np.asarray(world.tool.p_flange_torch)
            torch_err = np.asarray(tool["torch_tcp_mm"]) * 1e-3 - torch_true
            figures["tool"] = {
                "torch_measured": bool(tool.get("torch_measured")),
                "torch_error_mm": float(np.linalg.norm(torch_err) * 1e3),
                "torch_error_xyz_mm": (torch_err * 1e3).tolist(),
                "torch_config_error_mm": float(np.linalg.norm(np.asarray(world.tool.p_flange_torch_nominal) - torch_true) * 1e3),
                "job": tc["id"],
                "tip_error_mm": float(np.linalg.norm(err) * 1e3),
                "tip_error_xyz_mm": (err * 1e3).tolist(),
                "config_error_mm": float(np.linalg.norm(np.asarray(cfg.tool.tip_tcp) - tip_true) * 1e3),
                "tip_std_mm": tool["tip_std_mm"],
                "rms_mm": tq["rms_mm"],
                "poses": tool["poses"],
                "verdict": tq["verdict"],
                "forced": tool_forced,
            }
            say(
                f"tool calibration {tc['id']} accepted: tip {figures['tool']['tip_error_mm']:.3f} mm from the true tip "
                f"(the config's {figures['tool']['config_error_mm']:.3f} mm), torch "
                f"{figures['tool']['torch_error_mm']:.3f} mm from the true torch (the config's "
                f"{figures['tool']['torch_config_error_mm']:.3f} mm{'' if figures['tool']['torch_measured'] else ', not measured'}), "
                f"verdict {tq['verdict']}"
            )
        with TruthRecorder(cfg.robot.host) as recorder:
            weld = _job(cell.client, {"kind": "weld"}, say)
        if weld["state"] != "succeeded":
            return {**figures, "failed": _failed(weld, say), "loop": _loop(cell.client)}
        res = json.loads(Path(weld["result"]).read_text())  # the record names the result file
        paths = json.loads(Path(res["paths"]).read_text())
        planned, planned_wall = np.array(paths["planned"]), np.array(paths["planned_wall"])
        home = np.asarray(cfg.robot.home_q, dtype=np.float64)
        torch_true = true_torch_path(world, recorder.records(), cfg.robot.arc_output)
        plan_alone = open_loop_torch(world, planned, planned_wall, home)
        figures["weld"] = {
            "job": weld["id"],
            # Following the plan without the finger: the typed tool's torch on the plan, the true arm and tool.
            "plan_alone_error": lateral(part, plan_alone),
            # The torch's height over the true root against the height the cell welds at (weld.tip_height).
            "plan_alone_height": height(part, plan_alone, cfg.weld.tip_height),
            "torch_height": height(part, torch_true, cfg.weld.tip_height),
            # The plan itself, as the scan and the calibration placed it in the base frame.
            "plan_error": lateral(part, planned),
            # The torch as it truly went, Algorithm 2 tracking the wall by touch.
            "torch_error": lateral(part, torch_true),
            # The torch as the daemon believes it went (its kinematics and tool config).
            "torch_believed_error": lateral(part, np.array(res["torch_path"])),
            "figures": res["figures"],
            # The tip's height in the joint, probed by touch before tracking, and the correction made.
            "height_probe": res.get("height_probe"),
            # What the arc did, with a power source.
            "arc": res.get("arc"),
            "recording": res.get("recording"),
            "paths": res.get("paths"),
        }
        if tool_calibrate and figures.get("tool", {}).get("torch_measured"):
            # The same with the tool as its calibration measured it (as the weld used it): what touch adds beyond it.
            measured = measured_tool(cfg.tool, tool)
            alone_measured = open_loop_torch(world, planned, planned_wall, home, measured)
            figures["weld"]["plan_alone_measured_tool_error"] = lateral(part, alone_measured)
            figures["weld"]["plan_alone_measured_tool_height"] = height(part, alone_measured, cfg.weld.tip_height)
        # The finger as the world made it: its tag's gain along the tool's y, the joint's normal the touches press along.
        figures["weld"]["finger_truth"] = {
            "tag_gain": list(world.finger.tag_gain),
            "tag_softening_mm": world.finger.tag_softening * 1e3,
            "tip_over_tag": 1.0 / world.finger.tag_gain[1],
            # The same where the servo holds the tag's deformation at delta_d: the finger softened there.
            "delta_d_mm": cfg.servo.delta_d * 1e3,
            "tip_over_tag_held": tip_of_tag(cfg.servo.delta_d, world.finger.tag_gain[1], world.finger.tag_softening) / cfg.servo.delta_d,
        }
        probe = res.get("height_probe") or {}
        if probe.get("probed"):
            # What the touch check should have read: its point where the arm truly put it, against the part's true root;
            # the tip as the weld knew it (the tool calibration's, once accepted).
            tip_used = np.asarray(tool["tip_tcp_mm"]) * 1e-3 if tool_calibrate else cfg.tool.tip_tcp
            figures["weld"]["touch_check_truth"] = touch_check_truth(
                part, probe["touch_check"], recorder.records(), tip_used, world.tool.config.tip_tcp, cfg.robot.arc_output
            )
        figures["verification"] = _verification(Path(cfg.cell.state_dir))
        figures["loop"] = _loop(cell.client)
    return figures


def _verification(state: Path) -> dict[str, Any] | None:
    """The weld's verification of the calibration (celld.daemon.verify's record), None when it did not verify."""
    path = state / "verification.json"
    if not path.is_file():
        return None
    v = json.loads(path.read_text())
    return {k: v.get(k) for k in ("passed", "error_mm", "bound_mm", "calibration_bound_mm", "repeatability_mm")}


def robot2_figures(entry: dict[str, Any], T_base1_base2_true: np.ndarray, verification_pose: tuple[float, ...]) -> dict[str, Any]:
    """A robot-robot calibration (the calibration's ``robot2`` entry) against the truth, where the robots meet."""
    import numpy as np

    from celld import se3

    T_est = np.array(entry["T_base1_base2"])
    p = np.asarray(verification_pose[:3], dtype=np.float64)[None]
    _, dr = se3.error(T_est, T_base1_base2_true)
    return {
        "meet_mm": float(np.linalg.norm(se3.apply(T_est, p) - se3.apply(T_base1_base2_true, p))) * 1e3,
        "meet_std_mm": float(np.linalg.norm(entry["translation_std_mm"])),
        "rotation_deg": math.degrees(dr),
        "from_drawing_mm": entry["from_drawing_mm"],
        "verdict": entry["quality"].get("verdict"),
    }


def _height_lines(torch: dict[str, Any] | None, plan_alone: dict[str, Any] | None) -> list[str]:
    """The torch's height over the true root (contact tip to work), tracked and on the plan alone."""
    if not torch or not torch.get("points"):
        return []
    lines = [
        f"torch height over the true root: mean {torch['mean_mm']:.3f} mm ({torch['min_mm']:.3f} to {torch['max_mm']:.3f}), "
        f"at most {torch['error_max_mm']:.3f} mm from the height welded at"
    ]
    if plan_alone and plan_alone.get("points"):
        lines.append(f"  (on the plan alone: mean {plan_alone['mean_mm']:.3f} mm, at most {plan_alone['error_max_mm']:.3f} mm from it)")
    return lines


def _bound_lines(bound: dict[str, Any] | None) -> list[str]:
    """What the calibration reported of its own error, beside the truth above it."""
    if not bound or bound.get("calibration_box_mm") is None or bound.get("work_radius_mm") is None:
        return []
    return [
        f"  the calibration's own bounds ({bound['confidence']:.0%}): {bound['calibration_box_mm']:.3f} mm in the box, "
        f"{bound['work_radius_mm']:.3f} mm elsewhere in reach (the arm's own error there taken as {bound['arm_error_prior_mm']:.1f} mm)"
    ]


def _arm_lines(c: dict[str, Any]) -> list[str]:
    """The arm calibration's fit and its gain: the targeting with the hand-eye calibration alone beside it."""
    arm, he = c.get("arm"), c.get("targeting_hand_eye")
    if not arm or not he:
        return []
    return [
        f"  (with the arm's kinematic calibration: {arm['pairs']} wide poses, rank {arm['rank']}, condition {arm['condition']:.0f}; "
        f"the hand-eye calibration alone: mean {he['calibration']['mean_mm']:.3f} mm in the box, "
        f"{he['table']['mean_mm']:.3f} mm, max {he['table']['max_mm']:.3f} mm over the table)"
    ]


def summary_lines(figures: dict[str, Any]) -> list[str]:
    """The demo's figures side by side, as printed."""
    c, w = figures["calibration"], figures["weld"]
    tc, tt = c["targeting"]["calibration"], c["targeting"]["table"]
    pa, pl, to, tb = w["plan_alone_error"], w["plan_error"], w["torch_error"], w["torch_believed_error"]
    pm = w.get("plan_alone_measured_tool_error")
    measured = [f"  plan alone, the tool as measured             {pm['rms_mm']:7.3f}  {pm['max_mm']:7.3f}"] if pm else []
    return [
        "",
        f"world: preset {figures['world']['preset']}, seed {figures['world']['seed']}",
        f"calibration: {c['translation_error_mm']:.3f} mm, {c['rotation_error_deg']:.4f} deg from the true {c['transform']} ({c['pairs']} pairs, "
        f"quality gate {c['verdict']}{', accepted by force' if c['forced'] else ''})",
        f"  targeting (the flange sent to points the scanner saw): mean {tc['mean_mm']:.3f} mm, max {tc['max_mm']:.3f} mm "
        f"in the calibration box; mean {tt['mean_mm']:.3f}, max {tt['max_mm']:.3f} mm over the table",
        *_arm_lines(c),
        *_bound_lines(c.get("bound")),
        *_robot2_lines(figures.get("robot2")),
        *_verification_lines(figures.get("verification")),
        "weld, lateral distance from the true seam        RMS mm   max mm",
        f"  plan alone (scan + calibration, open loop)   {pa['rms_mm']:7.3f}  {pa['max_mm']:7.3f}",
        *measured,
        f"  torch, tracked by touch (Algorithm 2)        {to['rms_mm']:7.3f}  {to['max_mm']:7.3f}",
        f"  (the plan's points as placed                 {pl['rms_mm']:7.3f}  {pl['max_mm']:7.3f})",
        f"  (the torch as the daemon believes it went    {tb['rms_mm']:7.3f}  {tb['max_mm']:7.3f})",
        *_height_lines(w.get("torch_height"), w.get("plan_alone_height")),
        _probe_line(w.get("height_probe")),
        _finger_line(w.get("height_probe"), w.get("finger_truth")),
        f"tracked {w['figures']['tracked_mm']:.0f} mm, arc on {w['figures']['arc_on_s']:.1f} s, "
        f"delta_n error {w['figures']['delta_n_error_rms_mm']} mm RMS",
        *_arc_lines(w.get("arc")),
    ]


def _arc_lines(arc: dict[str, Any] | None) -> list[str]:
    """What a power source's arc did (a cell with a [power_source])."""
    if arc is None:
        return []
    d = arc["weld_data"]
    return [
        f"arc ({arc['procedure']}): {arc['ended_in']}, {arc['failed_starts']} failed starts, {arc['restrikes']} re-strikes, "
        f"{arc['arc_losses']} arc losses; welded {arc['welded_mm']:.1f} of {arc['seam_length_mm']:.1f} mm",
        f"  current {d['current_mean_a']:.0f} A ({d['current_min_a']:.0f}-{d['current_max_a']:.0f}), voltage "
        f"{d['voltage_mean_v']:.1f} V, {d['outside_s']:.2f} s outside the procedure's windows" + (" (flagged)" if arc["flagged"] else ""),
    ]


def _verification_lines(v: dict[str, Any] | None) -> list[str]:
    if v is None:
        return []
    return [
        f"verified before the weld: the flange {v['error_mm']:.3f} mm from where the calibration puts it, within "
        f"{v['bound_mm']:.3f} mm (its own {v['calibration_bound_mm']:.3f} + repeatability {v['repeatability_mm']:.3f})"
    ]


def _robot2_lines(r2: dict[str, Any] | None) -> list[str]:
    if r2 is None:
        return []
    return [
        f"robot 2's base (T_base1_base2): {r2['meet_mm']:.3f} mm where the robots meet (reported 1-sigma {r2['meet_std_mm']:.3f} mm), "
        f"{r2['rotation_deg']:.4f} deg from the truth (quality gate {r2['verdict']}); its drawing was {r2['from_drawing_mm']:.2f} mm off"
    ]


def _probe_line(probe: dict[str, Any] | None) -> str:
    if not probe or not probe.get("probed"):
        return f"height probe: not made ({(probe or {}).get('why', 'no figures')})"
    return (
        f"height probe: the joint {probe['joint_width_mm']:.3f} mm wide at the tip (the scan: {probe['scan_width_mm']:.3f} at the planned "
        f"height), the tip {probe['height_mm']:.3f} mm above the seam; plan moved {probe['height_correction_mm']:+.3f} mm"
    )


def _finger_line(probe: dict[str, Any] | None, truth: dict[str, Any] | None) -> str:
    from celld.tactile.fingermap import FingerGain

    finger = (probe or {}).get("finger")
    if not finger:
        return "finger gain: not measured (no height probe)"
    true = (
        f" (the world's: {truth['tip_over_tag']:.4f} along the joint's normal, {truth['tip_over_tag_held']:.4f} at "
        f"{truth['delta_d_mm']:g} mm, where the measured gives {FingerGain.of_reading(finger).over(truth['delta_d_mm'] * 1e-3):.4f})"
        if truth and finger.get("measured")
        else ""
    )
    if not finger["measured"]:
        return f"finger gain: not measured ({finger['why']}): the tag's deformation taken as the tip's{true}"
    return (
        f"finger gain: the tip moves {finger['gain']:.4f} +- {finger['gain_sigma']:.4f} times the tag{true}, "
        f"{finger['frames']} frames, residual {finger['residual_rms_um']:.1f} um"
    )


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


def _loop(client: Any) -> Any:
    """How late the daemon's event loop ran over the jobs so far (celld.daemon.loopwatch)."""
    return client.status().get("loop")


def _failed(record: dict[str, Any], say: Any) -> dict[str, Any]:
    say(f"job {record['id']} {record['state']}: {record.get('reason') or record}")
    return {"job": record["id"], "kind": record.get("kind"), "state": record["state"], "reason": record.get("reason")}


def _verification_joints(dataset: str) -> np.ndarray:
    """The joints a calibration session recorded at its verification pose (a scanner on the arm)."""
    from celld.calib.dataset import load_session
    from celld.errors import CelldError

    v = load_session(dataset).verification
    if v is None or v.q is None:
        raise CelldError(f"{dataset}: the session has no joints at its verification pose")
    return v.q
