"""Joint moves in the core: jerk-limited per joint, straight in joint space, closed at rest, stopped in joint space."""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld.config import MotionLimits
from celld.motion.commands import move_joints, stream
from celld.motion.core import Action, CoreParams, CycleInput, Mode, MotionCore
from celld.motion.limits import CartesianLimits, JointMoveLimits
from celld.motion.types import ControlStatus, RobotState
from celld.robot import kinematics as kin
from tests.motion.plant import JointPlant, KinematicPlant

PERIOD = 0.002
JOINT_LIMITS = JointMoveLimits(speed=1.0, accel=2.0, jerk=20.0)
Q0 = np.array([0.2, -1.6, 1.7, -1.7, -1.57, 0.1])
Q1 = np.array([-0.4, -1.2, 1.2, -1.6, -1.3, 0.9])
PROTECTIVE = 1 << 2


def _core() -> MotionCore:
    params = CoreParams(
        CartesianLimits.from_config(MotionLimits()),
        PERIOD,
        (-1.5, -1.5, -0.5),
        (1.5, 1.5, 1.5),
        state_stale=3 * PERIOD,
        tactile_stale=0.1,
        joint_limits=JOINT_LIMITS,
    )
    return MotionCore(params)


def _run(core: MotionCore, plant: JointPlant, cycles: int, first: dict, at: dict[int, dict] | None = None):
    outs = []
    for k in range(cycles):
        kw = first if k == 0 else (at or {}).get(k, {})
        out = core.step(plant.cycle_input(**kw))
        plant.apply(out)
        outs.append(out)
        if k > 0 and out.mode == Mode.IDLE and not (at and any(j > k for j in at)):
            break
    return outs


def _peaks(sent: list[np.ndarray]) -> tuple[float, float, float]:
    """Largest joint speed, acceleration and jerk of the speeds sent (finite differences from rest)."""
    v = np.vstack([np.zeros((2, 6)), np.array(sent)])
    a = np.diff(v, axis=0) / PERIOD
    j = np.diff(v, n=2, axis=0) / PERIOD**2
    return float(np.abs(v).max()), float(np.abs(a).max()), float(np.abs(j).max())


def test_a_joint_move_lands_within_a_hundredth_of_a_degree_straight_and_within_the_joint_limits() -> None:
    core = _core()
    # A robot that does 0.4 % less than it is told on every joint: the move corrects at rest.
    plant = JointPlant(Q0, PERIOD, latency_cycles=2, follow=np.full(6, 0.996))
    outs = _run(core, plant, 6000, {"command": move_joints(Q1), "command_id": 1})
    assert outs[-1].mode == Mode.IDLE, "the move never ended"
    assert outs[-1].status == ControlStatus.DONE and outs[-1].command_id == 1 and not outs[-1].event
    assert np.degrees(np.abs(plant.q - Q1)).max() < 0.01
    assert {o.action for o in outs} == {Action.SPEED_J}, "a joint move sends speedJ only"
    np.testing.assert_array_equal(outs[-1].twist, np.zeros(6))
    speed, accel, jerk = _peaks(plant.sent)
    assert speed <= JOINT_LIMITS.speed * (1 + 1e-9) and speed > 0.9 * JOINT_LIMITS.speed
    assert accel <= JOINT_LIMITS.accel * (1 + 1e-6) and jerk <= JOINT_LIMITS.jerk * (1 + 1e-6)
    assert all(o.faults == 0 for o in outs)
    # Straight in joint space (the path the daemon checked): every commanded
    # speed vector is parallel to the move while the reference runs.
    u = (Q1 - Q0) / np.linalg.norm(Q1 - Q0)
    for qd in plant.sent:
        n = float(np.linalg.norm(qd))
        if n > 1e-3:
            assert np.linalg.norm(qd / n - u) < 1e-6 or np.linalg.norm(qd / n + u) < 1e-6
    # After the end only watchdog kicks are sent.
    core_out = core.step(plant.cycle_input())
    assert core_out.action == Action.KICK and core_out.mode == Mode.IDLE


