"""Compact organized clouds: a 16-bit depth image, the projection that rebuilds x and y, exact pixels. Pure.

An organized cloud of a 2064 x 1544 scanner is 38 MB as float32 x y z. The
flange detector reads little of it: its coarse pass a grid of every s-th
pixel (about 12 000 of them, :func:`~celld.calib.detect.coarse_grid`), its
fine pass the full-resolution pixels around the flange. :func:`encode`
splits a cloud accordingly:

- the whole image as a depth image: z along the optical axis in counts of
  ``unit`` metres, uint16, 0 for no return (a pixel with any non-finite
  coordinate);
- x and y rebuilt from the depth by the pinhole projection of the pixel grid,
  ``x = z (col - cx) / fx``, ``y = z (row - cy) / fy`` (OpenCV convention),
  with fx, fy, cx, cy fitted to the cloud itself by least squares
  (:func:`fit_pinhole`); where that rebuild misses the stated precision (a
  scanner whose points are not a pinhole projection of its depth, after its
  own distortion model, say), x and y are stored as 16-bit images too, each
  with its unit and offset: of what the pinhole misses (the residual, smooth
  and a few counts wide, which a PNG holds in a fraction of the bytes) when
  a pinhole could be fitted, of x and y themselves when not;
- the pixels the detector reads, kept as they came, float32, bit for bit: a
  window of the image (around the flange) and a grid
  ``[row0:row1:s, col0:col1:s]``.

The stated precision is half a count (rounding) in every coordinate; the
encoder checks the rebuild against it and records the largest error it
measured elsewhere. :func:`decode` returns the organized cloud: equal to the
float32 original in the window and on the grid, within the precision
elsewhere, NaN where the original had no return. The detector (with the
parameters the grid was taken for, and no crop box) therefore finds in it
what it found in the original, to the bit.

Files (PNG, PLY, the JSON that ties them) are written by
:mod:`celld.calib.dataset`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from celld.errors import InputError

# Default depth unit, m per count: 0.1 mm, so +- 0.05 mm, below the depth noise
# of a PhoXi M (simulated: 0.1 mm at 0.65 m, 0.24 mm at 1 m). A 16-bit image
# then reaches 6.5 m; each halving of the unit costs about 0.4 MB more per
# PhoXi M image (1.8 MB at 0.1 mm).
DEPTH_UNIT = 1e-4
# Largest count of a 16-bit image; 0 means no return.
MAX_COUNT = 65535
# Units are picked from 1, 2, 5 x 10^k when the requested one cannot span the values.
_STEPS = (1.0, 2.0, 5.0)
# Fewest valid pixels to fit the pinhole on, and the grid it is fitted on
# (every 4th row and column: 200 000 pixels of a PhoXi M, plenty for two
# lines; the rebuild is then checked on every pixel).
_MIN_FIT_PIXELS = 16
_FIT_STEP = 4


@dataclass(frozen=True)
class Pinhole:
    """Pinhole intrinsics of an organized cloud's pixel grid, pixels (OpenCV: x right, y down)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def rays(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """``(col - cx) / fx`` per column (W,) and ``(row - cy) / fy`` per row (H,): x / z and y / z."""
        H, W = shape
        return (np.arange(W) - self.cx) / self.fx, (np.arange(H) - self.cy) / self.fy


