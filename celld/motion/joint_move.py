"""The joint move of the motion loop: jerk-limited per joint, straight in joint space, sent as speedJ.

A 6-DOF ruckig in its position interface plans the joints from where they
are (at rest) to ``q_goal`` within the move's speed, acceleration and jerk
per joint; phase synchronisation keeps the joints on the straight line from
start to goal, the path the daemon checked against the cell. The whole
trajectory is computed once, at the start, and each cycle sends its joint
speeds at the cycle's own time (the robot state's stamp; the trajectory
starts when the cycle before it sent its rest) exactly as ruckig gives them,
so the limits hold with no limiter in between.

The reference is a function of time, not of the number of cycles: the robot
integrates whatever speed it was last sent for as long as it holds it, so a
cycle that comes late (a loaded machine, a command that waited on the link)
must not stretch the plan, or the arm runs past its goal by every delay.
Sampled by the clock, a late cycle sends the speed the plan has by then, and
the arm ends where the plan ends up to the small difference between holding
a speed and following the plan over the delay.

The robot integrates the speeds with its own lag, so it ends near the goal,
not on it. The loop is closed at rest: once the reference has ended and the
joints are still, the error is measured and, when it is above the tolerance
but small (a tracking residual, not a robot that did not follow), a short
correction move is planned from the measured joints, again from rest. A move
is DONE when every joint is within ``tolerance`` of the goal and still.

A stop (requested, or a fault found by the core) is ruckig's velocity
interface from the speeds and accelerations last sent down to zero, in joint
space, at the cell's full joint limits, phase-synchronised so the arm brakes
along the checked line: jerk-limited like every other stop, and sampled by
the clock from the moment the last speeds went out.

A joint move starts only from rest (the core refuses it while another
motion runs), so it never has to take over a twist.

Pure: the robot state and the cycle's time come in as values; no clock, no I/O.
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from ruckig import ControlInterface, InputParameter, Ruckig, RuckigError, Synchronization, Trajectory

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
    FAILED = 3  # the planner refused the move


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
        self._otg = Ruckig(6)
        self._inp = InputParameter(6)
        self._traj = Trajectory(6)
        self._t0_ns = 0  # when the trajectory starts: when the speeds before its first went out
        self._last_ns = 0  # when the speeds last sent went out
        self._phase = _Phase.TRACK
        self._still = 0
        self._settle_ns = 0  # when the reference ended
        self.qd = _ZERO6.copy()  # the speeds sent last cycle
        self.qdd = _ZERO6.copy()  # and their acceleration

    # -- planning ----------------------------------------------------------------

    def _calculate(self, inp: InputParameter, t_ns: int) -> bool:
        """Plan ``inp`` as the trajectory sampled from ``t_ns``; False (with :attr:`reason`) if ruckig refuses."""
        try:
            res = self._otg.calculate(inp, self._traj)
        except RuckigError as exc:
            self.reason = f"joint move planner refused its input: {exc}"
            return False
        if int(res) < 0:
            self.reason = f"joint move planner failed: {res}"
            return False
        self._t0_ns = t_ns
        return True

    def _plan_to_goal(self, q: Array, t_ns: int) -> bool:
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
        self._phase = _Phase.TRACK
        return self._calculate(inp, t_ns)

    def _sample(self, t_ns: int) -> bool:
        """Take the trajectory's speeds at ``t_ns`` as the ones sent now; True once it has ended."""
        t = (t_ns - self._t0_ns) * 1e-9
        _, v, a = self._traj.at_time(min(t, self._traj.duration))
        self.qd = np.array(v)
        self.qdd = np.array(a)
        self._last_ns = t_ns
        return t >= self._traj.duration

    def start(self, state: RobotState, twist: Array, accel: Array, since: float | None = None) -> None:
        """Plan from the measured joints; the core starts a joint move only from rest.

        ``since`` is the time (s) since the last cycle sent something (one period by default): the
        trajectory starts then, from the rest it commanded, so this cycle's speeds follow on from it
        over the time that really passed (the monitor differences them over it).
        """
        self.reason = ""
        self.corrections = 0
        self.qd = _ZERO6.copy()
        self.qdd = _ZERO6.copy()
        self._last_ns = state.stamp_ns - round((self.period if since is None else since) * 1e9)
        if not self._plan_to_goal(state.q, self._last_ns):
            self._phase = _Phase.FAILED

    # -- the cycle ---------------------------------------------------------------

    def step(self, state: RobotState) -> tuple[Array, ControlStatus]:
        """The joint speeds to send this cycle (6,) rad/s, and a status."""
        if self._phase == _Phase.FAILED:
            self.qd = _ZERO6.copy()
            self.qdd = _ZERO6.copy()
            return self.qd, ControlStatus.FAULT
        if self._phase == _Phase.TRACK:
            if self._sample(state.stamp_ns):
                self._phase = _Phase.SETTLE
                self._still = 0
                self._settle_ns = state.stamp_ns
            return self.qd, ControlStatus.OK
        # SETTLE: the reference has ended at zero speed; wait for the arm.
        self.qd = _ZERO6.copy()
        self.qdd = _ZERO6.copy()
        before, self._last_ns = self._last_ns, state.stamp_ns
        still = float(np.max(np.abs(state.qd))) <= self.params.settle_speed
        self._still = self._still + 1 if still else 0
        if self._still < self.params.settle_cycles:
            if (state.stamp_ns - self._settle_ns) * 1e-9 > self.params.settle_timeout:
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
        # From the rest the last cycle sent, as at the start.
        self._last_ns = before
        if not self._plan_to_goal(state.q, before):
            self._phase = _Phase.FAILED
            return self.qd, ControlStatus.FAULT
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
        self._phase = _Phase.STOP
        # The brake starts from the speeds last sent, at the time they went out.
        if self.at_rest() or not self._calculate(inp, self._last_ns):
            # Cannot fail within the limits; brake at once rather than keep moving.
            self.qd = _ZERO6.copy()
            self.qdd = _ZERO6.copy()

    def stop_step(self, t_ns: int) -> tuple[Array, bool]:
        """The joint speeds to send while stopping at cycle time ``t_ns``, and whether the arm is commanded to rest."""
        if self._phase != _Phase.STOP:
            self.begin_stop()
        if self.at_rest():
            self.qd = _ZERO6.copy()
            self.qdd = _ZERO6.copy()
            return self.qd, True
        ended = self._sample(t_ns)
        return self.qd, ended and self.at_rest()

    def at_rest(self) -> bool:
        """The speeds and accelerations last sent are zero."""
        return bool(np.all(np.abs(self.qd) <= _REST_SPEED) and np.all(np.abs(self.qdd) <= _REST_ACCEL))
