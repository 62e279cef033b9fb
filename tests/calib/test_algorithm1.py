"""Algorithm 1: the pool of four, the replacement rule, the stopping rule, the online interface.

The scoring callable is a test double here (an e_icp whose translation is the
estimate's distance from a known transform), so each rule can be checked by
hand; tests/calib/test_metrics.py covers the real e_icp.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.calib.algorithm1 import POOL_SIZE, Algorithm1, run_algorithm1
from celld.calib.metrics import IcpMetric, translation_cost
from celld.errors import CalibrationError, InputError
from celld.se3 import apply, invert, transform_from

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
# Non-coplanar flange centres in the base frame.
P_BASE = np.array(
    [
        [0.5, -0.1, 0.4],
        [0.7, -0.1, 0.5],
        [0.5, 0.1, 0.5],
        [0.7, 0.1, 0.4],
        [0.6, 0.0, 0.35],
        [0.55, 0.05, 0.55],
        [0.65, -0.05, 0.45],
    ]
)
P_CAM = apply(invert(T_BASE_CAM), P_BASE)


class FakeMetric:
    """e_icp double: the estimate's camera-origin offset, as a translation; counts calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, T_base_cam: np.ndarray) -> IcpMetric:
        self.calls += 1
        T = invert(T_base_cam) @ T_BASE_CAM
        return IcpMetric(transform_from(np.eye(3), T[:3, 3]), True, 1.0, 0.0)


def corrupted(offsets: dict[int, list[float]]) -> np.ndarray:
    P = P_CAM.copy()
    for i, d in offsets.items():
        P[i] += d
    return P


def test_initial_pool_is_solved_and_scored() -> None:
    metric = FakeMetric()
    alg = Algorithm1(metric, translation_cost, e_required=1e-4, k_max=10)
    step = alg.start(["a", "b", "c", "d"], P_BASE[:4], P_CAM[:4])
    assert step.k == 0 and step.pool_ids == ("a", "b", "c", "d")
    assert step.cost_optimal < 1e-12 and step.reached
    assert alg.done and metric.calls == 1


def test_new_pair_replaces_the_slot_of_a_false_detection() -> None:
    # Slot 2 holds a false detection 10 mm off; the new good pair must take slot 2.
    P_cam = corrupted({2: [0.01, 0.0, 0.0]})
    alg = Algorithm1(FakeMetric(), translation_cost, e_required=1e-6, k_max=10)
    first = alg.start(["p0", "p1", "p2", "p3"], P_BASE[:4], P_cam[:4])
    assert first.cost_optimal > 1e-3
    step = alg.add("p4", P_BASE[4], P_cam[4])
    assert step.accepted_slot == 2
    assert step.pool_ids == ("p0", "p1", "p4", "p3")
    assert len(step.candidates) == POOL_SIZE
    # The accepted candidate is the cheapest of the four.
    assert step.cost_optimal == min(c.cost for c in step.candidates) < 1e-12
    assert step.reached and alg.done


def test_a_worse_pair_is_undone() -> None:
    P_cam = corrupted({4: [0.0, 0.02, 0.0]})
    alg = Algorithm1(FakeMetric(), translation_cost, e_required=0.0, k_max=10)
    first = alg.start(list("abcd"), P_BASE[:4], P_cam[:4])
    step = alg.add("e", P_BASE[4], P_cam[4])
    assert step.accepted_slot is None
    assert step.pool_ids == first.pool_ids
    np.testing.assert_array_equal(step.T_base_cam, first.T_base_cam)
    assert all(c.cost >= first.cost_optimal for c in step.candidates)


def test_stops_at_k_max_and_refuses_more_pairs() -> None:
    P_cam = corrupted({0: [0.005, 0.0, 0.0]})
    alg = Algorithm1(FakeMetric(), translation_cost, e_required=0.0, k_max=1)
    alg.start(list("abcd"), P_BASE[:4], P_cam[:4])
    assert not alg.done
    alg.add("e", P_BASE[4], P_cam[4])
    assert alg.done and not alg.reached
    with pytest.raises(CalibrationError, match="k_max = 1"):
        alg.add("f", P_BASE[5], P_cam[5])


