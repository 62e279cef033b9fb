"""Algorithm 2 of the paper: seam tracking by soft touch, as a servo law of the motion loop.

The plan's geometry (its plane, the smoothed path in it) is prepared by
:mod:`celld.motion.plan`; :func:`algorithm2_plan` builds the plan message in
the main process, :func:`make_algorithm2` turns it into the law in the
motion process.

The law works in the paper's plane (Fig. 8): the welding plane of the plan,
embedded in 3D by ``T_base_plane`` (z is the plane normal, pointing away from
the work, along the finger). Points and vectors below are 2D plane
coordinates, SI units. The tool (:mod:`celld.tactile.tool`) gives

- ``P_r``: the undeformed SRM tip, origin of the tool frame;
- ``t_d``, ``n_d``: the tool's x and y axes in the plane (line 4);
- ``P_t = P_r - |d| t_d``: the torch (Eq. 14, line 9);
- ``delta``: the deformation of Eq. 15, ``P_r = P_s + delta``, from the sample.

Each cycle (500 Hz) the law runs lines 3-14:

- SERVO (lines 21-26, Eq. 16): nearest planned point ``P_v`` to ``P_r``, its
  tangent ``t_v`` and normal ``n_v``, ``V_r = V_const t_v - k_p (delta_n -
  delta_d) n_v``. ``delta_d`` is signed by the side of the wall; the normal
  deformation is predicted to the current cycle from the TCP's motion since
  the frame was captured (the wall does not move), so the camera's latency
  does not enter the loop.
- REFINE (lines 16-20, Eq. 15): each new sample in contact adds the tip
  position ``P_s = P_r - delta`` (with ``P_r`` and ``t_d`` of the frame's
  capture time) to the refined path, moved by the tip radius onto the wall.
- Torch, nearest refined point, ``omega`` (lines 9-13, Eq. 17-18): ``omega``
  makes the torch's velocity normal to the refined path vanish.

Departures from the paper, each for a reason stated where it is coded:

1. Sign of ``omega``. With ``omega`` counter-clockwise about the plane normal
   and the torch behind the tip, the torch moves with ``V_r - omega |d| n_d``,
   so Eq. 18 gives ``omega = +(V_r . n_t) / (|d| n_d . n_t)``. The paper's
   line 13 carries a minus sign (its Eq. 17 writes ``+ omega |d| n_d``) and
   ``V_r^{n_d} . t_t`` where Eq. 18 has ``. n_t``; we follow Eq. 18.
2. Torch feedback. Eq. 18 only keeps the torch parallel to the refined path;
   a lateral error of the torch would never shrink. We ask for
   ``V_t . n_t = -k_torch e`` with ``e`` the torch's signed distance to the
   refined path (``k_torch = 0`` is the paper's law).
3. Singularity guard (paper 5.2). Where ``c = |d| n_d . n_t`` falls below
   ``eps = |d| guard_cos`` line 13 is damped: ``omega = N c / eps^2`` (the
   variable-damping inverse ``N c / (c^2 + lambda^2)`` with ``lambda^2 =
   eps^2 - c^2``), continuous at ``|c| = eps``, zero at ``c = 0``. Then
   ``|omega| <= omega_max`` always; a non-finite input gives 0.
4. Contact loss. The paper reset delta_d to 0 and saw jitter. Here no
   reference ever jumps: the last correction is kept and the tool goes on
   along the last tangent for at most ``search_distance``; contact back
   resumes tracking, otherwise the law reports ``CONTACT_LOST`` and the loop
   stops on a jerk-limited ramp. Near the end of the plan a loss is the end of
   the seam: the tip goes on until the torch reaches the end of the refined
   path, then the law reports ``DONE``.
5. Approach. Before tracking, the tool moves along the planned normal towards
   the wall at ``touch_speed`` until the deformation settles at ``delta_d``.

Three plan parameters reach beyond the paper:

- ``seam_offset`` (m, >= 0): the seam lies this far from the wall the finger
  touches, on the free side (against ``side n_s``). REFINE records the wall
  point moved by it, so the refined path, which the torch follows, is the
  seam; the finger still rides the wall. 0 records the wall itself.
- ``process`` (bool): the plan asks for the process (the welding arc).
  :meth:`Algorithm2Servo.telemetry` reports ``process_on`` while the phase is
  TRACK, SEARCH or FINISH; the motion core grants it (:mod:`celld.motion.core`).
- ``seam_offsets`` (optional array (n,), m, one per planned point): the
  seam's distance from the wall where it changes along the seam (a part's gap
  variation and twist, as the scan measured the wall); REFINE takes it at the
  tip's arc position on the plan. Without it ``seam_offset`` holds everywhere.
- ``touch_only`` (bool): the law touches the wall and reports ``DONE`` once the
  deformation has settled, without tracking (a probe of the wall's position;
  the caller reads it from the loop's records).
- ``sensor_yaw`` (rad): the tool frame of the plan was turned about its z
  from the configured one by a measured torch
  (:func:`celld.tactile.tool.with_measured_torch`); the finger's deformation
  arrives in the configured frame and turns by it first. 0: the tool as
  configured.

Pure: the state, samples and plan come in as values; no clock, no I/O. The
law allocates its buffers when built, not in the loop.
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import Any, NamedTuple

import numpy as np

from celld import polyline
from celld.config import SERVO_BOUNDS, MotionLimits, ServoConfig, ToolConfig
from celld.errors import InputError
from celld.motion.plan import PlannedPath, prepare_plan, welding_plane
from celld.motion.types import ControlStatus, RobotState, ServoInput, ServoPlan, ServoTelemetry
from celld.se3 import check_points, check_transform
from celld.tactile.fingermap import FingerGain, along_normal
from celld.tactile.sample import ContactState, TactileSample, TactileStatus
from celld.tactile.tool import MAX_TORCH_YAW, ToolGeometry, yaw_in_plane

Array = np.ndarray

NAME = "algorithm2"
# Search window for the nearest planned point, either side of the last one, m
# (the tip moves 20 um per cycle at 10 mm/s; the window only has to hold the
# nearest point and keep a path that comes back near itself out).
_PLAN_WINDOW = 0.008
# Least spacing of refined points, m: a tip standing still adds nothing.
_REFINED_STEP = 0.0001
# Search window for the nearest refined point either side of the last one, points
# (at least 0.1 mm apart, so at least 4 mm).
_REFINED_WINDOW = 40
# Cycles of TCP history kept to place a sample at its capture time.
_HISTORY = 512
# Touching is done when |delta_n - delta_d| < this share of delta_d.
_TOUCHED = 0.2
# Time constant of the correction kept for a contact loss, s, and the band of
# |delta_n - delta_d| (share of delta_d) within which the correction counts as
# steady tracking (a fading contact pulls hard towards the wall: not kept).
_KEEP_TAU = 0.3
_KEEP_BAND = 0.5
# Bound of the torch error fed back, m: a larger one is a fault of the plan, not a correction.
_E_MAX = 0.003
# Largest angle between the finger axis and the plane normal accepted at start, rad.
_MAX_TILT = math.radians(30.0)
_ZERO6 = np.zeros(6)
# With a power source (ServoInput.travel not None) the torch comes to rest at the seam's start before the
# arc is struck: its travel speed falls as sqrt(2 a d) over the last distance d (a, m/s^2), and it counts as
# at the start within this distance of it, m.
_START_DECEL = 0.05
_START_TOLERANCE = 0.0002
# The speed at which the torch backs off along the welded path before a re-strike, share of v_const.
_BACKOFF_SHARE = 0.5


# -- the lines of Algorithm 2, one pure function each ---------------------------


def torch_position(P_r: Array, t_d: Array, d: float) -> Array:
    """Line 9, Eq. 14: the torch ``P_t = P_r - |d| t_d`` (2,)."""
    return P_r - d * t_d


def servo_velocity(t_v: Array, n_v: Array, v_const: float, delta_n: float, delta_d: float, k_p: float, max_correction: float) -> Array:
    """Line 24, Eq. 16: ``V_r = V_const t_v - k_p (delta_n - delta_d) n_v`` (2,).

    The normal correction is bounded by ``max_correction`` (m/s), as a seam
    tracker bounds its correction rate.
    """
    correction = min(max(-k_p * (delta_n - delta_d), -max_correction), max_correction)
    return v_const * t_v + correction * n_v


def deformation_in_plane(delta_tool: Array, t_d: Array, n_d: Array) -> Array:
    """The sample's in-plane deformation as a plane vector (2,): ``delta_t t_d + delta_n n_d``."""
    return float(delta_tool[0]) * t_d + float(delta_tool[1]) * n_d


