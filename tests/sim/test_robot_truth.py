"""True state in shared memory: publisher, reader, interpolation, and the running simulator."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import rtde_control
import rtde_receive

from celld import se3
from celld.errors import InputError, RobotError
from celld.robot import kinematics as kin
from celld.sim.robot import SimRobotHandle, TruthReader
from celld.sim.robot.truth import HISTORY_CAPACITY, TRUTH_DTYPE, TruthPublisher


def _rows(T: np.ndarray) -> list[float]:
    return T[:3, :4].ravel().tolist()


def test_reader_interpolates_between_cycles(loopback_host: str) -> None:
    pub = TruthPublisher(loopback_host)
    reader = TruthReader(loopback_host, timeout=1.0)
    try:
        T0 = se3.from_xyz_rpy([0.5, 0.0, 0.3], [math.pi, 0.0, 0.0])
        T1 = se3.from_xyz_rpy([0.5, 0.01, 0.3], [math.pi, 0.0, 0.02])
        q = np.zeros(6)
        t0 = 1_000_000_000
        pub.publish(t0, q, q, _rows(T0), _rows(T0), _rows(np.eye(4)), 1, (7, 1, 2))
        pub.publish(t0 + 2_000_000, q + 0.02, q, _rows(T1), _rows(T1), _rows(np.eye(4)), 1, (7, 1, 2))
        latest = reader.latest()
        assert latest.stamp_ns == t0 + 2_000_000 and latest.digital_out == 1
        np.testing.assert_allclose(latest.T_base_tcp, T1, atol=1e-15)
        mid = reader.at(t0 + 500_000)  # a quarter of the way
        np.testing.assert_allclose(mid.T_base_tcp[:3, 3], [0.5, 0.0025, 0.3], atol=1e-12)
        np.testing.assert_allclose(mid.q, 0.005, atol=1e-12)
        assert se3.error(mid.T_base_tcp, se3.from_xyz_rpy([0.5, 0.0025, 0.3], [math.pi, 0.0, 0.005]))[1] < 1e-9
        with pytest.raises(InputError, match="outside the history"):
            reader.at(t0 - 1)
    finally:
        reader.close()
        pub.close()


def test_history_keeps_the_last_two_seconds(loopback_host: str) -> None:
    pub = TruthPublisher(loopback_host)
    reader = TruthReader(loopback_host, timeout=1.0)
    try:
        q = np.zeros(6)
        for k in range(HISTORY_CAPACITY + 100):
            pub.publish(k * 2_000_000, q, q, _rows(np.eye(4)), _rows(np.eye(4)), _rows(np.eye(4)), 0, (7, 1, 1))
        stamps = reader.history()["stamp_ns"]
        assert len(stamps) == HISTORY_CAPACITY
        assert stamps[-1] == (HISTORY_CAPACITY + 99) * 2_000_000 and np.all(np.diff(stamps) == 2_000_000)
    finally:
        reader.close()
        pub.close()


def test_latest_waits_out_a_write_in_progress_instead_of_answering_an_old_state(loopback_host: str) -> None:
    pub = TruthPublisher(loopback_host)
    reader = TruthReader(loopback_host, timeout=1.0)
    try:
        q = np.zeros(6)
        pub.publish(1_000_000, q, q, _rows(np.eye(4)), _rows(np.eye(4)), _rows(np.eye(4)), 0, (7, 1, 2))
        assert reader.latest().stamp_ns == 1_000_000  # the reader now holds a whole copy of that state
        # The simulator is caught half-way through a write (its seqlock counter odd), minutes later.
        seq = pub._slot._seq
        seq[0] += 1
        rec = np.zeros(1, TRUTH_DTYPE)
        rec["stamp_ns"], rec["q"] = 120_000_000_000, 0.5
        pub._slot._value[0] = rec[0]
        done = threading.Timer(0.05, lambda: seq.__setitem__(0, seq[0] + 1))
        done.start()
        latest = reader.latest()
        done.join()
        assert latest.stamp_ns == 120_000_000_000 and np.all(latest.q == 0.5)
        # A write that never completes is an error, not the old state.
        seq[0] += 1
        with pytest.raises(RobotError, match="torn"):
            reader.latest()
    finally:
        reader.close()
        pub.close()


@pytest.mark.process
def test_simulator_publishes_the_pose_it_streams(sim_robot: SimRobotHandle) -> None:
    r = rtde_receive.RTDEReceiveInterface(sim_robot.host)
    c = rtde_control.RTDEControlInterface(sim_robot.host)
    try:
        start = np.array(r.getActualTCPPose())
        target = start + [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]
        t_before = time.monotonic_ns()
        assert c.moveL(target.tolist(), 0.25, 1.2)
        time.sleep(0.02)
        stamp, T, q = sim_robot.truth()
        assert stamp > t_before
        np.testing.assert_allclose(T, se3.from_ur_pose(r.getActualTCPPose()), atol=1e-9)
        np.testing.assert_allclose(T, kin.forward(q), atol=1e-9)
        # Half-way through the move, by the clock: somewhere strictly between start and target.
        t_mid = t_before + 300_000_000
        x_mid = sim_robot.truth_at(t_mid).T_base_tcp[0, 3]
        assert start[0] + 0.01 < x_mid < target[0] - 0.01
    finally:
        c.stopScript()
        c.disconnect()
        r.disconnect()


@pytest.mark.process
def test_the_simulator_reports_its_model_and_publishes_the_physical_arm(loopback_host: str) -> None:
    from celld.sim.robot import launch
    from celld.sim.world import PRESETS, NominalCell, draw_world

    arm = draw_world(NominalCell(), PRESETS["realistic"], 1).arm
    with launch(loopback_host, realtime=True, arm=arm) as sim:
        r = rtde_receive.RTDEReceiveInterface(sim.host)
        try:
            time.sleep(0.2)
            # Both from one RTDE packet: the encoders' noise differs from packet to packet, and
            # ur-rtde's receive thread may update q and the pose between two getters.
            # Looked for over a second of packets (a loaded machine may leave few whole ones).
            consistent = 0
            deadline = time.monotonic() + 1.0
            while not consistent and time.monotonic() < deadline:
                q_rep, T_rep = np.array(r.getActualQ()), se3.from_ur_pose(r.getActualTCPPose())
                if np.array_equal(q_rep, np.array(r.getActualQ())) and np.allclose(T_rep, kin.forward(q_rep), atol=1e-9):
                    consistent += 1
                else:
                    time.sleep(0.0005)
            _, T_true, q_true = sim.truth()
        finally:
            r.disconnect()
    # RTDE: the controller's nominal kinematics of the joints its encoders read (with their noise).
    assert consistent, "no RTDE packet whose TCP pose is the nominal kinematics of its joints"
    np.testing.assert_allclose(T_rep, kin.forward(q_rep), atol=1e-9)
    # The truth: the arm's own kinematics (its links a fraction of a micrometre longer as it warms for
    # a second) of the physical joints, which are the encoders' plus the joint zeros and the sag under load.
    np.testing.assert_allclose(T_true, kin.forward(q_true, arm.dh), atol=1e-7)
    sag = np.array(arm.physical(q_rep)[0]) - q_rep - np.array(arm.joint_offsets)
    assert np.abs(sag).max() > 1e-4  # the shoulder and elbow carry the arm
    assert np.abs(q_true - np.array(arm.physical(q_rep)[0])).max() < 1e-4
    assert 0.05e-3 < np.linalg.norm(T_true[:3, 3] - T_rep[:3, 3]) < 3e-3
