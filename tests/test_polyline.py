"""Polylines: nearest points (the servo's), projection, offsets, thinning, sliding, resampling."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import polyline
from celld.seam.workpiece import curved_groove


def test_nearest_point_on_a_polyline_within_a_window() -> None:
    P = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    assert polyline.nearest(P, np.array([0.4, 0.3]), 0, 3) == (0, pytest.approx(0.4), pytest.approx(0.3))
    i, u, dist = polyline.nearest(P, np.array([1.2, 0.7]))
    assert (i, u, dist) == (1, pytest.approx(0.7), pytest.approx(0.2))
    # The window keeps the search local (Algorithm 2, lines 10 and 22).
    assert polyline.nearest(P, np.array([1.2, 0.7]), 0, 2)[0] == 0
    assert polyline.is_inside(P, 1, 0.7) and not polyline.is_inside(P, 1, 1.0) and not polyline.is_inside(P, 0, 0.0)


def test_projection_onto_a_polyline_matches_brute_force() -> None:
    seam = curved_groove(radius=0.15, segments=60).seam
    rng = np.random.default_rng(0)
    Q = rng.uniform([-0.08, -0.01, -0.005], [0.08, 0.05, 0.01], (300, 3))
    proj = polyline.project(Q, seam)
    # Brute force: the foot of the perpendicular on every segment, the nearest kept.
    A, B = seam[:-1], seam[1:]
    AB = B - A
    u = np.clip(np.einsum("nsk,sk->ns", Q[:, None, :] - A[None], AB) / np.einsum("sk,sk->s", AB, AB), 0.0, 1.0)
    feet = A[None] + u[..., None] * AB[None]
    best = np.argmin(np.linalg.norm(Q[:, None, :] - feet, axis=2), axis=1)
    np.testing.assert_allclose(proj.point, feet[np.arange(len(Q)), best], atol=1e-9)
    arc0 = polyline.arc_length(seam)
    np.testing.assert_allclose(proj.arc, arc0[best] + u[np.arange(len(Q)), best] * np.linalg.norm(AB[best], axis=1), atol=1e-9)
    np.testing.assert_allclose(polyline.distance(Q, seam), np.linalg.norm(Q - proj.point, axis=1), atol=1e-12)


def test_signed_offsets_are_positive_left_of_travel_and_ends_are_flagged() -> None:
    # A quarter circle, travelled anticlockwise: left of travel is towards the centre.
    a = np.linspace(0.0, math.pi / 2, 500)
    P = np.column_stack([0.1 * np.cos(a), 0.1 * np.sin(a)])
    mid = np.array([math.cos(0.7), math.sin(0.7)])
    Q = np.array([0.099 * mid, 0.102 * mid, [0.2, -0.05]])
    d, inside = polyline.signed_offset(Q, P, step=1e-5)
    np.testing.assert_allclose(d[:2], [0.001, -0.002], atol=1e-6)  # the chords sag 0.12 um from the arc
    assert inside.tolist() == [True, True, False]


def test_thin_keeps_points_a_step_apart_and_both_ends() -> None:
    P = np.column_stack([np.linspace(0, 0.01, 101), np.zeros(101), np.zeros(101)])
    T = polyline.thin(P, 0.0005)
    gaps = np.linalg.norm(np.diff(T, axis=0), axis=1)
    assert np.allclose(T[[0, -1]], P[[0, -1]]) and 19 <= len(T) <= 21
    assert np.all(gaps[:-1] >= 0.0005 - 1e-12) and np.all(gaps <= 0.0006 + 1e-12)


def test_slide_moves_points_along_and_past_the_ends() -> None:
    P = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    np.testing.assert_allclose(polyline.slide(P, 0.5), [[0.5, 0.0], [1.0, 0.5], [1.0, 1.5]], atol=1e-12)
    np.testing.assert_allclose(polyline.slide(P, -0.5)[0], [-0.5, 0.0], atol=1e-12)


def test_resample_keeps_the_ends_at_equal_steps() -> None:
    P = np.array([[0.0, 0.0, 0.0], [0.03, 0.0, 0.0], [0.03, 0.04, 0.0]])
    R, step = polyline.resample(P, 0.0011)
    assert step == pytest.approx(0.07 / 64) and len(R) == 65
    np.testing.assert_allclose(R[[0, -1]], P[[0, -1]])
    # Equal steps along the original path (a chord across the corner is shorter).
    np.testing.assert_allclose(polyline.project(R, P).arc, np.arange(65) * step, atol=1e-12)
