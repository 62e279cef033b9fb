"""The simulator's world: drawn deterministically, ideal means no error, each switch its own error, sizes within the budget."""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from celld import se3
from celld.calib.flange import preset
from celld.config import parse
from celld.errors import ConfigError, InputError
from celld.robot import kinematics as kin
from celld.sim.robot.truearm import ArmTruth, TrueArm
from celld.sim.world import (
    PRESETS,
    SOURCES,
    TRUNCATE,
    ErrorBudget,
    NominalCell,
    PartShape,
    WorldOptions,
    add_world_arguments,
    draw_world,
    options_from_args,
    world_from_table,
    world_of,
)

TABLE: dict[str, Any] = {
    "preset": "realistic",
    "seed": 4,
    "tool": {"tip_tcp_mm": [0.0, 0.0, 200.0]},
    "part": {"workpiece": "v-groove", "bow_mm": 1.0},
}
# With a second robot across the table, so that its own draws (base, arm, flange) are checked too.
NOMINAL = NominalCell(
    tool=world_from_table(TABLE).nominal.tool, workpiece="v-groove", robot2="ur10e", robot2_pose=(1.25, 0.0, 0.0, 0.0, 0.0, math.pi)
)
REALISTIC = PRESETS["realistic"]


def _components(w: Any) -> dict[str, str]:
    """Each error source's part of a world, as comparable text."""

    def t(*values: Any) -> str:
        return repr([np.asarray(v).round(15).tolist() if isinstance(v, np.ndarray) else v for v in values])

    f, sc, a, p, r2 = w.flange, w.scanner, w.arm, w.part, w.robot2
    # A world without a second robot compares as one with its first robot's arm and flange twice.
    a2, f2, k2 = (a, f, w.nominal_dh) if r2 is None else (r2.arm, r2.flange, r2.nominal_dh)

    def beyond(arm: Any, table: kin.DH) -> Any:
        """The true arm's table and joint zeros beyond its controller's."""
        return np.subtract(arm.dh[:3], table[:3]), np.subtract(arm.joint_offsets, table.theta)

    return {
        "factory_calibration": t(w.kinematics, None if r2 is None else r2.kinematics),
        "kinematics": t(*beyond(a, w.nominal_dh), *beyond(a2, k2)),
        "repeatability": t(a.repeatability, a2.repeatability),
        "encoder_noise": t(a.encoder_noise, a2.encoder_noise),
        "robot2_placement": t(None if r2 is None else r2.T_base1_base2),
        "settle": t(a.settle_amplitude, a2.settle_amplitude),
        "capture_delay": t(sc.capture_delay),
        "camera_jitter": t(w.camera.stamp_sigma, w.camera.delivery_jitter),
        "scanner_mount": t(sc.T_base_cam),
        "depth_scale": t(sc.depth_scale),
        "distortion": t(sc.field),
        "metal_bias": t(sc.metal_bias),
        "flange_tolerance": t(*(g.outer_diameter for g in (f, f2)), *(g.bore_diameter for g in (f, f2)), f.pitch_diameter, f2.thickness),
        "flange_variant": t(f.chamfer, f2.chamfer, f.bore_depth, f2.hole_depth, f.dowel_depth),
        "tool_offsets": t(w.tool.config, w.tool.p_flange_torch),
        "finger": t(w.finger.stiffening, w.finger.hysteresis, w.finger.static_friction_ratio),
        "tag_map": t(w.finger.tag_gain, w.finger.tag_softening),
        "srm_camera": t(w.srm),
        "part_placement": t(p.offset_xy, p.yaw),
        "part_shape": t(p.shape),
        # The joints' stiffness is drawn when either load is on, and belongs to neither alone.
        "compliance": t(a.link_mass, a.payload_mass, a.payload_com, a2.link_mass),
        "hose_pull": t(a.hose_force, a.hose_point, a2.hose_force),
        "thermal": t(a.warm_rise, a2.warm_rise),
        "lost_motion": t(a.lost_motion, a2.lost_motion),
    }


def test_a_world_is_a_function_of_its_seed() -> None:
    a, b = draw_world(NOMINAL, REALISTIC, 7), draw_world(NOMINAL, REALISTIC, 7)
    assert _components(a) == _components(b)
    c = draw_world(NOMINAL, REALISTIC, 8)
    assert all(
        _components(a)[s] != _components(c)[s] for s in ("kinematics", "scanner_mount", "tool_offsets", "part_shape", "robot2_placement")
    )
    # From the config's table too, and the command line's seed wins over the table's.
    assert _components(world_from_table(TABLE)) == _components(world_from_table({**TABLE, "seed": 9}, options=WorldOptions(seed=4)))


