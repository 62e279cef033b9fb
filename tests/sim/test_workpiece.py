"""The simulated part: the finger wall at its true pose."""

from __future__ import annotations

import numpy as np

from celld import se3
from celld.seam.weldpath import in_plane
from celld.seam.workpiece import v_groove_butt
from celld.sim.workpiece import nominal_pose, true_wall


def test_true_wall_runs_beside_the_true_seam_in_its_plane() -> None:
    wp = v_groove_butt()
    T = nominal_pose(wp)
    g = true_wall(wp, T, 0.004, "left")
    seam = se3.apply(T, wp.seam)
    # The torch's line is the seam lifted by the tip height along the part's up axis.
    assert np.allclose(g.seam_base[[0, -1]], seam + 0.004 * T[:3, 2], atol=1e-9)
    W = in_plane(g, g.wall_base)
    S = in_plane(g, g.seam_base)
    # Plane y is left of travel; the left wall lies offset to the left, all along.
    assert np.allclose(W[:, 1] - S[:, 1], g.offset, atol=1e-9)
    assert np.allclose(np.abs((g.wall_base - g.T_base_plane[:3, 3]) @ g.T_base_plane[:3, 2]), 0.0, atol=1e-9)