def refine_point(P_r: Array, delta: Array, t_s: Array, n_s: Array) -> Array:
    """Line 17, Eq. 15: ``P_s = (P_r . n_s - delta^{n_s}) n_s + (P_r . t_s - delta^{t_s}) t_s`` (2,).

    ``delta`` (2,) is the in-plane deformation vector; ``t_s``, ``n_s`` the
    path's axes at the tip.
    """
    return (float(P_r @ n_s) - float(delta @ n_s)) * n_s + (float(P_r @ t_s) - float(delta @ t_s)) * t_s


def omega_line13(
    V_r: Array,
    t_d: Array,
    n_d: Array,
    n_t: Array,
    d: float,
    e: float,
    k_torch: float,
    guard_cos: float,
    omega_max: float,
) -> tuple[float, bool]:
    """Lines 12-13, Eq. 17-18: the angular velocity that keeps the torch on the refined path.

    Parameters
    ----------
    V_r : (2,)
        Linear velocity of P_r, m/s.
    t_d, n_d : (2,)
        Tool axes.
    n_t : (2,)
        Normal of the refined path at the torch's nearest point.
    d : float
        ``|d|``, m.
    e : float
        Signed lateral error of the torch along ``n_t``, m (departure 2).
    k_torch, guard_cos, omega_max : float

    Returns
    -------
    omega : float
        rad/s, counter-clockwise about the plane normal (departure 1), bounded
        by ``omega_max`` for every input.
    guarded : bool
        The guard damped or clamped omega, or refused a non-finite input.
    """
    # Line 12: V_r projected along n_d and t_d.
    V_nd = float(V_r @ n_d) * n_d
    V_td = float(V_r @ t_d) * t_d
    # Eq. 18 with the torch feedback: (V_r^{t_d} + V_r^{n_d}) . n_t + k e = omega c.
    N = float(V_td @ n_t) + float(V_nd @ n_t) + k_torch * min(max(e, -_E_MAX), _E_MAX)
    c = d * float(n_d @ n_t)
    eps = d * guard_cos
    if not (math.isfinite(N) and math.isfinite(c)) or eps <= 0.0:
        return 0.0, True
    guarded = abs(c) < eps
    # Line 13, damped inside the guard band (departure 3).
    omega = N * c / (eps * eps) if guarded else N / c
    if omega > omega_max:
        return omega_max, True
    if omega < -omega_max:
        return -omega_max, True
    return omega, guarded


