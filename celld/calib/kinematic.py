"""The arm's kinematic calibration: corrections to the controller's kinematics, fitted with the scanner's pose (pure).

A rigid ``T_base_cam`` fitted around the calibration poses absorbs the arm's
own error there and nowhere else: at the weld, flange down over the table,
the arm is off by what its kinematics are off (0.2-1 mm on a UR10e). This
module fits that error from the same scans, at poses spread for it
(:data:`WIDE`): the flange's centre and face normal seen by the scanner
against where a corrected model of the arm puts them,

    T_base_cam p_cam  =  FK(q + dtheta + C tau(q); DH + dDH) origin
    R_base_cam n_cam  =  FK(...) z axis

with ``q`` the controller's joints, ``dDH`` corrections to the controller's
DH table (lengths d, a and twists alpha), ``dtheta`` to its joint zeros and
``C`` each joint's compliance under the static torque ``tau`` of the
published links and the configured payload (:mod:`celld.robot.dynamics`):
the sag that makes the error depend on the pose and that no DH table holds.

Not every parameter can be told apart from position and normal data (the
base's rotation about its axis is the camera's; along parallel axes only
the sum of the offsets shows; the flange's turn about its own axis moves
neither centre nor normal; gravity puts no torque on the base joint). The
fit finds which by a rank-revealing QR of its Jacobian, scaled by each
parameter's prior, holds those at zero, and reports the rank, the condition
number of what it kept and what it held. The kept ones are solved with
weak priors (a maximum a posteriori fit), so a parameter the poses barely
see stays near zero rather than wandering.

:class:`ArmModel` is the corrected arm: :meth:`ArmModel.forward` predicts
where the flange is, :meth:`ArmModel.precorrect` gives the pose to send the
controller (which moves by its own kinematics) so that the flange lands
where it is wanted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import qr
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from celld import se3
from celld.calib.detect import detect_flange
from celld.calib.detect_params import DetectParams
from celld.calib.flange import FlangeModel
from celld.calib.poses import calibration_poses
from celld.calib.quality import norm_bound
from celld.errors import CelldError, InputError
from celld.robot import dynamics, primary
from celld.robot import kinematics as kin
from celld.schemadoc import enum, integer, matrix4, number, obj, string, texts, vector

Array = NDArray[np.float64]

# Parameter groups, in the order of the parameter vector after the scanner's pose (rotation vector, translation).
GROUPS = ("d", "a", "alpha", "theta", "compliance")
POSE_NAMES = ("cam_rx", "cam_ry", "cam_rz", "cam_x", "cam_y", "cam_z")
NAMES: tuple[str, ...] = POSE_NAMES + tuple(f"{g}{j + 1}" for g in GROUPS for j in range(6))

# Prior 1 sigma of each group: what a factory-calibrated arm may still be off by (generous, so the data
# decides), and a compliance well above any UR joint's (rad/(N m)).
PRIOR = {"d": 1e-3, "a": 1e-3, "alpha": 1e-3, "theta": 1e-3, "compliance": 1e-4}
# The scanner's pose is free: its prior only scales the identifiability test (m, rad).
POSE_PRIOR = (0.01, 0.01, 0.01, 0.01, 0.01, 0.01)
# A parameter whose scaled column adds less than this to the rank (|R_kk| over the largest) is held fixed.
RANK_TOL = 1e-3
# The joints whose compliance is fitted: the shoulder and the elbow, which carry the arm. A wrist's torque
# hardly changes over poses the scanner can see the flange in (face up), so its compliance is barely seen
# there, and a poor estimate of it moves the flange more at the weld (face down) than the wrist's whole
# sag (about 0.02 mm under a 1.6 kg tool); the base's axis is vertical (gravity puts no torque on it).
COMPLIANT = (1, 2)
# The face normal's residual is weighed as a point this far along it (m): 1 mrad counts as 0.03 mm.
NORMAL_LEVER = 0.03
# Pose-to-pose error of a flange centre (m), the unit of the priors' residuals.
SIGMA_POINT = 0.1e-3
# What an arm still errs by after a kinematic calibration where its poses did not go (flange down over the
# table, after calibrating with it up): a scanner-based joint hand-eye and kinematic calibration of a real
# arm left 0.394 mm mean, 0.428 mm max (Sensors 2025, 25(15):4661). The bound away from the poses adds it whole.
REMAINING_PRIOR = 0.4e-3
# The bounds' confidence on the norm of the 3-D error.
BOUND_CONFIDENCE = 0.95
# Model selection: the arm's corrections are kept only where they predict poses the fit did not see better
# than the scanner's pose alone does with the controller's kinematics as they are. A dozen wide poses can fit
# two dozen corrections to a correct arm's noise and put the flange a millimetre off at the weld (the e2e
# cell's arm, whose table is right: 0.37-1.2 mm over the table against 0.07 mm with the hand-eye alone).
# Cross-validation over CV_FOLDS folds of the poses; of the models, simplest first ("pose": the scanner's pose
# on the controller's kinematics as they are; "sag": with the joints' compliance; "arm": with every correction
# the data tell apart), the simplest whose mean squared held-out miss is within one standard error of the
# best one's (the one-standard-error rule).
CV_FOLDS = 5
MODELS = ("pose", "sag", "arm")
# What a stored correction may be (the units of ArmModel.as_dict): far above what a factory-calibrated arm
# is off by (0.2-1 mm, a few mrad); beyond it the file is not an arm's calibration. The compliance bound is
# ten times PRIOR's.
STORED_BOUNDS: dict[str, tuple[float, float]] = {
    "d_mm": (-20.0, 20.0),
    "a_mm": (-20.0, 20.0),
    "alpha_mrad": (-50.0, 50.0),
    "theta_mrad": (-50.0, 50.0),
    "compliance_mrad_per_knm": (-1000.0, 1000.0),  # as fitted: noise may leave a held-near-zero one below 0
}
# The heaviest payload a stored model may carry (a UR20's is 20 kg), kg.
MAX_PAYLOAD_KG = 30.0
# Pre-correction: Newton steps and the residual (m, rad) that ends them.
_NEWTON_STEPS = 8
_NEWTON_TOL = 1e-9

# Wide poses for the arm's calibration: a larger box than the hand-eye calibration's, tilted further and
# turned all the way about the flange's axis, so every joint works over its range (the study behind the
# research notes: 48 such poses took the weld site's error from 0.54 to 0.06 mm on a pure-DH arm). With a
# flange centre off by 0.1 mm from pose to pose (what the simulated scanner and detector give), 40 poses
# leave the weld site 0.09-0.48 mm off over six drawn arms, 80 poses 0.07-0.13 mm, 120 poses 0.05-0.10 mm.


@dataclass(frozen=True)
class WidePoses:
    """Where the arm calibration shows the flange: a box (m) centred this far off the verification pose, tilts
    and turns about the flange's axis up to these (rad), so many poses."""

    box: tuple[float, float, float] = (0.5, 0.5, 0.2)
    centre_offset: tuple[float, float, float] = (0.0, 0.0, -0.05)
    max_tilt: float = 0.6
    max_spin: float = math.pi
    n_poses: int = 80


