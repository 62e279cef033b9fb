"""Fleets: several cells on one zenoh network, found through their liveliness tokens."""

from __future__ import annotations

import time
from dataclasses import replace

from celld.bus.client import CellClient, discover_cells


def test_two_peer_cells_are_discovered_and_one_leaving_is_noticed(serve_cell) -> None:
    a = serve_cell("cell-a")
    b = serve_cell("cell-b")
    # A client on the cell PC of a, told where b listens.
    bus = replace(a.client_bus(), connect=b.bus.listen)
    assert discover_cells(bus) == ["cell-a", "cell-b"]
    with CellClient(bus, "cell-b") as client:
        assert client.status()["cell"] == "cell-b"
    b.close()
    time.sleep(0.1)
    assert discover_cells(bus) == ["cell-a"]


def test_cells_in_client_mode_behind_a_router_cell(serve_cell) -> None:
    hub = serve_cell("cell-hub", mode="router")
    leaf = serve_cell("cell-leaf", mode="client", connect=hub.bus.listen)
    # The CLI of a client-mode cell connects where the cell does: to the router.
    bus = replace(leaf.client_bus(), connect=hub.bus.listen)
    assert discover_cells(bus) == ["cell-hub", "cell-leaf"]
    with CellClient(bus, "cell-leaf") as client:
        reply = client.submit({"kind": "health"})
        assert client.watch_progress().wait(reply["job"], timeout=5.0)["state"] == "succeeded"