def _unit(v: Array) -> Array:
    n = float(np.hypot(v[0], v[1]))
    return v / n if n > 0.0 else np.array([1.0, 0.0])


def _left(t: Array) -> Array:
    return np.array([-t[1], t[0]])


# -- parameters and the plan message ------------------------------------------------


class Algorithm2Params(NamedTuple):
    """Tuning of the law, SI units (from the servo, tool and motion sections of the config)."""

    delta_d: float  # m, desired normal deformation (unsigned)
    side: float  # +1: wall on the tool's +y side, -1: on its -y side
    k_p: float  # 1/s
    v_const: float  # m/s
    torch_offset: float  # m, |d|
    k_torch: float  # 1/s
    max_correction_speed: float  # m/s
    omega_max: float  # rad/s
    guard_cos: float
    plan_smoothing: float  # m
    refine_window: float  # m
    tip_radius: float  # m
    contact_loss_samples: int
    search_distance: float  # m
    touch_speed: float  # m/s
    touch_distance: float  # m
    tactile_stale: float  # s
    k_height: float  # 1/s, holds the tip's height above the plane
    process: bool = False  # the plan asks for the process (welding arc) while tracking
    seam_offset: float = 0.0  # m, seam's distance from the wall, on the free side (module docstring)
    touch_only: bool = False  # touch the wall, settle, report DONE (module docstring)
    sensor_yaw: float = 0.0  # rad, the tactile frame's yaw from the tool frame's (module docstring)
    # The finger's tip deflection for its tag's along the normal, a d + b d^3 (celld.tactile.fingermap), as the
    # weld's touches measured it: 1 and 0 take the tag's deformation as the tip's (Eq. 15).
    finger_gain: float = 1.0
    finger_cubic: float = 0.0  # 1/m^2

    @classmethod
    def from_config(cls, servo: ServoConfig, tool: ToolConfig, motion: MotionLimits) -> Algorithm2Params:
        return cls(
            delta_d=servo.delta_d,
            side=1.0 if tool.wall_side == "left" else -1.0,
            k_p=servo.k_p,
            v_const=servo.v_const,
            torch_offset=tool.torch_offset,
            k_torch=servo.k_torch,
            max_correction_speed=servo.max_correction_speed,
            omega_max=min(servo.omega_max, motion.max_angular_speed),
            guard_cos=servo.guard_cos,
            plan_smoothing=servo.plan_smoothing,
            refine_window=servo.refine_window,
            tip_radius=tool.tip_radius,
            contact_loss_samples=servo.contact_loss_samples,
            search_distance=servo.search_distance,
            touch_speed=servo.touch_speed,
            touch_distance=servo.touch_distance,
            tactile_stale=motion.tactile_stale,
            k_height=servo.k_p,
        )

    @classmethod
    def from_plan(cls, params: dict[str, Any]) -> Algorithm2Params:
        """Read and check the parameters carried by a :class:`ServoPlan`.

        Parameters with a default (``process``, ``seam_offset``, ``touch_only``, ``sensor_yaw``, ``finger_gain``,
        ``finger_cubic``) may be left out.
        """
        values: dict[str, Any] = {}
        for name in cls._fields:
            if name not in params:
                if name in cls._field_defaults:
                    continue
                raise InputError(f"algorithm2 plan: parameter {name!r} is missing")
            v = params[name]
            if name in ("process", "touch_only"):
                if not isinstance(v, bool):
                    raise InputError(f"algorithm2 plan: parameter {name!r} must be true or false, got {v!r}")
                values[name] = v
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise InputError(f"algorithm2 plan: parameter {name!r} must be a finite number, got {v!r}")
            values[name] = int(v) if name == "contact_loss_samples" else float(v)
        p = cls(**values)
        # The config's bounds (celld.config.SERVO_BOUNDS), checked again where the plan enters the motion process.
        for name, bound in SERVO_BOUNDS.items():
            if not bound.holds(getattr(p, name)):
                raise InputError(f"algorithm2 plan: {name} must be {bound.text()}, got {getattr(p, name)}")
        if p.side not in (1.0, -1.0):
            raise InputError(f"algorithm2 plan: side must be +1 or -1, got {p.side}")
        if p.tactile_stale <= 0.0 or min(p.tip_radius, p.k_height) < 0.0:
            raise InputError("algorithm2 plan: tactile_stale must be > 0, tip_radius and k_height >= 0")
        if not abs(p.sensor_yaw) <= MAX_TORCH_YAW:
            raise InputError(f"algorithm2 plan: sensor_yaw must be within {MAX_TORCH_YAW:.4f} rad of 0, got {p.sensor_yaw}")
        if not 0.0 <= p.seam_offset < p.torch_offset:
            # The torch trails the tip by |d|: it cannot reach a seam |d| or more off the wall.
            raise InputError(f"algorithm2 plan: seam_offset must be >= 0 and below torch_offset {p.torch_offset} m, got {p.seam_offset} m")
        try:
            FingerGain(p.finger_gain, p.finger_cubic).check(p.delta_d)
        except InputError as exc:
            raise InputError(f"algorithm2 plan: {exc}") from exc
        return p


