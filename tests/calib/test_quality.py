"""The quality gate: verdicts and their reasons, outliers named, uncertainty at the workspace centre."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.metrics import IcpMetric
from celld.calib.quality import QualityParams, assess_calibration, axis_name
from celld.calib.rigid import solve_rigid
from celld.calib.robust import RejectedPair, solve_robust
from celld.errors import InputError
from celld.se3 import apply, invert, transform_from

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
SIGMA = 0.1e-3  # per axis, a PhoXi M-like centre noise


def box_pairs(rng: np.random.Generator, n: int, sigma: float = SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """n centres in a 0.3 x 0.3 x 0.2 m box and their noisy camera-frame images (Eq. 20)."""
    P_base = rng.uniform(-0.5, 0.5, (n, 3)) * [0.3, 0.3, 0.2] + [0.6, 0.0, 0.45]
    return P_base, apply(invert(T_BASE_CAM), P_base) + rng.normal(0.0, sigma, (n, 3))


def strip_pairs(rng: np.random.Generator, n: int, width: float, sigma: float = SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """n centres in one plane (z = 0.45 m, 0.03 mm out of it): 300 mm along base x, ``width`` along y."""
    P_base = np.column_stack([rng.uniform(0.45, 0.75, n), rng.uniform(-width / 2, width / 2, n), 0.45 + rng.uniform(-3e-5, 3e-5, n)])
    return P_base, apply(invert(T_BASE_CAM), P_base) + rng.normal(0.0, sigma, (n, 3))


def assess_fit(P_base, P_cam, e_icp=None, **kw):
    """The gate on Eq. 9-12 over every pair (the svd method)."""
    fit = solve_rigid(P_base, P_cam)
    ids = [f"p{i}" for i in range(len(P_base))]
    return assess_calibration(ids, P_base, P_cam, fit.T_dst_src, used=range(len(P_base)), uncertainty=fit.uncertainty, e_icp=e_icp, **kw)


def identity_e_icp() -> IcpMetric:
    return IcpMetric(np.eye(4), True, 0.98, 5e-5)


def test_a_good_session_passes_with_its_uncertainty_at_the_workspace_centre(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 12)
    fit = solve_rigid(P_base, P_cam)
    q = assess_fit(P_base, P_cam, identity_e_icp())
    assert q.verdict == "ok" and q.passed and q.reasons == ()
    assert q.warnings == ()
    assert q.outliers == () and all(p.used and p.reason == "" for p in q.pairs)
    assert q.sigma_source == "residuals" and q.sigma == fit.uncertainty.sigma
    # At the centroid of the positions the rotation's lever arm vanishes: the
    # translation 1-sigma is sigma / sqrt(n) on every axis (research/handeye_anchors.md section 3).
    np.testing.assert_allclose(q.workspace_centre, P_base.mean(axis=0))
    np.testing.assert_allclose(q.translation_std, q.sigma / math.sqrt(12), rtol=1e-9)
    # ... while the camera's position, a metre above, carries it (across the lever arm).
    assert fit.uncertainty.translation_error > 3 * np.linalg.norm(q.translation_std)
    # The rotation 1-sigma is the fit's own (same noise, same pairs).
    np.testing.assert_allclose(q.rotation_std, fit.uncertainty.rotation_std, rtol=1e-9)
    assert max(a.std for a in q.rotation_axes) == pytest.approx(math.sqrt(np.max(np.linalg.eigvalsh(fit.uncertainty.covariance[:3, :3]))))
    d = q.as_dict()
    assert d["verdict"] == "ok" and d["n_used"] == 12 and len(d["pairs"]) == 12 and d["e_icp"]["ok"] is True


def test_the_box_bound_covers_a_new_point_seen_through_the_calibration(rng: np.random.Generator) -> None:
    """A point in the box, seen with the scanner's noise and mapped by the estimate, lands within the bound at its
    confidence (the estimate's own error there and the pose-to-pose error); a 1-sigma would not cover it."""
    covered, within_sigma, trials = 0, 0, 400
    for _ in range(trials):
        P_base, P_cam = box_pairs(rng, 8)
        q = assess_fit(P_base, P_cam)
        p = rng.uniform(-0.5, 0.5, 3) * [0.3, 0.3, 0.2] + [0.6, 0.0, 0.45]
        seen = apply(invert(T_BASE_CAM), p[None])[0] + rng.normal(0.0, SIGMA, 3)
        fit = solve_rigid(P_base, P_cam)
        miss = float(np.linalg.norm(apply(fit.T_dst_src, seen[None])[0] - p))
        covered += miss <= q.bound_box
        within_sigma += miss <= float(np.linalg.norm(q.translation_std))
    assert covered / trials >= 0.9, covered / trials
    assert within_sigma / trials < 0.5, within_sigma / trials
    # Not far beyond the confidence either: a bound that covers by being huge says nothing.
    assert covered / trials <= 0.995


def test_away_from_the_pairs_the_bound_carries_the_arms_own_error(rng: np.random.Generator) -> None:
    """Where no pair was measured the arm's own error is not in the residuals: the bound there adds its prior whole,
    and the estimate's uncertainty at the work radius (the rotation's lever)."""
    P_base, P_cam = box_pairs(rng, 12)
    bare = assess_fit(P_base, P_cam, params=QualityParams(arm_error_prior=0.0))
    with_prior = assess_fit(P_base, P_cam, params=QualityParams(arm_error_prior=1.0e-3))
    assert bare.bound_away > bare.bound_box  # the lever alone
    assert with_prior.bound_away == pytest.approx(bare.bound_away + 1.0e-3)
    assert with_prior.bound_box == bare.bound_box
    wider = assess_fit(P_base, P_cam, params=QualityParams(arm_error_prior=0.0, work_radius=1.5))
    assert wider.bound_away > bare.bound_away
    d = with_prior.as_dict()["bound"]
    assert d["confidence"] == 0.95 and d["arm_error_prior_mm"] == pytest.approx(1.0)
    assert d["work_radius_mm"] == pytest.approx(with_prior.bound_away * 1e3)
    assert d["calibration_box_mm"] == pytest.approx(with_prior.bound_box * 1e3)
    with pytest.raises(InputError, match="arm_error_prior"):
        QualityParams(arm_error_prior=-1e-3)
    with pytest.raises(InputError, match="bound_confidence"):
        QualityParams(bound_confidence=1.0)


def test_a_narrow_plane_warns_and_fails_on_the_rotation_about_its_long_axis(rng: np.random.Generator) -> None:
    # 300 x 30 mm in one plane: the lever arm about base x is the 30 mm width.
    P_base, P_cam = strip_pairs(rng, 8, 0.03, sigma=0.2e-3)
    q = assess_fit(P_base, P_cam, identity_e_icp())
    assert q.verdict == "insufficient_rotation" and not q.passed
    worst = q.rotation_axes[0]
    assert worst.name == "X" and worst.std > QualityParams().max_rotation_std
    assert q.reasons == (
        f"rotation about X poorly fixed: {math.degrees(worst.std):.2f} deg 1-sigma, above 0.25 deg; add poses off the plane",
    )
    assert f"rotation about X poorly fixed: {math.degrees(worst.std):.2f} deg 1-sigma; add poses off the plane" in q.warnings
    # The other two rotations are fixed by the 300 mm length.
    assert all(a.std < QualityParams().warn_rotation_std for a in q.rotation_axes[1:])


def test_a_wide_plane_passes(rng: np.random.Generator) -> None:
    # Coplanar positions spanning two directions fix every rotation: no flat-plane rule.
    P_base, P_cam = strip_pairs(rng, 10, 0.3)
    q = assess_fit(P_base, P_cam, identity_e_icp())
    assert q.verdict == "ok", q.reasons
    assert all(math.degrees(a.std) < 0.05 for a in q.rotation_axes)


def test_a_near_line_is_told_to_leave_the_line(rng: np.random.Generator) -> None:
    P_base, P_cam = strip_pairs(rng, 8, 0.004)
    q = assess_fit(P_base, P_cam, identity_e_icp())
    assert q.verdict == "insufficient_rotation"
    assert q.reasons[0].startswith("rotation about X poorly fixed") and q.reasons[0].endswith("add poses off the line")


def test_exact_data_is_judged_at_the_noise_floor(rng: np.random.Generator) -> None:
    P_base, P_cam = strip_pairs(rng, 8, 0.03, sigma=0.0)
    q = assess_fit(P_base, P_cam, identity_e_icp())
    # Zero residuals would make any geometry look perfect; the floor does not.
    assert q.sigma_source == "floor" and q.sigma == QualityParams().sigma_floor
    assert any("below the floor" in w for w in q.warnings)
    assert q.rotation_axes[0].name == "X" and q.rotation_axes[0].std > 0.0


def test_too_few_pairs(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 4)
    q = assess_fit(P_base, P_cam, identity_e_icp())
    assert q.verdict == "too_few_pairs"
    assert q.reasons[0].startswith("only 4 of 4 captures gave a flange centre; at least 5 are needed")
    assert assess_fit(*box_pairs(rng, 5), identity_e_icp()).verdict == "ok"


def test_failed_detections_are_listed_and_count_against_the_pairs(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 4)
    fit = solve_rigid(P_base, P_cam)
    lost = [
        RejectedPair("p4", -1, math.nan, "detection failed at circle: no rim"),
        RejectedPair("p5", -1, math.nan, "detection failed at plane: no plane"),
    ]
    q = assess_calibration(
        list("abcd"), P_base, P_cam, fit.T_dst_src, used=range(4), uncertainty=fit.uncertainty, rejected=lost, e_icp=identity_e_icp()
    )
    assert q.verdict == "too_few_pairs" and "only 4 of 6 captures" in q.reasons[0]
    assert [p.id for p in q.pairs] == ["a", "b", "c", "d", "p4", "p5"]
    assert math.isnan(q.pairs[4].residual) and q.pairs[4].reason == "detection failed at circle: no rim"
    assert q.as_dict()["pairs"][4]["residual_mm"] is None
    assert "2 of 6 captures gave no flange centre: p4, p5" in q.warnings


def test_an_outlier_kept_by_the_estimate_is_poor_data_and_named(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 12)
    P_cam[4] += [0.01, 0.0, 0.0]  # a false detection, 10 mm off
    q = assess_fit(P_base, P_cam, identity_e_icp())
    assert q.verdict == "poor_data"
    assert q.outliers == ("p4",)
    assert q.reasons[0].startswith("the estimate uses pairs that are outliers: p4")
    assert q.pairs[4].outlier and "exceeds the outlier threshold" in q.pairs[4].reason


def test_the_robust_estimate_leaves_the_outlier_out_and_passes(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 12)
    P_cam[4] += [0.01, 0.0, 0.0]
    ids = [f"p{i}" for i in range(12)]
    rob = solve_robust(P_base, P_cam, ids=ids)
    q = assess_calibration(
        ids, P_base, P_cam, rob.T_base_cam, used=rob.inliers, uncertainty=rob.fit.uncertainty, rejected=rob.rejected, e_icp=identity_e_icp()
    )
    assert q.verdict == "ok", q.reasons
    p4 = q.pairs[4]
    assert p4.outlier and not p4.used
    assert p4.residual == pytest.approx(0.01, abs=0.001)
    # Why it is an outlier, and why the solver left it out.
    assert "exceeds the outlier threshold" in p4.reason and "exceeds the inlier threshold" in p4.reason


def test_many_outliers_are_poor_data(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 9)
    for i, d in ((1, 0.01), (3, -0.012), (5, 0.015), (7, 0.02)):
        P_cam[i, 0] += d
    ids = [f"p{i}" for i in range(9)]
    rob = solve_robust(P_base, P_cam, ids=ids)
    q = assess_calibration(
        ids, P_base, P_cam, rob.T_base_cam, used=rob.inliers, uncertainty=rob.fit.uncertainty, rejected=rob.rejected, e_icp=identity_e_icp()
    )
    assert q.verdict == "poor_data"
    assert "4 of the 9 pairs with a centre are outliers" in q.reasons[0]


def test_large_residuals_are_poor_data(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 12, sigma=1.0e-3)  # a ToF camera's noise against PhoXi thresholds
    q = assess_fit(P_base, P_cam, identity_e_icp())
    assert q.verdict == "poor_data"
    assert any(r.startswith("the RMS residual of the 12 pairs used is") for r in q.reasons)
    assert assess_fit(P_base, P_cam, identity_e_icp(), params=QualityParams(max_rms=3e-3)).verdict == "ok"


def test_e_icp_of_the_estimate_gates_it(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 12)
    failed = assess_fit(P_base, P_cam, IcpMetric.failed("fitness 0.12 below 0.50 at 3 mm"))
    assert failed.verdict == "poor_data" and failed.reasons == (
        "e_icp (Eq. 13) of the estimate is infinite: fitness 0.12 below 0.50 at 3 mm",
    )
    far = IcpMetric(transform_from(Rotation.from_rotvec([0.0, 0.0, math.radians(0.8)]).as_matrix(), [0.003, 0.0, 0.0]), True, 0.9, 1e-4)
    q = assess_fit(P_base, P_cam, far)
    assert q.verdict == "poor_data"
    # Without the flange's axis all of the rotation counts as tilt.
    assert q.reasons == (
        "e_icp (Eq. 13) of the estimate is 3.000 mm, above 2.000 mm",
        "e_icp (Eq. 13) of the estimate tilts 0.800 deg, above 0.500 deg",
    )
    assert q.as_dict()["e_icp"]["translation_mm"] == pytest.approx([3.0, 0.0, 0.0])
    # Without a verification cloud the gate says what it could not check.
    none = assess_fit(P_base, P_cam, None)
    assert none.verdict == "ok" and none.warnings[0].startswith("no verification cloud")


def test_the_turn_about_the_flange_axis_judges_only_a_compensation(rng: np.random.Generator) -> None:
    # ICP fixes a flange's turn about its own axis only by the holes: 1.2 deg of
    # it about the camera's -z (the verification flange faces the camera), and
    # 0.1 deg of tilt.
    axis = np.array([0.0, 0.0, -1.0])
    rotvec = np.radians(1.2) * axis + np.radians(0.1) * np.array([1.0, 0.0, 0.0])
    e = IcpMetric(transform_from(Rotation.from_rotvec(rotvec).as_matrix(), [0.0003, 0.0, 0.0]), True, 0.95, 1e-4)
    P_base, P_cam = box_pairs(rng, 10)
    q = assess_fit(P_base, P_cam, e, flange_axis_cam=axis)
    assert q.verdict == "ok"
    assert math.degrees(q.e_icp_turn) == pytest.approx(1.2, abs=1e-9) and math.degrees(q.e_icp_tilt) == pytest.approx(0.1, abs=1e-9)
    assert any(w.startswith("e_icp (Eq. 13) turns 1.20 deg about the verification flange's axis") for w in q.warnings)
    stored = assess_fit(P_base, P_cam, e, flange_axis_cam=axis, compensated=True)
    assert stored.verdict == "poor_data"
    assert stored.reasons[0].startswith(
        "the compensation (Eq. 21) turns the stored transform 1.20 deg about the verification flange's axis"
    )
    d = stored.as_dict()
    assert d["e_icp_turn_deg"] == pytest.approx(1.2) and d["e_icp_tilt_deg"] == pytest.approx(0.1)


def test_e_icp_translation_is_judged_at_the_verification_flange(rng: np.random.Generator) -> None:
    # The verification flange sits a metre in front of the camera and 0.47 m
    # off its axis. ICP turns it 0.4 deg about its own axis (which it cannot
    # fix), tilts it 0.05 deg about its centre and shifts it 0.2 mm: 3.0 mm
    # at the camera's origin, 0.2 mm at the flange.
    centre = np.array([0.4, -0.25, 1.0])
    axis = np.array([0.0, 0.0, -1.0])
    R = Rotation.from_rotvec(np.radians(0.4) * axis + np.radians(0.05) * np.array([0.0, 1.0, 0.0])).as_matrix()
    t = centre - R @ centre + np.array([0.0002, 0.0, 0.0])
    e = IcpMetric(transform_from(R, t), True, 0.95, 1e-4)
    P_base, P_cam = box_pairs(rng, 10)
    at_origin = assess_fit(P_base, P_cam, e, flange_axis_cam=axis)
    assert at_origin.verdict == "poor_data"
    assert at_origin.reasons[0].startswith("e_icp (Eq. 13) of the estimate is ")
    at_flange = assess_fit(P_base, P_cam, e, flange_axis_cam=axis, flange_centre_cam=centre)
    assert at_flange.verdict == "ok", at_flange.reasons
    # A real offset at the flange still fails, and the reason says where it was judged.
    shifted = IcpMetric(transform_from(R, t + np.array([0.0, 0.0025, 0.0])), True, 0.95, 1e-4)
    q = assess_fit(P_base, P_cam, shifted, flange_axis_cam=axis, flange_centre_cam=centre)
    assert q.verdict == "poor_data"
    assert q.reasons == ("e_icp (Eq. 13) of the estimate moves the verification flange's centre 2.508 mm, above 2.000 mm",)


def test_verdicts_follow_their_order_and_list_every_reason(rng: np.random.Generator) -> None:
    P_base, P_cam = strip_pairs(rng, 4, 0.01)
    q = assess_fit(P_base, P_cam, IcpMetric.failed("no verification point within 3 mm of the placed model"))
    assert q.verdict == "too_few_pairs"
    kinds = [r.split()[0] for r in q.reasons]
    assert kinds == ["only", "e_icp", "rotation"]


def test_notes_become_warnings(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 8)
    q = assess_fit(P_base, P_cam, identity_e_icp(), notes=["compensation (Eq. 21) was asked for but not applied: no verification cloud"])
    assert q.verdict == "ok" and q.warnings == ("compensation (Eq. 21) was asked for but not applied: no verification cloud",)


def test_input_and_params_are_validated(rng: np.random.Generator) -> None:
    P_base, P_cam = box_pairs(rng, 8)
    fit = solve_rigid(P_base, P_cam)
    with pytest.raises(InputError, match="expected 8 pair ids"):
        assess_calibration(["a"], P_base, P_cam, fit.T_dst_src, used=range(8), uncertainty=fit.uncertainty)
    with pytest.raises(InputError, match="used"):
        assess_calibration(list("abcdefgh"), P_base, P_cam, fit.T_dst_src, used=[8], uncertainty=fit.uncertainty)
    with pytest.raises(InputError, match="min_pairs"):
        QualityParams(min_pairs=3)
    with pytest.raises(InputError, match="warn_rotation_std"):
        QualityParams(warn_rotation_std=0.01, max_rotation_std=0.001)
    assert QualityParams().outlier_k == pytest.approx(4.594, abs=0.001)


def test_axes_are_named_in_the_base_frame() -> None:
    assert axis_name([0.99, 0.11, -0.04]) == "X"
    assert axis_name([0.0, -1.0, 0.0]) == "Y"
    assert axis_name([0.6, 0.0, 0.8]) == "(+0.60, +0.00, +0.80)"
    assert axis_name([-0.6, 0.0, -0.8]) == "(+0.60, -0.00, +0.80)"