@dataclass(frozen=True)
class Quantizer:
    """``value = offset + count * unit`` for counts 1..65535; count 0 is no return. Metres."""

    unit: float
    offset: float

    @property
    def precision(self) -> float:
        """Largest rounding error, m."""
        return self.unit / 2.0

    def encode(self, values: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """(H, W) uint16 counts of ``values``; 0 where not ``valid``."""
        with np.errstate(invalid="ignore"):
            counts = np.rint((values - self.offset) / self.unit)
        counts = np.where(valid, counts, 0.0)
        if counts.min() < 0 or counts.max() > MAX_COUNT or np.any(valid & (counts < 1)):
            raise InputError(f"values out of the range of unit {self.unit} m from offset {self.offset} m")
        return counts.astype(np.uint16)

    def decode(self, counts: np.ndarray) -> np.ndarray:
        """(H, W) float64 values, NaN where the count is 0."""
        values = self.offset + counts.astype(np.float64) * self.unit
        values[counts == 0] = np.nan
        return values


@dataclass(frozen=True, eq=False)
class Image16:
    """One coordinate as a 16-bit image: (H, W) uint16 ``counts`` of ``q``, 0 for no return."""

    counts: np.ndarray
    q: Quantizer

    def values(self) -> np.ndarray:
        """(H, W) float64, metres, NaN for no return."""
        return self.q.decode(self.counts)


@dataclass(frozen=True, eq=False)
class CompactCloud:
    """An organized cloud as a depth image, a rebuild of x and y, and an exact window.

    Attributes
    ----------
    depth : Image16
        z (offset 0: an ordinary depth image).
    pinhole : Pinhole or None
        The intrinsics fitted to the cloud (None when it could not be fitted).
    xy : tuple of two Image16, or None
        x and y, when the pinhole rebuild misses the precision; None when x
        and y are rebuilt from the depth through ``pinhole``.
    xy_residual : bool
        ``xy`` holds what the pinhole rebuild from the stored depth misses
        (x = the pinhole's x + the image's value), not x and y themselves.
    pinhole_error : float or None
        Largest distance in x or y of the pinhole rebuild from the original
        with the depth unrounded, m (None without a pinhole).
    window_px : tuple of 4 int
        ``(row0, row1, col0, col1)`` of the window kept exactly.
    window : (row1 - row0, col1 - col0, 3) float32
        The original points of the window, NaN for no return.
    grid_px : tuple of 4 int
        ``(row0, row1, col0, col1)`` and ...
    grid_stride : int
        ... stride of the grid ``[row0:row1:stride, col0:col1:stride]`` kept exactly ...
    grid : (h, w, 3) float32
        ... here, NaN for no return.
    max_error : (3,) float64
        Largest error in x, y, z off the window and the grid, measured, m.
    """

    depth: Image16
    pinhole: Pinhole | None
    xy: tuple[Image16, Image16] | None
    pinhole_error: float | None
    window_px: tuple[int, int, int, int]
    window: np.ndarray
    grid_px: tuple[int, int, int, int]
    grid_stride: int
    grid: np.ndarray
    max_error: np.ndarray
    xy_residual: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.depth.counts.shape[0]), int(self.depth.counts.shape[1])

    @property
    def precision(self) -> float:
        """Stated bound of the error of any coordinate off the window and the grid, m."""
        return max(image.q.precision for image in (self.depth, *(self.xy or ())))

    @property
    def valid_count(self) -> int:
        return int(np.count_nonzero(self.depth.counts))


def _unit_for(span: float, unit: float) -> float:
    """``unit``, or the smallest 1-2-5 step above it that spans ``span`` (count 0 and two for the offset kept free)."""
    need = span / (MAX_COUNT - 3)
    if need <= unit:
        return unit
    k = math.floor(math.log10(need))
    return min(float(f"{s:g}e{e}") for e in (k, k + 1) for s in _STEPS if float(f"{s:g}e{e}") >= need)


