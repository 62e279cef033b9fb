"""The daemon's start-up: a second daemon on a state directory in use changes nothing in it; a damaged journal is
a storage fault the status names with its way out, and the daemon serves with its devices away."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from celld import config, fsutil
from celld.bus.client import CellClient
from celld.cli import main
from celld.daemon.app import Daemon
from celld.errors import JobError, JournalError
from celld.journal import Journal
from celld.robot.dashboard import robot_condition
from tests.bus.conftest import free_port
from tests.test_journal import DAMAGED_PAGE, damaged_journal


class NoDevices:
    """Devices a daemon must not reach before its state directory is its own."""

    def __getattr__(self, name: str) -> None:
        raise AssertionError(f"the daemon touched its devices ({name}) before it held its state directory")


def test_a_second_daemon_on_a_state_directory_in_use_is_refused_before_it_touches_it(tmp_path: Path) -> None:
    state = tmp_path / "state"
    cfg = config.parse({"cell": {"state_dir": str(state)}, "robot": {"host": "127.0.0.9"}})
    with Journal(state / "journal.db"):  # the running daemon
        in_flight = state / "results" / f".job-7.json{fsutil.TEMP_SUFFIX}"
        in_flight.parent.mkdir(parents=True)
        in_flight.write_text('{"half": ')  # its atomic write of a result, in flight
        with pytest.raises(JournalError, match="held by another process"):
            asyncio.run(Daemon(cfg, NoDevices(), {}).start())
        assert in_flight.read_text() == '{"half": '


class AwayDevices:
    """A cell whose devices are all away (robot off, no scanner, no camera): enough for the daemon to serve."""

    WHY = "robot link down: waiting (no link to the robot: a test)"

    def __init__(self) -> None:
        self.life = SimpleNamespace(exit_notes=[])
        self.tactile = SimpleNamespace(state_message=lambda: None, supervise=_nothing)
        self.scanner = SimpleNamespace(supervise=_nothing)

    async def open(self, loop_ticked) -> None:
        pass

    async def close(self) -> None:
        pass

    async def stop_robot(self) -> None:
        pass

    async def robot_action(self, action: str) -> dict:
        raise AssertionError("no robot command here")

    def link_state(self) -> str:
        return "down"

    def robot_report(self) -> dict:
        return {**robot_condition("down", None).as_dict(), "link": "down", "mode": None, "safety": None, "dashboard": "not read yet"}

    def unready(self, kind: str, dry_run: bool = False) -> str:
        return "" if kind == "health" else self.WHY

    def waiting(self) -> list[str]:
        return [self.WHY]

    def supervised(self) -> bool:
        return True

    def heartbeat_age(self) -> None:
        return None

    def robot_state_message(self) -> None:
        return None


async def _nothing() -> None:
    pass


def _away_config(name: str, state: Path, host: str) -> config.Config:
    """A cell of AwayDevices on its own loopback address, its jobs not recorded."""
    return config.parse(
        {
            "cell": {"name": name, "state_dir": str(state)},
            "robot": {"host": host},
            "bus": {"listen": [f"tcp/{host}:{free_port(host)}"]},
            "recording": {"enabled": False},
        }
    )


async def _serve_and_ask(cfg: config.Config, ask) -> object:
    """Start a daemon on AwayDevices, run ``ask(client)`` on a worker thread, stop the daemon; ``ask``'s answer."""

    async def health(ctx) -> dict:
        return {"checks": {}}

    daemon = Daemon(cfg, AwayDevices(), {"health": health, "move": health})
    try:
        await daemon.start()

        def asking() -> object:
            with CellClient(cfg.bus, cfg.cell.name, timeout=10.0) as client:
                return ask(client)

        return await asyncio.to_thread(asking)
    finally:
        await daemon.shutdown()


@pytest.mark.parametrize("where", DAMAGED_PAGE)
def test_a_damaged_journal_is_a_storage_fault_that_names_its_way_out_and_nothing_is_lost(
    tmp_path: Path, loopback_host: str, where: str
) -> None:
    state = tmp_path / "state"
    cfg = _away_config("damaged", state, loopback_host)
    damaged_journal(state / "journal.db", DAMAGED_PAGE[where])

    def refused(client: CellClient) -> dict:
        status = client.status()
        with pytest.raises(JobError, match=r"refused: storage: the job journal .*journal.db is damaged: .*celld journal set-aside"):
            client.submit({"kind": "health"})
        with pytest.raises(JobError, match=r"journal.db is damaged"):
            client.list()
        return status

    status = asyncio.run(_serve_and_ask(cfg, refused))
    assert status["state"] == "fault" and "journal.db is damaged" in status["message"] and "celld journal set-aside" in status["message"]
    assert not status["storage"]["ok"] and "is damaged" in status["storage"]["fault"]
    # The way out: the damaged journal set aside, kept; the daemon starts on a new one and takes jobs.
    config_path = tmp_path / "cell.toml"
    config_path.write_text(f'[cell]\nstate_dir = "{state}"\n[robot]\nhost = "{loopback_host}"\n')
    assert main(["journal", "set-aside", "--config", str(config_path)]) == 0
    assert len(list(state.glob("journal-set-aside-*.db"))) == 1

    def served(client: CellClient) -> dict:
        # Nothing needs the robot in a health job; a move waits for it and says so.
        with pytest.raises(JobError, match=r"refused: robot link down: waiting \(no link to the robot"):
            client.submit({"kind": "move", "target": {"space": "joint", "q": [0, -1.57, 1.57, -1.57, -1.57, 0]}})
        _, record = client.submit_and_wait({"kind": "health"}, timeout=20)
        return {"record": record, "status": client.status()}

    got = asyncio.run(_serve_and_ask(cfg, served))
    assert got["record"]["state"] == "succeeded", got["record"]
    assert got["status"]["storage"]["ok"] and got["status"]["message"] == AwayDevices.WHY


def test_a_recording_the_previous_daemon_left_open_is_finalised_and_its_job_says_so(tmp_path: Path, loopback_host: str) -> None:
    import subprocess
    import sys

    from tests.recording.test_job import _DIES_MID_JOB

    state = tmp_path / "state"
    cfg = _away_config("restarted", state, loopback_host)
    with Journal(state / "journal.db") as journal:  # the previous daemon, killed while its job ran and recorded
        job = journal.create("calibrate", {"kind": "calibrate"}, start=True).id
    subprocess.run([sys.executable, "-c", _DIES_MID_JOB, str(state), job], check=False, timeout=60)
    assert (state / "recordings" / f"{job}.rrd.part").is_file()

    def noted(client: CellClient) -> dict:  # the merge runs once the daemon serves
        deadline = time.monotonic() + 20
        while "recording" not in (record := client.status(job))["reason"] and time.monotonic() < deadline:
            time.sleep(0.1)
        return record

    record = asyncio.run(_serve_and_ask(cfg, noted))
    assert record["state"] == "interrupted"
    assert record["reason"] == (
        f"interrupted: the daemon stopped while the job was running; its recording was cut short when the daemon stopped: "
        f"what was written is in {state / 'recordings' / f'{job}.rrd'}"
    )
    assert (state / "recordings" / f"{job}.rrd").is_file() and not (state / "recordings" / f"{job}.rrd.part").exists()
