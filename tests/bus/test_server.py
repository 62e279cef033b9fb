"""BusServer and CellClient over real zenoh (peer mode, loopback): every request is answered."""

from __future__ import annotations

import asyncio
import itertools
import json
import time
from collections.abc import Mapping
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings

from celld.bus import messages, requests
from celld.bus.client import CellClient
from celld.errors import BusError, JobError
from tests.bus.strategies import HOSTILE_PAYLOADS, hostile_jobs

CALIBRATE = {"kind": "calibrate", "n_poses": 6, "e_required_mm": 0.3}
MS = timedelta(milliseconds=1)


def _wall(text: str) -> datetime:
    """A bus message's ``time`` (UTC, ISO 8601 with a Z)."""
    return datetime.fromisoformat(text)


def wait_until(condition, timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


@pytest.fixture
def cell(serve_cell):
    return serve_cell()


@pytest.fixture
def client(cell):
    with CellClient(cell.client_bus(), cell.keys.cell) as c:
        yield c


def test_submit_returns_a_job_id_and_the_job_runs_to_success(cell, client) -> None:
    reply = client.submit(CALIBRATE)
    messages.check_message("submit-reply", reply)
    assert reply["state"] == "running" and reply["position"] == 0
    record = client.watch_progress().wait(reply["job"], timeout=5.0)
    assert record["state"] == "succeeded"
    assert record["params"] == CALIBRATE
    assert cell.journal.get(reply["job"]).state == "succeeded"


def test_second_job_queues_and_reply_says_so(serve_cell) -> None:
    cell = serve_cell(job_duration=1.0)
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        first = client.submit({"kind": "health"})
        second = client.submit({"kind": "health", "check": "robot"})
        assert (first["state"], second["state"], second["position"]) == ("running", "queued", 1)
        status = client.status()
        messages.check_message("status-reply", status)
        assert status["running"] == first["job"] and status["queued"] == [second["job"]]
        assert client.cancel(second["job"])["state"] == "cancelled"
        assert client.cancel(first["job"])["state"] == "cancelled"
        assert [r["state"] for r in client.list(limit=2)] == ["cancelled", "cancelled"]


def test_full_queue_refuses_with_a_reason(serve_cell) -> None:
    cell = serve_cell(job_duration=5.0)
    cell.cell.queue_depth = 1
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        client.submit({"kind": "health"})
        client.submit({"kind": "health"})
        with pytest.raises(JobError) as err:
            client.submit({"kind": "health"})
        assert err.value.field == "$" and "refused" in err.value.reason
        assert len(cell.journal.jobs()) == 2


def test_progress_events_are_numbered_and_end_terminal(cell, client) -> None:
    events: list[dict[str, Any]] = []
    before = datetime.now(UTC)
    with client.watch_progress() as watch:
        reply = client.submit({"kind": "health"})
        watch.wait(reply["job"], events.append, timeout=5.0)
    after = datetime.now(UTC)
    for e in events:
        messages.check_message("progress", e)
    assert [e["seq"] for e in events] == list(range(len(events)))
    # Each event says when it happened, on the wall clock (to the millisecond), in order.
    times = [_wall(e["time"]) for e in events]
    assert times == sorted(times) and before - MS <= times[0] and times[-1] <= after + MS, (before, times, after)
    # queued, start, one per step, end.
    assert [e["stage"] for e in events] == ["queued", "start"] + ["wait"] * cell.cell.steps + ["end"]
    assert events[-1]["state"] == "succeeded"


def test_status_list_accept_calibration_replies_match_their_schemas(cell, client) -> None:
    assert client.calibration() is None
    reply = client.submit(CALIBRATE)
    client.watch_progress().wait(reply["job"], timeout=5.0)
    record = client.status(reply["job"])
    messages.check_message("job-reply", {"ok": True, "record": record})
    messages.check_message("list-reply", {"ok": True, "jobs": client.list()})
    accepted = client.accept(reply["job"])
    messages.check_message("accept-reply", accepted)
    current = client.calibration()
    messages.check_message("calibration-reply", {"ok": True, "calibration": current})
    assert current["job"] == reply["job"]


def test_unknown_job_is_refused_with_the_field(client) -> None:
    with pytest.raises(JobError) as err:
        client.status("20250101-000000-abcdef")
    assert err.value.field == "$.job" and "no such job" in err.value.reason


def test_hostile_payloads_each_get_an_error_reply_and_the_server_stays_up(cell, client) -> None:
    for payload in HOSTILE_PAYLOADS:
        reply = client.request_raw("submit", payload)
        messages.check_message("error-reply", reply)
        assert reply["error"]["reason"], payload[:40]
    assert client.status()["state"] == "idle"
    assert cell.journal.jobs() == [] and cell.journal.check() == []


def test_a_wildcard_query_gets_one_reply_per_queryable_on_its_own_key(cell, client) -> None:
    replies = list(client.session.get(f"{cell.keys.base}/*", timeout=3.0))
    keys = sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)
    assert keys == sorted(cell.keys.query(q) for q in ("submit", "status", "cancel", "list", "accept", "calibration", "robot"))
    assert cell.journal.jobs() == []  # an empty submit is refused ($.kind missing)


