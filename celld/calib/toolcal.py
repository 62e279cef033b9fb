"""Tool calibration: the SRM tip in the TCP frame from flange poses and scanner measurements (pure).

The welding tool's tip (and the torch, which sits at ``torch_offset`` along
-x of the tool frame, whose origin the tip is) must be measured, not typed.
The robot presents the tool to the scanner at several orientations; at each
the robot reports ``T_base_tcp_i = (R_i, o_i)`` and the scanner measures the
tip's centre ``p_base_i`` (its cloud placed with the current hand-eye
calibration ``T_base_cam``). The tip ``t = p_tcp_tip`` is fixed in the TCP
frame, so, per pose::

    p_base_i = R_i t + o_i + b                                   (T1)

``b`` is a constant offset in the base frame: what the hand-eye calibration
and the arm's kinematics get wrong, locally, where the tool is presented (a
residual translation of ``T_base_cam``, a time-of-flight range bias on the
tip). Solving for it as well makes ``t`` a differential measurement: it is
fixed by how the tip moves as the flange turns, not by where the scanner
puts it. The price: with one orientation (or turns about one axis only) the
component of ``t`` along that axis and ``b`` cannot be told apart. Hence the
orientation-spread check below: turns about at least two axes are needed.

Stacked over the poses, (T1) is the linear least-squares problem::

    [R_i  I] [t; b] = p_base_i - o_i,   i = 1..n                 (T2)

solved as is (``numpy.linalg.lstsq``), with a robust step around it in the
spirit of :mod:`celld.calib.robust` (same :class:`RobustParams`, same
per-pose chi-3 threshold, rejected poses reported as
:class:`~celld.calib.robust.RejectedPair` with the residual and the
threshold it failed):

1. least median of squares over minimal three-pose samples of (T2);
2. a noise scale from that median (chi-3, as the pairs of a rigid fit);
3. threshold, least squares on the inliers, new noise scale, until the
   inlier set settles.

The uncertainty of ``t`` is first order: ``sigma^2 (A^T A)^-1`` of (T2) on
the inliers, ``sigma`` per axis from the residuals with the six degrees of
freedom taken out, never below :attr:`ToolCalParams.sigma_floor`.

Orientation spread: eliminating ``b`` from (T2) leaves the normal matrix
``S = sum_i (R_i - R_mean)^T (R_i - R_mean)`` for ``t``; the square root of
its smallest eigenvalue over ``n`` is the *spread* (rad, about): the RMS turn
of the flange seen by the worst-fixed direction of ``t``. It is zero for
turns about one axis (and for one orientation), whatever the noise.

Verdicts (:data:`VERDICTS`; the first that applies wins, every reason is
listed): ``too_few_poses`` (fewer tip measurements than
:attr:`~ToolCalParams.min_poses`), ``poor_orientation_spread`` (spread below
:attr:`~ToolCalParams.min_spread`), ``poor_data`` (too many outliers, a
large RMS residual, or a tip 1-sigma beyond
:attr:`~ToolCalParams.max_tip_std`), ``ok``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld.calib.robust import CHI2_3_MEDIAN, RejectedPair, RobustParams, outliers
from celld.errors import CalibrationError, InputError
from celld.schemadoc import array, boolean, enum, integer, number, obj, string, texts, vector

Array = NDArray[np.float64]

VERDICTS = ("ok", "too_few_poses", "poor_orientation_spread", "poor_data")
# Fewest poses (T2) is solved from: three (two leave b and the axis of their relative turn free).
MIN_SOLVE_POSES = 3
# Minimal samples whose own spread is below this (rad) make no hypothesis (their solve is ill-posed).
_MIN_SAMPLE_SPREAD = 0.02


@dataclass(frozen=True)
class ToolCalParams:
    """Parameters of :func:`solve_tool_tip` and its verdict (SI units, rad).

    Attributes
    ----------
    min_poses : int
        Fewest tip measurements for an ``ok`` verdict.
    min_spread : float
        Smallest orientation spread (module docstring) for an ``ok`` verdict, rad.
    max_rms : float
        Largest RMS residual of the poses used, m.
    max_outlier_fraction : float
        Largest share of outliers among the poses.
    max_tip_std : float
        Largest 1-sigma of the tip along any TCP axis, m.
    sigma_floor : float
        Noise per axis the uncertainty uses at least, m (exact or lucky data
        would otherwise claim a perfect tip).
    robust : RobustParams
        The robust step's threshold and sampling (:mod:`celld.calib.robust`).
    """

    min_poses: int = 6
    min_spread: float = 0.08
    max_rms: float = 0.3e-3
    max_outlier_fraction: float = 0.25
    max_tip_std: float = 0.1e-3
    sigma_floor: float = 0.02e-3
    robust: RobustParams = field(default_factory=lambda: RobustParams(min_threshold=0.2e-3))

    def __post_init__(self) -> None:
        if self.min_poses < MIN_SOLVE_POSES:
            raise InputError(f"min_poses: expected >= {MIN_SOLVE_POSES}, got {self.min_poses}")
        for name in ("min_spread", "max_rms", "max_tip_std", "sigma_floor"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise InputError(f"{name}: expected a finite value > 0, got {v!r}")
        if not 0.0 <= self.max_outlier_fraction < 1.0:
            raise InputError(f"max_outlier_fraction: expected 0 <= value < 1, got {self.max_outlier_fraction!r}")


@dataclass(frozen=True)
class ToolTipFit:
    """Result of :func:`solve_tool_tip`.

    Attributes
    ----------
    p_tcp_tip : (3,) array
        The tip's centre in the TCP frame, m (``t`` of T1).
    tip_std : (3,) array
        Its 1-sigma along the TCP axes, m (inf when the spread leaves it free).
    offset_base : (3,) array
        ``b`` of T1, m: where the scanner and the arm disagree at the tool's place.
    offset_std : (3,) array
        Its 1-sigma, m.
    ids : tuple of str
        Pose ids, in input order.
    residuals : (n,) array
        Residual norm of every pose against the fit, m.
    inliers : tuple of int
        Indices of the poses used.
    rejected : tuple of RejectedPair
        The others, each with its residual and why.
    sigma : float
        Noise per axis the uncertainty uses, m.
    sigma_source : str
        ``"residuals"`` or ``"floor"``.
    spread : float
        Orientation spread of the poses used, rad (module docstring).
    spread_axis_tcp : (3,) array
        The direction of ``t`` (TCP frame) it is smallest along.
    verdict : str
        One of :data:`VERDICTS`.
    reasons, warnings : tuple of str
    """

    p_tcp_tip: Array
    tip_std: Array
    offset_base: Array
    offset_std: Array
    ids: tuple[str, ...]
    residuals: Array
    inliers: tuple[int, ...]
    rejected: tuple[RejectedPair, ...]
    sigma: float
    sigma_source: str
    spread: float
    spread_axis_tcp: Array
    verdict: str
    reasons: tuple[str, ...]
    warnings: tuple[str, ...]

    @property
    def passed(self) -> bool:
        return self.verdict == "ok"

    @property
    def rms(self) -> float:
        """RMS residual norm of the poses used, m."""
        r = self.residuals[list(self.inliers)]
        return float(np.sqrt(np.mean(r**2))) if len(r) else math.nan

    def as_dict(self) -> dict[str, Any]:
        """The report in message units (mm, deg): verdict, reasons, each pose's residual and why it is out (:data:`FIT_SCHEMA`)."""
        out_reason = {r.index: r.reason for r in self.rejected}
        used = set(self.inliers)
        return {
            "verdict": self.verdict,
            "passed": self.passed,
            "reasons": list(self.reasons),
            "warnings": list(self.warnings),
            "poses": [
                {
                    "id": pid,
                    "residual_mm": _finite_or_none(self.residuals[i] * 1e3),
                    "used": i in used,
                    "outlier": i in out_reason,
                    "reason": out_reason.get(i, ""),
                }
                for i, pid in enumerate(self.ids)
            ],
            "outliers": [r.id for r in self.rejected],
            "n_used": len(self.inliers),
            "rms_mm": _finite_or_none(self.rms * 1e3),
            "sigma_mm": self.sigma * 1e3,
            "sigma_source": self.sigma_source,
            "spread_deg": math.degrees(self.spread),
            "spread_axis_tcp": self.spread_axis_tcp.tolist(),
            "tip_std_mm": [_finite_or_none(v * 1e3) for v in self.tip_std],
            "offset_base_mm": (self.offset_base * 1e3).tolist(),
            "offset_std_mm": [_finite_or_none(v * 1e3) for v in self.offset_std],
        }


