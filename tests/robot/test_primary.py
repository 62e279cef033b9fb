"""The controller's own kinematics from its primary interface: parsing, refusals, and the simulated controller."""

from __future__ import annotations

import math
import socket
import struct
import threading

import numpy as np
import pytest

from celld.errors import InputError, RobotError
from celld.robot import kinematics as kin
from celld.robot import primary as pi
from celld.sim.robot import primary as sp


def _calibrated(seed: int = 1, size: float = 1e-3) -> kin.DH:
    rng = np.random.default_rng(seed)
    return kin.DH(*(tuple((np.asarray(row) + rng.normal(0.0, size, 6)).tolist()) for row in kin.UR10E))  # type: ignore[arg-type]


def test_a_robot_state_message_gives_the_controllers_table_past_other_messages_and_packages() -> None:
    dh = _calibrated()
    k = pi.parse_message(sp.robot_state_message(dh))
    assert k is not None and k.dh == dh and k.calibration_status == sp.CALIBRATED
    assert k.checksums == sp.checksums(dh) and k.id == pi.table_id(dh) and k.id != pi.table_id(kin.UR10E)
    assert pi.parse_message(sp.version_message((5, 11, 6, 1))) is None
    # A robot state without the package carries no kinematics.
    only_mode = pi.HEADER.pack(5 + 47, pi.MESSAGE_ROBOT_STATE) + pi.HEADER.pack(47, sp.PACKAGE_ROBOT_MODE) + bytes(42)
    assert pi.parse_message(only_mode) is None
    # Its table differs from the published one by what a factory calibration moves: millimetres.
    assert 1e-3 < pi.check_model(k.dh, kin.model("ur10e")) < pi.MODEL_TOLERANCE


def test_bad_messages_are_refused_naming_what_is_wrong() -> None:
    good = sp.robot_state_message(_calibrated())
    with pytest.raises(InputError, match="says 9999 bytes"):
        pi.parse_message(struct.pack(">i", 9999) + good[4:])
    with pytest.raises(InputError, match="shorter than its header"):
        pi.parse_message(b"\x00\x00")
    # A package running past the message's end.
    bad = bytearray(good)
    struct.pack_into(">i", bad, 5, 10_000)
    with pytest.raises(InputError, match="a package of 10000 bytes"):
        pi.parse_message(bytes(bad))
    with pytest.raises(InputError, match="kinematics info of 12 bytes"):
        pi.kinematics_of(bytes(12))
    nan = pi.KINEMATICS_INFO.pack(*(0,) * 6, *([math.nan] + [0.0] * 23), 0)
    with pytest.raises(InputError, match="not finite"):
        pi.kinematics_of(nan)
    # Another model's table: the config names the wrong robot.
    k = pi.parse_message(sp.robot_state_message(kin.model("ur5e").dh))
    assert k is not None
    with pytest.raises(RobotError, match=r"robot.model: .* mm from a ur10e's"):
        pi.check_model(k.dh, kin.model("ur10e"))


def _serve(host: str, payload: bytes) -> socket.socket:
    srv = socket.create_server((host, 0))

    def run() -> None:
        conn, _ = srv.accept()
        with conn:
            conn.sendall(payload)
            try:
                conn.recv(1)  # until the client closes
            except OSError:
                pass

    threading.Thread(target=run, daemon=True).start()
    return srv


def test_a_stream_that_is_not_the_primary_interfaces_or_says_nothing_is_a_robot_error(loopback_host: str) -> None:
    srv = _serve(loopback_host, b"HTTP/1.1 200 OK\r\n\r\n")
    with srv, pytest.raises(RobotError, match=rf"{loopback_host}:\d+: primary interface: a message header says"):
        pi.read_kinematics(loopback_host, srv.getsockname()[1], timeout=1.0)
    srv = _serve(loopback_host, sp.version_message((5, 11, 6, 1)))
    with srv, pytest.raises(RobotError, match="no kinematics info within 0.3 s"):
        pi.read_kinematics(loopback_host, srv.getsockname()[1], timeout=0.3)
    with pytest.raises(RobotError, match=f"primary interface {loopback_host}:1:"):
        pi.read_kinematics(loopback_host, 1, timeout=0.5)


@pytest.mark.process
def test_the_simulated_controller_serves_the_table_it_computes_with(loopback_host: str) -> None:
    from celld.sim.robot import launch

    dh = _calibrated(3)
    with launch(loopback_host, kinematics=dh) as sim:
        k = pi.read_kinematics(sim.host)
        assert k.dh == dh
        # And it computes with it: the pose it reports is the table's of the joints it reports.
        from rtde_receive import RTDEReceiveInterface

        r = RTDEReceiveInterface(sim.host, 500.0)
        try:
            q, tcp = r.getActualQ(), r.getActualTCPPose()
        finally:
            r.disconnect()
    from celld import se3

    T = kin.forward(q, dh)
    np.testing.assert_allclose(tcp[:3], T[:3, 3], atol=1e-9)
    assert np.linalg.norm(kin.forward(q)[:3, 3] - T[:3, 3]) > 1e-3  # the published table is elsewhere
    assert np.allclose(se3.from_ur_pose(tcp)[:3, :3], T[:3, :3], atol=1e-9)