def test_requests_of_every_queryable_with_garbage_get_errors(client) -> None:
    for name in ("status", "cancel", "list", "accept", "calibration", "robot"):
        reply = client.request_raw(name, b'{"bogus": 1}')
        assert reply["ok"] is False and reply["error"]["field"] == "$.bogus", (name, reply)


def _is_valid_submit(payload: bytes) -> bool:
    try:
        requests.parse_submit(payload)
    except JobError:
        return False
    return True


def test_fuzzed_submits_are_all_answered_and_the_journal_stays_intact(serve_cell) -> None:
    cell = serve_cell(job_duration=0.0)
    cell.cell.max_queue = 1000
    answered = {"ok": 0, "refused": 0}
    with CellClient(cell.client_bus(), cell.keys.cell) as client:

        @settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
        @given(hostile_jobs())
        def one(payload: bytes) -> None:
            reply = client.request_raw("submit", payload)
            messages.check_message("submit-reply" if reply["ok"] else "error-reply", reply)
            assert reply["ok"] == _is_valid_submit(payload)
            answered["ok" if reply["ok"] else "refused"] += 1

        one()
        assert client.status()["cell"] == cell.keys.cell
    assert sum(answered.values()) >= 200 and answered["refused"] > 150
    assert cell.journal.check() == []
    assert len(cell.journal.jobs(limit=1000)) == answered["ok"]


class _Faulty:
    """Handlers that fail in the ways a daemon bug could."""

    def __init__(self) -> None:
        self.slow_done = asyncio.Event()

    async def on_submit(self, job: Any, caller: Any = None) -> Mapping[str, Any]:
        raise RuntimeError("a bug")

    async def on_status(self, req: Any, caller: Any = None) -> Mapping[str, Any]:
        await asyncio.sleep(0.5)
        self.slow_done.set()
        return {"cell": "x", "state": "idle", "running": None, "queued": []}

    async def on_cancel(self, req: Any, caller: Any = None) -> Any:
        return ["not", "a", "mapping"]

    async def on_list(self, req: Any, caller: Any = None) -> Mapping[str, Any]:
        return {"jobs": [float("nan")]}

    async def on_accept(self, req: Any, caller: Any = None) -> Mapping[str, Any]:
        raise BusError("link down")

    async def on_calibration(self, req: Any, caller: Any = None) -> Mapping[str, Any]:
        return {"calibration": None}

    async def on_robot(self, req: Any, caller: Any = None) -> Mapping[str, Any]:
        raise RuntimeError("a handler's own bug")

    async def on_result(self, req: Any, caller: Any = None) -> Mapping[str, Any]:
        raise JobError("$.job", "no such job")


def test_handler_failures_become_error_replies(serve_cell) -> None:
    faulty = _Faulty()
    cell = serve_cell(handlers=faulty, reply_timeout=0.1)
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        replies = {
            "submit": client.request_raw("submit", b'{"kind": "health"}'),
            "status": client.request_raw("status", None),
            "cancel": client.request_raw("cancel", b'{"job": "abc"}'),
            "list": client.request_raw("list", None),
            "accept": client.request_raw("accept", b'{"job": "abc"}'),
        }
        assert all(r["ok"] is False for r in replies.values()), replies
        assert "internal error" in replies["submit"]["error"]["reason"]
        assert "may still take effect" in replies["status"]["error"]["reason"]
        assert "internal error" in replies["cancel"]["error"]["reason"]
        assert "not valid JSON" in replies["list"]["error"]["reason"]
        assert replies["accept"]["error"] == {"field": "", "reason": "link down"}
        assert client.calibration() is None
    assert cell.server.stats.internal_errors == 3 and cell.server.stats.timeouts == 1


def test_busy_server_answers_busy_without_queueing(serve_cell) -> None:
    faulty = _Faulty()
    cell = serve_cell(handlers=faulty, max_pending=1)
    bus = cell.client_bus()
    with CellClient(bus, cell.keys.cell) as client:
        # The first status holds the only slot for 0.5 s; a second one meanwhile is busy.
        pending = client.session.get(cell.keys.query("status"), timeout=3.0)
        wait_until(lambda: cell.server.stats.requests == 1)
        reply = client.request_raw("status", None)
        assert reply["ok"] is False and reply["error"]["reason"].startswith("busy")
        first = [json.loads(r.ok.payload.to_bytes()) for r in pending if r.ok is not None]
        assert first and first[0]["ok"] is True
    assert cell.server.stats.busy == 1