# The JSON shape of ToolTipFit.as_dict.
FIT_SCHEMA = obj(
    "The verdict on a point of the tool measured in the TCP frame (celld.calib.toolcal): why, each pose's residual and "
    "whether it is an outlier, the noise, the orientation spread and the point's 1-sigma; null where not finite.",
    {
        "verdict": enum(VERDICTS, "Only ok passes; accept refuses the others unless forced."),
        "passed": boolean(),
        "reasons": texts("Why the verdict is not ok."),
        "warnings": texts("What does not fail the verdict but should be known."),
        "poses": array(
            obj(
                "One pose.",
                {"id": string(), "residual_mm": number(null=True), "used": boolean(), "outlier": boolean(), "reason": string()},
                ("id", "residual_mm", "used", "outlier", "reason"),
            ),
            "Every pose with a measurement: residual against the fit, used, outlier, and why.",
        ),
        "outliers": texts("Ids of the outliers."),
        "n_used": integer(lo=0),
        "rms_mm": number("RMS residual of the poses used.", null=True),
        "sigma_mm": number("Noise per axis the uncertainty uses."),
        "sigma_source": enum(("residuals", "floor")),
        "spread_deg": number("Orientation spread of the poses used along the worst-fixed direction of the point."),
        "spread_axis_tcp": vector("That direction, TCP frame.", 3),
        "tip_std_mm": vector("1-sigma of the point along TCP x, y, z.", 3, null_items=True),
        "offset_base_mm": vector("Where the scanner and the arm disagree at the tool's place (solved with the point), base frame.", 3),
        "offset_std_mm": vector("Its 1-sigma.", 3, null_items=True),
    },
    (
        "verdict",
        "passed",
        "reasons",
        "warnings",
        "poses",
        "outliers",
        "n_used",
        "rms_mm",
        "sigma_mm",
        "sigma_source",
        "spread_deg",
        "spread_axis_tcp",
        "tip_std_mm",
        "offset_base_mm",
        "offset_std_mm",
    ),
)


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def check_tool_poses(T_base_tcp: ArrayLike, P_base_tip: ArrayLike) -> tuple[Array, Array]:
    """Validate the poses (n, 4, 4) and the measured tips (n, 3) where they enter a solve.

    Raises
    ------
    InputError
        Wrong shapes, lengths that differ, values that are not finite, a
        rotation block that is not a rotation.
    """
    T = np.asarray(T_base_tcp, dtype=np.float64)
    P = np.asarray(P_base_tip, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"T_base_tcp: expected an (n, 4, 4) array of poses, got shape {T.shape}")
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"P_base_tip: expected an (n, 3) array of points, got shape {P.shape}")
    if len(T) != len(P):
        raise InputError(f"expected one tip per pose, got {len(T)} poses and {len(P)} tips")
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(P))):
        raise InputError("T_base_tcp and P_base_tip: expected finite values, got NaN or infinity")
    R = T[:, :3, :3]
    ortho = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2)) if len(T) else np.zeros(0)
    det = np.linalg.det(R) if len(T) else np.zeros(0)
    bad = np.flatnonzero((ortho > 1e-6) | (np.abs(det - 1.0) > 1e-6) | np.any(np.abs(T[:, 3] - [0, 0, 0, 1]) > 1e-9, axis=1))
    if len(bad):
        raise InputError(f"T_base_tcp[{int(bad[0])}]: expected a homogeneous transform with a proper rotation")
    return T, P


