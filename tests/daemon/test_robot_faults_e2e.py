"""A protective stop seen and cleared through the daemon, with the systemd watchdog kept all along.

The daemon runs as systemd would start it, with a notify socket and
``WATCHDOG_USEC`` of 2 s (it kicks every second): the simulated robot raises
a protective stop; ``celld status`` says why the robot is down and what
clears it; an unlock too early is refused with the controller's reason, an
operator's command during a job is refused, the unlock after 5 s brings the
link back, and a move succeeds. No kick is missed meanwhile.
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import pytest

from celld.errors import JobError
from tests.daemon.test_daemon_e2e import e2e_config

pytestmark = pytest.mark.cell

WATCHDOG_USEC = 2_000_000


class NotifyReceiver:
    """A datagram socket standing in for systemd's NOTIFY_SOCKET: what the daemon sends, and when."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[tuple[float, str]] = []
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            for line in data.decode().splitlines():
                self.messages.append((time.monotonic(), line))

    def kicks(self, since: float) -> list[float]:
        return [t for t, m in self.messages if m == "WATCHDOG=1" and t >= since]

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=2.0)
        self.sock.close()


def _wait(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


def test_a_protective_stop_is_explained_refused_early_cleared_and_the_watchdog_kept(
    tmp_path: Path, cell_config, monkeypatch: pytest.MonkeyPatch
) -> None:
    from celld.sim.cell import run_cell

    receiver = NotifyReceiver(tmp_path / "notify.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify.sock"))
    monkeypatch.setenv("WATCHDOG_USEC", str(WATCHDOG_USEC))
    cfg_path = e2e_config(cell_config, recording=False)
    try:
        with run_cell(cfg_path, tmp_path / "daemon.log", timeout=60) as cell:
            client, robot = cell.client, cell.robot
            _wait(lambda: any(m == "READY=1" for _, m in receiver.messages), 30, "READY=1")
            t_ready = time.monotonic()
            status = _wait(lambda: client.status()["robot"]["ready"] and client.status(), 10, "robot ready")
            assert status["robot"]["mode"] == "RUNNING" and status["robot"]["safety"] == "NORMAL"

            robot.inject("protective_stop")
            t_stop = time.monotonic()
            down = _wait(lambda: (r := client.status()["robot"])["state"] == "protective_stop" and r, 10, "protective stop seen")
            assert not down["ready"] and "protective stop" in down["reason"]
            assert "celld robot unlock" in down["remedy"]
            # Too early: refused with the controller's own reason, nothing changes.
            with pytest.raises(JobError, match="5s after occurrence"):
                client.robot("unlock")
            assert client.status()["robot"]["state"] == "protective_stop"
            # A job meanwhile is refused at once, and says why.
            with pytest.raises(JobError, match=r"refused: robot link down: waiting \(protective stop.*celld robot unlock"):
                client.submit({"kind": "move", "target": {"space": "cartesian", "pose": [0.62, 0.0, 0.45, 0, 0, 0]}})

            time.sleep(max(0.0, t_stop + 5.5 - time.monotonic()))
            reply = client.robot("unlock")
            assert reply["action"] == "unlock"
            _wait(lambda: client.status()["robot"]["ready"], 30, "the robot back after the unlock")

            # An operator's command while a job runs is refused.
            submitted = client.submit({"kind": "move", "target": {"space": "cartesian", "pose": [0.62, 0.03, 0.47, 0, 0, 0]}})
            _wait(lambda: client.status()["running"] == submitted["job"], 10, "the move running")
            with pytest.raises(JobError, match="is running"):
                client.robot("brake-release")
            record = _wait(lambda: (r := client.status(submitted["job"]))["state"] in ("succeeded", "failed") and r, 60, "the move ended")
            assert record["state"] == "succeeded", record["reason"]

            kicks = receiver.kicks(t_ready)
            t_end = time.monotonic()
    finally:
        receiver.close()
    gaps = [b - a for a, b in zip([t_ready, *kicks], [*kicks, t_end], strict=True)]
    # Kicked every second through the stop and the unlock: never near systemd's 2 s.
    assert max(gaps) < 1.6, max(gaps)
    assert len(kicks) >= (t_end - t_ready) / 1.2
