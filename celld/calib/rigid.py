"""Rigid registration of point pairs: the closed form of Eq. 9-12 (SVD / Umeyama).

Owns the validation of point pairs where they enter a solver (shape, NaN,
count, mismatched lengths, positions that leave the rotation undetermined),
the closed-form least-squares transform between two point sets, the per-pair
residuals, and the first-order uncertainty of a fitted transform
(:class:`Uncertainty`, shared by every solver of :mod:`celld.calib`).

What the positions must be: Eq. 10-12 fix a rotation from any three
positions off one line; coplanar positions are fine (the determinant
correction of Eq. 12 picks the proper rotation when the third singular value
of Sigma is zero). Only a rank defect is refused here: positions that
coincide or lie on one line leave the rotation about that line free. How well
a solvable set fixes the rotation is a matter of degree, read from the
covariance of the solution (:mod:`celld.calib.quality`), not a refusal.

Uncertainty convention, used by every solver result of the package: a fitted
``T_a_b`` carries a (6, 6) covariance of the perturbation
``xi = [rx, ry, rz, tx, ty, tz]`` with ``T_true = (exp([r]x) R, t + dt)``:
the rotation perturbation is a rotation vector (rad) expressed in frame a,
applied on the left, and the translation perturbation is added to the
translation of ``T_a_b`` (metres, frame a). For the eye-on-base result
``T_base_cam`` the translation block is therefore the uncertainty of the
camera's position in the base frame. The covariance is
``sigma^2 (J^T J)^-1`` with ``J`` the Jacobian of the residuals at the
solution and ``sigma^2`` the residual variance with the degrees of freedom
taken out; it is a first-order (Gauss-Newton) estimate that assumes
isotropic, independent noise on the pairs and no outliers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from celld.errors import CalibrationError, InputError
from celld.schemadoc import integer, number, obj, vector
from celld.se3 import transform_from

Array = NDArray[np.float64]

# Eq. 9-12 need at least four pairs (paper, section 2.1.3, after [42]).
MIN_PAIRS = 4
# RMS spread (m) below which positions carry no direction: no scanner or robot
# resolves a micron, so positions within 1 um of a point coincide and positions
# within 1 um of a line are collinear (the rotation about it is undetermined).
MIN_SPREAD = 1e-6


@dataclass(frozen=True)
class Uncertainty:
    """First-order uncertainty of a fitted transform (see the module docstring).

    Attributes
    ----------
    covariance : (6, 6) array
        Covariance of ``[rx, ry, rz, tx, ty, tz]``, rad^2 / m^2.
    sigma : float
        Estimated per-axis noise of one residual component, metres.
    dof : int
        Degrees of freedom of the residuals (observations minus parameters).
    """

    covariance: Array
    sigma: float
    dof: int

    @property
    def rotation_std(self) -> Array:
        """Per-axis standard deviation of the rotation, rad, (3,)."""
        return np.sqrt(np.clip(np.diag(self.covariance)[:3], 0.0, None))

    @property
    def translation_std(self) -> Array:
        """Per-axis standard deviation of the translation, metres, (3,)."""
        return np.sqrt(np.clip(np.diag(self.covariance)[3:], 0.0, None))

    @property
    def rotation_error(self) -> float:
        """RMS expected rotation error, rad: sqrt of the trace of the rotation block."""
        return float(np.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0)))

    @property
    def translation_error(self) -> float:
        """RMS expected translation error, metres: sqrt of the trace of the translation block."""
        return float(np.sqrt(max(np.trace(self.covariance[3:, 3:]), 0.0)))

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (mm and deg at this boundary; :data:`UNCERTAINTY_SCHEMA` once its NaNs are nulls)."""
        return {
            "sigma_mm": self.sigma * 1e3,
            "dof": self.dof,
            "translation_std_mm": (self.translation_std * 1e3).tolist(),
            "rotation_std_deg": np.degrees(self.rotation_std).tolist(),
            "translation_error_mm": self.translation_error * 1e3,
            "rotation_error_deg": float(np.degrees(self.rotation_error)),
        }


