"""The range bias of a time-of-flight camera on metal, estimated with ``T_base_cam``.

Owns the model of the bias, its measurement in one capture, and the joint
least squares of ``(R, t, b)``.

The model: a time-of-flight camera (Azure Kinect) reads a return from bare
metal long by ``b`` (multipath), a return from paint as it is. A point
measured on metal ``p`` is the true point moved along its own ray, so the
truth is ``p - b p / |p|`` (:func:`correct_range_bias`): measured and true
point share the ray, and the correction needs nothing but ``b``. It is not a
rigid motion: the displacement follows each ray, and that is what makes ``b``
observable at all. ``b`` is the metal's bias relative to paint; the camera's
own factory calibration is taken as right on diffuse paint.

Two kinds of observations fix ``b``, both from the session alone (no ground
truth, no nominal camera pose):

1. **The finish step, per capture** (:func:`measure_finish_step`). The metal
   face of a UR flange stands ``thickness`` (6.5 mm) above the painted
   shoulder of the wrist around it, a fact of the robot's geometry. The
   camera reads the face ``b cos(theta)`` lower (``theta`` the angle between
   the ray and the flange axis), the shoulder as it is: one capture gives
   ``b = (thickness - step) / cos(theta)`` from hundreds of points on each
   surface, about 0.1 mm apart from the face's and shoulder's noise.
2. **The spread of the rays, over the pairs.** When the detected centre lies
   on metal (the 63 mm face circle, or a bare-metal wrist), Eq. 9 holds for
   the corrected centre: ``P_base_i = R (p_i - b u_i) + t`` with ``u_i`` the
   unit ray of ``p_i``. The part of ``b u_i`` common to every pair is a
   translation and goes into ``t``; only the spread of the ray directions
   across the workspace separates ``b`` from ``t``. Over a 0.3 m wide
   workspace seen from 0.7 m the rays spread by about +-0.2 rad, so ``b`` is
   fixed about five times worse than one centre per axis divided by the
   square root of the number of pairs: with the Azure Kinect's 1 mm centres
   and 20 pairs, 1-1.5 mm (1-sigma), against the 0.03 mm of twenty finish
   steps. That figure is reported (:attr:`RangeBiasFit.sigma_from_pairs`),
   and the quality gate refuses a bias fixed worse than its limit.

On the 90 mm wrist circle (``ur10e-wrist``) of a painted wrist the centres
lie on paint: the pairs say nothing about ``b`` and the joint solve separates
into the rigid fit of Eq. 9-12 and the weighted mean of the steps; on the
face circle both kinds of observations enter one least squares
(:func:`solve_range_bias`, ``scipy.optimize.least_squares``), weighted by
their noise, each estimated from its own residuals.

The estimated ``b`` is part of the calibration: the daemon moves every
scanner point it places with ``T_base_cam`` back along its ray by ``b``
(a weld's scan of a metal part on a steel table). A metal that biases
differently from the flange's (another finish, another alloy) is a residual
error this model does not see.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import norm

from celld.calib.flange import FlangeModel
from celld.calib.rigid import Array, Uncertainty, check_pairs, solve_rigid
from celld.calib.robust import RobustFit, RobustParams, solve_robust
from celld.errors import CalibrationError, InputError
from celld.schemadoc import array, boolean, const, integer, number, obj, string
from celld.se3 import transform_from

# Modes of the calibration's range_bias setting.
MODES = ("estimate", "none")
# Radial bands of the finish step, trimmed by this fraction of their width at
# each edge: a metal point read b long at an incidence theta moves b sin(theta)
# sideways (4 mm at 8 mm and 0.5 rad), and the edges hold mixed pixels.
_BAND_TRIM = 0.2
# Heights beyond this from the flange centre are not the flange (the table), m.
_STEP_WINDOW = 0.03
# Points of a capture's window a finish step looks at, at most (an even stride).
_STEP_POINTS = 20_000
# Fewest points on each surface of a finish step.
_MIN_BAND_POINTS = 30
# A surface's height: the mean within this many noise scales, iterated (at most this often).
_LEVEL_WINDOW = 2.0
_LEVEL_ROUNDS = 10
# The standard error of that mean is taken this much above the spread of the
# values kept divided by sqrt(n): a window at 2 sigma trims the Gaussian's tails.
_TRUNCATION_SLACK = 1.15
# Gaussian sigma from a median absolute deviation.
_MAD_TO_SIGMA = 1.4826
# Rays steeper than this against the flange axis (cos) give no step.
_MIN_COS = 0.3


@dataclass(frozen=True)
class FinishStep:
    """The metal face's height above the painted shoulder as one capture measured it (metres).

    Attributes
    ----------
    measured : float
        Median height of the face band above the median height of the
        shoulder band, along the flange axis.
    nominal : float
        The model's (``FlangeModel.finish_step``).
    std : float
        1-sigma of ``measured`` from the spread of the two bands.
    cos_incidence : float
        Cosine of the angle between the ray to the flange centre and the flange axis.
    n_metal, n_painted : int
        Points on each band.
    """

    measured: float
    nominal: float
    std: float
    cos_incidence: float
    n_metal: int
    n_painted: int

    @property
    def bias(self) -> float:
        """The range bias on metal this step says, m: ``(nominal - measured) / cos(theta)``."""
        return (self.nominal - self.measured) / self.cos_incidence

    @property
    def bias_std(self) -> float:
        """1-sigma of :attr:`bias`, m."""
        return self.std / self.cos_incidence

    def as_dict(self) -> dict[str, float | int]:
        """JSON-ready (mm at this boundary)."""
        return {
            "measured_mm": self.measured * 1e3,
            "nominal_mm": self.nominal * 1e3,
            "std_mm": self.std * 1e3,
            "cos_incidence": self.cos_incidence,
            "bias_mm": self.bias * 1e3,
            "n_metal": self.n_metal,
            "n_painted": self.n_painted,
        }


def measure_finish_step(points: ArrayLike, centre: ArrayLike, normal: ArrayLike, flange: FlangeModel) -> FinishStep | None:
    """The finish step of one capture around a detected flange (module docstring, item 1).

    Parameters
    ----------
    points : (n, 3) or (H, W, 3) array
        Camera-frame points around the flange, metres; non-finite ones are skipped.
    centre : (3,) array
        The flange centre (face centre) in the camera frame, metres.
    normal : (3,) array
        The flange axis, either sign.
    flange : FlangeModel

    Returns
    -------
    FinishStep or None
        None when the flange has no painted shoulder to see
        (``flange.finish_step``), the view is too steep, or either band
        holds fewer than 30 points.
    """
    nominal = flange.finish_step
    if nominal is None:
        return None
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    n = n / np.linalg.norm(n)
    up = n if n @ c < 0 else -n  # flange +z, toward the camera
    cos_inc = float(abs(up @ c) / np.linalg.norm(c))
    if cos_inc < _MIN_COS:
        return None
    P_all: np.ndarray = np.asarray(points).reshape(-1, 3)
    # A structured-light window holds 10^5 points: an even stride keeps a few
    # thousand per surface, plenty for its 0.1 mm noise; then only the points
    # within reach of the flange, cut in the cloud's own dtype (NaN compares false).
    P_all = P_all[:: max(1, len(P_all) // _STEP_POINTS)]
    reach = flange.wrist_diameter / 2 + _STEP_WINDOW
    with np.errstate(invalid="ignore"):
        near_c = np.einsum("ij,ij->i", P_all - c.astype(P_all.dtype), P_all - c.astype(P_all.dtype)) <= reach * reach
    d = P_all[near_c].astype(np.float64) - c
    h = d @ up
    rho = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))
    near = np.abs(h) < _STEP_WINDOW

    def band(r0: float, r1: float) -> np.ndarray:
        trim = _BAND_TRIM * (r1 - r0)
        return h[near & (rho > r0 + trim) & (rho < r1 - trim)]

    metal = band(flange.bore_diameter / 2, flange.face_radius)
    painted = band(flange.outer_diameter / 2, flange.wrist_diameter / 2)
    if len(metal) < _MIN_BAND_POINTS or len(painted) < _MIN_BAND_POINTS:
        return None
    hm, sm = _level(metal)
    hp, sp = _level(painted)
    return FinishStep(hm - hp, float(nominal), math.hypot(sm, sp), cos_inc, len(metal), len(painted))


def _level(h: np.ndarray) -> tuple[float, float]:
    """The height of one surface from its points' heights ``h`` (n,): its value and standard error, m.

    The mean within two noise scales, iterated from the median: the face of
    a flange holds the threaded holes, and mixed pixels at its edges read
    lower; both lie on one side and would pull a plain median by a few
    tenths of a millimetre.
    """
    centre = float(np.median(h))
    scale = _MAD_TO_SIGMA * float(np.median(np.abs(h - centre)))
    inside = h
    for _ in range(_LEVEL_ROUNDS):
        inside = h[np.abs(h - centre) <= _LEVEL_WINDOW * scale] if scale > 0.0 else h
        if len(inside) == 0:
            break
        new = float(np.mean(inside))
        if abs(new - centre) <= 1e-3 * max(scale, 1e-9):
            centre = new
            break
        centre = new
    n = max(len(inside), 1)
    spread = float(np.std(inside)) if len(inside) > 1 else scale
    return centre, _TRUNCATION_SLACK * spread / math.sqrt(n)


def correct_range_bias(P_cam: ArrayLike, bias: float, mask: ArrayLike | None = None) -> Array:
    """Points moved back along their rays by ``bias``: ``p - b p / |p|`` (module docstring).

    Parameters
    ----------
    P_cam : (..., 3) array
        Camera-frame points, metres; NaN (no return) stays NaN, and a point
        at the camera's origin stays where it is.
    bias : float
        The range bias on metal, metres.
    mask : (...) bool array, optional
        The points to correct (the metal ones); default all.

    Returns
    -------
    (..., 3) float64 array
        A new array; the input is not modified.
    """
    P = np.array(P_cam, dtype=np.float64)
    if P.shape[-1:] != (3,):
        raise InputError(f"P_cam: expected points (..., 3), got shape {P.shape}")
    if not math.isfinite(bias):
        raise InputError(f"bias: expected a finite range bias in metres, got {bias!r}")
    if bias == 0.0:
        return P
    r = np.linalg.norm(P, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where(r > 0.0, bias * P / r, 0.0)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != P.shape[:-1]:
            raise InputError(f"mask: expected shape {P.shape[:-1]}, got {m.shape}")
        shift = np.where(m[..., None], shift, 0.0)
    return P - shift


@dataclass(frozen=True)
class RangeBiasData:
    """What a session says about the range bias, beside its centre pairs.

    Attributes
    ----------
    centres_on_metal : bool
        The detected centres lie on bare metal (``FlangeModel.circle_on_metal``):
        they read long by ``b`` along their rays.
    step_bias : (n,) array
        Per pair, the bias its finish step says (:attr:`FinishStep.bias`), m;
        NaN for a pair without one.
    step_std : (n,) array
        Their 1-sigma, m; NaN where there is no step.
    """

    centres_on_metal: bool
    step_bias: Array
    step_std: Array

    @classmethod
    def from_steps(cls, centres_on_metal: bool, steps: Sequence[FinishStep | None]) -> RangeBiasData:
        """From the pairs' finish steps (None for a pair without one)."""
        b = np.array([math.nan if s is None else s.bias for s in steps], dtype=np.float64)
        s = np.array([math.nan if s is None else s.bias_std for s in steps], dtype=np.float64)
        return cls(bool(centres_on_metal), b, s)

    @property
    def n_steps(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.step_bias)))

    def subset(self, index: Sequence[int] | np.ndarray) -> RangeBiasData:
        """The data of the pairs ``index``, in that order."""
        idx = np.asarray(index, dtype=np.int64)
        return replace(self, step_bias=self.step_bias[idx], step_std=self.step_std[idx])


