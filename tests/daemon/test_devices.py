"""CellDevices' supervision of the tactile process (the motion process's has its own tests)."""

from __future__ import annotations

import asyncio

from celld.config import Config
from celld.daemon import devices as devices_mod
from celld.daemon.devices import CellDevices
from celld.errors import DeviceError
from celld.supervision import Backoff


class FakeTactile:
    def __init__(self, fail: bool = False) -> None:
        self.up = True
        self.fail = fail
        self.restarts = 0
        self.exitcode: int | None = None

    def alive(self) -> bool:
        return self.up

    def restart(self) -> int | None:
        self.restarts += 1
        if self.fail:
            raise DeviceError("the tactile process exited at start (exit code 1)")
        self.up = True
        return self.exitcode


def test_a_dead_tactile_process_is_restarted_with_a_delay_between_attempts(monkeypatch) -> None:
    async def scenario() -> None:
        dev = CellDevices(Config())
        dev.tactile = FakeTactile()
        await dev.supervise_tactile()
        assert dev.tactile.restarts == 0  # alive: left alone
        dev.tactile.up, dev.tactile.exitcode = False, -9
        await dev.supervise_tactile()
        assert dev.tactile.restarts == 1 and dev.tactile.alive()

        failing = FakeTactile(fail=True)
        failing.up = False
        dev.tactile = failing
        monkeypatch.setattr(devices_mod, "TACTILE_BACKOFF", Backoff(delays=(3600.0,)))
        await dev.supervise_tactile()  # restarted just before: waits
        assert failing.restarts == 0
        monkeypatch.setattr(devices_mod, "TACTILE_BACKOFF", Backoff(delays=(0.0,)))
        await dev.supervise_tactile()
        await dev.supervise_tactile()  # a failed restart is logged and tried again, never raised
        assert failing.restarts == 2 and not failing.alive()
        assert dev._tactile_failures == 2 and "exited at start" in dev.tactile_error  # the wait doubles each time
        failing.fail = False
        await dev.supervise_tactile()
        assert failing.alive() and dev.tactile_error == "" and dev._tactile_failures == 0

        dev.tactile = None
        await dev.supervise_tactile()  # a cell without a finger camera: nothing to do

    asyncio.run(asyncio.wait_for(scenario(), 10))
