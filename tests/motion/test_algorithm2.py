"""Algorithm 2: each line against hand-computed cases, omega's bound, and the law in closed loop.

The closed-loop tests step the real motion core (ruckig limiter, servo slot)
with a kinematic arm and the simulated finger's contact model; the tactile
samples are the simulator's truth plus noise (no images here: the image path
is tested in tests/tactile and benchmarked in bench/seam_tracking.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from celld.config import MotionLimits, ServoConfig, TactileConfig, ToolConfig
from celld.errors import InputError
from celld.motion.algorithm2 import (
    NAME,
    Algorithm2Params,
    Phase,
    algorithm2_plan,
    deformation_in_plane,
    make_algorithm2,
    omega_line13,
    refine_point,
    servo_velocity,
    torch_position,
)
from celld.motion.arc import plan_keys
from celld.motion.commands import start_servo
from celld.motion.core import CoreParams, CycleInput, Mode, MotionCore, SourceParams
from celld.motion.limits import CartesianLimits, sequence_peaks
from celld.motion.types import ControlStatus, RobotState, ServoInput
from celld.sim.srm import ContactParams, Wall, finger_contact
from celld.tactile.deformation import contact_state, invalid_sample
from celld.tactile.fingermap import FingerGain
from celld.tactile.sample import ContactState, TactileSample, TactileStatus

PERIOD = 0.002


def _rot(a: float) -> np.ndarray:
    return np.array([math.cos(a), math.sin(a)])


# -- each line by hand ------------------------------------------------------------------


def test_line9_torch_trails_the_tip_by_d() -> None:
    # Eq. 14: P_r = P_t + |d| t_d.
    np.testing.assert_allclose(torch_position(np.array([0.1, 0.2]), np.array([0.0, 1.0]), 0.03), [0.1, 0.17])
    t_d = _rot(math.radians(30))
    np.testing.assert_allclose(torch_position(np.zeros(2), t_d, 0.03), [-0.03 * math.cos(math.radians(30)), -0.015])


def test_line24_servo_velocity() -> None:
    t_v, n_v = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    # Pressed 0.5 mm too hard with k_p = 5/s: back off at 2.5 mm/s along -n_v.
    np.testing.assert_allclose(servo_velocity(t_v, n_v, 0.01, 0.002, 0.0015, 5.0, 0.01), [0.01, -0.0025])
    # Free (delta 0): press at k_p delta_d = 7.5 mm/s towards the wall.
    np.testing.assert_allclose(servo_velocity(t_v, n_v, 0.01, 0.0, 0.0015, 5.0, 0.01), [0.01, 0.0075])
    # The correction is bounded.
    np.testing.assert_allclose(servo_velocity(t_v, n_v, 0.01, 0.01, 0.0015, 5.0, 0.004), [0.01, -0.004])
    # A wall on the right: delta_d is negative, the same law presses towards -n_v.
    np.testing.assert_allclose(servo_velocity(t_v, n_v, 0.0, 0.0, -0.0015, 5.0, 0.01), [0.0, -0.0075])


def test_line6_deformation_into_the_plane() -> None:
    # Tool turned 90 degrees: its x is the plane's y.
    d = deformation_in_plane(np.array([0.0003, 0.0015, 0.0001]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]))
    np.testing.assert_allclose(d, [-0.0015, 0.0003])


def test_line17_refine_subtracts_the_deformation() -> None:
    P_r = np.array([0.1, 0.02])
    delta = np.array([0.0003, 0.0015])
    np.testing.assert_allclose(refine_point(P_r, delta, np.array([1.0, 0.0]), np.array([0.0, 1.0])), [0.0997, 0.0185])
    # Whatever the path's axes, the components recombine to P_r - delta (Eq. 15).
    t_s = _rot(0.7)
    n_s = np.array([-t_s[1], t_s[0]])
    np.testing.assert_allclose(refine_point(P_r, delta, t_s, n_s), P_r - delta, atol=1e-15)


def test_line13_omega_by_hand() -> None:
    # Tool along x, refined path along x, V_r with 1 mm/s towards +y:
    # the torch (30 mm behind) must not move sideways: omega = 0.001 / 0.03.
    V_r = np.array([0.01, 0.001])
    t_d, n_d, n_t = np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([0.0, 1.0])
    omega, guarded = omega_line13(V_r, t_d, n_d, n_t, 0.03, 0.0, 0.0, 0.25, 1.0)
    assert omega == pytest.approx(0.001 / 0.03)
    assert not guarded
    # Tool turned 30 degrees off the path, torch 1 mm left of it, k_torch 2/s:
    # omega = (V_r . n_t + k e) / (|d| n_d . n_t) = (0 + 0.002) / (0.03 cos 30).
    t_d = _rot(math.radians(30))
    n_d = np.array([-t_d[1], t_d[0]])
    omega, _ = omega_line13(np.array([0.01, 0.0]), t_d, n_d, n_t, 0.03, 0.001, 2.0, 0.25, 1.0)
    assert omega == pytest.approx(0.002 / (0.03 * math.cos(math.radians(30))))


def test_line13_makes_the_torch_velocity_follow_the_refined_path() -> None:
    # Eq. 17-18: V_t = V_r - omega |d| n_d, and V_t . n_t = -k e.
    rng = np.random.default_rng(2)
    for _ in range(50):
        V_r = rng.normal(0, 0.01, 2)
        t_d = _rot(rng.uniform(-math.pi, math.pi))
        n_d = np.array([-t_d[1], t_d[0]])
        t_t = _rot(math.atan2(t_d[1], t_d[0]) + rng.uniform(-1.0, 1.0))  # at most 57 deg off: outside the guard
        n_t = np.array([-t_t[1], t_t[0]])
        e = rng.uniform(-0.001, 0.001)
        omega, guarded = omega_line13(V_r, t_d, n_d, n_t, 0.03, e, 2.0, 0.25, 100.0)
        assert not guarded
        V_t = V_r - omega * 0.03 * n_d
        assert float(V_t @ n_t) == pytest.approx(-2.0 * e, abs=1e-12)


def test_guard_damps_omega_to_zero_at_the_singularity() -> None:
    t_d = np.array([1.0, 0.0])
    n_d = np.array([0.0, 1.0])
    V_r = np.array([0.0, 0.01])
    # n_t perpendicular to n_d: no omega can help (paper 5.2); the guard gives 0.
    omega, guarded = omega_line13(V_r, t_d, n_d, np.array([1.0, 0.0]), 0.03, 0.0, 0.0, 0.25, 0.5)
    assert omega == 0.0 and guarded
    # Continuous at the edge of the band: |n_d . n_t| = guard_cos from both sides.
    a = math.acos(0.25)
    # n_t at angle b from n_d has n_d . n_t = cos b.
    inside = omega_line13(V_r, t_d, n_d, np.array([math.sin(a + 1e-9), math.cos(a + 1e-9)]), 0.03, 0.0, 0.0, 0.25, 10.0)
    outside = omega_line13(V_r, t_d, n_d, np.array([math.sin(a - 1e-9), math.cos(a - 1e-9)]), 0.03, 0.0, 0.0, 0.25, 10.0)
    assert inside[1] and not outside[1]
    assert inside[0] == pytest.approx(outside[0], rel=1e-6)
    # Non-finite input: zero, flagged.
    assert omega_line13(np.array([math.nan, 0.0]), t_d, n_d, n_d, 0.03, 0.0, 0.0, 0.25, 0.5) == (0.0, True)


unit_angle = st.floats(-math.pi, math.pi, allow_nan=False)


@settings(max_examples=400, deadline=None)
@given(
    vx=st.floats(-1.0, 1.0),
    vy=st.floats(-1.0, 1.0),
    a_d=unit_angle,
    a_t=unit_angle,
    d=st.floats(1e-4, 0.5),
    e=st.floats(-0.1, 0.1),
    k=st.floats(0.0, 20.0),
    guard=st.floats(0.01, 0.9),
    omega_max=st.floats(0.01, 3.0),
    perpendicular=st.booleans(),
)
def test_omega_is_bounded_for_any_geometry(vx, vy, a_d, a_t, d, e, k, guard, omega_max, perpendicular) -> None:
    t_d = _rot(a_d)
    n_d = np.array([-t_d[1], t_d[0]])
    # Half the cases put n_t exactly perpendicular to n_d (the paper's singularity).
    n_t = np.array([n_d[1], -n_d[0]]) if perpendicular else _rot(a_t)
    omega, guarded = omega_line13(np.array([vx, vy]), t_d, n_d, n_t, d, e, k, guard, omega_max)
    assert math.isfinite(omega)
    assert abs(omega) <= omega_max
    if perpendicular:
        assert guarded
        assert abs(omega) <= (abs(vx) + abs(vy) + k * 0.003) * abs(float(n_d @ n_t)) / (d * guard * guard) + 1e-12


# -- the plan message ------------------------------------------------------------------


def test_plan_message_is_checked() -> None:
    servo, tool, motion = ServoConfig(), ToolConfig(), MotionLimits()
    plan = algorithm2_plan(np.column_stack([np.linspace(0, 0.1, 50), np.zeros(50), np.zeros(50)]), servo, tool, motion)
    assert plan.name == NAME
    law = make_algorithm2(plan)
    assert law.p == Algorithm2Params.from_config(servo, tool, motion)
    bad = plan._replace(params={**plan.params, "k_p": -1.0})
    with pytest.raises(InputError, match="k_p"):
        make_algorithm2(bad)
    with pytest.raises(InputError, match="missing"):
        make_algorithm2(plan._replace(arrays={"P_base": plan.arrays["P_base"]}))
    with pytest.raises(InputError, match="travel"):
        make_algorithm2(plan._replace(arrays={**plan.arrays, "P_base": np.zeros((3, 3))}))


# -- closed loop -------------------------------------------------------------------------

T_PLANE = np.array([[1.0, 0, 0, 0.45], [0, 1.0, 0, -0.1], [0, 0, 1.0, 0.12], [0, 0, 0, 1.0]])


class Loop:
    """The motion core with Algorithm 2, a kinematic arm, and the finger's contact model.

    The seam is a straight wall along +x (left of the tool); ``gap`` removes
    the wall over an interval of x. Samples (truth plus 3 um noise) are
    captured at ``fps`` and delivered ``latency`` later; ``tamper`` may
    replace a sample (faults).
    """

    def __init__(
        self,
        length: float = 0.06,
        gap: tuple[float, float] | None = None,
        plan_offset: float = -0.002,
        fps: float = 60.0,
        latency: float = 0.006,
        process: bool = False,
        seam_offset: float = 0.0,
        touch_only: bool = False,
        source=None,
        arc=None,
        tag_gain: float = 1.0,
        finger: FingerGain = FingerGain(),
    ) -> None:
        """``source`` (callable of t_s and the core's last ArcOutput, returning SourceSignals) is a power source
        on the cell's I/O, ``arc`` (ArcParams) the weld's sequence; without them the cell has none. The samples
        show ``tag_gain`` of the tip's deflection (a tag inside the finger); the plan carries ``finger``."""
        self.tag_gain = tag_gain
        self.sensor, self.servo_cfg, self.tool = TactileConfig(), ServoConfig(), ToolConfig()
        self.motion = MotionLimits()
        self.limits = CartesianLimits.from_config(self.motion)
        x = np.arange(0.0, length, 0.0002)
        walls = [np.column_stack([x, np.zeros_like(x)])]
        if gap is not None:
            walls = [w for w in (walls[0][x < gap[0]], walls[0][x > gap[1]]) if len(w) > 1]
        self.walls = [Wall(w, free=-1.0) for w in walls]
        plan2 = np.column_stack([np.arange(0.0, length, 0.001), np.full(len(np.arange(0.0, length, 0.001)), plan_offset)])
        P_plan = np.column_stack([plan2, np.zeros(len(plan2))]) @ T_PLANE[:3, :3].T + T_PLANE[:3, 3]
        self.plan = algorithm2_plan(
            P_plan,
            self.servo_cfg,
            self.tool,
            self.motion,
            T_base_plane=T_PLANE,
            process=process,
            seam_offset=seam_offset,
            touch_only=touch_only,
            finger=finger,
        )
        if arc is not None:
            self.plan = self.plan._replace(params={**self.plan.params, **plan_keys(arc)})
        self.source = source
        self.core = MotionCore(
            CoreParams(
                self.limits,
                PERIOD,
                (-1.5, -1.5, -0.5),
                (1.5, 1.5, 1.5),
                0.05,
                self.motion.tactile_stale,
                source=SourceParams() if source is not None else None,
            ),
            {NAME: make_algorithm2},
        )
        self.arc_out = None  # the core's last ArcOutput
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # TCP x along the seam, z down the finger
        T[:3, 3] = P_plan[5] - np.array([0.0, 0.003, 0.0])
        self.T = T
        self.v = np.zeros(6)
        self._next = np.zeros(6)
        self.fps, self.latency = fps, latency
        self.rng = np.random.default_rng(1)
        self.t_ns = 0
        self.next_frame = 0
        self.pending: list[tuple[int, TactileSample]] = []
        self.latest: TactileSample | None = None
        self.seq = 0
        self.contact = ContactState.NONE
        self.servo = None
        self.twists: list[np.ndarray] = []
        self.statuses: list[ControlStatus] = []
        self.phases: list[Phase] = []
        self.outs: list = []  # the core's CycleOutput of every cycle the servo ran
        self.tamper = None  # callable(sample, t_s) -> sample | None (None: the frame never comes)

    def _sample(self, stamp: int) -> TactileSample:
        T_bt = self.T  # the tool frame at the TCP (default tool), orientation of the tool: x = TCP x
        p = (T_bt[:3, 3] - T_PLANE[:3, 3])[:2]
        v = self.v[:2]
        shift = np.zeros(2)
        for w in self.walls:
            c = finger_contact(p, v, w, self.tool.tip_radius, ContactParams())
            if c.in_contact:
                shift = c.tip_shift_plane
        t_d = T_bt[:2, 0] / np.linalg.norm(T_bt[:2, 0])
        n_d = np.array([-t_d[1], t_d[0]])
        delta = self.tag_gain * np.array([-shift @ t_d, -shift @ n_d, 0.0]) + self.rng.normal(0, 3e-6, 3)
        self.seq += 1
        state = contact_state(delta, self.contact, self.sensor.contact_threshold, self.sensor.overload)
        self.contact = state
        return TactileSample(stamp, self.seq, delta, state, 1.0, True, 1_000_000)

    def run(self, seconds: float, start_after: float = 0.02, stop_at: float = math.inf) -> None:
        """Run up to ``seconds`` (until the servo has ended); ``stop_at`` (s) posts a stop request."""
        for _ in range(int(seconds / PERIOD)):
            while self.next_frame <= self.t_ns:
                s = self._sample(self.next_frame)
                if self.tamper is not None:
                    s = self.tamper(s, self.next_frame * 1e-9)
                if s is not None:
                    self.pending.append((self.next_frame + int(self.latency * 1e9), s))
                self.next_frame += int(1e9 / self.fps)
            while self.pending and self.pending[0][0] <= self.t_ns:
                self.latest = self.pending.pop(0)[1]
            state = RobotState(self.t_ns, np.zeros(6), np.zeros(6), self.T.copy(), self.v.copy())
            age = (self.t_ns - self.latest.stamp_ns) * 1e-9 if self.latest is not None else math.inf
            starting = self.servo is None and self.t_ns * 1e-9 >= start_after and self.latest is not None
            cmd = start_servo(self.plan) if starting else None
            sig = self.source(self.t_ns * 1e-9, self.arc_out) if self.source is not None else None
            out = self.core.step(
                CycleInput(
                    state,
                    0.0,
                    1,
                    self.latest,
                    age,
                    np.zeros(6),
                    math.inf,
                    cmd,
                    1 if starting else 0,
                    stop=self.t_ns * 1e-9 >= stop_at,
                    source=sig,
                )
            )
            self.arc_out = out.arc
            if starting:
                self.servo = self.core.controller.law
            self.v, self._next = self._next, out.twist.copy()
            self.T[:3, 3] += self.v[:3] * PERIOD
            self.T[:3, :3] = Rotation.from_rotvec(self.v[3:] * PERIOD).as_matrix() @ self.T[:3, :3]
            self.t_ns += int(PERIOD * 1e9)
            if self.servo is not None:
                self.twists.append(out.twist.copy())
                self.statuses.append(out.status)
                self.phases.append(self.servo.phase)
                self.outs.append(out)
                if self.core.mode == Mode.IDLE:
                    return

    def assert_jerk_limited(self) -> None:
        peaks = sequence_peaks(np.array(self.twists), PERIOD, np.zeros((2, 6))).ratios(self.limits)
        assert max(peaks) <= 1.0 + 1e-6, peaks

    def torch_error(self) -> float:
        """Lateral distance (m) of the torch to the wall line y = 0."""
        torch = self.T[:3, 3] - self.tool.torch_offset * self.T[:3, 0]
        return float(torch[1] - T_PLANE[1, 3])


def test_tracks_a_straight_seam_and_stops_cleanly_at_its_end() -> None:
    loop = Loop(length=0.06)
    loop.run(20.0)
    assert loop.core.mode == Mode.IDLE
    assert loop.statuses[-1] == ControlStatus.DONE
    assert Phase.TRACK in loop.phases and Phase.FINISH in loop.phases
    assert loop.servo.phase == Phase.DONE
    # The torch reached the end of the refined path on the seam line.
    assert abs(loop.torch_error()) < 1e-4
    assert np.linalg.norm(loop.twists[-1]) == 0.0
    loop.assert_jerk_limited()


def test_contact_lost_mid_seam_ends_in_a_controlled_stop() -> None:
    # A 15 mm gap in the wall: longer than the 5 mm search distance.
    loop = Loop(length=0.08, gap=(0.03, 0.045))
    loop.run(20.0)
    assert loop.core.mode == Mode.IDLE
    assert ControlStatus.CONTACT_LOST in loop.statuses
    assert Phase.SEARCH in loop.phases
    assert loop.servo.phase == Phase.FAULT and "contact lost" in loop.servo.reason
    # The search ran along the last tangent, no further than the search distance (+ the stop).
    x_stop = loop.T[0, 3] - T_PLANE[0, 3]
    assert x_stop < 0.03 + 0.005 + 0.002
    assert np.linalg.norm(loop.twists[-1]) == 0.0
    loop.assert_jerk_limited()


def test_a_short_gap_is_bridged_by_the_search() -> None:
    loop = Loop(length=0.08, gap=(0.03, 0.033))
    loop.run(25.0)
    assert Phase.SEARCH in loop.phases
    assert loop.statuses[-1] == ControlStatus.DONE


def _fault_after(t_fault: float, make):
    def tamper(sample: TactileSample, t: float) -> TactileSample | None:
        return sample if t < t_fault else make(sample)

    return tamper


@pytest.mark.parametrize(
    ("name", "make", "why"),
    [
        ("wrong tag id", lambda s: invalid_sample(s.stamp_ns, s.seq, TactileStatus.WRONG_ID), "WRONG_ID"),
        ("no tag", lambda s: invalid_sample(s.stamp_ns, s.seq, TactileStatus.NO_TAG), "NO_TAG"),
        ("blurred frames", lambda s: invalid_sample(s.stamp_ns, s.seq, TactileStatus.BLURRED), "BLURRED"),
        ("camera unplugged", lambda s: invalid_sample(s.stamp_ns, s.seq, TactileStatus.CAMERA_LOST), "CAMERA_LOST"),
        ("camera silent", lambda s: None, ""),
        ("late samples", lambda s: s._replace(stamp_ns=s.stamp_ns - 150_000_000), ""),
    ],
)
def test_tactile_faults_stop_without_a_jump(name: str, make, why: str) -> None:
    t_fault = 4.0  # mid-seam, tracking
    loop = Loop(length=0.08)
    loop.tamper = _fault_after(t_fault, make)
    loop.run(15.0)
    assert Phase.TRACK in loop.phases
    assert loop.core.mode == Mode.IDLE, name
    assert loop.statuses[-1] == ControlStatus.STALE_TACTILE, name
    if why:
        assert why in loop.servo.reason
    loop.assert_jerk_limited()
    # The stop began within the staleness bound (0.1 s) and took a jerk-limited ramp.
    n_before = int((t_fault - 0.02) / PERIOD)
    assert (len(loop.twists) - n_before) * PERIOD < 0.1 + 0.02 + 0.2, name


# -- the process output and the seam offset ----------------------------------------------------


def _on(loop: Loop) -> np.ndarray:
    return np.array([o.process_on for o in loop.outs])


def test_the_process_is_asked_for_only_while_the_torch_tracks_the_refined_path_and_dropped_at_the_end() -> None:
    loop = Loop(length=0.03, process=True)
    loop.run(20.0)
    on, phases = _on(loop), np.array(loop.phases)
    assert loop.statuses[-1] == ControlStatus.DONE and loop.servo.phase == Phase.DONE
    assert np.count_nonzero(phases == Phase.TOUCH) > 100 and not on[phases == Phase.TOUCH].any()
    # Tracking starts with the torch |d| behind the first refined point: the arc
    # lights once the torch reaches it, then stays on to the end of the path.
    tracking = np.flatnonzero((phases == Phase.TRACK) | (phases == Phase.FINISH))
    first_on = int(np.argmax(on))
    assert on.any() and not on[tracking[0]] and first_on > tracking[0]
    assert on[first_on : tracking[-1] + 1].all()
    # The torch moves at about V_const: it takes about (|d| - refine_window) / V_const to get there.
    dt = (first_on - tracking[0]) * 0.002
    assert dt == pytest.approx((loop.tool.torch_offset - loop.servo_cfg.refine_window) / loop.servo_cfg.v_const, rel=0.3)
    assert not on[phases == Phase.DONE].any()
    assert not any(o.process_on for o in loop.outs if o.mode != Mode.ACTIVE)
    # The telemetry the core passes on is the law's.
    tel = [o.telemetry for o in loop.outs]
    assert [t.phase for t in tel[:-1]] == [int(p) for p in phases[:-1]]
    track = [t for t, p in zip(tel, phases) if p == Phase.TRACK]
    assert np.all(np.isfinite([t.refined_base for t in track[-100:]]))
    assert np.median([t.delta_n for t in track]) == pytest.approx(loop.servo_cfg.delta_d, abs=1e-4)


def test_without_the_process_in_the_plan_it_is_never_asked_for() -> None:
    loop = Loop(length=0.03, process=False)
    loop.run(20.0)
    assert loop.statuses[-1] == ControlStatus.DONE and Phase.TRACK in loop.phases
    assert not _on(loop).any()


def test_a_stop_request_mid_seam_drops_the_process_on_that_cycle() -> None:
    loop = Loop(length=0.06, process=True)
    loop.run(20.0, stop_at=5.0)  # the torch reached the refined path at about 3.5 s
    on = _on(loop)
    first_stop = next(i for i, o in enumerate(loop.outs) if o.mode == Mode.STOPPING)
    assert loop.phases[first_stop - 1] == Phase.TRACK and on[first_stop - 1]
    assert not on[first_stop:].any()
    assert loop.statuses[-1] == ControlStatus.STOPPED


def test_a_tactile_fault_mid_seam_drops_the_process() -> None:
    loop = Loop(length=0.06, process=True)
    loop.tamper = _fault_after(5.0, lambda s: invalid_sample(s.stamp_ns, s.seq, TactileStatus.NO_TAG))
    loop.run(20.0)
    on = _on(loop)
    first_stop = next(i for i, o in enumerate(loop.outs) if o.mode == Mode.STOPPING)
    assert on[first_stop - 1] and not on[first_stop:].any()
    assert loop.outs[first_stop].status == ControlStatus.STALE_TACTILE


def _scripted_refined_path(
    seam_offset: float | np.ndarray, process: bool = False, sensor_yaw: float = 0.0, sample_yaw: float = 0.0
) -> tuple[np.ndarray, list]:
    """Algorithm 2 fed a fixed script: the tip slides along +x at 10 mm/s, 3 mm off the plan, pressed
    into the wall by exactly delta_d each cycle (seen in a frame turned by ``-sample_yaw`` about z).
    Returns the refined path and the telemetry per cycle."""
    servo, tool, motion = ServoConfig(), ToolConfig(), MotionLimits()
    x = np.arange(0.0, 0.06, 0.001)
    P_plan = np.column_stack([x, np.full(len(x), -0.002), np.zeros(len(x))]) @ T_PLANE[:3, :3].T + T_PLANE[:3, 3]
    plan = algorithm2_plan(
        P_plan, servo, tool, motion, T_base_plane=T_PLANE, process=process, seam_offset=seam_offset, sensor_yaw=sensor_yaw
    )
    law = make_algorithm2(plan)
    c, s = math.cos(-sample_yaw), math.sin(-sample_yaw)
    delta = np.array([-s * servo.delta_d, c * servo.delta_d, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = P_plan[5] - np.array([0.0, 0.003, 0.0])
    law.start(RobotState(0, np.zeros(6), np.zeros(6), T.copy(), np.zeros(6)))
    tel = []
    for k in range(1, 500):
        T[0, 3] += 0.01 * PERIOD
        sample = TactileSample(k * 2_000_000, k, delta, ContactState.CONTACT, 1.0, True, 0)
        law.step(ServoInput(RobotState(k * 2_000_000, np.zeros(6), np.zeros(6), T.copy(), np.zeros(6)), sample, 0.0))
        tel.append(law.telemetry())
    return law.refined_plane, tel


def test_seam_offset_moves_the_refined_path_by_exactly_the_offset_on_a_straight_wall() -> None:
    R0, tel0 = _scripted_refined_path(0.0)
    R1, tel1 = _scripted_refined_path(0.0012)
    assert len(R0) > 50 and len(R1) == len(R0)
    # The wall side is +y (left): the seam lies towards -y. Same script, same points, shifted.
    np.testing.assert_allclose(R1 - R0, np.tile([0.0, -0.0012], (len(R0), 1)), rtol=0, atol=1e-12)
    # The telemetry's refined point is the latest one, in the base frame (the plane is parallel to base xy).
    np.testing.assert_allclose(tel1[-1].refined_base, [R1[-1, 0] + T_PLANE[0, 3], R1[-1, 1] + T_PLANE[1, 3], T_PLANE[2, 3]], atol=1e-12)
    assert np.all(np.isnan(tel0[0].refined_base)) and tel0[-1].phase == Phase.TRACK
    assert tel0[-1].delta_n == pytest.approx(ServoConfig().delta_d, abs=1e-12)
    # process is False in these plans: never asked for, whatever the phase.
    assert not any(t.process_on for t in tel0 + tel1)
    # With the process asked for: the torch, |d| = 30 mm behind the tip, never
    # reaches the 10 mm of refined path this script lays down, so no arc yet.
    _, tel2 = _scripted_refined_path(0.0, process=True)
    assert tel2[-1].phase == Phase.TRACK and not any(t.process_on for t in tel2)


def test_with_a_seam_offset_the_torch_follows_the_seam_not_the_wall() -> None:
    loop = Loop(length=0.03, seam_offset=0.001)
    loop.run(20.0)
    assert loop.statuses[-1] == ControlStatus.DONE
    R = loop.servo.refined_plane
    # The wall is y = 0 in the plane: the refined path (the seam) 1 mm on the free side,
    # within the 3 um noise of the samples.
    assert abs(float(np.mean(R[:, 1])) + 0.001) < 5e-6 and np.ptp(R[:, 1]) < 3e-5
    assert abs(loop.torch_error() + 0.001) < 1e-4


def test_a_tag_that_shows_less_than_the_tip_leaves_the_seam_off_unless_the_plan_carries_the_finger_s_gain() -> None:
    delta_d = ServoConfig().delta_d
    off = Loop(length=0.03, seam_offset=0.001, tag_gain=0.9)
    off.run(20.0)
    fixed = Loop(length=0.03, seam_offset=0.001, tag_gain=0.9, finger=FingerGain(1 / 0.9))
    fixed.run(20.0)
    assert off.statuses[-1] == ControlStatus.DONE and fixed.statuses[-1] == ControlStatus.DONE
    # Taken as the tip's, the tag's deformation puts the wall delta_d (1 / 0.9 - 1) = 0.167 mm too far in; the
    # finger's gain puts it back on the wall (y = 0 in the plane), the seam 1 mm on the free side.
    y_off, y_fixed = (float(np.mean(loop.servo.refined_plane[:, 1])) for loop in (off, fixed))
    assert y_off + 0.001 == pytest.approx(delta_d * (1 / 0.9 - 1), abs=5e-6)
    assert abs(y_fixed + 0.001) < 5e-6 and abs(fixed.torch_error() + 0.001) < 1e-4
    # It holds the tip, not the tag, at delta_d: the law's delta_n while tracking is the tip's, so the tag shows 0.9 of it.
    held = np.array([o.telemetry.delta_n for o in fixed.outs if o.telemetry.phase == Phase.TRACK])
    assert len(held) > 100 and float(np.median(held)) == pytest.approx(delta_d, abs=2e-5)


def test_the_new_plan_parameters_are_checked() -> None:
    servo, tool, motion = ServoConfig(), ToolConfig(), MotionLimits()
    P = np.column_stack([np.linspace(0, 0.1, 50), np.zeros(50), np.zeros(50)])
    for bad in (-0.001, tool.torch_offset):
        with pytest.raises(InputError, match="seam_offset"):
            algorithm2_plan(P, servo, tool, motion, seam_offset=bad)
    plan = algorithm2_plan(P, servo, tool, motion, process=True, seam_offset=0.002)
    law = make_algorithm2(plan)
    assert law.p.process is True and law.p.seam_offset == 0.002
    with pytest.raises(InputError, match="process"):
        make_algorithm2(plan._replace(params={**plan.params, "process": 1}))
    # A plan that leaves them out gets the defaults: no process, the wall is the seam.
    older = {
        k: v
        for k, v in plan.params.items()
        if k not in ("process", "seam_offset", "touch_only", "sensor_yaw", "finger_gain", "finger_cubic")
    }
    p = make_algorithm2(plan._replace(params=older)).p
    assert (p.process, p.seam_offset, p.touch_only, p.sensor_yaw) == (False, 0.0, False, 0.0)
    with pytest.raises(InputError, match="touch_only"):
        make_algorithm2(plan._replace(params={**plan.params, "touch_only": 0}))
    # Seam offsets along the plan: one per planned point, each a valid seam_offset.
    for bad_offsets in (np.full(49, 0.002), np.r_[np.full(49, 0.002), -0.001], np.r_[np.full(49, 0.002), np.nan]):
        with pytest.raises(InputError, match="seam_offsets"):
            algorithm2_plan(P, servo, tool, motion, seam_offset=bad_offsets)
    for bad_yaw in (0.2, -0.2, math.nan):
        with pytest.raises(InputError, match="sensor_yaw"):
            make_algorithm2(plan._replace(params={**plan.params, "sensor_yaw": bad_yaw}))
    # The finger's gain: left out, Eq. 15 as is; no finger has a gain outside 0.7-1.4.
    assert (p.finger_gain, p.finger_cubic) == (1.0, 0.0)
    for bad_gain in (0.5, 2.0, math.nan, True):
        with pytest.raises(InputError, match="finger_gain|finger gain"):
            make_algorithm2(plan._replace(params={**plan.params, "finger_gain": bad_gain}))
    with pytest.raises(InputError, match="cubic term"):
        algorithm2_plan(P, servo, tool, motion, finger=FingerGain(1.0, 1e6))


def test_sensor_yaw_turns_the_deformation_into_the_measured_tool_frame() -> None:
    """A tool re-framed on its measured torch: the finger camera still reports in the configured
    frame, turned 3 deg from the plan's; with sensor_yaw the law sees the same deformation as an
    unturned tool, without it the wall reads 3 deg off (a tangential part, a shorter normal)."""
    yaw = math.radians(3.0)
    R0, _ = _scripted_refined_path(0.0)
    R1, tel1 = _scripted_refined_path(0.0, sensor_yaw=yaw, sample_yaw=yaw)
    R2, tel2 = _scripted_refined_path(0.0, sample_yaw=yaw)
    np.testing.assert_allclose(R1, R0, rtol=0, atol=1e-12)
    assert tel1[-1].delta_n == pytest.approx(ServoConfig().delta_d, abs=1e-12)
    assert tel2[-1].delta_n == pytest.approx(ServoConfig().delta_d * math.cos(yaw), abs=1e-9)
    assert np.max(np.abs(R2 - R0)) > 0.05 * ServoConfig().delta_d


def test_seam_offsets_along_the_plan_move_each_refined_point_by_the_offset_where_the_tip_was() -> None:
    x = np.arange(0.0, 0.06, 0.001)
    offsets = 0.001 + 0.01 * x  # 1 mm at the start, growing 0.01 mm per mm of seam
    R0, _ = _scripted_refined_path(0.0)
    R1, _ = _scripted_refined_path(offsets)
    assert len(R0) > 50 and len(R1) == len(R0)
    # The plan starts at x = 0 in the plane; its points are 1 mm apart: the offset at the tip's x.
    np.testing.assert_allclose(R1[:, 1] - R0[:, 1], -(0.001 + 0.01 * R0[:, 0]), rtol=0, atol=1e-9)


def test_touch_only_settles_on_the_wall_and_ends_without_tracking() -> None:
    loop = Loop(length=0.06, touch_only=True)
    loop.run(10.0)
    assert loop.core.mode == Mode.IDLE and loop.statuses[-1] == ControlStatus.DONE
    assert Phase.TRACK not in loop.phases and loop.servo.phase == Phase.DONE
    assert len(loop.servo.refined_plane) == 0
    # It ended pressed into the wall y = 0 (on the tip's +y side) by about delta_d: the undeformed tip
    # centre delta_d - tip_radius beyond it (settled: within a fifth of delta_d, and the ramp to rest).
    y_tip = float(loop.T[1, 3] - T_PLANE[1, 3])
    assert abs(y_tip - (loop.servo_cfg.delta_d - loop.tool.tip_radius)) < 0.25 * loop.servo_cfg.delta_d
    # At rest: it moved along the normal only, and stopped.
    assert np.linalg.norm(loop.twists[-1]) == 0.0
    loop.assert_jerk_limited()