@dataclass(frozen=True)
class RejectedStep:
    """A finish step left out of the estimate: its pair, the bias it said (m) and why."""

    id: str
    bias: float
    reason: str


@dataclass(frozen=True)
class RangeBiasFit:
    """The joint least squares of ``(R, t, b)`` (module docstring).

    Attributes
    ----------
    T_base_cam : (4, 4) array
    bias : float
        The range bias on metal, m (positive: metal reads long).
    bias_std : float
        Its 1-sigma, m, from both kinds of observations.
    sigma_from_pairs : float
        The 1-sigma the centre pairs alone would give ``b`` (with ``R`` and
        ``t`` free), m; infinite when the centres lie on paint.
    sigma_from_steps : float
        The 1-sigma the finish steps alone give, m; infinite without steps.
    centres_on_metal : bool
    n_pairs : int
        Pairs in the solve.
    step_ids : tuple of str
        Pairs whose finish step entered the solve.
    rejected_steps : tuple of RejectedStep
        Finish steps left out as outliers.
    pair_sigma : float
        Noise per axis of a centre, from the pair residuals, m.
    step_sigma : float
        Noise of one step's bias, from the steps' spread (never below their
        own reported 1-sigma), m; NaN without steps.
    uncertainty : Uncertainty
        Of ``T_base_cam`` (convention of :mod:`celld.calib.rigid`), with the
        bias's own uncertainty taken into account.
    covariance : (7, 7) array
        Of ``[rx, ry, rz, tx, ty, tz, b]``.
    residuals : (n,) array
        ``|R (p_i - k b u_i) + t - P_base_i|`` per pair, m.
    P_cam_corrected : (n, 3) array
        The centres corrected for the bias (unchanged when they lie on paint).
    """

    T_base_cam: Array
    bias: float
    bias_std: float
    sigma_from_pairs: float
    sigma_from_steps: float
    centres_on_metal: bool
    n_pairs: int
    step_ids: tuple[str, ...]
    rejected_steps: tuple[RejectedStep, ...]
    pair_sigma: float
    step_sigma: float
    uncertainty: Uncertainty
    covariance: Array
    residuals: Array
    P_cam_corrected: Array

    @property
    def source(self) -> str:
        """Where ``b`` comes from: ``"steps"``, ``"pairs"`` or ``"steps+pairs"``."""
        parts = [name for name, s in (("steps", self.sigma_from_steps), ("pairs", self.sigma_from_pairs)) if math.isfinite(s)]
        return "+".join(parts)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready (mm at this boundary; None where not finite; :data:`RANGE_BIAS_SCHEMA`)."""

        def mm(x: float) -> float | None:
            return x * 1e3 if math.isfinite(x) else None

        return {
            "mode": "estimate",
            "bias_mm": self.bias * 1e3,
            "std_mm": mm(self.bias_std),
            "source": self.source,
            "sigma_from_pairs_mm": mm(self.sigma_from_pairs),
            "sigma_from_steps_mm": mm(self.sigma_from_steps),
            "centres_on_metal": self.centres_on_metal,
            "n_pairs": self.n_pairs,
            "n_steps": len(self.step_ids),
            "step_sigma_mm": mm(self.step_sigma),
            "pair_sigma_mm": mm(self.pair_sigma),
            "rejected_steps": [{"id": r.id, "bias_mm": r.bias * 1e3, "reason": r.reason} for r in self.rejected_steps],
        }


# The JSON shape of RangeBiasFit.as_dict.
RANGE_BIAS_SCHEMA = obj(
    "The range bias on metal estimated with the transform (mode estimate); null where not finite.",
    {
        "mode": const("estimate"),
        "bias_mm": number("The range bias on metal (positive: metal reads long)."),
        "std_mm": number("Its 1-sigma.", null=True),
        "source": string("What fixed it: steps, pairs, or steps+pairs."),
        "sigma_from_pairs_mm": number("The 1-sigma the centre pairs alone would give.", null=True),
        "sigma_from_steps_mm": number("The 1-sigma the finish steps alone give.", null=True),
        "centres_on_metal": boolean(),
        "n_pairs": integer(lo=0),
        "n_steps": integer(lo=0),
        "step_sigma_mm": number(null=True),
        "pair_sigma_mm": number(null=True),
        "rejected_steps": array(
            obj("A finish step left out.", {"id": string(), "bias_mm": number(), "reason": string()}, ("id", "bias_mm", "reason"))
        ),
    },
    (
        "mode",
        "bias_mm",
        "std_mm",
        "source",
        "sigma_from_pairs_mm",
        "sigma_from_steps_mm",
        "centres_on_metal",
        "n_pairs",
        "n_steps",
        "step_sigma_mm",
        "pair_sigma_mm",
        "rejected_steps",
    ),
)


def _unit_rays(P: Array) -> Array:
    return P / np.linalg.norm(P, axis=1, keepdims=True)


def _steps(ids: tuple[str, ...], data: RangeBiasData, alpha: float) -> tuple[np.ndarray, float, tuple[RejectedStep, ...]]:
    """The usable steps (mask), their common noise and the outliers left out.

    A step more than ``k`` noise scales from the median (``k`` from a
    two-sided Gaussian tail ``alpha``) is an outlier: an occluded shoulder,
    a wrong face. The noise is the steps' spread, never below the median of
    their own 1-sigma (a few steps may agree by chance).
    """
    b, s = data.step_bias, data.step_std
    ok = np.isfinite(b) & np.isfinite(s)
    if not np.any(ok):
        return ok, math.nan, ()
    floor = float(np.median(s[ok]))
    med = float(np.median(b[ok]))
    scale = max(_MAD_TO_SIGMA * float(np.median(np.abs(b[ok] - med))), floor)
    k = float(norm.isf(alpha / 2))
    out = ok & (np.abs(b - med) > k * scale)
    keep = ok & ~out
    spread = float(np.std(b[keep], ddof=1)) if np.count_nonzero(keep) >= 3 else 0.0
    sigma = max(spread, floor)
    rejected = tuple(
        RejectedStep(
            ids[i],
            float(b[i]),
            f"bias {b[i] * 1e3:.2f} mm is {abs(b[i] - med) / scale:.1f} noise scales from the median {med * 1e3:.2f} mm",
        )
        for i in np.flatnonzero(out)
    )
    return keep, sigma, rejected


def _rotation(w: Array, R0: Array) -> Array:
    return Rotation.from_rotvec(w).as_matrix() @ R0


def solve_range_bias(
    P_base: ArrayLike,
    P_cam: ArrayLike,
    data: RangeBiasData,
    *,
    ids: Sequence[str] | None = None,
    pair_sigma: float | None = None,
    alpha: float = 1e-4,
) -> RangeBiasFit:
    """Joint least squares of ``T_base_cam`` and the range bias ``b`` (module docstring).

    Residuals, each divided by its noise: per pair the three components of
    ``R (p_i - k b u_i) + t - P_base_i`` (Eq. 9 with the centre corrected
    along its ray; ``k`` is 1 when the centres lie on metal, else 0), and per
    finish step ``b - b_i``. The pair noise is estimated from the pair
    residuals (starting from ``pair_sigma`` if given), the step noise from
    the steps' spread; outlying steps are left out first.

    Parameters
    ----------
    P_base, P_cam : (n, 3) arrays
        Flange centres in the base and camera frames, metres (consistent
        pairs: run a robust solve first, :func:`solve_robust_range_bias`).
    data : RangeBiasData
        For the same pairs.
    ids : sequence of str, optional
        Pair ids for the report.
    pair_sigma : float, optional
        A first noise per axis of the centres, m (default: the rigid fit's).
    alpha : float
        Probability that a good finish step is left out as an outlier.

    Raises
    ------
    InputError
        Malformed pairs or data of another length.
    CalibrationError
        Fewer than four pairs, positions that leave the rotation free, or no
        observation of ``b`` at all (centres on paint and no finish step).
    """
    P_b, P_c = check_pairs(P_base, P_cam)
    n = len(P_b)
    ids_t = tuple(str(i) for i in range(n)) if ids is None else tuple(str(i) for i in ids)
    if len(ids_t) != n:
        raise InputError(f"ids: expected {n} pair ids, got {len(ids_t)}")
    if data.step_bias.shape != (n,) or data.step_std.shape != (n,):
        raise InputError(f"range bias data: expected {n} steps, got {data.step_bias.shape} and {data.step_std.shape}")
    if not 0.0 < alpha < 0.5:
        raise InputError(f"alpha: expected 0 < alpha < 0.5, got {alpha}")
    keep, step_sigma, rejected = _steps(ids_t, data, alpha)
    b_steps = data.step_bias[keep]
    k = 1.0 if data.centres_on_metal else 0.0
    if k == 0.0 and len(b_steps) == 0:
        raise CalibrationError(
            "the range bias cannot be observed in this session: the detected centres lie on paint and no capture "
            "showed the flange's metal face over its painted shoulder (finish step)"
        )
    rigid = solve_rigid(P_b, P_c)
    R0, t0 = rigid.T_dst_src[:3, :3], rigid.T_dst_src[:3, 3]
    sigma_p = pair_sigma if pair_sigma is not None and pair_sigma > 0 else rigid.uncertainty.sigma
    sigma_p = sigma_p if math.isfinite(sigma_p) and sigma_p > 0 else 1e-4
    U = _unit_rays(P_c)
    b0 = float(np.median(b_steps)) if len(b_steps) else 0.0

    def pieces(x: Array) -> tuple[Array, Array]:
        R = _rotation(x[:3], R0)
        Q = (P_c - k * x[6] * U) @ R.T  # R (p - k b u), base frame
        return Q, Q + t0 + x[3:6] - P_b

    def residuals(x: Array, sp: float, ss: float) -> Array:
        _, r = pieces(x)
        parts = [r.reshape(-1) / sp]
        if len(b_steps):
            parts.append((x[6] - b_steps) / ss)
        return np.concatenate(parts)

    def jacobian(x: Array, sp: float, ss: float) -> Array:
        Q, _ = pieces(x)
        R = _rotation(x[:3], R0)
        J = np.zeros((3 * n + len(b_steps), 7))
        # d(exp([w]x) R q)/dw = -[R q]x ; d/dt = I ; d/db = -k R u
        Jw = np.zeros((n, 3, 3))
        Jw[:, 0, 1], Jw[:, 0, 2] = Q[:, 2], -Q[:, 1]
        Jw[:, 1, 0], Jw[:, 1, 2] = -Q[:, 2], Q[:, 0]
        Jw[:, 2, 0], Jw[:, 2, 1] = Q[:, 1], -Q[:, 0]
        J[: 3 * n, :3] = Jw.reshape(-1, 3)
        J[: 3 * n, 3:6] = np.tile(np.eye(3), (n, 1))
        J[: 3 * n, 6] = (-k * U @ R.T).reshape(-1)
        J[: 3 * n] /= sp
        J[3 * n :, 6] = 1.0 / ss
        return J

    x = np.zeros(7)
    x[6] = b0
    ss = step_sigma if math.isfinite(step_sigma) else 1.0
    dof = 3 * n - 6 - (1 if k else 0)
    for _ in range(3):  # the pair noise from the pair residuals, then solve again with it
        sol = least_squares(residuals, x, jac=jacobian, args=(sigma_p, ss), method="lm", xtol=1e-12, ftol=1e-12)
        x = sol.x
        _, r = pieces(x)
        new_sigma = math.sqrt(float(np.sum(r * r)) / dof) if dof > 0 else sigma_p
        converged = abs(new_sigma - sigma_p) <= 1e-3 * sigma_p
        sigma_p = max(new_sigma, 1e-9)
        if converged:
            break
    J = jacobian(x, sigma_p, ss)
    cov: Array
    try:
        cov = np.asarray(np.linalg.inv(J.T @ J), dtype=np.float64)
    except np.linalg.LinAlgError:
        cov = np.full((7, 7), np.inf)
    # What each kind of observation alone says about b (its marginal information).
    J_pairs = J[: 3 * n]
    info_pairs = 0.0
    if k:
        F = J_pairs.T @ J_pairs
        try:
            info_pairs = float(F[6, 6] - F[6, :6] @ np.linalg.solve(F[:6, :6], F[:6, 6]))
        except np.linalg.LinAlgError:
            info_pairs = 0.0
    sigma_from_pairs = 1.0 / math.sqrt(info_pairs) if info_pairs > 0.0 else math.inf
    sigma_from_steps = ss / math.sqrt(len(b_steps)) if len(b_steps) else math.inf
    T = transform_from(_rotation(x[:3], R0), t0 + x[3:6])
    bias = float(x[6])
    P_corr = P_c - k * bias * U
    _, r = pieces(x)
    return RangeBiasFit(
        T_base_cam=T,
        bias=bias,
        bias_std=float(math.sqrt(cov[6, 6])) if np.isfinite(cov[6, 6]) and cov[6, 6] >= 0 else math.inf,
        sigma_from_pairs=sigma_from_pairs,
        sigma_from_steps=sigma_from_steps,
        centres_on_metal=bool(k),
        n_pairs=n,
        step_ids=tuple(ids_t[i] for i in np.flatnonzero(keep)),
        rejected_steps=rejected,
        pair_sigma=sigma_p,
        step_sigma=step_sigma,
        uncertainty=Uncertainty(covariance=cov[:6, :6], sigma=sigma_p, dof=dof),
        covariance=cov,
        residuals=np.linalg.norm(r, axis=1),
        P_cam_corrected=P_corr,
    )


def solve_robust_range_bias(
    P_base: ArrayLike,
    P_cam: ArrayLike,
    data: RangeBiasData,
    ids: Sequence[str] | None = None,
    params: RobustParams = RobustParams(),
) -> tuple[RobustFit, RangeBiasFit]:
    """The robust estimator (:mod:`celld.calib.robust`) with the range bias: every consistent pair, and ``b``.

    The consistent pairs are found on the centres as measured; the joint
    solve runs on them (with their finish steps). When the centres lie on
    metal, the pairs are sorted again on the centres corrected by that ``b``
    (a bias of several millimetres bends the rigid residuals by about one)
    and the joint solve runs once more on the new set.

    Returns
    -------
    (RobustFit, RangeBiasFit)
        The robust fit on the corrected centres (its inliers and rejections
        are the solve's) and the joint fit on its inliers.
    """
    P_b, P_c = check_pairs(P_base, P_cam)
    ids_t = tuple(str(i) for i in range(len(P_b))) if ids is None else tuple(str(i) for i in ids)

    def joint(rob: RobustFit) -> RangeBiasFit:
        inl = np.asarray(rob.inliers, dtype=np.int64)
        return solve_range_bias(P_b[inl], P_c[inl], data.subset(inl), ids=[ids_t[i] for i in inl], pair_sigma=rob.sigma)

    rob = solve_robust(P_b, P_c, ids=ids_t, params=params)
    fit = joint(rob)
    if data.centres_on_metal:
        rob = solve_robust(P_b, correct_range_bias(P_c, fit.bias), ids=ids_t, params=params)
        fit = joint(rob)
    return rob, fit


def bias_from_steps(steps: Sequence[FinishStep | None]) -> float | None:
    """A quick estimate of ``b`` from finish steps alone (their median), m; None without one.

    For the online Algorithm 1, before the joint solve: twenty steps agree
    to a few hundredths of a millimetre.
    """
    values = [s.bias for s in steps if s is not None and math.isfinite(s.bias)]
    return float(np.median(values)) if values else None
