"""Model-free groove measurement on sampled walls with known geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.config.seam import GrooveParams
from celld.seam import groove as gm
from celld.seam.groove import CONTRADICTS, OK, UNSEEN, fit_groove, lateral_offsets, smooth_offsets
from celld.seam.workpiece import LEFT_WALL, RIGHT_WALL, sample_surface, v_groove_butt

T, ALPHA, B, C = 0.010, math.radians(60.0), 0.002, 0.001
# Apex of the two bevel planes, below the root line: z = c - (b/2) / tan(alpha/2).
APEX_Z = C - (B / 2.0) / math.tan(ALPHA / 2.0)


def _walls(noise: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    wp = v_groove_butt(thickness=T, groove_angle=ALPHA, root_gap=B, root_face=C)
    P, _N, tri = sample_surface(wp.vertices, wp.triangles, 0.0004, seed=seed)
    labels = wp.wall_labels[tri]
    P = P + noise * np.random.default_rng(seed).standard_normal(P.shape)
    return P, labels


@pytest.fixture(scope="module")
def model():
    wp = v_groove_butt(thickness=T, groove_angle=ALPHA, root_gap=B, root_face=C)
    P, labels = _walls()
    prior = fit_groove(P, labels, wp.seam, wp.approach, wp.wall_band, GrooveParams())
    return wp, prior


def test_noise_free_walls_meet_at_the_analytic_apex(model) -> None:
    _wp, prior = model
    assert np.all(prior.status == OK)
    np.testing.assert_allclose(prior.apex[:, 1:], np.tile([0.0, APEX_Z], (len(prior.apex), 1)), atol=1e-9)
    np.testing.assert_allclose(np.abs(prior.direction[:, 0]), 1.0, atol=1e-9)
    # Normals face into the groove: left wall toward -y, both upward.
    np.testing.assert_allclose(prior.normals[0, 0], [0.0, -math.cos(ALPHA / 2), math.sin(ALPHA / 2)], atol=1e-9)
    np.testing.assert_allclose(prior.normals[0, 1], [0.0, math.cos(ALPHA / 2), math.sin(ALPHA / 2)], atol=1e-9)


def test_noisy_walls_give_the_apex_with_an_honest_uncertainty(model) -> None:
    wp, prior = model
    P, labels = _walls(noise=1e-4, seed=3)
    fit = fit_groove(P, labels, wp.seam, wp.approach, wp.wall_band, GrooveParams(), prior)
    assert np.all(fit.status == OK)
    err = np.linalg.norm(fit.apex[:, 1:] - [0.0, APEX_Z], axis=1)
    assert np.sqrt(np.mean(err**2)) < 50e-6
    # The predicted 1-sigma matches the scatter within a factor of two.
    ratio = math.sqrt(np.mean(err**2) / np.mean(fit.sigma**2))
    assert 0.5 < ratio < 2.0


def test_a_shifted_joint_moves_the_seam_but_an_opened_gap_does_not(model) -> None:
    wp, prior = model
    P, labels = _walls(noise=5e-5, seed=4)
    left, right = labels == LEFT_WALL, labels == RIGHT_WALL
    # Whole joint 0.6 mm to the left (+y): the seam follows.
    shifted = P + [0.0, 0.0006, 0.0]
    fit = fit_groove(shifted, labels, wp.seam, wp.approach, wp.wall_band, GrooveParams(), prior)
    s, _sig, valid = lateral_offsets(fit, prior, wp.seam, wp.approach, GrooveParams().step)
    assert valid.all()
    assert np.mean(s) == pytest.approx(0.0006, abs=2e-5)
    # Gap opened by 1 mm, symmetric: the walls look like a deeper groove,
    # and the seam stays where it is across.
    opened = P.copy()
    opened[left] += [0.0, 0.0005, 0.0]
    opened[right] -= [0.0, 0.0005, 0.0]
    fit = fit_groove(opened, labels, wp.seam, wp.approach, wp.wall_band, GrooveParams(), prior)
    s, _, valid = lateral_offsets(fit, prior, wp.seam, wp.approach, GrooveParams().step)
    assert valid.all()
    assert abs(np.mean(s)) < 2e-5
    assert np.nanmean(fit.apex[:, 2]) < APEX_Z - 0.0008  # the apex did drop


def test_a_wall_at_the_wrong_angle_contradicts_the_model(model) -> None:
    wp, prior = model
    P, labels = _walls(noise=5e-5, seed=5)
    right = labels == RIGHT_WALL
    R = Rotation.from_euler("x", 20.0, degrees=True).as_matrix()
    pivot = np.array([0.0, -B / 2.0, C])
    P = P.copy()
    P[right] = (P[right] - pivot) @ R.T + pivot
    fit = fit_groove(P, labels, wp.seam, wp.approach, wp.wall_band, GrooveParams(), prior)
    assert np.count_nonzero(fit.status == CONTRADICTS) > 0.9 * len(fit.status)


def test_a_missing_wall_is_unseen_not_guessed(model) -> None:
    wp, prior = model
    P, labels = _walls(noise=5e-5, seed=6)
    keep = labels != RIGHT_WALL
    fit = fit_groove(P[keep], labels[keep], wp.seam, wp.approach, wp.wall_band, GrooveParams(), prior)
    assert np.all(fit.status == UNSEEN)
    assert np.all(np.isnan(fit.apex))


def test_sparse_wall_gets_a_longer_window(model) -> None:
    wp, prior = model
    P, labels = _walls(noise=5e-5, seed=7)
    rng = np.random.default_rng(7)
    thin = (labels != RIGHT_WALL) | (rng.random(len(P)) < 0.02)  # 2 % of the right wall
    params = GrooveParams(window=0.010, max_window=0.040, min_points=15)
    fit = fit_groove(P[thin], labels[thin], wp.seam, wp.approach, wp.wall_band, params, prior)
    assert np.mean(fit.length > params.window) > 0.8
    # Half windows at the seam ends may stay short of points; the rest are measured.
    assert np.count_nonzero(fit.status == OK) > 0.85 * len(fit.status)


def test_smoothing_recovers_a_slow_ramp_and_shrinks_the_error() -> None:
    rng = np.random.default_rng(1)
    arc_w = np.arange(0.0, 0.150 + 1e-9, 0.002)
    truth = 0.0002 + 0.002 * (arc_w - 0.075)  # 0.2 mm offset, 2 mm/m twist
    sigma = np.full(len(arc_w), 5e-5)
    noisy = truth + sigma * rng.standard_normal(len(arc_w))
    arc = np.linspace(0.0, 0.150, 151)
    s, se = smooth_offsets(arc_w, noisy, sigma, np.full(len(arc_w), 0.002), np.ones(len(arc_w), bool), arc, 0.030, 0.002)
    expected = 0.0002 + 0.002 * (arc - 0.075)
    assert np.sqrt(np.mean((s - expected) ** 2)) < 2.5e-5
    assert np.all(se < 5e-5)


def test_plane_fit_ignores_points_of_a_neighbouring_face() -> None:
    rng = np.random.default_rng(2)
    plane = np.column_stack([rng.uniform(0, 0.01, 300), rng.uniform(0, 0.01, 300), 1e-5 * rng.standard_normal(300)])
    stray = np.column_stack([rng.uniform(0, 0.01, 30), np.full(30, 0.01), rng.uniform(0.0, 0.005, 30)])
    p = gm.fit_plane(np.vstack([plane, stray]))
    assert abs(p.normal[2]) > 1.0 - 1e-6
    assert p.count == pytest.approx(300, abs=5)