def algorithm2_plan(
    P_base: Array,
    servo: ServoConfig,
    tool: ToolConfig,
    motion: MotionLimits,
    T_base_plane: Array | None = None,
    normal_hint: Array = np.array([0.0, 0.0, 1.0]),
    *,
    process: bool = False,
    seam_offset: float | Array = 0.0,
    sensor_yaw: float = 0.0,
    touch_only: bool = False,
    finger: FingerGain = FingerGain(),
) -> ServoPlan:
    """The :class:`ServoPlan` that starts Algorithm 2 on the planned seam ``P_base`` (n, 3).

    Built where the plan is made (the main process); the motion process turns
    it into the law with :func:`make_algorithm2`. ``process`` asks for the
    process output (welding arc) while tracking; ``seam_offset`` (m) is the
    seam's distance from the wall the finger touches, one value or one per
    point of ``P_base``; ``sensor_yaw`` (rad) the tactile frame's yaw from the
    tool frame's; ``touch_only`` ends the law once the finger has settled on
    the wall (module docstring); ``finger`` the finger's tip deflection for its
    tag's, as the weld's touches measured it (:mod:`celld.tactile.fingermap`).

    Raises
    ------
    InputError
        A parameter is out of range (the same checks as the motion process's).
    """
    P = check_points(P_base, "P_base", min_points=2)
    plane = welding_plane(P, normal_hint) if T_base_plane is None else check_transform(T_base_plane, "T_base_plane")
    geometry = ToolGeometry.from_config(tool)
    arrays = {"P_base": P, "T_base_plane": plane, "T_tcp_tool": geometry.T_tcp_tool}
    offsets = np.asarray(seam_offset, dtype=np.float64)
    if offsets.ndim:
        _offset_profile(P, plane, offsets, tool.torch_offset)  # one per point, each valid
        arrays["seam_offsets"] = offsets
        seam_offset = float(np.median(offsets))
    params = Algorithm2Params.from_config(servo, tool, motion)._replace(
        process=bool(process),
        seam_offset=float(seam_offset),
        sensor_yaw=float(sensor_yaw),
        touch_only=bool(touch_only),
        finger_gain=float(finger.gain),
        finger_cubic=float(finger.cubic),
    )
    Algorithm2Params.from_plan(dict(params._asdict()))  # refuse a bad plan where it is made
    return ServoPlan(NAME, arrays, dict(params._asdict()))


def make_algorithm2(plan: ServoPlan) -> Algorithm2Servo:
    """The servo factory registered under ``"algorithm2"`` in the motion process."""
    for key in ("P_base", "T_base_plane", "T_tcp_tool"):
        if key not in plan.arrays:
            raise InputError(f"algorithm2 plan: array {key!r} is missing")
    params = Algorithm2Params.from_plan(dict(plan.params))
    path = prepare_plan(plan.arrays["P_base"], plan.arrays["T_base_plane"], params.plan_smoothing)
    offsets = None
    if "seam_offsets" in plan.arrays:
        offsets = _offset_profile(plan.arrays["P_base"], plan.arrays["T_base_plane"], plan.arrays["seam_offsets"], params.torch_offset)
    return Algorithm2Servo(path, params, check_transform(plan.arrays["T_tcp_tool"], "T_tcp_tool"), offsets)


def _offset_profile(P_base: Array, T_base_plane: Array, seam_offsets: Array, torch_offset: float) -> tuple[Array, Array]:
    """``(s, offset)``: the seam offsets of the planned points at their arc positions in the plane
    (as :func:`~celld.motion.plan.prepare_plan` measures them); checked like ``seam_offset``."""
    P = np.asarray(P_base, dtype=np.float64)
    off = np.asarray(seam_offsets, dtype=np.float64)
    if off.shape != (len(P),):
        raise InputError(f"algorithm2 plan: seam_offsets must hold one value per planned point ({len(P)}), got shape {off.shape}")
    if not np.all(np.isfinite(off)) or off.min() < 0.0 or off.max() >= torch_offset:
        raise InputError(f"algorithm2 plan: seam_offsets must be finite, >= 0 and below torch_offset {torch_offset} m")
    T = np.asarray(T_base_plane, dtype=np.float64)
    Q = (P - T[:3, 3]) @ T[:3, :2]
    s = polyline.arc_length(Q)
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    return s[keep], off[keep]


# -- the law -------------------------------------------------------------------------


class Phase(IntEnum):
    """Where the law is on the seam."""

    TOUCH = 0  # moving towards the wall until the deformation settles at delta_d
    TRACK = 1  # Algorithm 2
    SEARCH = 2  # contact lost mid-seam: last correction, last tangent, bounded travel
    FINISH = 3  # the seam ended ahead of the tip: the torch finishes the refined path
    DONE = 4
    FAULT = 5


class Diagnostics(NamedTuple):
    """What the law did in its last cycle (for tests, benchmarks and logs outside the loop)."""

    phase: Phase
    status: ControlStatus
    omega: float  # rad/s
    guarded: bool  # the singularity guard acted
    e_torch: float  # m, torch's signed distance to the refined path (NaN before it exists)
    delta_n: float  # m, normal deformation used by SERVO (predicted to this cycle)
    V_r: Array  # (2,) m/s
    P_r: Array  # (2,) plane
    P_t: Array  # (2,) plane
    latency: float  # s from the capture of the newest sample to the cycle that first used it (NaN: none new)
    reason: str


