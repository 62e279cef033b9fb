"""Reading the simulator's truth after a fault: the arc off, the first lasting stop, the travel to it."""

from __future__ import annotations

import math

import numpy as np

from celld.sim.robot.truth import TRUTH_DTYPE
from celld.sim.score import after_fault

PERIOD_NS = 2_000_000


def _history(y: np.ndarray, arc_on: np.ndarray, t0_ns: int) -> np.ndarray:
    h = np.zeros(len(y), TRUTH_DTYPE)
    h["stamp_ns"] = t0_ns + PERIOD_NS * np.arange(len(y))
    h["T_base_tcp"] = np.eye(4)
    h["T_base_tcp"][:, 1, 3] = y
    h["digital_out"] = np.where(arc_on, 1 << 3, 0)
    return h


def test_the_first_lasting_rest_counts_and_a_later_move_on_purpose_does_not() -> None:
    t = np.arange(600) * PERIOD_NS * 1e-9  # 1.2 s at 500 Hz
    t_fault = 0.2
    # 10 mm/s until the fault, then a linear slow-down to rest 0.1 s later, at rest 0.3 s, then a retract at 50 mm/s.
    v = np.where(t < t_fault, 0.01, np.clip(0.01 * (1.0 - (t - t_fault) / 0.1), 0.0, None))
    v[t >= 0.6] = 0.05
    y = np.r_[0.0, np.cumsum(v[:-1] * PERIOD_NS * 1e-9)]
    arc_on = t < t_fault + 0.006
    t0_ns = 10**12
    seen = after_fault(_history(y, arc_on, t0_ns), t0_ns + int(t_fault * 1e9), arc_output=3)
    assert math.isclose(seen.speed_at_fault, 0.01, rel_tol=1e-6)
    assert 0.098 <= seen.stopped_s <= 0.104, seen  # the slow-down's end, not the retract's
    assert math.isclose(seen.travel, 0.5 * 0.01 * 0.1, rel_tol=0.05), seen  # the stopping distance
    assert 0.005 <= seen.arc_off_s <= 0.009, seen

    # Still moving at the history's end: never stopped; the arc never on after the fault: off already.
    seen = after_fault(_history(np.linspace(0.0, 0.01, 100), np.zeros(100, bool), t0_ns), t0_ns + 50 * PERIOD_NS, 3)
    assert seen.stopped_s == math.inf and seen.arc_off_s == 0.0
