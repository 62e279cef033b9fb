"""A scanner on the arm end to end over the bus: calibrate it on its link (Eq. 8), solve it again offline,
and place a scan taken at other joints with it.

The simulated cell of ``configs/sim-cell-eye-on-arm.toml`` (its scanner on a
boom on link 1, turning with the base joint) in its ideal world, so that
what is measured is the plumbing: the daemon's calibrate job solves
``T_link1_cam`` from the flange at each capture placed in link 1's frame by
the joints of that capture, and the weld's scan at the scan pose (the base
joint elsewhere than at every calibration pose) is placed with the joints
there (placed with the verification pose's, it would land 14 mm off). The
realistic worlds (the arm's kinematic error, the boom's mounting error, the
scanner's) are benchmark 4 of bench/calib_accuracy.py. Scored against the
simulator's truth only at the end. Slow (eight poses at half resolution and
a dry-run weld, about a minute).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from celld import se3
from celld.calib.dataset import load_session
from celld.calib.mount import ScannerMount
from celld.sim.cell import run_cell
from celld.sim.score import targeting, true_camera
from tests.daemon.exported import check_exported, checked_result
from tests.daemon.scans import planned_from_the_scan_pose, rms_mm

pytestmark = pytest.mark.cell

WORLD_SEED = 2
# Where the flange lands when sent to points the scanner saw, mean over the calibration box, m: the
# cell's target (issue 13; the paper's hardware 0.28 mm). Here only the scanner's noise at half
# resolution over seven or eight pairs spends it (0.03-0.11 mm in these runs); a pose solved in the
# wrong frame would miss by centimetres.
TARGETING_MEAN = 0.25e-3
# The scan's plan against the true root line, RMS, m: the scanner's noise and the seam fit.
SCAN_RMS = 0.3e-3


def _config(cell_config) -> Path:
    return cell_config(
        "sim-cell-eye-on-arm.toml",
        "eye-on-arm-e2e",
        {
            "calibration": {"n_poses": 8},
            # Nothing here touches a seam (the weld is a dry run): the finger camera at a quarter of its rate.
            "tactile": {"fps": 15},
            "sim": {"preset": "ideal", "seed": WORLD_SEED, "scanner": {"resolution_scale": 0.5}},
        },
        recording=False,  # nothing here reads a recording
    )


def test_a_scanner_on_the_arm_is_calibrated_on_its_link_and_places_a_scan_at_other_joints(tmp_path: Path, cell_config) -> None:
    cfg_path = _config(cell_config)
    with run_cell(cfg_path, tmp_path / "daemon.log", timeout=120) as cell:
        client, cfg, world = cell.client, cell.config, cell.world
        assert cfg.scanner.mount == "link1" and world.scanner.link == 1

        _, record = client.submit_and_wait({"kind": "calibrate", "seed": 1}, timeout=900)
        assert record["state"] == "succeeded", record["reason"]
        result = checked_result(client, record)
        calibration = result["calibration"]
        # Stored in the link's frame, with the DH table it was solved with; no T_base_cam (it moves).
        assert calibration["mount"] == "link1" and "T_base_cam" not in calibration
        T_link_cam = np.array(calibration["T_link1_cam"])
        report = result["report"]
        assert "T_link1_cam" in report and "T_base_cam" not in report
        quality = report["quality"]
        assert quality["verdict"] == "ok", quality["reasons"]
        # (The job may stop early once Algorithm 1 and the quality gate are satisfied: at the gate's five pairs.)
        assert len(quality["pairs"]) >= 5 and all(np.isfinite(quality["translation_std_mm"]))

        # Against the truth: where the arm lands when sent to what the scanner saw, with the scanner
        # where the arm holds it at the verification pose.
        mount = ScannerMount.of("link1", cfg.robot.model)
        session = load_session(calibration["dataset"])
        assert session.mount == mount and session.verification is not None and session.verification.q is not None
        q_v = session.verification.q
        aim = targeting(world, mount.T_base_cam(T_link_cam, q_v), cfg, true_camera(world, q_v))
        assert aim["calibration"]["mean_mm"] <= TARGETING_MEAN * 1e3, aim
        dt, dr = se3.error(T_link_cam, world.scanner.T_mount_cam)
        assert dt < 1e-3 and math.degrees(dr) < 0.1, (dt * 1e3, math.degrees(dr))

        # The saved session solves again offline, in the link's frame, to the same transform.
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "celld.cli",
                "calib",
                "solve",
                calibration["dataset"],
                "--json",
                "--config",
                str(cfg_path),
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        assert out.returncode == 0, out.stderr
        offline = json.loads(out.stdout)
        assert offline["mount"] == "link1"
        np.testing.assert_allclose(np.array(offline["T_link1_cam"]), T_link_cam, atol=1e-9)

        accepted = client.accept(record["id"])
        check_exported("accept-reply", accepted)
        current = client.calibration()
        check_exported("calibration-reply", {"ok": True, "calibration": current})
        assert current["T_link1_cam"] == calibration["T_link1_cam"]

        # A scan at the scan pose (the base joint and the boom elsewhere than at the calibration poses),
        # placed with the joints there: the plan against the part's true root line at the tip's height.
        result, d = planned_from_the_scan_pose(client, cfg, world)
        assert float(np.sqrt(np.mean(d**2))) <= SCAN_RMS, rms_mm(d)
        assert result["calibration_job"] == record["id"]
        # The joints matter: placed where the boom was at the verification pose, the same scan would be off by
        # far more than that (14 mm here: the base joint turns 0.03 rad between the two).
        q_scan = np.asarray(cell.robot.truth()[2])  # the arm is still at the scan pose
        swing = se3.error(mount.T_base_cam(T_link_cam, q_scan), mount.T_base_cam(T_link_cam, q_v))[0]
        assert swing > 10 * SCAN_RMS, swing
