"""The weld data of one weld: arc time, starts and breaks, current and voltage, and the time outside the windows.

Pure: the per-cycle samples the motion loop read while the weld ran (its
time stamps, the power source's arc-stable signal, the measured current and
voltage) in, a frozen :class:`WeldData` out. A weld whose current or voltage
left its procedure's window is flagged (:attr:`WeldData.flagged`), never
passed in silence.

Definitions (the samples are ``i = 0 .. n-1`` at times ``t_i``):

- a sample stands for the time to the next one, ``t_{i+1} - t_i``; the last
  for the spacing before it (one loop period), so n samples of a 500 Hz loop
  are n / 500 s;
- an **arc start** is a sample with the arc on whose predecessor had it off;
  data that starts with the arc on starts with one;
- an **arc end** is a sample with the arc off whose predecessor had it on,
  at that sample's time. It is an **arc break** (the arc went out on its
  own) when it comes before ``ended_at_s``, the time the cell itself switched
  the arc off, or always when the cell never did (``None``); an end at or
  after ``ended_at_s`` is the cell's own arc-off. Data that ends with the arc
  on has no end there;
- the windows are **judged** on the arc-on samples at least ``grace_s`` after
  their arc's start (the arc settles first) whose current and voltage are
  both numbers; a judged sample is **outside** when either its current or its
  voltage is outside its window (ends inclusive). A NaN current or voltage on
  an arc-on sample past the grace is counted (``nan_samples``) and left out of
  every figure: it is neither inside nor outside.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld.errors import InputError
from celld.schemadoc import boolean, integer, number, obj

# as_dict rounds to this many decimals: 0.1 ms, 0.1 mA, 0.1 mV, well below what a source measures.
_DECIMALS = 4
# A sample this close to the end of its arc's grace counts as past it, s: a grace of a whole number of loop
# periods then takes that many samples, whatever the rounding of the time stamps.
_GRACE_TOL = 1e-9


@dataclass(frozen=True)
class WeldData:
    """The weld data of one weld (module docstring for the definitions); all zeros for no samples.

    Attributes
    ----------
    samples : int
        Every sample given.
    arc_time_s : float
        The time with the arc on, s.
    arc_starts, arc_breaks : int
        Arc starts, and arc ends that were not the cell's own arc-off.
    judged_samples, judged_s : int, float
        The samples (and their time, s) the windows were applied to.
    current_mean_a, current_min_a, current_max_a : float
        The current over the judged samples, A (0 when none was judged).
    voltage_mean_v, voltage_min_v, voltage_max_v : float
        The voltage over the judged samples, V (0 when none was judged).
    outside_samples, outside_s : int, float
        The judged samples (and their time, s) with the current or the voltage outside its window.
    nan_samples : int
        Arc-on samples past the grace whose current or voltage was NaN (left out of the figures).
    """

    samples: int = 0
    arc_time_s: float = 0.0
    arc_starts: int = 0
    arc_breaks: int = 0
    judged_samples: int = 0
    judged_s: float = 0.0
    current_mean_a: float = 0.0
    current_min_a: float = 0.0
    current_max_a: float = 0.0
    voltage_mean_v: float = 0.0
    voltage_min_v: float = 0.0
    voltage_max_v: float = 0.0
    outside_samples: int = 0
    outside_s: float = 0.0
    nan_samples: int = 0

    @property
    def flagged(self) -> bool:
        """True when the weld spent any time outside its current or voltage window."""
        return self.outside_s > 0.0

    def as_dict(self) -> dict[str, Any]:
        """The weld data as a weld's result and recording carry it (:data:`WELD_DATA_SCHEMA`)."""
        out: dict[str, Any] = {k: round(v, _DECIMALS) if isinstance(v, float) else v for k, v in asdict(self).items()}
        out["flagged"] = self.flagged
        return out


