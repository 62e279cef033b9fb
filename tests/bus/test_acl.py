"""Access control over real zenoh: passwords and roles decide who may connect, submit and read."""

from __future__ import annotations

from dataclasses import replace

import pytest

from celld.bus.client import CellClient, discover_cells
from celld.config import BusUser
from celld.errors import BusError

USERS = (BusUser("olga", "op-secret", "operator"), BusUser("vic", "view-secret", "viewer"))


@pytest.fixture
def cell(serve_cell):
    return serve_cell(users=USERS)


def test_operator_may_submit_cancel_and_read(cell) -> None:
    with CellClient(cell.client_bus("olga", "op-secret"), cell.keys.cell) as client:
        reply = client.submit({"kind": "health"})
        assert client.status(reply["job"])["kind"] == "health"
        assert client.list(limit=1)[0]["id"] == reply["job"]
    assert len(cell.journal.jobs()) == 1


def test_viewer_may_read_but_not_submit_cancel_or_accept(cell) -> None:
    with CellClient(cell.client_bus("vic", "view-secret"), cell.keys.cell) as client:
        assert client.status()["state"] == "idle"
        assert client.list() == []
        assert client.calibration() is None
        assert discover_cells(cell.client_bus("vic", "view-secret"), session=client.session) == [cell.keys.cell]
        for call in (lambda: client.submit({"kind": "health"}), lambda: client.cancel("abc"), lambda: client.accept("abc")):
            with pytest.raises(BusError, match="no reply"):
                call()
    assert cell.journal.jobs() == []


def test_viewer_receives_progress_events(cell) -> None:
    with (
        CellClient(cell.client_bus("vic", "view-secret"), cell.keys.cell) as viewer,
        CellClient(cell.client_bus("olga", "op-secret"), cell.keys.cell) as operator,
    ):
        with viewer.watch_progress() as events:
            reply = operator.submit({"kind": "health"})
            record = events.wait(reply["job"], timeout=5.0)
        assert record["state"] == "succeeded"


@pytest.mark.parametrize(("user", "password"), [("olga", "wrong"), ("mallory", "op-secret"), ("", "")])
def test_wrong_or_missing_credentials_cannot_connect(cell, user: str, password: str) -> None:
    bus = replace(cell.client_bus(user, password), connect_timeout=0.5)
    with pytest.raises(BusError, match="no link"):
        CellClient(bus, cell.keys.cell)
    assert cell.journal.jobs() == []
