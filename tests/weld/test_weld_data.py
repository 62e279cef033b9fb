"""The weld data of one weld on synthetic samples whose answer is known: arc time, starts and breaks, the grace, the windows, NaN."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from celld.bus.checker import validate
from celld.errors import InputError
from celld.weld.weld_data import WELD_DATA_SCHEMA, WeldData, summarize

RATE_HZ = 500.0
DT = 1.0 / RATE_HZ
CURRENT_WINDOW = (120.0, 180.0)
VOLTAGE_WINDOW = (15.0, 25.0)
GRACE = 0.3  # 150 samples


def _weld() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """2.4 s at 500 Hz (samples 0-1199): the arc on over samples 50-1099 (2.1 s) but for a break over 500-549,
    so 1000 samples (2.0 s) of arc in two runs, started at samples 50 and 550.

    150 A and 18 V steady; a 450 A, 40 V strike transient over the first 50 samples of each run (inside the
    0.3 s grace); the current out of its window (200 A) over 800-849 and the voltage out of its (35 V) over
    840-859, 60 samples (0.12 s) outside together; the current NaN over 300-304, the voltage over 304-307
    (8 samples unread). The arc off at the end of the data is read as such (0 A, 0 V).
    """
    n = 1200
    t = 12.0 + np.arange(n) * DT  # any origin: the loop's monotonic clock
    on = np.zeros(n, dtype=bool)
    on[50:1100] = True
    on[500:550] = False
    current = np.where(on, 150.0, 0.0)
    voltage = np.where(on, 18.0, 0.0)
    for start in (50, 550):
        current[start : start + 50] = 450.0
        voltage[start : start + 50] = 40.0
    current[800:850] = 200.0
    voltage[840:860] = 35.0
    current[300:305] = np.nan
    voltage[304:308] = np.nan
    return t, on, current, voltage


# The judged samples: the runs past their grace, 200-499 and 700-1099, less the 8 unread: 692.
JUDGED = 300 + 400 - 8


def test_a_weld_with_a_break_an_excursion_and_unread_samples_has_its_known_figures() -> None:
    t, on, current, voltage = _weld()
    wd = summarize(t, on, current, voltage, CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE, ended_at_s=float(t[1100]))
    assert wd.samples == 1200
    assert wd.arc_time_s == pytest.approx(2.0, abs=1e-9)
    assert (wd.arc_starts, wd.arc_breaks) == (2, 1)  # the end at 1100 is the cell's own arc-off
    assert wd.judged_samples == JUDGED and wd.judged_s == pytest.approx(JUDGED * DT)
    assert wd.nan_samples == 8
    # The transients (450 A, 40 V) are inside the grace: the greatest values are the excursions'.
    assert (wd.current_min_a, wd.current_max_a) == (150.0, 200.0)
    assert (wd.voltage_min_v, wd.voltage_max_v) == (18.0, 35.0)
    assert wd.current_mean_a == pytest.approx((50 * 200.0 + (JUDGED - 50) * 150.0) / JUDGED)
    assert wd.voltage_mean_v == pytest.approx((20 * 35.0 + (JUDGED - 20) * 18.0) / JUDGED)
    # Outside either window: the union of the two excursions, not their sum (70 samples).
    assert wd.outside_samples == 60 and wd.outside_s == pytest.approx(0.12)
    assert wd.flagged


def test_without_a_grace_the_strike_transients_count_against_the_window() -> None:
    t, on, current, voltage = _weld()
    wd = summarize(t, on, current, voltage, CURRENT_WINDOW, VOLTAGE_WINDOW, 0.0, ended_at_s=float(t[1100]))
    assert wd.current_max_a == 450.0 and wd.voltage_max_v == 40.0
    assert wd.outside_samples == 60 + 2 * 50
    assert wd.judged_samples == 1000 - 8


def test_an_arc_that_goes_out_before_the_cell_switches_it_off_is_a_break() -> None:
    t, on, current, voltage = _weld()

    def breaks(ended_at_s: float | None) -> int:
        return summarize(t, on, current, voltage, CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE, ended_at_s).arc_breaks

    assert breaks(float(t[1100])) == 1  # switched off where the arc went out at the end
    assert breaks(float(t[1090])) == 1  # the signal drops a few cycles after the command: still the cell's
    assert breaks(float(t[1150])) == 2  # the arc went out 0.1 s before the cell switched it off: it ended early
    assert breaks(None) == 2  # the cell never switched it off: every arc end was the arc's own
    assert breaks(float(t[400])) == 0  # both ends after the cell's arc-off


def test_a_clean_weld_is_not_flagged() -> None:
    t, on, current, voltage = _weld()
    current[800:850] = 150.0
    voltage[840:860] = 18.0
    wd = summarize(t, on, current, voltage, CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE, ended_at_s=float(t[1100]))
    assert wd.outside_s == 0.0 and wd.outside_samples == 0 and not wd.flagged
    assert (wd.current_min_a, wd.current_max_a, wd.current_mean_a) == (150.0, 150.0, 150.0)


def test_a_weld_that_starts_with_the_arc_on_starts_once_and_the_window_ends_are_inside() -> None:
    n = 1000
    t = np.arange(n) * DT
    current = np.full(n, 150.0)
    current[600:610] = CURRENT_WINDOW[1]  # on the window's end: inside
    current[700:702] = np.nextafter(CURRENT_WINDOW[1], np.inf)  # just past it: outside
    wd = summarize(t, np.ones(n, dtype=bool), current, np.full(n, 18.0), CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE)
    assert (wd.arc_starts, wd.arc_breaks) == (1, 0)
    assert wd.arc_time_s == pytest.approx(2.0)
    assert wd.judged_samples == n - 150
    assert wd.outside_samples == 2 and wd.outside_s == pytest.approx(2 * DT)


def test_an_arc_shorter_than_its_grace_is_timed_and_counted_but_not_judged() -> None:
    t = np.arange(100) * DT
    on = np.zeros(100, dtype=bool)
    on[10:60] = True  # 0.1 s of arc, a 0.3 s grace
    wd = summarize(t, on, np.where(on, 500.0, 0.0), np.full(100, 18.0), CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE)
    assert wd.arc_time_s == pytest.approx(0.1) and (wd.arc_starts, wd.arc_breaks) == (1, 1)
    assert wd.judged_samples == 0 and wd.current_max_a == 0.0 and not wd.flagged


def test_the_time_of_a_sample_is_the_spacing_to_the_next_one() -> None:
    # A cycle that came late (a 10 ms gap after sample 2) counts for its real time: the arc on from 0 until
    # the off sample at 16 ms, though it was read on only 4 times.
    t = np.array([0.0, 0.002, 0.004, 0.014, 0.016])
    wd = summarize(t, [1, 1, 1, 1, 0], np.full(5, 150.0), np.full(5, 18.0), CURRENT_WINDOW, VOLTAGE_WINDOW, 0.0, 0.016)
    assert wd.arc_time_s == pytest.approx(0.016)
    assert wd.judged_s == pytest.approx(0.016) and wd.judged_samples == 4
    assert (wd.arc_starts, wd.arc_breaks) == (1, 0)


def test_no_samples_give_zeros_and_no_arc_gives_no_figures() -> None:
    assert summarize([], [], [], [], CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE) == WeldData()
    t = np.arange(10) * DT
    wd = summarize(t, np.zeros(10, dtype=bool), np.zeros(10), np.zeros(10), CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE)
    assert wd == WeldData(samples=10)
    one = summarize([0.0], [True], [150.0], [18.0], CURRENT_WINDOW, VOLTAGE_WINDOW, 0.0)
    assert (one.arc_starts, one.arc_time_s, one.judged_samples) == (1, 0.0, 1)


def test_as_dict_is_the_shape_it_promises_and_json_ready() -> None:
    t, on, current, voltage = _weld()
    for wd in (summarize(t, on, current, voltage, CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE), WeldData()):
        d = wd.as_dict()
        validate(WELD_DATA_SCHEMA, d)
        assert json.loads(json.dumps(d, allow_nan=False)) == d
        assert d["flagged"] is wd.flagged and d["outside_s"] == pytest.approx(wd.outside_s, abs=1e-4)


def test_values_are_frozen_and_inputs_untouched() -> None:
    t, on, current, voltage = _weld()
    copies = [a.copy() for a in (t, on, current, voltage)]
    wd = summarize(t, on, current, voltage, CURRENT_WINDOW, VOLTAGE_WINDOW, GRACE)
    for a, b in zip((t, on, current, voltage), copies):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(dataclasses.FrozenInstanceError):
        wd.outside_s = 0.0  # type: ignore[misc]


def _args(**change: object) -> dict[str, object]:
    n = 10
    base: dict[str, object] = {
        "t_s": np.arange(n) * DT,
        "arc_on": np.ones(n, dtype=bool),
        "current_a": np.full(n, 150.0),
        "voltage_v": np.full(n, 18.0),
        "current_window_a": CURRENT_WINDOW,
        "voltage_window_v": VOLTAGE_WINDOW,
        "grace_s": GRACE,
    }
    return {**base, **change}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"current_a": np.full(9, 150.0)}, r"current_a: expected shape \(10,\) like t_s, got \(9,\)"),
        ({"arc_on": np.ones(11, dtype=bool)}, r"arc_on: expected shape \(10,\)"),
        ({"t_s": np.zeros((10, 1))}, r"t_s: expected a 1-D array, got shape \(10, 1\)"),
        ({"t_s": np.r_[0.0, 0.002, np.nan, np.arange(3, 10) * DT]}, "t_s: expected finite times, got 1"),
        (
            {"t_s": np.r_[0.0, 0.004, 0.002, np.arange(3, 10) * DT]},
            r"t_s: expected non-decreasing times, got t\[2\] = 0.002 after t\[1\] = 0.004",
        ),
        ({"arc_on": np.full(10, 2)}, "arc_on: expected booleans .* 10 other values such as 2"),
        ({"arc_on": np.array(["on"] * 10)}, "arc_on: expected booleans"),
        ({"voltage_v": np.r_[np.inf, np.full(9, 18.0)]}, "voltage_v: expected numbers .* 1 infinite"),
        ({"current_a": ["a"] * 10}, "current_a: expected an array of numbers"),
        ({"current_window_a": (180.0, 120.0)}, "current_window_a: expected finite .lo, hi. with lo below hi"),
        ({"voltage_window_v": (15.0, np.nan)}, "voltage_window_v: expected finite"),
        ({"voltage_window_v": (15.0,)}, r"voltage_window_v: expected \(lo, hi\)"),
        ({"grace_s": -0.1}, "grace_s: expected a finite number >= 0 s"),
        ({"grace_s": float("inf")}, "grace_s: expected a finite number"),
        ({"ended_at_s": float("nan")}, "ended_at_s: expected a finite time"),
    ],
)
def test_bad_input_is_refused_naming_the_argument(change: dict[str, object], message: str) -> None:
    with pytest.raises(InputError, match=message):
        summarize(**_args(**change))  # type: ignore[arg-type]


def test_time_stamps_may_repeat() -> None:
    # A cycle read twice has the same stamp: non-decreasing is enough, and the repeat takes no time.
    wd = summarize(**_args(t_s=np.r_[0.0, 0.0, np.arange(2, 10) * DT], grace_s=0.0))  # type: ignore[arg-type]
    assert wd.arc_time_s == pytest.approx(10 * DT) and wd.judged_samples == 10
