"""The weld's sequence with its power source, one cycle at a time (pure).

The servo law asks for the arc when the torch reaches the seam's start; what
the power source is told and when the torch may travel is this sequence's::

    OFF ─ask─▶ PREFLOW ─preflow─▶ STRIKE ─arc stable (─▶ RETURN after a scratch)─▶ WELD ─seam end, at rest─▶ CRATER ─▶ BURNBACK ─▶ POSTFLOW ─▶ DONE
                                   │  ▲                  │                                    │
                timeout, restrikes │  │ pause            │ arc lost: travel 0 at once          └ wire stuck ─▶ STUCK
                left               ▼  │                  ▼
                                  PAUSE ◀── at rest ── LOST ──(restrike policy, restrikes left)──▶ BACKOFF ─▶ STRIKE
              no restrikes left, source fault, heartbeat lost, ...  ─▶ FAILED (arc off, gas post-flows)

- PREFLOW: gas on for ``preflow`` before the first strike (not again for a re-strike: the gas still flows).
- STRIKE: ``arc_start`` on; the arc must be stable within ``strike_timeout``.
  A start that times out switches ``arc_start`` off, counts a failed start,
  and after ``restrike_pause`` tries again, at most ``restrikes`` times in all
  over the weld (a failed start and an arc loss each take one).
- A re-strike (a strike after the first) is a scratch start: while the arc is
  not yet stable the torch moves forward along the seam from the point it
  strikes at (``travel`` +1), at most ``scratch``, then holds; once the arc
  is stable it comes back to that point with the arc on (RETURN, ``travel``
  -1) and welds on from there. A scratch that timed out comes back to the
  strike point with the arc off (in PAUSE) before the next strike. The
  scratch is not travel: the weld starts where the torch struck.
- WELD: the torch may travel (``travel`` +1) for as long as the arc is stable.
- LOST: the arc went out mid-seam: ``travel`` is 0 from the same cycle (the
  law's travel command drops at once; the limiter brakes it jerk-limited),
  ``arc_start`` off; once the arm is at rest the policy decides: with the
  ``restrike`` policy and restrikes left, BACKOFF (``travel`` -1 until the torch
  has gone ``backoff`` back along the welded path, then at rest) and a new
  STRIKE at that point; otherwise FAILED, the law stops and the job retracts
  and reports the unwelded length.
- CRATER: at the seam's end, the arm at rest, the arc on with the crater set
  points for ``crater``; then ``arc_start`` off and BURNBACK for ``burnback``
  with the gas still on; then the wire must be free (``wire_stuck`` low) or
  the sequence is STUCK: the arm holds where it is and the weld ends in a
  fault, never dragging the torch; then POSTFLOW: gas for ``postflow``, and
  the arm dwells while the source says ``process_active`` (at most
  ``postflow_max``).
- :meth:`ArcSequence.abort` (any stop that is not the seam's end: a stop
  request, a fault, the robot stopping itself, a hung daemon): ``arc_start``
  off and the set points to zero at once; the gas runs its post-flow and goes
  off (the sequence is stepped while the loop runs, at rest or not).

The source's ``fault`` or a ``ready`` that drops ends the weld (FAILED) from
any phase but OFF and DONE; a wired ``heartbeat`` that stops changing for
``heartbeat_timeout`` does too. The torch collision input is the core's, not
the sequence's (a stop of any motion, weld or not).

No clock, I/O or allocation here: the loop feeds it time and the source's
signals each cycle and writes what it answers.
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple


class ArcPhase(IntEnum):
    OFF = 0
    PREFLOW = 1
    STRIKE = 2
    PAUSE = 3
    WELD = 4
    LOST = 5
    BACKOFF = 6
    CRATER = 7
    BURNBACK = 8
    POSTFLOW = 9
    DONE = 10
    STUCK = 11
    FAILED = 12
    RETURN = 13  # after a scratch start: back to the strike point with the arc on


# The phases after which no more arc comes in this weld.
FINAL = (ArcPhase.DONE, ArcPhase.STUCK, ArcPhase.FAILED)
# arc_loss policies.
ARC_LOSS_POLICIES = ("restrike", "retract")


class ArcParams(NamedTuple):
    """One weld's sequence in SI units, from its weld procedure (:mod:`celld.weld.procedure`)."""

    preflow: float = 0.3  # s
    strike_timeout: float = 0.5  # s
    restrikes: int = 2
    restrike_pause: float = 0.2  # s
    arc_loss: str = "restrike"  # ARC_LOSS_POLICIES
    backoff: float = 0.003  # m
    # How far a re-strike's scratch goes along the seam at most, m (0: re-strikes at rest).
    scratch: float = 0.002
    crater: float = 0.3  # s
    burnback: float = 0.08  # s
    postflow: float = 0.5  # s
    # The arm dwells at most this long on the source's process_active after the post-flow, s.
    postflow_max: float = 3.0
    wire_feed: float = 0.1  # m/s
    voltage: float = 19.0  # V
    crater_wire_feed: float = 0.05  # m/s
    crater_voltage: float = 17.0  # V
    heartbeat_timeout: float = 2.5  # s