def _system(T: Array, P: Array) -> tuple[Array, Array]:
    """(T2) stacked: A (3n, 6) and y (3n,)."""
    n = len(T)
    A = np.zeros((3 * n, 6))
    A[:, :3] = T[:, :3, :3].reshape(3 * n, 3)
    A[:, 3:] = np.tile(np.eye(3), (n, 1))
    y = (P - T[:, :3, 3]).reshape(3 * n)
    return A, y


def _residuals(T: Array, P: Array, x: Array) -> Array:
    """Residual norm of each pose of (T1) at ``x = [t, b]``, m."""
    pred = np.einsum("nij,j->ni", T[:, :3, :3], x[:3]) + T[:, :3, 3] + x[3:]
    return np.asarray(np.linalg.norm(pred - P, axis=1), dtype=np.float64)


def orientation_spread(R: ArrayLike) -> tuple[float, Array]:
    """The spread of rotations (n, 3, 3), rad, and the TCP direction it is smallest along (module docstring)."""
    Rs = np.asarray(R, dtype=np.float64)
    if len(Rs) < 2:
        return 0.0, np.array([0.0, 0.0, 1.0])
    D = Rs - Rs.mean(axis=0)
    S = np.einsum("nji,njk->ik", D, D) / len(Rs)
    w, V = np.linalg.eigh(S)
    return float(math.sqrt(max(w[0], 0.0))), np.asarray(V[:, 0], dtype=np.float64)