def test_the_ideal_world_is_its_drawing() -> None:
    w = draw_world(replace(NOMINAL, part_bow=0.001), PRESETS["ideal"], 3)
    assert w.arm.is_model(kin.UR10E) and w.arm.joint_offsets == (0.0,) * 6
    np.testing.assert_array_equal(w.scanner.T_base_cam, np.array(NOMINAL.T_base_cam))
    assert w.scanner.ideal and w.scanner.metal_bias is None and w.scanner.capture_delay == (0.0, 0.0)
    assert w.flange == preset("ur10e")
    assert w.robot2 is not None and w.robot2.arm.is_model(kin.UR10E) and w.robot2.flange == preset("ur10e")
    np.testing.assert_array_equal(w.robot2.T_base1_base2, w.robot2.T_base1_base2_drawn)
    assert w.tool.config == NOMINAL.tool
    np.testing.assert_allclose(w.tool.p_flange_torch, [-0.03, 0.0, 0.2])
    assert w.finger.hysteresis == 0.0 and w.finger.static_friction_ratio == 1.0 and math.isinf(w.finger.stiffening)
    assert w.finger.tag_gain == (1.0, 1.0) and math.isinf(w.finger.tag_softening)
    assert w.camera.stamp_sigma == 0.0 and w.camera.delivery_jitter == 0.0
    assert w.srm == replace(NOMINAL.srm, T_tool_cam=NOMINAL.tool.T_tool_cam)
    assert w.part is not None and w.part.offset_xy == (0.0, 0.0) and w.part.yaw == 0.0
    assert w.part.shape == PartShape(bow=0.001)
    # The arm in the ideal world is the controller's model: the true pose is the reported one.
    arm = TrueArm(w.arm)
    q = [2.8, -1.4, 2.3, -2.5, 1.57, -1.3]
    arm.update(q, [0.0] * 6, 1.0)
    assert arm.q == q and arm.q_reported == q and arm.T_flange == kin.forward_rows(q)


@pytest.mark.parametrize("source", SOURCES)
def test_each_switch_toggles_only_its_own_error(source: str) -> None:
    nominal = replace(NOMINAL, scanner="azure-kinect") if source == "metal_bias" else NOMINAL
    on, off = draw_world(nominal, REALISTIC, 11), draw_world(nominal, REALISTIC.with_sources(off=[source]), 11)
    a, b = _components(on), _components(off)
    assert [k for k in a if a[k] != b[k]] == [source]
    # ... and from the ideal world, switching it on alone changes only it.
    ideal = PRESETS["ideal"]
    a, b = _components(draw_world(nominal, ideal.with_sources(on=[source]), 11)), _components(draw_world(nominal, ideal, 11))
    assert [k for k in a if a[k] != b[k]] == [source]


def _workspace_q() -> list[np.ndarray]:
    """Joints of flange poses over the table and up in the calibration box, near the simulated cell's home."""
    home = np.array([2.847, -1.401, 2.311, -2.481, 1.571, -1.276])
    out = []
    for x in (0.45, 0.6, 0.75):
        for y in (-0.15, 0.0, 0.15):
            for z, rpy in ((0.2, (math.pi, 0.0, math.pi / 2)), (0.45, (0.0, 0.0, 0.0)), (0.6, (0.2, -0.2, 0.0))):
                q = kin.inverse(se3.from_xyz_rpy([x, y, z], rpy), home)
                assert q is not None
                out.append(q)
    return out


def test_the_realistic_arm_is_off_by_a_ur_e_series_class_absolute_error() -> None:
    qs = _workspace_q()
    means, maxes = [], []
    for seed in range(20):
        w = draw_world(NOMINAL, REALISTIC, seed)
        k = w.nominal_dh  # the controller's table: its factory calibration's
        d_dh = np.abs(np.concatenate([np.subtract(w.arm.dh.d, k.d), np.subtract(w.arm.dh.a, k.a)]))
        assert d_dh.max() <= TRUNCATE * REALISTIC.dh_length + 1e-12
        assert np.abs(np.subtract(w.arm.dh.alpha, k.alpha)).max() <= TRUNCATE * REALISTIC.dh_twist + 1e-12
        assert np.abs(np.subtract(w.arm.joint_offsets, k.theta)).max() <= TRUNCATE * REALISTIC.joint_offset + 1e-12
        e = [np.linalg.norm(kin.forward(q + w.arm.joint_offsets, w.arm.dh)[:3, 3] - kin.forward(q, k)[:3, 3]) for q in qs]
        means.append(np.mean(e))
        maxes.append(np.max(e))
    # "About 0.3-1 mm across the workspace" beyond the controller's own table: each arm's mean in it, and no
    # point far beyond.
    assert 0.3e-3 <= np.mean(means) <= 1.0e-3, np.mean(means)
    assert min(means) >= 0.1e-3 and max(maxes) <= 2.0e-3, (min(means), max(maxes))


