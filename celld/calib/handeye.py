"""Eye-in-hand and eye-on-arm calibration from flange features (Eq. 1, 3, 7, 8).

Owns the two moving-camera configurations of section 2.1.1, solved from the
point features this project detects (a flange centre, optionally its normal)
rather than from marker poses:

- Camera on a robot link, looking at a feature fixed in the base frame
  (eye-in-hand, Eq. 1 and 3, with the link the flange; eye-on-arm first case,
  Eq. 7, with the link an arm link). Unknowns: ``T_link_cam`` and the
  feature's position (and normal) in the base frame. Per pose ``i``::

      T_base_link_i T_link_cam p_cam_i = p_base            (3 equations)
      R_base_link_i R_link_cam n_cam_i = n_base            (with normals)

- Camera on an arm link, looking at the robot's own flange (eye-on-arm second
  case, Eq. 8). The flange centre's position in the base frame is the TCP,
  so ``p_arm_i = T_base_arm_i^-1 p_base_i`` is known and ``T_arm_cam`` is the
  rigid fit of Eq. 9-12 in the arm frame; normals add the flange axis.

Both are solved by nonlinear least squares on SE(3)
(:func:`scipy.optimize.least_squares`, perturbation ``exp([w]x) R, t + dt``)
started from a closed form: for the fixed feature, the linear system in
``vec(R)``, ``t`` and ``p_base`` (DLT-like) projected onto SO(3); for Eq. 8,
Eq. 9-12. Results carry per-pose residuals and the covariance of
``T_link_cam`` in the convention of :mod:`celld.calib.rigid`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from celld.calib.rigid import (
    MIN_PAIRS,
    Array,
    Uncertainty,
    covariance_from_jacobian,
    solve_rigid,
)
from celld.errors import CalibrationError, InputError
from celld.se3 import check_transform, invert, transform_from

# Weight of a normal residual (unit vectors) against a position residual, m/rad:
# about a flange-face plane fit's centre noise over its normal noise.
NORMAL_WEIGHT = 0.03
# Robot rotations must span at least two axes: second singular value of the
# relative rotation vectors above this, rad.
MIN_ROTATION_SPREAD = 0.02
# Condition number of J^T J above which the poses do not determine the unknowns.
MAX_CONDITION = 1e12


@dataclass(frozen=True)
class HandEyeFit:
    """A moving-camera calibration.

    Attributes
    ----------
    T_link_cam : (4, 4) array
        Pose of the camera on its link: ``T_flange_cam`` (eye-in-hand) or
        ``T_arm_cam`` (eye-on-arm).
    p_base : (3,) array | None
        The fixed feature's position in the base frame (None for Eq. 8).
    n_base : (3,) array | None
        The fixed feature's normal in the base frame, when normals were given.
    residuals : (n,) array
        Position residual per pose, metres, in pose order.
    normal_residuals : (n,) array | None
        Angle between predicted and observed normal per pose, rad.
    uncertainty : Uncertainty
        Covariance of ``T_link_cam`` (the other unknowns marginalised).
    T_closed_form : (4, 4) array
        The closed-form start of the nonlinear solve.
    n_evaluations : int
    """

    T_link_cam: Array
    p_base: Array | None
    n_base: Array | None
    residuals: Array
    normal_residuals: Array | None
    uncertainty: Uncertainty
    T_closed_form: Array
    n_evaluations: int

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))


def _check_poses(T_base_link: ArrayLike, name: str) -> Array:
    T = np.asarray(T_base_link, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"{name}: expected an (n, 4, 4) stack of poses, got shape {T.shape}")
    for i, Ti in enumerate(T):
        check_transform(Ti, f"{name}[{i}]")
    return T


def _check_optional(V: ArrayLike | None, n: int, name: str, unit: bool = False) -> Array | None:
    return None if V is None else _check_vectors(V, n, name, unit)


def _check_vectors(V: ArrayLike, n: int, name: str, unit: bool = False) -> Array:
    arr = np.asarray(V, dtype=np.float64)
    if arr.shape != (n, 3):
        raise InputError(f"{name}: expected shape ({n}, 3) to match the poses, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: pairs {np.flatnonzero(~np.all(np.isfinite(arr), axis=1)).tolist()} contain NaN")
    if unit:
        norms = np.linalg.norm(arr, axis=1)
        if np.any(norms < 1e-9):
            raise InputError(f"{name}: zero-length normals at {np.flatnonzero(norms < 1e-9).tolist()}")
        arr = arr / norms[:, None]
    return arr


def _check_rotation_spread(R: Array, what: str) -> None:
    """Refuse poses whose rotations do not span two axes (the translation is then undetermined)."""
    rel = Rotation.from_matrix(R[1:] @ R[0].T).as_rotvec() if len(R) > 1 else np.zeros((0, 3))
    s = np.linalg.svd(rel, compute_uv=False) if len(rel) else np.zeros(1)
    spread = s[1] / np.sqrt(len(rel)) if len(s) > 1 else 0.0
    if spread < MIN_ROTATION_SPREAD:
        raise CalibrationError(
            f"{what}: the {len(R)} poses rotate about fewer than two axes (spread {np.degrees(spread):.2f} deg "
            f"about the second axis, at least {np.degrees(MIN_ROTATION_SPREAD):.2f} deg needed); rotate the link about two axes"
        )


def _project_so3(M: Array) -> Array:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def _numeric_jacobian(fun: Callable[[Array], Array], x: Array, step: float = 1e-7) -> Array:
    f0 = fun(x)
    J = np.zeros((len(f0), len(x)))
    for j in range(len(x)):
        d = np.zeros_like(x)
        d[j] = step
        J[:, j] = (fun(x + d) - fun(x - d)) / (2 * step)
    return J


def _solve(
    fun_factory: Callable[[Array], Callable[[Array], Array]],
    T0: Array,
    extra0: Array,
) -> tuple[Array, Array, Array, int, Array]:
    """Least squares over ``[w, dt, extra]`` around ``T0``; return T, extra, residuals, nfev, J at the optimum."""
    fun = fun_factory(T0)
    x0 = np.concatenate([np.zeros(6), extra0])
    sol = least_squares(fun, x0, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
    w, dt, extra = sol.x[:3], sol.x[3:6], sol.x[6:]
    T = transform_from(Rotation.from_rotvec(w).as_matrix() @ T0[:3, :3], T0[:3, 3] + dt)
    # Jacobian in the module convention: re-linearise around the optimum.
    fun_hat = fun_factory(T)
    x_hat = np.concatenate([np.zeros(6), extra])
    J = _numeric_jacobian(fun_hat, x_hat)
    return T, extra, fun_hat(x_hat), int(sol.nfev), J


def _uncertainty(J: Array, r: Array) -> Uncertainty:
    JtJ = J.T @ J
    ev = np.linalg.eigvalsh(JtJ)
    if ev[0] <= ev[-1] / MAX_CONDITION:
        raise CalibrationError(
            f"the poses do not determine the unknowns (condition number of J^T J {ev[-1] / max(ev[0], 1e-300):.3g}); "
            "vary the link's position and orientation more"
        )
    cov, sigma, dof = covariance_from_jacobian(J, r, J.shape[1])
    return Uncertainty(covariance=cov[:6, :6], sigma=sigma, dof=dof)


def solve_eye_in_hand(
    T_base_link: ArrayLike,
    p_cam: ArrayLike,
    n_cam: ArrayLike | None = None,
    *,
    normal_weight: float = NORMAL_WEIGHT,
) -> HandEyeFit:
    """Camera on a link, fixed feature: ``T_link_cam`` and ``p_base`` (Eq. 1, 3, 7).

    Parameters
    ----------
    T_base_link : (n, 4, 4) array
        Pose of the link carrying the camera at each capture (the flange for
        eye-in-hand, an arm link for Eq. 7).
    p_cam : (n, 3) array
        The fixed feature (e.g. a flange centre held still) seen in the camera, m.
    n_cam : (n, 3) array, optional
        Its normal seen in the camera (unit vectors).
    normal_weight : float
        Metres per radian of a normal residual.

    Raises
    ------
    InputError
        Bad shapes, NaN, non-rigid poses.
    CalibrationError
        Fewer than 4 poses (5 without normals), rotations about fewer than
        two axes, or poses that leave the unknowns undetermined.
    """
    T = _check_poses(T_base_link, "T_base_link")
    n = len(T)
    P = _check_vectors(p_cam, n, "p_cam")
    N = _check_optional(n_cam, n, "n_cam", unit=True)
    need = MIN_PAIRS if N is not None else 5
    if n < need:
        raise CalibrationError(f"eye-in-hand: expected at least {need} poses{'' if N is not None else ' without normals'}, got {n}")
    R_i, t_i = T[:, :3, :3], T[:, :3, 3]
    _check_rotation_spread(R_i, "eye-in-hand")

    # Closed form: R_i (p_i^T kron I) vec(R) + R_i t - p_base = -t_i (vec column-major),
    # and R_i (n_i^T kron I) vec(R) - n_base = 0 with normals.
    n_unknown = 15 + (3 if N is not None else 0)
    rows, rhs = [], []
    for i in range(n):
        A = np.zeros((3, n_unknown))
        A[:, :9] = R_i[i] @ np.kron(P[i][None, :], np.eye(3))
        A[:, 9:12] = R_i[i]
        A[:, 12:15] = -np.eye(3)
        rows.append(A)
        rhs.append(-t_i[i])
        if N is not None:
            B = np.zeros((3, n_unknown))
            B[:, :9] = normal_weight * R_i[i] @ np.kron(N[i][None, :], np.eye(3))
            B[:, 15:18] = -normal_weight * np.eye(3)
            rows.append(B)
            rhs.append(np.zeros(3))
    A_all, b_all = np.vstack(rows), np.concatenate(rhs)
    x_lin, *_ = np.linalg.lstsq(A_all, b_all, rcond=None)
    R0 = _project_so3(x_lin[:9].reshape(3, 3, order="F"))
    # Re-solve t and p_base with R fixed: R_i t - p_base = -t_i - R_i R0 p_i.
    A_t = np.hstack([R_i.reshape(-1, 3), -np.tile(np.eye(3), (n, 1))])
    b_t = (-t_i - np.einsum("nij,jk,nk->ni", R_i, R0, P)).reshape(-1)
    tp, *_ = np.linalg.lstsq(A_t, b_t, rcond=None)
    T0 = transform_from(R0, tp[:3])
    extra0 = tp[3:6]
    if N is not None:
        n0 = np.mean(np.einsum("nij,jk,nk->ni", R_i, R0, N), axis=0)
        extra0 = np.concatenate([extra0, n0 / np.linalg.norm(n0)])

    def factory(T_ref: Array) -> Callable[[Array], Array]:
        R_ref, t_ref = T_ref[:3, :3], T_ref[:3, 3]

        def fun(x: Array) -> Array:
            R = Rotation.from_rotvec(x[:3]).as_matrix() @ R_ref
            t = t_ref + x[3:6]
            q = np.einsum("nij,nj->ni", R_i, P @ R.T + t) + t_i - x[6:9]
            if N is None:
                return q.reshape(-1)
            nb = x[9:12] / np.linalg.norm(x[9:12])
            m = np.einsum("nij,nj->ni", R_i, N @ R.T) - nb
            return np.concatenate([q.reshape(-1), normal_weight * m.reshape(-1)])

        return fun

    T_hat, extra, r, nfev, J = _solve(factory, T0, extra0)
    if N is not None:
        # The normal is a unit vector: its length direction is no parameter.
        nb = extra[3:6] / np.linalg.norm(extra[3:6])
        J = np.hstack([J[:, :9], _tangent_jacobian(J[:, 9:12], nb)])
    unc = _uncertainty(J, r)
    pos = r[: 3 * n].reshape(n, 3)
    nres = None
    n_base = None
    if N is not None:
        n_base = extra[3:6] / np.linalg.norm(extra[3:6])
        pred = np.einsum("nij,nj->ni", R_i, N @ T_hat[:3, :3].T)
        nres = np.arccos(np.clip(pred @ n_base, -1.0, 1.0))
    return HandEyeFit(
        T_link_cam=T_hat,
        p_base=extra[:3].copy(),
        n_base=n_base,
        residuals=np.linalg.norm(pos, axis=1),
        normal_residuals=nres,
        uncertainty=unc,
        T_closed_form=T0,
        n_evaluations=nfev,
    )


def _tangent_jacobian(J_n: Array, nb: Array) -> Array:
    """Restrict the Jacobian columns of a unit-vector parameter to its 2-D tangent plane."""
    a = np.array([1.0, 0.0, 0.0]) if abs(nb[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(nb, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nb, e1)
    return J_n @ np.column_stack([e1, e2])


def solve_eye_on_arm(
    T_base_arm: ArrayLike,
    T_base_flange: ArrayLike,
    p_cam: ArrayLike,
    n_cam: ArrayLike | None = None,
    *,
    normal_weight: float = NORMAL_WEIGHT,
) -> HandEyeFit:
    """Camera on an arm link looking at the robot's own flange: ``T_arm_cam`` (Eq. 8).

    Parameters
    ----------
    T_base_arm : (n, 4, 4) array
        Pose of the arm link carrying the camera at each capture.
    T_base_flange : (n, 4, 4) array
        Pose of the flange at each capture (its origin is the flange centre).
    p_cam : (n, 3) array
        The flange centre seen in the camera, metres.
    n_cam : (n, 3) array, optional
        The flange normal (+z of the flange) seen in the camera.

    Raises
    ------
    InputError, CalibrationError
        As :func:`~celld.calib.rigid.solve_rigid` (the flange positions in the
        arm frame must not be collinear; coplanar ones are fine).
    """
    Ta = _check_poses(T_base_arm, "T_base_arm")
    Tf = _check_poses(T_base_flange, "T_base_flange")
    if len(Ta) != len(Tf):
        raise InputError(f"T_base_arm and T_base_flange: expected the same number of poses, got {len(Ta)} and {len(Tf)}")
    n = len(Ta)
    P = _check_vectors(p_cam, n, "p_cam")
    N = _check_optional(n_cam, n, "n_cam", unit=True)
    T_arm_flange = np.einsum("nij,njk->nik", np.array([invert(T) for T in Ta]), Tf)
    P_arm = T_arm_flange[:, :3, 3]
    fit0 = solve_rigid(P_arm, P, names=("P_arm", "p_cam"))  # Eq. 9-12 in the arm frame
    Z_arm = T_arm_flange[:, :3, 2]

    def factory(T_ref: Array) -> Callable[[Array], Array]:
        R_ref, t_ref = T_ref[:3, :3], T_ref[:3, 3]

        def fun(x: Array) -> Array:
            R = Rotation.from_rotvec(x[:3]).as_matrix() @ R_ref
            q = P @ R.T + t_ref + x[3:6] - P_arm
            if N is None:
                return q.reshape(-1)
            m = N @ R.T - Z_arm
            return np.concatenate([q.reshape(-1), normal_weight * m.reshape(-1)])

        return fun

    T_hat, _, r, nfev, J = _solve(factory, fit0.T_dst_src, np.zeros(0))
    unc = _uncertainty(J, r)
    nres = None
    if N is not None:
        nres = np.arccos(np.clip(np.sum((N @ T_hat[:3, :3].T) * Z_arm, axis=1), -1.0, 1.0))
    return HandEyeFit(
        T_link_cam=T_hat,
        p_base=None,
        n_base=None,
        residuals=np.linalg.norm(r[: 3 * n].reshape(n, 3), axis=1),
        normal_residuals=nres,
        uncertainty=unc,
        T_closed_form=fit0.T_dst_src,
        n_evaluations=nfev,
    )