def _lstsq(T: Array, P: Array) -> Array:
    A, y = _system(T, P)
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    return np.asarray(x, dtype=np.float64)


def _lmeds(T: Array, P: Array, params: RobustParams) -> tuple[Array, float]:
    """Least median of squares over minimal three-pose samples of (T2): ``[t, b]`` and its median squared residual."""
    n = len(T)
    if math.comb(n, 3) <= params.n_hypotheses:
        samples = np.array(list(combinations(range(n), 3)), dtype=np.int64)
    else:
        rng = np.random.default_rng(params.seed)
        samples = np.argsort(rng.random((params.n_hypotheses, n)), axis=1)[:, :3]
    best: tuple[float, Array] | None = None
    for s in samples:
        if orientation_spread(T[s, :3, :3])[0] < _MIN_SAMPLE_SPREAD:
            continue
        x = _lstsq(T[s], P[s])
        med = float(np.median(_residuals(T, P, x) ** 2))
        if best is None or med < best[0]:
            best = (med, x)
    if best is None:  # no sample turns enough on its own: all of them at once
        x = _lstsq(T, P)
        return x, float(np.median(_residuals(T, P, x) ** 2))
    return best[1], best[0]


def solve_tool_tip(
    T_base_tcp: ArrayLike,
    P_base_tip: ArrayLike,
    ids: Sequence[str] | None = None,
    params: ToolCalParams = ToolCalParams(),
) -> ToolTipFit:
    """The tip in the TCP frame from flange poses and measured tips (T1, T2), with its verdict.

    Parameters
    ----------
    T_base_tcp : (n, 4, 4)
        The TCP poses the robot reported, base frame, m.
    P_base_tip : (n, 3)
        The tip centres the scanner measured at each, base frame, m.
    ids : sequence of str, optional
        Pose ids for the report (default ``"0"``, ``"1"``, ...).
    params : ToolCalParams

    Returns
    -------
    ToolTipFit
        Never raises on poor data: the verdict says why it is not ``ok``
        (with fewer than three poses the tip is NaN).

    Raises
    ------
    InputError
        Bad shapes, NaN, lengths or ids that do not match.
    """
    T, P = check_tool_poses(T_base_tcp, P_base_tip)
    n = len(T)
    ids_t = tuple(str(i) for i in range(n)) if ids is None else tuple(str(i) for i in ids)
    if len(ids_t) != n or len(set(ids_t)) != n:
        raise InputError(f"ids: expected {n} unique pose ids, got {len(ids_t)} ({len(set(ids_t))} unique)")
    nan3 = np.full(3, math.nan)
    inf3 = np.full(3, math.inf)
    if n < MIN_SOLVE_POSES:
        return ToolTipFit(
            nan3,
            inf3,
            nan3,
            inf3,
            ids_t,
            np.full(n, math.nan),
            (),
            (),
            math.nan,
            "floor",
            0.0,
            np.array([0.0, 0.0, 1.0]),
            "too_few_poses",
            (f"{n} tip measurements; at least {params.min_poses} are needed (the solve needs {MIN_SOLVE_POSES})",),
            (),
        )
    spread_all, _ = orientation_spread(T[:, :3, :3])
    rp = params.robust
    if spread_all < _MIN_SAMPLE_SPREAD:
        # Nothing to be robust with: every subset is as degenerate as the whole.
        x = _lstsq(T, P)
        residuals = _residuals(T, P, x)
        inlier: NDArray[np.bool_] = np.ones(n, dtype=bool)
        sigma = float(np.sqrt(np.sum(residuals**2) / max(3 * n - 6, 1)))
        threshold = math.inf
    else:
        x, med2 = _lmeds(T, P, rp)
        sigma = math.sqrt(med2 / CHI2_3_MEDIAN)
        residuals = _residuals(T, P, x)
        inlier_prev: NDArray[np.bool_] | None = None
        rounds = 0
        while True:
            threshold = max(rp.k * sigma, rp.min_threshold)
            if rp.max_threshold is not None:
                threshold = min(threshold, rp.max_threshold)
            inlier = np.asarray(residuals <= threshold, dtype=bool)
            if inlier_prev is not None and (np.array_equal(inlier, inlier_prev) or rounds >= rp.max_rounds):
                break
            inlier_prev = inlier
            rounds += 1
            if int(inlier.sum()) < MIN_SOLVE_POSES:
                break
            x = _lstsq(T[inlier], P[inlier])
            residuals = _residuals(T, P, x)
            dof = 3 * int(inlier.sum()) - 6
            if dof > 0:
                sigma = float(np.sqrt(np.sum(residuals[inlier] ** 2) / dof))
    used = np.flatnonzero(inlier)
    rejected = outliers(ids_t, residuals, inlier, threshold, rp.k, sigma)
    spread, axis = orientation_spread(T[used, :3, :3])
    sigma_used = max(sigma, params.sigma_floor) if math.isfinite(sigma) else params.sigma_floor
    source = "residuals" if math.isfinite(sigma) and sigma >= params.sigma_floor else "floor"
    A, _ = _system(T[used], P[used])
    N = A.T @ A
    if len(used) >= MIN_SOLVE_POSES and spread >= _MIN_SAMPLE_SPREAD / 10 and np.linalg.cond(N) < 1e12:
        cov = sigma_used**2 * np.linalg.inv(N)
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    else:
        std = np.full(6, math.inf)
    fit = ToolTipFit(
        p_tcp_tip=x[:3].copy(),
        tip_std=std[:3],
        offset_base=x[3:].copy(),
        offset_std=std[3:],
        ids=ids_t,
        residuals=residuals,
        inliers=tuple(int(i) for i in used),
        rejected=rejected,
        sigma=float(sigma_used),
        sigma_source=source,
        spread=spread,
        spread_axis_tcp=axis,
        verdict="ok",
        reasons=(),
        warnings=(),
    )
    verdict, reasons, warnings = _verdict(fit, n, params)
    return ToolTipFit(**{**fit.__dict__, "verdict": verdict, "reasons": reasons, "warnings": warnings})


