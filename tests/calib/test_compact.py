"""Compact organized clouds: exact where the detector reads, within the stated precision elsewhere."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from celld.calib.compact import DEPTH_UNIT, Pinhole, decode, encode, fit_pinhole
from celld.errors import InputError

# A small pinhole camera (OpenCV convention), pixels.
K = Pinhole(fx=300.0, fy=310.0, cx=79.5, cy=59.0)
SHAPE = (120, 160)


def scene(rng: np.random.Generator, k1: float = 0.0) -> np.ndarray:
    """(H, W, 3) float32: a tilted plane 0.5-1.1 m away with noise and holes, seen by K (radial distortion k1)."""
    H, W = SHAPE
    u, v = K.rays(SHAPE)
    u, v = np.meshgrid(u, v)
    r2 = u**2 + v**2
    u, v = u * (1 + k1 * r2), v * (1 + k1 * r2)  # where the points really are, for a distorted lens
    z = 0.5 + 0.6 * (np.arange(W) / W)[None, :] + 0.05 * (np.arange(H) / H)[:, None] + rng.normal(0, 1e-4, (H, W))
    P = np.stack([z * u, z * v, z], axis=-1).astype(np.float32)
    P[rng.random((H, W)) < 0.05] = np.nan  # no returns
    P[40:50, 60:90] = np.nan  # a shadow
    return P


def test_pinhole_fitted_from_the_cloud_itself(rng: np.random.Generator) -> None:
    fit = fit_pinhole(scene(rng))
    assert fit is not None
    np.testing.assert_allclose([fit.fx, fit.fy, fit.cx, fit.cy], [K.fx, K.fy, K.cx, K.cy], rtol=1e-5, atol=1e-3)
    assert fit_pinhole(np.full((4, 4, 3), np.nan, dtype=np.float32)) is None  # nothing to fit


def test_exact_in_the_window_and_on_the_grid_within_precision_elsewhere(rng: np.random.Generator) -> None:
    P = scene(rng)
    c = encode(P, (30, 70, 50, 100), (5, 120, 0, 160), grid_stride=7)
    assert c.xy is None and c.pinhole is not None  # x, y rebuilt from the depth
    assert c.depth.q.unit == DEPTH_UNIT and c.precision == DEPTH_UNIT / 2
    Q = decode(c)
    assert Q.shape == P.shape and Q.dtype == np.float64
    # Missing returns stay missing, nothing else goes missing.
    np.testing.assert_array_equal(np.isnan(Q).any(axis=2), np.isnan(P).any(axis=2))
    # Bit for bit (float32) where the detector reads.
    np.testing.assert_array_equal(Q[30:70, 50:100], P[30:70, 50:100])
    np.testing.assert_array_equal(Q[5::7, ::7], P[5::7, ::7])
    # Elsewhere within half a count, and the measured maximum is what was stated.
    err = np.abs(Q - P)[np.isfinite(P).all(axis=2)].max(axis=0)
    assert np.all(err <= c.precision * (1 + 1e-9))
    np.testing.assert_allclose(c.max_error, err, rtol=1e-12)
    assert err[2] > 0.4 * c.precision  # it is rounding, not exact
    assert c.pinhole_error is not None and c.pinhole_error < 1e-6  # float32 rounding only


def test_points_that_are_not_a_pinhole_of_their_depth_get_x_and_y_images(rng: np.random.Generator) -> None:
    P = scene(rng, k1=0.05)  # a lens distortion the scanner corrected: x/z is no longer linear in the column
    c = encode(P, (0, 10, 0, 10), (0, 120, 0, 160), grid_stride=16)
    assert c.pinhole_error is not None and c.pinhole_error > c.depth.q.precision
    assert c.xy is not None and c.xy_residual  # what the fitted pinhole misses, not x and y themselves
    Q = decode(c)
    valid = np.isfinite(P).all(axis=2)
    assert np.abs(Q - P)[valid].max() <= c.precision * (1 + 1e-9)
    np.testing.assert_array_equal(np.isnan(Q).any(axis=2), ~valid)
    # The residual spans a few hundred counts where x itself spans thousands.
    span = [int(np.ptp(image.counts[image.counts > 0])) for image in c.xy]
    assert max(span) < 0.2 * np.nanmax(np.abs(P[..., :2])) / c.depth.q.unit, span
    # A residual without the pinhole it completes is refused.
    with pytest.raises(InputError, match="residual"):
        decode(replace(c, pinhole=None))


def test_the_unit_grows_to_what_16_bits_can_span(rng: np.random.Generator) -> None:
    P = scene(rng)
    c = encode(P, (0, 10, 0, 10), (0, 120, 0, 160), grid_stride=16, depth_unit=1e-5)  # 65535 x 10 um = 0.66 m < 1.15 m
    assert c.depth.q.unit == 2e-5
    assert np.abs(decode(c) - P)[np.isfinite(P).all(axis=2)].max() <= 1e-5 * (1 + 1e-9)


def test_what_cannot_be_encoded_is_refused(rng: np.random.Generator) -> None:
    P = scene(rng)
    with pytest.raises(InputError, match="window_px"):
        encode(P, (0, 200, 0, 10), (0, 120, 0, 160), grid_stride=4)
    with pytest.raises(InputError, match="4 integers"):
        encode(P, (0, 10.5, 0, 10), (0, 120, 0, 160), grid_stride=4)
    with pytest.raises(InputError, match="grid_stride"):
        encode(P, (0, 10, 0, 10), (0, 120, 0, 160), grid_stride=0)
    with pytest.raises(InputError, match="organized"):
        encode(P.reshape(-1, 3), (0, 10, 0, 10), (0, 120, 0, 160), grid_stride=4)
    P[5, 5, 2] = -0.1
    with pytest.raises(InputError, match="behind the camera"):
        encode(P, (0, 10, 0, 10), (0, 120, 0, 160), grid_stride=4)
