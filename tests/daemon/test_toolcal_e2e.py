"""Tool-calibrate, then weld, over the bus, in the realistic world: the measured tip and torch against the tool as
built, and the weld plan alone against the torch tracked by touch.

The cell is ``configs/sim-cell.toml`` on this test's own loopback address in
the realistic world, whose tool is built off its drawing (the tip about a
millimetre from ``tool.tip_tcp_mm``): the ray-cast PhoXi M sees the tool as
built (its torch bent and trimmed off the drawing too), the daemon only its
config; the arm, the scanner, the finger and the part have their errors too.
The scanner casts its full resolution in a window around the tool and the
part only (``[sim.scanner] roi_px``). The calibration the tool calibration
needs is a real one of this world, solved offline before the cell starts
(10 poses, :func:`tests.daemon.cells.solve_offline`) and installed as the
accepted one once the daemon has refused a tool calibration without it; the
calibrate job is tested end to end in ``test_daemon_e2e.py``. About two
minutes (a tool calibration of 14 poses and a weld). The
weld is this suite's whole one: its stages, paths, recording and timeline are
checked here (:func:`tests.daemon.welds.check_weld`); ``test_weld_e2e.py``
refuses, dry-runs, cancels and kills welds in the ideal world.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from celld import se3
from celld.calib.toolcal import solve_tool_tip
from celld.errors import JobError
from celld.sim.cell import run_cell, sim_part
from celld.sim.score import TruthRecorder, lateral, open_loop_torch, touch_check_truth, true_flange, true_torch_path
from celld.sim.srm import tip_of_tag
from celld.tactile.fingermap import FingerGain
from tests.daemon.cells import install_calibration
from tests.daemon.exported import check_exported, checked_result
from tests.daemon.welds import ArcWatch, check_weld

pytestmark = pytest.mark.cell

# This test's world: its tool's tip is about 1.1 mm and its torch 1.3 mm off the drawing, and the arm's
# error over the table (the calibration never saw it) leaves the plan alone 0.6-0.8 mm RMS off the seam
# and the tip half a millimetre low in the groove (bench/realistic_cell.py, seed 3).
# (Seed 1's plan alone is only 0.22-0.29 mm off: too close to the target to show it missed.)
WORLD_SEED = 3
# The measured tip against the tip a perfect scanner gives through this arm, m: a
# fifth of the tip's own radius, well inside the 1-2 mm a typed tool is off.
TIP_TOLERANCE = 0.2e-3
# The wire's end: each axis within this many of the job's own 1-sigma (the cut end's cap fit spreads 0.04-0.07 mm
# per axis over the job's default 12 poses; along the tool's x it only sets how far behind the tip the
# torch is). Over 8 poses the arm's own error at each orientation once left the wire end fixed to 0.13 mm
# (1 sigma), and the job rightly refused it; over the default 12 it once came to 0.101 mm against the job's
# 0.100 (a weak axis at 0.068-0.101 mm between runs of this world): this test takes 14.
TORCH_SIGMAS = 4.0
TOOL_POSES = 14
# The PhoXi M's full-resolution pixels this test's assertions need (row0, row1, col0, col1): the tip and the
# wire's end at every tool calibration pose (rows 792-934, columns 914-1068 in this world) and the part for
# the weld's scan (rows 660-955, columns 870-1228), with 60-80 pixels (15 mm or more) around them.
ROI_PX = [600, 1020, 810, 1290]
# The calibration the tool calibration starts from: every pose of 10 (Algorithm 1 down to 0.01 mm keeps
# them all: the realistic arm's error needs the pairs), the scanner's whole view at half resolution.
CAL_POSES = 10
# The touch check against its truth, mm: the finger's estimate of its deformation and the scan's wall shape are
# all that part them (bench/realistic_cell.py's target is 0.10 mm; here one weld, with room for its scatter).
TOUCH_CHECK_AGREE = 0.15
CAL_SCALE = 0.5
# The finger's measured gain against the world's tag where the servo holds it: within this many of the gain's
# own 1 sigma (0.06-0.7 % off against 1.3-1.9 % in this world's runs, bench/README.md; the touch's frames
# scatter through the finger's play and end short of delta_d).
FINGER_SIGMAS = 3.0


def _config(cell_config) -> Path:
    return cell_config(
        "sim-cell.toml",
        "toolcal-e2e",
        {
            # The scanner sees only ROI_PX here: the verification's poses around the verification pose lie outside
            # it, so this cell leaves verification to verify jobs (tests/daemon/test_weld_e2e.py verifies).
            "calibration": {"n_poses": CAL_POSES, "e_required_mm": 0.01, "verify_before_weld": False},
            "sim": {"preset": "realistic", "seed": WORLD_SEED, "scanner": {"roi_px": ROI_PX}},
        },
    )


def _as_this_arm_knows_it(world, cfg, detections: list[dict], p_flange: np.ndarray) -> np.ndarray:
    """The point ``p_flange`` of the tool as built, solved (T1-T2) from where a perfect scanner sees it at
    the detections' TCP poses, the flange truly placed by the world's arm."""
    q = np.asarray(cfg.robot.home_q, dtype=np.float64)
    T_rep, P_true = [], []
    for det in detections:
        T = np.asarray(det["T_base_tcp"])
        got = true_flange(world, T, q)
        assert got is not None
        T_rep.append(T)
        P_true.append(se3.apply(got[0], p_flange[None])[0])
        q = got[1]
    return solve_tool_tip(np.array(T_rep), np.array(P_true)).p_tcp_tip


def test_tool_calibrate_measures_the_tip_as_built(tmp_path: Path, cell_config, offline_calibration) -> None:
    cfg_path = _config(cell_config)
    calibration = offline_calibration(cfg_path, CAL_POSES, WORLD_SEED, whole_view_scale=CAL_SCALE)
    with run_cell(cfg_path, tmp_path / "daemon.log", timeout=120) as cell:
        client, cfg, world = cell.client, cell.config, cell.world
        tip_true = np.asarray(world.tool.config.tip_tcp)
        tip_config = np.asarray(cfg.tool.tip_tcp)
        assert np.linalg.norm(tip_true - tip_config) > 0.5e-3, "this world's tool must differ from its drawing"
        torch_true, torch_config = np.asarray(world.tool.p_flange_torch), np.asarray(world.tool.p_flange_torch_nominal)
        assert np.linalg.norm(torch_true - torch_config) > 0.5e-3, "this world's torch must differ from its drawing"

        # Without a calibration a tool calibration is refused, with the reason.
        _, refused = client.submit_and_wait({"kind": "tool-calibrate"}, timeout=60)
        assert refused["state"] == "failed" and "no current calibration" in refused["reason"]
        assert checked_result(client, refused) is None

        # This world's calibration, made current as an accept (with force, if its gate failed) makes it.
        install_calibration(cfg.cell.state_dir, calibration)
        assert client.status()["calibration"] == calibration["job"]

        # (A weld on this unmeasured tool is refused, naming tool.measured: tests/daemon/test_weld_inputs.py.)
        events: list[dict] = []
        _, tc = client.submit_and_wait({"kind": "tool-calibrate", "seed": 1, "n_poses": TOOL_POSES}, on_event=events.append, timeout=900)
        assert tc["state"] == "succeeded", tc["reason"]
        assert [e for e in events if e["stage"] == "pose" and e.get("data", {}).get("detected")]
        for e in events:
            check_exported("progress", e)
        result = checked_result(client, tc)
        tool = result["tool"]
        assert tool["quality"]["verdict"] == "ok", tool["quality"]
        tip = np.asarray(tool["tip_tcp_mm"]) * 1e-3
        # The tip as this arm can know it: what a perfect scanner gives at the same poses through the
        # controller's nominal kinematics (the true flange from the world's arm). The arm's own error
        # (its link lengths and offsets) moves it off the tool as built, and the
        # controller carries that error into every TCP pose: this is the tip it needs.
        dataset = json.loads(Path(result["dataset"]).read_text())
        tip_arm = _as_this_arm_knows_it(world, cfg, dataset["detections"], tip_true)
        assert tool["torch_measured"] is True and tool["quality"]["torch"]["verdict"] == "ok", tool["quality"]["torch"]
        torch = np.asarray(tool["torch_tcp_mm"]) * 1e-3
        torch_arm = _as_this_arm_knows_it(world, cfg, dataset["torch_detections"], torch_true)
        err, err_built = tip - tip_arm, tip - tip_true
        print(
            f"tool calibration: tip {np.linalg.norm(err) * 1e3:.4f} mm from the tip a perfect scanner gives ({np.round(err * 1e3, 4).tolist()}), "
            f"{np.linalg.norm(err_built) * 1e3:.4f} mm from the tool as built ({np.round(err_built * 1e3, 4).tolist()}; the arm's part "
            f"{np.round((tip_arm - tip_true) * 1e3, 4).tolist()}), the config {np.linalg.norm(tip_config - tip_true) * 1e3:.3f} mm; "
            f"1-sigma {tool['tip_std_mm']} mm, rms {tool['quality']['rms_mm']:.4f} mm, {tool['poses']} poses"
        )
        assert np.linalg.norm(err) <= TIP_TOLERANCE, (err, tool)
        assert np.linalg.norm(err_built) < np.linalg.norm(tip_config - tip_true)
        t_err = torch - torch_arm
        print(
            f"tool calibration: torch {np.linalg.norm(t_err) * 1e3:.4f} mm from the torch a perfect scanner gives "
            f"({np.round(t_err * 1e3, 4).tolist()}), the config {np.linalg.norm(torch_config - torch_true) * 1e3:.3f} mm from the "
            f"torch as built; 1-sigma {tool['torch_std_mm']} mm, {len(dataset['torch_detections'])} poses"
        )
        # Within what the job reports of itself; how far across the tool it lands (the weld's 0.1 mm) is a
        # figure of bench/realistic_cell.py, over its seeds: one run's scatter is the job's own 1-sigma.
        assert np.all(np.abs(t_err) <= TORCH_SIGMAS * np.asarray(tool["torch_std_mm"]) * 1e-3), (t_err, tool)
        assert np.linalg.norm(torch - torch_true) < np.linalg.norm(torch_config - torch_true)

        accepted = client.accept(tc["id"])
        check_exported("accept-reply", accepted)
        assert accepted["kind"] == "tool-calibrate" and accepted["tool"]["tip_tcp_mm"] == tool["tip_tcp_mm"]
        current = client.request("calibration")
        check_exported("calibration-reply", current)
        assert current["tool"]["job"] == tc["id"] and current["calibration"]["job"] == calibration["job"]
        # A calibrate job is not a tool calibration, nor the reverse: each accept goes to its own store.
        with pytest.raises(JobError):
            client.accept(refused["id"])

        # The weld: the plan from the scan and the calibration alone misses the seam by more than the
        # tactile targets (the part as placed and distorted, the arm's error over the table); the
        # torch tracked by touch, placed by the measured tool, meets them (issue targets: 0.2 mm RMS, 0.5 mm max).
        # (The weld's stages, paths, recording and timeline are checked as every weld's: tests/daemon/welds.py.)
        arc = ArcWatch(cell.robot, cfg.robot.arc_output)
        weld_events: list[dict] = []
        with TruthRecorder(cfg.robot.host) as truth:
            _, weld = client.submit_and_wait({"kind": "weld"}, on_event=weld_events.append, timeout=600)
        arc_seen = arc.close()
        assert weld["state"] == "succeeded", (weld["reason"], cell.robot.status())
        res = checked_result(client, weld)
        assert res["torch"]["measured"] and res["tool_calibration_job"] == tc["id"], res["torch"]
        paths = check_weld(res, weld_events, arc_seen)
        assert int(cell.robot.status()["digital_out"]) & (1 << cfg.robot.arc_output) == 0, "the arc is off after the weld"
        part = sim_part(world)
        plan_alone = lateral(part, open_loop_torch(world, np.array(paths["planned"]), np.array(paths["planned_wall"]), cfg.robot.home_q))
        torch_path = lateral(part, true_torch_path(world, truth.records(), cfg.robot.arc_output))
        print(f"weld: plan alone {plan_alone}, torch tracked by touch {torch_path}")
        assert plan_alone["rms_mm"] > 0.2 or plan_alone["max_mm"] > 0.5, plan_alone
        assert torch_path["points"] > 100 and torch_path["rms_mm"] <= 0.2 and torch_path["max_mm"] <= 0.5, (torch_path, plan_alone)
        # The touch check: the calibration's error at the weld's start as the probe's touches read it, against where
        # the arm truly put the checked point (the controller's belief against the truth, near it).
        # The finger's gain, measured by the probe's touches, against the world's tag along the tool's y (the joint's
        # normal), where the servo holds the tag's deformation (delta_d): the tip's deflection there over the tag's.
        finger = res["height_probe"]["finger"]
        d = cfg.servo.delta_d
        held = FingerGain.of_reading(finger).over(d)
        held_true = tip_of_tag(d, world.finger.tag_gain[1], world.finger.tag_softening) / d
        print(f"finger: {finger}, at {d * 1e3:g} mm {held:.4f}, the world's {held_true:.4f} (its tag {world.finger.tag_gain})")
        assert finger["measured"] and abs(held_true - 1.0) > 0.05, finger
        assert abs(held - held_true) <= FINGER_SIGMAS * finger["gain_sigma"], (held, held_true, finger)
        check = res["height_probe"]["touch_check"]
        truth_check = touch_check_truth(part, check, truth.records(), tip, world.tool.config.tip_tcp, cfg.robot.arc_output)
        assert truth_check is not None
        print(f"touch check: {check}, its truth {truth_check}")
        assert check["verdict"] in ("ok", "beyond_bound") and check["bound_mm"] is not None
        assert math.hypot(check["across_mm"] - truth_check["across_mm"], check["height_mm"] - truth_check["height_mm"]) <= TOUCH_CHECK_AGREE
