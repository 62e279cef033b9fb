"""The arm's kinematic calibration on arms drawn here: it recovers what position and normal data can tell,
holds what they cannot, and the pre-correction lands the drawn arm's flange where it is sent."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from celld import se3
from celld.calib import kinematic as km
from celld.calib.poses import calibration_poses
from celld.errors import InputError
from celld.robot import dynamics, primary
from celld.robot import kinematics as kin
from celld.sim.robot.truearm import ArmTruth

NOMINAL = kin.UR10E
LINKS = dynamics.links("ur10e")
PAYLOAD = dynamics.Payload(1.6, (0.0, 0.0, 0.09))
HOME = np.array([2.847, -1.401, 2.311, -2.481, 1.571, -1.276])
T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
R_DOWN = se3.from_xyz_rpy([0.0, 0.0, 0.0], [math.pi, 0.0, math.pi / 2])[:3, :3]


def _arm(seed: int) -> ArmTruth:
    """An arm off its DH table by 0.15 mm / 0.15 mrad (1 sigma) whose joints yield under the published links."""
    r = np.random.default_rng(seed)
    d = np.asarray(NOMINAL.d) + r.normal(0.0, 0.15e-3, 6)
    a = np.asarray(NOMINAL.a) + r.normal(0.0, 0.15e-3, 6)
    alpha = np.asarray(NOMINAL.alpha) + r.normal(0.0, 0.15e-3, 6)
    assert LINKS is not None
    return ArmTruth(
        dh=kin.DH(tuple(d), tuple(a), tuple(alpha)),  # type: ignore[arg-type]
        joint_offsets=tuple(r.normal(0.0, 0.15e-3, 6)),
        compliance=tuple(1.0 / r.uniform(*k) for k in ((1.2e5, 2e5),) * 2 + ((6e4, 1e5),) + ((1.5e4, 3e4),) * 3),
        link_mass=LINKS.mass,
        link_com=LINKS.com,
        payload_mass=PAYLOAD.mass,
        payload_com=PAYLOAD.com,
    )


def _session(arm: ArmTruth, n: int, seed: int, noise: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The controller's joints, and the flange centres and normals a scanner at T_BASE_CAM sees, at wide poses."""
    T_c = se3.from_xyz_rpy([0.6, 0.0, 0.4], [0.0, 0.0, 0.0])
    poses = calibration_poses(T_c, km.WIDE.box, n, km.WIDE.max_tilt, seed=seed, max_spin=km.WIDE.max_spin)
    r = np.random.default_rng(seed)
    T_cam_base = se3.invert(T_BASE_CAM)
    Q, P, N = [], [], []
    q = HOME
    for T in poses:
        q = kin.inverse(T, q, NOMINAL)
        assert q is not None
        T_true = arm.flange(q)
        Q.append(q)
        P.append(se3.apply(T_cam_base, T_true[:3, 3]) + r.normal(0.0, noise, 3))
        N.append(T_cam_base[:3, :3] @ T_true[:3, 2] + r.normal(0.0, 40.0 * noise, 3))  # 0.03 mm: 1.2 mrad
    return np.array(Q), np.array(P), np.array(N)


def _weld_errors(arm: ArmTruth, model: km.ArmModel, T_base_cam: np.ndarray) -> np.ndarray:
    """Where the flange truly lands, sent flange down through the calibration to points over the table."""
    out, q = [], HOME
    for x in (0.45, 0.6, 0.75):
        for y in (-0.15, 0.0, 0.15):
            for z in (0.15, 0.3):
                p = np.array([x, y, z])
                target = se3.apply(T_base_cam @ se3.invert(T_BASE_CAM), p)  # what the calibration makes of p
                got = model.precorrect(se3.transform_from(R_DOWN, target), q)
                assert got is not None
                T_cmd, q = got
                out.append(np.linalg.norm(arm.flange(kin.inverse(T_cmd, q, NOMINAL))[:3, 3] - p))
    return np.array(out)