# The JSON shape of Uncertainty.as_dict in a report (null where not finite).
UNCERTAINTY_SCHEMA = obj(
    "First-order uncertainty of the transform (celld.calib.rigid's convention); null where not finite.",
    {
        "sigma_mm": number("Noise per axis of one residual component.", null=True),
        "dof": integer("Degrees of freedom of the residuals."),
        "translation_std_mm": vector("1-sigma of the translation along x, y, z.", 3, null_items=True),
        "rotation_std_deg": vector("1-sigma of the rotation about x, y, z.", 3, null_items=True),
        "translation_error_mm": number("RMS expected translation error.", null=True),
        "rotation_error_deg": number("RMS expected rotation error.", null=True),
    },
    ("sigma_mm", "dof", "translation_std_mm", "rotation_std_deg", "translation_error_mm", "rotation_error_deg"),
)


@dataclass(frozen=True)
class RigidFit:
    """A least-squares rigid (or similarity) transform between point pairs.

    Attributes
    ----------
    T_dst_src : (4, 4) array
        Maps the source points into the destination frame (rotation and
        translation only; the scale is kept apart). For Eq. 9 it is
        ``T_base_cam``, with ``P_base`` the destination and ``P_cam`` the source.
    scale : float
        ``c`` of Eq. 11; 1.0 unless the scale was estimated.
    residuals : (n,) array
        ``|c R p_src + t - p_dst|`` per pair, metres, in pair order.
    uncertainty : Uncertainty
        Covariance of the pose of ``T_dst_src`` (module docstring).
    """

    T_dst_src: Array
    scale: float
    residuals: Array
    uncertainty: Uncertainty

    @property
    def rms(self) -> float:
        """Root mean square of the residuals, metres."""
        return float(np.sqrt(np.mean(self.residuals**2)))

    @property
    def n_pairs(self) -> int:
        return int(len(self.residuals))