# The JSON shape of WeldData.as_dict: every key always there.
_WELD_DATA_PROPERTIES = {
    "samples": integer("Every sample of the weld.", lo=0),
    "arc_time_s": number("The time with the arc on.", lo=0.0),
    "arc_starts": integer("Arc starts (off to on; data that starts with the arc on starts with one).", lo=0),
    "arc_breaks": integer("Arc ends before the cell switched the arc off itself (all of them when it never did).", lo=0),
    "judged_samples": integer("Arc-on samples past each start's grace with a current and a voltage.", lo=0),
    "judged_s": number("Their time.", lo=0.0),
    "current_mean_a": number("Mean current over the judged samples (0 when none)."),
    "current_min_a": number("Least current over the judged samples (0 when none)."),
    "current_max_a": number("Greatest current over the judged samples (0 when none)."),
    "voltage_mean_v": number("Mean voltage over the judged samples (0 when none)."),
    "voltage_min_v": number("Least voltage over the judged samples (0 when none)."),
    "voltage_max_v": number("Greatest voltage over the judged samples (0 when none)."),
    "outside_samples": integer("Judged samples with the current or the voltage outside its window.", lo=0),
    "outside_s": number("Their time.", lo=0.0),
    "nan_samples": integer("Arc-on samples past the grace whose current or voltage was not a number (left out).", lo=0),
    "flagged": boolean("The weld spent time outside its current or voltage window."),
}
WELD_DATA_SCHEMA = obj(
    "The weld data of one weld: arc time, starts and breaks, the current and voltage past each start's grace, and "
    "the time outside the procedure's windows.",
    _WELD_DATA_PROPERTIES,
    _WELD_DATA_PROPERTIES,
)


def summarize(
    t_s: ArrayLike,
    arc_on: ArrayLike,
    current_a: ArrayLike,
    voltage_v: ArrayLike,
    current_window_a: tuple[float, float],
    voltage_window_v: tuple[float, float],
    grace_s: float,
    ended_at_s: float | None = None,
) -> WeldData:
    """The weld data of one weld from its per-cycle samples (the module docstring defines each figure).

    Parameters
    ----------
    t_s : (n,) array
        Sample times, s, finite and non-decreasing (any origin: the loop's monotonic clock).
    arc_on : (n,) array of bool (or 0/1)
        The source's arc-stable signal as the cell read it.
    current_a, voltage_v : (n,) arrays
        The measured current (A) and arc voltage (V); NaN where no reading came, never infinite.
    current_window_a, voltage_window_v : (lo, hi)
        The procedure's windows, A and V, lo below hi.
    grace_s : float
        After each arc start the windows are not applied for this long, s (>= 0).
    ended_at_s : float or None
        When the cell itself switched the arc off (the seam's end), on ``t_s``'s clock; None when it never did.

    Raises
    ------
    InputError
        An array that is not 1-D or not of ``t_s``'s length, a time that is not finite or goes back, an arc
        signal that is not 0/1, an infinite current or voltage, a window that is not (lo, hi) with lo < hi, or a
        grace or an end time that is not a finite number (the grace >= 0).
    """
    t, on, current, voltage = _check_samples(t_s, arc_on, current_a, voltage_v)
    i_lo, i_hi = _check_window(current_window_a, "current_window_a")
    v_lo, v_hi = _check_window(voltage_window_v, "voltage_window_v")
    if not _is_finite_number(grace_s) or grace_s < 0.0:
        raise InputError(f"grace_s: expected a finite number >= 0 s, got {grace_s!r}")
    if ended_at_s is not None and not _is_finite_number(ended_at_s):
        raise InputError(f"ended_at_s: expected a finite time in s or None, got {ended_at_s!r}")
    n = t.size
    if n == 0:
        return WeldData()

    # Each sample's time: to the next sample, the last one the spacing before it.
    gaps = np.diff(t)
    dt = np.append(gaps, gaps[-1] if n > 1 else 0.0)
    before = np.concatenate(([False], on[:-1]))
    starts = on & ~before
    ends = ~on & before
    end_times = t[ends]
    breaks = end_times.size if ended_at_s is None else int(np.count_nonzero(end_times < ended_at_s))

    base = WeldData(
        samples=n,
        arc_time_s=float(dt[on].sum()),
        arc_starts=int(np.count_nonzero(starts)),
        arc_breaks=int(breaks),
    )
    if not on.any():
        return base
    # Each sample's arc start time: the start times indexed by the count of starts up to it (used where the arc is on).
    started_at = t[starts][np.maximum(np.cumsum(starts) - 1, 0)]
    settled = on & (t - started_at >= grace_s - _GRACE_TOL)
    readable = np.isfinite(current) & np.isfinite(voltage)
    judged = settled & readable
    nan_samples = int(np.count_nonzero(settled & ~readable))
    if not judged.any():
        return replace(base, nan_samples=nan_samples)
    c, v, dt_judged = current[judged], voltage[judged], dt[judged]
    outside = (c < i_lo) | (c > i_hi) | (v < v_lo) | (v > v_hi)
    return replace(
        base,
        judged_samples=int(c.size),
        judged_s=float(dt_judged.sum()),
        current_mean_a=float(c.mean()),
        current_min_a=float(c.min()),
        current_max_a=float(c.max()),
        voltage_mean_v=float(v.mean()),
        voltage_min_v=float(v.min()),
        voltage_max_v=float(v.max()),
        outside_samples=int(np.count_nonzero(outside)),
        outside_s=float(dt_judged[outside].sum()),
        nan_samples=nan_samples,
    )