@pytest.mark.parametrize("seed", [1, 2])
def test_the_fit_recovers_the_arm_where_it_is_identifiable_and_lands_the_weld(seed: int) -> None:
    arm = _arm(seed)
    Q, P, N = _session(arm, 40, seed, noise=0.03e-3)
    T0 = T_BASE_CAM @ se3.from_ur_pose([1e-3, -2e-3, 1e-3, 2e-3, 1e-3, -1e-3])  # a hand-eye start, mm off
    fit = km.fit_arm(Q, P, T0, NOMINAL, LINKS, PAYLOAD, n_cam=N)
    # The corrections predict poses their fit did not see far better than the scanner's pose alone: kept.
    assert fit.chosen == "arm" and fit.held_out_rms is not None, fit.held_out_rms
    assert fit.held_out_rms["arm"] < 0.5 * fit.held_out_rms["pose"], fit.held_out_rms
    # What cannot be told apart from centres and normals is held, and said.
    # (the base's turn is the camera's; the flange's turn about its axis moves neither centre nor normal; the
    # base carries no gravity torque; the wrists' compliance is held by design, km.COMPLIANT).
    for name in ("theta1", "theta6", "compliance1", "compliance4", "compliance5", "compliance6"):
        assert name in fit.held, fit.held
    assert set(fit.held) | set(fit.estimated) == set(km.NAMES) and not set(fit.held) & set(fit.estimated)
    assert fit.rank <= len(km.NAMES) - 2 and 1.0 < fit.condition < 1e4
    # The elbow's compliance within a tenth, the shoulder's within a third (it shares its effect with the
    # upper arm's length).
    assert fit.model.compliance[2] == pytest.approx(arm.compliance[2], rel=0.1), (fit.model.compliance, arm.compliance)
    assert fit.model.compliance[1] == pytest.approx(arm.compliance[1], rel=0.35), (fit.model.compliance, arm.compliance)
    # The fit explains the data to the noise, which the controller's kinematics did not.
    assert fit.rms < 0.06e-3 and float(np.sqrt(np.mean(fit.residuals_before**2))) > 1e-3
    # At the weld, flange down (never seen): pre-corrected through the model, within 0.1 mm; without the
    # model, the same arm is off by what the rigid fit cannot hold.
    e = _weld_errors(arm, fit.model, fit.T_base_cam)
    assert e.mean() < 0.1e-3 and e.max() < 0.2e-3, e * 1e3
    # Its bounds cover it: where its poses went (a flange centre seen without noise, placed by the fit's
    # T_base_cam, against where the fit's model puts the flange there: the miss of a target there) and at the weld.
    seen = se3.apply(fit.T_base_cam @ se3.invert(T_BASE_CAM), np.array([arm.flange(q)[:3, 3] for q in Q]))
    at_poses = np.linalg.norm(seen - np.array([fit.model.forward(q)[:3, 3] for q in Q]), axis=1)
    assert np.mean(at_poses <= fit.bound_poses) >= 0.9 and fit.bound_poses < 0.2e-3, (at_poses.max(), fit.bound_poses)
    assert fit.bound_away == pytest.approx(fit.bound_poses + km.REMAINING_PRIOR) and e.max() <= fit.bound_away
    assert fit.report()["bound"]["away_mm"] == pytest.approx(fit.bound_away * 1e3)
    rigid = km.fit_arm(Q, P, T0, NOMINAL, compliance=False)
    assert _weld_errors(arm, km.ArmModel.identity(NOMINAL), rigid.T_base_cam).mean() > 2 * e.mean()


def test_without_a_sag_model_the_compliance_is_not_fitted() -> None:
    arm = replace(_arm(3), compliance=(0.0,) * 6)
    Q, P, N = _session(arm, 30, 3, noise=0.0)
    fit = km.fit_arm(Q, P, T_BASE_CAM, NOMINAL, LINKS, PAYLOAD, n_cam=N, compliance=False)
    assert all(n in fit.held for n in (f"compliance{j}" for j in range(1, 7)))
    # Noise-free: the residuals vanish to micrometres; the weak priors leave the weld within 0.05 mm.
    assert fit.model.compliance == (0.0,) * 6 and fit.rms < 5e-6
    assert _weld_errors(arm, fit.model, fit.T_base_cam).max() < 50e-6


