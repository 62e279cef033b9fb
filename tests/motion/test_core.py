"""The per-cycle state machine: moves, streaming, stops, faults and refusals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.config import MotionLimits
from celld.motion.commands import move_to, start_servo, stream
from celld.motion.core import Action, CoreParams, Mode, MotionCore
from celld.motion.limits import CartesianLimits, sequence_peaks
from celld.motion.safety import Fault
from celld.motion.types import NO_TELEMETRY, ControlStatus, RobotState, ServoInput, ServoPlan, ServoTelemetry
from celld.se3 import error, from_ur_pose
from celld.tactile.sample import ContactState, TactileSample
from tests.motion.laws import Probe, make_probe
from tests.motion.plant import KinematicPlant, run

LIMITS = CartesianLimits.from_config(MotionLimits())
PERIOD = 0.002
T0 = from_ur_pose([0.5, 0.1, 0.4, 3.1, 0.1, 0.0])
# UR safety_status_bits: normal mode; protective stop.
NORMAL = 1
PROTECTIVE = 1 << 2


def _core() -> MotionCore:
    params = CoreParams(LIMITS, PERIOD, (-1.0, -1.0, 0.02), (1.0, 1.0, 1.2), state_stale=3 * PERIOD, tactile_stale=0.1)
    return MotionCore(params)


def _peaks_ok(outs) -> bool:
    tw = np.array([o.twist for o in outs])
    return max(sequence_peaks(tw, PERIOD, initial=np.zeros((2, 6))).ratios(LIMITS)) <= 1 + 1e-6


def _peaks_ok_over(outs, spacing) -> bool:
    """The limits held over the times the twists were shaped over (``spacing``: each one's time since the one before)."""
    tw = np.array([o.twist for o in outs])
    return max(sequence_peaks(tw, PERIOD, initial=np.zeros((2, 6)), spacing=np.array(spacing)).ratios(LIMITS)) <= 1 + 1e-6


def test_move_arrives_within_tolerance_straight_and_within_limits() -> None:
    core = _core()
    plant = KinematicPlant(T0, PERIOD, latency_cycles=2)
    goal = from_ur_pose([0.3, -0.2, 0.5, 2.9, 0.3, 0.2])
    outs = run(core, plant, 1600, command=move_to(goal), command_id=1)
    idle = [i for i, o in enumerate(outs) if o.mode == Mode.IDLE]
    assert idle, "the move never ended"
    assert outs[idle[0]].status == ControlStatus.DONE and outs[idle[0]].command_id == 1
    dt, dr = error(plant.T, goal)
    assert dt < 1e-4 and dr < 1e-3
    assert _peaks_ok(outs)
    # Straight: the TCP never strays from the segment start-goal by more than a millimetre.
    p0, p1 = T0[:3, 3], goal[:3, 3]
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    # Re-run to sample the path.
    core, plant = _core(), KinematicPlant(T0, PERIOD, latency_cycles=2)
    worst = 0.0
    for k in range(idle[0]):
        out = core.step(plant.cycle_input(**({"command": move_to(goal), "command_id": 1} if k == 0 else {})))
        plant.apply(out)
        d = plant.T[:3, 3] - p0
        worst = max(worst, float(np.linalg.norm(d - (d @ u) * u)))
    assert worst < 1e-3
    # After the end only watchdog kicks are sent.
    assert all(o.action == Action.KICK for o in outs[idle[0] + 1 :])


@pytest.mark.parametrize("late_periods, past_bound", [(3, 0.5e-3), (15, 10e-3)])
def test_a_move_whose_cycles_come_late_still_lands_on_its_goal(late_periods: int, past_bound: float) -> None:
    # One cycle in seven comes late (4 or 28 ms more), and the robot holds the twist it was sent all
    # that time. A reference and a limiter stepped once per cycle fell behind the clock: the TCP ran
    # 0.58 m past this goal and never settled. Over the cycles' own times it lands; what it overshoots
    # on the way is what the robot travels on one held twist.
    core = _core()
    plant = KinematicPlant(T0, PERIOD, latency_cycles=2)
    goal = from_ur_pose([0.3, -0.2, 0.5, 2.9, 0.3, 0.2])
    p0 = T0[:3, 3].copy()
    u = (goal[:3, 3] - p0) / np.linalg.norm(goal[:3, 3] - p0)
    length = float(np.linalg.norm(goal[:3, 3] - p0))
    past, outs = 0.0, []
    for k in range(6000):
        out = core.step(plant.cycle_input(**({"command": move_to(goal), "command_id": 1} if k == 0 else {})))
        for _ in range(late_periods if k % 7 == 3 else 1):
            plant.apply(out)
        past = max(past, float((plant.T[:3, 3] - p0) @ u) - length)
        outs.append(out)
        if k > 0 and out.mode == Mode.IDLE:
            break
    assert outs[-1].status == ControlStatus.DONE, outs[-1].event
    dt, dr = error(plant.T, goal)
    assert dt < 1e-4 and dr < 1e-3
    assert past < past_bound, past
    assert all(o.faults == 0 for o in outs)


@pytest.mark.parametrize("late_cycle", [0, 1, 2])
def test_a_move_whose_first_twists_go_out_late_lands_without_overshoot(late_cycle: int) -> None:
    # ur-rtde waits for the control script's handshake before the first command after a pause: one of the
    # move's first twists goes out 18 ms late, and the loop's next cycle comes 0.5 ms after that one, on its
    # schedule. With the plan's clock run on over it, the TCP ran 22 mm past this goal and took 2.7 s.
    core = _core()
    plant = KinematicPlant(T0, PERIOD, latency_cycles=3)
    goal = T0.copy()
    goal[:3, 3] += [0.2, 0.1, -0.1]
    goal[:3, :3] = Rotation.from_rotvec([0.2, 0.1, 0.3]).as_matrix() @ goal[:3, :3]
    p0 = T0[:3, 3].copy()
    u = (goal[:3, 3] - p0) / np.linalg.norm(goal[:3, 3] - p0)
    length = float(np.linalg.norm(goal[:3, 3] - p0))
    late = {late_cycle: 0.018, late_cycle + 1: 0.0005}
    past, outs = 0.0, []
    for k in range(3000):
        out = core.step(plant.cycle_input(**({"command": move_to(goal), "command_id": 1} if k == 0 else {})))
        plant.apply(out, late.get(k))
        past = max(past, float((plant.T[:3, 3] - p0) @ u) - length)
        outs.append(out)
        if k > 0 and out.mode == Mode.IDLE:
            break
    assert outs[-1].status == ControlStatus.DONE, outs[-1].event
    dt, dr = error(plant.T, goal)
    assert dt < 1e-4 and dr < 1e-3
    assert past < 1e-3, past
    # The straight move's plan is 1.3 s; a second more was the creep back from the overshoot.
    assert plant.stamp_ns * 1e-9 < 1.8, plant.stamp_ns * 1e-9
    assert _peaks_ok_over(outs, [late.get(k - 1, PERIOD) for k in range(len(outs))])


def test_stop_request_ramps_to_rest_jerk_limited_and_cancels_nothing_else() -> None:
    core = _core()
    plant = KinematicPlant(T0, PERIOD)
    setpoint = np.array([0.2, 0.0, 0.1, 0.0, 0.0, 0.5])
    outs = []
    for k in range(600):
        inp = plant.cycle_input(
            setpoint=setpoint, setpoint_age=0.0, **({"command": stream(), "command_id": 7} if k == 0 else {}), stop=(k == 250)
        )
        out = core.step(inp)
        plant.apply(out)
        outs.append(out)
    assert outs[249].mode == Mode.ACTIVE and np.linalg.norm(outs[249].twist[:3]) > 0.2
    stops = [o for o in outs[250:] if o.mode == Mode.IDLE]
    assert stops and stops[0].status == ControlStatus.STOPPED and stops[0].command_id == 7
    first_idle = next(i for i, o in enumerate(outs) if i > 250 and o.mode == Mode.IDLE)
    np.testing.assert_array_equal(outs[first_idle].twist, np.zeros(6))
    assert _peaks_ok(outs)


def test_streaming_dead_man_brings_the_robot_to_rest_and_holds() -> None:
    core = _core()
    plant = KinematicPlant(T0, PERIOD)
    outs = run(core, plant, 50, command=stream(timeout=0.05), command_id=1, setpoint=np.array([0.1, 0, 0, 0, 0, 0]), setpoint_age=0.0)
    # After the first cycle the setpoint is "never written" (age inf): the twist ramps to zero.
    assert all(o.mode == Mode.ACTIVE for o in outs)
    assert outs[-1].status == ControlStatus.HOLD
    assert np.linalg.norm(outs[-1].twist) < 1e-9


def test_protective_stop_ends_the_motion_at_once_and_refuses_new_commands() -> None:
    core = _core()
    plant = KinematicPlant(T0, PERIOD)
    goal = T0.copy()
    goal[:3, 3] += [0.2, 0.0, 0.0]
    run(core, plant, 100, command=move_to(goal), command_id=3)
    out = core.step(plant.cycle_input(safety_bits=PROTECTIVE))
    assert out.mode == Mode.IDLE and out.action == Action.KICK and out.status == ControlStatus.SAFETY
    assert out.faults & Fault.PROTECTIVE_STOP
    assert out.event_id == 3 and "protective stop" in out.event
    out = core.step(plant.cycle_input(safety_bits=PROTECTIVE, command=move_to(goal), command_id=4))
    assert out.event_id == 4 and out.event_status == ControlStatus.SAFETY and out.action == Action.KICK


def test_stale_robot_state_stops_the_motion() -> None:
    core = _core()
    plant = KinematicPlant(T0, PERIOD)
    goal = T0.copy()
    goal[:3, 3] += [0.2, 0.0, 0.0]
    run(core, plant, 200, command=move_to(goal), command_id=1)
    outs = [core.step(plant.cycle_input(state_age=4 * PERIOD))]
    assert outs[0].mode == Mode.STOPPING and outs[0].status == ControlStatus.STALE_STATE
    for _ in range(300):
        outs.append(core.step(plant.cycle_input(state_age=0.0)))
    assert outs[-1].mode == Mode.IDLE and outs[-1].status == ControlStatus.STALE_STATE
    assert "stale" in next(o.event for o in outs if o.event)
    # A new command is refused while the state is stale.
    out = core.step(plant.cycle_input(state_age=1.0, command=move_to(goal), command_id=2))
    assert out.event_id == 2 and out.event_status == ControlStatus.STALE_STATE


def test_streaming_towards_a_wall_stops_inside_the_workspace() -> None:
    core = _core()
    start = T0.copy()
    start[:3, 3] = [0.9, 0.0, 0.5]  # 0.1 m from x = 1.0
    plant = KinematicPlant(start, PERIOD)
    twist = np.array([0.25, 0.0, 0.0, 0.0, 0.0, 0.0])
    outs = []
    for k in range(800):
        out = core.step(plant.cycle_input(setpoint=twist, setpoint_age=0.0, **({"command": stream(), "command_id": 1} if k == 0 else {})))
        plant.apply(out)
        outs.append(out)
    assert outs[-1].mode == Mode.IDLE and outs[-1].status == ControlStatus.WORKSPACE
    assert plant.T[0, 3] <= 1.0
    assert _peaks_ok(outs)
    # Moving back in from there is allowed.
    back = core.step(plant.cycle_input(setpoint=-twist, setpoint_age=0.0, command=stream(), command_id=2))
    assert back.mode == Mode.ACTIVE


def test_commands_that_cannot_run_are_refused_with_a_reason() -> None:
    core = _core()
    plant = KinematicPlant(T0, PERIOD)
    outside = T0.copy()
    outside[:3, 3] = [1.5, 0.0, 0.4]
    out = core.step(plant.cycle_input(command=move_to(outside), command_id=5))
    assert out.event_id == 5 and out.event_status == ControlStatus.WORKSPACE and "workspace" in out.event
    out = core.step(plant.cycle_input(command_error="command: bad magic", command_id=6))
    assert out.event_status == ControlStatus.BAD_COMMAND and out.mode == Mode.IDLE
    plan = ServoPlan("nope", {"P_base": np.zeros((3, 3))}, {})
    out = core.step(plant.cycle_input(command=start_servo(plan), command_id=7))
    assert out.event_status == ControlStatus.BAD_COMMAND and "no servo law registered" in out.event


def test_a_new_command_takes_over_smoothly() -> None:
    core = _core()
    plant = KinematicPlant(T0, PERIOD)
    g1, g2 = T0.copy(), T0.copy()
    g1[:3, 3] += [0.3, 0.0, 0.0]
    g2[:3, 3] += [0.0, 0.2, 0.0]
    outs = run(core, plant, 200, command=move_to(g1), command_id=1)
    outs += run(core, plant, 1500, command=move_to(g2), command_id=2)
    assert outs[-1].command_id == 2 and outs[-1].status == ControlStatus.DONE
    assert _peaks_ok(outs)
    assert error(plant.T, g2)[0] < 1e-4


class _Law:
    """A stand-in servo law: moves along +y until the tactile sample says overload."""

    def __init__(self, plan: ServoPlan) -> None:
        self.speed = float(plan.params["speed"])
        self.started: RobotState | None = None
        self.reason = ""

    def start(self, state: RobotState) -> None:
        self.started = state

    def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
        if inp.tactile is not None and inp.tactile.contact == ContactState.OVERLOAD:
            return np.zeros(6), ControlStatus.OVERLOAD
        return np.array([0.0, self.speed, 0.0, 0.0, 0.0, 0.0]), ControlStatus.OK

    def telemetry(self) -> ServoTelemetry:
        return NO_TELEMETRY


def _sample(contact: ContactState) -> TactileSample:
    return TactileSample(0, 1, np.zeros(3), contact, 1.0, True, 0)


def test_servo_slot_runs_a_registered_law_and_stops_on_its_fault_or_stale_tactile() -> None:
    core = MotionCore(_core().params, {"test": _Law})
    plant = KinematicPlant(T0, PERIOD)
    plan = ServoPlan("test", {"P_base": np.zeros((2, 3))}, {"speed": 0.01})
    ok = _sample(ContactState.CONTACT)
    outs = run(core, plant, 300, command=start_servo(plan), command_id=1, tactile=ok, tactile_age=0.0)
    # Only the first cycle had a fresh sample: the rest are "never written" (inf) -> stale.
    assert outs[-1].status == ControlStatus.STALE_TACTILE and outs[-1].mode == Mode.IDLE

    core = MotionCore(_core().params, {"test": _Law})
    plant = KinematicPlant(T0, PERIOD)
    outs = []
    for k in range(300):
        sample = _sample(ContactState.OVERLOAD if k >= 150 else ContactState.CONTACT)
        out = core.step(
            plant.cycle_input(tactile=sample, tactile_age=0.01, **({"command": start_servo(plan), "command_id": 2} if k == 0 else {}))
        )
        plant.apply(out)
        outs.append(out)
    assert outs[149].mode == Mode.ACTIVE and outs[149].twist[1] == pytest.approx(0.01)
    assert outs[-1].mode == Mode.IDLE and outs[-1].status == ControlStatus.OVERLOAD
    assert _peaks_ok(outs)


def test_a_law_that_raises_is_a_fault_not_a_crash() -> None:
    class Broken(_Law):
        def step(self, inp: ServoInput) -> tuple[np.ndarray, ControlStatus]:
            raise ZeroDivisionError("boom")

    core = MotionCore(_core().params, {"broken": Broken})
    plant = KinematicPlant(T0, PERIOD)
    plan = ServoPlan("broken", {}, {"speed": 0.01})
    outs = run(core, plant, 5, command=start_servo(plan), command_id=1, tactile=_sample(ContactState.CONTACT), tactile_age=0.0)
    assert outs[-1].mode == Mode.IDLE and outs[-1].status == ControlStatus.FAULT
    assert any("boom" in o.event for o in outs)


# -- the process output (welding arc) -------------------------------------------------


def _probe_plan(process: bool = True, cycles: int = 200, process_from: int = 20) -> ServoPlan:
    """tests.motion.laws.Probe: asks for the process from its cycle ``process_from`` until it ends."""
    return ServoPlan(
        "probe",
        {"direction": np.array([0.0, 1.0, 0.0])},
        {"speed": 0.01, "cycles": cycles, "process": process, "process_from": process_from},
    )


def _run_probe(plan: ServoPlan, cycles: int, at: int = -1, factory=make_probe, **at_kw) -> list:
    """Run the probe law in the core; ``at_kw`` go into the input of cycle ``at`` (and stay after it)."""
    core = MotionCore(_core().params, {"probe": factory})
    plant = KinematicPlant(T0, PERIOD)
    outs = []
    for k in range(cycles):
        kw = {"tactile": _sample(ContactState.CONTACT), "tactile_age": 0.0}
        if k == 0:
            kw |= {"command": start_servo(plan), "command_id": 1}
        if 0 <= at <= k:
            kw |= at_kw
        out = core.step(plant.cycle_input(**kw))
        plant.apply(out)
        outs.append(out)
    return outs


def test_the_process_goes_on_only_while_the_law_asks_and_off_at_done() -> None:
    outs = _run_probe(_probe_plan(process=True), 300)
    on = [o.process_on for o in outs]
    # The probe asks from its 20th cycle (index 19) to its 199th; its 200th says DONE.
    assert not any(on[:19]) and all(on[19:199]) and not any(on[199:])
    assert outs[199].mode == Mode.STOPPING and outs[-1].mode == Mode.IDLE and outs[-1].status == ControlStatus.DONE
    # The law's telemetry rides along while the servo slot runs, NO_TELEMETRY once it is gone.
    assert outs[50].telemetry.phase == 1 and outs[50].telemetry.delta_n == pytest.approx(0.051)
    np.testing.assert_allclose(outs[50].telemetry.refined_base, [0.0, 0.0, 0.051])
    assert outs[-1].telemetry is NO_TELEMETRY
    assert all(type(o.process_on) is bool for o in outs)


def test_a_plan_without_the_process_never_switches_it_on() -> None:
    outs = _run_probe(_probe_plan(process=False), 300)
    assert not any(o.process_on for o in outs)
    assert outs[-1].status == ControlStatus.DONE


def test_a_stop_request_switches_the_process_off_on_the_cycle_it_begins() -> None:
    outs = _run_probe(_probe_plan(cycles=10_000), 400, at=100, stop=True)
    assert outs[99].process_on and outs[99].mode == Mode.ACTIVE
    assert outs[100].mode == Mode.STOPPING and not outs[100].process_on
    assert not any(o.process_on for o in outs[100:])
    assert outs[-1].mode == Mode.IDLE and outs[-1].status == ControlStatus.STOPPED


@pytest.mark.parametrize(
    ("fault", "status"),
    [
        ({"tactile_age": 0.2}, ControlStatus.STALE_TACTILE),
        ({"state_age": 4 * PERIOD}, ControlStatus.STALE_STATE),
        ({"tactile": _sample(ContactState.OVERLOAD)}, ControlStatus.OVERLOAD),
    ],
)
def test_a_fault_switches_the_process_off_on_the_cycle_it_is_seen(fault: dict, status: ControlStatus) -> None:
    outs = _run_probe(_probe_plan(cycles=10_000), 400, at=100, **fault)
    assert outs[99].process_on
    assert outs[100].mode == Mode.STOPPING and outs[100].status == status and not outs[100].process_on
    assert not any(o.process_on for o in outs[100:])
    assert outs[-1].mode == Mode.IDLE and outs[-1].status == status


def test_the_robot_stopping_itself_switches_the_process_off() -> None:
    outs = _run_probe(_probe_plan(cycles=10_000), 150, at=100, safety_bits=PROTECTIVE)
    assert outs[99].process_on
    assert outs[100].mode == Mode.IDLE and outs[100].status == ControlStatus.SAFETY and not outs[100].process_on
    assert outs[100].telemetry.phase == -1


def test_another_command_taking_over_switches_the_process_off() -> None:
    outs = _run_probe(_probe_plan(cycles=10_000), 150, at=100, command=stream(), command_id=2)
    assert outs[99].process_on
    assert outs[100].mode == Mode.ACTIVE and outs[100].command_id == 2 and not outs[100].process_on
    assert outs[100].telemetry.phase == -1


def test_a_law_whose_telemetry_raises_once_running_runs_on_with_the_process_off() -> None:
    class Broken(Probe):
        def telemetry(self):
            if self.count >= 1:  # well-formed at start (the slot checks it then), broken from the first step on
                raise RuntimeError("no telemetry")
            return super().telemetry()

    laws: list[Broken] = []

    def factory(plan: ServoPlan) -> Broken:
        laws.append(Broken(plan))
        return laws[-1]

    outs = _run_probe(_probe_plan(cycles=100, process_from=1), 150, factory=factory)
    assert all(o.mode == Mode.ACTIVE for o in outs[:99]) and outs[-1].status == ControlStatus.DONE
    assert all(o.telemetry is NO_TELEMETRY and not o.process_on for o in outs)
    assert laws[0].count == 100  # the law ran to its end


def test_a_law_whose_telemetry_is_malformed_at_start_is_refused_with_the_reason() -> None:
    class Malformed(Probe):
        def telemetry(self):
            return (1, 2)

    outs = _run_probe(_probe_plan(cycles=100), 20, factory=Malformed)
    assert outs[-1].mode == Mode.IDLE and outs[-1].status == ControlStatus.FAULT
    assert not any(o.process_on for o in outs)
