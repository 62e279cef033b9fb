"""A time-of-flight cell end to end over the bus: calibrate on the 90 mm wrist circle, then place a seam.

The simulated cell of ``configs/sim-cell.toml`` in its ideal world, with
the ray-cast Azure Kinect instead of the PhoXi M (both the cell's belief,
``[scanner]``, and the world's truth, ``[sim.scanner]``): it reads bare
metal (the tool flange, the steel part and table) 8 mm long. The daemon's calibrate job estimates that
range bias with T_base_cam (``calibration.range_bias`` defaults to estimate
for this scanner) and stores it with the calibration; a weld's scan is
corrected by it before its seam is placed. The test talks to ``celld run``
only over the bus and scores against the simulator's truth. Slow.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from celld import se3
from celld.sim.cell import run_cell
from celld.sim.scanner import SCANNER_MODELS
from tests.daemon.exported import check_exported, checked_result
from tests.daemon.scans import planned_from_the_scan_pose, rms_mm

pytestmark = pytest.mark.cell


def _config(cell_config) -> Path:
    return cell_config(
        "sim-cell.toml",
        "tof-e2e",
        {
            "scanner": {"model": "azure-kinect"},
            "calibration": {
                "flange": "ur10e-wrist",
                "n_poses": 12,
                "e_required_mm": 0.0,
                # 0.68 m below the camera: the Azure Kinect sees from 0.5 m.
                "verification_pose": [0.6, 0.0, 0.32, 0.0, 0.0, 0.0],
            },
            "tactile": {"fps": 15},
            # The Azure Kinect's wide view holds the robot's base column: look for the part only around the fixture.
            "seam": {"roi_min": [0.3, -0.35, -0.05], "roi_max": [0.9, 0.35, 0.3]},
            "sim": {"preset": "ideal", "flange": "ur10e-wrist", "scanner": {"model": "azure-kinect"}},
        },
        recording=False,  # nothing here reads a recording
    )


def test_calibrate_estimates_the_range_bias_and_the_weld_scan_is_placed_with_it(tmp_path: Path, cell_config) -> None:
    with run_cell(_config(cell_config), tmp_path / "daemon.log", timeout=120) as cell:
        client, cfg, world = cell.client, cell.config, cell.world
        # The simulator's truth, to score only.
        true_bias = SCANNER_MODELS["azure-kinect"].metal_bias if world.scanner.metal_bias is None else world.scanner.metal_bias
        assert (
            world.scanner.model == "azure-kinect" and cfg.calibration.range_bias == "estimate"
        )  # the default for a time-of-flight scanner

        events: list[dict] = []
        _, record = client.submit_and_wait({"kind": "calibrate", "seed": 1}, on_event=events.append, timeout=900)
        assert record["state"] == "succeeded", record["reason"]
        # Each pair's progress event says the bias its finish step measured.
        steps = [e["data"]["range_bias_mm"] for e in events if e.get("stage") == "pair" and "range_bias_mm" in e.get("data", {})]
        assert len(steps) >= 10 and abs(float(np.median(steps)) - true_bias * 1e3) < 0.5, steps

        result = checked_result(client, record)
        calibration = result["calibration"]
        dt, dr = se3.error(np.array(calibration["T_base_cam"]), world.scanner.T_base_cam)
        # The time-of-flight target: 1.5 mm at the camera's origin.
        assert dt <= 1.5e-3 and math.degrees(dr) < 0.2, (dt * 1e3, math.degrees(dr))
        assert calibration["range_bias"] == "estimate"
        assert abs(calibration["range_bias_mm"] - true_bias * 1e3) < 0.3, calibration["range_bias_mm"]
        assert 0.0 < calibration["range_bias_std_mm"] < 0.15
        quality = result["report"]["quality"]
        assert quality["verdict"] == "ok", quality["reasons"]
        assert quality["range_bias_mm"] == pytest.approx(calibration["range_bias_mm"])
        assert quality["range_bias_std_mm"] == pytest.approx(calibration["range_bias_std_mm"])
        assert result["report"]["range_bias"]["source"] == "steps"

        # Accepted as it is (the gate passed), and it is what the cell now holds.
        accepted = client.accept(record["id"])
        check_exported("accept-reply", accepted)
        current = client.calibration()
        check_exported("calibration-reply", {"ok": True, "calibration": current})
        assert current["range_bias_mm"] == calibration["range_bias_mm"]

        # The weld's scan of the steel part, placed with the calibration and its bias.
        # Against the true root line raised to the tip's height, in 3D (the bias reads deep).
        _, d = planned_from_the_scan_pose(client, cfg, world)
        # 8 mm off without the bias (the steel reads that deep); within the Kinect's 1.5 mm with it.
        assert float(np.sqrt(np.mean(d**2))) <= 1.5e-3, rms_mm(d)
