"""The twist limiter holds the speed, acceleration and jerk norms in every cycle."""

from __future__ import annotations

import numpy as np
import pytest

from celld.config import MotionLimits
from celld.errors import InputError
from celld.motion.limits import CartesianLimits, LimiterResult, TwistLimiter, clamp_norms, sequence_peaks

LIMITS = CartesianLimits.from_config(MotionLimits())
PERIOD = 0.002
# Rounding only: the norms must hold to this relative slack.
RTOL = 1e-6


def _random_target(rng: np.random.Generator) -> np.ndarray:
    t = rng.normal(size=6)
    # Half the targets on or beyond the speed ball, half inside it.
    t[:3] *= rng.choice([1.0, 1.3, rng.uniform(0.0, 1.0)]) * LIMITS.linear_speed / np.linalg.norm(t[:3])
    t[3:] *= rng.choice([1.0, 1.3, rng.uniform(0.0, 1.0)]) * LIMITS.angular_speed / np.linalg.norm(t[3:])
    return t


@pytest.mark.parametrize("change_probability", [0.01, 0.05, 0.3])
def test_norms_hold_in_every_cycle_for_random_targets(rng: np.random.Generator, change_probability: float) -> None:
    for _ in range(5):
        lim = TwistLimiter(LIMITS, PERIOD)
        target = np.zeros(6)
        sent = []
        for _ in range(1200):
            if rng.random() < change_probability:
                target = _random_target(rng)
            v, result = lim.step(target)
            assert result != LimiterResult.ERROR
            sent.append(v)
        ratios = sequence_peaks(np.array(sent), PERIOD, initial=np.zeros((2, 6))).ratios(LIMITS)
        assert max(ratios) <= 1.0 + RTOL, ratios


def test_the_guard_keeps_the_speed_ball_when_the_direction_turns_at_full_speed() -> None:
    # Cruise at full speed along x, then turn to y: without the guard the
    # unsynchronised unwinding of x and winding of y leaves the ball.
    lim = TwistLimiter(LIMITS, PERIOD)
    v_max = LIMITS.linear_speed
    sent, results = [], []
    for target, cycles in (([v_max, 0, 0], 300), ([0, v_max, 0], 40), ([-v_max, 0.0, 0], 40), ([0, 0, v_max], 600)):
        for _ in range(cycles):
            v, r = lim.step(np.array([*target, 0.0, 0.0, 0.0]))
            sent.append(v)
            results.append(r)
    ratios = sequence_peaks(np.array(sent), PERIOD, initial=np.zeros((2, 6))).ratios(LIMITS)
    assert max(ratios) <= 1.0 + RTOL
    assert LimiterResult.GUARDED in results
    np.testing.assert_allclose(sent[-1][:3], [0, 0, v_max], atol=1e-9)


def test_a_step_is_reached_straight_and_in_the_time_optimal_duration() -> None:
    lim = TwistLimiter(LIMITS, PERIOD)
    target = np.array([0.15, -0.2, 0.0, 0.3, 0.0, -0.4]) * 0.9
    sent = np.array([lim.step(target)[0] for _ in range(400)])
    np.testing.assert_allclose(sent[-1], target, atol=1e-12)
    # Each part moves (nearly) straight in velocity space, a multiple of its
    # target: the per-cycle re-shaping of the boxes bends it by < 0.1 %.
    for part in (slice(0, 3), slice(3, 6)):
        t, v = target[part], sent[:, part]
        s = v @ t / (t @ t)
        off = np.linalg.norm(v - s[:, None] * t[None, :], axis=1)
        assert off.max() < 1e-3 * np.linalg.norm(t)
    # The linear part needs t = v/a + a/j at the full budget; the axis floor of
    # the boxes and the per-cycle re-planning may cost a few per cent.
    v = np.linalg.norm(target[:3])
    t_min = v / LIMITS.linear_accel + LIMITS.linear_accel / LIMITS.linear_jerk
    reached = int(np.argmax(np.linalg.norm(sent[:, :3] - target[:3], axis=1) < 1e-9)) * PERIOD
    assert t_min - 2 * PERIOD <= reached <= t_min * 1.05 + 2 * PERIOD


def test_targets_beyond_the_speed_ball_are_clamped() -> None:
    t = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 5.0])
    c = clamp_norms(t, LIMITS)
    assert np.linalg.norm(c[:3]) == pytest.approx(LIMITS.linear_speed)
    assert np.linalg.norm(c[3:]) == pytest.approx(LIMITS.angular_speed)
    lim = TwistLimiter(LIMITS, PERIOD)
    for _ in range(600):
        v, _ = lim.step(t)
    np.testing.assert_allclose(v, c, atol=1e-12)


def test_reset_and_rest() -> None:
    lim = TwistLimiter(LIMITS, PERIOD)
    assert lim.at_rest()
    lim.step(np.full(6, 0.05))
    assert not lim.at_rest()
    lim.reset()
    assert lim.at_rest() and np.all(lim.twist == 0)


@pytest.mark.parametrize("bad", [np.full(5, 0.1), np.array([np.nan, 0, 0, 0, 0, 0])])
def test_reset_refuses_malformed_twists(bad: np.ndarray) -> None:
    with pytest.raises(InputError):
        TwistLimiter(LIMITS, PERIOD).reset(bad)


def test_limits_must_be_positive() -> None:
    with pytest.raises(InputError, match="limit"):
        TwistLimiter(LIMITS._replace(linear_jerk=0.0), PERIOD)
    with pytest.raises(InputError, match="factor"):
        LIMITS.scaled(1.5)


def test_sequence_peaks_measures_finite_differences() -> None:
    v = np.zeros((4, 6))
    v[2, 0] = 0.001  # one step: accel 0.5 m/s^2, jerk 250 m/s^3 at 2 ms
    peaks = sequence_peaks(v, PERIOD)
    assert peaks.linear_speed == pytest.approx(0.001)
    assert peaks.linear_accel == pytest.approx(0.5)
    assert peaks.linear_jerk == pytest.approx(0.001 * 2 / PERIOD**2)
    assert peaks.angular_speed == 0.0
