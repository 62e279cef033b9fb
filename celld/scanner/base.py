"""What every scanner driver gives: the organized cloud, the Scanner protocol, health counters.

A scanner returns an :class:`OrganizedCloud`: (H, W, 3) float32 points in the
camera frame, metres, NaN where a pixel has no return. Drivers convert their
device's units and its "no return" marker (often (0, 0, 0)) at this boundary,
once; everything after it sees SI and NaN.

A driver is opened ready to capture and is used by one caller at a time (the
daemon calls :meth:`Scanner.capture` from a worker thread: a capture blocks
for hundreds of milliseconds). :class:`CaptureStats` keeps the counters that
:meth:`Scanner.health` reports.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from celld.errors import InputError


@dataclass(frozen=True, eq=False)
class OrganizedCloud:
    """One capture: an organized cloud in the camera frame.

    Attributes
    ----------
    points : numpy.ndarray
        (H, W, 3) float32, camera frame, metres; NaN where there is no return.
    stamp_ns : int
        ``time.monotonic_ns()`` of the capture.
    """

    points: np.ndarray
    stamp_ns: int

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the image grid."""
        return int(self.points.shape[0]), int(self.points.shape[1])

    def valid(self) -> np.ndarray:
        """The (n, 3) finite points, row-major pixel order."""
        P = self.points.reshape(-1, 3)
        return P[np.isfinite(P[:, 2])]

    def valid_count(self) -> int:
        """Number of pixels with a return."""
        return int(np.count_nonzero(np.isfinite(self.points[..., 2])))


def check_organized(points: ArrayLike, name: str = "cloud", scale: float = 1.0) -> np.ndarray:
    """Return ``points`` as an (H, W, 3) float32 organized cloud in metres, or raise InputError.

    Parameters
    ----------
    points : array_like
        (H, W, 3) coordinates in the camera frame, in the source's unit.
    name : str
        What the cloud is (a file name, a device), for the message.
    scale : float
        Metres per source unit (1e-3 for millimetres).

    Returns
    -------
    numpy.ndarray
        A new float32 array; a pixel whose three coordinates are exactly 0 (the
        "no return" of most scanners: a real return cannot sit at the optical
        centre) becomes NaN, as does any pixel with a NaN coordinate.

    Raises
    ------
    InputError
        Wrong shape, a non-numeric type, or infinite values.
    """
    arr = np.asarray(points)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise InputError(f"{name}: expected an organized (H, W, 3) cloud, got shape {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{name}: expected numeric coordinates, got dtype {arr.dtype}")
    P = arr.astype(np.float32) * np.float32(scale)
    if np.isinf(P).any():
        bad = int(np.count_nonzero(np.isinf(P).any(axis=2)))
        raise InputError(f"{name}: {bad} pixels hold infinite coordinates (no return must be NaN or 0, 0, 0)")
    no_return = np.isnan(P).any(axis=2) | np.all(P == 0.0, axis=2)
    P[no_return] = np.nan
    return P


@runtime_checkable
class Scanner(Protocol):
    """A 3D scanner fixed in the cell."""

    def capture(self) -> OrganizedCloud:
        """Take one capture; blocks until it is complete.

        Raises
        ------
        DeviceError
            The device failed, timed out, or a replay ran out of files.
        InputError
            The data that came back is malformed (replay files).
        """
        ...

    def info(self) -> dict[str, Any]:
        """Static facts: ``kind``, ``model``, ``device``, ``width_px``, ``height_px`` and driver details."""
        ...

    def health(self) -> dict[str, Any]:
        """Counters: ``ok``, ``captures``, ``failures``, ``last_capture_ns``, ``last_error``."""
        ...

    def close(self) -> None:
        """Release the device; safe to call twice."""
        ...


class CaptureStats:
    """Thread-safe capture counters behind :meth:`Scanner.health`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.captures = 0
        self.failures = 0
        self.last_capture_ns: int | None = None
        self.last_duration: float | None = None  # s
        self.last_error: str | None = None

    def success(self, stamp_ns: int, started_ns: int) -> None:
        with self._lock:
            self.captures += 1
            self.last_capture_ns = stamp_ns
            self.last_duration = (time.monotonic_ns() - started_ns) * 1e-9
            self.last_error = None

    def failure(self, exc: BaseException) -> None:
        with self._lock:
            self.failures += 1
            self.last_error = f"{type(exc).__name__}: {exc}"

    def as_dict(self, open_: bool) -> dict[str, Any]:
        with self._lock:
            return {
                "ok": open_ and self.last_error is None,
                "open": open_,
                "captures": self.captures,
                "failures": self.failures,
                "last_capture_ns": self.last_capture_ns,
                "last_duration": self.last_duration,
                "last_error": self.last_error,
            }
