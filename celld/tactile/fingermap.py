"""The finger's tag against its tip: how far the tip is deflected for the deformation the tag shows.

Eq. 15 reads the tip's deflection from the tag's displacement, as if the tag
moved with the tip. It sits inside the finger, short of the tip, so it moves
less, and less still as the finger bends. Along the direction the finger is
pressed into a wall the cell measures the relation itself: while a touch
comes onto a wall, the tip stays on it, so every frame's tag deformation
``d`` and the tip's position across the joint ``y`` at that frame's capture
obey::

    y = w + side * (a d + b d^3)

with ``w`` the touched wall (one per touch) and ``(a, b)`` the finger's gain
and its cubic term, shared by the touches (:func:`fit_finger_gain`). The
servo then holds and refines with ``a d + b d^3`` in place of ``d`` along the
joint's normal (:meth:`FingerGain.tip`); along the wall (where friction, not
the wall, sets the tip) the tag's deformation is used as it is.

All functions here are pure.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from celld.errors import InputError, TactileError

Array = np.ndarray

# The gains a working finger can have: outside them the tag has come loose or the finger is broken.
GAIN_RANGE = (0.7, 1.4)
# The cubic term's largest effect at the deformation held, as a share of the linear one.
MAX_CUBIC_SHARE = 0.3
# A touch's frames must span at least this share of the deformation held to tell a slope.
MIN_SPAN = 0.3
# And the fit needs this many frames in all.
MIN_FRAMES = 8


class FingerRefused(TactileError):
    """The touches measured a gain no working finger has: its tag has come loose, or the finger is broken."""


class FingerGain(NamedTuple):
    """The tip's deflection for the tag's, along the joint's normal: ``gain d + cubic d^3`` (m)."""

    gain: float = 1.0
    cubic: float = 0.0  # 1/m^2

    def tip(self, d: float | Array) -> float | Array:
        """The tip's deflection (m) for the tag's ``d`` (m, signed)."""
        return self.gain * d + self.cubic * d * d * d

    def over(self, d: float) -> float:
        """The tip's deflection over the tag's where the tag shows ``d`` (m)."""
        return self.gain + self.cubic * d * d

    def reading(self) -> dict[str, float]:
        """The gain in a result's units (``gain``, ``cubic_per_mm2``)."""
        return {"gain": round(self.gain, 5), "cubic_per_mm2": round(self.cubic * 1e-6, 6)}

    @classmethod
    def of_reading(cls, reading: Mapping[str, Any]) -> FingerGain:
        """The gain of a reading in a result's units (:meth:`reading`)."""
        return cls(float(reading["gain"]), float(reading["cubic_per_mm2"]) * 1e6)

    def check(self, delta_d: float) -> FingerGain:
        """This gain, if a finger can have it where the servo holds ``delta_d`` (m).

        Raises
        ------
        InputError
            Not finite, the gain outside :data:`GAIN_RANGE`, or the cubic term more than
            :data:`MAX_CUBIC_SHARE` of the linear one at ``delta_d``.
        """
        if not (math.isfinite(self.gain) and math.isfinite(self.cubic)):
            raise InputError(f"finger gain: expected finite numbers, got {self.gain!r}, {self.cubic!r}")
        if not GAIN_RANGE[0] <= self.gain <= GAIN_RANGE[1]:
            raise InputError(f"finger gain: {self.gain:.4f} is outside {GAIN_RANGE[0]}-{GAIN_RANGE[1]}")
        if abs(self.cubic) * delta_d * delta_d > MAX_CUBIC_SHARE * self.gain:
            raise InputError(
                f"finger gain: the cubic term {self.cubic:.4g} /m^2 changes the deflection by more than "
                f"{MAX_CUBIC_SHARE:.0%} at {delta_d * 1e3:g} mm"
            )
        return self


class Press(NamedTuple):
    """One touch's frames while the tip stayed on its wall."""

    y: Array  # (k,) the undeformed tip centre's position across the joint at each frame's capture, m
    d: Array  # (k,) the tag's normal deformation in that frame, m (signed as the servo's delta_n)
    side: float  # +1 or -1: y = wall + side * tip deflection


