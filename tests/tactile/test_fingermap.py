"""The finger's gain from touches onto walls: recovered from a drawn tag-to-tip relation, refused where no finger is."""

from __future__ import annotations

import numpy as np
import pytest

from celld.errors import InputError, TactileError
from celld.sim.srm import ContactParams, tag_of_tip
from celld.tactile.fingermap import FingerGain, FingerRefused, Press, along_normal, fit_finger_gain

DELTA_D = 1.5e-3


def _press(wall: float, towards: float, params: ContactParams, noise: float, rng: np.random.Generator, n: int = 20) -> Press:
    """A touch coming onto a wall at ``wall`` (m across) in the direction ``towards`` (+1, -1): the tip pressed 0.3-1.6 mm,
    the tag as the world's finger moves it, seen with ``noise`` (m, 1 sigma); the finger wall on the +1 side."""
    tip = np.linspace(0.3e-3, 1.6e-3, n)
    tag = np.array([tag_of_tip(np.array([0.0, towards * t, 0.0]), params)[1] for t in tip]) + rng.normal(0.0, noise, n)
    return Press(wall + towards * tip, tag, 1.0)


def test_the_fit_recovers_the_tip_a_drawn_finger_hides_behind_its_tag() -> None:
    rng = np.random.default_rng(4)
    # A tag at 92 % of the bending length (0.87 of the tip), softening at 8 mm: not the fit's own family.
    params = ContactParams(tag_gain=(0.9, 0.87), tag_softening=8e-3)
    presses = [_press(0.0123, 1.0, params, 2e-6, rng), _press(-0.0071, -1.0, params, 2e-6, rng)]
    fit = fit_finger_gain(presses, DELTA_D)
    assert fit.frames == 40 and fit.walls == pytest.approx((0.0123, -0.0071), abs=5e-6)
    assert fit.finger.gain == pytest.approx(1 / 0.87, rel=0.01) and fit.finger.cubic > 0.0  # the softening: the cubic term
    # The tip's deflection from the tag's, over the range the servo works in, to a few um (it was 13 % off).
    for tip in (0.5e-3, 1.0e-3, 1.5e-3):
        tag = tag_of_tip(np.array([0.0, tip, 0.0]), params)[1]
        assert fit.finger.tip(tag) == pytest.approx(tip, abs=4e-6)
        assert abs(tag - tip) > 0.05 * tip
    assert fit.residual_rms < 4e-6 and 0.0 < fit.gain_sigma < 0.01
    # Without the cubic term a straight line through the same frames leaves the softening in its residual.
    assert fit_finger_gain(presses, DELTA_D, cubic=False).residual_rms > 2 * fit.residual_rms


def test_a_finger_whose_tag_moves_with_its_tip_fits_to_one() -> None:
    rng = np.random.default_rng(5)
    fit = fit_finger_gain([_press(0.01, 1.0, ContactParams(), 1e-6, rng), _press(-0.01, -1.0, ContactParams(), 1e-6, rng)], DELTA_D)
    assert fit.finger.gain == pytest.approx(1.0, abs=0.005) and abs(fit.finger.cubic) * DELTA_D**2 < 0.005


def test_touches_that_cannot_tell_a_gain_are_refused_and_a_broken_finger_is_refused_apart() -> None:
    rng = np.random.default_rng(6)
    good = _press(0.01, 1.0, ContactParams(), 1e-6, rng)
    with pytest.raises(TactileError, match="touch 1's frames span 0.000 mm"):
        fit_finger_gain([good, Press(np.full(5, 0.01), np.full(5, 1e-3), -1.0)], DELTA_D)
    with pytest.raises(TactileError, match="3 frames in contact, at least 8"):
        fit_finger_gain([Press(good.y[[0, 10, 19]], good.d[[0, 10, 19]], 1.0)], DELTA_D)
    # A tag come loose: it moves twice what the tip does.
    loose = ContactParams(tag_gain=(2.0, 2.0))
    with pytest.raises(FingerRefused, match="the tag moves 2.0"):
        fit_finger_gain([_press(0.01, 1.0, loose, 1e-6, rng)], DELTA_D)
    with pytest.raises(InputError, match="side must be"):
        fit_finger_gain([good._replace(side=0.5)], DELTA_D)


def test_a_gain_is_checked_where_it_is_used_and_taken_along_the_normal_only() -> None:
    FingerGain(1.1, 0.0).check(DELTA_D)
    for bad in (FingerGain(0.5), FingerGain(float("nan")), FingerGain(1.0, 0.4 / DELTA_D**2)):
        with pytest.raises(InputError, match="finger gain"):
            bad.check(DELTA_D)
    n = np.array([0.6, 0.8])
    t = np.array([-0.8, 0.6])
    delta = 1e-3 * n + 0.4e-3 * t
    mapped = along_normal(delta, n, FingerGain(1.2, 0.0))
    assert mapped @ n == pytest.approx(1.2e-3) and mapped @ t == pytest.approx(0.4e-3)


def test_a_gain_goes_to_a_result_and_back_in_its_units_and_gives_its_ratio_where_the_tag_shows_a_deformation() -> None:
    finger = FingerGain(1.12, 0.03e6)  # 0.03 /mm^2
    assert finger.reading() == {"gain": 1.12, "cubic_per_mm2": 0.03}
    assert FingerGain.of_reading(finger.reading()) == (1.12, pytest.approx(0.03e6))
    assert finger.over(1.5e-3) == pytest.approx(1.12 + 0.03 * 1.5**2) == pytest.approx(float(finger.tip(1.5e-3)) / 1.5e-3)
