"""The joint move of the motion loop: jerk-limited per joint, straight in joint space, sent as speedJ.

A 6-DOF ruckig in its position interface plans the joints from where they
are (at rest) to ``q_goal`` within the move's speed, acceleration and jerk
per joint; phase synchronisation keeps the joints on the straight line from
start to goal, the path the daemon checked against the cell. Each cycle the
planned joint speeds go out as speedJ exactly as ruckig gives them, so the
limits hold in every cycle with no limiter in between.

The robot integrates the speeds with its own lag, so it ends near the goal,
not on it. The loop is closed at rest: once the reference has ended and the
joints are still, the error is measured and, when it is above the tolerance
but small (a tracking residual, not a robot that did not follow), a short
correction move is planned from the measured joints, again from rest. A move
is DONE when every joint is within ``tolerance`` of the goal and still.

A stop (requested, or a fault found by the core) is ruckig's velocity
interface from the speeds and accelerations last sent down to zero, in joint
space, at the cell's full joint limits, phase-synchronised so the arm brakes
along the checked line: jerk-limited like every other stop.

A joint move starts only from rest (the core refuses it while another
motion runs), so it never has to take over a twist.

Pure: the robot state comes in as values; no clock, no I/O.
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, RuckigError, Synchronization

from celld.motion.limits import JointMoveLimits
from celld.motion.types import ControlStatus, RobotState

Array = NDArray[np.float64]

_ZERO6 = np.zeros(6)
# Commanded speeds and accelerations below these count as zero at the end of a stop.
_REST_SPEED = 1e-9
_REST_ACCEL = 1e-7


class JointMoveParams(NamedTuple):
    """Tuning of the joint move (SI)."""

    settle_speed: float = 0.002  # rad/s, measured joint speed below which the arm counts as still
    settle_cycles: int = 5  # cycles the arm must stay still before the error is measured
    settle_timeout: float = 2.0  # s after a reference ends before the move gives up
    max_corrections: int = 4  # correction moves at rest before the move gives up
    max_residual: float = 0.02  # rad; a larger error at rest means the robot did not follow: a fault


class _Phase(IntEnum):
    TRACK = 0  # sending the planned speeds
    SETTLE = 1  # reference ended; waiting for the joints to be still
    STOP = 2  # braking to zero speed


class JointMove:
    """A jerk-limited joint move to ``q_goal`` (module docstring).

    Parameters
    ----------
    q_goal : np.ndarray, shape (6,)
        Target joints, rad.
    limits : JointMoveLimits
        The cell's joint limits: the move uses ``speed_scale`` of them, a stop all of them.
    period : float
        Control period, s.
    speed_scale : float
        0 < speed_scale <= 1.
    tolerance : float
        Largest joint error at arrival, rad.
    params : JointMoveParams
    """

    name = "joint move"

    def __init__(
        self,
        q_goal: Array,
        limits: JointMoveLimits,
        period: float,
        speed_scale: float = 1.0,
        tolerance: float = 5e-5,
        params: JointMoveParams = JointMoveParams(),
    ) -> None:
        self.q_goal = np.array(q_goal, dtype=np.float64)
        self.limits = limits
        self.move_limits = limits.scaled(speed_scale)
        self.period = period
        self.tolerance = tolerance
        self.params = params
        self.reason = ""
        self.corrections = 0
        self._otg = Ruckig(6, period)
        self._inp = InputParameter(6)
        self._out = OutputParameter(6)
        self._phase = _Phase.TRACK
        self._still = 0
        self._settling = 0
        self._settle_limit = int(math.ceil(params.settle_timeout / period))
        self.qd = _ZERO6.copy()  # the speeds sent last cycle
        self.qdd = _ZERO6.copy()  # and their acceleration

    # -- planning ----------------------------------------------------------------

    def _plan_to_goal(self, q: Array) -> None:
        inp = self._inp
        lim = self.move_limits
        inp.control_interface = ControlInterface.Position
        inp.synchronization = Synchronization.Phase
        inp.max_velocity = [lim.speed] * 6
        inp.max_acceleration = [lim.accel] * 6
        inp.max_jerk = [lim.jerk] * 6
        inp.current_position = [float(x) for x in q]
        inp.current_velocity = [0.0] * 6
        inp.current_acceleration = [0.0] * 6
        inp.target_position = self.q_goal.tolist()
        inp.target_velocity = [0.0] * 6
        inp.target_acceleration = [0.0] * 6
        self._otg.reset()
        self._phase = _Phase.TRACK

    def start(self, state: RobotState, twist: Array, accel: Array) -> None:
        """Plan from the measured joints; the core starts a joint move only from rest."""
        self.reason = ""
        self.corrections = 0
        self.qd = _ZERO6.copy()
        self.qdd = _ZERO6.copy()
        self._plan_to_goal(state.q)

    def _advance(self) -> Result | None:
        try:
            res = self._otg.update(self._inp, self._out)
        except RuckigError as exc:
            self.reason = f"joint move planner refused its input: {exc}"
            return None
        if int(res) < 0:
            self.reason = f"joint move planner failed: {res}"
            return None
        out = self._out
        self.qd = np.array(out.new_velocity)
        self.qdd = np.array(out.new_acceleration)
        out.pass_to_input(self._inp)
        return res

    # -- the cycle ---------------------------------------------------------------

    def step(self, state: RobotState) -> tuple[Array, ControlStatus]:
        """The joint speeds to send this cycle (6,) rad/s, and a status."""
        if self._phase == _Phase.TRACK:
            res = self._advance()
            if res is None:
                self.qd = _ZERO6.copy()
                return self.qd, ControlStatus.FAULT
            if res == Result.Finished:
                self._phase = _Phase.SETTLE
                self._still = self._settling = 0
            return self.qd, ControlStatus.OK
        # SETTLE: the reference has ended at zero speed; wait for the arm.
        self.qd = _ZERO6.copy()
        self.qdd = _ZERO6.copy()
        self._settling += 1
        still = float(np.max(np.abs(state.qd))) <= self.params.settle_speed
        self._still = self._still + 1 if still else 0
        if self._still < self.params.settle_cycles:
            if self._settling > self._settle_limit:
                self.reason = (
                    f"joint move did not come to rest within {self.params.settle_timeout} s of its reference "
                    f"(joint speeds {np.round(state.qd, 4).tolist()} rad/s)"
                )
                return self.qd, ControlStatus.FAULT
            return self.qd, ControlStatus.OK
        err = self.q_goal - state.q
        worst = int(np.argmax(np.abs(err)))
        e = float(abs(err[worst]))
        if e <= self.tolerance:
            return self.qd, ControlStatus.DONE
        if e > self.params.max_residual:
            self.reason = (
                f"the robot did not follow the joint move: joint {worst + 1} rests {math.degrees(e):.3f} deg "
                f"from its goal (a tracking residual is below {math.degrees(self.params.max_residual):.2f} deg)"
            )
            return self.qd, ControlStatus.FAULT
        if self.corrections >= self.params.max_corrections:
            self.reason = (
                f"joint move did not arrive after {self.corrections} corrections: joint {worst + 1} is "
                f"{math.degrees(e):.4f} deg from its goal (tolerance {math.degrees(self.tolerance):.4f} deg)"
            )
            return self.qd, ControlStatus.FAULT
        self.corrections += 1
        self._plan_to_goal(state.q)
        return self.step(state)

    # -- stopping ----------------------------------------------------------------

    def begin_stop(self) -> None:
        """Brake from the speeds and acceleration last sent to zero, at the cell's full joint limits."""
        inp = self._inp
        lim = self.limits
        inp.control_interface = ControlInterface.Velocity
        # On the move's line the speeds and accelerations are proportional:
        # phase synchronisation brakes them along it, on the checked path.
        inp.synchronization = Synchronization.Phase
        inp.max_velocity = [lim.speed] * 6
        # The acceleration last sent lies within the move's (scaled) limits, so within these.
        inp.max_acceleration = [lim.accel] * 6
        inp.max_jerk = [lim.jerk] * 6
        inp.current_velocity = self.qd.tolist()
        inp.current_acceleration = self.qdd.tolist()
        inp.target_velocity = [0.0] * 6
        inp.target_acceleration = [0.0] * 6
        self._otg.reset()
        self._phase = _Phase.STOP

    def stop_step(self) -> tuple[Array, bool]:
        """The joint speeds to send while stopping, and whether the arm is commanded to rest."""
        if self._phase != _Phase.STOP:
            self.begin_stop()
        if self.at_rest():
            self.qd = _ZERO6.copy()
            self.qdd = _ZERO6.copy()
            return self.qd, True
        res = self._advance()
        if res is None:
            # Cannot happen within the limits; brake at once rather than keep moving.
            self.qd = _ZERO6.copy()
            self.qdd = _ZERO6.copy()
            return self.qd, True
        return self.qd, res == Result.Finished and self.at_rest()

    def at_rest(self) -> bool:
        """The speeds and accelerations last sent are zero."""
        return bool(np.all(np.abs(self.qd) <= _REST_SPEED) and np.all(np.abs(self.qdd) <= _REST_ACCEL))