WIDE = WidePoses()


def wide_poses(T_base_flange_v: ArrayLike, n: int, seed: int, wide: WidePoses = WIDE) -> Array:
    """The arm calibration's flange poses (n, 4, 4): ``wide``'s box around the verification pose ``T_base_flange_v``."""
    T_c = se3.check_transform(T_base_flange_v, "T_base_flange_v").copy()
    T_c[:3, 3] += wide.centre_offset
    return calibration_poses(T_c, wide.box, n, wide.max_tilt, seed=seed, max_spin=wide.max_spin)


@dataclass(frozen=True)
class ArmModel:
    """The controller's kinematics with the calibration's corrections (SI, rad).

    ``nominal`` is the DH table the controller moves by; ``dh`` the corrected
    one; ``theta`` the joint zeros' corrections; ``compliance`` each joint's
    (rad/(N m)) under the torque of ``links`` and ``payload``.
    """

    nominal: kin.DH
    dh: kin.DH
    theta: tuple[float, ...] = (0.0,) * 6
    compliance: tuple[float, ...] = (0.0,) * 6
    links: dynamics.Links | None = None
    payload: dynamics.Payload = dynamics.Payload()

    @classmethod
    def identity(cls, nominal: kin.DH) -> ArmModel:
        """The controller's own kinematics, no correction."""
        return cls(nominal, nominal)

    @property
    def is_identity(self) -> bool:
        return tuple(self.dh) == tuple(self.nominal) and not any(self.theta) and not any(self.compliance)

    def joints(self, q: ArrayLike) -> Array:
        """The model's joint angles (n, 6) for the controller's joints ``q`` (n, 6): zeros and sag added."""
        Q = np.atleast_2d(np.asarray(q, dtype=np.float64)) + np.asarray(self.theta)
        if any(self.compliance):
            F = kin.forward_batch(Q, self.dh)[:, :, :3, :]
            Q = Q + np.asarray(self.compliance) * dynamics.joint_torques(F, self.links, self.payload)
        return Q

    def flanges(self, q: ArrayLike) -> Array:
        """Where the model puts the flange (n, 4, 4) with the controller at joints ``q`` (n, 6)."""
        return kin.forward_batch(self.joints(q), self.dh)[:, 5]

    def forward(self, q: ArrayLike) -> Array:
        """Where the model puts the flange (4, 4) with the controller at joints ``q`` (6,)."""
        return self.flanges(q)[0]

    def precorrect(self, T_base_flange: ArrayLike, q_near: ArrayLike) -> tuple[Array, Array] | None:
        """The pose to send the controller so that the flange lands at ``T_base_flange`` by this model.

        Returns ``(T_cmd (4, 4), q (6,))``: the controller's joints ``q``
        (nearest ``q_near``) put the modelled flange at the target, and
        ``T_cmd`` is where the controller believes those joints put it. None
        when the target is out of reach.
        """
        T = se3.check_transform(T_base_flange, "T_base_flange")
        q = kin.inverse(T, q_near, self.nominal)
        if q is None:
            return None
        if self.is_identity:
            return T, q
        for _ in range(_NEWTON_STEPS):
            M = self.forward(q)
            e = np.concatenate([T[:3, 3] - M[:3, 3], Rotation.from_matrix(T[:3, :3] @ M[:3, :3].T).as_rotvec()])
            if np.linalg.norm(e) < _NEWTON_TOL:
                break
            q = q + np.linalg.lstsq(kin.jacobian(q, self.nominal), e, rcond=None)[0]
        return kin.forward(q, self.nominal), q

    def correction(self, q: ArrayLike) -> Array:
        """``D`` (4, 4) with ``D @ T_reported`` where the model puts what the controller reports at ``T_reported``
        with its joints at ``q`` (6,): the flange, or any frame fixed to it (the TCP)."""
        q = np.asarray(q, dtype=np.float64)
        return self.forward(q) @ se3.invert(kin.forward(q, self.nominal))

    def as_dict(self) -> dict[str, Any]:
        """The corrections, for the stored calibration: mm, mrad and mrad/(kN m) beside the nominal table, and
        the payload the sag was fitted with (:meth:`from_dict` reads them back)."""
        return {
            "d_mm": (np.subtract(self.dh.d, self.nominal.d) * 1e3).tolist(),
            "a_mm": (np.subtract(self.dh.a, self.nominal.a) * 1e3).tolist(),
            "alpha_mrad": (np.subtract(self.dh.alpha, self.nominal.alpha) * 1e3).tolist(),
            "theta_mrad": (np.asarray(self.theta) * 1e3).tolist(),
            "compliance_mrad_per_knm": (np.asarray(self.compliance) * 1e6).tolist(),
            "payload_kg": self.payload.mass,
            "payload_com_mm": (np.asarray(self.payload.com) * 1e3).tolist(),
        }

    @classmethod
    def from_dict(cls, doc: Any, robot_model: str, where: str = "arm", table: kin.DH | None = None) -> ArmModel:
        """The model :meth:`as_dict` stored, on the controller's kinematics ``table`` (the published table of
        ``robot_model`` when None).

        Raises
        ------
        InputError
            A correction that is missing, not six finite numbers, or larger than an arm's own error can be
            (:data:`STORED_BOUNDS`), or a payload that is no payload; the message names the key.
        """
        if not isinstance(doc, dict):
            raise InputError(f"{where}: expected the arm's corrections (an object), got {type(doc).__name__}")
        rows: dict[str, Array] = {}
        for key, (lo, hi) in STORED_BOUNDS.items():
            arr = kin.six_numbers(doc, key, where)
            if np.any(arr < lo) or np.any(arr > hi):
                raise InputError(f"{where}.{key}: expected each within [{lo:g}, {hi:g}], got {arr.tolist()}")
            rows[key] = arr
        mass, com = doc.get("payload_kg"), doc.get("payload_com_mm")
        if isinstance(mass, bool) or not isinstance(mass, (int, float)) or not 0.0 <= float(mass) <= MAX_PAYLOAD_KG:
            raise InputError(f"{where}.payload_kg: expected a mass within [0, {MAX_PAYLOAD_KG:g}] kg, got {mass!r}")
        try:
            com_m = np.asarray(com, dtype=np.float64) * 1e-3
        except (TypeError, ValueError):
            com_m = np.zeros(0)
        if com_m.shape != (3,) or not np.all(np.isfinite(com_m)) or np.linalg.norm(com_m) > 1.0:
            raise InputError(f"{where}.payload_com_mm: expected the payload's centre of mass, 3 numbers within 1 m, got {com!r}")
        nominal = table or kin.model(robot_model).dh
        dh = kin.DH(
            tuple(np.add(nominal.d, rows["d_mm"] * 1e-3).tolist()),
            tuple(np.add(nominal.a, rows["a_mm"] * 1e-3).tolist()),
            tuple(np.add(nominal.alpha, rows["alpha_mrad"] * 1e-3).tolist()),
            nominal.theta,
        )
        return cls(
            nominal,
            dh,
            tuple((rows["theta_mrad"] * 1e-3).tolist()),
            tuple((rows["compliance_mrad_per_knm"] * 1e-6).tolist()),
            dynamics.links(robot_model),
            dynamics.Payload(float(mass), (float(com_m[0]), float(com_m[1]), float(com_m[2]))),
        )


