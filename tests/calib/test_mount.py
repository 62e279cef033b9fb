"""A scanner on the arm (Eq. 8): its frame from the joints, a session solved in it, a calibration read back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld import se3
from celld.calib.dataset import SessionWriter, load_session
from celld.calib.mount import ScannerMount, in_frame, mount_entry, placement_of
from celld.calib.session import calibrate_session
from celld.calib.solve import SolveParams
from celld.errors import InputError
from celld.robot import kinematics as kin
from celld.se3 import apply, error, invert, transform_from

MOUNT = ScannerMount.of("link1", "ur10e")
# The boom of configs/sim-cell-eye-on-arm.toml: 0.82 m over the shoulder, 0.58 m out, looking down.
T_LINK_CAM = np.array([[0.0, -1.0, 0.0, -0.578], [0.0, 0.0, -1.0, 0.82], [1.0, 0.0, 0.0, 0.162], [0.0, 0.0, 0.0, 1.0]])
HOME = np.array([2.847, -1.401, 2.311, -2.481, 1.571, -1.276])


def poses(rng: np.random.Generator, n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Flange poses about (0.6, 0, 0.45), tilted up to 0.3 rad, and the joints that reach them near home."""
    T_out, q_out = [], []
    while len(T_out) < n:
        R = Rotation.from_rotvec(rng.uniform(-0.3, 0.3, 3)).as_matrix()
        T = transform_from(R, [0.6, 0.0, 0.45] + rng.uniform(-0.5, 0.5, 3) * [0.3, 0.3, 0.2])
        q = kin.inverse(T, HOME)
        if q is not None:
            T_out.append(T)
            q_out.append(q)
    return T_out, q_out


def test_the_scanner_frame_follows_the_joints_before_it_and_not_those_after() -> None:
    q = HOME.copy()
    T0 = MOUNT.T_base_link(q)
    np.testing.assert_allclose(T0, kin.matrix_from_rows(kin.forward_all_rows(list(q))[0]), atol=1e-15)
    q2 = q + [0.0, 0.3, -0.2, 0.4, 0.5, 0.6]  # every joint after the first
    np.testing.assert_allclose(MOUNT.T_base_link(q2), T0, atol=1e-15)
    turned = MOUNT.T_base_link(q + [0.2, 0, 0, 0, 0, 0])
    # Link 1 turns about the base's z by the first joint.
    np.testing.assert_allclose(turned[:3, :3], Rotation.from_rotvec([0, 0, 0.2]).as_matrix() @ T0[:3, :3], atol=1e-12)
    # A pose in the link frame and back.
    T = transform_from(Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix(), [0.5, 0.1, 0.4])
    np.testing.assert_allclose(MOUNT.T_base_link(q) @ MOUNT.to_link(T, q), T, atol=1e-12)
    # On the base nothing moves, and no joints are needed.
    base = ScannerMount()
    np.testing.assert_array_equal(base.to_link(T, None), T)
    np.testing.assert_array_equal(base.T_base_cam(T_LINK_CAM, None), T_LINK_CAM)
    with pytest.raises(InputError, match="needs the robot's joints"):
        MOUNT.T_base_cam(T_LINK_CAM, None)
    with pytest.raises(InputError, match="expected one of base, link1"):
        ScannerMount("link6")