def test_late_cycles_do_not_stretch_the_move_past_its_goal() -> None:
    # A loaded machine: one cycle in seven comes 30 ms late, and the robot holds the speeds it was
    # sent all that time (as a UR holds speedJ). A plan stepped once per cycle fell behind the
    # clock by every delay and the arm ran tens of degrees past its goal; sampled by the clock it lands.
    core = _core()
    plant = JointPlant(Q0, PERIOD, latency_cycles=2)
    outs = []
    for k in range(6000):
        out = core.step(plant.cycle_input(**({"command": move_joints(Q1), "command_id": 1} if k == 0 else {})))
        plant.apply(out, periods=15 if k % 7 == 3 else 1)
        outs.append(out)
        if k > 0 and out.mode == Mode.IDLE:
            break
    assert outs[-1].status == ControlStatus.DONE, outs[-1].event
    assert np.degrees(np.abs(plant.q - Q1)).max() < 0.01
    # The speeds sent keep the limits over the times they went out: no fault from the sequence monitor.
    assert all(o.faults == 0 for o in outs)
    assert max(float(np.abs(o.twist).max()) for o in outs) <= JOINT_LIMITS.speed * (1 + 1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cycles_that_come_early_or_late_keep_the_limits_to_the_end_of_the_move(seed: int) -> None:
    # A loop keeps its phase: after a late cycle the next comes early, as little as tens of microseconds
    # after it. Every speed sent, corrections at rest included, follows on from the last over the time
    # that really passed, so the monitor sees the limits kept; and the move lands.
    rng = np.random.default_rng(seed)
    core = _core()
    q, pending, t = Q0.copy(), [np.zeros(6), np.zeros(6)], 10**9
    out = None
    for k in range(30000):
        state = RobotState(t, q.copy(), pending[0].copy(), kin.forward(q), np.zeros(6))
        kw = {"command": move_joints(Q1, speed_scale=0.4), "command_id": 1} if k == 3 else {}
        out = core.step(CycleInput(state, 0.0, 1, None, math.inf, np.zeros(6), math.inf, **kw))
        assert out.faults == 0, (k, out.faults)
        dt = float(rng.choice([rng.uniform(1e-5, 4e-4), rng.uniform(0.0019, 0.0021), rng.uniform(0.003, 0.03)], p=[0.1, 0.8, 0.1]))
        pending.append(out.twist.copy() if out.action == Action.SPEED_J else pending[-1])
        q = q + pending.pop(0) * dt
        t += round(dt * 1e9)
        if k > 3 and out.mode == Mode.IDLE:
            break
    assert out is not None and out.status == ControlStatus.DONE, out
    assert np.degrees(np.abs(q - Q1)).max() < 0.01


def test_speed_scale_slows_every_joint() -> None:
    core = _core()
    plant = JointPlant(Q0, PERIOD)
    outs = _run(core, plant, 12000, {"command": move_joints(Q1, speed_scale=0.25), "command_id": 1})
    assert outs[-1].status == ControlStatus.DONE
    speed, accel, _ = _peaks(plant.sent)
    assert speed <= 0.25 * JOINT_LIMITS.speed * (1 + 1e-9) and accel <= 0.25 * JOINT_LIMITS.accel * (1 + 1e-6)


def test_a_stop_request_brakes_in_joint_space_jerk_limited() -> None:
    core = _core()
    plant = JointPlant(Q0, PERIOD)
    outs = _run(core, plant, 3000, {"command": move_joints(Q1), "command_id": 5}, at={300: {"stop": True}})
    moving = outs[299]
    assert moving.mode == Mode.ACTIVE and np.abs(moving.twist).max() > 0.5
    idle = next(o for o in outs[300:] if o.mode == Mode.IDLE)
    assert idle.status == ControlStatus.STOPPED and idle.event_id == 5 and "stopped on request" in idle.event
    _, accel, jerk = _peaks(plant.sent)
    assert accel <= JOINT_LIMITS.accel * (1 + 1e-6) and jerk <= JOINT_LIMITS.jerk * (1 + 1e-6)
    # The brake stays on the move's line in joint space (the checked path).
    u = (Q1 - Q0) / np.linalg.norm(Q1 - Q0)
    for qd in plant.sent:
        n = float(np.linalg.norm(qd))
        if n > 1e-3:
            assert np.linalg.norm(qd / n - u) < 1e-6
    for _ in range(3):  # the plant's latency
        plant.apply(core.step(plant.cycle_input()))
    assert np.abs(plant.qd).max() < 1e-9, "at rest after the stop"
    assert np.degrees(np.abs(plant.q - Q1)).max() > 1.0, "the stop ended the move short of its goal"


def test_a_joint_that_does_not_follow_is_a_fault_not_a_correction() -> None:
    core = _core()
    plant = JointPlant(Q0, PERIOD, follow=np.array([1.0, 1.0, 0.0, 1.0, 1.0, 1.0]))
    outs = _run(core, plant, 6000, {"command": move_joints(Q1), "command_id": 2})
    end = outs[-1]
    assert end.mode == Mode.IDLE and end.status == ControlStatus.FAULT
    assert "did not follow the joint move: joint 3 rests" in end.event


def test_commands_during_a_joint_move_are_refused_and_a_joint_move_waits_for_rest() -> None:
    core = _core()
    plant = JointPlant(Q0, PERIOD)
    _run(core, plant, 100, {"command": move_joints(Q1), "command_id": 1}, at={99: {}})
    out = core.step(plant.cycle_input(command=stream(), command_id=2))
    assert out.mode == Mode.ACTIVE and out.command_id == 1
    assert out.event_id == 2 and out.event_status == ControlStatus.BAD_COMMAND and "joint move (command 1)" in out.event

    # A joint move while a Cartesian motion runs is refused; the motion goes on.
    core = _core()
    cart = KinematicPlant(kin.forward(Q0), PERIOD)
    setpoint = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])
    core.step(cart.cycle_input(command=stream(), command_id=1, setpoint=setpoint, setpoint_age=0.0))
    out = core.step(cart.cycle_input(command=move_joints(Q1), command_id=2, setpoint=setpoint, setpoint_age=0.0))
    assert out.mode == Mode.ACTIVE and out.command_id == 1 and out.action == Action.SPEED
    assert out.event_id == 2 and "a joint move starts from rest" in out.event


