"""A weld with its power source, over the bus: the daemon, the simulated cell with a simulated source on the
controller's I/O, real ur-rtde (the source's signals on standard digital and analog I/O).

The cell is ``configs/sim-cell.toml`` on this test's own loopback address in the ideal world, its arc not a
bare digital output but a power source on the control box's I/O (``configs/power-source-io.toml``), welding with the procedure
``e2e-mag-short`` (tests/daemon/procedures/: configs/procedures/steel-1.0mm-mag-short.toml with short times). The world's source fails the weld's first start, loses the
arc after 3 s of arc and sticks the wire at the weld's end (``[sim.power_source]``); the daemon sees only its
signals. The weld re-strikes at the start, stops where the arc went out, backs off and strikes again, fills
the crater, and then holds the arm where it is with the wire stuck: the job fails saying so and how much of
the seam it welded, which the test checks against the simulator's truth. Then a kill -9 of the daemon mid-weld,
the arc burning: the source's outputs go off with the orphaned motion process. About a minute and a half.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from celld.recording import layout
from celld.recording.readback import read_scalars
from celld.sim.cell import run_cell, sim_part
from celld.sim.score import TruthRecorder, arc_truth
from tests.daemon.cells import install_calibration
from tests.daemon.exported import checked_result
from tests.daemon.orphans import after_kill, motion_exits

pytestmark = pytest.mark.cell

WORLD_SEED = 3
CAL_POSES = 8
CAL_SEED = 5
# configs/procedures/steel-1.0mm-mag-short.toml with its times shortened and its travel at 10 mm/s.
PROCEDURE = "e2e-mag-short"
PROCEDURES = Path(__file__).resolve().parent / "procedures"
TRAVEL = 0.010  # m/s, the procedure's
SCRATCH = 0.002  # m, the procedure's re-strike scratch
ARC_START_BIT = 0  # power_source.arc_start in configs/power-source-io.toml: do0


def _config(cell_config) -> Path:
    return cell_config(
        ["sim-cell.toml", "power-source-io.toml"],
        "weld-process-e2e",
        {
            "weld": {"procedure": PROCEDURE, "procedures_dir": str(PROCEDURES)},
            "calibration": {"n_poses": CAL_POSES},
            "sim": {
                "preset": "ideal",
                "seed": WORLD_SEED,
                "scanner": {"resolution_scale": 0.5},
                "power_source": {"fail_first_start": True, "arc_loss_after_s": 3.0, "stuck_every": 1, "stuck_clear_s": [2.0, 2.0]},
            },
        },
    )


def test_a_weld_restrikes_after_a_failed_start_and_an_arc_loss_and_holds_on_a_stuck_wire(
    tmp_path: Path, cell_config, offline_calibration
) -> None:
    cfg_path = _config(cell_config)
    calibration = offline_calibration(cfg_path, CAL_POSES, CAL_SEED)
    with run_cell(cfg_path, tmp_path / "daemon.log", timeout=120) as cell:
        client, cfg, world, robot = cell.client, cell.config, cell.world, cell.robot
        part = sim_part(world)
        install_calibration(cfg.cell.state_dir, calibration)

        # The health check reads the source as the motion loop does: ready, no fault, the wire free.
        _, health = client.submit_and_wait({"kind": "health", "check": "robot"}, timeout=60)
        assert health["state"] == "succeeded", health["reason"]
        source = checked_result(client, health)["power_source"]
        assert source["ready"] and not source["fault"] and not source["wire_stuck"] and not source["arc_stable"], source

        # A procedure the cell does not have is refused before anything moves, naming the ones it has.
        _, refused = client.submit_and_wait({"kind": "weld", "procedure": "no-such-procedure"}, timeout=60)
        assert refused["state"] == "failed" and PROCEDURE in refused["reason"], refused["reason"]

        with TruthRecorder(cfg.robot.host) as truth:
            _, record = client.submit_and_wait({"kind": "weld"}, timeout=400)
        # The seam was welded to its end; then the wire stuck in the crater: the arm held where it was.
        assert record["state"] == "failed" and "wire is stuck" in record["reason"], record["reason"]
        assert f"the arc ({PROCEDURE}@2) welded" in record["reason"], record["reason"]
        report = json.loads((Path(cfg.cell.state_dir) / "jobs" / record["id"] / "arc.json").read_text())
        assert report["ended_in"] == "stuck" and report["procedure"] == f"{PROCEDURE}@2", report
        assert report["failed_starts"] == 1 and report["arc_losses"] == 1 and report["restrikes"] == 2, report

        # Against the truth: the welded stretches and the reported unwelded length make the seam.
        t = arc_truth(world, part, truth.records(), ARC_START_BIT)
        assert abs(t["welded_m"] * 1e3 + report["unwelded_mm"] - t["seam_length_m"] * 1e3) <= 1.0, (t, report)
        # Unwelded only before the point where the finger first touched (the arc lights there, Algorithm 2):
        # the stretch the arc went out in was backed over and welded again.
        assert len(report["unwelded_stretches_mm"]) == 1, report
        a, b = report["unwelded_stretches_mm"][0]
        assert a == 0.0 and b < 8.0, report
        # Three starts: the first that failed, its re-strike, and the re-strike after the loss. The torch waited for
        # the arc at the first (at most one 2 ms cycle of the procedure's travel: 20 um); each re-strike is a
        # scratch start, at most the procedure's 2 mm and the arm's stop along the seam before the arc caught, and
        # the report says no less than the truth.
        starts = t["start_travel_m"]
        assert len(starts) == 3 and starts[0] <= TRAVEL * 0.002, t
        assert 0.0 < max(starts[1:]) <= SCRATCH + 0.001, t
        assert max(starts[1:]) * 1e3 <= report["scratch_max_mm"] + 0.2 and report["scratch_max_mm"] <= SCRATCH * 1e3 + 1.0, (t, report)
        assert t["arc_on_off_seam_samples"] == 0, t
        assert t["stuck_windows"] == 1 and t["stuck_wire_moves"] == 0, t

        # The weld's data in the recording at the loop's rate: the current while the arc burned.
        _, current = read_scalars(Path(cfg.cell.state_dir) / "recordings" / f"{record['id']}.rrd", layout.WELD_CURRENT)
        burning = current[:, 0] > 50.0
        assert burning.sum() > 5 * 500 and 100.0 < float(np.median(current[burning, 0])) < 200.0

        # The operator cuts the wire (the world's 2 s): the arm moves again.
        time.sleep(2.5)
        _, moved = client.submit_and_wait({"kind": "move", "target": {"space": "cartesian", "pose": list(cfg.weld.scan_pose)}}, timeout=120)
        assert moved["state"] == "succeeded", moved["reason"]

        # kill -9 of the daemon mid-weld with the arc burning: the orphaned motion process switches the source's
        # arc start off at once and stops the arm; the gas and every other output of the source go off with it.
        with client.watch_progress() as events:
            killed = client.submit({"kind": "weld", "ref": "killed"})["job"]
            events.wait_stage(killed, "track", timeout=240)
        deadline = time.monotonic() + 90
        burning_since = None
        while burning_since is None or time.monotonic() - burning_since < 0.5:  # past the failed first start
            assert time.monotonic() < deadline, "the arc never burned"
            on = bool(robot.status()["power_source"]["arc_on"])
            burning_since = (burning_since or time.monotonic()) if on else None
            time.sleep(0.02)
        t_kill = time.monotonic_ns()
        cell.daemon.send_signal(signal.SIGKILL)
        cell.daemon.wait(10)
        seen = after_kill(robot, t_kill, arc_output=ARC_START_BIT)
        assert seen.moving_at_kill > 0.002, seen  # welding at the procedure's 10 mm/s
        assert seen.arc_off_s < 0.05 and seen.at_rest_s < 0.5, (seen, motion_exits(tmp_path / "daemon.log"))
        deadline = time.monotonic() + 5
        while int(robot.status()["digital_out"]) & 0b111:  # arc start, gas, robot ready
            assert time.monotonic() < deadline, robot.status()["digital_out"]
            time.sleep(0.05)
        assert not robot.status()["power_source"]["arc_on"]
