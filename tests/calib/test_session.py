"""CalibrationSession: Algorithm 1 online, its early stop behind the quality gate, and the final solve.

Algorithm 1 can be done (its cost under e_required) after five pairs while two
of them are false detections millimetres off: stopping there would fail the
job although more poses remain. The session stops early only on pairs that
pass the quality gate as the estimator left them. Pairs a few tenths of a
millimetre apart, as a realistic arm's pose-dependent error makes them, are
no outliers (celld.calib.quality.OUTLIER_FLOOR).
"""

from __future__ import annotations

import numpy as np
import pytest

from celld import se3
from celld.calib.metrics import IcpMetric
from celld.calib.session import CalibrationSession, CaptureStep
from celld.calib.solve import SolveParams
from celld.errors import CalibrationError

T_BASE_CAM = se3.from_xyz_rpy([0.6, 0.1, 1.2], [np.pi, 0.05, 0.1])


class PerfectVerifier:
    """e_icp double: every estimate scores zero, so Algorithm 1 is done at its first pool."""

    def strict(self) -> PerfectVerifier:
        return self

    def __call__(self, T_base_cam: np.ndarray) -> IcpMetric:
        return IcpMetric(np.eye(4), True, 1.0, 1e-5)


def _pairs(n: int, off: dict[int, float], seed: int = 3) -> tuple[list[str], np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    P_base = np.array([0.6, 0.0, 0.45]) + rng.uniform(-0.1, 0.1, (n, 3))
    P_cam = se3.apply(se3.invert(T_BASE_CAM), P_base) + rng.normal(0.0, 20e-6, (n, 3))
    for i, d in off.items():
        P_cam[i] += d * np.array([1.0, 0.0, 0.0])
    return [f"p{i:03d}" for i in range(n)], P_base, P_cam


def _feed(session: CalibrationSession, n: int, off: dict[int, float]) -> list[CaptureStep]:
    """Recorded pairs into the session until it stops or they run out."""
    ids, P_base, P_cam = _pairs(n, off)
    steps: list[CaptureStep] = []
    for pid, pb, pc in zip(ids, P_base, P_cam):
        steps.append(session.add(pid, pb, p_cam=pc))
        if steps[-1].stop:
            break
    return steps


def test_consistent_pairs_stop_the_session_at_the_gates_minimum() -> None:
    params = SolveParams()
    session = CalibrationSession(None, params, planned=20, verifier=PerfectVerifier())
    steps = _feed(session, 20, {})
    first = steps[3].algorithm1
    assert first is not None and first.k == 0 and first.reached
    assert len(steps) == params.quality.min_pairs and steps[-1].stop and not any(s.held for s in steps)
    result = session.finish()
    assert session.stopped_early and session.reached and result.quality.verdict == "ok"
    assert se3.error(result.T_base_cam, T_BASE_CAM)[0] < 0.1e-3
    with pytest.raises(CalibrationError, match="has stopped"):
        session.add("late", np.zeros(3), p_cam=np.zeros(3))


def test_false_detections_keep_it_capturing_until_they_are_outvoted() -> None:
    session = CalibrationSession(None, SolveParams(), planned=20, verifier=PerfectVerifier())
    steps = _feed(session, 20, {1: 4e-3, 3: -3e-3})
    # At five pairs the estimate would rest on three: held, with the reason.
    assert not steps[4].stop and steps[4].held, [s.held for s in steps]
    # More poses outvote them: the two are left out and the gate passes on the five good ones.
    assert steps[-1].stop and len(steps) == 7, [s.held for s in steps]
    result = session.finish()
    assert result.quality.verdict == "ok" and sorted(r.id for r in result.rejected) == ["p001", "p003"]


def test_pairs_a_few_tenths_off_are_the_arms_error_not_outliers() -> None:
    """A realistic arm's pose-dependent error puts pairs a few tenths of a millimetre apart: they are kept (the
    calibration's bound carries that error), and the session stops at the gate's five pairs."""
    session = CalibrationSession(None, SolveParams(), planned=20, verifier=PerfectVerifier())
    steps = _feed(session, 20, {1: 0.4e-3, 3: -0.3e-3})
    assert len(steps) == 5 and steps[-1].stop and not any(s.held for s in steps), [s.held for s in steps]
    result = session.finish()
    assert result.quality.verdict == "ok" and result.rejected == () and result.quality.outliers == ()
    assert result.quality.bound_box > 0.3e-3


def test_the_last_planned_capture_never_stops_early_and_offline_collects_every_pair() -> None:
    online = CalibrationSession(None, SolveParams(), planned=5, verifier=PerfectVerifier())
    steps = _feed(online, 5, {})
    assert len(steps) == 5 and not any(s.stop for s in steps) and not online.stopped_early
    offline = CalibrationSession(None, SolveParams(), planned=20, online=False, verifier=PerfectVerifier())
    steps = _feed(offline, 20, {})
    assert len(steps) == 20 and all(s.algorithm1 is None and not s.stop for s in steps)
    result = offline.finish()
    assert len(result.pair_ids) == 20 and result.n_pairs == 20 and result.algorithm1 is not None


def test_fewer_than_four_pairs_are_refused_naming_the_misses() -> None:
    session = CalibrationSession(None, SolveParams(), planned=6, online=False)
    ids, P_base, P_cam = _pairs(3, {})
    for pid, pb, pc in zip(ids, P_base, P_cam):
        session.add(pid, pb, p_cam=pc)
    session.add("p003", P_base[0])  # neither a centre nor a cloud
    with pytest.raises(CalibrationError, match=r"only 3 of 4 captures showed the flange.*p003: no flange centre recorded"):
        session.finish()


def test_online_needs_the_verification_capture_before_its_first_pool() -> None:
    session = CalibrationSession(None, SolveParams(), planned=8)
    with pytest.raises(CalibrationError, match="verification capture first"):
        _feed(session, 8, {})