def check_pairs(
    P_dst: ArrayLike,
    P_src: ArrayLike,
    *,
    names: tuple[str, str] = ("P_base", "P_cam"),
    min_pairs: int = MIN_PAIRS,
    determined: bool = True,
) -> tuple[Array, Array]:
    """Validate two (n, 3) point sets as pairs; return them as float64 arrays.

    The one validation of pairs in :mod:`celld.calib`: every solver calls it
    where its pairs enter.

    Parameters
    ----------
    P_dst, P_src : (n, 3) arrays
    names : (str, str)
        Names of the two sets in error messages.
    min_pairs : int
    determined : bool
        Also refuse positions that leave a rigid fit undetermined
        (:func:`geometry_defect`, on each set). Off only for callers that take
        pairs one at a time (Algorithm 1's online feed).

    Raises
    ------
    InputError
        Wrong shape, mismatched lengths, NaN or infinite values.
    CalibrationError
        Fewer than ``min_pairs`` pairs, or (``determined``) coincident or
        collinear positions.
    """
    out = []
    for P, name in zip((P_dst, P_src), names):
        arr = np.asarray(P, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise InputError(f"{name}: expected an (n, 3) array of positions, got shape {arr.shape}")
        finite = np.all(np.isfinite(arr), axis=1)
        if not np.all(finite):
            bad = np.flatnonzero(~finite).tolist()
            raise InputError(f"{name}: pairs {bad} contain NaN or infinite values")
        out.append(arr)
    if len(out[0]) != len(out[1]):
        raise InputError(f"{names[0]} and {names[1]}: expected the same number of pairs, got {len(out[0])} and {len(out[1])}")
    if len(out[0]) < min_pairs:
        raise CalibrationError(f"expected at least {min_pairs} pairs, got {len(out[0])}")
    if determined:
        for arr, name in zip(out, names):
            defect = geometry_defect(arr)
            if defect is not None:
                raise CalibrationError(f"{name}: {defect}")
    return out[0], out[1]


def geometry_defect(P: Array) -> str | None:
    """Say why the positions ``P`` (n, 3) leave a rigid fit undetermined, or None.

    A rank test: the RMS spread of the centred positions along their principal
    axes, ``s0 >= s1``, against :data:`MIN_SPREAD`. ``s0`` below it: the
    positions coincide (fewer than two distinct points); ``s1`` below it: they
    lie on one line (fewer than three distinct points off it), and no
    rotation about that line changes the fit. Coplanar positions pass: a plane
    spanning two directions fixes every rotation (how well is a matter of the
    covariance, :mod:`celld.calib.quality`).
    """
    P = np.asarray(P, dtype=np.float64)
    if len(P) == 0:
        return "no positions"
    centred = P - P.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    s = np.concatenate([s, np.zeros(3 - len(s))]) if len(s) < 3 else s
    spread = s / np.sqrt(len(P))
    if spread[0] < MIN_SPREAD:
        return f"all {len(P)} positions coincide (spread {spread[0] * 1e3:.3g} mm); the transform is undetermined"
    if spread[1] < MIN_SPREAD:
        return (
            f"the {len(P)} positions are collinear (spread {spread[0] * 1e3:.3g} mm along the line, "
            f"{spread[1] * 1e3:.3g} mm across it): the rotation about the line is undetermined; "
            "at least three positions off one line are needed"
        )
    return None


def umeyama(P_dst: Array, P_src: Array, with_scale: bool = False) -> tuple[Array, Array, float]:
    """Closed-form least squares ``P_dst ~ c R P_src + t`` (Eq. 10-12), unchecked.

    The caller validates the input; this kernel is also used on minimal
    three-point samples by the robust estimator.

    Returns
    -------
    R : (3, 3) array
    t : (3,) array
    c : float
        1.0 unless ``with_scale``.
    """
    n = len(P_dst)
    mu_dst = P_dst.mean(axis=0)  # Eq. 11, ^{Base}mu
    mu_src = P_src.mean(axis=0)  # Eq. 11, ^{Cam}mu
    A = P_dst - mu_dst
    B = P_src - mu_src
    Sigma = A.T @ B / n  # Eq. 11, Sigma
    U, D, Vt = np.linalg.svd(Sigma)
    # Eq. 12. The paper tests det(Sigma); det(U) det(V) has the same sign
    # when Sigma has full rank and stays defined when it does not (Umeyama 1991).
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0
    R = U @ np.diag(S) @ Vt  # Eq. 10a
    c = 1.0
    if with_scale:
        c = float(n * np.sum(D * S) / np.sum(B * B))  # Eq. 11, c = n tr(DS) / sum |p - mu|^2
    t = mu_dst - c * R @ mu_src  # Eq. 10b
    return R, t, c


def pair_residuals(T_dst_src: ArrayLike, P_dst: ArrayLike, P_src: ArrayLike, scale: float = 1.0) -> Array:
    """Per-pair distance ``|c R p_src + t - p_dst|`` (n,), metres."""
    T = np.asarray(T_dst_src, dtype=np.float64)
    P_dst = np.asarray(P_dst, dtype=np.float64)
    P_src = np.asarray(P_src, dtype=np.float64)
    return np.linalg.norm(scale * P_src @ T[:3, :3].T + T[:3, 3] - P_dst, axis=1)


def covariance_from_jacobian(J: Array, r: Array, n_params: int) -> tuple[Array, float, int]:
    """Return ``(sigma^2 (J^T J)^-1, sigma, dof)`` for stacked residuals ``r``.

    ``sigma^2 = |r|^2 / (m - n_params)``; with no redundancy (dof 0) the
    covariance is infinite. A singular ``J^T J`` also gives infinite variances.
    """
    m = len(r)
    dof = m - n_params
    if dof <= 0:
        return np.full((J.shape[1], J.shape[1]), np.inf), float("nan"), dof
    sigma2 = float(r @ r) / dof
    JtJ = J.T @ J
    try:
        cov: Array = np.asarray(np.linalg.inv(JtJ), dtype=np.float64) * sigma2
    except np.linalg.LinAlgError:
        return np.full_like(JtJ, np.inf), float(np.sqrt(sigma2)), dof
    return cov, float(np.sqrt(sigma2)), dof


def _skew_rows(V: Array) -> Array:
    """Stack of skew-symmetric matrices [v]x for each row of V, (n, 3, 3)."""
    Z = np.zeros((len(V), 3, 3))
    Z[:, 0, 1], Z[:, 0, 2] = -V[:, 2], V[:, 1]
    Z[:, 1, 0], Z[:, 1, 2] = V[:, 2], -V[:, 0]
    Z[:, 2, 0], Z[:, 2, 1] = -V[:, 1], V[:, 0]
    return Z


def rigid_jacobian(T_dst_src: Array, P_dst: Array, P_src: Array, scale: float = 1.0, with_scale: bool = False) -> tuple[Array, Array]:
    """Jacobian (3n, 6 or 7) of the stacked residuals of Eq. 9 at ``T_dst_src``, and the residuals (3n,).

    Columns: the perturbation ``[rx, ry, rz, tx, ty, tz]`` of the module
    convention, then the scale when ``with_scale``. ``(J^T J)^-1`` is the
    covariance per unit noise variance: the geometry's part of it.
    """
    R = T_dst_src[:3, :3]
    q = scale * P_src @ R.T  # c R p_src, in the dst frame
    r = (q + T_dst_src[:3, 3] - P_dst).reshape(-1)
    n = len(P_dst)
    J = np.zeros((3 * n, 7 if with_scale else 6))
    # d(c exp([w]x) R p)/dw = -[c R p]x ; d/dt = I ; d/dc = R p
    J[:, :3] = (-_skew_rows(q)).reshape(-1, 3)
    J[:, 3:6] = np.tile(np.eye(3), (n, 1))
    if with_scale:
        J[:, 6] = (P_src @ R.T).reshape(-1)
    return J, r


def rigid_uncertainty(T_dst_src: Array, P_dst: Array, P_src: Array, scale: float = 1.0, with_scale: bool = False) -> Uncertainty:
    """First-order covariance of the pose of a fitted ``T_dst_src`` (module docstring)."""
    J, r = rigid_jacobian(T_dst_src, P_dst, P_src, scale, with_scale)
    cov, sigma, dof = covariance_from_jacobian(J, r, J.shape[1])
    return Uncertainty(covariance=cov[:6, :6], sigma=sigma, dof=dof)


def solve_rigid(
    P_base: ArrayLike,
    P_cam: ArrayLike,
    *,
    with_scale: bool = False,
    names: tuple[str, str] = ("P_base", "P_cam"),
) -> RigidFit:
    """Least-squares ``T_base_cam`` from flange-centre pairs, Eq. 9-12.

    Parameters
    ----------
    P_base : (n, 3) array
        Flange centres (TCP) in the base frame, from the robot, metres.
    P_cam : (n, 3) array
        The same centres in the camera frame, from the clouds, metres.
    with_scale : bool
        Estimate the scale ``c`` of Eq. 11 (off by default: both sides are
        metric, and a free scale absorbs a range error of the scanner).
    names : (str, str)
        Names of the two sets in error messages (other frames use this solver too).

    Returns
    -------
    RigidFit
        ``T_dst_src`` is ``T_base_cam``; residuals per pair in pair order.

    Raises
    ------
    InputError
        Bad shape, NaN, mismatched lengths.
    CalibrationError
        Fewer than four pairs, or coincident / collinear positions
        (coplanar ones are solved; their conditioning is in ``uncertainty``).
    """
    P_dst, P_src = check_pairs(P_base, P_cam, names=names)
    R, t, c = umeyama(P_dst, P_src, with_scale)
    if with_scale and not c > 0.0:
        raise CalibrationError(f"scale c of Eq. 11 came out {c:.3g}: the pairs do not describe a similarity")
    T = transform_from(R, t)
    return RigidFit(
        T_dst_src=T,
        scale=c,
        residuals=pair_residuals(T, P_dst, P_src, c),
        uncertainty=rigid_uncertainty(T, P_dst, P_src, c, with_scale),
    )


def perturb(T: Array, xi: Array) -> Array:
    """Apply the perturbation ``xi = [rx, ry, rz, tx, ty, tz]`` of the module convention to ``T``."""
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix() @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + xi[3:]
    return out


def perturbation(T: Array, T_ref: Array) -> Array:
    """The ``xi`` that takes ``T_ref`` to ``T`` (inverse of :func:`perturb`), (6,)."""
    rot = Rotation.from_matrix(T[:3, :3] @ T_ref[:3, :3].T).as_rotvec()
    return np.concatenate([rot, T[:3, 3] - T_ref[:3, 3]])


def propagate(
    f: Callable[..., Array],
    transforms: Sequence[Array],
    covariances: Sequence[Array],
    step: float = 1e-6,
) -> Array:
    """First-order covariance of ``f(*transforms)`` (a (4, 4) transform).

    Each input transform carries a (6, 6) covariance in the module convention;
    the inputs are taken as independent. The Jacobian is taken by central
    differences of step ``step`` (rad or m).
    """
    T0 = f(*transforms)
    blocks = []
    for k, T in enumerate(transforms):
        Jk = np.zeros((6, 6))
        for j in range(6):
            d = np.zeros(6)
            d[j] = step
            args_p = list(transforms)
            args_m = list(transforms)
            args_p[k] = perturb(T, d)
            args_m[k] = perturb(T, -d)
            Jk[:, j] = (perturbation(f(*args_p), T0) - perturbation(f(*args_m), T0)) / (2 * step)
        blocks.append(Jk @ covariances[k] @ Jk.T)
    return np.sum(blocks, axis=0)
