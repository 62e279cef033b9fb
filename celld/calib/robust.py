"""The default estimator of ``T_base_cam``: every consistent pair, none of the others.

Owns the robust solve of Eq. 9 over all flange-centre pairs. A false flange
detection (another part of the arm segmented as the flange, paper section
3.2.2) lands tens of millimetres away and drags an all-points SVD by
millimetres (Table 1); keeping only four pairs (Algorithm 1) throws away the
averaging of the good ones. This estimator keeps every pair that agrees with
the others:

1. Least median of squares over minimal three-pair samples (every triple
   when there are few pairs, random ones otherwise): the transform whose
   median squared residual is smallest. It needs no threshold and survives
   up to half the pairs being false.
2. A noise scale from that median (3-D residual norms of isotropic Gaussian
   noise follow a chi distribution with 3 degrees of freedom). With few
   pairs the median falls among the sample's own near-zero residuals and
   the scale comes out small, and a three-pair fit carries its own noise out
   to the other pairs: when the first threshold keeps fewer than four pairs,
   each other pair is tested against the kept ones fitted together with it,
   at a threshold from the scale with its small-sample correction.
   (Before, five good pairs of a half-resolution scan, 0.05 mm apart, were
   refused more often than not.)
3. Iterate until the inlier set stops changing: threshold the residuals of
   every pair at ``k sigma`` (``k`` from the chi-3 quantile of a per-pair
   false-rejection probability), least squares (Eq. 9-12) on the inliers,
   re-estimate ``sigma`` from the inliers' residuals with the degrees of
   freedom taken out.

With no outlier among the pairs it returns the least-squares solution on all
of them (a good pair is dropped with probability ``alpha`` each). Every
rejected pair is reported with its residual and the threshold it failed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from celld.calib.rigid import (
    MIN_PAIRS,
    MIN_SPREAD,
    Array,
    RigidFit,
    check_pairs,
    pair_residuals,
    solve_rigid,
)
from celld.errors import CalibrationError, InputError
from celld.se3 import transform_from

# Median of the chi-square distribution with 3 degrees of freedom: the median
# of |r|^2 / sigma^2 for a 3-D isotropic Gaussian residual.
CHI2_3_MEDIAN = float(chi2.median(3))
# Triangles thinner than this (second / first singular value) make no
# hypothesis while fatter ones exist (a thin triangle's rotation about its long
# side is mostly noise).
_MIN_TRIANGLE_RATIO = 0.05


@dataclass(frozen=True)
class RobustParams:
    """Parameters of :func:`solve_robust`.

    Attributes
    ----------
    alpha : float
        Probability that a good pair is rejected (sets ``k`` of the
        threshold ``k sigma`` from the chi-3 distribution: 1e-4 -> 4.59).
    min_threshold : float
        Floor of the inlier threshold, metres: pairs closer than this are
        never rejected (noise-free data would otherwise have a zero threshold).
    max_threshold : float or None
        Ceiling of the inlier threshold, metres (None: no ceiling).
    n_hypotheses : int
        Random minimal samples when there are more triples than this;
        otherwise every triple is tried.
    max_rounds : int
        Bound on the threshold / least-squares rounds.
    seed : int
        Seed of the sampler (the result is deterministic for a given input).
    with_scale : bool
        Estimate the scale ``c`` of Eq. 11 in the final least squares.
    """

    alpha: float = 1e-4
    min_threshold: float = 1e-4
    max_threshold: float | None = None
    n_hypotheses: int = 200
    max_rounds: int = 20
    seed: int = 0
    with_scale: bool = False

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 0.5:
            raise InputError(f"alpha: expected 0 < alpha < 0.5, got {self.alpha}")
        if not self.min_threshold >= 0.0:
            raise InputError(f"min_threshold: expected >= 0 m, got {self.min_threshold}")
        if self.max_threshold is not None and not self.max_threshold > self.min_threshold:
            raise InputError(f"max_threshold: expected above min_threshold {self.min_threshold}, got {self.max_threshold}")
        if self.n_hypotheses < 1 or self.max_rounds < 1:
            raise InputError("n_hypotheses and max_rounds: expected at least 1")

    @property
    def k(self) -> float:
        """Threshold in units of the noise scale."""
        return float(math.sqrt(chi2.isf(self.alpha, 3)))


@dataclass(frozen=True)
class RejectedPair:
    """A pair left out of the solve, and why.

    ``index`` is the pair's position in the arrays given to the solver, -1
    for a pair that never reached it (e.g. its flange detection failed).
    """

    id: str
    index: int
    residual: float  # m, against the final transform (nan if never solved)
    reason: str

    def as_dict(self) -> dict[str, object]:
        return {"id": self.id, "index": self.index, "residual_mm": self.residual * 1e3, "reason": self.reason}


def outliers(
    ids: Sequence[str], residuals: np.ndarray, inlier: np.ndarray, threshold: float, k: float, sigma: float
) -> tuple[RejectedPair, ...]:
    """The pairs outside ``inlier``, each with its residual and why: over ``threshold`` = ``k`` x the noise ``sigma`` (m)."""
    return tuple(
        RejectedPair(
            id=ids[i],
            index=int(i),
            residual=float(residuals[i]),
            reason=(
                f"residual {residuals[i] * 1e3:.3f} mm exceeds the inlier threshold {threshold * 1e3:.3f} mm "
                f"({k:.2f} x estimated noise {sigma * 1e3:.3f} mm per axis)"
            ),
        )
        for i in np.flatnonzero(~inlier)
    )


@dataclass(frozen=True)
class RobustFit:
    """Result of :func:`solve_robust`.

    Attributes
    ----------
    fit : RigidFit
        Least squares (Eq. 9-12) on the inliers; its uncertainty is theirs.
    ids : tuple of str
        Pair ids, in input order.
    inliers : tuple of int
        Indices of the pairs used, in input order.
    rejected : tuple of RejectedPair
        The others, each with its reason.
    residuals : (n,) array
        Residual of every pair (inlier or not) against the final transform, m.
    sigma : float
        Final noise scale, metres per axis.
    threshold : float
        Final inlier threshold on the residual norm, metres.
    rounds : int
        Threshold / least-squares rounds until the inlier set settled.
    """

    fit: RigidFit
    ids: tuple[str, ...]
    inliers: tuple[int, ...]
    rejected: tuple[RejectedPair, ...]
    residuals: Array
    sigma: float
    threshold: float
    rounds: int

    @property
    def T_base_cam(self) -> Array:
        return self.fit.T_dst_src

    @property
    def inlier_ids(self) -> tuple[str, ...]:
        return tuple(self.ids[i] for i in self.inliers)


def _kabsch_batch(A: Array, B: Array) -> tuple[Array, Array]:
    """Rigid fits ``A ~ R B + t`` for a batch of point sets (N, m, 3): R (N, 3, 3), t (N, 3)."""
    mu_a = A.mean(axis=1)
    mu_b = B.mean(axis=1)
    H = (A - mu_a[:, None]).transpose(0, 2, 1) @ (B - mu_b[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d[d == 0] = 1.0
    U = U.copy()
    U[:, :, 2] *= d[:, None]
    R = U @ Vt
    t = mu_a - (R @ mu_b[:, :, None])[:, :, 0]
    return R, t


def _samples(n: int, params: RobustParams) -> NDArray[np.int64]:
    if math.comb(n, 3) <= params.n_hypotheses:
        return np.array(list(combinations(range(n), 3)), dtype=np.int64)
    rng = np.random.default_rng(params.seed)
    # Random triples of distinct indices (argsort of uniforms is a permutation).
    return np.argsort(rng.random((params.n_hypotheses, n)), axis=1)[:, :3]


def least_median_of_squares(P_base: Array, P_cam: Array, params: RobustParams = RobustParams()) -> tuple[Array, float]:
    """Minimal-sample LMedS transform and its median squared residual (m^2)."""
    idx = _samples(len(P_base), params)
    A = P_base[idx]
    B = P_cam[idx]
    # Thin triangles (in the robot's positions) fix the rotation poorly: skip
    # them, unless every triangle is thin (an elongated set), then keep every
    # one that spans a triangle at all (the same rank test as check_pairs).
    s = np.linalg.svd(A - A.mean(axis=1, keepdims=True), compute_uv=False)
    keep = s[:, 1] > _MIN_TRIANGLE_RATIO * s[:, 0]
    if not np.any(keep):
        keep = s[:, 1] / np.sqrt(3.0) >= MIN_SPREAD
    if not np.any(keep):
        raise CalibrationError("no three pairs span a triangle: the positions are collinear")
    R, t = _kabsch_batch(A[keep], B[keep])
    res2 = np.sum((P_cam @ R.transpose(0, 2, 1) + t[:, None, :] - P_base[None]) ** 2, axis=2)
    med = np.median(res2, axis=1)
    best = int(np.argmin(med))
    return transform_from(R[best], t[best]), float(med[best])


def _joined(P_dst: Array, P_src: Array, core: NDArray[np.bool_], threshold: float) -> NDArray[np.bool_]:
    """The first round's inliers when the minimal sample's fit keeps fewer than four: each other pair joins
    when, fitted together with the core, it lies within ``threshold`` of that fit (a three-pair fit carries
    its own noise out to the other pairs, a false detection stays tens of millimetres off either way)."""
    out = core.copy()
    for j in np.flatnonzero(~core):
        with_j = core.copy()
        with_j[j] = True
        fit = solve_rigid(P_dst[with_j], P_src[with_j])
        out[j] = pair_residuals(fit.T_dst_src, P_dst[j : j + 1], P_src[j : j + 1])[0] <= threshold
    return out


def solve_robust(
    P_base: ArrayLike,
    P_cam: ArrayLike,
    ids: Sequence[str] | None = None,
    params: RobustParams = RobustParams(),
) -> RobustFit:
    """Robust ``T_base_cam`` from flange-centre pairs (see the module docstring).

    Parameters
    ----------
    P_base, P_cam : (n, 3) arrays
        Flange centres in the base and camera frames, metres, in pair order.
    ids : sequence of str, optional
        Pair ids for the report (default ``"0"``, ``"1"``, ...).
    params : RobustParams

    Raises
    ------
    InputError
        Bad shapes, NaN, mismatched lengths or ids.
    CalibrationError
        Fewer than four pairs, coincident or collinear positions
        (:func:`~celld.calib.rigid.check_pairs`), or fewer than four mutually
        consistent pairs.
    """
    P_dst, P_src = check_pairs(P_base, P_cam)
    n = len(P_dst)
    ids_t = tuple(str(i) for i in range(n)) if ids is None else tuple(str(i) for i in ids)
    if len(ids_t) != n:
        raise InputError(f"ids: expected {n} pair ids, got {len(ids_t)}")
    if len(set(ids_t)) != n:
        raise InputError("ids: pair ids must be unique")

    T0, med2 = least_median_of_squares(P_dst, P_src, params)
    sigma = math.sqrt(med2 / CHI2_3_MEDIAN)
    k = params.k
    residuals = pair_residuals(T0, P_dst, P_src)
    inlier: NDArray[np.bool_] | None = None
    rounds = 0
    while True:
        threshold = max(k * sigma, params.min_threshold)
        if params.max_threshold is not None:
            threshold = min(threshold, params.max_threshold)
        new_inlier = residuals <= threshold
        if inlier is None and np.count_nonzero(new_inlier) < MIN_PAIRS:
            # The rescue of step 2, its scale with least median of squares' finite-sample correction,
            # 1 + 5 / (n - 3) (Rousseeuw and Leroy 1987, the minimal sample being three pairs).
            rescue = max(k * sigma * (1.0 + 5.0 / (n - 3)), params.min_threshold)
            new_inlier = _joined(P_dst, P_src, new_inlier, rescue)
        if inlier is not None and (np.array_equal(new_inlier, inlier) or rounds >= params.max_rounds):
            break
        inlier = new_inlier
        rounds += 1
        m = int(np.count_nonzero(inlier))
        if m < MIN_PAIRS:
            raise CalibrationError(
                f"only {m} of {n} pairs agree within {threshold * 1e3:.3g} mm; at least {MIN_PAIRS} consistent pairs are needed"
            )
        fit = solve_rigid(P_dst[inlier], P_src[inlier], with_scale=params.with_scale)
        residuals = pair_residuals(fit.T_dst_src, P_dst, P_src, fit.scale)
        # Noise scale from the inliers' residual sum of squares (dof taken out).
        if fit.uncertainty.dof > 0:
            sigma = fit.uncertainty.sigma
    rejected = outliers(ids_t, residuals, inlier, threshold, k, sigma)
    return RobustFit(
        fit=fit,
        ids=ids_t,
        inliers=tuple(int(i) for i in np.flatnonzero(inlier)),
        rejected=rejected,
        residuals=residuals,
        sigma=float(sigma),
        threshold=float(threshold),
        rounds=rounds,
    )