def check_window(window_px: ArrayLike, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Return ``(row0, row1, col0, col1)`` as ints, or raise InputError if it is not a non-empty window of ``shape``."""
    values = np.asarray(window_px).tolist() if np.ndim(window_px) == 1 else None
    if values is None or len(values) != 4 or not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        raise InputError(f"window_px: expected 4 integers (row0, row1, col0, col1), got {window_px!r}")
    r0, r1, c0, c1 = values
    H, W = shape
    if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
        raise InputError(f"window_px: expected 0 <= row0 < row1 <= {H}, 0 <= col0 < col1 <= {W}, got {(r0, r1, c0, c1)}")
    return r0, r1, c0, c1


def fit_pinhole(P: np.ndarray) -> Pinhole | None:
    """Least-squares pinhole intrinsics of an organized cloud: ``col = fx x/z + cx``, ``row = fy y/z + cy``.

    Fitted on every 4th row and column of the cloud.

    Parameters
    ----------
    P : (H, W, 3) array
        Camera frame, NaN for no return.

    Returns
    -------
    Pinhole or None
        None when fewer than 16 pixels have a return in front of the camera,
        they span a single row or column, or a fitted focal length is not
        positive.
    """
    S = P[::_FIT_STEP, ::_FIT_STEP]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(S[..., 0]) & np.isfinite(S[..., 1]) & (S[..., 2] > 0)
    rows, cols = (i * _FIT_STEP for i in np.nonzero(valid))
    if len(rows) < _MIN_FIT_PIXELS:
        return None
    Q = S[valid].astype(np.float64)
    out = []
    for pix, ratio in ((cols, Q[:, 0] / Q[:, 2]), (rows, Q[:, 1] / Q[:, 2])):
        # Straight-line least squares pix = f ratio + c, centred for precision.
        r = ratio - ratio.mean()
        p = pix - pix.mean()
        var = float(r @ r)
        if not var > 0.0:
            return None
        f = float(r @ p) / var
        if not (math.isfinite(f) and f > 0.0):
            return None
        out.append((f, float(pix.mean() - f * ratio.mean())))
    (fx, cx), (fy, cy) = out
    return Pinhole(fx, fy, cx, cy)


def _pinhole_xy(z: np.ndarray, pinhole: Pinhole) -> tuple[np.ndarray, np.ndarray]:
    u, v = pinhole.rays((z.shape[0], z.shape[1]))
    return z * u[None, :], z * v[:, None]


def _max_abs(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    with np.errstate(invalid="ignore"):
        return float(np.max(np.abs(a - b), where=mask, initial=0.0))


def encode(P_cam: ArrayLike, window_px: ArrayLike, grid_px: ArrayLike, grid_stride: int, depth_unit: float = DEPTH_UNIT) -> CompactCloud:
    """Split an organized cloud into a depth image, the rebuild of x and y, and exact pixels.

    Parameters
    ----------
    P_cam : (H, W, 3) array
        Camera frame, metres; a pixel with a non-finite coordinate has no
        return. Kept as float32 (the precision of a scanner's cloud and of the
        float PLY files).
    window_px : (row0, row1, col0, col1)
        The window kept exactly.
    grid_px : (row0, row1, col0, col1)
    grid_stride : int
        The grid ``[row0:row1:grid_stride, col0:col1:grid_stride]`` is kept exactly too.
    depth_unit : float
        Metres per count of the depth image; a coarser 1-2-5 step is taken if
        the deepest point would not fit in 16 bits.

    Raises
    ------
    InputError
        Not an (H, W, 3) cloud, a bad window, stride or unit, or a return at
        or behind the camera (z <= 0 has no depth image).
    """
    P = np.asarray(P_cam)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[0] < 1 or P.shape[1] < 1:
        raise InputError(f"P_cam: expected an organized (H, W, 3) cloud, got shape {P.shape}")
    if not (math.isfinite(depth_unit) and depth_unit > 0):
        raise InputError(f"depth_unit: expected a positive number of metres, got {depth_unit!r}")
    if isinstance(grid_stride, bool) or not isinstance(grid_stride, (int, np.integer)) or grid_stride < 1:
        raise InputError(f"grid_stride: expected a positive integer, got {grid_stride!r}")
    s = int(grid_stride)
    P = P.astype(np.float32)
    shape = (P.shape[0], P.shape[1])
    r0, r1, c0, c1 = check_window(window_px, shape)
    g0, g1, h0, h1 = check_window(grid_px, shape)
    # Per channel: a reduction over the last axis of 3 is several times slower.
    valid = np.isfinite(P[..., 0]) & np.isfinite(P[..., 1]) & np.isfinite(P[..., 2])
    P[~valid] = np.nan
    x, y, z = (P[..., i].astype(np.float64) for i in range(3))
    if np.any(z[valid] <= 0):
        raise InputError(f"P_cam: {int(np.count_nonzero(z[valid] <= 0))} returns at or behind the camera (z <= 0)")
    z_max = float(z[valid].max()) if valid.any() else 0.0
    depth_q = Quantizer(_unit_for(z_max, depth_unit), 0.0)
    depth = Image16(depth_q.encode(z, valid), depth_q)
    z_q = depth.values()

    outside = valid.copy()
    outside[r0:r1, c0:c1] = False
    outside[g0:g1:s, h0:h1:s] = False
    pinhole = fit_pinhole(P)
    pinhole_error = None
    xy: tuple[Image16, Image16] | None = None
    use_pinhole = False
    if pinhole is not None:
        x_exact, y_exact = _pinhole_xy(z, pinhole)
        pinhole_error = max(_max_abs(x_exact, x, valid), _max_abs(y_exact, y, valid))
        x_rec, y_rec = _pinhole_xy(z_q, pinhole)
        use_pinhole = max(_max_abs(x_rec, x, outside), _max_abs(y_rec, y, outside)) <= depth_q.precision
    if not use_pinhole:
        images = []
        if pinhole is not None:
            # What the pinhole misses of the rebuild from the stored depth: rounded to a count, the rebuild is
            # within half a count of x and y as with whole images, in a few counts' range.
            x_rec, y_rec = _pinhole_xy(z_q, pinhole)
            with np.errstate(invalid="ignore"):
                planes = (x - x_rec, y - y_rec)
        else:
            planes = (x, y)
        for values in planes:
            lo, hi = (float(values[valid].min()), float(values[valid].max())) if valid.any() else (0.0, 0.0)
            unit = _unit_for(hi - lo, depth_q.unit)
            q = Quantizer(unit, (math.floor(lo / unit) - 1) * unit)
            images.append(Image16(q.encode(values, valid), q))
        xy = (images[0], images[1])
    compact = CompactCloud(
        depth=depth,
        pinhole=pinhole,
        xy=xy,
        pinhole_error=pinhole_error,
        window_px=(r0, r1, c0, c1),
        window=P[r0:r1, c0:c1].copy(),
        grid_px=(g0, g1, h0, h1),
        grid_stride=s,
        grid=P[g0:g1:s, h0:h1:s].copy(),
        max_error=np.zeros(3),
        xy_residual=xy is not None and pinhole is not None,
    )
    rebuilt = decode(compact)
    max_error = np.array([_max_abs(rebuilt[..., i], original, outside) for i, original in enumerate((x, y, z))])
    return replace(compact, max_error=max_error)


def decode(compact: CompactCloud) -> np.ndarray:
    """The organized cloud (H, W, 3) float64, metres, NaN for no return.

    In the window and on the grid it is the float32 original exactly;
    elsewhere it is within ``compact.precision`` of it.
    """
    z = compact.depth.values()
    if compact.xy is not None and compact.xy_residual:
        if compact.pinhole is None:
            raise InputError("compact cloud: x, y residual images without the pinhole they complete")
        x, y = _pinhole_xy(z, compact.pinhole)
        x += compact.xy[0].values()
        y += compact.xy[1].values()
    elif compact.xy is not None:
        x, y = compact.xy[0].values(), compact.xy[1].values()
    elif compact.pinhole is not None:
        x, y = _pinhole_xy(z, compact.pinhole)
    else:
        raise InputError("compact cloud: neither x, y images nor a pinhole to rebuild them")
    P = np.stack([x, y, z], axis=-1)
    g0, g1, h0, h1 = compact.grid_px
    s = compact.grid_stride
    P[g0:g1:s, h0:h1:s] = compact.grid
    r0, r1, c0, c1 = compact.window_px
    P[r0:r1, c0:c1] = compact.window
    return P
