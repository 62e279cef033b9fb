"""The simulated SRM: the finger against the seam wall, and the tag image."""

from __future__ import annotations

import numpy as np
import pytest

from celld.sim.srm import ContactParams, Wall, finger_contact, tag_pose_tool

# A straight wall along +x at y = 0; the free side (the tip's) is y < 0, right
# of the wall's direction.
WALL = Wall(np.array([[0.0, 0.0], [0.1, 0.0]]), free=-1.0)
PARAMS = ContactParams(friction=0.3, k_normal=400.0, k_tangential=400.0, max_deformation=0.005)
R_TIP = 0.001


def test_no_contact_while_the_tip_clears_the_wall() -> None:
    c = finger_contact(np.array([0.05, -0.0012]), np.array([0.01, 0.0]), WALL, R_TIP, PARAMS)
    assert not c.in_contact
    np.testing.assert_array_equal(c.tip_shift_plane, [0.0, 0.0])


def test_tip_is_pushed_back_onto_the_wall_and_dragged_by_friction() -> None:
    # The undeformed tip centre is 1.5 mm into the wall (tip surface 1.5 mm past it).
    c = finger_contact(np.array([0.05, 0.0005]), np.array([0.01, 0.0]), WALL, R_TIP, PARAMS)
    assert c.in_contact and not c.bottomed
    assert c.tip_shift_plane[1] == pytest.approx(-0.0015)
    # Drag = mu * k_n / k_t * normal deflection, against the motion (tanh saturated).
    assert c.tip_shift_plane[0] == pytest.approx(-0.3 * 0.0015, rel=1e-3)
    assert c.force == pytest.approx(400.0 * 0.0015)
    back = finger_contact(np.array([0.05, 0.0005]), np.array([-0.01, 0.0]), WALL, R_TIP, PARAMS)
    assert back.tip_shift_plane[0] == pytest.approx(+0.3 * 0.0015, rel=1e-3)


def test_the_finger_bottoms_out_at_its_maximum_deformation() -> None:
    c = finger_contact(np.array([0.05, 0.007]), np.zeros(2), WALL, R_TIP, PARAMS)
    assert c.bottomed
    assert c.tip_shift_plane[1] == pytest.approx(-0.005)


def test_there_is_no_wall_past_its_ends() -> None:
    c = finger_contact(np.array([0.102, 0.0005]), np.array([0.01, 0.0]), WALL, R_TIP, PARAMS)
    assert not c.in_contact


def test_tag_tilts_like_a_bent_cantilever() -> None:
    T = tag_pose_tool(np.array([0.0, -0.0015, 0.0]), 0.04)
    np.testing.assert_allclose(T[:3, 3], [0.0, -0.0015, 0.0])
    # The tag faces back along the bent finger: its normal leans against the
    # shift by atan(1.5 * shift / length).
    z = T[:3, 2]
    assert np.arctan2(z[1], z[2]) == pytest.approx(1.5 * 0.0015 / 0.04, rel=1e-6)
    assert z[0] == pytest.approx(0.0)


