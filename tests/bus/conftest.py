"""Fixtures for bus tests: a cell served on its own loopback address from an asyncio loop thread."""

from __future__ import annotations

import asyncio
import socket
import threading
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pytest

from celld.bus.keys import CellKeys
from celld.bus.server import BusServer
from celld.bus.session import ServerSession, callers, open_server
from celld.config import BusConfig, BusUser
from celld.journal import Journal
from tests.standin import DummyCell


def free_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class LoopThread:
    """An asyncio loop on a thread of its own, as the daemon has it."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="test-loop", daemon=True)
        self.thread.start()

    def run(self, coro: Coroutine[Any, Any, Any], timeout: float = 10.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def stop(self) -> None:
        async def cancel_all() -> None:
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        self.run(cancel_all())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5.0)
        self.loop.close()


@dataclass
class ServedCell:
    """A cell on the bus: its config, keys, server, handlers and journal."""

    bus: BusConfig
    keys: CellKeys
    server: BusServer
    cell: DummyCell
    journal: Journal
    session: ServerSession
    loop: LoopThread

    def client_bus(self, user: str = "", password: str = "") -> BusConfig:
        """The bus config a client of this cell uses, with these credentials."""
        return replace(self.bus, user=user, password=password, connect_timeout=2.0, query_timeout=3.0)

    def close(self) -> None:
        self.loop.run(self.server.close())
        self.loop.run(self.cell.close())
        self.session.close()
        self.journal.close()


@pytest.fixture
def loop_thread() -> Iterator[LoopThread]:
    lt = LoopThread()
    yield lt
    lt.stop()


@pytest.fixture
def serve_cell(loopback_host: str, tmp_path: Path, loop_thread: LoopThread) -> Iterator[Callable[..., ServedCell]]:
    """Factory: serve a DummyCell named ``name`` on ``loopback_host`` (a fresh port each)."""
    served: list[ServedCell] = []

    def make(
        name: str = "cell-a",
        users: tuple[BusUser, ...] = (),
        job_duration: float = 0.05,
        handlers: Any = None,
        mode: str = "peer",
        connect: tuple[str, ...] = (),
        tls: Any = None,
        **server_options: Any,
    ) -> ServedCell:
        proto = "tls" if tls is not None else "tcp"
        listen = () if mode == "client" else (f"{proto}/{loopback_host}:{free_port(loopback_host)}",)
        bus = BusConfig(mode=mode, listen=listen, connect=connect, users=users, tls=tls)
        keys = CellKeys.of(bus.prefix, name)
        journal = Journal(tmp_path / name / "jobs.sqlite3")
        cell = DummyCell(name, journal, job_duration=job_duration)
        session = open_server(bus, keys)
        server = BusServer(session.session, keys, handlers or cell, callers=callers(bus), **server_options)
        cell.attach(server)
        loop_thread.run(server.start())
        s = ServedCell(bus, keys, server, cell, journal, session, loop_thread)
        served.append(s)
        return s

    yield make
    for s in served:
        if not s.session.session.is_closed():
            s.close()
