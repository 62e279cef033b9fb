"""3D circle maths: circles through triples, distances, RANSAC with the radius check, refinement."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import se3
from celld.calib.circle import (
    angular_coverage,
    circle_distances,
    circles_through,
    fit_plane,
    ransac_circle,
    refine_circle,
)
from celld.errors import InputError

# A tilted plane in a camera-like frame: circles live in its xy plane.
T_CAM_CIRCLE = se3.from_xyz_rpy([0.05, -0.02, 0.55], [2.9, 0.25, 0.4])


def circle_points(radius: float, n: int, rng: np.random.Generator, arc: float = 2 * math.pi, noise: float = 0.0) -> np.ndarray:
    theta = rng.uniform(0.0, arc, n)
    P = np.column_stack([radius * np.cos(theta), radius * np.sin(theta), np.zeros(n)])
    return se3.apply(T_CAM_CIRCLE, P + rng.normal(0.0, noise, P.shape))


def test_circle_through_three_points_recovers_centre_normal_radius(rng: np.random.Generator) -> None:
    P = circle_points(0.031, 3, rng)
    c, n, r, ok = circles_through(P[:1], P[1:2], P[2:3])
    assert ok[0]
    np.testing.assert_allclose(c[0], T_CAM_CIRCLE[:3, 3], atol=1e-12)
    assert r[0] == pytest.approx(0.031, abs=1e-12)
    assert abs(n[0] @ T_CAM_CIRCLE[:3, 2]) == pytest.approx(1.0, abs=1e-12)


def test_collinear_and_repeated_triples_define_no_circle() -> None:
    A = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    B = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    C = np.array([[2.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    _, _, _, ok = circles_through(A, B, C)
    assert not ok.any()


def test_distance_to_a_circle_combines_height_and_radial_offset() -> None:
    P = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [0.03, 0.0, 0.004], [0.0, 0.03, 0.0]])
    d = circle_distances(P, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0.03]))[0]
    np.testing.assert_allclose(d, [0.03, 0.01, 0.004, 0.0], atol=1e-12)


def test_ransac_picks_the_circle_of_the_expected_radius_among_others(rng: np.random.Generator) -> None:
    # A flange-like rim: the 31 mm edge, the 15.75 mm bore edge, and clutter.
    rim = circle_points(0.031, 600, rng, noise=5e-5)
    bore = circle_points(0.01575, 300, rng, noise=5e-5)
    clutter = T_CAM_CIRCLE[:3, 3] + rng.uniform(-0.04, 0.04, (300, 3))
    P = np.vstack([bore, clutter, rim])
    fit = ransac_circle(P, 0.031, 0.001, 0.0003, 10_000, np.random.default_rng(1))
    assert fit is not None
    assert fit.radius == pytest.approx(0.031, abs=2e-4)
    np.testing.assert_allclose(fit.centre, T_CAM_CIRCLE[:3, 3], atol=2e-4)
    assert fit.inliers[-600:].mean() > 0.95 and fit.inliers[:300].sum() == 0
    # Adaptive stopping: nowhere near k_max with half the points on the rim.
    assert fit.samples < 2000


def test_ransac_without_a_circle_in_the_radius_window_returns_none(rng: np.random.Generator) -> None:
    P = circle_points(0.031, 500, rng)
    assert ransac_circle(P, 0.0495, 0.001, 0.0003, 5000, np.random.default_rng(2)) is None


def test_ransac_normal_check_refuses_circles_off_the_given_plane(rng: np.random.Generator) -> None:
    P = circle_points(0.031, 300, rng)
    wrong = T_CAM_CIRCLE[:3, 0]  # in the circle's plane: 90 degrees off its normal
    assert ransac_circle(P, 0.031, 0.001, 0.0003, 2000, np.random.default_rng(3), wrong, math.radians(5)) is None
    right = ransac_circle(P, 0.031, 0.001, 0.0003, 2000, np.random.default_rng(3), T_CAM_CIRCLE[:3, 2], math.radians(5))
    assert right is not None


def test_ransac_is_deterministic_per_seed(rng: np.random.Generator) -> None:
    P = np.vstack([circle_points(0.031, 200, rng, noise=1e-4), T_CAM_CIRCLE[:3, 3] + rng.uniform(-0.04, 0.04, (200, 3))])
    a = ransac_circle(P, 0.031, 0.001, 0.0003, 3000, np.random.default_rng(7))
    b = ransac_circle(P, 0.031, 0.001, 0.0003, 3000, np.random.default_rng(7))
    assert a is not None and b is not None
    np.testing.assert_array_equal(a.centre, b.centre)


def test_least_squares_refinement_beats_the_ransac_sample(rng: np.random.Generator) -> None:
    noise = 1e-4
    P = circle_points(0.031, 800, rng, noise=noise)
    fit = ransac_circle(P, 0.031, 0.001, 0.0004, 10_000, np.random.default_rng(4))
    assert fit is not None
    point, normal, _ = fit_plane(P)
    ref = refine_circle(P, fit, point, normal, 0.0004)
    err_ransac = np.linalg.norm(fit.centre - T_CAM_CIRCLE[:3, 3])
    err_ref = np.linalg.norm(ref.centre - T_CAM_CIRCLE[:3, 3])
    # The least-squares centre is good to about noise * sqrt(2 / n) = 5 um.
    assert err_ref < 2e-5 and err_ref <= err_ransac
    assert ref.radius == pytest.approx(0.031, abs=2e-5)
    assert ref.residual == pytest.approx(noise * math.sqrt(3), rel=0.2)


def test_fit_plane_recovers_a_known_plane(rng: np.random.Generator) -> None:
    P = se3.apply(T_CAM_CIRCLE, np.column_stack([rng.uniform(-0.03, 0.03, (500, 2)), rng.normal(0, 1e-5, 500)]))
    point, normal, rms = fit_plane(P)
    assert abs(normal @ T_CAM_CIRCLE[:3, 2]) == pytest.approx(1.0, abs=1e-6)
    assert abs((point - T_CAM_CIRCLE[:3, 3]) @ T_CAM_CIRCLE[:3, 2]) < 5e-6
    assert rms == pytest.approx(1e-5, rel=0.15)
    with pytest.raises(InputError, match="at least 3"):
        fit_plane(P[:2])


def test_angular_coverage_of_a_half_circle_is_one_half(rng: np.random.Generator) -> None:
    P = circle_points(0.031, 2000, rng, arc=math.pi)
    cov = angular_coverage(P, T_CAM_CIRCLE[:3, 3], T_CAM_CIRCLE[:3, 2], bins=36)
    assert cov == pytest.approx(0.5, abs=2 / 36)  # the two end sectors are partly covered
    assert angular_coverage(P[:0], T_CAM_CIRCLE[:3, 3], T_CAM_CIRCLE[:3, 2]) == 0.0


def test_ransac_refuses_malformed_points() -> None:
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        ransac_circle(np.zeros((5, 2)), 0.031, 0.001, 0.0003, 10, np.random.default_rng(0))