@dataclass(frozen=True)
class ArmFit:
    """The arm's calibration from one session."""

    T_base_cam: Array
    model: ArmModel
    residuals: Array  # (n,) distance of each flange centre from the model's, m
    residuals_before: Array  # (n,) the same with the controller's kinematics and the start's T_base_cam
    estimated: tuple[str, ...]  # the parameters fitted (the scanner's pose always)
    held: tuple[str, ...]  # those held at zero: not told apart by the data, or held by design (COMPLIANT)
    rank: int  # of the data's Jacobian over every parameter, scaled by the priors
    condition: float  # of the fitted parameters' scaled Jacobian
    # Bounds on the norm of the flange's error at BOUND_CONFIDENCE, m: where the poses went (the fit's own
    # uncertainty there and what the pairs err from pose to pose), and anywhere else (that plus REMAINING_PRIOR).
    bound_poses: float = math.inf
    bound_away: float = math.inf
    # The model kept (:data:`MODELS`) and each candidate's RMS miss at the poses its fit did not see, m.
    chosen: str = "arm"
    held_out_rms: dict[str, float] | None = None

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))

    def report(self) -> dict[str, Any]:
        """What the job reports: identifiability, residuals, the corrections."""
        return {
            "rank": self.rank,
            "parameters": len(NAMES),
            "condition": self.condition,
            "estimated": list(self.estimated),
            "held": list(self.held),
            "residual_rms_mm": self.rms * 1e3,
            "residual_max_mm": float(self.residuals.max()) * 1e3,
            "residual_rms_before_mm": float(np.sqrt(np.mean(self.residuals_before**2))) * 1e3,
            "model": self.chosen,
            "held_out_rms_mm": {name: v * 1e3 for name, v in (self.held_out_rms or {}).items()},
            "bound": {
                "confidence": BOUND_CONFIDENCE,
                "poses_mm": self.bound_poses * 1e3,
                "away_mm": self.bound_away * 1e3,
                "remaining_prior_mm": REMAINING_PRIOR * 1e3,
            },
            "corrections": self.model.as_dict(),
        }