def test_the_realistic_controller_computes_with_its_factory_calibration() -> None:
    qs = _workspace_q()
    means = []
    for seed in range(20):
        w = draw_world(NOMINAL, REALISTIC, seed)
        k = w.nominal_dh
        assert k != kin.UR10E and w.robot2 is not None and w.robot2.nominal_dh not in (kin.UR10E, k)
        assert np.abs(k.theta).max() <= TRUNCATE * REALISTIC.factory_joint_zero + 1e-12
        # The published table puts the flange millimetres from where the controller does.
        means.append(np.mean([np.linalg.norm(kin.forward(q, k)[:3, 3] - kin.forward(q)[:3, 3]) for q in qs]))
    assert 2e-3 <= np.mean(means) <= 10e-3 and max(means) <= 20e-3, (np.mean(means), max(means))
    assert draw_world(NOMINAL, REALISTIC.with_sources(off=["factory_calibration"]), 3).nominal_dh == kin.UR10E


def _weld_q() -> list[np.ndarray]:
    """Joints of flange-down poses over the table (a 300 x 300 x 150 mm box around the part), near home."""
    q = np.array([2.847, -1.401, 2.311, -2.481, 1.571, -1.276])
    out = []
    for x in (0.45, 0.6, 0.75):
        for y in (-0.15, 0.0, 0.15):
            for z in (0.15, 0.3):
                q = kin.inverse(se3.from_xyz_rpy([x, y, z], [math.pi, 0.0, math.pi / 2]), q)
                assert q is not None
                out.append(q)
    return out


def test_the_realistic_arm_sags_warms_and_lags_by_its_anchored_sizes() -> None:
    qs = _weld_q()
    for seed in range(5):
        a = draw_world(NOMINAL, REALISTIC, seed).arm
        rigid = replace(a, compliance=(0.0,) * 6)
        sag = [np.linalg.norm(a.flange(q)[:3, 3] - rigid.flange(q)[:3, 3]) for q in qs]
        # The sag under gravity and the hose at weld poses: the 0.2-0.7 mm, give or take the draw.
        assert 0.15e-3 <= np.mean(sag) and max(sag) <= 0.8e-3, (seed, np.mean(sag), max(sag))
        warm = [np.linalg.norm(a.flange(q, rise=a.warm_rise)[:3, 3] - a.flange(q)[:3, 3]) for q in qs]
        assert 0.05e-3 <= np.mean(warm) <= 0.3e-3, (seed, np.mean(warm))
        assert a.temperature_rise(0.0) == 0.0 and a.temperature_rise(1e9) == pytest.approx(a.warm_rise)
        assert a.temperature_rise(a.warmup_tau) == pytest.approx(a.warm_rise * (1.0 - math.exp(-1.0)))
        # Lost motion: coming from one side or the other puts the flange apart by some hundredths of a mm.
        lag = [np.linalg.norm(a.flange(q, np.ones(6))[:3, 3] - a.flange(q, -np.ones(6))[:3, 3]) for q in qs]
        assert 0.003e-3 <= np.mean(lag) <= 0.06e-3, (seed, np.mean(lag))
        assert np.linalg.norm(a.hose_force) >= REALISTIC.hose_force[0] - 1e-9 and a.hose_force[2] < 0.0


def test_the_simulated_controller_puts_the_flange_where_the_static_truth_says() -> None:
    a = replace(draw_world(NOMINAL, REALISTIC, 4).arm, repeatability=0.0, settle_amplitude=0.0, encoder_noise=0.0)
    arm = TrueArm(a)
    q0, q1 = _weld_q()[0], _weld_q()[5]
    t = 0.0
    for s in np.linspace(0.0, 1.0, 50):  # a move from q0 to q1, then at rest
        arm.update((q0 + s * (q1 - q0)).tolist(), (q1 - q0).tolist(), t)
        t += 0.002
    for _ in range(20):
        arm.update(q1.tolist(), [0.0] * 6, t)
        t += 0.002
    T = kin.matrix_from_rows(arm.T_flange)
    np.testing.assert_allclose(T, a.flange(q1, q1 - q0, a.temperature_rise(t - 0.002)), atol=1e-9)
    # Coming the other way rests elsewhere by the lost motion.
    assert np.linalg.norm(T[:3, 3] - a.flange(q1, q0 - q1)[:3, 3]) > 1e-6


