"""The SRM tip and the torch's wire end in a scanner cloud, each found near where it is believed (pure).

The finger ends in a small ball (``tool.tip_radius``, 1 mm on the SRM). The
controller believes the tip is at ``p_pred`` (its tool config and the robot
pose, placed in the camera frame with the current calibration); the truth
may be a millimetre or two away. :func:`detect_tip` finds it:

1. crop: the points within ``window`` of ``p_pred`` (a cloud with none is
   refused, with the reason);
2. apex: the finger's end is the extreme of those points along the finger
   axis, away from the flange (``-u``): the mean of the few most extreme
   points, and the ball's centre one radius back along ``u``;
3. sphere of known radius: Gauss-Newton on ``sum (|p - c| - r)^2`` over the
   points in a shell of the ball around the current centre, leaving out the
   finger's (those more than a fraction of the radius towards the flange),
   selection and fit repeated until the selection settles.

With a known radius a visible cap suffices: the centre lies one radius
behind the surface the scanner sees.

The torch point is the centre of the welding wire's cut end, a cylinder of
the wire's radius ending in a flat face. :func:`detect_wire_end` finds it
the same way: crop near the prediction, the extreme points along the wire's
axis, then a least-squares fit of a capped cylinder of known radius and
known axis (the tool's, from the robot pose) to the wire's last millimetres:
the end face fixes the point along the axis, the face and the wire's side
fix it across (an end-on view sees the face, an oblique one the side).
Everything is in the camera frame, m.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from celld.errors import CalibrationError, InputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TipDetectParams:
    """Parameters of :func:`detect_tip` (SI units).

    Attributes
    ----------
    window : float
        Radius of the search window around the predicted tip, m.
    apex_points : int
        How many of the most extreme points give the finger's end.
    shell : float
        Points within ``radius +- shell`` of the centre are the ball's, m.
    axial_cut : float
        Points more than this times the radius towards the flange (along
        ``u``) from the centre are the finger's, not the ball's.
    min_points : int
        Fewest ball points for a detection.
    max_rms : float
        Largest RMS distance of the ball points from the fitted sphere, m.
    rounds : int
        Most selection / fit rounds.
    """

    window: float = 0.015
    apex_points: int = 5
    shell: float = 0.4e-3
    axial_cut: float = 0.3
    min_points: int = 12
    max_rms: float = 0.2e-3
    rounds: int = 8

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window) and 0.001 <= self.window <= 0.1):
            raise InputError(f"window: expected 1 mm <= window <= 100 mm, got {self.window!r} m")
        if not (math.isfinite(self.shell) and self.shell > 0.0 and math.isfinite(self.max_rms) and self.max_rms > 0.0):
            raise InputError("shell and max_rms: expected finite values > 0")
        if self.apex_points < 1 or self.min_points < 4 or self.rounds < 1:
            raise InputError("apex_points >= 1, min_points >= 4 and rounds >= 1 expected")
        if not (math.isfinite(self.axial_cut) and -1.0 <= self.axial_cut <= 1.0):
            raise InputError(f"axial_cut: expected -1 <= value <= 1, got {self.axial_cut!r}")


@dataclass(frozen=True)
class TipDetection:
    """A tip found in a cloud, camera frame.

    Attributes
    ----------
    p_cam : (3,) array
        The ball's centre, m.
    n_points : int
        Points of the ball the fit used.
    rms : float
        Their RMS distance from the sphere, m.
    window_points : int
        Points in the search window.
    offset : float
        Distance of the centre from the prediction, m.
    """

    p_cam: Array
    n_points: int
    rms: float
    window_points: int
    offset: float


def window_points(points_cam: ArrayLike, p_pred: ArrayLike, window: float) -> Array:
    """The finite points of a cloud ((H, W, 3) organized or (n, 3), NaN for no return) within ``window`` of ``p_pred``."""
    P = np.asarray(points_cam)
    if P.ndim < 2 or P.shape[-1] != 3:
        raise InputError(f"points_cam: expected an (H, W, 3) or (n, 3) cloud, got shape {P.shape}")
    P = P.reshape(-1, 3)
    c = np.asarray(p_pred, dtype=np.float64)
    # Cheap box test first (float32 of millions of points), the exact distance on what is left.
    near = np.all(np.abs(P - c.astype(P.dtype)) <= window, axis=1)
    Q = P[near].astype(np.float64)
    Q = Q[np.all(np.isfinite(Q), axis=1)]
    return np.asarray(Q[np.linalg.norm(Q - c, axis=1) <= window], dtype=np.float64)


def fit_sphere_known_radius(P: ArrayLike, c0: ArrayLike, radius: float, iterations: int = 20) -> tuple[Array, float]:
    """Gauss-Newton on ``sum (|p - c| - r)^2``: the centre (3,) and the RMS of ``|p - c| - r``, m."""
    Q = np.asarray(P, dtype=np.float64)
    c = np.asarray(c0, dtype=np.float64).copy()
    for _ in range(iterations):
        d = Q - c
        dist = np.linalg.norm(d, axis=1)
        dist = np.where(dist < 1e-12, 1e-12, dist)
        r = dist - radius
        J = -d / dist[:, None]  # d(|p - c|)/dc
        step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        c = c + step
        if float(np.linalg.norm(step)) < 1e-9:
            break
    res = np.linalg.norm(Q - c, axis=1) - radius
    return c, float(np.sqrt(np.mean(res**2)))


def detect_tip(
    points_cam: ArrayLike,
    p_pred: ArrayLike,
    u_cam: ArrayLike,
    radius: float,
    params: TipDetectParams = TipDetectParams(),
) -> TipDetection:
    """The tip ball's centre in a cloud (module docstring), camera frame.

    Parameters
    ----------
    points_cam : (H, W, 3) or (n, 3)
        The cloud, camera frame, m; NaN where there is no return.
    p_pred : (3,)
        Where the tool config puts the tip's centre, camera frame, m.
    u_cam : (3,)
        The finger's axis from the tip towards the flange, camera frame (normalised here).
    radius : float
        The tip ball's radius, m.
    params : TipDetectParams

    Raises
    ------
    InputError
        A prediction, axis or radius that is not usable.
    CalibrationError
        No points in the window, too few on the ball, or a fit that does not
        hold (the message says which and the figures).
    """

    def start(W: Array, p: Array, u: Array) -> Array:
        s = (W - p) @ (-u)
        apex = W[np.argsort(s)[-min(params.apex_points, len(W)) :]].mean(axis=0)
        return np.asarray(apex + radius * u, dtype=np.float64)

    def select(W: Array, c: Array, u: Array) -> NDArray[np.bool_]:
        d = W - c
        return np.asarray((np.abs(np.linalg.norm(d, axis=1) - radius) <= params.shell) & (d @ u <= params.axial_cut * radius))

    def fit(Q: Array, c: Array, u: Array) -> tuple[Array, float]:
        return fit_sphere_known_radius(Q, c, radius)

    names = _Names("tip", "the tip", "the tip ball", "the tip ball's points", f"a {radius * 1e3:.2f} mm sphere", "the tip", "tip")
    return _detect(points_cam, p_pred, u_cam, radius, params, names, start, select, fit)


@dataclass(frozen=True)
class WireDetectParams:
    """Parameters of :func:`detect_wire_end` (SI units).

    Attributes
    ----------
    window : float
        Radius of the search window around the predicted wire end, m.
    apex_points : int
        How many of the most extreme points give the wire's end.
    length : float
        How much of the wire, back from its end, the fit uses, m (the nozzle
        and the contact tip lie further back).
    shell : float
        Points within this of the fitted surface are the wire's, m.
    min_points : int
        Fewest wire points for a detection.
    max_rms : float
        Largest RMS distance of the wire points from the fitted surface, m.
    rounds : int
        Most selection / fit rounds.
    """

    window: float = 0.015
    apex_points: int = 3
    length: float = 0.005
    shell: float = 0.3e-3
    min_points: int = 8
    max_rms: float = 0.2e-3
    rounds: int = 4

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window) and 0.001 <= self.window <= 0.1):
            raise InputError(f"window: expected 1 mm <= window <= 100 mm, got {self.window!r} m")
        if not (math.isfinite(self.length) and 0.0005 <= self.length <= self.window):
            raise InputError(f"length: expected 0.5 mm <= length <= window, got {self.length!r} m")
        if not (math.isfinite(self.shell) and self.shell > 0.0 and math.isfinite(self.max_rms) and self.max_rms > 0.0):
            raise InputError("shell and max_rms: expected finite values > 0")
        if self.apex_points < 1 or self.min_points < 4 or self.rounds < 1:
            raise InputError("apex_points >= 1, min_points >= 4 and rounds >= 1 expected")


def capped_cylinder_distance(Q: Array, c: Array, u: Array, radius: float) -> Array:
    """Signed distance (n,) of points from a solid half-infinite cylinder: end-face centre ``c``, axis ``u`` into the solid.

    Positive outside, negative inside, m.
    """
    d = Q - c
    a = d @ u  # along the axis, into the wire
    rho = np.linalg.norm(d - np.outer(a, u), axis=1)
    side = rho - radius
    beyond = np.where(side > 0.0, np.hypot(side, a), -a)
    inside = -np.minimum(a, -side)
    return np.asarray(np.where(a >= 0.0, np.where(side >= 0.0, side, inside), beyond), dtype=np.float64)


def _check_prediction(p_pred: ArrayLike, u_cam: ArrayLike, radius: float) -> tuple[Array, Array]:
    p = np.asarray(p_pred, dtype=np.float64)
    u = np.asarray(u_cam, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"p_pred: expected a finite (3,) point, got {p.tolist()}")
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-9:
        raise InputError(f"u_cam: expected a non-zero finite (3,) direction, got {u.tolist()}")
    if not (math.isfinite(radius) and 0.0 < radius <= 0.02):
        raise InputError(f"radius: expected 0 < radius <= 20 mm, got {radius!r} m")
    return p, u / np.linalg.norm(u)


class _Names(NamedTuple):
    """How :func:`_detect`'s messages name what it looks for."""

    predicted: str  # "no points within ... of the predicted <predicted>"
    hidden: str  # "<hidden> is out of the scanner's view"
    part: str  # "only n points on <part>"
    points: str  # "<points> lie ... RMS off"
    surface: str  # "lie ... RMS off <surface>"
    not_what: str  # "...: not <not_what>"
    fitted: str  # "the fitted <fitted> lies ... from the prediction"