def _tool_pose(y: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # default tool: x along the wall, TCP z down the finger
    T[1, 3] = y
    return T


def test_a_frame_carries_the_contact_truth_in_the_tool_frame() -> None:
    from celld.config import TactileConfig, ToolConfig
    from celld.sim.srm import SimSrm

    # A wall on the tool's left (+y of the plane) along +x; the tip is 0.5 mm into it.
    srm = SimSrm(TactileConfig(), ToolConfig(), Wall(np.array([[-0.05, 0.0], [0.05, 0.0]]), free=-1.0), np.eye(4))
    f = srm.frame(0, _tool_pose(-0.0005), np.array([0.01, 0.0, 0.0]), 0.0)
    assert f.in_contact and not f.bottomed
    # Eq. 15's delta: 0.5 mm towards the wall (normal), friction drag along the motion (tangential).
    np.testing.assert_allclose(f.delta_true, [0.3 * 0.0005, 0.0005, 0.0], atol=1e-9)
    assert f.image.shape == (480, 640) and f.image.dtype == np.uint8
    free = srm.frame(0, _tool_pose(-0.003), np.zeros(3), 0.0)
    assert not free.in_contact
    np.testing.assert_array_equal(free.delta_true, 0.0)


def test_the_simulated_camera_keeps_its_frame_rate_and_skips_frames_it_missed() -> None:
    from celld.config import TactileConfig, ToolConfig
    from celld.sim.srm import SimSrm, SimSrmCamera

    now = [0]
    srm = SimSrm(TactileConfig(), ToolConfig(), Wall(np.array([[-0.05, 0.0], [0.05, 0.0]]), free=-1.0), np.eye(4))
    cam = SimSrmCamera(
        srm, lambda t: (_tool_pose(-0.003), np.zeros(6)), lambda: now[0], lambda s: now.__setitem__(0, now[0] + int(s * 1e9))
    )
    cam.open()
    stamps = [cam.read()[0] for _ in range(3)]
    period = int(round(1e9 / 60.0))
    assert np.diff(stamps).tolist() == [period, period]
    # Delivered after the configured latency.
    assert now[0] == stamps[-1] + int(srm.params.latency * 1e9)
    now[0] += 5 * period  # the reader fell behind by five frames
    late = cam.read()[0]
    assert late > stamps[-1] + 4 * period and (late - stamps[0]) % period == 0
    cam.unplug()
    assert cam.read() is None


def test_a_default_finger_is_the_stateless_contact() -> None:
    from celld.sim.srm import Finger

    finger = Finger(PARAMS)
    for y in (0.0005, 0.0008, -0.002):
        c, tag = finger.touch(np.array([0.05, y]), np.array([0.01, 0.0]), WALL, R_TIP)
        ref = finger_contact(np.array([0.05, y]), np.array([0.01, 0.0]), WALL, R_TIP, PARAMS)
        np.testing.assert_array_equal(c.tip_shift_plane, ref.tip_shift_plane)
        np.testing.assert_array_equal(tag, ref.tip_shift_plane)


def test_the_finger_stiffens_as_it_bends() -> None:
    from dataclasses import replace

    stiff = replace(PARAMS, stiffening=0.0015)
    assert stiff.force(0.0015) == pytest.approx(2.0 * PARAMS.force(0.0015))
    c = finger_contact(np.array([0.05, 0.0005]), np.array([0.01, 0.0]), WALL, R_TIP, stiff)
    # The same normal deflection, twice the force, twice the friction drag.
    assert c.tip_shift_plane[1] == pytest.approx(-0.0015)
    assert c.tip_shift_plane[0] == pytest.approx(-2 * 0.3 * 0.0015, rel=1e-3)


def test_the_tip_sticks_and_slips_along_the_wall() -> None:
    from dataclasses import replace

    from celld.sim.srm import Finger

    finger = Finger(replace(PARAMS, static_friction_ratio=1.5))
    kinetic = 0.3 * 0.0015
    drags = []
    for k in range(60):  # the base slides 0.1 mm per frame, 1.5 mm into the wall
        c, _ = finger.touch(np.array([0.02 + 1e-4 * k, 0.0005]), np.array([0.01, 0.0]), WALL, R_TIP)
        drags.append(-c.tip_shift_plane[0])
        assert c.tip_shift_plane[1] == pytest.approx(-0.0015)
    drags = np.array(drags[1:])
    # A saw tooth between the kinetic drag and the static limit.
    assert drags.min() == pytest.approx(kinetic, rel=1e-6) and kinetic * 1.4 < drags.max() <= kinetic * 1.5 + 1e-12
    assert np.sum(np.diff(drags) < 0) >= 10  # it slipped many times
    c, _ = finger.touch(np.array([0.05, -0.003]), np.zeros(2), WALL, R_TIP)  # off the wall: the drag is gone
    assert not c.in_contact and finger.touch(np.array([0.05, 0.0005]), np.zeros(2), WALL, R_TIP)[0].tip_shift_plane[0] == 0.0


def test_the_tag_follows_the_tip_through_a_play() -> None:
    from dataclasses import replace

    from celld.sim.srm import Finger

    finger = Finger(replace(PARAMS, hysteresis=0.00006))
    _, tag = finger.touch(np.array([0.05, 0.0005]), np.zeros(2), WALL, R_TIP)  # pressed 1.5 mm
    assert tag[1] == pytest.approx(-0.0015 + 0.00003)  # lags by half the play
    c, tag = finger.touch(np.array([0.05, -0.003]), np.zeros(2), WALL, R_TIP)  # released
    assert not c.in_contact and tag[1] == pytest.approx(-0.00003)  # does not quite come back


def test_the_camera_stamps_are_off_the_exposure_and_frames_arrive_late() -> None:
    from dataclasses import replace

    from celld.config import TactileConfig, ToolConfig
    from celld.sim.srm import SimSrm, SimSrmCamera, SrmSimParams

    now = [0]
    params = replace(SrmSimParams(), stamp_sigma=0.0005, delivery_jitter=0.004)
    srm = SimSrm(TactileConfig(), ToolConfig(), Wall(np.array([[-0.05, 0.0], [0.05, 0.0]]), free=-1.0), np.eye(4), params)
    asked: list[int] = []

    def pose_at(t: int):
        asked.append(t)
        return _tool_pose(-0.003), np.zeros(6)

    cam = SimSrmCamera(srm, pose_at, lambda: now[0], lambda s: now.__setitem__(0, now[0] + int(s * 1e9)))
    cam.open()
    late = []
    for _ in range(50):
        stamp, _ = cam.read()
        late.append(now[0] - stamp)
    off = np.array(asked) - (np.arange(50) * int(round(1e9 / 60.0)))
    assert 0.0002 < np.std(off) * 1e-9 < 0.001
    assert min(late) >= 2_000_000 and max(late) > 4_000_000 and max(late) <= 6_000_000


def test_a_tip_moved_across_the_joint_meets_its_other_wall() -> None:
    from celld.config import TactileConfig, ToolConfig
    from celld.sim.srm import SimSrm, WallSurface

    # The finger wall at y = 0 (on the tool's left), the joint's other wall 6 mm across at y = -6 mm.
    finger = Wall(np.array([[-0.05, 0.0], [0.05, 0.0]]), free=-1.0)
    line = np.array([[-0.05, -0.006], [0.05, -0.006]])
    far = WallSurface(np.stack([line, line]), np.array([0.0, 0.01]), np.zeros(2), free=1.0)
    srm = SimSrm(TactileConfig(), ToolConfig(), finger, np.eye(4), far_wall=far)
    pressed = srm.frame(0, _tool_pose(-0.0005), np.zeros(3), 0.0)  # 0.5 mm into the finger wall
    assert pressed.in_contact and pressed.delta_true[1] == pytest.approx(0.0005)
    between = srm.frame(0, _tool_pose(-0.003), np.zeros(3), 0.0)
    assert not between.in_contact
    across = srm.frame(0, _tool_pose(-0.0058), np.zeros(3), 0.0)  # the tip's surface 0.8 mm past the far wall
    assert across.in_contact and across.delta_true[1] == pytest.approx(-0.0008)
    # Without the other wall the tip passes through where it stands.
    alone = SimSrm(TactileConfig(), ToolConfig(), finger, np.eye(4)).frame(0, _tool_pose(-0.0058), np.zeros(3), 0.0)
    assert not alone.in_contact


def _reader(camera):  # type: ignore[no-untyped-def]
    """``read(shift_tool) -> tag centre (3,) in the camera frame`` as the controller's detector finds it (told
    [tactile]'s defaults), through the simulated SRM with ``camera``, noise-free."""
    from celld.config import TactileConfig, ToolConfig
    from celld.sim.srm import Imaging, SimSrm, SrmSimParams
    from celld.tactile.aruco import TagDetector

    cfg = TactileConfig()
    srm = SimSrm(cfg, ToolConfig(), WALL, np.eye(4), SrmSimParams(seed=5), camera=camera)
    detector = TagDetector.from_config(cfg)
    return lambda shift: detector.detect(srm.image(np.asarray(shift, dtype=np.float64), Imaging(noise=0.0))).p_cam


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_the_worlds_srm_camera_is_its_own_and_the_estimator_reads_it_through_what_it_was_told(seed: int) -> None:
    from celld.config import ToolConfig
    from celld.se3 import invert
    from celld.sim.world import PRESETS, NominalCell, draw_world
    from celld.tactile.deformation import deformation_tool, tare

    drawn = draw_world(NominalCell(), PRESETS["ideal"], seed).srm
    assert drawn.tag_size == 0.008 and drawn.intrinsics_px == (600.0, 600.0, 320.0, 240.0)
    built = draw_world(NominalCell(), PRESETS["ideal"].with_sources(on=["srm_camera"]), seed).srm
    assert built.tag_size != drawn.tag_size and built.intrinsics_px != drawn.intrinsics_px and built.T_tool_cam != drawn.T_tool_cam

    # The finger at rest: the tag at the tool frame's origin, seen by the camera as built and read with the drawn
    # intrinsics and tag size. A pinhole camera predicts the reading: each coordinate scaled by the told over
    # the printed size, the depth by the told over the true focal length, and the principal point's error as a
    # lateral shift in proportion to the depth.
    fx_told, _, cx_told, cy_told = drawn.intrinsics_px
    fx, _, cx, cy = built.intrinsics_px
    x, y, z = invert(np.asarray(built.T_tool_cam))[:3, 3]
    k = drawn.tag_size / built.tag_size
    predicted = k * np.array([x + (cx - cx_told) * z / fx, y + (cy - cy_told) * z / fx, z * fx_told / fx])
    read_drawn, read_built = _reader(drawn), _reader(built)
    at_rest = read_built(np.zeros(3))
    told = invert(np.asarray(drawn.T_tool_cam))[:3, 3]
    assert np.linalg.norm(read_drawn(np.zeros(3)) - told) < 20e-6  # the camera as drawn reads where it was told
    assert np.linalg.norm(at_rest - told) > 200e-6, at_rest
    assert np.linalg.norm(at_rest - predicted) < 40e-6, (at_rest, predicted)

    # A 1 mm shift across the seam (n_d) after a tare: read through the built camera's turn, scale and depth, the
    # deformation differs from the drawn camera's reading by a few hundredths of a millimetre at these sizes.
    R_tool_cam = ToolConfig().R_tool_cam()
    shift = np.array([0.0, 1.0e-3, 0.0])

    def deformation(read) -> np.ndarray:  # type: ignore[no-untyped-def]
        return deformation_tool(read(shift), tare(np.array([read(np.zeros(3))]), max_spread=1e-3), R_tool_cam)

    ideal, seen = deformation(read_drawn), deformation(read_built)
    assert np.linalg.norm(ideal + shift) < 20e-6, ideal
    assert 5e-6 < np.linalg.norm(seen - ideal) < 100e-6, (seen, ideal)


def test_the_tag_inside_the_finger_shows_less_than_the_tip_and_the_camera_reads_what_the_tag_shows() -> None:
    from celld.config import TactileConfig, ToolConfig
    from celld.sim.srm import Imaging, SimSrm, SrmSimParams, tag_of_tip
    from celld.tactile.aruco import TagDetector
    from celld.tactile.deformation import deformation_tool, tare

    wall = Wall(np.array([[-0.05, 0.0], [0.05, 0.0]]), free=-1.0)
    cfg, tool = TactileConfig(), ToolConfig()
    detector = TagDetector.from_config(cfg)

    def seen(params: ContactParams) -> tuple[np.ndarray, np.ndarray]:
        """The tip's deflection 1 mm into the wall and the deformation the controller reads from the image of it."""
        srm = SimSrm(cfg, tool, wall, np.eye(4), SrmSimParams(contact=params, seed=3))
        rest = detector.detect(srm.image(np.zeros(3), Imaging(noise=0.0))).p_cam
        _, tip, tag = srm.contact(_tool_pose(0.0), np.zeros(3))  # the tip's centre on the wall: its radius, 1 mm, into it
        read = deformation_tool(detector.detect(srm.image(tag, Imaging(noise=0.0))).p_cam, tare(np.array([rest]), 1e-3), tool.R_tool_cam())
        return -tip, read  # both as Eq. 15's delta

    truth, read = seen(ContactParams())
    assert truth[1] == pytest.approx(0.001) and read[1] == pytest.approx(truth[1], abs=10e-6)
    inside = ContactParams(tag_gain=(0.95, 0.9), tag_softening=8e-3)
    truth, read = seen(inside)
    # The tip is where it was, the tag (and so Eq. 15's reading) 0.9 (1 - (1/8)^2) of it: 0.114 mm short.
    assert truth[1] == pytest.approx(0.001)
    assert read[1] == pytest.approx(0.9 * (1 - (1 / 8) ** 2) * truth[1], abs=10e-6)
    np.testing.assert_allclose(tag_of_tip(np.array([1e-3, 0.0, 2e-4]), inside), [0.95 * (1 - (1 / 8) ** 2) * 1e-3, 0.0, 2e-4])


def test_the_tip_for_a_tag_s_deformation_is_the_inverse_of_the_tag_for_the_tip() -> None:
    from celld.sim.srm import tag_of_tip, tip_of_tag

    params = ContactParams(tag_gain=(0.95, 0.87), tag_softening=6.4e-3)
    for tip in (0.2e-3, 1.0e-3, 1.8e-3):
        tag = tag_of_tip(np.array([0.0, tip, 0.0]), params)[1]
        assert tip_of_tag(tag, 0.87, 6.4e-3) == pytest.approx(tip, rel=1e-9)
