"""Weld on a calibrated cell, over the bus: the daemon, the simulated cell, real zenoh and real ur-rtde.

The cell is ``configs/sim-cell.toml`` on this test's own loopback address, in
the ideal world of :mod:`celld.sim.world` (the truth is the cell as drawn):
the simulated UR10e in real time, the ray-cast PhoXi M, a V-groove placed off
its place, the simulated SRM camera read by the real ArUco detector. The
test talks to ``celld run`` only over the bus and scores the results against
the world's truth, which the daemon never reads. The calibration the weld
needs is a real one of this world, solved offline before the cell starts (8
poses, :func:`tests.daemon.cells.solve_offline`) and installed as the
accepted one once the daemon has refused a weld without it; the calibrate job
is tested end to end in ``test_daemon_e2e.py``. The realistic worlds, with
their robot, scanner, tool, finger and part errors, run in
bench/realistic_cell.py. About a minute and a half: a dry run, a weld
cancelled in its track (the torch until then scored against the part), a
kill -9 of the daemon mid-weld and the next daemon's dry run. A whole seam's
weld, its recording and timeline are ``test_toolcal_e2e.py``'s.
"""

from __future__ import annotations

import math
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from celld import se3, sealed
from celld.calib.kinematic import ArmModel
from celld.journal import Journal
from celld.recording.readback import read_entities
from celld.robot import kinematics as kin
from celld.sim.cell import run_cell, sim_part, start_daemon, stop_daemon
from celld.sim.score import TruthRecorder, lateral, targeting, true_torch_path
from tests.daemon.cells import install_calibration
from tests.daemon.exported import check_exported, checked_result
from tests.daemon.orphans import after_kill, motion_exits
from tests.daemon.welds import ArcWatch

pytestmark = pytest.mark.cell

ARC = 0  # the arc's digital output in configs/sim-cell.toml
# The world of this test: the ideal cell (its truth is its drawing). The
# realistic worlds, where the tactile correction must do the work, run in
# bench/realistic_cell.py, which reports their figures.
WORLD_SEED = 3
# The calibration the weld starts from: 8 generated poses (seed 5), every one kept.
CAL_POSES = 8
CAL_SEED = 5


def _config(cell_config) -> Path:
    return cell_config(
        "sim-cell.toml",
        "weld-e2e",
        {
            "calibration": {"n_poses": CAL_POSES},
            # Half the PhoXi M's resolution: a quarter of the rays per capture (the tool calibration's e2e and
            # the benchmarks scan at full resolution).
            "sim": {"preset": "ideal", "seed": WORLD_SEED, "scanner": {"resolution_scale": 0.5}},
        },
    )