def _detect(
    points_cam: ArrayLike,
    p_pred: ArrayLike,
    u_cam: ArrayLike,
    radius: float,
    params: TipDetectParams | WireDetectParams,
    names: _Names,
    start: Callable[[Array, Array, Array], Array],
    select: Callable[[Array, Array, Array], NDArray[np.bool_]],
    fit: Callable[[Array, Array, Array], tuple[Array, float]],
) -> TipDetection:
    """The shared detection: the window about the prediction, a start ``c`` from its points,
    then rounds of selecting the points near the shape at ``c`` and fitting it to them, and the checks."""
    p, u = _check_prediction(p_pred, u_cam, radius)
    W = window_points(points_cam, p, params.window)
    if len(W) == 0:
        raise CalibrationError(
            f"no points within {params.window * 1e3:.1f} mm of the predicted {names.predicted}: {names.hidden} is out of "
            "the scanner's view or hidden, or the tool config or the calibration is far off"
        )
    c = start(W, p, u)
    sel: NDArray[np.bool_] | None = None
    rms = math.inf
    for _ in range(params.rounds):
        new = select(W, c, u)
        if sel is not None and np.array_equal(new, sel):
            break
        sel = new
        if int(sel.sum()) < params.min_points:
            break
        c, rms = fit(W[sel], c, u)
    n = int(sel.sum()) if sel is not None else 0
    if n < params.min_points:
        raise CalibrationError(
            f"only {n} points on {names.part} ({len(W)} in the {params.window * 1e3:.1f} mm window); "
            f"at least {params.min_points} are needed"
        )
    if not rms <= params.max_rms:
        raise CalibrationError(
            f"{names.points} lie {rms * 1e3:.3f} mm RMS off {names.surface} (at most {params.max_rms * 1e3:.3f} mm): not {names.not_what}"
        )
    offset = float(np.linalg.norm(c - p))
    if offset > params.window:
        raise CalibrationError(
            f"the fitted {names.fitted} lies {offset * 1e3:.2f} mm from the prediction, outside the {params.window * 1e3:.1f} mm window"
        )
    return TipDetection(np.asarray(c, dtype=np.float64), n, rms, len(W), offset)


