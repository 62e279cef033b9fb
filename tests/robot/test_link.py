"""RtdeLink's process output through ur-rtde's IO interface (a stand-in for the interface)."""

from __future__ import annotations

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