class FingerFit(NamedTuple):
    """What :func:`fit_finger_gain` found."""

    finger: FingerGain
    gain_sigma: float  # 1 sigma of the gain from the fit's scatter
    residual_rms: float  # m, the frames' RMS distance from the fit
    walls: tuple[float, ...]  # m, each touch's wall (the tip centre's position across the joint at zero deflection)
    frames: int
    span: tuple[float, float]  # m, the least and largest |d| fitted

    def as_dict(self) -> dict[str, float | int | list[float]]:
        """The fit as a weld's result has it (mm, um)."""
        return {
            **self.finger.reading(),
            "gain_sigma": round(self.gain_sigma, 5),
            "residual_rms_um": round(self.residual_rms * 1e6, 3),
            "frames": self.frames,
            "span_mm": [round(self.span[0] * 1e3, 4), round(self.span[1] * 1e3, 4)],
        }


def fit_finger_gain(presses: Sequence[Press], delta_d: float, cubic: bool = True) -> FingerFit:
    """The finger's gain (and cubic term) from touches onto walls (module docstring), by linear least squares.

    Parameters
    ----------
    presses
        The touches' frames in contact (:class:`Press`), one per wall.
    delta_d : float
        The deformation the servo holds, m: what the frames must span a share of, and where the gain is checked.
    cubic : bool
        Fit the cubic term too (else it is zero).

    Raises
    ------
    TactileError
        Too few frames, or a touch whose frames do not span :data:`MIN_SPAN` of ``delta_d``.
    FingerRefused
        A gain no working finger has (the tag loose, the finger broken).
    """
    if not presses:
        raise InputError("finger gain: no touch to fit")
    rows, ys = [], []
    for j, p in enumerate(presses):
        y, d = np.asarray(p.y, dtype=np.float64), np.asarray(p.d, dtype=np.float64)
        if y.shape != d.shape or y.ndim != 1 or not (np.all(np.isfinite(y)) and np.all(np.isfinite(d))):
            raise InputError(f"finger gain: touch {j}: expected finite (k,) positions and deformations")
        if p.side not in (1.0, -1.0):
            raise InputError(f"finger gain: touch {j}: side must be +1 or -1, got {p.side}")
        if len(d) == 0 or float(np.ptp(np.abs(d))) < MIN_SPAN * delta_d:
            span = float(np.ptp(np.abs(d))) if len(d) else 0.0
            raise TactileError(
                f"finger gain: touch {j}'s frames span {span * 1e3:.3f} mm of deformation (at least "
                f"{MIN_SPAN * delta_d * 1e3:.3f} mm needed): the touch came onto its wall too fast for the camera"
            )
        for yk, dk in zip(y, d, strict=True):
            row = [0.0] * len(presses) + [p.side * dk] + ([p.side * dk**3] if cubic else [])
            row[j] = 1.0
            rows.append(row)
            ys.append(yk)
    A, b = np.asarray(rows, dtype=np.float64), np.asarray(ys, dtype=np.float64)
    n, m = A.shape
    if n < max(MIN_FRAMES, m + 2):
        raise TactileError(f"finger gain: {n} frames in contact, at least {max(MIN_FRAMES, m + 2)} needed")
    # Columns scaled to unit norm: the cubic one is some 1e-9 of the others.
    scale = np.linalg.norm(A, axis=0)
    x, *_ = np.linalg.lstsq(A / scale, b, rcond=None)
    x = x / scale
    r = b - A @ x
    s2 = float(r @ r) / (n - m)
    cov = s2 * np.linalg.inv(A.T @ A)
    k = len(presses)
    finger = FingerGain(float(x[k]), float(x[k + 1]) if cubic else 0.0)
    try:
        finger.check(delta_d)
    except InputError as exc:
        raise FingerRefused(f"{exc}: the tag moves {1.0 / finger.gain:.3f} times the tip; check the finger and its tag") from exc
    d_all = np.abs(np.concatenate([np.asarray(p.d, dtype=np.float64) for p in presses]))
    return FingerFit(
        finger,
        float(math.sqrt(cov[k, k])),
        float(math.sqrt(float(r @ r) / n)),
        tuple(float(v) for v in x[:k]),
        n,
        (float(d_all.min()), float(d_all.max())),
    )


def along_normal(delta: Array, n: Array, finger: FingerGain) -> Array:
    """A plane deformation (2,) with its component along the unit normal ``n`` (2,) taken through ``finger``."""
    d = float(delta @ n)
    return np.asarray(delta + (float(finger.tip(d)) - d) * n, dtype=np.float64)