@pytest.mark.parametrize("seed", [0, 2, 4])
def test_a_dozen_poses_of_an_arm_as_its_table_says_keep_the_scanners_pose_alone_and_say_how_sure(seed: int) -> None:
    # The controller's table is right and nothing sags: two dozen corrections fitted to 12 poses' noise (0.1 mm
    # a centre) put the flange 0.35-1.2 mm off at the weld. Cross-validation sees that they predict the poses
    # they did not see worse than the scanner's pose alone, and keeps that.
    arm = replace(_arm(seed), dh=NOMINAL, joint_offsets=(0.0,) * 6, compliance=(0.0,) * 6)
    Q, P, N = _session(arm, 12, seed + 10, noise=0.1e-3)
    T0 = T_BASE_CAM @ se3.from_ur_pose([1e-3, -2e-3, 1e-3, 2e-3, 1e-3, -1e-3])
    fit = km.fit_arm(Q, P, T0, NOMINAL, LINKS, PAYLOAD, n_cam=N, arm_error_prior=1.0e-3)
    assert fit.chosen == "pose" and fit.held_out_rms is not None and fit.held_out_rms["pose"] < fit.held_out_rms["arm"]
    assert fit.estimated == km.POSE_NAMES and set(fit.held) == set(km.NAMES[6:])
    assert fit.model.as_dict()["d_mm"] == [0.0] * 6 and fit.model.compliance == (0.0,) * 6
    e = _weld_errors(arm, fit.model, fit.T_base_cam)
    assert e.mean() < 0.15e-3, e * 1e3
    # The geometry was not earned by the data: the bound away from the poses carries the arm's class.
    assert fit.bound_away == pytest.approx(fit.bound_poses + 1.0e-3) and e.max() <= fit.bound_away
    report = km.arm_entry(fit, "ur10e", len(Q))
    assert report["model"] == "pose" and set(report["held_out_rms_mm"]) >= {"pose", "arm"}
    _, model = km.arm_of(report)
    np.testing.assert_allclose(model.forward(Q[0]), kin.forward(Q[0], NOMINAL), atol=1e-12)


def test_precorrection_puts_the_modelled_flange_on_the_target_and_is_the_identity_without_corrections() -> None:
    arm = _arm(4)
    model = km.ArmModel(NOMINAL, arm.dh, arm.joint_offsets, arm.compliance, LINKS, PAYLOAD)
    T = se3.transform_from(R_DOWN, [0.62, 0.05, 0.2])
    got = model.precorrect(T, HOME)
    assert got is not None
    T_cmd, q = got
    np.testing.assert_allclose(model.forward(q), T, atol=1e-9)
    np.testing.assert_allclose(kin.forward(q, NOMINAL), T_cmd, atol=1e-12)  # what the controller is told
    assert np.linalg.norm(T_cmd[:3, 3] - T[:3, 3]) > 0.1e-3  # it is told somewhere else than the target
    ident = km.ArmModel.identity(NOMINAL)
    got = ident.precorrect(T, HOME)
    assert got is not None and np.array_equal(got[0], T)
    assert model.precorrect(se3.transform_from(R_DOWN, [3.0, 0.0, 0.2]), HOME) is None  # out of reach


def test_bad_sessions_are_refused_with_what_was_wrong() -> None:
    Q, P, _ = _session(_arm(5), 8, 5, noise=0.0)
    with pytest.raises(InputError, match="joints"):
        km.fit_arm(Q[:, :5], P, T_BASE_CAM, NOMINAL)
    bad = P.copy()
    bad[2, 1] = np.nan
    with pytest.raises(InputError, match="finite"):
        km.fit_arm(Q, bad, T_BASE_CAM, NOMINAL)
    with pytest.raises(InputError, match="at least 4"):
        km.fit_arm(Q[:3], P[:3], T_BASE_CAM, NOMINAL)


