"""sd_notify: datagrams as systemd receives them, on a bound socket."""

from __future__ import annotations

import asyncio
import os
import socket
from pathlib import Path

import pytest

from celld.sdnotify import Notifier, run_watchdog, watchdog_interval


@pytest.fixture
def receiver(tmp_path: Path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify"
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield str(path), sock
    sock.close()


def test_messages_arrive_as_systemd_reads_them(receiver) -> None:
    path, sock = receiver
    with Notifier(path) as n:
        assert n.enabled
        assert n.ready("robot link up")
        assert sock.recv(4096) == b"READY=1\nSTATUS=robot link up"
        assert n.watchdog() and sock.recv(4096) == b"WATCHDOG=1"
        assert n.stopping() and sock.recv(4096) == b"STOPPING=1"
        assert n.status("two\nlines") and sock.recv(4096) == b"STATUS=two lines"
        with pytest.raises(ValueError):
            n.notify("READY")


def test_abstract_socket_names(monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"celld-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        with Notifier() as n:
            assert n.ready()
        assert sock.recv(64) == b"READY=1"
    finally:
        sock.close()


def test_no_socket_is_a_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier()
    assert not n.enabled and n.ready() is False and n.watchdog() is False


def test_a_vanished_socket_is_not_fatal(tmp_path: Path) -> None:
    n = Notifier(str(tmp_path / "gone"))
    assert n.ready() is False and n.watchdog() is False and n.failures == 2


def test_watchdog_interval_is_half_of_watchdog_usec() -> None:
    assert watchdog_interval({"WATCHDOG_USEC": "2000000"}) == 1.0
    assert watchdog_interval({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, pid=2) is None
    assert watchdog_interval({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "7"}, pid=7) == 1.0
    assert watchdog_interval({}) is None and watchdog_interval({"WATCHDOG_USEC": "x"}) is None


def test_watchdog_kicks_only_while_healthy(receiver) -> None:
    path, sock = receiver
    sock.setblocking(False)
    healthy = {"now": True}
    skipped: list[int] = []

    async def scenario() -> None:
        task = asyncio.create_task(run_watchdog(Notifier(path), lambda: healthy["now"], 0.01, lambda: skipped.append(1)))
        await asyncio.sleep(0.055)
        healthy["now"] = False
        await asyncio.sleep(0.05)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)

    asyncio.run(scenario())
    kicks = []
    while True:
        try:
            kicks.append(sock.recv(64))
        except BlockingIOError:
            break
    assert set(kicks) == {b"WATCHDOG=1"} and 3 <= len(kicks) <= 7
    assert len(skipped) >= 3
