"""A weld's figures: offsets towards the finger wall, lateral error against a seam in its plane."""

from __future__ import annotations

import numpy as np

from celld import se3
from celld.seam.figures import height_over_root, lateral_error, lateral_offsets
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


def test_height_over_root_follows_a_root_that_climbs_and_ignores_the_lateral_offset() -> None:
    wp = v_groove_butt()
    g = model_geometry(wp, nominal_pose(wp), 0.004)
    z = g.T_base_plane[:3, 2]
    # The root rises 2 mm from start to end (a part lying tilted): heights are taken over it where each point is.
    ramp = np.linspace(0.0, 0.002, len(g.seam_base))[:, None] * z
    seam = g.seam_base + ramp
    i, j = len(seam) // 4, 3 * len(seam) // 4
    P = np.array(
        [
            seam[i] + 0.004 * z + 0.0005 * g.normals[i],  # 4 mm over the root, 0.5 mm across
            seam[j] + 0.0035 * z,
            seam[-1] + 0.02 * g.tangents[-1] + 0.004 * z,  # beyond the end
        ]
    )
    h = height_over_root(P, seam, g.T_base_plane)
    assert h["points"] == 2
    np.testing.assert_allclose([h["max_mm"], h["min_mm"], h["mean_mm"]], [4.0, 3.5, 3.75], atol=1e-3)


def test_a_touch_finds_the_deformed_tip_where_the_settled_cycles_put_it() -> None:
    import pytest

    from celld.config import ToolConfig
    from celld.errors import CelldError
    from celld.motion.channels import STATE_DTYPE
    from celld.seam.figures import contact_across
    from celld.tactile.tool import ToolGeometry

    tool = ToolGeometry.from_config(ToolConfig(tip_tcp=(0.0, 0.0, 0.2)))
    delta_d = 0.0015
    recs = np.zeros(60, STATE_DTYPE)
    recs["servo_phase"] = 0
    recs["delta_n"] = np.r_[np.full(30, np.nan), np.linspace(0.0002, 0.0008, 10), np.full(20, 0.0014)]
    # The TCP over the tool: the tool's +y is base +y here (tool x along base x, z down).
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.5, 0.0102, 0.4]
    recs["tcp_pose"] = se3.to_ur_pose(T)
    across = np.array([0.0, 1.0, 0.0])
    # A finger on the left (+1): the deformed tip is the undeformed one minus delta_n along +y; only the
    # settled cycles count (|delta_n| within a fifth of delta_d).
    y = contact_across(recs, tool, np.zeros(3), across, 1.0, delta_d)
    assert y == pytest.approx(0.0102 - 0.0014, abs=1e-12)
    # The same cycles seen by a finger on the right: the deformation counts the other way.
    assert contact_across(recs, tool, np.zeros(3), -across, -1.0, delta_d) == pytest.approx(-0.0102 + 0.0014, abs=1e-12)
    recs["delta_n"][40:] = 0.0005  # never settled
    with pytest.raises(CelldError, match="without settling"):
        contact_across(recs, tool, np.zeros(3), across, 1.0, delta_d)


def test_a_touch_s_approach_gives_each_frame_s_tag_deformation_beside_where_the_tip_was_at_its_capture() -> None:
    import pytest

    from celld.config import ToolConfig
    from celld.motion.channels import STATE_DTYPE
    from celld.seam.figures import touch_press
    from celld.tactile.fingermap import fit_finger_gain
    from celld.tactile.tool import ToolGeometry

    tool = ToolGeometry.from_config(ToolConfig(tip_tcp=(0.0, 0.0, 0.2)))
    delta_d, gain, latency = 0.0015, 0.88, 0.012  # the tag moves 0.88 of the tip; frames 12 ms late
    # 1.5 s at 500 Hz: the tip's centre comes onto a wall at y = 10 mm (contact from y = 10 mm on), decelerating
    # as Algorithm 2's touch does, to 1.6 mm into it, then backs off 0.1 mm (the settle).
    t = np.arange(750) * 0.002
    y = 0.0095 + 0.0021 * (1.0 - np.exp(-t / 0.25)) - 0.0001 * np.clip((t - 1.2) / 0.3, 0.0, 1.0)
    frames = np.arange(0.0, 1.5, 1 / 60)  # capture times
    recs = np.zeros(len(t), STATE_DTYPE)
    recs["t_ns"] = (t * 1e9).astype(np.int64)
    recs["servo_phase"] = 0
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # the tool's +y along base +y
    poses = np.repeat(T[None], len(t), axis=0)
    poses[:, 1, 3] = y
    poses[:, 0, 3], poses[:, 2, 3] = 0.5, 0.4 + 0.2  # the tip (0.2 m down the TCP's z) at z = 0.4
    recs["tcp_pose"] = [se3.to_ur_pose(P) for P in poses]
    for k, tk in enumerate(t):
        seen = frames[frames + latency <= tk]  # the newest frame delivered by this cycle
        if len(seen) == 0:
            recs["delta_n"][k], recs["tactile_seq"][k] = np.nan, -1
            continue
        cap = seen[-1]
        y_cap = float(np.interp(cap, t, y))
        tag = gain * max(0.0, y_cap - 0.010)
        recs["tactile_seq"][k], recs["tactile_age_ns"][k] = len(seen), int(round((tk - cap) * 1e9))
        recs["delta_n"][k] = tag + (y[k] - y_cap)  # the law's prediction from the tip's motion since the capture
    press = touch_press(recs, tool, np.zeros(3), np.array([0.0, 1.0, 0.0]), 1.0, delta_d)
    assert len(press.d) >= 10 and press.d.min() >= 0.25 * delta_d and press.d.max() <= 1.15 * delta_d
    # Each kept frame is one of the approach's, before the deepest: the tag's own deformation at its capture.
    np.testing.assert_allclose(press.d, gain * (press.y - 0.010), atol=2e-6)
    assert press.y.max() <= float(y.max()) + 1e-12
    fit = fit_finger_gain([press], delta_d)
    assert fit.finger.gain == pytest.approx(1 / gain, rel=2e-3) and fit.walls[0] == pytest.approx(0.010, abs=2e-6)
