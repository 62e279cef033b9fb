"""Robot-robot (co-manipulation) calibration by the decomposition of Eq. 5 into Eq. 6.

Owns the calibration of two robots sharing a camera: robot 1 carries the
camera on its flange, robot 2's flange is the feature the camera sees (the
"mark" of Eq. 5 is robot 2's flange centre, so ``T_flan2_mark`` is known).
Eq. 5 has three unknowns; the paper splits it into two standard problems and
a composition:

(a) robot 2 holds still, robot 1 moves: an eye-in-hand problem for robot 1,
    giving ``T_flan1_cam`` (and robot 2's flange centre in base 1);
(b) robot 1 holds still at ``T_base1_flan1_fixed``, robot 2 moves: an
    eye-on-base problem for robot 2 with the camera where robot 1 holds it,
    giving ``T_base2_cam`` (Eq. 9-12, robust over the pairs);
(c) ``T_base1_base2 = T_base1_flan1_fixed T_flan1_cam T_base2_cam^-1``.

When robot 2's flange pose during (a) is known, the position of its centre
found in (a) closes a loop with (c): the closure residual is reported as an
independent check.

When the camera is not on a robot but fixed (the cell's scanner above the
table) and sees both robots' flanges, (a) is not needed: both bases are
calibrated to the camera by Eq. 9-12 and (c) becomes
``T_base1_base2 = T_base1_cam T_base2_cam^-1`` (:func:`solve_shared_camera`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from celld.calib.handeye import NORMAL_WEIGHT, HandEyeFit, solve_eye_in_hand
from celld.calib.rigid import Array, Uncertainty, propagate
from celld.calib.robust import RobustFit, RobustParams, solve_robust
from celld.errors import InputError
from celld.se3 import apply, check_transform, invert


@dataclass(frozen=True)
class CoManipulationFit:
    """The three transforms of Eq. 6 and their checks.

    Attributes
    ----------
    T_flan1_cam : (4, 4) array
        Eq. 6a, robot 1's hand-eye transform.
    T_base2_cam : (4, 4) array
        Eq. 6b, the camera (held by robot 1 at its fixed pose) in robot 2's base.
    T_base1_base2 : (4, 4) array
        Eq. 6c, robot 2's base in robot 1's base.
    uncertainty : Uncertainty
        Covariance of ``T_base1_base2``, propagated to first order from (a) and (b).
    eye_in_hand : HandEyeFit
        The solve of (a), with its residuals.
    eye_on_base : RobustFit
        The solve of (b), with its residuals and rejected pairs.
    closure : float | None
        Distance between robot 2's flange centre found in (a) and the same
        centre through (c) and robot 2's reported pose, metres.
    """

    T_flan1_cam: Array
    T_base2_cam: Array
    T_base1_base2: Array
    uncertainty: Uncertainty
    eye_in_hand: HandEyeFit
    eye_on_base: RobustFit
    closure: float | None


def solve_comanipulation(
    T_base1_flan1_a: ArrayLike,
    p_cam_a: ArrayLike,
    T_base1_flan1_fixed: ArrayLike,
    T_base2_flan2_b: ArrayLike,
    p_cam_b: ArrayLike,
    *,
    n_cam_a: ArrayLike | None = None,
    T_base2_flan2_fixed_a: ArrayLike | None = None,
    ids_b: Sequence[str] | None = None,
    robust: RobustParams = RobustParams(),
    normal_weight: float = NORMAL_WEIGHT,
) -> CoManipulationFit:
    """Solve Eq. 5 by Eq. 6 (a), (b), (c).

    Parameters
    ----------
    T_base1_flan1_a : (n, 4, 4) array
        Robot 1's flange poses during (a).
    p_cam_a : (n, 3) array
        Robot 2's (still) flange centre seen by the camera during (a), m.
    T_base1_flan1_fixed : (4, 4) array
        Robot 1's flange pose during (b).
    T_base2_flan2_b : (m, 4, 4) array
        Robot 2's flange poses during (b).
    p_cam_b : (m, 3) array
        Robot 2's flange centre seen by the camera during (b), m.
    n_cam_a : (n, 3) array, optional
        Robot 2's flange normal seen during (a), for the eye-in-hand solve.
    T_base2_flan2_fixed_a : (4, 4) array, optional
        Robot 2's flange pose during (a): enables the closure check.
    ids_b : sequence of str, optional
        Pair ids of (b) for the rejection report.

    Raises
    ------
    InputError, CalibrationError
        From the two solves (too few poses, degenerate motion, bad input).
    """
    T_fixed = check_transform(T_base1_flan1_fixed, "T_base1_flan1_fixed")
    a = solve_eye_in_hand(T_base1_flan1_a, p_cam_a, n_cam_a, normal_weight=normal_weight)  # Eq. 6a
    T_b2f2 = np.asarray(T_base2_flan2_b, dtype=np.float64)
    if T_b2f2.ndim != 3 or T_b2f2.shape[1:] != (4, 4):
        raise InputError(f"T_base2_flan2_b: expected an (m, 4, 4) stack of poses, got shape {T_b2f2.shape}")
    b = solve_robust(T_b2f2[:, :3, 3], p_cam_b, ids=ids_b, params=robust)  # Eq. 6b, Eq. 9-12

    def compose(T_flan1_cam: Array, T_base2_cam: Array) -> Array:
        return T_fixed @ T_flan1_cam @ invert(T_base2_cam)  # Eq. 6c

    T_b1b2 = compose(a.T_link_cam, b.T_base_cam)
    cov = propagate(compose, [a.T_link_cam, b.T_base_cam], [a.uncertainty.covariance, b.fit.uncertainty.covariance])
    unc = Uncertainty(
        covariance=cov,
        sigma=float(np.hypot(a.uncertainty.sigma, b.fit.uncertainty.sigma)),
        dof=a.uncertainty.dof + b.fit.uncertainty.dof,
    )
    closure = None
    if T_base2_flan2_fixed_a is not None and a.p_base is not None:
        T2 = check_transform(T_base2_flan2_fixed_a, "T_base2_flan2_fixed_a")
        p_via_c = apply(T_b1b2, T2[:3, 3][None])[0]
        closure = float(np.linalg.norm(p_via_c - a.p_base))
    return CoManipulationFit(
        T_flan1_cam=a.T_link_cam,
        T_base2_cam=b.T_base_cam,
        T_base1_base2=T_b1b2,
        uncertainty=unc,
        eye_in_hand=a,
        eye_on_base=b,
        closure=closure,
    )


@dataclass(frozen=True)
class SharedCameraFit:
    """Two robots calibrated to one fixed camera, and the robot-robot transform."""

    T_base1_cam: Array
    T_base2_cam: Array
    T_base1_base2: Array
    uncertainty: Uncertainty
    robot1: RobustFit
    robot2: RobustFit


def solve_shared_camera(
    P_base1: ArrayLike,
    P_cam1: ArrayLike,
    P_base2: ArrayLike,
    P_cam2: ArrayLike,
    *,
    ids1: Sequence[str] | None = None,
    ids2: Sequence[str] | None = None,
    robust: RobustParams = RobustParams(),
) -> SharedCameraFit:
    """``T_base1_base2`` from a fixed camera that sees both robots' flanges.

    Each robot's flange centres (base frame) and their images (camera frame)
    give its ``T_base_cam`` (robust Eq. 9-12); the composition is Eq. 6c with
    the camera fixed: ``T_base1_base2 = T_base1_cam T_base2_cam^-1``, with the
    covariance propagated to first order.
    """
    f1 = solve_robust(P_base1, P_cam1, ids=ids1, params=robust)
    f2 = solve_robust(P_base2, P_cam2, ids=ids2, params=robust)
    T_b1b2, unc = robots_through_camera(f1.T_base_cam, f1.fit.uncertainty, f2.T_base_cam, f2.fit.uncertainty)
    return SharedCameraFit(f1.T_base_cam, f2.T_base_cam, T_b1b2, unc, f1, f2)


def robots_through_camera(
    T_base1_cam: ArrayLike, unc1: Uncertainty, T_base2_cam: ArrayLike, unc2: Uncertainty
) -> tuple[Array, Uncertainty]:
    """Eq. 6c with the camera fixed: ``T_base1_base2 = T_base1_cam T_base2_cam^-1``, and its uncertainty.

    The two calibrations are independent (each from its own robot's
    captures); the covariance is propagated to first order, in the
    convention of :mod:`celld.calib.rigid`.
    """
    T1 = check_transform(T_base1_cam, "T_base1_cam")
    T2 = check_transform(T_base2_cam, "T_base2_cam")

    def compose(T_b1c: Array, T_b2c: Array) -> Array:
        return T_b1c @ invert(T_b2c)  # Eq. 6c

    cov = propagate(compose, [T1, T2], [unc1.covariance, unc2.covariance])
    unc = Uncertainty(covariance=cov, sigma=float(np.hypot(unc1.sigma, unc2.sigma)), dof=unc1.dof + unc2.dof)
    return compose(T1, T2), unc


def point_std(T_a_b: ArrayLike, unc: Uncertainty, p_b: ArrayLike) -> Array:
    """1-sigma (3,) along frame a's axes of the point ``p_b`` placed by ``T_a_b``, m.

    In the convention of :mod:`celld.calib.rigid` the rotation perturbs about
    frame a's origin, so a point far from it (robot 2's workspace seen from
    base 1) takes the rotation's error times its lever.
    """
    T = check_transform(T_a_b, "T_a_b")
    lever = T[:3, :3] @ np.asarray(p_b, dtype=np.float64).reshape(3)
    J = np.hstack([-np.cross(np.eye(3), lever), np.eye(3)])  # d(T p) / d[w, t]: w x lever + t
    cov = J @ unc.covariance @ J.T
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))