class Algorithm2Servo:
    """Algorithm 2 as a :class:`~celld.motion.types.ServoLaw` (module docstring).

    Parameters
    ----------
    path : PlannedPath
    params : Algorithm2Params
    T_tcp_tool : (4, 4)
        The tool frame (undeformed tip) in the TCP frame.
    """

    def __init__(
        self, path: PlannedPath, params: Algorithm2Params, T_tcp_tool: Array, seam_offsets: tuple[Array, Array] | None = None
    ) -> None:
        self.path = path
        self.p = params
        self._finger = FingerGain(params.finger_gain, params.finger_cubic)
        self._offsets = seam_offsets
        self.T_tcp_tool = np.array(T_tcp_tool, dtype=np.float64)
        self._tip_offset = bool(np.any(self.T_tcp_tool[:3, 3] != 0.0))
        self._R_bp = path.T_base_plane[:3, :3]
        self._o_bp = path.T_base_plane[:3, 3]
        self._z = self._R_bp[:, 2]
        self._plan_window = int(math.ceil(_PLAN_WINDOW / float(path.s[1] - path.s[0])))
        cap = int(1.5 * path.s[-1] / _REFINED_STEP) + 1000
        self._ref = np.zeros((cap, 2))
        self._ref_s = np.zeros(cap)
        self._hist_t = np.zeros(_HISTORY, dtype=np.int64)
        self._hist_p = np.zeros((_HISTORY, 2))
        self._hist_a = np.zeros((_HISTORY, 2))
        self.guard_cycles = 0
        self.omega_peak = 0.0
        self.samples_used = 0
        self._reset()

    def _reset(self) -> None:
        self.phase = Phase.TOUCH
        self.reason = ""
        self._n_ref = 0
        self._torch_on_path = False
        self._n_hist = 0
        self._i_plan = 0
        self._i_torch = 0
        self._last_seq = -1
        self._last_valid: TactileSample | None = None
        self._last_invalid = TactileStatus.OK
        self._delta_meas = np.zeros(2)  # in-plane delta of the last valid sample (plane vector)
        self._P_r_cap = np.zeros(2)  # P_r at that sample's capture
        self._none_run = 0
        self._contact_run = 0
        self._settled_run = 0
        self._corr_kept = 0.0
        self._t_last = np.array([1.0, 0.0])
        self._n_last = np.array([0.0, 1.0])
        self._last_ns = 0
        self._travel = 0.0
        self._P_prev = np.zeros(2)
        self._P_touch0 = np.zeros(2)
        self._h0 = 0.0
        self._start_ns = 0
        self._status = ControlStatus.OK
        self._d_start = math.inf  # the torch's distance to the seam's start along the path (last cycle), m
        self._tel_n = 0  # refined points when _tel_refined was computed
        self._tel_refined = np.full(3, math.nan)
        self.last = Diagnostics(
            Phase.TOUCH, ControlStatus.OK, 0.0, False, math.nan, math.nan, np.zeros(2), np.zeros(2), np.zeros(2), math.nan, ""
        )

    # -- the refined path, read-only views for callers outside the loop --

    @property
    def refined_plane(self) -> Array:
        """The refined path so far, (k, 2) plane coordinates (a copy)."""
        return self._ref[: self._n_ref].copy()

    def to_base(self, P_plane: Array) -> Array:
        """Plane points (k, 2) to base points (k, 3)."""
        return self._o_bp + np.asarray(P_plane) @ self._R_bp[:, :2].T

    def telemetry(self) -> ServoTelemetry:
        """Phase, delta_n, latest refined point (base frame) and process wish after the last step.

        ``process_on`` is the plan's ``process`` while the phase is TRACK,
        SEARCH or FINISH and the torch is on the refined path (past its first
        point: the arc lights where the finger first touched, not |d| before it). Cheap: the refined point is converted when it changes.
        """
        n = self._n_ref
        if n != self._tel_n:
            self._tel_n = n
            self._tel_refined = self.to_base(self._ref[n - 1]) if n > 0 else np.full(3, math.nan)
            self._tel_refined.flags.writeable = False  # handed out every cycle: nobody may change it
        on = self.p.process and self._torch_on_path and self.phase in (Phase.TRACK, Phase.SEARCH, Phase.FINISH)
        return ServoTelemetry(int(self.phase), float(self.last.delta_n), self._tel_refined, bool(on), self.p.side * self.p.delta_d)

    # -- geometry of the current state --

    def _tool_in_plane(self, T_base_tcp: Array) -> tuple[Array, Array, float]:
        T_bt = T_base_tcp @ self.T_tcp_tool
        rel = T_bt[:3, 3] - self._o_bp
        P_r = rel @ self._R_bp[:, :2]
        t_d = _unit(T_bt[:3, 0] @ self._R_bp[:, :2])
        return P_r, t_d, float(rel @ self._z)

    def _remember(self, stamp_ns: int, P_r: Array, t_d: Array) -> None:
        k = self._n_hist % _HISTORY
        self._hist_t[k] = stamp_ns
        self._hist_p[k] = P_r
        self._hist_a[k] = t_d
        self._n_hist += 1

    def _at(self, stamp_ns: int) -> tuple[Array, Array]:
        """P_r and t_d at ``stamp_ns``, interpolated in the history (clamped at its ends)."""
        n = min(self._n_hist, _HISTORY)
        newest = (self._n_hist - 1) % _HISTORY
        if n == 0:
            return np.zeros(2), np.array([1.0, 0.0])
        # Walk back from the newest entry: a sample is a few cycles old.
        k = newest
        for _ in range(n - 1):
            prev = (k - 1) % _HISTORY
            if self._hist_t[prev] <= stamp_ns:
                t0, t1 = self._hist_t[prev], self._hist_t[k]
                w = 0.0 if t1 == t0 else min(max((stamp_ns - t0) / (t1 - t0), 0.0), 1.0)
                P = (1 - w) * self._hist_p[prev] + w * self._hist_p[k]
                return P, _unit((1 - w) * self._hist_a[prev] + w * self._hist_a[k])
            k = prev
        return self._hist_p[k].copy(), self._hist_a[k].copy()

    def _plan_at(self, q: Array) -> tuple[Array, Array, Array, float, bool]:
        """Line 22-23: nearest planned point to ``q``, its t_v, n_v, arc position, and whether past the end."""
        path = self.path
        i, u, _ = polyline.nearest(path.P, q, self._i_plan - self._plan_window, self._i_plan + self._plan_window + 2)
        self._i_plan = i
        j = min(i + 1, len(path.P) - 1)
        P_v = (1 - u) * path.P[i] + u * path.P[j]
        t_v = _unit((1 - u) * path.T[i] + u * path.T[j])
        s = (1 - u) * path.s[i] + u * path.s[j]
        past_end = j == len(path.P) - 1 and u >= 1.0 and float((q - path.P[-1]) @ path.T[-1]) >= 0.0
        return P_v, t_v, _left(t_v), s, past_end

    def _refined_at(self, P_t: Array) -> tuple[Array, Array, float, bool] | None:
        """Lines 10-11: the refined path's axes at the torch's nearest point and the torch's error.

        Returns ``(t_t, n_t, e, past_end)`` or None while the refined path is
        shorter than ``refine_window``. Before its first point and after its
        last the path is extended along its end chords.
        """
        n = self._n_ref
        if n < 2 or self._ref_s[n - 1] < self.p.refine_window:
            return None
        R, S = self._ref, self._ref_s
        i, u, _ = polyline.nearest(R[:n], P_t, self._i_torch - _REFINED_WINDOW, self._i_torch + _REFINED_WINDOW)
        self._i_torch = i
        j = min(i + 1, n - 1)
        s_near = (1 - u) * S[i] + u * S[j]
        # Line 11: tangent from a chord of refine_window centred on the nearest point.
        half = 0.5 * self.p.refine_window
        s0 = min(max(s_near - half, 0.0), S[n - 1] - 2 * half)
        k0 = int(np.searchsorted(S[:n], s0, side="right")) - 1
        k1 = int(np.searchsorted(S[:n], s0 + 2 * half, side="left"))
        k0, k1 = max(k0, 0), min(max(k1, k0 + 1), n - 1)
        t_t = _unit(R[k1] - R[k0])
        n_t = _left(t_t)
        anchor = (1 - u) * R[i] + u * R[j]
        e = float((P_t - anchor) @ n_t)
        past_end = j == n - 1 and u >= 1.0 and float((P_t - R[n - 1]) @ t_t) >= 0.0
        return t_t, n_t, e, past_end

    # -- ServoLaw --

    def start(self, state: RobotState) -> None:
        """Take over: remember the height above the plane and check the tool's axis."""
        self._reset()
        T = np.asarray(state.T_base_tcp, dtype=np.float64)
        if not np.all(np.isfinite(T)):
            self._fault(ControlStatus.FAULT, "the robot state at start is not finite")
            return
        T_bt = T @ self.T_tcp_tool
        tilt = math.acos(min(max(float(T_bt[:3, 2] @ self._z), -1.0), 1.0))
        if tilt > _MAX_TILT:
            self._fault(
                ControlStatus.FAULT,
                f"the finger axis is {math.degrees(tilt):.1f} deg from the welding plane's normal "
                f"(at most {math.degrees(_MAX_TILT):.0f} deg): the tool does not face the seam plane",
            )
            return
        P_r, t_d, h = self._tool_in_plane(T)
        self._h0 = h
        self._P_prev = P_r
        self._P_touch0 = P_r
        self._start_ns = state.stamp_ns
        self._i_plan = polyline.nearest(self.path.P, P_r, 0, len(self.path.P))[0]
        self._remember(state.stamp_ns, P_r, t_d)

    def _fault(self, status: ControlStatus, reason: str) -> None:
        self.phase = Phase.FAULT
        self._status = status
        self.reason = reason

    def _take_sample(self, sample: TactileSample | None, now_ns: int) -> float:
        """Consume a new sample; returns its latency at first use (s) or NaN."""
        if sample is None or sample.seq == self._last_seq:
            return math.nan
        self._last_seq = sample.seq
        latency = (now_ns - sample.stamp_ns) * 1e-9
        if not sample.valid or not np.all(np.isfinite(sample.delta_tool)):
            self._last_invalid = sample.status if sample.status != TactileStatus.OK else TactileStatus.BAD_POSE
            return latency
        self._last_invalid = TactileStatus.OK
        self.samples_used += 1
        self._last_valid = sample
        P_cap, t_cap = self._at(sample.stamp_ns)
        n_cap = _left(t_cap)
        # The tip's deflection along the normal from the tag's (the finger's gain; Eq. 15 as is with 1 and 0).
        delta = along_normal(deformation_in_plane(yaw_in_plane(sample.delta_tool, self.p.sensor_yaw), t_cap, n_cap), n_cap, self._finger)
        self._delta_meas = delta
        self._P_r_cap = P_cap
        if sample.contact == ContactState.OVERLOAD:
            self._fault(ControlStatus.OVERLOAD, f"the finger is overloaded: in-plane deformation {np.hypot(*delta) * 1e3:.2f} mm")
            return latency
        if sample.contact == ContactState.NONE:
            self._none_run += 1
            self._contact_run = 0
            return latency
        self._none_run = 0
        self._contact_run += 1
        if self.phase in (Phase.TRACK, Phase.SEARCH):
            # REFINE, lines 16-20, at the sample's capture time.
            _, t_s, n_s, s_cap, _ = self._plan_at(P_cap)
            P_s = refine_point(P_cap, delta, t_s, n_s)
            # The tip's centre rides tip_radius off the wall: record the wall,
            # moved to the seam seam_offset off it on the free side.
            P_wall = P_s + self.p.side * self.p.tip_radius * n_s
            offset = self.p.seam_offset if self._offsets is None else float(np.interp(s_cap, *self._offsets))
            P_seam = P_wall - self.p.side * offset * n_s
            self._append_refined(P_seam, t_s)
        return latency

    def _append_refined(self, P: Array, t_s: Array) -> None:
        n = self._n_ref
        if n > 0:
            step = P - self._ref[n - 1]
            if float(step @ t_s) < _REFINED_STEP:
                return
            if n >= len(self._ref):
                self._fault(ControlStatus.FAULT, "the refined path is full: the seam is longer than the plan allows")
                return
            self._ref_s[n] = self._ref_s[n - 1] + float(np.hypot(step[0], step[1]))
        self._ref[n] = P
        self._n_ref = n + 1

    def step(self, inp: ServoInput) -> tuple[Array, ControlStatus]:
        """One cycle of Algorithm 2 (module docstring); never raises on finite input."""
        state = inp.state
        T = np.asarray(state.T_base_tcp, dtype=np.float64)
        if self.phase == Phase.FAULT:
            return self._out(_ZERO6, self._status, math.nan)
        if self.phase == Phase.DONE:
            return self._out(_ZERO6, ControlStatus.DONE, math.nan)
        if not np.all(np.isfinite(T)):
            self._fault(ControlStatus.FAULT, "the robot state is not finite")
            return self._out(_ZERO6, self._status, math.nan)
        # Lines 3-5: the tool's angle, axes and position.
        P_r, t_d, h = self._tool_in_plane(T)
        n_d = _left(t_d)
        self._remember(state.stamp_ns, P_r, t_d)
        if self._last_ns == 0:
            self._last_ns = state.stamp_ns
        self._travel += float(np.hypot(*(P_r - self._P_prev)))
        self._P_prev = P_r
        # Line 6: the newest deformation.
        latency = self._take_sample(inp.tactile, state.stamp_ns)
        if self.phase == Phase.FAULT:
            return self._out(_ZERO6, self._status, latency)
        ref_ns = self._last_valid.stamp_ns if self._last_valid is not None else self._start_ns
        age = (state.stamp_ns - ref_ns) * 1e-9
        if age > self.p.tactile_stale:
            why = self._last_invalid.name if self._last_invalid != TactileStatus.OK else "no new sample"
            self._fault(ControlStatus.STALE_TACTILE, f"no valid tactile sample for {age * 1e3:.0f} ms (last: {why})")
            return self._out(_ZERO6, self._status, latency)

        delta_d = self.p.side * self.p.delta_d
        gate = inp.travel
        v_t = self._travel_speed(gate)
        _, t_v, n_v, s_tip, past_end = self._plan_at(P_r)
        # The wall stands still: the normal deformation grows by how far the
        # tip has moved towards it since the frame was captured.
        delta_n = float(self._delta_meas @ n_v) + float((P_r - self._P_r_cap) @ n_v) if self._last_valid else 0.0
        in_contact = self._last_valid is not None and self._none_run == 0

        if self.phase == Phase.TOUCH:
            if in_contact and abs(delta_n - delta_d) < _TOUCHED * self.p.delta_d:
                self._settled_run += 1
            else:
                self._settled_run = 0
            if self._settled_run >= self.p.contact_loss_samples:
                if self.p.touch_only:
                    self.phase = Phase.DONE
                    return self._out(_ZERO6, ControlStatus.DONE, latency)
                self.phase = Phase.TRACK
            elif float(np.hypot(*(P_r - self._P_touch0))) > self.p.touch_distance:
                self._fault(ControlStatus.CONTACT_LOST, f"no wall within the touch distance of {self.p.touch_distance * 1e3:.1f} mm")
                return self._out(_ZERO6, self._status, latency)
            # Approach along n_v with the law of Eq. 16 and no tangential speed.
            V_r = servo_velocity(t_v, n_v, 0.0, delta_n if in_contact else 0.0, delta_d, self.p.k_p, self.p.touch_speed)
            return self._twist(T, V_r, 0.0, False, h, math.nan, delta_n, P_r, torch_position(P_r, t_d, self.p.torch_offset), latency)

        if self.phase == Phase.TRACK:
            if past_end:
                self._begin_finish()
            elif self._none_run >= self.p.contact_loss_samples:
                if s_tip >= self.path.s[-1] - self.p.search_distance:
                    self._begin_finish()
                else:
                    self.phase = Phase.SEARCH
                    self._travel = 0.0
        elif self.phase == Phase.SEARCH:
            if self._contact_run >= self.p.contact_loss_samples:
                self.phase = Phase.TRACK
            elif past_end or s_tip >= self.path.s[-1] - 1e-9:
                self._begin_finish()
            elif self._travel > self.p.search_distance:
                self._fault(
                    ControlStatus.CONTACT_LOST,
                    f"contact lost for {self._travel * 1e3:.1f} mm (search distance {self.p.search_distance * 1e3:.1f} mm)",
                )
                return self._out(_ZERO6, self._status, latency)

        if self.phase == Phase.TRACK:
            # Line 8: SERVO (the travel speed gated by the arc, when there is a power source).
            V_r = servo_velocity(t_v, n_v, v_t, delta_n, delta_d, self.p.k_p, self.p.max_correction_speed)
            if abs(delta_n - delta_d) < _KEEP_BAND * self.p.delta_d:
                # The steady correction (the drift between plan and wall), kept for a loss.
                a = min(max((state.stamp_ns - self._last_ns) * 1e-9 / _KEEP_TAU, 0.0), 1.0)
                self._corr_kept += a * (float(V_r @ n_v) - self._corr_kept)
            self._t_last, self._n_last = t_v, n_v
        elif self.phase == Phase.SEARCH:
            # Keep the last steady correction and the last tangent (departure 4).
            V_r = v_t * self._t_last + self._corr_kept * self._n_last
        else:
            V_r = v_t * self._t_last
        # Line 9: the torch.
        P_t = torch_position(P_r, t_d, self.p.torch_offset)
        # Lines 10-11 on the refined path; on the plan until it is long enough.
        near = self._refined_at(P_t)
        if near is None:
            i, _, _ = polyline.nearest(self.path.P, P_t, 0, len(self.path.P))
            n_t, e, torch_done = self.path.N[i], 0.0, False
            self._torch_on_path = False
        else:
            t_t, n_t, e, torch_done = near
            # The torch has reached the refined path once it is past its first point (with a power source:
            # once it has come to rest there, within _START_TOLERANCE).
            self._d_start = float((self._ref[0] - P_t) @ t_t)
            reach = 0.0 if gate is None else _START_TOLERANCE
            on_now = self._i_torch > 0 or self._d_start <= reach
            self._torch_on_path = on_now or (gate is not None and self._torch_on_path)
            if self.phase == Phase.FINISH:
                # The seam has ended ahead: go on along the refined path where the torch is.
                V_r = v_t * t_t
        if self.phase == Phase.FINISH and torch_done:
            self.phase = Phase.DONE
            return self._out(_ZERO6, ControlStatus.DONE, latency)
        if gate == 0 and self._torch_on_path:
            # The arc is not established and the torch is where it must burn (the seam's start, or where it went
            # out): the arm holds still, no correction across or in height either, so the torch does not creep.
            return self._out(_ZERO6, ControlStatus.OK, latency)
        # Lines 12-13 (no turning while the torch backs off: the heading law steers forward travel).
        if gate is not None and gate < 0:
            omega, guarded = 0.0, False
        else:
            omega, guarded = omega_line13(V_r, t_d, n_d, n_t, self.p.torch_offset, e, self.p.k_torch, self.p.guard_cos, self.p.omega_max)
        return self._twist(T, V_r, omega, guarded, h, e if near is not None else math.nan, delta_n, P_r, P_t, latency)

    def _travel_speed(self, gate: int | None) -> float:
        """The speed along the seam the arc's travel gate allows (ServoInput.travel), m/s."""
        v = self.p.v_const
        if gate is None or gate > 0:
            return v
        if gate < 0:
            return -_BACKOFF_SHARE * v
        if self._torch_on_path:
            return 0.0  # at the start, or where the arc went out: held still until it burns (step)
        return min(v, math.sqrt(2.0 * _START_DECEL * max(self._d_start - _START_TOLERANCE, 0.0)))

    def _begin_finish(self) -> None:
        self.phase = Phase.FINISH

    def _twist(
        self,
        T: Array,
        V_r: Array,
        omega: float,
        guarded: bool,
        h: float,
        e: float,
        delta_n: float,
        P_r: Array,
        P_t: Array,
        latency: float,
    ) -> tuple[Array, ControlStatus]:
        """Line 14: the TCP twist (6,) in the base frame that moves P_r with V_r and turns at omega."""
        if guarded:
            self.guard_cycles += 1
        self.omega_peak = max(self.omega_peak, abs(omega))
        self._last_ns = self._hist_t[(self._n_hist - 1) % _HISTORY]
        # In the plane, plus a hold of the tip's height above it.
        v_tip = self._R_bp[:, :2] @ V_r - self.p.k_height * (h - self._h0) * self._z
        w = omega * self._z
        # P_r is the tool origin; the TCP moves with v_tip + w x (p_tcp - p_tip).
        if self._tip_offset:
            r = -(T[:3, :3] @ self.T_tcp_tool[:3, 3])
            v_tip = v_tip + np.array([w[1] * r[2] - w[2] * r[1], w[2] * r[0] - w[0] * r[2], w[0] * r[1] - w[1] * r[0]])
        v_tcp = v_tip
        self.last = Diagnostics(self.phase, ControlStatus.OK, omega, guarded, e, delta_n, V_r.copy(), P_r, P_t, latency, "")
        return np.concatenate([v_tcp, w]), ControlStatus.OK

    def _out(self, twist: Array, status: ControlStatus, latency: float) -> tuple[Array, ControlStatus]:
        self.last = Diagnostics(
            self.phase, status, 0.0, False, math.nan, math.nan, np.zeros(2), self.last.P_r, self.last.P_t, latency, self.reason
        )
        return twist, status