def _unpack(x: Array, nominal: kin.DH, links: dynamics.Links | None, payload: dynamics.Payload) -> tuple[Array, ArmModel]:
    """Parameter vector -> (the scanner's pose correction (6,), the arm's model)."""
    g = x[6:].reshape(5, 6)
    dh = kin.DH(
        tuple((np.asarray(nominal.d) + g[0]).tolist()),
        tuple((np.asarray(nominal.a) + g[1]).tolist()),
        tuple((np.asarray(nominal.alpha) + g[2]).tolist()),
        nominal.theta,
    )
    return x[:6], ArmModel(nominal, dh, tuple(g[3].tolist()), tuple(g[4].tolist()), links, payload)


class _Problem:
    """The residuals of one session under a parameter vector."""

    def __init__(
        self,
        q: Array,
        p_cam: Array,
        n_cam: Array | None,
        T_base_cam0: Array,
        nominal: kin.DH,
        links: dynamics.Links | None,
        payload: dynamics.Payload,
    ) -> None:
        self.q, self.p_cam, self.n_cam, self.T0 = q, p_cam, n_cam, T_base_cam0
        self.nominal, self.links, self.payload = nominal, links, payload
        self.bends = links is not None or payload.mass > 0.0

    def subset(self, rows: NDArray[np.intp]) -> _Problem:
        """The same problem on the poses ``rows``."""
        n_cam = None if self.n_cam is None else self.n_cam[rows]
        return _Problem(self.q[rows], self.p_cam[rows], n_cam, self.T0, self.nominal, self.links, self.payload)

    def misses(self, x: Array) -> Array:
        """(n,) distance of each seen flange centre, placed by the scanner's pose, from the model's, m."""
        T_cam = self.camera(x[:6])
        return np.linalg.norm(self.p_cam @ T_cam[:3, :3].T + T_cam[:3, 3] - self.flange(x)[:, :3, 3], axis=1)

    def model(self, x: Array) -> tuple[Array, ArmModel]:
        return _unpack(x, self.nominal, self.links, self.payload)

    def camera(self, pose: Array) -> Array:
        return se3.transform_from(Rotation.from_rotvec(pose[:3]).as_matrix() @ self.T0[:3, :3], self.T0[:3, 3] + pose[3:])

    def flange(self, x: Array) -> Array:
        """The model's flange poses (n, 4, 4) under ``x``."""
        return self.model(x)[1].flanges(self.q)

    def residuals(self, x: Array) -> Array:
        T_cam = self.camera(x[:6])
        M = self.flange(x)
        r = [(self.p_cam @ T_cam[:3, :3].T + T_cam[:3, 3]) - M[:, :3, 3]]
        if self.n_cam is not None:
            r.append(NORMAL_LEVER * (self.n_cam @ T_cam[:3, :3].T - M[:, :3, 2]))
        return np.concatenate([v.ravel() for v in r])

    def jacobian(self, x: Array, steps: Array) -> Array:
        r0 = self.residuals(x)
        J = np.empty((r0.size, x.size))
        for k in range(x.size):
            dx = np.zeros_like(x)
            dx[k] = steps[k]
            J[:, k] = (self.residuals(x + dx) - self.residuals(x - dx)) / (2.0 * steps[k])
        return J