def test_degenerate_pools_cost_infinity_with_the_reason() -> None:
    # Three coincident pairs: two distinct points, the initial pool cannot be solved.
    P_b = np.array([P_BASE[0], P_BASE[0], P_BASE[0], P_BASE[1]])
    P_c = apply(invert(T_BASE_CAM), P_b)
    alg = Algorithm1(FakeMetric(), translation_cost, e_required=0.0, k_max=5)
    step = alg.start(list("abcd"), P_b, P_c)
    assert step.T_base_cam is None and step.cost_optimal == math.inf
    assert "collinear" in step.candidates[0].reason
    # A third point in place of a duplicate: three points off one line (a plane)
    # fix the rotation (Eq. 10-12), the candidate is solved and beats infinity.
    step = alg.add("e", P_BASE[2], P_CAM[2])
    assert step.accepted_slot in (0, 1, 2) and step.cost_optimal < 1e-12
    # Putting a point of the line P0-P1 in place of that third point leaves the
    # pool on one line again: that candidate is infinite, with the reason.
    slot = step.accepted_slot
    on_line = 2 * P_BASE[1] - P_BASE[0]
    step = alg.add("f", on_line, apply(invert(T_BASE_CAM), on_line[None])[0])
    assert step.candidates[slot].cost == math.inf and "collinear" in step.candidates[slot].reason


def test_online_interface_validates_its_input() -> None:
    alg = Algorithm1(FakeMetric(), translation_cost, e_required=0.0, k_max=5)
    with pytest.raises(CalibrationError, match="has not started"):
        alg.add("x", P_BASE[0], P_CAM[0])
    with pytest.raises(InputError, match="expected 4 pairs"):
        alg.start(list("abc"), P_BASE[:3], P_CAM[:3])
    with pytest.raises(InputError, match="unique"):
        alg.start(list("abca"), P_BASE[:4], P_CAM[:4])
    alg.start(list("abcd"), P_BASE[:4], corrupted({0: [0.001, 0, 0]})[:4])
    with pytest.raises(InputError, match="already given"):
        alg.add("a", P_BASE[4], P_CAM[4])
    with pytest.raises(InputError, match="NaN"):
        alg.add("e", [np.nan, 0.0, 0.0], P_CAM[4])
    with pytest.raises(CalibrationError, match="already started"):
        alg.start(list("efgh"), P_BASE[:4], P_CAM[:4])
    with pytest.raises(InputError, match="e_required"):
        Algorithm1(FakeMetric(), translation_cost, e_required=-1.0, k_max=5)


def test_batch_helper_stops_when_the_target_is_reached() -> None:
    P_cam = corrupted({1: [0.004, 0.0, 0.0], 3: [0.0, 0.003, 0.0]})
    metric = FakeMetric()
    res = run_algorithm1([f"p{i}" for i in range(7)], P_BASE, P_cam, metric, translation_cost, e_required=1e-9)
    assert res.reached
    assert set(res.pool_ids).isdisjoint({"p1", "p3"})
    # It stopped at the first step that reached the target.
    assert [s.reached for s in res.steps].index(True) == len(res.steps) - 1
    assert res.n_pairs_used == 4 + res.steps[-1].k
    # The optimum carries its pool's residuals and uncertainty (12 equations, 6 unknowns).
    assert res.fit is not None and res.fit.residuals.shape == (4,) and res.fit.uncertainty.dof == 6
    assert metric.calls == 1 + POOL_SIZE * res.steps[-1].k
    assert res.steps[-1].as_dict()["reached"] is True


def test_batch_helper_refuses_mismatched_ids() -> None:
    with pytest.raises(InputError, match="expected 7 pair ids"):
        run_algorithm1(["a"], P_BASE, P_CAM, FakeMetric(), e_required=0.0)