def test_state_publications_are_decimated(cell) -> None:
    robot: list[dict[str, Any]] = []
    tactile: list[dict[str, Any]] = []
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        subs = [client.subscribe_state("robot", robot.append), client.subscribe_state("tactile", tactile.append)]
        # Warm up on the tactile stream: once a sample arrives, both subscriptions reached the cell.
        t_ns = 0
        while not tactile:
            t_ns += 10**9
            cell.server.publish_tactile_state({"t_ns": t_ns, "valid": True}, now_ns=t_ns)
            time.sleep(0.01)
        period_ns = int(1e9 / 20.0)
        t0 = time.monotonic_ns()
        stamps = [t0 + i * period_ns // 10 for i in range(50)]  # 10x the rate, over 2.5 periods
        sent = [cell.server.publish_robot_state({"t_ns": t, "link": "up"}, now_ns=t) for t in stamps]
        wait_until(lambda: len(robot) >= 5)
        time.sleep(0.05)
        for s in subs:
            s.undeclare()
    assert sum(sent) == 5 and [i for i, ok in enumerate(sent) if ok] == [0, 10, 20, 30, 40]
    assert [r["t_ns"] for r in robot] == [stamps[i] for i in (0, 10, 20, 30, 40)]
    for r in robot + tactile:
        messages.check_message("state-robot" if "link" in r else "state-tactile", r)
    # A sample's wall-clock time is its own (t_ns on the monotonic clock), not when it was sent: 50 ms apart here.
    gaps = [(_wall(b["time"]) - _wall(a["time"])).total_seconds() for a, b in itertools.pairwise(robot)]
    assert all(abs(g - 0.050) <= 0.0015 for g in gaps), gaps


def test_a_state_sample_is_stamped_with_its_own_time_on_the_wall_clock(cell) -> None:
    robot: list[dict[str, Any]] = []
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        sub = client.subscribe_state("robot", robot.append)
        while not robot:
            t_ns = time.monotonic_ns() - 2 * 10**9  # samples taken two seconds ago
            cell.server.publish_robot_state({"t_ns": t_ns, "link": "up"}, now_ns=t_ns)
            time.sleep(0.01)
        cell.server.publish_robot_state({"t_ns": 0, "link": "down"}, now_ns=t_ns + 10**9)  # no sample: the link is down
        wait_until(lambda: robot[-1]["link"] == "down")
        sub.undeclare()
    now, now_ns = datetime.now(UTC), time.monotonic_ns()
    first = robot[0]
    # Its age on the wall clock is its age on the monotonic one (two seconds and a little), not the moment it was sent.
    age = (now - _wall(first["time"])).total_seconds()
    assert first["t_ns"] < now_ns - 2 * 10**9 and abs(age - (now_ns - first["t_ns"]) * 1e-9) < 0.02, (age, first)
    # A sample without its own time (t_ns 0) is stamped when it is sent.
    assert abs((now - _wall(robot[-1]["time"])).total_seconds()) < 0.25


def test_no_cell_no_reply_is_a_bus_error(cell) -> None:
    bus = cell.client_bus()
    with CellClient(bus, "other-cell", timeout=0.5) as client:
        with pytest.raises(BusError, match="no reply"):
            client.status()


def test_client_without_a_listening_cell_fails_to_connect(loopback_host) -> None:
    from celld.config import BusConfig

    bus = BusConfig(listen=(f"tcp/{loopback_host}:9",), connect_timeout=0.3)
    t0 = time.monotonic()
    with pytest.raises(BusError, match="no link"):
        CellClient(bus, "cell-a")
    assert time.monotonic() - t0 < 2.0


def test_close_answers_in_flight_requests_and_withdraws_the_token(serve_cell) -> None:
    faulty = _Faulty()
    cell = serve_cell(handlers=faulty)
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        alive = [str(r.ok.key_expr) for r in client.session.liveliness().get(cell.keys.alive, timeout=1.0) if r.ok]
        assert alive == [cell.keys.alive]
        pending = client.session.get(cell.keys.query("status"), timeout=3.0)
        wait_until(lambda: cell.server.stats.requests == 1)
        cell.loop.run(cell.server.close())
        replies = [json.loads(r.ok.payload.to_bytes()) for r in pending if r.ok is not None]
        assert replies == [{"ok": False, "error": {"field": "", "reason": "the cell is shutting down"}}]
        wait_until(lambda: not [r for r in client.session.liveliness().get(cell.keys.alive, timeout=0.5) if r.ok])
