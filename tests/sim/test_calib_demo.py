"""``celld sim calibrate``: the cell's calibration, offline, in a world of the simulator, scored only at the end."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from celld.sim import calib_demo, cli


def test_the_offline_calibration_solves_in_the_ideal_world_and_saves_a_session_that_solves_again(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers())
    out = tmp_path / "session"
    args = parser.parse_args(["sim", "calibrate", "--poses", "6", "--json", "--out", str(out), "--preset", "ideal", "--world-seed", "1"])
    assert args.func(args) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # Six poses of the cell's box, the scanner's noise only: a tenth of a millimetre or so.
    assert report["error_vs_truth"]["translation_mm"] < 0.3 and report["error_vs_truth"]["rotation_deg"] < 0.05, report
    assert len(report["pairs"]) >= 5 and report["dataset"] == str(out), report
    assert (out / "poses.json").exists() and (out / "verification.cloud.json").exists()
    # The same world, the solve called directly, the truth handed back for scoring only.
    from celld.config import load
    from celld.sim.world import WorldOptions, world_of

    cfg = load(calib_demo.DEFAULT_CONFIG)
    done = calib_demo.calibrate_in_world(cfg, world_of(cfg, WorldOptions(preset="ideal", seed=1)), 6, 0)
    np.testing.assert_allclose(done.result.T_base_cam, done.T_mount_cam_true, atol=5e-4)
