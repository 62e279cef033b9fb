"""From calibration pairs to ``T_base_cam``: the solve, Algorithm 1 over the pairs, e_icp, the report.

The pure core of a calibration (arrays in): the centre pairs of a session
(flange positions and the centres found in the clouds, pairs whose detection
failed already rejected with the detector's reason) are solved by the chosen
method, Algorithm 1 runs over the pairs in their captured order when a
verification cloud is there, the final estimate is scored by e_icp (Eq. 13,
run to convergence) and, on request, compensated by Eq. 21. The result says
which pairs were used, which were rejected and why, the residual of each pair
and the uncertainty, and carries the quality gate's verdict
(:mod:`celld.calib.quality`). A session that gathers the pairs capture by
capture drives it: :mod:`celld.calib.session`.

Compensation: with ``compensate`` set and a finite e_icp, the transform to
store (and accept) is the compensated one, ``T_base_cam e_icp`` (Eq. 21);
:attr:`CalibrationResult.stored` says which one it is. Without a verification
cloud, or with an infinite e_icp, nothing can compensate: the estimate is
stored and the quality report says why.

Range bias (``range_bias = "estimate"``, time-of-flight cameras): the bias
of the camera's range on bare metal is estimated with the transform
(:mod:`celld.calib.rangebias`: the detections' finish steps and, when the
centres lie on metal, the spread of their rays), the centres on metal and
the verification cloud's metal points are corrected by it before Algorithm 1
and e_icp, and the result carries it with its 1-sigma: the daemon applies it
to every scan it places with the calibration.

Methods:

- ``robust`` (default): :func:`~celld.calib.robust.solve_robust`, every
  consistent pair;
- ``svd``: Eq. 9-12 on every detected pair (the paper's Table 1);
- ``algorithm1``: the optimum pool of Algorithm 1 (needs the verification cloud).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from celld import se3
from celld.calib.algorithm1 import STEP_SCHEMA, Algorithm1Result, run_algorithm1
from celld.calib.dataset import MAX_CAMERA_DISTANCE
from celld.calib.detect import detect_flange
from celld.calib.detect_params import DetectParams
from celld.calib.flange import FlangeModel
from celld.calib.metrics import E_ICP_SCHEMA, IcpMetric, IcpParams, IcpVerifier, compensate, cost_function, model_cloud_with_normals
from celld.calib.pairs import Detections
from celld.calib.quality import OUTLIER_FLOOR, QUALITY_SCHEMA, CalibrationQuality, QualityParams, assess_calibration
from celld.calib.rangebias import MODES as RANGE_BIAS_MODES
from celld.calib.rangebias import (
    RANGE_BIAS_SCHEMA,
    RangeBiasData,
    RangeBiasFit,
    correct_range_bias,
    solve_range_bias,
    solve_robust_range_bias,
)
from celld.calib.rigid import UNCERTAINTY_SCHEMA, Array, Uncertainty, check_pairs, pair_residuals, solve_rigid
from celld.calib.robust import RejectedPair, RobustParams, solve_robust
from celld.config import CalibrationConfig
from celld.errors import CalibrationError, DetectionError, InputError
from celld.schemadoc import array, boolean, const, enum, integer, matrix4, nullable, number, obj, one_of, string, texts

METHODS = ("robust", "svd", "algorithm1")
# Which transform a calibration stores: the estimate, or the estimate compensated by Eq. 21.
STORED = ("estimate", "compensated")
# Margin around the flange model when the verification cloud is cropped, m.
_VERIFICATION_MARGIN = 0.005
# Verification points this far outside the tool flange's radius still count as
# its metal (a point read long at a tilt moves sideways by b sin(theta)), m.
_METAL_MARGIN = 0.0015


@dataclass(frozen=True)
class SolveParams:
    """How a session is solved.

    Attributes
    ----------
    method : str
        ``robust``, ``svd`` or ``algorithm1``.
    robust : RobustParams
    icp : IcpParams
        e_icp registration (Algorithm 1's ranking; the final score runs it to convergence).
    model_spacing : float
        Point spacing of the flange model cloud for ICP, metres.
    cost : str
        Algorithm 1's cost metric: ``translation`` or ``se3``.
    work_radius : float
        r of the ``se3`` cost, metres.
    e_required : float
        Algorithm 1's target cost, metres.
    k_max : int | None
        Algorithm 1's bound on new pairs (None: all of them).
    compensate : bool
        Store the estimate compensated by Eq. 21 (needs a verification cloud).
    with_scale : bool
        Estimate the scale of Eq. 11.
    range_bias : str
        ``"estimate"``: estimate the range bias on metal with the transform
        (:mod:`celld.calib.rangebias`); ``"none"``: the scanner has none.
    quality : QualityParams
        Thresholds of the quality gate.
    """

    method: str = "robust"
    robust: RobustParams = field(default_factory=lambda: RobustParams(min_threshold=OUTLIER_FLOOR))
    icp: IcpParams = field(default_factory=IcpParams)
    model_spacing: float = 0.002
    cost: str = "translation"
    work_radius: float = 0.5
    e_required: float = 0.0005
    k_max: int | None = None
    compensate: bool = False
    with_scale: bool = False
    range_bias: str = "none"
    quality: QualityParams = field(default_factory=QualityParams)

    @classmethod
    def from_config(cls, cal: CalibrationConfig, **overrides: Any) -> SolveParams:
        """The parameters of a cell's ``[calibration]`` section; ``overrides`` win."""
        values: dict[str, Any] = {
            "method": cal.method,
            "icp": IcpParams(max_distances=(cal.icp_max_distance,), max_points=cal.icp_points),
            "model_spacing": cal.model_spacing,
            "cost": cal.cost,
            "work_radius": cal.work_radius,
            "e_required": cal.e_required,
            "k_max": cal.k_max,
            "compensate": cal.compensate,
            "range_bias": cal.range_bias or "none",
            "robust": RobustParams(min_threshold=cal.outlier_floor),
            "quality": QualityParams(arm_error_prior=cal.arm_error_prior, work_radius=cal.work_radius, outlier_floor=cal.outlier_floor),
        }
        values.update(overrides)
        return cls(**values)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        cost_function(self.cost, self.work_radius)  # validates the name and radius
        if self.range_bias not in RANGE_BIAS_MODES:
            raise InputError(f"range_bias: expected one of {', '.join(RANGE_BIAS_MODES)}, got {self.range_bias!r}")
        if self.range_bias == "estimate" and self.with_scale:
            raise InputError("range_bias estimate and with_scale exclude each other: a free scale absorbs a range bias")


@dataclass(frozen=True)
class CalibrationResult:
    """An eye-on-base calibration and its report.

    Attributes
    ----------
    T_base_cam : (4, 4) array
        The estimate of the chosen method, metres (before Eq. 21; the
        transform to store is :attr:`T_base_cam_stored`).
    method : str
    pair_ids : tuple of str
        The pairs the estimate uses, in pair order.
    residuals : (k,) array
        Residual of each used pair, metres, aligned with ``pair_ids``.
    rejected : tuple of RejectedPair
        Pairs left out (failed detection, inconsistent, or outside Algorithm
        1's pool), each with its reason.
    uncertainty : Uncertainty
        Of ``T_base_cam`` (convention of :mod:`celld.calib.rigid`).
    all_residuals : dict
        Residual of every pair with a centre against ``T_base_cam``, metres.
    e_icp : IcpMetric | None
        Eq. 13 of the estimate against the verification cloud.
    T_base_cam_compensated : (4, 4) array | None
        Eq. 21, when asked for and e_icp is finite.
    algorithm1 : Algorithm1Result | None
        Algorithm 1 over the pairs in order, when a verification cloud is there.
    n_pairs : int
        Pairs in the session.
    quality : CalibrationQuality
        The quality gate's verdict on the estimate.
    stored : str
        ``"compensated"`` when the transform to store is Eq. 21's, else ``"estimate"``.
    range_bias : RangeBiasFit | None
        The range bias on metal estimated with the transform (``range_bias =
        "estimate"``), None when not estimated.
    gated : tuple of str
        Pairs the robust estimate used that the quality gate found to be
        outliers; the estimate was solved again without them (they are in
        ``rejected`` with that reason).
    """

    T_base_cam: Array
    method: str
    pair_ids: tuple[str, ...]
    residuals: Array
    rejected: tuple[RejectedPair, ...]
    uncertainty: Uncertainty
    all_residuals: dict[str, float]
    e_icp: IcpMetric | None
    T_base_cam_compensated: Array | None
    algorithm1: Algorithm1Result | None
    n_pairs: int
    quality: CalibrationQuality
    stored: str = "estimate"
    range_bias: RangeBiasFit | None = None
    # Pairs the robust estimate used that its quality gate found to be outliers: left out and solved again.
    gated: tuple[str, ...] = ()

    @property
    def bias(self) -> float:
        """The range bias on metal to apply with the calibration, m (0 when not estimated)."""
        return 0.0 if self.range_bias is None else self.range_bias.bias

    @property
    def T_base_cam_stored(self) -> Array:
        """The transform to store and accept: Eq. 21's when :attr:`stored` is ``"compensated"``."""
        if self.stored == "compensated" and self.T_base_cam_compensated is not None:
            return self.T_base_cam_compensated
        return self.T_base_cam

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready report: transforms in metres, residuals in mm.

        ``T_base_cam`` is the transform to store (:attr:`T_base_cam_stored`),
        ``stored`` says which one it is and ``T_base_cam_estimate`` is the
        estimate before Eq. 21; ``range_bias`` holds the range bias on metal
        (``bias_mm``, ``std_mm``; 0 with mode ``none``). Its shape:
        :data:`REPORT_SCHEMA`.
        """
        out: dict[str, Any] = {
            "T_base_cam": self.T_base_cam_stored.tolist(),
            "stored": self.stored,
            "T_base_cam_estimate": self.T_base_cam.tolist(),
            "method": self.method,
            "pairs": list(self.pair_ids),
            "residuals_mm": (self.residuals * 1e3).tolist(),
            "rejected": [r.id for r in self.rejected],
            "rejected_detail": [
                {"id": r.id, "reason": r.reason, "residual_mm": r.residual * 1e3 if np.isfinite(r.residual) else None}
                for r in self.rejected
            ],
            "rms_mm": float(np.sqrt(np.mean(self.residuals**2)) * 1e3),
            "uncertainty": _finite_or_none(self.uncertainty.as_dict()),
            "n_pairs": self.n_pairs,
            "e_icp": None if self.e_icp is None else self.e_icp.as_dict(),
            "T_base_cam_compensated": None if self.T_base_cam_compensated is None else self.T_base_cam_compensated.tolist(),
            "quality": self.quality.as_dict(),
            "range_bias": {"mode": "none", "bias_mm": 0.0} if self.range_bias is None else self.range_bias.as_dict(),
        }
        if self.algorithm1 is not None:
            a = self.algorithm1
            out["algorithm1"] = {
                "pool": list(a.pool_ids),
                "cost_mm": a.cost * 1e3 if np.isfinite(a.cost) else None,
                "reached": a.reached,
                "pairs_used": a.n_pairs_used,
                "T_base_cam": None if a.T_base_cam is None else a.T_base_cam.tolist(),
                "steps": [s.as_dict() for s in a.steps],
            }
        return out


# The JSON shape of CalibrationResult.as_dict (its T_base_cam names in the base frame; a scanner on
# the arm's report names them in its link's frame: celld.calib.mount.in_frame, in_any_frame).
REPORT_SCHEMA = obj(
    "A calibration's solve: the transform stored and the estimate, the pairs used and left out with their residuals, "
    "the uncertainty, e_icp (Eq. 13), Eq. 21's compensated transform, the quality gate's verdict, the range bias on "
    "metal and Algorithm 1's history. Transforms in metres, residuals in mm.",
    {
        "T_base_cam": matrix4("The transform to store (stored says which)."),
        "stored": enum(STORED, "T_base_cam is the estimate or Eq. 21's compensated estimate."),
        "T_base_cam_estimate": matrix4("The estimate before Eq. 21."),
        "method": enum(METHODS, "The estimator that gave the estimate."),
        "pairs": texts("The pairs the estimate uses, in pair order."),
        "residuals_mm": array(number(), "Residual of each pair used, aligned with pairs."),
        "rejected": texts("Pairs left out."),
        "rejected_detail": array(
            obj(
                "A pair left out, and why.",
                {"id": string(), "reason": string(), "residual_mm": number(null=True)},
                ("id", "reason", "residual_mm"),
            )
        ),
        "rms_mm": number("RMS residual of the pairs used."),
        "uncertainty": UNCERTAINTY_SCHEMA,
        "n_pairs": integer("Pairs in the session.", lo=0),
        "e_icp": nullable(E_ICP_SCHEMA, "e_icp of the estimate; null without a verification cloud."),
        "T_base_cam_compensated": nullable(matrix4(), "Eq. 21's transform, when asked for and e_icp is finite; else null."),
        "quality": QUALITY_SCHEMA,
        "range_bias": one_of(
            "The range bias on metal: estimated with the transform, or not (mode none).",
            RANGE_BIAS_SCHEMA,
            obj("Not estimated.", {"mode": const("none"), "bias_mm": const(0.0)}, ("mode", "bias_mm")),
        ),
        "algorithm1": obj(
            "Algorithm 1 over the pairs in order (when there is a verification cloud).",
            {
                "pool": texts("The final pool."),
                "cost_mm": number("Its cost, null when infinite.", null=True),
                "reached": boolean("The cost reached e_required."),
                "pairs_used": integer(lo=0),
                "T_base_cam": nullable(matrix4(), "The pool's transform, null when degenerate."),
                "steps": array(STEP_SCHEMA, "Every step, k = 0 first."),
            },
            ("pool", "cost_mm", "reached", "pairs_used", "T_base_cam", "steps"),
        ),
    },
    (
        "T_base_cam",
        "stored",
        "T_base_cam_estimate",
        "method",
        "pairs",
        "residuals_mm",
        "rejected",
        "rejected_detail",
        "rms_mm",
        "uncertainty",
        "n_pairs",
        "e_icp",
        "T_base_cam_compensated",
        "quality",
        "range_bias",
    ),
)


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def solve_pairs(
    ids: Sequence[str],
    P_base: ArrayLike,
    P_cam: ArrayLike,
    params: SolveParams = SolveParams(),
    verifier: IcpVerifier | None = None,
    pre_rejected: Sequence[RejectedPair] = (),
    n_pairs: int | None = None,
    range_data: RangeBiasData | None = None,
) -> CalibrationResult:
    """Solve ``T_base_cam`` from detected centre pairs (the pure core).

    With the robust method, pairs the estimate used that its quality gate
    finds to be outliers are left out once and the estimate solved again
    (:attr:`CalibrationResult.gated`; each is in ``rejected`` with why),
    when enough pairs remain for the gate.

    Parameters
    ----------
    ids : sequence of str
        Pair ids in captured order.
    P_base, P_cam : (n, 3) arrays
        Flange centres in the base and camera frames, metres.
    params : SolveParams
    verifier : IcpVerifier | None
        e_icp against the verification cloud; without it Algorithm 1 and
        e_icp are skipped (and ``algorithm1`` refused).
    pre_rejected : sequence of RejectedPair
        Pairs already rejected upstream (failed detections), reported as such.
    n_pairs : int | None
        Pairs in the session (default: detected plus pre-rejected).
    range_data : RangeBiasData | None
        The pairs' finish steps and where their centres lie, for
        ``range_bias = "estimate"`` (:mod:`celld.calib.rangebias`).

    Raises
    ------
    InputError, CalibrationError
        Malformed or too few pairs, coincident or collinear positions (the
        rotation is undetermined; coplanar ones are solved and their
        conditioning reported by the quality gate), no consistent set, or
        ``algorithm1`` without a verification cloud, or a range bias to
        estimate without the data that observe it.
    """
    P_b, P_c = check_pairs(P_base, P_cam)
    P_c_measured = P_c
    ids_t = tuple(str(i) for i in ids)
    if len(ids_t) != len(P_b):
        raise InputError(f"ids: expected {len(P_b)} pair ids, got {len(ids_t)}")
    if params.method == "algorithm1" and verifier is None:
        raise CalibrationError("method algorithm1 needs a verification cloud (the session has none)")
    cost = cost_function(params.cost, params.work_radius)

    # The range bias first (robust, on the consistent pairs): Algorithm 1 and
    # e_icp then see centres and a verification cloud corrected by it.
    rb = rob_rb = None
    if params.range_bias == "estimate":
        if range_data is None:
            raise CalibrationError("range_bias = estimate: the session gives no finish steps nor centre finish to observe it")
        if range_data.step_bias.shape != (len(P_b),):
            raise InputError(f"range_data: expected {len(P_b)} steps, got {range_data.step_bias.shape[0]}")
        rob_rb, rb = solve_robust_range_bias(P_b, P_c, range_data, ids_t, params.robust)
        if range_data.centres_on_metal:
            P_c = correct_range_bias(P_c, rb.bias)
        if verifier is not None:
            verifier = verifier.with_range_bias(rb.bias)

    a1 = None
    if verifier is not None and len(P_b) >= 4:
        a1 = run_algorithm1(ids_t, P_b, P_c, verifier, cost, e_required=params.e_required, k_max=params.k_max, with_scale=params.with_scale)

    # The robust estimate leaves out, once, the pairs the quality gate finds to be
    # outliers among those it used (its consistency test and the gate's read the
    # noise differently when an arm's pose-dependent error gives the residuals a
    # long tail), and is solved and judged again; each such pair is reported.
    gated: dict[int, str] = {}
    est = _estimate(ids_t, P_b, P_c, P_c_measured, params, verifier, pre_rejected, a1, rb, rob_rb, range_data, gated)
    flagged = {ids_t.index(q.id): q.residual for q in est.quality.pairs if q.used and q.outlier}
    if params.method == "robust" and rb is None and flagged and len(est.used) - len(flagged) >= params.quality.min_pairs:
        gated = {
            i: f"an outlier of the quality gate (residual {r * 1e3:.3f} mm) among the pairs the robust estimate used: "
            "left out, and the estimate solved again"
            for i, r in flagged.items()
        }
        est = _estimate(ids_t, P_b, P_c, P_c_measured, params, verifier, pre_rejected, a1, rb, rob_rb, range_data, gated)
    return CalibrationResult(
        T_base_cam=est.T,
        method=params.method,
        pair_ids=tuple(ids_t[i] for i in est.used),
        residuals=est.residuals[est.used],
        rejected=tuple(est.rejected),
        uncertainty=est.uncertainty,
        all_residuals={i: float(r) for i, r in zip(ids_t, est.residuals)},
        e_icp=est.e_icp,
        T_base_cam_compensated=est.T_compensated,
        algorithm1=a1,
        n_pairs=n_pairs if n_pairs is not None else len(P_b) + len(pre_rejected),
        quality=est.quality,
        stored="compensated" if est.T_compensated is not None else "estimate",
        gated=tuple(ids_t[i] for i in sorted(gated)),
        range_bias=est.rb,
    )


def range_bias_data(params: SolveParams, flange: FlangeModel | None, detections: Detections) -> RangeBiasData | None:
    """What the detections say about the range bias, when ``params`` estimate it (else None).

    Raises
    ------
    CalibrationError
        A range bias to estimate without a flange preset (it says which surfaces are bare metal).
    """
    if params.range_bias != "estimate":
        return None
    if flange is None:
        raise CalibrationError("range_bias = estimate needs the flange preset: it says which surfaces are bare metal")
    steps = detections.steps if len(detections.steps) == len(detections.ids) else (None,) * len(detections.ids)
    return RangeBiasData.from_steps(flange.circle_on_metal, steps)


def verifier_from_cloud(
    P_v_cam: ArrayLike,
    T_base_flange_v: ArrayLike,
    flange: FlangeModel,
    params: SolveParams = SolveParams(),
    detect_params: DetectParams | None = None,
) -> IcpVerifier:
    """e_icp against a verification capture, cropped around the flange found in it.

    The crop is the cylinder the flange model fills, about the detected
    centre and along the detected normal, plus a margin: what the model
    cannot explain (other links, the table) stays out of the registration.
    The points of the tool flange are marked as bare metal, so that a range
    bias can be corrected (:meth:`~celld.calib.metrics.IcpVerifier.with_range_bias`).
    The detection only says where the flange is in the cloud. ``P_v_cam`` may
    be organized (H, W, 3) with NaN for no return.

    Raises
    ------
    CalibrationError
        The flange is not found in the verification cloud.
    """
    P_v = np.asarray(P_v_cam, dtype=np.float64)
    try:
        det = detect_flange(P_v, flange, detect_params)  # organized if given so: the detector uses the grid
    except DetectionError as exc:
        raise CalibrationError(f"verification cloud: {exc}") from exc
    P_v = P_v.reshape(-1, 3)
    P_v = P_v[np.all(np.isfinite(P_v), axis=1)]
    P_model, N_model = model_cloud_with_normals(flange, params.model_spacing)
    m = _VERIFICATION_MARGIN
    r_max = float(np.max(np.linalg.norm(P_model[:, :2], axis=1))) + m
    d = P_v - det.center
    h = d @ det.normal  # along the flange's +z (toward the camera)
    radial = np.linalg.norm(d - np.outer(h, det.normal), axis=1)
    keep = (h >= P_model[:, 2].min() - m) & (h <= P_model[:, 2].max() + m) & (radial <= r_max)
    P_v = P_v[keep]
    # The points on bare metal, for a range bias correction: the tool flange is
    # the cylinder of its outer diameter (a metal point read long moves along
    # its ray, so heights cannot tell); all of it on a bare-metal wrist.
    on_metal = radial[keep] <= flange.outer_diameter / 2 + _METAL_MARGIN
    if flange.wrist_finish == "metal":
        on_metal[:] = True
    return IcpVerifier(P_v, P_model, T_base_flange_v, params.icp, normals_flange=N_model, on_metal=on_metal)


@dataclass(frozen=True)
class _Estimate:
    """One estimate of :func:`solve_pairs` and what was judged with it."""

    T: Array
    used: list[int]
    uncertainty: Uncertainty
    rejected: list[RejectedPair]
    e_icp: IcpMetric | None
    T_compensated: Array | None
    quality: CalibrationQuality
    residuals: Array  # (n,) every pair's, against T, m
    rb: RangeBiasFit | None


def _estimate(
    ids_t: tuple[str, ...],
    P_b: Array,
    P_c: Array,
    P_c_measured: Array,
    params: SolveParams,
    verifier: IcpVerifier | None,
    pre_rejected: Sequence[RejectedPair],
    a1: Algorithm1Result | None,
    rb: RangeBiasFit | None,
    rob_rb: Any,
    range_data: RangeBiasData | None,
    gated: Mapping[int, str],
) -> _Estimate:
    """One estimate of :func:`solve_pairs` by its method, its e_icp, compensation and quality verdict.

    ``gated`` maps pairs left out by an earlier verdict (robust method) to why.
    """
    rejected = list(pre_rejected)
    if params.method == "robust" and rb is not None and rob_rb is not None:
        # The joint fit on the consistent pairs: its covariance carries the bias's.
        T, used, unc, scale = rb.T_base_cam, list(rob_rb.inliers), rb.uncertainty, 1.0
        rejected += list(rob_rb.rejected)
    elif params.method == "robust":
        keep = [i for i in range(len(P_b)) if i not in gated]
        rob = solve_robust(P_b[keep], P_c[keep], ids=[ids_t[i] for i in keep], params=replace(params.robust, with_scale=params.with_scale))
        T, used, unc, scale = rob.T_base_cam, [keep[j] for j in rob.inliers], rob.fit.uncertainty, rob.fit.scale
        rejected += [replace(r, index=keep[r.index]) for r in rob.rejected]
        rejected += [RejectedPair(ids_t[i], i, float("nan"), why) for i, why in gated.items()]
    elif params.method == "svd" and rb is not None and range_data is not None:
        rb = solve_range_bias(P_b, P_c_measured, range_data, ids=ids_t)  # every pair, as measured
        T, used, unc, scale = rb.T_base_cam, list(range(len(P_b))), rb.uncertainty, 1.0
        if range_data.centres_on_metal:
            P_c = rb.P_cam_corrected
    elif params.method == "svd":
        fit = solve_rigid(P_b, P_c, with_scale=params.with_scale)
        T, used, unc, scale = fit.T_dst_src, list(range(len(P_b))), fit.uncertainty, fit.scale
    else:
        if a1 is None or a1.fit is None or a1.T_base_cam is None:
            raise CalibrationError("Algorithm 1 found no solvable pool of four pairs")
        used = sorted(ids_t.index(i) for i in a1.pool_ids)
        T, unc, scale = a1.T_base_cam, a1.fit.uncertainty, a1.fit.scale
        rejected += [RejectedPair(ids_t[i], i, float("nan"), "not in Algorithm 1's final pool") for i in range(len(P_b)) if i not in used]
    d_cam = float(np.linalg.norm(T[:3, 3]))
    if d_cam > MAX_CAMERA_DISTANCE:
        raise CalibrationError(
            f"the solve puts the camera {d_cam:.3g} m from the robot base, which no cell has (at most "
            f"{MAX_CAMERA_DISTANCE:g} m): the poses and the clouds are likely in different units (poses must be "
            "in metres, clouds in the session's declared unit)"
        )
    res_all = pair_residuals(T, P_b, P_c, scale)
    for k, r in enumerate(rejected):
        if r.id in ids_t and not np.isfinite(r.residual):
            rejected[k] = replace(r, residual=float(res_all[ids_t.index(r.id)]))

    e_final = None
    T_comp = None
    notes = []
    if verifier is not None:
        e_final = verifier.strict()(T)
        if params.compensate and e_final.ok:
            T_comp = compensate(T, e_final)
    if params.compensate and T_comp is None:
        why = "no verification cloud" if e_final is None else f"e_icp is infinite ({e_final.reason})"
        notes.append(f"compensation (Eq. 21) was asked for but not applied: {why}; the estimate is stored")
    # The verification flange's axis in the camera frame, by the estimate: e_icp's
    # turn about it is fixed only by the flange's holes (quality module).
    T_base_flange_v = getattr(verifier, "T_base_flange_v", None)
    axis_cam = centre_cam = None
    if T_base_flange_v is not None:
        T_cam_flange_v = se3.invert(T) @ np.asarray(T_base_flange_v)
        axis_cam, centre_cam = T_cam_flange_v[:3, 2], T_cam_flange_v[:3, 3]
    quality = assess_calibration(
        ids_t,
        P_b,
        P_c,
        T,
        used=used,
        uncertainty=unc,
        scale=scale,
        with_scale=params.with_scale,
        rejected=rejected,
        e_icp=e_final,
        flange_axis_cam=axis_cam,
        flange_centre_cam=centre_cam,
        compensated=T_comp is not None,
        notes=notes,
        range_bias=rb,
        params=params.quality,
    )
    return _Estimate(T, used, unc, rejected, e_final, T_comp, quality, res_all, rb)
