"""The weld's arc sequence with its power source: the pure sequence, then Algorithm 2 in the motion core with a
scripted source (the finger's contact model and a kinematic arm of tests/motion/test_algorithm2.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.motion.arc import ArcParams, ArcPhase, ArcSequence, SourceSignals, params_of, plan_keys
from celld.motion.commands import move_to, start_servo
from celld.motion.core import CycleInput, Mode
from celld.motion.types import ControlStatus, RobotState
from tests.motion.test_algorithm2 import Loop

PERIOD = 0.002
# Short times, so a closed-loop weld takes a few simulated seconds.
ARC = ArcParams(preflow=0.1, strike_timeout=0.2, restrikes=2, restrike_pause=0.05, backoff=0.002, crater=0.15, burnback=0.05, postflow=0.2)
READY = SourceSignals(ready=True, arc_stable=False)


class Source:
    """A power source as the cell's inputs show it, driven by what the core tells it.

    The arc is stable ``delay`` after ``arc_start`` rises, unless that start's number (from 1) is in ``fail``; it
    goes out after ``loss_after`` s of arc (once) and comes back only on a new start; after the arc-off that
    follows the crater, the wire sticks if ``stuck``. ``history`` keeps (t, arc_start, gas, arc burning).
    """

    def __init__(self, delay: float = 0.06, fail: tuple[int, ...] = (), loss_after: float | None = None, stuck: bool = False) -> None:
        self.delay, self.fail, self.loss_after, self.stuck = delay, fail, loss_after, stuck
        self.attempt = 0
        self.t_start = math.nan
        self.burning = False
        self.arc_time = 0.0
        self.lost = False
        self.crater_seen = False
        self.wire_stuck = False
        self.fault = False
        self.ready = True
        self.prev_start = False
        self.history: list[tuple[float, bool, bool, bool]] = []

    def __call__(self, t: float, out) -> SourceSignals:
        start = bool(out.arc_start) if out is not None else False
        gas = bool(out.gas) if out is not None else False
        if out is not None and out.phase == ArcPhase.CRATER:
            self.crater_seen = True
        if start and not self.prev_start:
            self.attempt += 1
            self.t_start = t
        if not start:
            if self.prev_start and self.crater_seen and self.stuck:
                self.wire_stuck = True
            self.burning = False
        elif not self.burning and self.attempt not in self.fail and t - self.t_start >= self.delay and (self.t_start > self._lost_at):
            self.burning = True
        if self.burning:
            self.arc_time += PERIOD
            if self.loss_after is not None and not self.lost and self.arc_time >= self.loss_after:
                self.lost, self.burning = True, False
                self._lost_at = t
        self.prev_start = start
        self.history.append((t, start, gas, self.burning))
        return SourceSignals(self.ready and not self.fault, self.burning, start or gas, self.wire_stuck, self.fault)

    _lost_at = -math.inf


def _x(loop: Loop) -> np.ndarray:
    return loop.T[:3, 3].copy()


def _run(source: Source, arc: ArcParams = ARC, length: float = 0.03, seconds: float = 30.0, **kw) -> Loop:
    loop = Loop(length=length, process=True, source=source, arc=arc, **kw)
    loop.positions = []

    orig = loop.core.step

    def step(inp: CycleInput):
        loop.positions.append(inp.state.T_base_tcp[:3, 3].copy())
        return orig(inp)

    loop.core.step = step  # type: ignore[method-assign]
    loop.run(seconds)
    return loop


def _phases(loop: Loop) -> list[ArcPhase]:
    return [o.arc.phase for o in loop.outs]


def _travel_without_arc(loop: Loop, source: Source) -> float:
    """Metres the TCP moved along the seam (x) in cycles with the arc asked for but not burning, after the first ask."""
    arc = np.array([h[3] for h in source.history])[-len(loop.outs) :]
    asked = np.array([o.arc.phase in (ArcPhase.PREFLOW, ArcPhase.STRIKE, ArcPhase.PAUSE) for o in loop.outs])
    x = np.array(loop.positions)[-len(loop.outs) :, 0]
    dx = np.abs(np.diff(x, prepend=x[0]))
    return float(dx[asked & ~arc].sum())


# -- the pure sequence ------------------------------------------------------------------------------------


def _steps(seq: ArcSequence, t0: float, seconds: float, sig: SourceSignals, want=True, end=False, speed=0.0):
    out = None
    n = int(round(seconds / PERIOD))
    for k in range(n):
        out = seq.step(t0 + k * PERIOD, want, end, speed, PERIOD, sig)
    return t0 + n * PERIOD, out


def test_the_gas_flows_for_the_preflow_before_the_first_strike_and_travel_waits_for_a_stable_arc() -> None:
    seq = ArcSequence(ARC)
    t, out = _steps(seq, 0.0, 0.098, READY)
    assert out.phase == ArcPhase.PREFLOW and out.gas and not out.arc_start and out.travel == 0
    t, out = _steps(seq, t, 0.01, READY)
    assert out.phase == ArcPhase.STRIKE and out.arc_start and out.wire_feed == ARC.wire_feed and out.travel == 0
    t, out = _steps(seq, t, PERIOD, READY._replace(arc_stable=True))
    assert out.phase == ArcPhase.WELD and out.travel == 1 and seq.failed_starts == 0 and seq.strikes == 1


def test_each_failed_start_takes_one_restrike_and_the_last_one_fails_the_weld() -> None:
    seq = ArcSequence(ARC)
    t, out = _steps(seq, 0.0, 0.1 + 0.2 + 0.004, READY)
    assert out.phase == ArcPhase.PAUSE and not out.arc_start and out.gas and seq.failed_starts == 1
    t, out = _steps(seq, t, 0.06, READY)
    assert out.phase == ArcPhase.STRIKE and seq.restrikes == 1
    t, out = _steps(seq, t, 0.6, READY)  # two more failures: the third failed start is one too many
    assert out.phase == ArcPhase.FAILED and seq.failed_starts == 3 and seq.restrikes == 2
    assert "no stable arc 200 ms after welding start" in seq.reason and "no re-strike left (2 allowed)" in seq.reason
    assert not out.arc_start and out.gas and out.travel == 0  # the gas post-flows
    _, out = _steps(seq, t, ARC.postflow + 0.01, READY)
    assert not out.gas


def test_a_pause_waits_for_the_arm_at_rest() -> None:
    seq = ArcSequence(ARC)
    t, out = _steps(seq, 0.0, 0.1 + 0.2 + 0.004, READY)
    t, out = _steps(seq, t, 0.5, READY, speed=0.01)
    assert out.phase == ArcPhase.PAUSE


def test_an_arc_lost_mid_seam_stops_travel_at_once_backs_off_and_strikes_again() -> None:
    seq = ArcSequence(ARC)
    t, _ = _steps(seq, 0.0, 0.11, READY)
    t, out = _steps(seq, t, 0.5, READY._replace(arc_stable=True), speed=0.008)
    assert out.phase == ArcPhase.WELD and out.travel == 1
    t, out = _steps(seq, t, PERIOD, READY, speed=0.008)
    assert out.phase == ArcPhase.LOST and out.travel == 0 and not out.arc_start and out.gas and seq.arc_losses == 1
    t, out = _steps(seq, t, 0.1, READY, speed=0.004)  # braking: still lost
    assert out.phase == ArcPhase.LOST
    t, out = _steps(seq, t, PERIOD, READY)
    assert out.phase == ArcPhase.BACKOFF and out.travel == -1
    t, out = _steps(seq, t, 0.4, READY, speed=0.004)  # 1.6 mm back: not yet the 2 mm
    assert out.phase == ArcPhase.BACKOFF and out.travel == -1
    t, out = _steps(seq, t, 0.2, READY, speed=0.004)
    assert out.travel == 0  # gone back far enough: wait for rest
    t, out = _steps(seq, t, ARC.restrike_pause + 0.01, READY)
    assert out.phase == ArcPhase.STRIKE and seq.restrikes == 1 and seq.strikes == 2


def test_with_the_retract_policy_an_arc_loss_fails_the_weld() -> None:
    seq = ArcSequence(ARC._replace(arc_loss="retract"))
    t, _ = _steps(seq, 0.0, 0.11, READY)
    t, _ = _steps(seq, t, 0.1, READY._replace(arc_stable=True), speed=0.008)
    t, out = _steps(seq, t, 0.02, READY)
    assert out.phase == ArcPhase.FAILED and "arc_loss = retract" in seq.reason and seq.arc_losses == 1


def test_the_seam_end_fills_the_crater_burns_back_checks_the_wire_and_dwells_on_process_active() -> None:
    seq = ArcSequence(ARC, has_process_active=True)
    burning = READY._replace(arc_stable=True, process_active=True)
    t, _ = _steps(seq, 0.0, 0.11, burning)
    t, out = _steps(seq, t, 0.05, burning, end=True, speed=0.005)  # still moving: no crater yet
    assert out.phase == ArcPhase.WELD
    t, out = _steps(seq, t, PERIOD, burning, end=True)
    assert out.phase == ArcPhase.CRATER and out.arc_start and out.wire_feed == ARC.crater_wire_feed and out.travel == 0
    t, out = _steps(seq, t, ARC.crater + 0.004, burning, end=True)
    assert out.phase == ArcPhase.BURNBACK and not out.arc_start and out.gas
    t, out = _steps(seq, t, ARC.burnback + 0.004, burning, end=True)
    assert out.phase == ArcPhase.POSTFLOW and out.gas
    t, out = _steps(seq, t, ARC.postflow + 0.5, burning, end=True)  # the source still says process active
    assert out.phase == ArcPhase.POSTFLOW
    t, out = _steps(seq, t, PERIOD, burning._replace(process_active=False), end=True)
    assert out.phase == ArcPhase.DONE and not out.gas and not out.arc_start


def test_the_dwell_on_process_active_is_bounded() -> None:
    seq = ArcSequence(ARC._replace(postflow_max=0.3), has_process_active=True)
    burning = READY._replace(arc_stable=True, process_active=True)
    t, _ = _steps(seq, 0.0, 0.11, burning)
    _, out = _steps(seq, t, ARC.crater + ARC.burnback + ARC.postflow + 0.3 + 0.05, burning, end=True)
    assert out.phase == ArcPhase.DONE


def test_a_wire_stuck_after_arc_off_ends_in_stuck_with_the_arc_off() -> None:
    seq = ArcSequence(ARC)
    t, _ = _steps(seq, 0.0, 0.11, READY._replace(arc_stable=True))
    t, _ = _steps(seq, t, ARC.crater + 0.01, READY._replace(arc_stable=True), end=True)
    t, out = _steps(seq, t, ARC.burnback + 0.01, READY._replace(wire_stuck=True), end=True)
    assert out.phase == ArcPhase.STUCK and not out.arc_start and out.travel == 0 and "stuck" in seq.reason


@pytest.mark.parametrize(
    ("sig", "why"),
    [(READY._replace(fault=True), "reported a fault"), (READY._replace(ready=False), "dropped its ready signal")],
)
def test_a_source_fault_or_lost_ready_mid_weld_fails_it_with_the_arc_off(sig: SourceSignals, why: str) -> None:
    seq = ArcSequence(ARC)
    t, _ = _steps(seq, 0.0, 0.11, READY._replace(arc_stable=True))
    _, out = _steps(seq, t, PERIOD, sig)
    assert out.phase == ArcPhase.FAILED and why in seq.reason and not out.arc_start


def test_a_source_that_is_not_ready_fails_the_weld_before_the_gas() -> None:
    seq = ArcSequence(ARC)
    _, out = _steps(seq, 0.0, PERIOD, READY._replace(ready=False))
    assert out.phase == ArcPhase.FAILED and "not ready" in seq.reason


def test_a_heartbeat_that_stops_fails_the_weld() -> None:
    seq = ArcSequence(ARC._replace(heartbeat_timeout=0.5), has_heartbeat=True)
    t, out = 0.0, None
    for k in range(400):  # 0.8 s with a beat every 0.25 s
        out = seq.step(t, True, False, 0.0, PERIOD, READY._replace(arc_stable=True, heartbeat=(k // 125) % 2 == 1))
        t += PERIOD
    assert out.phase == ArcPhase.WELD
    _, out = _steps(seq, t, 0.6, READY._replace(arc_stable=True, heartbeat=True))
    assert out.phase == ArcPhase.FAILED and "heartbeat stopped" in seq.reason


def test_an_abort_switches_the_arc_off_at_once_and_the_gas_after_its_postflow() -> None:
    seq = ArcSequence(ARC)
    t, _ = _steps(seq, 0.0, 0.11, READY._replace(arc_stable=True))
    seq.abort(t, "stopped on request")
    out = seq.output(t)
    assert out.phase == ArcPhase.FAILED and not out.arc_start and out.gas and out.wire_feed == 0.0 and out.travel == 0
    assert not seq.output(t + ARC.postflow + 1e-3).gas


def test_the_plan_keys_round_trip_and_bad_ones_are_refused() -> None:
    assert params_of(plan_keys(ARC)) == ARC
    assert params_of({}) == ArcParams()
    for bad, why in (
        ({"arc_preflow": -1.0}, "arc_preflow"),
        ({"arc_preflow": math.nan}, "arc_preflow"),
        ({"arc_restrikes": 1.5}, "arc_restrikes"),
        ({"arc_restrikes": True}, "arc_restrikes"),
        ({"arc_arc_loss": "ignore"}, "arc_arc_loss"),
    ):
        with pytest.raises(ValueError, match=why):
            params_of(bad)


# -- Algorithm 2 in the core with a source -----------------------------------------------------------------


def test_the_weld_rests_at_the_start_until_the_arc_burns_then_tracks_and_closes_the_crater() -> None:
    source = Source()
    loop = _run(source)
    phases = _phases(loop)
    assert loop.statuses[-1] == ControlStatus.DONE and loop.core.mode == Mode.IDLE
    seen = [p for i, p in enumerate(phases) if i == 0 or p != phases[i - 1]]
    assert seen == [
        ArcPhase.OFF,
        ArcPhase.PREFLOW,
        ArcPhase.STRIKE,
        ArcPhase.WELD,
        ArcPhase.CRATER,
        ArcPhase.BURNBACK,
        ArcPhase.POSTFLOW,
        ArcPhase.DONE,
    ]
    # No travel along the seam while the arc was asked for and not yet burning: the torch came to rest first.
    assert _travel_without_arc(loop, source) < loop.servo_cfg.v_const * PERIOD  # at most one cycle's travel
    x = np.array(loop.positions)[-len(loop.outs) :, 0]
    i_strike = phases.index(ArcPhase.STRIKE)
    i_weld = phases.index(ArcPhase.WELD)
    assert abs(x[i_weld] - x[i_strike]) < 1e-5
    # The torch welded on along the seam to its end, tracking the wall.
    i_crater = phases.index(ArcPhase.CRATER)
    assert x[i_crater] - x[i_weld] > 0.015
    assert abs(loop.torch_error()) < 2e-4
    # At rest from the crater to the end.
    assert np.ptp(x[i_crater:]) < 1e-5
    assert loop.core.arc.failed_starts == 0 and loop.core.arc.arc_losses == 0
    loop.assert_jerk_limited()


def test_a_failed_first_start_is_struck_again_at_the_start_point_and_the_weld_completes() -> None:
    source = Source(fail=(1,))
    loop = _run(source)
    assert loop.statuses[-1] == ControlStatus.DONE
    assert loop.core.arc.failed_starts == 1 and loop.core.arc.restrikes == 1 and source.attempt >= 2
    phases = _phases(loop)
    x = np.array(loop.positions)[-len(loop.outs) :, 0]
    i_restrike = next(i for i in range(1, len(phases)) if phases[i - 1] == ArcPhase.PAUSE and phases[i] == ArcPhase.STRIKE)
    i_weld = phases.index(ArcPhase.WELD)
    # The re-strike scratched forward from the start point, came back to it with the arc on, and welded from there.
    assert ArcPhase.RETURN in phases[i_restrike:i_weld]
    assert 0.0 < np.max(x[i_restrike:i_weld]) - x[i_restrike] <= ARC.scratch
    assert abs(x[i_weld] - x[i_restrike]) < 2e-4
    assert np.ptp(x[phases.index(ArcPhase.STRIKE) : i_restrike]) < 2e-5  # the first start was struck at rest


def test_a_restrike_scratches_at_most_its_distance_then_comes_back_to_where_it_struck() -> None:
    seq = ArcSequence(ARC)
    t, out = _steps(seq, 0.0, 0.1 + 0.2 + 0.004 + 0.06, READY)  # a failed start, then the pause
    assert out.phase == ArcPhase.STRIKE and seq.restrikes == 1 and out.travel == 1 and out.arc_start
    t, out = _steps(seq, t, 0.05, READY, speed=0.02)  # 1 mm of scratch: on
    assert out.phase == ArcPhase.STRIKE and out.travel == 1
    t, out = _steps(seq, t, 0.05 + PERIOD, READY, speed=0.02)  # 2 mm: the scratch's end, held there
    assert out.phase == ArcPhase.STRIKE and out.travel == 0
    t, out = _steps(seq, t, 0.02, READY._replace(arc_stable=True), speed=0.002)  # braking on: 2.04 mm out
    assert out.phase == ArcPhase.RETURN and out.travel == 0 and out.arc_start and out.wire_feed == ARC.wire_feed
    t, out = _steps(seq, t, PERIOD, READY._replace(arc_stable=True))  # at rest: back the 2.04 mm
    assert out.phase == ArcPhase.RETURN and out.travel == -1
    t, out = _steps(seq, t, 0.1, READY._replace(arc_stable=True), speed=0.02)
    assert out.phase == ArcPhase.RETURN and out.travel == -1
    t, out = _steps(seq, t, 0.01, READY._replace(arc_stable=True), speed=0.02)
    assert out.phase == ArcPhase.RETURN and out.travel == 0  # back: now to rest
    t, out = _steps(seq, t, PERIOD, READY._replace(arc_stable=True))
    assert out.phase == ArcPhase.WELD and out.travel == 1
    assert seq.failed_starts == 1 and seq.strikes == 2


def test_a_scratch_that_finds_no_arc_comes_back_with_the_arc_off_before_the_next_strike() -> None:
    seq = ArcSequence(ARC)
    t, out = _steps(seq, 0.0, 0.1 + 0.2 + 0.004 + 0.06, READY)
    t, out = _steps(seq, t, 0.2, READY, speed=0.01)  # scratched out to 2 mm, no arc: timed out
    assert out.phase == ArcPhase.PAUSE and not out.arc_start and out.gas and out.travel == 0 and seq.failed_starts == 2
    t, out = _steps(seq, t, PERIOD, READY)  # at rest 2 mm out: back to the strike point
    assert out.phase == ArcPhase.PAUSE and out.travel == -1
    t, out = _steps(seq, t, 0.1, READY, speed=0.01)  # 1 mm back of 2: still going
    assert out.phase == ArcPhase.PAUSE and out.travel == -1
    t, out = _steps(seq, t, 0.11, READY, speed=0.01)
    assert out.phase == ArcPhase.PAUSE and out.travel == 0
    t, out = _steps(seq, t, PERIOD, READY)  # at rest at the strike point, the pause long over
    assert out.phase == ArcPhase.STRIKE and seq.restrikes == 2


def test_without_a_scratch_distance_a_restrike_strikes_at_rest() -> None:
    seq = ArcSequence(ARC._replace(scratch=0.0))
    t, out = _steps(seq, 0.0, 0.1 + 0.2 + 0.004 + 0.06, READY)
    assert out.phase == ArcPhase.STRIKE and seq.restrikes == 1 and out.travel == 0
    t, out = _steps(seq, t, PERIOD, READY._replace(arc_stable=True))
    assert out.phase == ArcPhase.WELD


def test_no_arc_at_all_ends_the_weld_with_its_reason_and_the_torch_never_left_the_start() -> None:
    source = Source(fail=(1, 2, 3))
    loop = _run(source)
    assert loop.statuses[-1] == ControlStatus.ARC and loop.core.mode == Mode.IDLE
    assert "no re-strike left" in loop.core.controller.reason or "no re-strike left" in loop.outs[-1].event
    phases = _phases(loop)
    x = np.array(loop.positions)[-len(loop.outs) :, 0]
    x_start = x[phases.index(ArcPhase.STRIKE)]
    # Each re-strike scratched out and came back to the start before the next: never farther than the scratch
    # and the arm's stop from it.
    scratched = float(np.max(x[phases.index(ArcPhase.STRIKE) :]) - x_start)
    assert 0.9 * ARC.scratch < scratched < ARC.scratch + 1e-3
    restrikes = [i for i in range(1, len(phases)) if phases[i - 1] == ArcPhase.PAUSE and phases[i] == ArcPhase.STRIKE]
    assert len(restrikes) == 2 and all(abs(x[i] - x_start) < 2e-4 for i in restrikes)
    assert not any(h[3] for h in source.history)


def test_an_arc_loss_mid_seam_stops_backs_off_strikes_again_and_the_weld_completes() -> None:
    source = Source(loss_after=1.0)
    loop = _run(source)
    assert loop.statuses[-1] == ControlStatus.DONE
    arc = loop.core.arc
    assert arc.arc_losses == 1 and arc.restrikes == 1
    phases = _phases(loop)
    i_lost = phases.index(ArcPhase.LOST)
    # The law's travel command is zero from the cycle the loss was seen: the torch's travel only brakes.
    V_r = [o for o in loop.outs[i_lost : i_lost + 3]]
    assert all(o.arc.travel == 0 for o in V_r)
    x = np.array(loop.positions)[-len(loop.outs) :, 0]
    i_back = phases.index(ArcPhase.BACKOFF)
    assert np.ptp(x[i_lost:i_back]) < 5e-4  # the jerk-limited stop from 8 mm/s
    i_strike = i_back + phases[i_back:].index(ArcPhase.STRIKE)
    backed = x[i_back] - x[i_strike]
    assert backed == pytest.approx(ARC.backoff, abs=5e-4)
    assert phases[-1] == ArcPhase.DONE


def test_with_the_retract_policy_an_arc_loss_ends_the_weld_where_it_stopped() -> None:
    source = Source(loss_after=1.0)
    loop = _run(source, arc=ARC._replace(arc_loss="retract"))
    assert loop.statuses[-1] == ControlStatus.ARC
    assert not loop.outs[-1].arc.arc_start and loop.outs[-1].arc.gas  # the gas post-flows
    assert "arc_loss = retract" in loop.outs[-1].event


def test_a_stuck_wire_holds_the_arm_and_refuses_every_motion_until_it_is_cut() -> None:
    source = Source(stuck=True)
    loop = _run(source)
    assert loop.statuses[-1] == ControlStatus.ARC and "wire is stuck" in loop.outs[-1].event
    phases = _phases(loop)
    x = np.array(loop.positions)[-len(loop.outs) :, 0]
    assert np.ptp(x[phases.index(ArcPhase.CRATER) :]) < 1e-5
    # A retract now would drag the torch: refused while the source says wire stuck.
    state = RobotState(loop.t_ns, np.zeros(6), np.zeros(6), loop.T.copy(), np.zeros(6))
    T_up = loop.T.copy()
    T_up[2, 3] += 0.05
    out = loop.core.step(
        CycleInput(
            state, 0.0, 1, loop.latest, 0.01, np.zeros(6), math.inf, move_to(T_up), 99, source=source(loop.t_ns * 1e-9, loop.arc_out)
        )
    )
    assert out.event_id == 99 and out.event_status == ControlStatus.ARC and "wire is stuck" in out.event


def test_a_source_fault_mid_seam_switches_the_arc_off_on_that_cycle_and_stops() -> None:
    source = Source()
    loop = Loop(length=0.03, process=True, source=source, arc=ARC)

    def faulty(t: float, out) -> SourceSignals:
        source.fault = source.arc_time > 0.5
        return source(t, out)

    loop.source = faulty
    loop.run(30.0)
    assert loop.statuses[-1] == ControlStatus.ARC and "fault" in loop.outs[-1].event
    i = next(k for k, o in enumerate(loop.outs) if o.arc.phase == ArcPhase.FAILED)
    assert not loop.outs[i].arc.arc_start and loop.outs[i - 1].arc.arc_start


def test_a_stop_request_mid_weld_switches_the_arc_off_on_that_cycle_and_the_gas_post_flows() -> None:
    source = Source()
    loop = Loop(length=0.06, process=True, source=source, arc=ARC)
    loop.run(30.0, stop_at=7.0)  # the arc burns from about 5 s
    assert loop.statuses[-1] == ControlStatus.STOPPED
    first_stop = next(i for i, o in enumerate(loop.outs) if o.mode == Mode.STOPPING)
    assert loop.outs[first_stop - 1].arc.arc_start and not loop.outs[first_stop].arc.arc_start
    assert all(o.arc.gas and not o.arc.arc_start for o in loop.outs[first_stop:])


def test_a_source_that_is_not_ready_refuses_the_weld() -> None:
    loop = Loop(length=0.03, process=True, source=Source(), arc=ARC)
    state = RobotState(0, np.zeros(6), np.zeros(6), loop.T.copy(), np.zeros(6))
    out = loop.core.step(
        CycleInput(state, 0.0, 1, None, math.inf, np.zeros(6), math.inf, start_servo(loop.plan), 3, source=READY._replace(ready=False))
    )
    assert out.event_id == 3 and out.event_status == ControlStatus.ARC and "not ready" in out.event
    assert loop.core.mode == Mode.IDLE and not out.arc.arc_start and not out.arc.gas


def test_a_torch_collision_stops_the_weld_and_refuses_motion_while_it_is_set() -> None:
    source = Source()
    loop = Loop(length=0.06, process=True, source=source, arc=ARC)
    orig = loop.core.step
    collided = {"on": False}

    def step(inp: CycleInput):
        collided["on"] = collided["on"] or source.arc_time > 0.5
        return orig(inp._replace(collision=collided["on"]))

    loop.core.step = step  # type: ignore[method-assign]
    loop.run(30.0)
    assert loop.statuses[-1] == ControlStatus.COLLISION
    i = next(k for k, o in enumerate(loop.outs) if o.mode == Mode.STOPPING)
    assert not loop.outs[i].arc.arc_start
    state = RobotState(loop.t_ns, np.zeros(6), np.zeros(6), loop.T.copy(), np.zeros(6))
    out = loop.core.step(CycleInput(state, 0.0, 1, loop.latest, 0.01, np.zeros(6), math.inf, move_to(loop.T.copy()), 7, source=READY))
    assert out.event_id == 7 and out.event_status == ControlStatus.COLLISION
