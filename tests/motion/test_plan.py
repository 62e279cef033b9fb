"""The planned seam: its welding plane and the smoothed path in it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.motion.plan import prepare_plan, welding_plane


def test_plan_is_smoothed_and_its_plane_found() -> None:
    rng = np.random.default_rng(0)
    x = np.arange(0.0, 0.2, 0.001)
    P = np.column_stack([x, 0.3 + 0.05 * x + rng.normal(0, 3e-4, len(x)), 0.1 + rng.normal(0, 3e-4, len(x))])
    T_bp = welding_plane(P, np.array([0.0, 0.0, 1.0]))
    # A straight plan: the plane through it nearest to horizontal, normal up.
    assert T_bp[2, 2] > 0.999
    path = prepare_plan(P, T_bp, 0.012)
    angles = np.arctan2(path.T[:, 1], path.T[:, 0])
    # The plane's x runs along the plan. The raw points' tangents scatter by
    # tens of degrees; a quadratic over 12 mm has a slope noise of about
    # 0.3 mm / 12 mm = 1.4 degrees RMS.
    raw = np.diff(P[:, :2], axis=0)
    assert np.degrees(np.abs(np.arctan2(raw[:, 1], raw[:, 0]) - math.atan2(0.05, 1.0))).max() > 20.0
    inner = np.degrees(angles[20:-20])
    assert np.sqrt(np.mean(inner**2)) < 2.0
    assert np.abs(inner).max() < 5.0
    assert path.s[-1] == pytest.approx(0.2 * math.hypot(1.0, 0.05), rel=0.01)
    # An arc fixes its plane: tilted by 10 degrees about x.
    a = np.linspace(0, 1.5, 200)
    arc = np.column_stack([0.1 * np.sin(a), 0.1 * (1 - np.cos(a)), np.zeros_like(a)])
    R = Rotation.from_rotvec([math.radians(10), 0, 0]).as_matrix()
    T_arc = welding_plane(arc @ R.T, np.array([0.0, 0.0, 1.0]))
    assert math.degrees(math.acos(min(float(T_arc[:3, 2] @ R[:, 2]), 1.0))) < 0.01