def test_the_stored_arm_entry_reads_back_as_the_same_model_and_bad_entries_are_refused_by_key() -> None:
    arm = _arm(6)
    Q, P, N = _session(arm, 40, 6, noise=0.02e-3)
    fit = km.fit_arm(Q, P, T_BASE_CAM, NOMINAL, LINKS, PAYLOAD, n_cam=N)
    entry = km.arm_entry(fit, "ur10e", len(Q))
    T, model = km.arm_of(entry)
    np.testing.assert_allclose(T, fit.T_base_cam, atol=1e-12)
    for q in Q[:5]:
        np.testing.assert_allclose(model.forward(q), fit.model.forward(q), atol=1e-12)
    assert entry["pairs"] == 40 and entry["held"] and entry["corrections"]["payload_kg"] == pytest.approx(1.6)
    # The controller's reported pose, corrected by the model at the joints it was reported at.
    q = Q[3]
    np.testing.assert_allclose(model.correction(q) @ kin.forward(q, NOMINAL), model.forward(q), atol=1e-12)
    bad = {**entry, "corrections": {**entry["corrections"], "a_mm": [0.0, 35.0, 0.0, 0.0, 0.0, 0.0]}}
    with pytest.raises(InputError, match=r"calibration\.arm\.corrections\.a_mm: expected each within \[-20, 20\]"):
        km.arm_of(bad)
    bad = {**entry, "corrections": {**entry["corrections"], "theta_mrad": [0.0] * 5}}
    with pytest.raises(InputError, match=r"theta_mrad: expected 6 finite numbers"):
        km.arm_of(bad)
    with pytest.raises(InputError, match=r"calibration\.arm\.robot: expected one of"):
        km.arm_of({**entry, "robot": "ur99"})
    with pytest.raises(InputError, match=r"calibration\.arm\.T_base_cam"):
        km.arm_of({**entry, "T_base_cam": [[1.0, 0.0], [0.0, 1.0]]})
    with pytest.raises(InputError, match=r"payload_kg"):
        km.arm_of({**entry, "corrections": {**entry["corrections"], "payload_kg": -1.0}})


def test_corrections_to_a_controllers_own_table_are_stored_with_it_and_checked() -> None:
    # The controller computes with its factory calibration's table; the arm is off that table as _arm's is off
    # the published one.
    r = np.random.default_rng(11)
    table = kin.DH(
        *(tuple((np.asarray(row) + r.normal(0.0, 1e-3, 6)).tolist()) for row in NOMINAL[:3]), tuple(r.normal(0.0, 1.5e-3, 6).tolist())
    )  # type: ignore[arg-type]
    base = _arm(7)
    arm = replace(
        base,
        dh=kin.DH(*(tuple(np.add(t, np.subtract(b, n)).tolist()) for t, b, n in zip(table[:3], base.dh[:3], NOMINAL[:3]))),  # type: ignore[arg-type]
        joint_offsets=tuple(np.add(base.joint_offsets, table.theta).tolist()),
    )
    T_c = se3.from_xyz_rpy([0.6, 0.0, 0.4], [0.0, 0.0, 0.0])
    Q, P, N, q = [], [], [], HOME
    T_cam_base = se3.invert(T_BASE_CAM)
    for T in calibration_poses(T_c, km.WIDE.box, 40, km.WIDE.max_tilt, seed=7, max_spin=km.WIDE.max_spin):
        q = kin.inverse(T, q, table)  # the controller's own joints for the pose
        assert q is not None
        Q.append(q)
        P.append(se3.apply(T_cam_base, arm.flange(q)[:3, 3]))
        N.append(T_cam_base[:3, :3] @ arm.flange(q)[:3, 2])
    fit = km.fit_arm(np.array(Q), np.array(P), T_BASE_CAM, table, LINKS, PAYLOAD, n_cam=np.array(N))
    assert fit.rms < 0.03e-3  # the corrections to the controller's table explain the arm
    entry = km.arm_entry(fit, "ur10e", len(Q))
    assert entry["kinematics"]["id"] == primary.table_id(table)
    _, model = km.arm_of(entry)
    assert model.nominal == table
    for q in Q[:5]:
        np.testing.assert_allclose(model.forward(q), fit.model.forward(q), atol=1e-12)
    # A table that is not its id's, or not the robot's model, is refused.
    with pytest.raises(InputError, match=r"kinematics\.id: .* is not the id of the table"):
        km.arm_of({**entry, "kinematics": {**entry["kinematics"], "id": "0123456789abcdef"}})
    other = kin.model("ur5e").dh
    doc = {"id": primary.table_id(other), **{k: list(getattr(other, k)) for k in ("d", "a", "alpha", "theta")}}
    with pytest.raises(InputError, match=r"kinematics: robot\.model: .* from a ur10e's"):
        km.arm_of({**entry, "kinematics": doc})
    # On the published table nothing more is stored.
    assert "kinematics" not in km.arm_entry(km.fit_arm(np.array(Q), np.array(P), T_BASE_CAM, NOMINAL, LINKS, PAYLOAD), "ur10e", 40)
