"""The quality gate of an eye-on-base calibration: may this ``T_base_cam`` be accepted?

Owns the verdict on a solved calibration, computed from what the solve
already holds (pairs, residuals, the estimate, e_icp): no cloud, no ground
truth. :func:`assess_calibration` returns a frozen :class:`CalibrationQuality`:

- every pair with its residual against the estimate, whether the estimate
  used it, whether it is an outlier and why (or why it has no centre);
- the noise per axis (from the residuals, never below a floor) and the
  first-order uncertainty of the estimate (:mod:`celld.calib.rigid`'s
  convention) with that noise: translation 1-sigma at the workspace centre
  (the centroid of the positions used, where the cell works; the camera's
  own position, a metre away, carries the rotation's lever arm), rotation
  1-sigma about the base axes and about the principal axes of the rotation
  covariance, the worst named in the base frame;
- the e_icp (Eq. 13) of the estimate against the verification cloud, run to
  convergence, when the session has one. Its rotation is split into the turn
  about the verification flange's own axis and the tilt across it: the disc
  of a flange fixes the tilt, only its holes and pin fix the turn, and ICP
  leaves that turn loose (a degree and more on a sparse cloud). The tilt
  judges the estimate; the turn judges a compensated transform (Eq. 21
  applies it whole), and is a warning otherwise;
- the range bias on metal estimated with the transform (time-of-flight
  cameras, :mod:`celld.calib.rangebias`), with its 1-sigma: it moves the
  camera's origin along its axis and every metal point of a scan by as
  much, so a bias fixed worse than a limit fails the gate; the uncertainty
  of the transform carries the bias's when the centres lie on metal;
- a verdict, one of :data:`VERDICTS`, with the reasons, and warnings that do
  not fail the gate.

How well the positions fix the rotation is read here from the covariance,
axis by axis: Eq. 10-12 solve any set of positions off one line (coplanar
ones included), and a set that fixes one rotation poorly gets a warning with
the figure and, past :attr:`QualityParams.max_rotation_std`, the verdict
``insufficient_rotation``; only a rank defect is refused, by
:func:`celld.calib.rigid.check_pairs`.

The noise floor matters when the residuals are small by chance (few pairs:
with four, the fit residual is about 0.7 of the true localisation error,
Fitzpatrick et al. 1998) or by construction (exact synthetic data): the
conditioning of the geometry is then still judged at a realistic noise.

Verdicts, in the order they are decided (the first that applies wins; every
reason is listed):

- ``too_few_pairs``: fewer pairs with a flange centre than
  :attr:`QualityParams.min_pairs`, or an estimate that rests on fewer;
- ``poor_data``: a pair the estimate uses is an outlier, too many pairs are
  outliers, the residuals of the pairs used are too large, e_icp of the
  estimate is infinite or too large, or a stored compensation turns the
  estimate too far about the flange's axis;
- ``insufficient_rotation``: a rotation of the estimate is fixed worse than
  :attr:`QualityParams.max_rotation_std` (1-sigma);
- ``insufficient_range_bias``: the range bias is fixed worse than
  :attr:`QualityParams.max_range_bias_std` (1-sigma);
- ``ok``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from celld.calib.metrics import E_ICP_SCHEMA, IcpMetric
from celld.calib.rangebias import RangeBiasFit
from celld.calib.rigid import (
    Array,
    Uncertainty,
    check_pairs,
    pair_residuals,
    rigid_jacobian,
)
from celld.calib.robust import CHI2_3_MEDIAN, RejectedPair
from celld.errors import InputError
from celld.schemadoc import array, boolean, enum, integer, nullable, number, obj, string, texts, vector

# The verdicts; only "ok" passes the gate.
VERDICTS = ("ok", "too_few_pairs", "poor_data", "insufficient_rotation", "insufficient_range_bias")
# Floor of the outlier threshold on a pair's residual, m, for the robust estimator and the gate alike
# (calibration.outlier_floor_mm): an arm's error is never an outlier. What the arm errs from pose to pose
# inside a calibration box (0.04-0.19 mm measured in the simulated worlds; a UR's repeatability is
# +-0.05 mm) and a structured-light scanner's centre noise (0.05-0.3 mm) stay well below it; a false
# detection, another part of the arm taken for the flange, lies millimetres to tens of millimetres off
# (paper section 3.2.2). Without it, at five to seven pairs the median residual fell among the fit's own
# near-zero residuals and good pairs were dropped in one session in five (bench/arm_calibration.py).
OUTLIER_FLOOR = 1.0e-3
# A principal axis within this angle of a base axis is named after it (X, Y, Z).
_AXIS_NAME_TOLERANCE = math.radians(20.0)
# Positions whose second (third) principal spread is below this fraction of the
# first (second) are called a line (a plane) in the advice of a warning; the
# advice only, never a refusal.
_THIN = 0.1


@dataclass(frozen=True)
class QualityParams:
    """Thresholds of the gate (SI units). The defaults and why:

    Attributes
    ----------
    min_pairs : int
        Pairs with a flange centre needed (5): four for Eq. 9-12 and one to
        spare. With four, every pair is needed to solve and a false detection
        (paper section 3.2.2) cannot be told from the others; with five it can
        be outvoted and rejected.
    max_rms : float
        RMS residual of the pairs used, metres (1 mm): about three times what
        good PhoXi data gives (0.24-0.31 mm on the authors' Franka sample);
        the paper's false segmentations sit tens of millimetres off. A noisier
        scanner (a ToF camera) needs a higher value.
    max_outlier_fraction : float
        Share of the pairs with a centre that may be outliers (1/3): beyond
        it the detector or the robot poses are suspect as a whole, and the
        robust estimator (breakdown at one half) is close to its limit.
    outlier_alpha : float
        Probability that a good pair is flagged as an outlier (1e-4, the
        robust estimator's default; threshold 4.59 sigma on the residual norm).
    sigma_floor : float
        Lowest noise per axis the uncertainty is computed with, metres
        (0.05 mm): the repeatability of a UR10e (+-0.05 mm) and about the
        centre noise of a PhoXi, below which no real session goes.
    warn_rotation_std : float
        A rotation 1-sigma above this is a warning, rad (0.1 deg: three sigma
        then exceed the paper's 0.25 deg rotation error).
    max_rotation_std : float
        A rotation 1-sigma above this fails the gate, rad (0.25 deg: one sigma
        alone is the paper's whole rotation error; at 0.5 m from the workspace
        centre it is 2 mm).
    max_e_icp_translation : float
        Largest offset e_icp (Eq. 13) of the estimate puts on the verification
        flange's centre, metres (2 mm; the paper reaches 0.28 mm). Judged at
        the flange, not at e_icp's own origin (the camera's, about a metre
        away, where every 0.1 deg of rotation, including the turn about the
        flange's axis that ICP does not fix, adds about 1.7 mm); at the
        camera's origin only when the flange's centre is not known.
    max_e_icp_rotation : float
        Largest tilt of e_icp of the estimate (its rotation across the
        verification flange's axis), and largest turn about that axis a
        stored compensation may apply, rad (0.5 deg: twice the paper's
        0.25 deg).
    warn_range_bias_std : float
        A range bias 1-sigma above this is a warning, m (0.25 mm).
    max_range_bias_std : float
        A range bias 1-sigma above this fails the gate, m (0.5 mm: three
        sigma then reach the 1.5 mm a time-of-flight calibration is held to,
        along the camera's axis and on every metal point of a scan).
    outlier_floor : float
        The outlier threshold is never below this, m (:data:`OUTLIER_FLOOR`).
    bound_confidence : float
        Confidence of the reported bounds on the norm of the 3-D error (0.95).
    arm_error_prior : float
        The arm's own error away from the calibration poses, which a
        hand-eye calibration cannot see (the fit absorbs it where the pairs
        are, nowhere else), m: the prior of the arm's class
        (``calibration.arm_error_prior_mm``, 1 mm: a real industrial arm
        calibrated hand-eye only from a 3-D scanner misses by 0.81 mm mean,
        1.04 mm max, Sensors 2025, 25(15):4661).
    work_radius : float
        How far from the workspace centre the cell works, m
        (``calibration.work_radius``): the bound away from the calibration
        poses is taken at this distance, where the rotation's lever is longest.
    """

    min_pairs: int = 5
    max_rms: float = 1.0e-3
    max_outlier_fraction: float = 1.0 / 3.0
    outlier_alpha: float = 1e-4
    sigma_floor: float = 0.05e-3
    warn_rotation_std: float = math.radians(0.1)
    max_rotation_std: float = math.radians(0.25)
    max_e_icp_translation: float = 2.0e-3
    max_e_icp_rotation: float = math.radians(0.5)
    warn_range_bias_std: float = 0.25e-3
    max_range_bias_std: float = 0.5e-3
    outlier_floor: float = OUTLIER_FLOOR
    bound_confidence: float = 0.95
    arm_error_prior: float = 1.0e-3
    work_radius: float = 0.5

    def __post_init__(self) -> None:
        if self.min_pairs < 4:
            raise InputError(f"min_pairs: expected at least 4 (Eq. 9-12), got {self.min_pairs}")
        if not 0.0 < self.outlier_alpha < 0.5:
            raise InputError(f"outlier_alpha: expected 0 < alpha < 0.5, got {self.outlier_alpha}")
        if not 0.0 <= self.max_outlier_fraction < 1.0:
            raise InputError(f"max_outlier_fraction: expected a fraction in [0, 1), got {self.max_outlier_fraction}")
        for name in (
            "max_rms",
            "sigma_floor",
            "outlier_floor",
            "warn_rotation_std",
            "max_rotation_std",
            "max_e_icp_translation",
            "max_e_icp_rotation",
            "warn_range_bias_std",
            "max_range_bias_std",
        ):
            if not getattr(self, name) > 0.0:
                raise InputError(f"{name}: expected a positive value (SI units), got {getattr(self, name)}")
        if not 0.0 < self.bound_confidence < 1.0:
            raise InputError(f"bound_confidence: expected 0 < confidence < 1, got {self.bound_confidence}")
        if not (self.arm_error_prior >= 0.0 and self.work_radius > 0.0):
            raise InputError(f"arm_error_prior, work_radius: expected >= 0 and > 0 m, got {self.arm_error_prior} and {self.work_radius}")
        if self.warn_rotation_std > self.max_rotation_std:
            raise InputError(f"warn_rotation_std: expected at most max_rotation_std {self.max_rotation_std}, got {self.warn_rotation_std}")
        if self.warn_range_bias_std > self.max_range_bias_std:
            raise InputError(
                f"warn_range_bias_std: expected at most max_range_bias_std {self.max_range_bias_std}, got {self.warn_range_bias_std}"
            )

    @property
    def outlier_k(self) -> float:
        """Outlier threshold in units of the noise per axis."""
        return float(math.sqrt(chi2.isf(self.outlier_alpha, 3)))


@dataclass(frozen=True)
class PairQuality:
    """One pair as the gate sees it.

    Attributes
    ----------
    id : str
    residual : float
        ``|R p_cam + t - p_base|`` against the estimate, metres; NaN when the
        pair has no flange centre.
    used : bool
        The estimate uses the pair.
    outlier : bool
        The residual exceeds the outlier threshold.
    reason : str
        Why it is an outlier, why it is not used, or why it has no centre
        (``""`` for a used, consistent pair).
    """

    id: str
    residual: float
    used: bool
    outlier: bool
    reason: str

    def as_dict(self) -> dict[str, Any]:
        r = self.residual * 1e3 if math.isfinite(self.residual) else None
        return {"id": self.id, "residual_mm": r, "used": self.used, "outlier": self.outlier, "reason": self.reason}


@dataclass(frozen=True)
class RotationAxis:
    """A principal axis of the rotation covariance: unit ``direction`` in the base frame, 1-sigma ``std`` (rad)."""

    name: str
    direction: Array
    std: float

    def as_dict(self) -> dict[str, Any]:
        return {"axis": self.name, "direction": self.direction.tolist(), "std_deg": _finite(math.degrees(self.std))}


@dataclass(frozen=True)
class CalibrationQuality:
    """The gate's view of one calibration (module docstring); SI units.

    Attributes
    ----------
    verdict : str
        One of :data:`VERDICTS`.
    reasons : tuple of str
        Why the verdict is not ``ok`` (every failed check, in verdict order);
        empty when it is.
    warnings : tuple of str
        What an operator should know that does not fail the gate.
    pairs : tuple of PairQuality
        Every pair of the session: first those with a centre in pair order,
        then those without.
    rms : float
        RMS residual of the pairs used, metres.
    sigma : float
        Noise per axis the uncertainty uses, metres.
    sigma_source : str
        ``"residuals"`` (the fit's estimate) or ``"floor"``
        (:attr:`QualityParams.sigma_floor`, the estimate was lower).
    workspace_centre : (3,) array
        Centroid of the positions used, base frame, metres.
    translation_std : (3,) array
        1-sigma of a point at the workspace centre mapped by the estimate,
        along base x, y, z, metres.
    rotation_std : (3,) array
        1-sigma of the rotation about base x, y, z, rad.
    rotation_axes : tuple of RotationAxis
        Principal axes of the rotation covariance, the worst fixed first.
    e_icp : IcpMetric | None
        e_icp (Eq. 13) of the estimate; None without a verification cloud.
    e_icp_tilt : float
        Rotation angle of e_icp across the verification flange's axis (all of
        it when the axis is not known), rad; NaN without a finite e_icp.
    e_icp_turn : float
        Rotation of e_icp about the verification flange's axis, rad (signed,
        right-handed about the flange's +z); NaN when not known.
    range_bias : float
        The range bias on metal estimated with the transform, m; NaN when
        not estimated.
    range_bias_std : float
        Its 1-sigma, m; NaN when not estimated.
    range_bias_source : str
        What fixed it: ``"steps"``, ``"pairs"``, ``"steps+pairs"``; ``""``
        when not estimated.
    bound_box : float
        Bound on the norm of the 3-D error of a point the calibration maps,
        at :attr:`QualityParams.bound_confidence`, within the box the
        positions used span, m: the estimate's own uncertainty there and the
        pose-to-pose error the pairs show (the noise per axis, which carries
        what the arm errs from pose to pose inside the box).
    bound_away : float
        The same bound anywhere within the work radius outside that box, m:
        the estimate's uncertainty at the work radius, the pose-to-pose
        error, and the arm's own error there (:attr:`QualityParams.arm_error_prior`),
        which no pair measured.
    """

    verdict: str
    reasons: tuple[str, ...]
    warnings: tuple[str, ...]
    pairs: tuple[PairQuality, ...]
    rms: float
    sigma: float
    sigma_source: str
    workspace_centre: Array
    translation_std: Array
    rotation_std: Array
    rotation_axes: tuple[RotationAxis, ...]
    e_icp: IcpMetric | None
    e_icp_tilt: float = math.nan
    e_icp_turn: float = math.nan
    range_bias: float = math.nan
    range_bias_std: float = math.nan
    range_bias_source: str = ""
    bound_box: float = math.nan
    bound_away: float = math.nan
    bound_confidence: float = math.nan
    arm_error_prior: float = math.nan

    @property
    def passed(self) -> bool:
        """True when the verdict is ``ok``: the estimate may be accepted without force."""
        return self.verdict == "ok"

    @property
    def outliers(self) -> tuple[str, ...]:
        """Ids of the pairs flagged as outliers."""
        return tuple(p.id for p in self.pairs if p.outlier)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (mm and deg at this boundary; None where not finite; :data:`QUALITY_SCHEMA`)."""
        return {
            "verdict": self.verdict,
            "passed": self.passed,
            "reasons": list(self.reasons),
            "warnings": list(self.warnings),
            "pairs": [p.as_dict() for p in self.pairs],
            "outliers": list(self.outliers),
            "n_used": sum(p.used for p in self.pairs),
            "rms_mm": _finite(self.rms * 1e3),
            "sigma_mm": _finite(self.sigma * 1e3),
            "sigma_source": self.sigma_source,
            "workspace_centre": self.workspace_centre.tolist(),
            "translation_std_mm": [_finite(x * 1e3) for x in self.translation_std],
            "rotation_std_deg": [_finite(math.degrees(x)) for x in self.rotation_std],
            "rotation_axes": [a.as_dict() for a in self.rotation_axes],
            "e_icp": None if self.e_icp is None else self.e_icp.as_dict(),
            "e_icp_tilt_deg": _finite(math.degrees(self.e_icp_tilt)),
            "e_icp_turn_deg": _finite(math.degrees(self.e_icp_turn)),
            "range_bias_mm": _finite(self.range_bias * 1e3),
            "range_bias_std_mm": _finite(self.range_bias_std * 1e3),
            "range_bias_source": self.range_bias_source,
            "bound": {
                "confidence": _finite(self.bound_confidence),
                "calibration_box_mm": _finite(self.bound_box * 1e3),
                "work_radius_mm": _finite(self.bound_away * 1e3),
                "arm_error_prior_mm": _finite(self.arm_error_prior * 1e3),
            },
        }


# The JSON shape of CalibrationQuality.as_dict.
QUALITY_SCHEMA = obj(
    "The quality gate's view of a calibration (celld.calib.quality): a verdict and why, per-pair residuals and "
    "outliers, the uncertainty at the workspace centre, e_icp of the estimate; null where not finite.",
    {
        "verdict": enum(VERDICTS, "Only ok passes; accept refuses the others unless forced."),
        "passed": boolean(),
        "reasons": texts("Why the verdict is not ok."),
        "warnings": texts("What does not fail the gate but should be known."),
        "pairs": array(
            obj(
                "One pair.",
                {
                    "id": string(),
                    "residual_mm": number("Null when the pair has no flange centre.", null=True),
                    "used": boolean(),
                    "outlier": boolean(),
                    "reason": string("Why it is an outlier, not used, or without a centre."),
                },
                ("id", "residual_mm", "used", "outlier", "reason"),
            ),
            "Every pair: residual against the estimate, used, outlier, and why.",
        ),
        "outliers": texts("Ids of the outliers."),
        "n_used": integer(lo=0),
        "rms_mm": number("RMS residual of the pairs used.", null=True),
        "sigma_mm": number("Noise per axis the uncertainty uses.", null=True),
        "sigma_source": enum(("residuals", "floor")),
        "workspace_centre": vector("Centroid of the positions used, base frame, m.", 3),
        "translation_std_mm": vector("1-sigma at the workspace centre, base x, y, z.", 3, null_items=True),
        "rotation_std_deg": vector("1-sigma about base x, y, z.", 3, null_items=True),
        "rotation_axes": array(
            obj(
                "One axis.",
                {"axis": string(), "direction": vector("Unit direction, base frame.", 3), "std_deg": number(null=True)},
                ("axis", "direction", "std_deg"),
            ),
            "Principal axes of the rotation covariance, the worst fixed first.",
        ),
        "e_icp": nullable(E_ICP_SCHEMA, "e_icp (Eq. 13) of the estimate; null without a verification cloud."),
        "e_icp_tilt_deg": number("e_icp's rotation across the verification flange's axis.", null=True),
        "e_icp_turn_deg": number("e_icp's rotation about the verification flange's axis (fixed only by its holes).", null=True),
        "range_bias_mm": number("The scanner's range bias on bare metal estimated with T_base_cam; null when not estimated.", null=True),
        "range_bias_std_mm": number("Its 1-sigma.", null=True),
        "range_bias_source": string(
            "What fixed it: steps (the metal face over the painted shoulder), pairs (the spread of the rays), or both; "
            "empty when not estimated."
        ),
        "bound": obj(
            "Bounds on the norm of the 3-D error of a point the calibration maps, at the stated confidence; null where not "
            "finite. Absent from calibrations stored before celld reported it.",
            {
                "confidence": number("Confidence of the bounds (0.95).", null=True),
                "calibration_box_mm": number(
                    "Within the box the positions used span: the estimate's uncertainty and the pose-to-pose error.", null=True
                ),
                "work_radius_mm": number(
                    "Anywhere within the work radius outside that box: adds the arm's own error there, which no pair measured.",
                    null=True,
                ),
                "arm_error_prior_mm": number("The arm's own error away from the calibration poses, the prior of its class.", null=True),
            },
            ("confidence", "calibration_box_mm", "work_radius_mm", "arm_error_prior_mm"),
        ),
    },
    (
        "verdict",
        "passed",
        "reasons",
        "warnings",
        "pairs",
        "outliers",
        "n_used",
        "rms_mm",
        "sigma_mm",
        "sigma_source",
        "workspace_centre",
        "translation_std_mm",
        "rotation_std_deg",
        "rotation_axes",
        "e_icp",
        "e_icp_tilt_deg",
        "e_icp_turn_deg",
        "range_bias_mm",
        "range_bias_std_mm",
        "range_bias_source",
    ),
)


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def axis_name(v: ArrayLike) -> str:
    """Name a direction of the base frame: ``X``, ``Y`` or ``Z`` when it is within 20 deg of one, else its components."""
    v = np.asarray(v, dtype=np.float64)
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) >= math.cos(_AXIS_NAME_TOLERANCE):
        return "XYZ"[k]
    v = v if v[k] > 0 else -v
    return f"({v[0]:+.2f}, {v[1]:+.2f}, {v[2]:+.2f})"


def _advice(axis: Array, P: Array) -> str:
    """Where to add poses so that rotation about ``axis`` is fixed better, from the positions used ``P``."""
    centred = P - P.mean(axis=0)
    _, s, Vt = np.linalg.svd(centred, full_matrices=True)
    s = np.concatenate([s, np.zeros(3 - len(s))]) if len(s) < 3 else s
    if s[1] < _THIN * s[0]:
        return "add poses off the line"
    # The lever arm about the axis is the spread across it: add poses along the
    # direction across the axis in which the positions spread least.
    across = centred - np.outer(centred @ axis, axis)
    _, V = np.linalg.eigh(across.T @ across)  # ascending; the axis itself has eigenvalue 0
    d = V[:, 1]
    if s[2] < _THIN * s[1] and abs(float(d @ Vt[2])) >= math.cos(_AXIS_NAME_TOLERANCE):
        return "add poses off the plane"
    return f"add poses spread further along {axis_name(d)}"


def assess_calibration(
    ids: Sequence[str],
    P_base: ArrayLike,
    P_cam: ArrayLike,
    T_base_cam: ArrayLike,
    *,
    used: Sequence[int],
    uncertainty: Uncertainty,
    scale: float = 1.0,
    with_scale: bool = False,
    rejected: Sequence[RejectedPair] = (),
    e_icp: IcpMetric | None = None,
    flange_axis_cam: ArrayLike | None = None,
    flange_centre_cam: ArrayLike | None = None,
    compensated: bool = False,
    notes: Sequence[str] = (),
    range_bias: RangeBiasFit | None = None,
    params: QualityParams = QualityParams(),
) -> CalibrationQuality:
    """The quality gate of one estimate (module docstring). Pure: arrays in, a value out.

    Parameters
    ----------
    ids : sequence of str
        The pairs with a flange centre, in pair order.
    P_base, P_cam : (n, 3) arrays
        Their centres in the base and camera frames, metres.
    T_base_cam : (4, 4) array
        The estimate (before any compensation by Eq. 21).
    used : sequence of int
        Indices (into ``ids``) of the pairs the estimate uses.
    uncertainty : Uncertainty
        The estimate's, for the noise estimated from its residuals.
    scale : float
        ``c`` of Eq. 11 the estimate was solved with.
    with_scale : bool
        The scale was estimated (it then takes a degree of freedom).
    rejected : sequence of RejectedPair
        Why pairs were left out: the solver's rejections, and pairs without a
        centre (failed detections), which are reported after the others.
    e_icp : IcpMetric | None
        e_icp (Eq. 13) of the estimate, None without a verification cloud.
    flange_axis_cam : (3,) array, optional
        The verification flange's +z in the camera frame (by the estimate),
        to split e_icp's rotation; without it all of it counts as tilt.
    flange_centre_cam : (3,) array, optional
        The verification flange's centre in the camera frame (by the
        estimate), metres, where e_icp's translation is judged; without it
        e_icp's translation at the camera's origin is.
    compensated : bool
        The transform stored is the estimate compensated by e_icp (Eq. 21).
    notes : sequence of str
        Warnings the caller adds (e.g. a compensation that could not be applied).
    range_bias : RangeBiasFit | None
        The range bias estimated with the transform; ``P_cam`` are then the
        centres corrected by it.
    params : QualityParams

    Raises
    ------
    InputError
        Malformed pairs, ids or indices.
    """
    P_b, P_c = check_pairs(P_base, P_cam, min_pairs=1, determined=False)
    ids_t = tuple(str(i) for i in ids)
    n = len(P_b)
    if len(ids_t) != n:
        raise InputError(f"ids: expected {n} pair ids, got {len(ids_t)}")
    used_idx = sorted({int(i) for i in used})
    if not used_idx or used_idx[0] < 0 or used_idx[-1] >= n:
        raise InputError(f"used: expected indices of pairs in 0..{n - 1}, got {list(used)}")
    T = np.asarray(T_base_cam, dtype=np.float64)
    is_used = np.zeros(n, dtype=bool)
    is_used[used_idx] = True
    why_rejected = {r.id: r.reason for r in rejected}
    no_centre = [r for r in rejected if r.id not in ids_t]
    n_session = n + len(no_centre)

    # Noise per axis: the fit's estimate, never below the floor.
    sigma_fit = uncertainty.sigma if uncertainty.dof > 0 and math.isfinite(uncertainty.sigma) else math.nan
    if math.isfinite(sigma_fit) and sigma_fit >= params.sigma_floor:
        sigma, source = sigma_fit, "residuals"
    else:
        sigma, source = params.sigma_floor, "floor"

    # Covariance of the estimate at that noise: sigma^2 (J^T J)^-1 on the pairs used.
    J, _ = rigid_jacobian(T, P_b[is_used], P_c[is_used], scale, with_scale)
    JtJ = J.T @ J
    if range_bias is not None and range_bias.centres_on_metal:
        # The bias is a parameter of the pairs too: its column, d r_i / d b = -R u_i,
        # and what the finish steps add to its information (at the same noise scale).
        U = P_c[is_used] / np.linalg.norm(P_c[is_used], axis=1, keepdims=True)
        J = np.column_stack([J, -(U @ T[:3, :3].T).reshape(-1)])
        JtJ = J.T @ J
        if math.isfinite(range_bias.sigma_from_steps) and range_bias.sigma_from_steps > 0.0:
            JtJ[-1, -1] += (sigma / range_bias.sigma_from_steps) ** 2
    try:
        cov = np.linalg.inv(JtJ)[:6, :6] * sigma**2
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    P_used = P_b[is_used]
    centre = P_used.mean(axis=0)
    if np.all(np.isfinite(cov)):
        # A point p at the centre maps as exp([r]x) R p_cam + t + dt: d = -[centre - t]x r + dt.
        lever = centre - T[:3, 3]
        G = np.hstack([-_skew(lever), np.eye(3)])
        translation_std = np.sqrt(np.clip(np.diag(G @ cov @ G.T), 0.0, None))
        rotation_std = np.sqrt(np.clip(np.diag(cov[:3, :3]), 0.0, None))
        w, V = np.linalg.eigh(cov[:3, :3])
        order = np.argsort(w)[::-1]
        axes = tuple(RotationAxis(axis_name(V[:, k]), _canonical(V[:, k]), float(np.sqrt(max(w[k], 0.0)))) for k in order)
    else:
        translation_std = np.full(3, np.inf)
        rotation_std = np.full(3, np.inf)
        axes = tuple(RotationAxis("XYZ"[k], np.eye(3)[k], math.inf) for k in range(3))

    bound_box, bound_away = _bounds(np.asarray(cov, dtype=np.float64), T, P_used, centre, sigma, params)

    # Outliers: residual norm beyond k sigma, sigma from the median residual of
    # every pair (robust to up to half of them being false), never below the floor.
    residuals = pair_residuals(T, P_b, P_c, scale)
    sigma_med = math.sqrt(float(np.median(residuals**2)) / CHI2_3_MEDIAN)
    sigma_ref = max(sigma_med, params.sigma_floor)
    k = params.outlier_k
    threshold = max(k * sigma_ref, params.outlier_floor)
    is_outlier = residuals > threshold
    pairs = []
    for i, pid in enumerate(ids_t):
        why = []
        if is_outlier[i]:
            why.append(
                f"residual {residuals[i] * 1e3:.3f} mm exceeds the outlier threshold {threshold * 1e3:.3f} mm "
                f"({k:.2f} x noise {sigma_ref * 1e3:.3f} mm per axis, from the median residual, "
                f"never below {params.outlier_floor * 1e3:.3f} mm)"
            )
        if not is_used[i]:
            why.append(why_rejected.get(pid, "not used by the estimate"))
        pairs.append(PairQuality(pid, float(residuals[i]), bool(is_used[i]), bool(is_outlier[i]), "; ".join(why)))
    pairs += [PairQuality(r.id, math.nan, False, False, r.reason) for r in no_centre]

    rms = float(np.sqrt(np.mean(residuals[is_used] ** 2)))
    too_few: list[str] = []
    poor: list[str] = []
    rotation: list[str] = []
    warnings: list[str] = []

    if n < params.min_pairs:
        too_few.append(
            f"only {n} of {n_session} captures gave a flange centre; at least {params.min_pairs} are needed "
            "(four for Eq. 9-12, one more to outvote a false detection)"
        )
    elif len(used_idx) < params.min_pairs:
        too_few.append(
            f"the estimate rests on {len(used_idx)} pairs (of {n} with a centre); at least {params.min_pairs} are needed "
            "(four for Eq. 9-12, one more to outvote a false detection)"
        )
    used_outliers = [ids_t[i] for i in np.flatnonzero(is_outlier & is_used)]
    if used_outliers:
        poor.append(f"the estimate uses pairs that are outliers: {', '.join(used_outliers)} (residual above {threshold * 1e3:.3f} mm)")
    n_out = int(np.count_nonzero(is_outlier))
    if n_out > params.max_outlier_fraction * n:
        poor.append(
            f"{n_out} of the {n} pairs with a centre are outliers (more than {params.max_outlier_fraction:.0%}): "
            "the flange detections or the robot poses are suspect"
        )
    if rms > params.max_rms:
        poor.append(f"the RMS residual of the {len(used_idx)} pairs used is {rms * 1e3:.3f} mm, above {params.max_rms * 1e3:.3f} mm")
    turn = tilt = math.nan
    if e_icp is None:
        warnings.append("no verification cloud: e_icp (Eq. 13) was not computed; the estimate is checked against its own pairs only")
    elif not e_icp.ok:
        poor.append(f"e_icp (Eq. 13) of the estimate is infinite: {e_icp.reason}")
    else:
        T_e = e_icp.T_camhat_cam
        where = "of the estimate is"
        if flange_centre_cam is None:
            dt = float(np.linalg.norm(T_e[:3, 3]))
        else:
            c = np.asarray(flange_centre_cam, dtype=np.float64)
            dt = float(np.linalg.norm(T_e[:3, :3] @ c + T_e[:3, 3] - c))
            where = "of the estimate moves the verification flange's centre"
        rotvec = Rotation.from_matrix(e_icp.T_camhat_cam[:3, :3]).as_rotvec()
        if flange_axis_cam is not None:
            a = np.asarray(flange_axis_cam, dtype=np.float64)
            a = a / np.linalg.norm(a)
            turn = float(rotvec @ a)
            tilt = float(np.linalg.norm(rotvec - turn * a))
        else:
            turn, tilt = math.nan, float(np.linalg.norm(rotvec))
        limit = math.degrees(params.max_e_icp_rotation)
        if dt > params.max_e_icp_translation:
            poor.append(f"e_icp (Eq. 13) {where} {dt * 1e3:.3f} mm, above {params.max_e_icp_translation * 1e3:.3f} mm")
        if tilt > params.max_e_icp_rotation:
            poor.append(f"e_icp (Eq. 13) of the estimate tilts {math.degrees(tilt):.3f} deg, above {limit:.3f} deg")
        if abs(turn) > params.max_e_icp_rotation:
            turned = f"{abs(math.degrees(turn)):.2f} deg about the verification flange's axis, a rotation only the flange's holes fix"
            if compensated:
                poor.append(
                    f"the compensation (Eq. 21) turns the stored transform {turned} (above {limit:.2f} deg); "
                    "solve without compensation or check the verification capture"
                )
            else:
                warnings.append(f"e_icp (Eq. 13) turns {turned}; it does not judge the estimate (not compensated)")

    for axis in axes:
        if not axis.std > params.warn_rotation_std:
            continue
        figure = f"{math.degrees(axis.std):.2f} deg 1-sigma" if math.isfinite(axis.std) else "not fixed at all"
        advice = _advice(axis.direction, P_used)
        warnings.append(f"rotation about {axis.name} poorly fixed: {figure}; {advice}")
        if axis.std > params.max_rotation_std:
            rotation.append(
                f"rotation about {axis.name} poorly fixed: {figure}, above {math.degrees(params.max_rotation_std):.2f} deg; {advice}"
            )
    bias_reasons: list[str] = []
    if range_bias is not None:
        b_std = range_bias.bias_std
        if not b_std <= params.warn_range_bias_std:
            figure = f"{b_std * 1e3:.2f} mm 1-sigma" if math.isfinite(b_std) else "not fixed at all"
            if math.isfinite(range_bias.sigma_from_steps):
                advice = "add poses where the flange's face and the painted shoulder around it are both in view"
            else:
                advice = (
                    "only the spread of the rays fixes it (no capture showed the metal face over a painted shoulder): "
                    "spread the poses wider across the field of view or take more of them, or calibrate where a "
                    "painted shoulder around the flange is in view"
                )
            warnings.append(f"range bias on metal ({range_bias.bias * 1e3:.2f} mm) poorly fixed: {figure}; {advice}")
            if not b_std <= params.max_range_bias_std:
                bias_reasons.append(
                    f"the range bias on metal ({range_bias.bias * 1e3:.2f} mm) is fixed to {figure}, above "
                    f"{params.max_range_bias_std * 1e3:.2f} mm: it moves the camera along its axis and every metal point "
                    f"of a scan by as much; {advice}"
                )
        if range_bias.rejected_steps:
            warnings.append(
                f"{len(range_bias.rejected_steps)} finish steps left out of the range bias as outliers: "
                + ", ".join(r.id for r in range_bias.rejected_steps)
            )
    if source == "floor" and math.isfinite(sigma_fit):
        warnings.append(
            f"the noise estimated from the residuals ({sigma_fit * 1e3:.3f} mm per axis) is below the floor "
            f"{params.sigma_floor * 1e3:.3f} mm; the uncertainty uses the floor"
        )
    if no_centre:
        warnings.append(f"{len(no_centre)} of {n_session} captures gave no flange centre: {', '.join(r.id for r in no_centre)}")
    warnings += [str(x) for x in notes]

    verdict = "ok"
    for name, found in (
        ("too_few_pairs", too_few),
        ("poor_data", poor),
        ("insufficient_rotation", rotation),
        ("insufficient_range_bias", bias_reasons),
    ):
        if found:
            verdict = name
            break
    return CalibrationQuality(
        verdict=verdict,
        reasons=tuple(too_few + poor + rotation + bias_reasons),
        warnings=tuple(warnings),
        pairs=tuple(pairs),
        rms=rms,
        sigma=float(sigma),
        sigma_source=source,
        workspace_centre=centre,
        translation_std=translation_std,
        rotation_std=rotation_std,
        rotation_axes=axes,
        e_icp=e_icp,
        e_icp_tilt=tilt,
        e_icp_turn=turn,
        range_bias=math.nan if range_bias is None else range_bias.bias,
        range_bias_std=math.nan if range_bias is None else range_bias.bias_std,
        range_bias_source="" if range_bias is None else range_bias.source,
        bound_box=bound_box,
        bound_away=bound_away,
        bound_confidence=params.bound_confidence,
        arm_error_prior=params.arm_error_prior,
    )


def _bounds(cov: Array, T: Array, P_used: Array, centre: Array, sigma: float, params: QualityParams) -> tuple[float, float]:
    """(in the box the positions span, anywhere within the work radius outside it), m (:attr:`CalibrationQuality.bound_box`).

    At a point p the estimate's error is Gaussian with covariance G(p) cov G(p)^T;
    its norm is bounded at the confidence by the chi-3 quantile on the largest
    axis (conservative for the others). The pose-to-pose error adds the same
    quantile of the noise per axis; the arm's own error away from the pairs
    adds its prior, whole (it is systematic, not a scatter).
    """

    def at(points: Array) -> Array:
        """The estimate's covariance (k, 3, 3) at each point (k, 3)."""
        G = np.stack([np.hstack([-_skew(p - T[:3, 3]), np.eye(3)]) for p in points])
        return np.asarray(G @ cov @ G.transpose(0, 2, 1))

    lo, hi = P_used.min(axis=0), P_used.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    box = norm_bound(at(corners), sigma, params.bound_confidence)
    away_points = centre + params.work_radius * np.vstack([np.eye(3), -np.eye(3)])
    away = norm_bound(at(away_points), sigma, params.bound_confidence) + params.arm_error_prior
    return box, max(away, box + params.arm_error_prior)


def norm_bound(cov_points: Array, sigma: float, confidence: float) -> float:
    """A bound on the norm of a 3-D error, the largest over points: at each, the error of an estimate with
    covariance ``cov_points[i]`` (3, 3), taken on its largest axis (conservative for the others), and a
    scatter of ``sigma`` per axis, at the chi-3 quantile of ``confidence``; inf for a covariance not finite."""
    C = np.asarray(cov_points, dtype=np.float64).reshape(-1, 3, 3)
    if not np.all(np.isfinite(C)):
        return math.inf
    worst = max(float(np.linalg.eigvalsh(C)[:, -1].max()), 0.0) if len(C) else 0.0
    return math.sqrt(float(chi2.ppf(confidence, 3))) * math.sqrt(worst + sigma**2)


def _skew(v: Array) -> Array:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _canonical(v: Array) -> Array:
    """A unit direction with its largest component positive (an axis has no sign)."""
    v = v / np.linalg.norm(v)
    return v if v[int(np.argmax(np.abs(v)))] > 0 else -v
