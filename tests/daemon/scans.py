"""A weld's scan from the scan pose, over the bus, scored against the simulated part's true root line (its results
checked against the exported schemas)."""

from __future__ import annotations

from typing import Any

import numpy as np

from celld import polyline
from celld.sim.cell import sim_part
from tests.daemon.exported import checked_result


def planned_from_the_scan_pose(client: Any, cfg: Any, world: Any) -> tuple[dict[str, Any], np.ndarray]:
    """Move the arm to ``weld.scan_pose``, dry-run a weld there; return its result and the distances (n,) m
    of its planned path from the part's true root line raised to the tip's height (the planned path is the
    seam raised so, :func:`celld.seam.weldpath.weld_geometry`), in 3D."""
    _, moved = client.submit_and_wait({"kind": "move", "target": {"space": "cartesian", "pose": list(cfg.weld.scan_pose)}}, timeout=120)
    assert moved["state"] == "succeeded", moved["reason"]
    checked_result(client, moved)
    _, dry = client.submit_and_wait({"kind": "weld", "dry_run": True}, timeout=300)
    assert dry["state"] == "succeeded", dry["reason"]
    result = checked_result(client, dry)
    assert result is not None and result["dry_run"] is True
    part = sim_part(world)
    assert part is not None
    truth, _ = polyline.resample(part.seam_base + cfg.weld.tip_height * part.T_base_plane[:3, 2], 2e-4)
    return result, polyline.distance(np.array(result["planned_path"]), truth)


def rms_mm(d: np.ndarray) -> tuple[float, float]:
    """RMS and max of distances (m), in mm, for a failure's message."""
    return float(np.sqrt(np.mean(d**2))) * 1e3, float(d.max()) * 1e3