def test_a_protective_stop_during_a_joint_move_ends_it_at_once() -> None:
    core = _core()
    plant = JointPlant(Q0, PERIOD)
    _run(core, plant, 300, {"command": move_joints(Q1), "command_id": 4}, at={299: {}})
    out = core.step(plant.cycle_input(safety_bits=PROTECTIVE))
    assert out.mode == Mode.IDLE and out.action == Action.KICK and out.status == ControlStatus.SAFETY
    assert out.event_id == 4
    # The next joint move starts cleanly once the robot is back.
    outs = _run(core, JointPlant(plant.q, PERIOD), 6000, {"command": move_joints(Q0), "command_id": 6})
    assert outs[-1].status == ControlStatus.DONE


def test_a_joint_move_heading_out_of_the_workspace_box_stops() -> None:
    params = CoreParams(
        CartesianLimits.from_config(MotionLimits()),
        PERIOD,
        (-1.5, -1.5, -0.5),
        (1.5, 1.5, 1.5),
        state_stale=3 * PERIOD,
        tactile_stale=0.1,
        joint_limits=JOINT_LIMITS,
    )
    # The TCP's y grows monotonically along this move (-0.305 m to 0.168 m):
    # put a wall of the box half-way.
    start_y, goal_y = float(kin.forward(Q0)[1, 3]), float(kin.forward(Q1)[1, 3])
    hi = list(params.workspace_max)
    hi[1] = 0.5 * (start_y + goal_y)
    core = MotionCore(params._replace(workspace_max=tuple(hi)))
    plant = JointPlant(Q0, PERIOD)
    # At 0.3 of the joint limits the TCP keeps under the Cartesian 0.25 m/s,
    # as the daemon scales every joint move (daemon/planning.py).
    outs = _run(core, plant, 6000, {"command": move_joints(Q1, speed_scale=0.3), "command_id": 3})
    end = outs[-1]
    assert end.mode == Mode.IDLE and end.status == ControlStatus.WORKSPACE
    # The guard predicts the stop with the Cartesian limits from the measured
    # TCP twist; the joint-space stop ends inside the wall.
    y = float(kin.forward(plant.q)[1, 3])
    assert hi[1] - 0.03 < y < hi[1], (y, hi[1])


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_a_move_to_the_joints_it_is_at_is_done_at_once(scale: float) -> None:
    core = _core()
    plant = JointPlant(Q0, PERIOD)
    outs = _run(core, plant, 200, {"command": move_joints(Q0, speed_scale=scale), "command_id": 1})
    assert outs[-1].status == ControlStatus.DONE and len(outs) < 20
    assert math.isclose(float(np.abs(plant.q - Q0).max()), 0.0, abs_tol=1e-12)
