"""What every end-to-end weld is checked for, beyond its torch: the arc as the controller saw it, the job's
stages, its paths and its recording (the scene, the servo's timeline, the arc and the finger's contact)."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import numpy as np

from celld.recording import layout
from celld.recording.readback import read_entities, read_scalars

STAGES = ("scan", "seam", "approach", "tare", "track", "retract")


class ArcWatch:
    """Samples the simulated controller's digital outputs while a job runs: was the arc ever on?"""

    def __init__(self, robot: Any, output: int) -> None:
        self.robot = robot
        self.output = output
        self.seen_on = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            if int(self.robot.status()["digital_out"]) & (1 << self.output):
                self.seen_on = True

    def close(self) -> bool:
        self._stop.set()
        self._thread.join(5)
        return self.seen_on


def check_weld(result: dict[str, Any], events: list[dict[str, Any]], arc_seen: bool) -> dict[str, Any]:
    """Check a succeeded weld's stages, figures, paths and recording; return its paths."""
    stages = [e["stage"] for e in events]
    for stage in STAGES:
        assert stage in stages, stages
    paths = json.loads(Path(result["paths"]).read_text())
    assert len(paths["refined"]) > 100 and len(paths["torch"]) > 100
    assert result["figures"]["tracked_mm"] > 120.0, result["figures"]  # most of the 150 mm seam
    assert arc_seen and result["figures"]["arc_on_s"] > 5.0, result["figures"]

    rrd = Path(result["recording"])
    entities = read_entities(rrd)
    for name in ("planned", "refined", "torch"):
        assert any(e.endswith(name) and e.startswith("/world") for e in entities), (name, entities)
    assert any(e.startswith("/servo") for e in entities), entities
    assert "/srm/camera" in entities and "/srm/camera/tag" in entities, entities
    assert "/world/workpiece" in entities and "/world/robot/arm" in entities and "/world/cell/table" in entities, entities
    assert any(e.startswith("/motion/loop") for e in entities), entities
    # The weld's timeline: the arc on as long as the figures say; while Algorithm 2 tracks, the finger
    # in contact and delta_n held at delta_d (in the finish the tip has left the part, the torch not yet).
    _, arc_rec = read_scalars(rrd, layout.WELD_ARC)
    _, dn = read_scalars(rrd, f"{layout.SERVO_DELTA_N}/delta_n")
    _, dd = read_scalars(rrd, f"{layout.SERVO_DELTA_N}/delta_d")
    _, contact = read_scalars(rrd, layout.WELD_CONTACT)
    _, phase = read_scalars(rrd, layout.SERVO_PHASE)
    burning = arc_rec[:, 0] > 0
    assert abs(burning.sum() * 2e-3 - result["figures"]["arc_on_s"]) < 0.1 * result["figures"]["arc_on_s"]
    tracking = burning & (phase[:, 0] == 1)  # Phase.TRACK
    assert tracking.sum() > 0.5 * burning.sum() and np.all(np.abs(dd[tracking, 0]) > 0)
    assert float(np.median(np.abs(dn[tracking, 0] - dd[tracking, 0]))) < 0.3 * float(np.median(np.abs(dd[tracking, 0])))
    assert float(np.mean(contact[tracking, 0] >= 1)) > 0.95
    return paths