def _verdict(fit: ToolTipFit, n: int, params: ToolCalParams) -> tuple[str, tuple[str, ...], tuple[str, ...]]:
    found: list[tuple[str, str]] = []
    warnings: list[str] = []
    if n < params.min_poses:
        found.append(("too_few_poses", f"{n} tip measurements; at least {params.min_poses} are needed"))
    if fit.spread < params.min_spread:
        ax = np.round(fit.spread_axis_tcp, 3).tolist()
        found.append(
            (
                "poor_orientation_spread",
                f"the flange orientations spread {math.degrees(fit.spread):.2f} deg along the TCP direction {ax}, "
                f"at least {math.degrees(params.min_spread):.2f} deg are needed: turn the tool about at least two axes",
            )
        )
    n_out = len(fit.rejected)
    if n_out > params.max_outlier_fraction * n:
        found.append(
            (
                "poor_data",
                f"{n_out} of {n} poses are outliers (at most {params.max_outlier_fraction:.0%} allowed): "
                + ", ".join(r.id for r in fit.rejected),
            )
        )
    elif n_out:
        warnings.append(f"{n_out} of {n} poses left out as outliers: " + ", ".join(r.id for r in fit.rejected))
    if math.isfinite(fit.rms) and fit.rms > params.max_rms:
        found.append(("poor_data", f"RMS residual {fit.rms * 1e3:.3f} mm exceeds {params.max_rms * 1e3:.3f} mm"))
    worst = float(np.max(fit.tip_std))
    if fit.spread >= params.min_spread and not worst <= params.max_tip_std:
        found.append(("poor_data", f"the tip is fixed to {worst * 1e3:.3f} mm (1 sigma), worse than {params.max_tip_std * 1e3:.3f} mm"))
    if fit.sigma_source == "floor":
        warnings.append(f"residuals below the noise floor; the uncertainty uses {params.sigma_floor * 1e3:.3f} mm per axis")
    if not found:
        return "ok", (), tuple(warnings)
    order = {v: i for i, v in enumerate(VERDICTS)}
    verdict = min((v for v, _ in found), key=lambda v: order[v])
    return verdict, tuple(r for _, r in found), tuple(warnings)