class SourceSignals(NamedTuple):
    """The power source's inputs as the loop read them this cycle (False: not wired, except ``ready``)."""

    ready: bool
    arc_stable: bool
    process_active: bool = False
    wire_stuck: bool = False
    fault: bool = False
    heartbeat: bool = False


class ArcOutput(NamedTuple):
    """What to tell the source, and the travel gate for the law: +1 travel, 0 hold, -1 back off."""

    arc_start: bool
    gas: bool
    wire_feed: float  # m/s
    voltage: float  # V
    travel: int
    phase: ArcPhase


# The arm counts as at rest below this TCP speed, m/s.
AT_REST_SPEED = 1e-3


class ArcSequence:
    """One weld's arc sequence (module docstring).

    Parameters
    ----------
    params : ArcParams
    has_process_active, has_heartbeat : bool
        Whether those inputs are wired (without them post-flow is timed alone
        and no heartbeat is watched).
    """

    def __init__(self, params: ArcParams, has_process_active: bool = False, has_heartbeat: bool = False) -> None:
        self.p = params
        self._has_active = has_process_active
        self._has_beat = has_heartbeat
        self.phase = ArcPhase.OFF
        self.reason = ""  # why the sequence FAILED or is STUCK
        self.failed_starts = 0
        self.restrikes = 0  # strikes after the first
        self.arc_losses = 0
        self.strikes = 0
        self._since = math.nan  # when the phase began, s
        # Where the torch is along the seam since the weld began (m): its speed along the direction it was last
        # told to travel in (a braking arm goes on the same way; the gate turns round only at rest, _turn).
        self._s = 0.0
        self._dir = 0
        self._moving = False
        self._backoff_to = 0.0  # where BACKOFF goes back to
        self._strike_at: float | None = None  # where a scratch start struck (None: no scratch to come back from)
        self._beat = False
        self._beat_since = math.nan
        self._gas_until = -math.inf  # the gas flows until then after an abort, s
        self._gas_open = False

    @property
    def travel_allowed(self) -> bool:
        return self.phase == ArcPhase.WELD

    @property
    def active(self) -> bool:
        """The weld's sequence has begun and not ended."""
        return self.phase not in (ArcPhase.OFF, *FINAL)

    @property
    def _to_undo(self) -> bool:
        """The torch is ahead of the point a scratch start struck at."""
        return self._strike_at is not None and self._s > self._strike_at

    def _enter(self, phase: ArcPhase, t: float) -> None:
        self.phase = phase
        self._since = t

    def _fail(self, t: float, reason: str) -> None:
        self.reason = reason
        self._gas_until = t + self.p.postflow
        self._enter(ArcPhase.FAILED, t)

    def abort(self, t: float, reason: str) -> None:
        """A stop that is not the seam's end: arc off at once, gas through its post-flow (module docstring)."""
        if self.active:
            self._fail(t, reason)

    def _strike_or_fail(self, t: float, why: str) -> None:
        if self.failed_starts + self.arc_losses > self.p.restrikes:
            self._fail(t, f"{why}: no re-strike left ({self.p.restrikes} allowed)")
        else:
            self._enter(ArcPhase.PAUSE, t)

    def step(self, t: float, want: bool, end: bool, speed: float, dt: float, sig: SourceSignals) -> ArcOutput:
        """One cycle at time ``t`` (s).

        ``want``: the law asks for the arc (the torch is at the seam's start or on it); ``end``: the law has
        finished the seam; ``speed``: the TCP's measured speed, m/s; ``dt``: s since the last cycle.
        """
        ph = self.phase
        p = self.p
        if ph == ArcPhase.OFF:
            if want:
                if not sig.ready or sig.fault:
                    self._fail(t, "the power source is not ready" if not sig.ready else "the power source reports a fault")
                else:
                    self._enter(ArcPhase.PREFLOW, t)
                    self._beat, self._beat_since = sig.heartbeat, t
        elif self.active:
            if sig.fault:
                self._fail(t, f"the power source reported a fault in {ph.name.lower()}")
            elif not sig.ready:
                self._fail(t, f"the power source dropped its ready signal in {ph.name.lower()}")
            elif self._has_beat:
                if sig.heartbeat != self._beat:
                    self._beat, self._beat_since = sig.heartbeat, t
                elif t - self._beat_since > p.heartbeat_timeout:
                    self._fail(t, f"the power source's heartbeat stopped {t - self._beat_since:.1f} s ago")
        ph = self.phase
        age = t - self._since
        self._moving = speed >= AT_REST_SPEED
        self._s += self._dir * speed * dt
        if ph == ArcPhase.PREFLOW and age >= p.preflow:
            self.strikes += 1
            self._enter(ArcPhase.STRIKE, t)
        elif ph == ArcPhase.STRIKE:
            if sig.arc_stable:
                self._enter(ArcPhase.WELD if self._strike_at is None else ArcPhase.RETURN, t)
            elif age >= p.strike_timeout:
                self.failed_starts += 1
                self._strike_or_fail(t, f"no stable arc {p.strike_timeout * 1e3:.0f} ms after welding start")
        elif ph == ArcPhase.PAUSE and age >= p.restrike_pause and speed < AT_REST_SPEED and not self._to_undo:
            self.strikes += 1
            self.restrikes += 1
            # A scratch start from where the torch rests now.
            self._strike_at = self._s if p.scratch > 0.0 else None
            self._enter(ArcPhase.STRIKE, t)
        elif ph == ArcPhase.RETURN:
            if not sig.arc_stable:
                self.arc_losses += 1
                self._strike_at = None
                self._enter(ArcPhase.LOST, t)
            elif not self._to_undo and speed < AT_REST_SPEED:
                self._strike_at = None
                self._enter(ArcPhase.WELD, t)
        elif ph == ArcPhase.WELD:
            if end and speed < AT_REST_SPEED:
                self._enter(ArcPhase.CRATER, t)
            elif not sig.arc_stable:
                self.arc_losses += 1
                self._enter(ArcPhase.LOST, t)
        elif ph == ArcPhase.LOST and speed < AT_REST_SPEED:
            if end:
                # Lost while the arm was coming to rest at the seam's end: nothing left to weld.
                self._enter(ArcPhase.BURNBACK, t)
            elif p.arc_loss != "restrike":
                self._fail(t, "the arc went out mid-seam (arc_loss = retract)")
            elif self.failed_starts + self.arc_losses > p.restrikes:
                self._fail(t, f"the arc went out mid-seam: no re-strike left ({p.restrikes} allowed)")
            else:
                self._backoff_to = self._s - p.backoff
                self._enter(ArcPhase.BACKOFF, t)
        elif ph == ArcPhase.BACKOFF:
            if self._s <= self._backoff_to and speed < AT_REST_SPEED:
                self._enter(ArcPhase.PAUSE, t)
        elif ph == ArcPhase.CRATER and age >= p.crater:
            self._enter(ArcPhase.BURNBACK, t)
        elif ph == ArcPhase.BURNBACK and age >= p.burnback:
            if sig.wire_stuck:
                self.reason = "the wire is stuck in the pool after arc off: the arm holds where it is; cut the wire"
                self._gas_until = t + p.postflow
                self._enter(ArcPhase.STUCK, t)
            else:
                self._enter(ArcPhase.POSTFLOW, t)
        elif (
            ph == ArcPhase.POSTFLOW
            and age >= p.postflow
            and (not (self._has_active and sig.process_active) or age >= p.postflow + p.postflow_max)
        ):
            self._gas_until = -math.inf
            self._enter(ArcPhase.DONE, t)
        out = self.output(t)
        if out.travel:
            self._dir = out.travel
        return out

    def output(self, t: float) -> ArcOutput:
        """What the source is told and the travel gate in the current phase at ``t`` (s); no transition."""
        ph = self.phase
        p = self.p
        back = self._to_undo
        if ph == ArcPhase.WELD:  # entered at rest
            return ArcOutput(True, True, p.wire_feed, p.voltage, 1, ph)
        if ph == ArcPhase.STRIKE:
            scratch = self._strike_at is not None and self._s - self._strike_at < p.scratch
            return ArcOutput(True, True, p.wire_feed, p.voltage, self._turn(1) if scratch else 0, ph)
        if ph == ArcPhase.RETURN:
            return ArcOutput(True, True, p.wire_feed, p.voltage, self._turn(-1) if back else 0, ph)
        if ph == ArcPhase.CRATER:
            return ArcOutput(True, True, p.crater_wire_feed, p.crater_voltage, 0, ph)
        gas = ph in (ArcPhase.PREFLOW, ArcPhase.PAUSE, ArcPhase.LOST, ArcPhase.BACKOFF, ArcPhase.BURNBACK, ArcPhase.POSTFLOW)
        gas = gas or t < self._gas_until
        backing = (ph == ArcPhase.BACKOFF and self._s > self._backoff_to) or (ph == ArcPhase.PAUSE and back)
        return ArcOutput(False, gas, 0.0, 0.0, self._turn(-1) if backing else 0, ph)

    def _turn(self, travel: int) -> int:
        """``travel``, or 0 (hold) while the arm still moves the other way: the gate turns round at rest."""
        return 0 if self._moving and self._dir == -travel else travel