def test_the_arm_rests_within_its_repeatability_and_settles() -> None:
    w = draw_world(NOMINAL, REALISTIC, 2)
    arm = TrueArm(w.arm)
    q = list(_workspace_q()[4])
    rests, t = [], 0.0
    for _ in range(200):
        arm.update(q, [0.1] * 6, t)  # moving
        t += 0.5
        arm.update(q, [0.0] * 6, t)  # stopped: a new rest error, ringing down
        first = np.array(arm.T_flange[3::4])
        t += 2.0
        arm.update(q, [0.0] * 6, t)  # 2 s later: settled
        rests.append(np.array(arm.T_flange[3::4]))
    rests = np.array(rests)
    d = np.linalg.norm(rests - rests.mean(axis=0), axis=1)
    rp = d.mean() + 3.0 * d.std()  # ISO 9283 pose repeatability
    assert 0.02e-3 <= rp <= 0.06e-3, rp  # the UR10e datasheet's +-0.05 mm
    assert np.linalg.norm(first - rests[-1]) < 0.5e-3
    # The reported joints carry the encoder noise; the arm does not move with it.
    assert arm.q_reported != q and np.max(np.abs(np.subtract(arm.q_reported, q))) < TRUNCATE * 3 * REALISTIC.encoder_noise


def test_the_scanner_tool_flange_and_part_errors_are_sized_as_budgeted() -> None:
    b = REALISTIC
    for seed in range(30):
        w = draw_world(NOMINAL, b, seed)
        dt, dr = se3.error(w.scanner.T_base_cam, np.array(NOMINAL.T_base_cam))
        assert dt <= TRUNCATE * b.mount_translation * math.sqrt(3) and dr <= TRUNCATE * b.mount_rotation * math.sqrt(3)
        assert abs(w.scanner.depth_scale) <= TRUNCATE * b.depth_scale
        f, f0 = w.flange, preset("ur10e")
        assert f0.outer_diameter - 46e-6 <= f.outer_diameter <= f0.outer_diameter  # h8
        assert f0.bore_diameter <= f.bore_diameter <= f0.bore_diameter + 25e-6  # H7
        assert b.chamfer[0] <= f.chamfer <= b.chamfer[1] and abs(f.bore_depth - f0.bore_depth) <= b.bore_depth
        assert f.circle_radius == pytest.approx(f.outer_diameter / 2 - f.chamfer)
        tip = np.subtract(w.tool.config.tip_tcp, NOMINAL.tool.tip_tcp)
        assert np.abs(tip).max() <= 1.5e-3 + 1e-12 and np.abs(w.tool.p_flange_torch - w.tool.p_flange_torch_nominal).max() <= 1.5e-3 + 1e-12
        turn = math.degrees(math.acos(np.clip(np.dot(w.tool.config.tool_z_tcp, NOMINAL.tool.tool_z_tcp), -1, 1)))
        assert turn <= 1.75  # cut at 1 degree per axis
        assert b.hysteresis[0] <= w.finger.hysteresis <= b.hysteresis[1]
        # The tag at 90-100 % of the finger's bending length moves 0.85-1.0 of the tip, each axis 2 % apart at 1 sigma.
        assert all(0.8505 * (1 - TRUNCATE * b.tag_anisotropy) <= g <= 1 + TRUNCATE * b.tag_anisotropy for g in w.finger.tag_gain)
        assert b.tag_softening[0] <= w.finger.tag_softening <= b.tag_softening[1]
        p = w.part
        assert np.abs(p.offset_xy).max() <= TRUNCATE * b.placement_offset and abs(p.yaw) <= TRUNCATE * b.placement_yaw
        assert b.bow[0] <= abs(p.shape.bow) <= b.bow[1]  # NOMINAL's part has no bow of its own
        assert abs(p.shape.twist) <= b.twist and b.gap_variation[0] <= p.shape.gap_amplitude <= b.gap_variation[1]
    # The distortion field's RMS over the measuring volume is the budget's (PhoXi M class).
    fld = draw_world(NOMINAL, b, 0).scanner.field
    g = np.linspace(-1, 1, 9)
    U, V, Wz = (a.ravel() for a in np.meshgrid(g, g, g, indexing="ij"))
    z = fld.z_mid + fld.z_half * Wz
    P = np.column_stack([U * fld.u_half * z, V * fld.v_half * z, z])
    rms = np.sqrt(np.mean(np.sum(fld.displacement(P) ** 2, axis=1)))
    assert rms == pytest.approx(b.distortion, rel=0.1)