def _check_samples(
    t_s: ArrayLike, arc_on: ArrayLike, current_a: ArrayLike, voltage_v: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """The four sample arrays as float, bool, float, float, checked: 1-D, one length, times finite and in order."""
    t = _as_1d(t_s, "t_s")
    n = t.size
    raw_on = np.asarray(arc_on)
    current = _as_1d(current_a, "current_a")
    voltage = _as_1d(voltage_v, "voltage_v")
    for name, arr in (("arc_on", raw_on), ("current_a", current), ("voltage_v", voltage)):
        if arr.shape != (n,):
            raise InputError(f"{name}: expected shape ({n},) like t_s, got {arr.shape}")
    if raw_on.dtype != np.bool_:
        if not np.issubdtype(raw_on.dtype, np.number):
            raise InputError(f"arc_on: expected booleans (or 0 and 1), got dtype {raw_on.dtype}")
        other = raw_on[~np.isin(raw_on, (0, 1))]
        if other.size:
            raise InputError(f"arc_on: expected booleans (or 0 and 1), got {other.size} other values such as {other[0].item()!r}")
    if not np.isfinite(t).all():
        raise InputError(f"t_s: expected finite times, got {int(np.count_nonzero(~np.isfinite(t)))} that are not")
    back = np.flatnonzero(np.diff(t) < 0.0)
    if back.size:
        i = int(back[0])
        raise InputError(f"t_s: expected non-decreasing times, got t[{i + 1}] = {t[i + 1]} after t[{i}] = {t[i]}")
    for name, arr in (("current_a", current), ("voltage_v", voltage)):
        if np.isinf(arr).any():
            raise InputError(f"{name}: expected numbers (NaN where no reading came), got {int(np.count_nonzero(np.isinf(arr)))} infinite")
    return t, raw_on.astype(bool), current, voltage


def _as_1d(values: ArrayLike, name: str) -> NDArray[np.float64]:
    """``values`` as a 1-D float array; InputError naming ``name`` for another shape or a non-number."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected an array of numbers: {exc}") from exc
    if arr.ndim != 1:
        raise InputError(f"{name}: expected a 1-D array, got shape {arr.shape}")
    return arr


def _check_window(window: tuple[float, float], name: str) -> tuple[float, float]:
    """A (lo, hi) window of finite numbers with lo below hi."""
    try:
        lo, hi = (float(x) for x in window)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected (lo, hi), got {window!r}") from exc
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise InputError(f"{name}: expected finite (lo, hi) with lo below hi, got {window!r}")
    return lo, hi


def _is_finite_number(value: object) -> bool:
    """``value`` is a finite int or float (a bool is not a number here)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