def params_of(plan: dict[str, float | int | bool | str]) -> ArcParams:
    """The sequence's parameters from a servo plan's ``arc_*`` keys (defaults for those it lacks).

    Raises
    ------
    ValueError
        A value of the wrong type, not finite, negative, or an unknown arc-loss policy.
    """
    kwargs: dict[str, float | int | str] = {}
    for name, default in ArcParams._field_defaults.items():
        key = f"arc_{name}"
        if key not in plan:
            continue
        v = plan[key]
        if isinstance(default, str):
            if v not in ARC_LOSS_POLICIES:
                raise ValueError(f"{key}: expected one of {', '.join(ARC_LOSS_POLICIES)}, got {v!r}")
            kwargs[name] = str(v)
        elif isinstance(default, int):
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 10:
                raise ValueError(f"{key}: expected an integer 0-10, got {v!r}")
            kwargs[name] = v
        else:
            if isinstance(v, (bool, str)) or not math.isfinite(float(v)) or float(v) < 0.0:
                raise ValueError(f"{key}: expected a finite number >= 0, got {v!r}")
            kwargs[name] = float(v)
    return ArcParams(**kwargs)  # type: ignore[arg-type]


def plan_keys(params: ArcParams) -> dict[str, float | int | bool | str]:
    """``params`` as a servo plan's ``arc_*`` keys (the inverse of :func:`params_of`)."""
    return {f"arc_{k}": v for k, v in params._asdict().items()}