def detect_wire_end(
    points_cam: ArrayLike,
    p_pred: ArrayLike,
    u_cam: ArrayLike,
    radius: float,
    params: WireDetectParams = WireDetectParams(),
) -> TipDetection:
    """The centre of the welding wire's cut end in a cloud (module docstring), camera frame.

    Parameters
    ----------
    points_cam : (H, W, 3) or (n, 3)
        The cloud, camera frame, m; NaN where there is no return.
    p_pred : (3,)
        Where the tool config puts the wire's end, camera frame, m.
    u_cam : (3,)
        The wire's axis from its end back into the torch, camera frame (normalised here).
    radius : float
        The wire's radius, m.
    params : WireDetectParams

    Raises
    ------
    InputError
        A prediction, axis or radius that is not usable.
    CalibrationError
        No points in the window, too few on the wire, or a fit that does not
        hold (the message says which and the figures).
    """

    def start(W: Array, p: Array, u: Array) -> Array:
        s = (W - p) @ (-u)
        s_end = float(np.sort(s)[-min(params.apex_points, len(W)) :].mean())
        # Across the axis: the end's points, centred (an oblique view's side points pull this by
        # well under a radius; the fit takes it out). Along: the extreme.
        lateral = W[s >= s_end - radius].mean(axis=0)
        lateral = lateral - ((lateral - p) @ u) * u
        return np.asarray(lateral - s_end * u, dtype=np.float64)

    def select(W: Array, c: Array, u: Array) -> NDArray[np.bool_]:
        return np.asarray((np.abs(capped_cylinder_distance(W, c, u, radius)) <= params.shell) & ((W - c) @ u <= params.length))

    def fit(Q: Array, c: Array, u: Array) -> tuple[Array, float]:
        got = least_squares(lambda x: capped_cylinder_distance(Q, x, u, radius), c, loss="soft_l1", f_scale=params.shell / 3.0)
        c = np.asarray(got.x, dtype=np.float64)
        return c, float(np.sqrt(np.mean(capped_cylinder_distance(Q, c, u, radius) ** 2)))

    names = _Names("wire end", "the torch", "the wire's end", "the wire's points", f"a {radius * 2e3:.2f} mm wire", "the wire", "wire end")
    return _detect(points_cam, p_pred, u_cam, radius, params, names, start, select, fit)