def test_the_sim_table_is_read_and_checked_by_the_simulator() -> None:
    cfg = parse({"sim": TABLE})
    assert dict(cfg.sim)["preset"] == "realistic"  # production keeps it raw
    w = world_of(cfg)
    assert w.preset == "realistic" and w.seed == 4 and w.budget == REALISTIC
    off = world_of(parse({"sim": {**TABLE, "errors": {"tool_offsets": False, "bow_mm": [0.1, 0.2]}}}))
    assert not off.budget.on("tool_offsets") and off.budget.bow == (0.0001, 0.0002) and off.preset == "realistic (changed)"
    assert world_of(parse({})).preset == "ideal" and world_of(parse({})).part is None
    for table, key in (
        ({**TABLE, "colour": "red"}, "sim.colour"),
        ({**TABLE, "preset": "perfect"}, "sim.preset"),
        ({**TABLE, "errors": {"tool_offset": True}}, "sim.errors.tool_offset"),
        ({**TABLE, "errors": {"tip_offset_mm": -1.0}}, "sim.errors.tip_offset_mm"),
        ({**TABLE, "part": {"workpiece": "fillet-t", "bow_mm": 1.0}}, "sim.part.bow_mm"),
        ({**TABLE, "scanner": {"model": "kinect"}}, "sim.scanner.model"),
        ({**TABLE, "scanner": {"mount": "link1"}}, "sim.scanner.T_link_cam"),
        ({**TABLE, "scanner": {"T_link_cam": np.eye(4).tolist()}}, "sim.scanner.T_link_cam"),
        ({**TABLE, "scanner": {"mount": "elbow"}}, "sim.scanner.mount"),
        ({**TABLE, "scanner": {"roi_px": [0, 100, 0]}}, "sim.scanner.roi_px"),
        ({**TABLE, "scanner": {"roi_px": [0, 100.5, 0, 100]}}, "sim.scanner.roi_px"),
        ({**TABLE, "scanner": {"roi_px": [100, 100, 0, 100]}}, "sim.scanner.roi_px"),
        # Pixels of the image at its resolution_scale: the PhoXi M's 1544 rows are 772 at half.
        ({**TABLE, "scanner": {"resolution_scale": 0.5, "roi_px": [0, 800, 0, 100]}}, "sim.scanner.roi_px"),
        ({**TABLE, "srm": {"intrinsics_px": [600.0, 600.0, 700.0, 240.0]}}, "sim.srm.intrinsics_px"),
        ({**TABLE, "srm": {"intrinsics_px": [0.0, 600.0, 320.0, 240.0]}}, "sim.srm.intrinsics_px"),
        ({**TABLE, "srm": {"tag_size_mm": 0.1}}, "sim.srm.tag_size_mm"),
        ({**TABLE, "srm": {"lens": "wide"}}, "sim.srm.lens"),
        ({**TABLE, "errors": {"tag_print": 0.5}}, "sim.errors.tag_print"),
    ):
        with pytest.raises(ConfigError) as exc:
            world_of(parse({"sim": table}))
        assert exc.value.key == key, (exc.value.key, key)


def test_the_scanners_region_of_interest_is_read_in_pixels_of_its_scaled_image() -> None:
    w = world_of(parse({"sim": {**TABLE, "scanner": {"resolution_scale": 0.5, "roi_px": [100, 772, 0, 1032]}}}))
    assert w.scanner.roi_px == (100, 772, 0, 1032) and w.scanner.resolution_scale == 0.5
    assert world_of(parse({"sim": TABLE})).scanner.roi_px is None
    # A capture setting, not an error: the world drawn is the same.
    same = world_of(parse({"sim": {**TABLE, "scanner": {"resolution_scale": 0.5}}}))
    assert _components(w) == _components(same)


