"""Commands survive the mailbox byte form; malformed bytes are refused with a reason."""

from __future__ import annotations

import numpy as np
import pytest

from celld.errors import InputError
from celld.motion import commands as cmd
from celld.motion.types import ServoPlan
from celld.se3 import from_ur_pose


def test_move_to_round_trip() -> None:
    T = from_ur_pose([0.4, -0.1, 0.3, 3.0, 0.2, -0.1])
    got = cmd.decode(cmd.encode(cmd.move_to(T, speed_scale=0.5, tolerance=1e-4)))
    assert isinstance(got, cmd.MoveTo)
    np.testing.assert_array_equal(got.T_base_tcp, T)
    assert got.speed_scale == 0.5 and got.tolerance == 1e-4


def test_move_joints_round_trip_and_bad_targets() -> None:
    q = np.array([0.1, -1.2, 1.4, -1.8, -1.57, 0.3])
    got = cmd.decode(cmd.encode(cmd.move_joints(q, speed_scale=0.25, tolerance=1e-4)))
    assert isinstance(got, cmd.MoveJoints)
    np.testing.assert_array_equal(got.q_goal, q)
    assert got.speed_scale == 0.25 and got.tolerance == 1e-4
    with pytest.raises(InputError, match="6 finite joint positions"):
        cmd.move_joints([0.0] * 5)
    with pytest.raises(InputError, match="6 finite joint positions"):
        cmd.move_joints([0.0, 0.0, np.nan, 0.0, 0.0, 0.0])
    with pytest.raises(InputError, match=r"within \+-2 pi"):
        cmd.move_joints([0.0, 0.0, 7.0, 0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="q_goal are missing"):
        cmd.decode(b"CMD1" + bytes([4]) + (2).to_bytes(4, "little") + b"{}")


def test_stream_and_servo_round_trip(rng: np.random.Generator) -> None:
    assert cmd.decode(cmd.encode(cmd.stream(0.25))) == cmd.Stream(0.25)
    path = rng.normal(size=(500, 3))
    plan = ServoPlan(
        "algorithm2",
        {"P_base": path, "normals": rng.normal(size=(500, 3))},
        {"k_p": 2.0, "v_const": 0.01, "mode": "track", "closed": False, "n": 3},
    )
    got = cmd.decode(cmd.encode(cmd.start_servo(plan)))
    assert isinstance(got, cmd.StartServo)
    assert got.plan.name == "algorithm2" and got.plan.params == plan.params
    np.testing.assert_array_equal(got.plan.arrays["P_base"], path)
    assert set(got.plan.arrays) == {"P_base", "normals"}


@pytest.mark.parametrize(
    "payload, match",
    [
        (b"", "at least"),
        (b"XXXX" + bytes(5), "magic"),
        (b"CMD1" + bytes([9]) + (2).to_bytes(4, "little") + b"{}", "unknown kind"),
        (b"CMD1" + bytes([1]) + (3).to_bytes(4, "little") + b"{x}", "JSON"),
        (b"CMD1" + bytes([1]) + (2).to_bytes(4, "little") + b"{}", "T_base_tcp is missing"),
    ],
)
def test_malformed_payloads_are_refused(payload: bytes, match: str) -> None:
    with pytest.raises(InputError, match=match):
        cmd.decode(payload)


def test_truncated_arrays_and_bad_values_are_refused() -> None:
    good = cmd.encode(cmd.move_to(np.eye(4)))
    with pytest.raises(InputError, match="bytes"):
        cmd.decode(good[:-8])
    with pytest.raises(InputError, match="speed_scale"):
        cmd.move_to(np.eye(4), speed_scale=2.0)
    with pytest.raises(InputError, match="speed_scale: expected at least"):
        cmd.move_joints(np.zeros(6), speed_scale=1e-9)  # a plan degenerate enough to stall the loop
    with pytest.raises(InputError, match="rotation"):
        cmd.move_to(np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(InputError, match="NaN"):
        cmd.start_servo(ServoPlan("x", {"P_base": np.array([[np.nan, 0.0, 0.0]])}, {}))