def test_a_session_of_a_scanner_on_the_arm_solves_its_pose_on_the_link(tmp_path: Path, rng: np.random.Generator) -> None:
    """Eq. 8: flange centres seen by a scanner that moved with the base joint; the base-frame fit cannot
    explain them, the link-frame fit does to the noise."""
    T_flange, q = poses(rng, 10)
    writer = SessionWriter(tmp_path / "s", flange="ur10e", scanner="phoxi-m", mount=MOUNT, compact=False)
    for T, qq in zip(T_flange, q):
        # The flange centre as the scanner on link 1 sees it at these joints (0.05 mm noise).
        p_cam = apply(invert(MOUNT.T_base_cam(T_LINK_CAM, qq)), T[:3, 3][None])[0] + rng.normal(0.0, 0.05e-3, 3)
        writer.add_pair(T, p_cam[None] + rng.normal(0.0, 1e-4, (50, 3)), q=qq)
    with pytest.raises(InputError, match="needs the robot's joints"):
        writer.add_pair(T_flange[0], np.zeros((5, 3)))
    doc = json.loads((tmp_path / "s" / "poses.json").read_text())
    assert doc["version"] == 4 and doc["mount"] == "link1" and len(doc["pairs"][0]["q"]) == 6

    session = load_session(tmp_path / "s")
    assert session.mount == MOUNT
    centres = [np.mean(session.cloud(r), axis=0) for r in session.pairs]
    # Solve with the recorded centres (the clouds are blobs around them).
    rec = [r.__class__(r.id, r.p_base, r.T_base_flange, None, c, r.q) for r, c in zip(session.pairs, centres)]
    result = calibrate_session(session.__class__(session.root, "celld", tuple(rec), None, None, None, "m", MOUNT), None, SolveParams())
    dt, dr = error(result.T_base_cam, T_LINK_CAM)
    assert dt < 0.3e-3 and np.degrees(dr) < 0.05, (dt, np.degrees(dr))
    assert float(np.sqrt(np.mean(result.residuals**2))) < 0.2e-3
    # The same centres against the base-frame flange positions: the boom turned between captures.
    flat = session.__class__(session.root, "celld", tuple(rec), None, None, None, "m", ScannerMount())
    base_fit = calibrate_session(flat, None, SolveParams(method="svd"))
    assert float(np.sqrt(np.mean(base_fit.residuals**2))) > 5e-3

    # A session without joints, or with a mount it cannot place, is refused with the place.
    del doc["pairs"][1]["q"]
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"pairs\[1\]\.q: missing"):
        load_session(tmp_path / "s")
    doc["mount"] = "link9"
    (tmp_path / "s" / "poses.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="mount: expected one of"):
        load_session(tmp_path / "s")


def test_a_calibration_on_the_arm_is_stored_and_read_back_in_its_frame() -> None:
    report = {"T_base_cam": T_LINK_CAM.tolist(), "algorithm1": {"T_base_cam": None, "cost_mm": 0.1}, "T_base_cam_estimate": []}
    named = in_frame(report, MOUNT)
    assert set(named) == {"T_link1_cam", "algorithm1", "T_link1_cam_estimate"} and "T_link1_cam" in named["algorithm1"]
    assert in_frame(report, ScannerMount()) is report

    entry = mount_entry(MOUNT, T_LINK_CAM)
    assert entry["mount"] == "link1" and "T_base_cam" not in entry
    placed = placement_of(json.loads(json.dumps(entry)))
    assert placed.mount == MOUNT
    np.testing.assert_allclose(placed.T_base_cam(HOME), MOUNT.T_base_link(HOME) @ T_LINK_CAM, atol=1e-15)
    base = placement_of(mount_entry(ScannerMount(), T_LINK_CAM))
    assert not base.mount.on_arm
    np.testing.assert_array_equal(base.T_base_cam(None), T_LINK_CAM)

    with pytest.raises(InputError, match=r"calibration\.dh: expected the robot's DH table"):
        placement_of({**entry, "dh": {"d": [0.1] * 5, "a": [0.0] * 6, "alpha": [0.0] * 6}})
    with pytest.raises(InputError, match=r"calibration\.T_link1_cam"):
        placement_of({k: v for k, v in entry.items() if k != "T_link1_cam"})
    with pytest.raises(InputError, match=r"calibration\.mount"):
        placement_of({**entry, "mount": "wrist"})


def test_a_calibration_with_an_arm_entry_places_the_scanner_and_corrects_poses_through_the_arm() -> None:
    from celld.calib.kinematic import ArmModel
    from celld.robot import dynamics

    nominal = kin.UR10E
    dh = kin.DH(nominal.d, tuple(np.add(nominal.a, [0.0, 0.4e-3, -0.3e-3, 0.0, 0.0, 0.0])), nominal.alpha)
    model = ArmModel(
        nominal, dh, (0.0, 0.2e-3, 0.0, 0.0, 0.0, 0.0), (0.0,) * 6, dynamics.links("ur10e"), dynamics.Payload(1.6, (0.0, 0.0, 0.09))
    )
    T_arm = se3.from_ur_pose([0.6, -0.01, 1.0, 3.1, 0.02, 0.0])
    T_hand_eye = se3.from_ur_pose([0.6, -0.012, 1.0, 3.1, 0.02, 0.0])
    corrections = model.as_dict()
    arm_entry = {"robot": "ur10e", "T_base_cam": T_arm.tolist(), "corrections": corrections}
    placed = placement_of({"T_base_cam": T_hand_eye.tolist(), "arm": arm_entry})
    # The scanner is where the arm fit put it, the arm as the fit corrected it.
    np.testing.assert_allclose(placed.T_base_cam(None), T_arm)
    q = np.array([2.847, -1.401, 2.311, -2.481, 1.571, -1.276])
    T_flange_tcp = se3.from_ur_pose([0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    T_tcp = kin.forward(q, nominal) @ T_flange_tcp  # what the controller reports
    np.testing.assert_allclose(placed.modelled(T_tcp, q), model.forward(q) @ T_flange_tcp, atol=1e-12)
    # A TCP target pre-corrected: the controller sent there puts the modelled TCP on the target.
    target = se3.from_ur_pose([0.55, 0.05, 0.25, 3.14, 0.0, 0.0])
    T_cmd = placed.precorrect(target, q, T_flange_tcp)
    q_cmd = kin.inverse(T_cmd @ se3.invert(T_flange_tcp), q, nominal)
    assert q_cmd is not None
    np.testing.assert_allclose(model.forward(q_cmd) @ T_flange_tcp, target, atol=1e-8)
    assert np.linalg.norm(T_cmd[:3, 3] - target[:3, 3]) > 0.1e-3
    # Without an arm entry: the hand-eye calibration, poses as they are.
    plain = placement_of({"T_base_cam": T_hand_eye.tolist()})
    assert plain.arm is None and np.array_equal(plain.precorrect(target, q, T_flange_tcp), target)
    np.testing.assert_array_equal(plain.modelled(T_tcp, q), T_tcp)
    with pytest.raises(InputError, match="out of the calibrated arm's reach"):
        placed.precorrect(se3.from_ur_pose([3.0, 0.0, 0.2, 3.14, 0.0, 0.0]), q)
    with pytest.raises(InputError, match=r"calibration\.arm\.corrections\.d_mm"):
        placement_of({"T_base_cam": T_hand_eye.tolist(), "arm": {**arm_entry, "corrections": {**corrections, "d_mm": "x"}}})
    with pytest.raises(InputError, match="needs a fixed scanner"):
        placement_of({"mount": "link1", "dh": kin.UR10E._asdict(), "T_link1_cam": T_arm.tolist(), "arm": arm_entry})
