"""RtdeLink through stand-ins for ur-rtde's interfaces: the process output, and the loop's calls on a dropped link."""

from __future__ import annotations

import pytest

from celld.errors import LinkLost
from celld.robot.link import RtdeLink


class IO:
    def __init__(self, reply: object) -> None:
        self.reply = reply
        self.calls: list[tuple[int, bool]] = []

    def setStandardDigitalOut(self, output_id: int, signal_level: bool) -> bool:
        self.calls.append((output_id, signal_level))
        if isinstance(self.reply, Exception):
            raise self.reply
        return self.reply  # type: ignore[return-value]


def test_set_digital_out_sets_the_standard_output_and_passes_on_the_reply() -> None:
    io = IO(True)
    link = RtdeLink("127.0.0.9", object(), object(), io)
    assert link.set_digital_out(3, True) is True
    assert link.set_digital_out(3, False) is True
    assert io.calls == [(3, True), (3, False)]
    io.reply = False
    assert link.set_digital_out(3, True) is False


def test_set_digital_out_on_a_lost_link_returns_false_instead_of_raising() -> None:
    io = IO(RuntimeError("RTDEIOInterface: could not reconnect"))
    link = RtdeLink("127.0.0.9", object(), object(), io)
    assert link.set_digital_out(0, False) is False
    assert io.calls == [(0, False)]


class _Dropped:
    """ur-rtde's control and receive interfaces on a link that has just dropped: every call tries to reconnect and fails."""

    def __getattr__(self, name: str):
        def call(*args: object) -> object:
            raise RuntimeError("Error: Could not connect to: 127.0.0.9 at 30004, verify the IP")

        return call


@pytest.mark.parametrize(
    "what, call",
    [
        ("speedL", lambda link: link.speed([0.0] * 6, 1.0)),
        ("speedJ", lambda link: link.speed_joints([0.0] * 6, 1.0)),
        ("kicking the watchdog", lambda link: link.kick()),
        ("reading the robot state", lambda link: link.read()),
    ],
)
def test_a_loop_call_on_a_dropped_link_is_the_link_lost_not_a_crash(what: str, call) -> None:
    # Raised as ur-rtde raises it, the motion process took it for a fault of its own ("motion process
    # failed"), not the link's, and the job heard of a failure instead of the lost link it was.
    link = RtdeLink("127.0.0.9", _Dropped(), _Dropped(), IO(True))
    with pytest.raises(LinkLost, match=f"robot 127.0.0.9: {what} failed: Error: Could not connect"):
        call(link)