def test_a_scanner_on_the_arm_is_where_the_true_joints_put_its_link() -> None:
    T_link_cam = [[0.0, -1.0, 0.0, -0.578], [0.0, 0.0, -1.0, 0.82], [1.0, 0.0, 0.0, 0.162], [0.0, 0.0, 0.0, 1.0]]
    w = world_of(parse({"sim": {**TABLE, "scanner": {"mount": "link1", "T_link_cam": T_link_cam}}}))
    sc = w.scanner
    assert sc.link == 1
    with pytest.raises(InputError, match="follows the joints"):
        sc.T_base_cam  # noqa: B018 - the property refuses
    # The boom's mounting error is drawn in the link's frame, within the budget.
    dt, dr = se3.error(sc.T_mount_cam, np.array(T_link_cam))
    b = w.budget
    assert 0.0 < dt <= TRUNCATE * b.mount_translation * math.sqrt(3) and 0.0 < dr <= TRUNCATE * b.mount_rotation * math.sqrt(3)
    q = np.array([2.847, -1.401, 2.311, -2.481, 1.571, -1.276])
    T1 = kin.matrix_from_rows(kin.forward_all_rows(list(q), w.arm.dh)[0])
    np.testing.assert_allclose(sc.T_base_cam_at(q, w.arm.dh), T1 @ sc.T_mount_cam, atol=1e-15)
    # Joints after the first do not move it; the first turns it about the base's z.
    np.testing.assert_allclose(sc.T_base_cam_at(q + [0, 0.3, 0.2, 0.1, 0.4, 0.5], w.arm.dh), T1 @ sc.T_mount_cam, atol=1e-12)
    assert not np.allclose(sc.T_base_cam_at(q + [0.1, 0, 0, 0, 0, 0], w.arm.dh), T1 @ sc.T_mount_cam, atol=1e-3)


def test_world_options_go_through_the_command_line() -> None:
    parser = argparse.ArgumentParser()
    add_world_arguments(parser)
    opts = WorldOptions("ideal", 5, ("tool_offsets",), ("part_shape", "settle"))
    assert options_from_args(parser.parse_args(opts.to_argv())) == opts
    assert options_from_args(parser.parse_args([])) == WorldOptions()
    with pytest.raises(ConfigError, match="unknown error source"):
        options_from_args(parser.parse_args(["--without", "gravity"]))
    with pytest.raises(InputError, match="unknown source"):
        ErrorBudget(enabled=frozenset({"gravity"}))


def test_arm_truth_survives_the_command_line() -> None:
    a = draw_world(NOMINAL, REALISTIC, 1).arm
    assert ArmTruth.from_json(a.to_json()) == a
    with pytest.raises(ConfigError):
        ArmTruth.from_json("{}x")


def test_a_second_robot_stands_off_its_drawing_by_the_budget_with_an_arm_of_its_own() -> None:
    offsets, angles = [], []
    for seed in range(30):
        w = draw_world(NOMINAL, REALISTIC, seed)
        assert w.robot2 is not None
        dt, dr = se3.error(w.robot2.T_base1_base2, w.robot2.T_base1_base2_drawn)
        offsets.append(dt)
        angles.append(dr)
        # Its own kinematic error, not a copy of robot 1's.
        assert w.robot2.arm.dh != w.arm.dh and w.robot2.arm.seed != w.arm.seed
    bound = TRUNCATE * math.sqrt(3)
    assert max(offsets) <= bound * REALISTIC.base_translation and max(angles) <= bound * REALISTIC.base_rotation
    assert np.median(offsets) > 0.5 * REALISTIC.base_translation and np.median(angles) > 0.5 * REALISTIC.base_rotation


def test_a_second_robot_in_the_sim_table_needs_its_drawn_base_and_the_configs_robot2() -> None:
    from celld.sim.cell import check_robot2

    with pytest.raises(ConfigError, match=r"sim\.robot2\.base_pose"):
        world_from_table({**TABLE, "robot2": {"robot": "ur10e"}})
    with pytest.raises(ConfigError, match=r"sim\.robot2\.flange"):
        world_from_table({**TABLE, "robot2": {"base_pose": [1.25, 0, 0, 0, 0, 3.1], "flange": "nope"}})
    w = world_from_table({**TABLE, "robot2": {"base_pose": [1.25, 0, 0, 0, 0, 3.1]}})
    assert w.robot2 is not None and w.robot2.model == "ur10e"
    with pytest.raises(ConfigError, match=r"robot2: the config has \[sim.robot2\] but no \[robot2\]"):
        check_robot2(parse({}), w)
    check_robot2(parse({}), world_from_table(TABLE))  # neither: a one-robot cell
