"""The daemon's start-up order: a second daemon on a state directory in use changes nothing in it."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from celld import config, fsutil
from celld.daemon.app import Daemon
from celld.errors import JournalError
from celld.journal import Journal


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