def solve_or_raise(
    T_base_tcp: ArrayLike, P_base_tip: ArrayLike, ids: Sequence[str] | None = None, params: ToolCalParams = ToolCalParams()
) -> ToolTipFit:
    """:func:`solve_tool_tip`, raising CalibrationError when there are too few poses to solve at all."""
    fit = solve_tool_tip(T_base_tcp, P_base_tip, ids, params)
    if not np.all(np.isfinite(fit.p_tcp_tip)):
        raise CalibrationError("; ".join(fit.reasons) or "the tip could not be solved")
    return fit


def tool_calibration_poses(
    R_base_face: ArrayLike,
    p_base_tip: ArrayLike,
    p_tcp_tip: ArrayLike,
    z_tcp_finger: ArrayLike,
    n: int,
    max_tilt: float,
    seed: int = 0,
    max_spin: float = 0.6,
) -> Array:
    """TCP poses (n, 4, 4) that present the tip at ``p_base_tip`` at ``n`` orientations turned about it.

    The first is ``R_base_face`` itself (the TCP orientation that faces the
    scanner: the calibration's verification pose). The others are it tilted
    by up to ``max_tilt`` (rad) about axes across the finger, their directions
    spread round the circle (golden angle, seeded jitter), magnitudes
    alternating between the full and two thirds of it, and spun about the
    finger by up to ``max_spin`` (rad): turns about three axes, so (T1) fixes
    every component of the tip. Each pose puts the believed tip
    ``p_tcp_tip`` at ``p_base_tip``.

    ``z_tcp_finger`` is the finger's axis (from the tip towards the flange),
    TCP frame: the tool config's ``tool_z_tcp``.
    """
    R0 = np.asarray(R_base_face, dtype=np.float64)
    p = np.asarray(p_base_tip, dtype=np.float64)
    t = np.asarray(p_tcp_tip, dtype=np.float64)
    if R0.shape != (3, 3) or p.shape != (3,) or t.shape != (3,):
        raise InputError(f"expected R (3, 3), p_base_tip (3,), p_tcp_tip (3,); got {R0.shape}, {p.shape}, {t.shape}")
    if n < 1 or not (math.isfinite(max_tilt) and 0.0 <= max_tilt <= math.pi / 3):
        raise InputError(f"expected n >= 1 and 0 <= max_tilt <= 60 deg, got n={n}, max_tilt={max_tilt!r} rad")
    from scipy.spatial.transform import Rotation

    d = -(R0 @ np.asarray(z_tcp_finger, dtype=np.float64))  # the finger's direction, flange to tip, base frame
    d /= np.linalg.norm(d)
    e1 = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    rng = np.random.default_rng(seed)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    out = np.zeros((n, 4, 4))
    for i in range(n):
        if i == 0:
            R = R0
        else:
            phi = i * golden + rng.uniform(-0.2, 0.2)
            tilt = max_tilt * (1.0 if i % 2 else 2.0 / 3.0)
            axis = math.cos(phi) * e1 + math.sin(phi) * e2
            spin = max_spin * rng.uniform(-1.0, 1.0)
            R = Rotation.from_rotvec(tilt * axis).as_matrix() @ Rotation.from_rotvec(spin * d).as_matrix() @ R0
        out[i, :3, :3] = R
        out[i, :3, 3] = p - R @ t
        out[i, 3, 3] = 1.0
    return out