def _prior_sigmas() -> Array:
    return np.concatenate([np.asarray(POSE_PRIOR), *(np.full(6, PRIOR[g]) for g in GROUPS)])


def identifiable(J: Array, sigmas: Array, tol: float = RANK_TOL) -> tuple[NDArray[np.bool_], int]:
    """Which parameters the data tells apart, a mask over the columns of ``J``, and its rank: each column
    scaled by its prior ``sigmas``, a rank-revealing QR with column pivoting."""
    _, R, piv = qr(J * sigmas, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    rank = int(np.count_nonzero(d > tol * d[0])) if d.size and d[0] > 0 else 0
    keep = np.zeros(J.shape[1], dtype=bool)
    keep[piv[:rank]] = True
    return keep, rank


def fit_arm(
    q: ArrayLike,
    p_cam: ArrayLike,
    T_base_cam0: ArrayLike,
    nominal: kin.DH,
    links: dynamics.Links | None = None,
    payload: dynamics.Payload = dynamics.Payload(),
    n_cam: ArrayLike | None = None,
    compliance: bool = True,
    arm_error_prior: float = 1.0e-3,
) -> ArmFit:
    """Fit the arm's corrections and the scanner's pose from one session.

    ``q`` (n, 6) are the controller's joints at each pose, ``p_cam`` (n, 3)
    the flange centres the scanner saw (camera frame), ``n_cam`` (n, 3) the
    face normals it saw (optional), ``T_base_cam0`` the hand-eye calibration
    to start from, ``nominal`` the DH table the controller moves by; ``links``
    and ``payload`` give the torques of the sag (``compliance`` False, or no
    masses at all: no sag in the model). ``arm_error_prior`` is what an arm of
    its class errs by away from where it was seen (m,
    ``calibration.arm_error_prior_mm``): the bound away from the poses where
    the data did not earn the geometric corrections.
    """
    Q = np.asarray(q, dtype=np.float64)
    P = np.asarray(p_cam, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[1] != 6 or P.shape != (len(Q), 3):
        raise InputError(f"arm calibration: expected joints (n, 6) and centres (n, 3), got {Q.shape} and {P.shape}")
    if not (np.all(np.isfinite(Q)) and np.all(np.isfinite(P))):
        raise InputError("arm calibration: the joints and centres must be finite")
    N = None
    if n_cam is not None:
        N = np.asarray(n_cam, dtype=np.float64)
        if N.shape != P.shape or not np.all(np.isfinite(N)):
            raise InputError(f"arm calibration: expected finite normals (n, 3), got {N.shape}")
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
    if len(Q) < 4:
        raise InputError(f"arm calibration: {len(Q)} poses cannot fit an arm (at least 4)")
    T0 = se3.check_transform(T_base_cam0, "T_base_cam0")
    if not compliance:
        links, payload = None, dynamics.Payload()
    prob = _Problem(Q, P, N, T0, nominal, links, payload)
    if N is not None:
        # The detector's normal may point either way along the flange's axis: take the side the model sees.
        z = prob.flange(np.zeros(len(NAMES)))[:, :3, 2]
        if np.mean(np.sum((N @ T0[:3, :3].T) * z, axis=1)) < 0.0:
            prob.n_cam = -N
    n_params = len(NAMES)
    sigmas = _prior_sigmas()
    J = prob.jacobian(np.zeros(n_params), sigmas * 1e-3)
    keep, rank = identifiable(J, sigmas)
    comp = 6 + 4 * 6
    keep[comp : comp + 6] = keep[comp : comp + 6] & np.isin(np.arange(6), COMPLIANT) & prob.bends
    keep[:6] = True  # the scanner's pose is always fitted
    # The candidates (MODELS); "sag" only where the compliance is fitted at all.
    masks = {"pose": np.arange(n_params) < 6, "arm": keep}
    sag = masks["pose"].copy()
    sag[comp : comp + 6] = keep[comp : comp + 6]
    if not np.array_equal(sag, masks["pose"]) and not np.array_equal(sag, keep):
        masks["sag"] = sag
    held_out = {name: _held_out_misses(prob, np.flatnonzero(mask), sigmas) for name, mask in masks.items()}
    chosen = _choose(held_out)
    keep = masks[chosen]
    idx = np.flatnonzero(keep)
    sv = np.linalg.svd(J[:, idx] * sigmas[idx], compute_uv=False)  # the condition of what is fitted
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    sol = _solve(prob, idx, sigmas)
    x = np.zeros(n_params)
    x[idx] = sol.x
    pose, model = prob.model(x)
    T_cam = prob.camera(pose)
    res = prob.misses(x)
    res0 = prob.misses(np.zeros(n_params))
    # The bound where the poses went: at each, the fit's own error (its Gauss-Newton covariance, scaled by
    # the residuals' spread, carried to the flange centre) and the pose-to-pose error (the residuals' RMS
    # per axis), and never below what the chosen model missed at the poses it did not see (at the same
    # confidence); away from them that plus what the arm keeps there: after the corrections, REMAINING_PRIOR;
    # with its geometry as the controller has it, what an arm of its class errs by (``arm_error_prior``).
    bound_poses = bound_away = math.inf
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * float(np.sum(sol.fun**2) / max(sol.fun.size - idx.size, 1))
        G = sol.jac[: 3 * len(Q)].reshape(len(Q), 3, idx.size)
        bound_poses = norm_bound(G @ cov @ G.transpose(0, 2, 1), float(np.sqrt(np.mean(res**2) / 3.0)), BOUND_CONFIDENCE)
        bound_poses = max(bound_poses, float(np.quantile(held_out[chosen], BOUND_CONFIDENCE)))
        bound_away = bound_poses + (REMAINING_PRIOR if chosen == "arm" else arm_error_prior)
    except np.linalg.LinAlgError:
        pass
    held = tuple(NAMES[i] for i in range(n_params) if not keep[i])
    held_out_rms = {name: float(np.sqrt(np.mean(e**2))) for name, e in held_out.items()}
    return ArmFit(T_cam, model, res, res0, tuple(NAMES[i] for i in idx), held, rank, cond, bound_poses, bound_away, chosen, held_out_rms)


def _solve(prob: _Problem, idx: NDArray[np.intp], sigmas: Array) -> Any:
    """The maximum a posteriori fit of the parameters ``idx`` (the others at zero): scipy's least-squares result."""
    prior_w = SIGMA_POINT / sigmas[idx]
    prior_w[idx < 6] = 0.0  # no prior on the scanner's pose
    n_params = sigmas.size

    def fun(xk: Array) -> Array:
        x = np.zeros(n_params)
        x[idx] = xk
        return np.concatenate([prob.residuals(x), prior_w * xk])

    return least_squares(fun, np.zeros(idx.size), x_scale=sigmas[idx], method="trf")


def _held_out_misses(prob: _Problem, idx: NDArray[np.intp], sigmas: Array) -> Array:
    """(n,) each pose's miss (:meth:`_Problem.misses`) under the fit of ``idx`` on the other folds' poses."""
    n = len(prob.q)
    folds = min(CV_FOLDS, n)
    out = np.empty(n)
    for f in range(folds):
        test = np.arange(f, n, folds)
        sol = _solve(prob.subset(np.setdiff1d(np.arange(n), test)), idx, sigmas)
        x = np.zeros(sigmas.size)
        x[idx] = sol.x
        out[test] = prob.subset(test).misses(x)
    return out


def _choose(held_out: dict[str, Array]) -> str:
    """The simplest model (in :data:`MODELS`' order) whose mean squared held-out miss is within one standard
    error of the best one's."""
    score = {name: float(np.mean(e**2)) for name, e in held_out.items()}
    best = min(score, key=score.__getitem__)
    e2 = held_out[best] ** 2
    margin = float(np.std(e2, ddof=1) / math.sqrt(e2.size)) if e2.size > 1 else 0.0
    return next(name for name in MODELS if name in score and score[name] <= score[best] + margin)


class ArmPairs:
    """The flanges of an arm calibration's session: each found in its cloud near where ``T_base_cam`` (the
    hand-eye calibration) puts it, its centre and face normal (camera frame) kept with the controller's
    joints of the capture; then fitted (:func:`fit_arm`) as a cell of ``robot_model`` carrying ``payload``."""

    def __init__(self, flange: FlangeModel, params: DetectParams, T_base_cam: ArrayLike) -> None:
        self.flange, self.params = flange, params
        self.T_base_cam = se3.check_transform(T_base_cam, "T_base_cam")
        self._T_cam_base = se3.invert(self.T_base_cam)
        self.q: list[Array] = []
        self.p_cam: list[Array] = []
        self.n_cam: list[Array] = []
        self.skipped: list[str] = []

    def add(self, name: str, cloud: ArrayLike, p_base: ArrayLike, q: ArrayLike) -> bool:
        """One capture: ``cloud`` (camera frame), the flange centre the controller reports ``p_base`` and its
        joints ``q``; False (and why in :attr:`skipped`) when the flange is not found."""
        try:
            det = detect_flange(np.asarray(cloud), self.flange, self.params, roi_center=se3.apply(self._T_cam_base, p_base))
        except CelldError as exc:
            self.skipped.append(f"{name}: {exc}")
            return False
        self.q.append(np.asarray(q, dtype=np.float64))
        self.p_cam.append(det.center)
        self.n_cam.append(det.normal)
        return True

    def fit(self, robot_model: str, payload: dynamics.Payload, table: kin.DH | None = None, arm_error_prior: float = 1.0e-3) -> ArmFit:
        """The fit on the controller's kinematics ``table`` (``robot_model``'s published one when None);
        ``arm_error_prior`` as :func:`fit_arm`'s."""
        if len(self.q) < 4:
            why = "; ".join(self.skipped[:3])
            raise InputError(
                f"arm calibration: {len(self.q)} pairs with the flange found; it needs many more" + (f" ({why})" if why else "")
            )
        nominal, links = table or kin.model(robot_model).dh, dynamics.links(robot_model)
        return fit_arm(
            np.asarray(self.q),
            np.asarray(self.p_cam),
            self.T_base_cam,
            nominal,
            links,
            payload,
            n_cam=np.asarray(self.n_cam),
            arm_error_prior=arm_error_prior,
        )


# -- the calibration's arm entry ---------------------------------------------------------

_SIX = {key: vector(f"{key}: one per joint.", 6) for key in STORED_BOUNDS}
# The JSON shape of a calibration's ``arm`` entry (:func:`arm_entry`).
ARM_ENTRY_SCHEMA = obj(
    "The arm's kinematic calibration, fitted with the scanner's pose from wide poses (celld.calib.kinematic): "
    "corrections to the controller's kinematics, by which the cell pre-corrects where it sends the arm and "
    "reads where the arm is; T_base_cam is the scanner's pose fitted with them (it replaces the hand-eye one).",
    {
        "robot": string("The robot model whose controller kinematics the corrections are to."),
        "T_base_cam": matrix4("The scanner's pose in the base frame the corrected arm is in."),
        "corrections": obj(
            "ArmModel.as_dict: mm, mrad and mrad/(kN m) beside the controller's table, and the payload of the sag.",
            {
                **_SIX,
                "payload_kg": number("The payload the sag was fitted with, kg."),
                "payload_com_mm": vector("Its centre of mass, flange frame, mm.", 3),
            },
            (*STORED_BOUNDS, "payload_kg", "payload_com_mm"),
        ),
        "kinematics": obj(
            "The controller's own DH table the corrections are to, as its primary interface sent it (m, rad); "
            "absent: the model's published table.",
            {
                "id": string("celld.robot.primary.table_id of the table: the cell uses the corrections only on it."),
                **{k: vector(f"DH {k}, one per joint.", 6) for k in ("d", "a", "alpha", "theta")},
            },
            ("id", "d", "a", "alpha", "theta"),
        ),
        "pairs": integer("Wide poses whose flange the fit rests on.", lo=0),
        "rank": integer("Rank of the fit's scaled Jacobian over every parameter.", lo=0),
        "parameters": integer("Parameters there are (the scanner's pose and the arm's).", lo=0),
        "condition": number("Condition number of the fitted parameters' scaled Jacobian."),
        "estimated": texts("The parameters fitted."),
        "held": texts("The parameters held at zero: not told apart by the data, or held by design."),
        "residual_rms_mm": number("RMS distance of the flange centres from the fitted model's, mm."),
        "residual_max_mm": number("The largest, mm."),
        "residual_rms_before_mm": number("The same with the controller's kinematics and the hand-eye T_base_cam, mm."),
        "model": enum(
            MODELS,
            "The model kept, whichever predicts the poses its fit did not see best by cross-validation (the simplest "
            "within one standard error): 'pose' (the scanner's pose alone, the controller's kinematics as they are), "
            "'sag' (with the joints' compliance) or 'arm' (every correction the data tell apart); absent: 'arm'.",
        ),
        "held_out_rms_mm": obj(
            "Each candidate's RMS miss of a flange centre at the poses its fit did not see (cross-validation), mm.",
            {name: number(f"Model {name!r}.") for name in MODELS},
            ("pose", "arm"),
        ),
        "bound": obj(
            "Bounds on the norm of the flange's error (the poses' own region, and away from it).",
            {
                "confidence": number("The bounds' confidence."),
                "poses_mm": number("Where the wide poses went, mm."),
                "away_mm": number("Anywhere else in reach, mm (adds what an arm keeps after such a calibration)."),
                "remaining_prior_mm": number("That remainder, mm."),
            },
            ("confidence", "poses_mm", "away_mm", "remaining_prior_mm"),
        ),
    },
    ("robot", "T_base_cam", "corrections", "pairs", "rank", "parameters", "condition", "estimated", "held", "bound"),
)


def arm_entry(fit: ArmFit, robot_model: str, pairs: int) -> dict[str, Any]:
    """A calibration's ``arm`` entry (:data:`ARM_ENTRY_SCHEMA`) from an arm fit over ``pairs`` flanges of ``robot_model``."""
    report = fit.report()
    corrections = report.pop("corrections")
    entry = {"robot": robot_model, "T_base_cam": fit.T_base_cam.tolist(), "corrections": corrections, "pairs": int(pairs), **report}
    table = fit.model.nominal
    if table != kin.model(robot_model).dh:
        entry["kinematics"] = kinematics_doc(table)
    return entry


# A calibration dataset's file of the controller's table its poses were reported with (:func:`kinematics_doc`).
KINEMATICS_FILE = "kinematics.json"


def kinematics_doc(table: kin.DH) -> dict[str, Any]:
    """A controller's DH table as stored (an arm entry's ``kinematics``, a dataset's :data:`KINEMATICS_FILE`):
    its id and its rows; :func:`table_of` reads it back."""
    return {"id": primary.table_id(table), **kin.dh_as_dict(table)}


def table_of(doc: Any, robot_model: str, where: str) -> kin.DH:
    """The controller's table an arm entry's ``kinematics`` holds, checked against its id and its model.

    Raises
    ------
    InputError
        Not four rows of six finite numbers, an id that is not the table's, or a table that is not one of
        ``robot_model`` (:func:`celld.robot.primary.check_model`).
    """
    table = kin.dh_from_dict(doc, where)
    if doc.get("id") != primary.table_id(table):
        raise InputError(f"{where}.id: {doc.get('id')!r} is not the id of the table beside it ({primary.table_id(table)})")
    try:
        primary.check_model(table, kin.model(robot_model))
    except CelldError as exc:
        raise InputError(f"{where}: {exc}") from exc
    return table


def arm_of(entry: Any, where: str = "calibration.arm") -> tuple[Array, ArmModel]:
    """The scanner's pose and the arm's model a calibration's ``arm`` entry holds (:func:`arm_entry`).

    Raises
    ------
    InputError
        Not such an entry: an unknown robot model, a transform that is none, a correction out of bounds
        (:meth:`ArmModel.from_dict`); the message names the key.
    """
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected the arm's calibration (an object), got {type(entry).__name__}")
    robot = entry.get("robot")
    if not isinstance(robot, str):
        raise InputError(f"{where}.robot: expected a robot model name, got {robot!r}")
    try:
        kin.model(robot)
    except InputError as exc:
        raise InputError(f"{where}.robot: {str(exc).removeprefix('robot model: ')}") from exc
    try:
        T = se3.check_transform(entry.get("T_base_cam", []), f"{where}.T_base_cam")
    except (ValueError, TypeError) as exc:
        raise InputError(f"{where}.T_base_cam: expected a 4x4 rigid transform: {exc}") from exc
    table = table_of(entry["kinematics"], robot, f"{where}.kinematics") if "kinematics" in entry else None
    return T, ArmModel.from_dict(entry.get("corrections"), robot, f"{where}.corrections", table)
