"""A weld's figures: offsets towards the finger wall, lateral error against a seam in its plane."""

from __future__ import annotations

import numpy as np

from celld import se3
from celld.seam.figures import lateral_error, lateral_offsets
from celld.seam.weldpath import model_geometry
from celld.seam.workpiece import v_groove_butt


def nominal_pose(wp) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The part on the table at (0.6, 0), its seam along base y."""
    return se3.from_xyz_rpy([0.6, 0.0, -float(wp.vertices[:, 2].min())], [0.0, 0.0, np.pi / 2])


def test_lateral_offsets_are_signed_towards_the_finger_wall() -> None:
    for side in ("left", "right"):
        wp = v_groove_butt()
        g = model_geometry(wp, nominal_pose(wp), 0.004, side)
        # Points 1 mm towards the wall and 2 mm away from it, beside the middle of the seam.
        mid = g.seam_base[len(g.seam_base) // 2]
        n = g.normals[len(g.seam_base) // 2]
        d = lateral_offsets(g, np.array([mid + 0.001 * n, mid - 0.002 * n]), g.seam_base)
        np.testing.assert_allclose(d, [0.001, -0.002], atol=1e-9)


def test_lateral_error_ignores_height_and_points_beyond_the_seam() -> None:
    wp = v_groove_butt()
    g = model_geometry(wp, nominal_pose(wp), 0.004)
    z = g.T_base_plane[:3, 2]
    mid = len(g.seam_base) // 2
    P = np.array(
        [
            g.seam_base[mid] + 0.0003 * g.normals[mid] + 0.01 * z,  # 0.3 mm across, 10 mm up
            g.seam_base[mid + 5] - 0.0004 * g.normals[mid + 5],
            g.seam_base[-1] + 0.02 * g.tangents[-1],
        ]
    )  # beyond the end
    e = lateral_error(P, g.seam_base, g.T_base_plane)
    assert e["points"] == 2 and e["outside"] == 1
    assert abs(e["max_mm"] - 0.4) < 1e-6 and abs(e["rms_mm"] - np.sqrt((0.3**2 + 0.4**2) / 2)) < 1e-6