def test_a_calibrated_weld_tracks_the_seam_and_a_cancelled_or_killed_weld_stops(tmp_path: Path, cell_config, offline_calibration) -> None:
    cfg_path = _config(cell_config)
    calibration = offline_calibration(cfg_path, CAL_POSES, CAL_SEED)
    with run_cell(cfg_path, tmp_path / "daemon.log", timeout=120) as cell:
        client, cfg, robot, world = cell.client, cell.config, cell.robot, cell.world
        assert world.preset == "ideal"
        part = sim_part(world)

        # A weld before any calibration is refused with the reason.
        _, record = client.submit_and_wait({"kind": "weld"}, timeout=60)
        assert record["state"] == "failed" and "no current calibration" in record["reason"]
        assert checked_result(client, record) is None

        # This world's calibration, made current as an accept makes it; the daemon serves it as it stores it (sealed).
        install_calibration(cfg.cell.state_dir, calibration)
        current = client.calibration()
        check_exported("calibration-reply", {"ok": True, "calibration": current})
        assert current == sealed.seal(calibration, "calibration") and client.status()["calibration"] == calibration["job"]
        T_est = np.array(current["T_base_cam"])
        # T_base_cam absorbs what it can of the arm's kinematic error, so it is off the true one by
        # more than the scanner's noise; what counts is where the arm lands when sent to what the
        # scanner saw: the realistic cell's target, 0.25 mm on average in the calibrated volume (met here a fortiori).
        dt, dr = se3.error(T_est, world.scanner.T_base_cam)
        assert dt <= 2e-3 and math.degrees(dr) <= 0.2, (dt * 1e3, math.degrees(dr))
        aim = targeting(world, T_est, cfg)
        assert aim["calibration"]["mean_mm"] <= 0.25, aim

        # The arm at the scan pose: a dry run scans, plans and checks the weld, and moves nothing.
        _, moved = client.submit_and_wait({"kind": "move", "target": {"space": "cartesian", "pose": list(cfg.weld.scan_pose)}}, timeout=120)
        assert moved["state"] == "succeeded", (moved["reason"], robot.status())
        time.sleep(1.0)  # the arm has rung down after its stop
        q_before = robot.truth()[2]
        _, dry = client.submit_and_wait({"kind": "weld", "dry_run": True}, timeout=300)
        assert dry["state"] == "succeeded", dry["reason"]
        planned = checked_result(client, dry)
        assert planned["dry_run"] and len(planned["tcp_path"]) > 10 and planned["min_clearance_mm"] > 5.0, planned
        assert np.max(np.abs(robot.truth()[2] - q_before)) < 1e-6, "a dry run moved the arm"
        assert "/world/robot/pose_01" in read_entities(Path(planned["recording"]))

        # Planned through an arm calibration that says the upper arm is half a millimetre longer than the
        # controller believes: what the controller is sent moves by what that model corrects at the weld.
        nominal = kin.UR10E
        longer = kin.DH(nominal.d, tuple(np.add(nominal.a, [0.0, -0.5e-3, 0.0, 0.0, 0.0, 0.0]).tolist()), nominal.alpha)
        model = ArmModel(nominal, longer)
        arm_entry = {"robot": "ur10e", "T_base_cam": calibration["T_base_cam"], "corrections": model.as_dict()}
        install_calibration(cfg.cell.state_dir, {**calibration, "arm": arm_entry})
        _, dry_arm = client.submit_and_wait({"kind": "weld", "dry_run": True}, timeout=300)
        assert dry_arm["state"] == "succeeded", dry_arm["reason"]
        through_arm = checked_result(client, dry_arm)
        shift = np.linalg.norm(np.array(through_arm["planned_path"]) - np.array(planned["planned_path"]), axis=1)
        # The tool over the seam: the model moves the flange 0.2-0.5 mm there (a 0.5 mm longer link, turned by
        # the shoulder and elbow); the scan's own noise moves the seam a few hundredths.
        assert 0.1e-3 < float(np.median(shift)) < 1.0e-3 and float(np.ptp(shift)) < 0.2e-3, (shift.min(), shift.max())
        install_calibration(cfg.cell.state_dir, calibration)

        # The scanner knocked 50 mm and turned 2 degrees since, its calibration file intact (moved here with the
        # calibration, which is the same to the cell): the verification refuses with its figure, and so does every
        # weld, until a calibration that holds is accepted.
        knocked = np.array(calibration["T_base_cam"]) @ se3.from_ur_pose([0.05, 0.0, 0.0, 0.0, 0.0, math.radians(2.0)])
        install_calibration(cfg.cell.state_dir, {**calibration, "T_base_cam": knocked.tolist()})
        _, verified = client.submit_and_wait({"kind": "verify"}, timeout=180)
        assert verified["state"] == "failed" and "the current calibration failed its verification" in verified["reason"]
        figure = float(verified["reason"].split("the flange is ")[1].split(" mm")[0])
        assert 40.0 < figure < 80.0, verified["reason"]
        # The worst pose decides: the arm stopped looking once two poses were seen, one of them that far off.
        record = sealed.read_sealed(Path(cfg.cell.state_dir) / "verification.json", "verification", "the verification record")
        assert not record["passed"] and sum(p["seen"] for p in record["poses"]) == 2 < cfg.calibration.verify_poses, record
        _, refused = client.submit_and_wait({"kind": "weld"}, timeout=60)
        assert refused["state"] == "failed" and f"failed its verification by job {verified['id']}" in refused["reason"]
        assert f"the flange is {figure:.2f} mm" in refused["reason"]
        assert f"failed its verification by job {verified['id']}" in client.status()["message"]
        install_calibration(cfg.cell.state_dir, calibration)
        _, verified = client.submit_and_wait({"kind": "verify"}, timeout=180)
        assert verified["state"] == "succeeded", verified["reason"]
        check = checked_result(client, verified)
        assert check["passed"] and check["error_mm"] <= check["bound_mm"] and len(check["poses"]) == cfg.calibration.verify_poses

        # Cancel during the track: a jerk-limited stop, the arc off, the job cancelled. Until then the torch,
        # tracked by touch with Algorithm 2, met the tactile targets (a whole seam's weld, its recording and
        # timeline: tests/daemon/test_toolcal_e2e.py, in the realistic world).
        arc = ArcWatch(robot, ARC)
        with TruthRecorder(cfg.robot.host) as truth, client.watch_progress() as events:
            job = client.submit({"kind": "weld", "ref": "cancelled"})["job"]
            events.wait_stage(job, "track", timeout=240)
            time.sleep(6.0)
            assert client.cancel(job, "operator")["state"] == "cancelled"
        assert arc.close()
        torch = lateral(part, true_torch_path(world, truth.records(), ARC))
        assert torch["points"] > 20 and torch["rms_mm"] <= 0.2 and torch["max_mm"] <= 0.5, torch
        assert client.status(job)["state"] == "cancelled"
        assert checked_result(client, job) is None
        time.sleep(0.5)
        q0 = robot.truth()[2]
        time.sleep(0.3)
        assert np.max(np.abs(robot.truth()[2] - q0)) < 1e-4
        assert int(robot.status()["digital_out"]) & (1 << ARC) == 0, "the arc goes off with the stop"

        # kill -9 of the daemon mid-weld, the arc on: its orphaned motion process stops
        # the arm (jerk-limited) with the arc off at once, and ends; the next daemon welds.
        with client.watch_progress() as events:
            killed = client.submit({"kind": "weld", "ref": "killed"})["job"]
            events.wait_stage(killed, "track", timeout=240)
        deadline = time.monotonic() + 60
        while not int(robot.status()["digital_out"]) & (1 << ARC):
            assert time.monotonic() < deadline, "the arc never came on"
            time.sleep(0.02)
        time.sleep(0.5)
        t_kill = time.monotonic_ns()
        cell.daemon.send_signal(signal.SIGKILL)
        cell.daemon.wait(10)
        seen = after_kill(robot, t_kill, arc_output=ARC)
        assert seen.moving_at_kill > 0.002, seen  # tracking at V_const (10 mm/s)
        # The motion process looks for its daemon every 10 ms (its /proc entry shows the kill at once).
        assert seen.arc_off_s < 0.05, (seen, motion_exits(tmp_path / "daemon.log"))
        assert seen.at_rest_s < 0.5, (seen, motion_exits(tmp_path / "daemon.log"))
        journal = Journal(Path(cfg.cell.state_dir) / "journal.db")  # the killed daemon held it
        assert journal.get(job).state == "cancelled"
        assert journal.check() == []
        journal.close()
        # The next daemon runs jobs: it takes the tool off the part to the scan pose and plans the weld
        # again (a whole weld after a restart is the first weld's path; the tactile process's own restart
        # is tests/tactile/test_camera.py's).
        with open(tmp_path / "daemon2.log", "ab") as log:
            second = start_daemon(cfg_path, log, timeout=120)
            try:
                record = second.client.status(killed)
                # Interrupted, and why: what the orphaned motion process noted (its daemon killed), no operator's stop.
                assert record["state"] == "interrupted" and "motion process: the daemon" in record["reason"], record
                target = {"space": "cartesian", "pose": list(cfg.weld.scan_pose)}
                _, moved = second.client.submit_and_wait({"kind": "move", "target": target}, timeout=120)
                assert moved["state"] == "succeeded", (moved["reason"], robot.status())
                checked_result(second.client, moved)
                _, dry = second.client.submit_and_wait({"kind": "weld", "dry_run": True, "ref": "after the kill"}, timeout=300)
                assert dry["state"] == "succeeded", (dry["reason"], robot.status())
                checked_result(second.client, dry)
            finally:
                second.client.close()
                stop_daemon(second.process)
