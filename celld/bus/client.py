"""The client side of the bus: :class:`CellClient` for one cell, :func:`discover_cells` for a fleet.

The CLI is built on this module; MES connectors and scripts can use it the
same way::

    with CellClient(config.load("/etc/celld/cell.toml").bus, "cell-01") as cell:
        with cell.watch_progress() as events:     # subscribe before submitting
            reply = cell.submit({"kind": "calibrate", "n_poses": 12, "request_id": "order-7-step-1"})
            record = events.wait(reply["job"], on_event=print)
        result = cell.result(reply["job"])["result"]

With a user (``user=`` or ``bus.user``) the client sends its requests to that
user's keys (``<prefix>/<cell>/u/<user>/...``), which is what a cell with
``bus.users`` answers; without one, to the open bus's ``<prefix>/<cell>/...``.

Calls are synchronous (zenoh's ``get`` blocks the calling thread); from
asyncio code run them with ``asyncio.to_thread``. A refused request raises
:class:`~celld.errors.JobError` with the field and reason the cell gave (or
found locally: ``submit`` validates the message before sending it); no
reply, a timeout or a malformed reply raise :class:`~celld.errors.BusError`.
"""

from __future__ import annotations

import json
import queue
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import zenoh

from celld.bus.checker import describe
from celld.bus.keys import CellKeys, alive_all, cell_of_alive_key
from celld.bus.messages import TERMINAL_STATES
from celld.bus.requests import parse_submit
from celld.bus.session import open_client
from celld.bus.wire import encode
from celld.config import BusConfig
from celld.errors import BusError, JobError

# Progress events kept while nobody reads them; older ones are dropped.
_EVENT_BACKLOG = 1024
# With no event for this long, wait() asks status instead, s.
_STATUS_POLL = 1.0
# Default wait for liveliness replies, s.
DISCOVERY_TIMEOUT = 1.0
# A fresh session may not know a cell's queryables yet: a request that reaches
# none is sent again for up to this long after the client was made, s.
_SETTLE = 1.0
# Pause between such attempts, s.
_SETTLE_STEP = 0.02


def _decode_reply(data: bytes, where: str) -> dict[str, Any]:
    try:
        value = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise BusError(f"{where}: the reply is not JSON: {exc}") from exc
    if not isinstance(value, dict) or not isinstance(value.get("ok"), bool):
        raise BusError(f"{where}: expected a reply object with 'ok', got {describe(value)}")
    return value


def _describe_reply_error(reply: Any) -> str:
    try:
        return reply.err.payload.to_string()
    except Exception:  # an error without a text payload  # noqa: BLE001
        return "error"


class CellClient:
    """Requests to one cell, and its progress events.

    Parameters
    ----------
    bus : BusConfig
        Bus settings; the session follows :func:`celld.bus.session.open_client`.
    cell : str
        The cell's name (``cell.name`` in its config).
    user, password : str, optional
        Credentials; default ``bus.user`` and ``bus.password``.
    session : zenoh.Session, optional
        Share an open session (several cells, one link); it is not closed here.
    timeout : float, optional
        Reply timeout, s; default ``bus.query_timeout``.
    """

    def __init__(
        self,
        bus: BusConfig,
        cell: str,
        *,
        user: str | None = None,
        password: str | None = None,
        session: zenoh.Session | None = None,
        timeout: float | None = None,
    ) -> None:
        self.keys = CellKeys.of(bus.prefix, cell)
        self.user = bus.user if user is None else user
        self.timeout = bus.query_timeout if timeout is None else timeout
        self._owns_session = session is None
        self.session = open_client(bus, user, password) if session is None else session
        self._settle_until = time.monotonic() + min(_SETTLE, bus.connect_timeout)

    def close(self) -> None:
        if self._owns_session and not self.session.is_closed():
            self.session.close()

    def __enter__(self) -> CellClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- requests ---------------------------------------------------------------------

    def key(self, name: str) -> str:
        """Where this client's ``name`` requests go (its user's keys on a bus with users)."""
        return self.keys.query(name, self.user)

    def request_raw(self, name: str, payload: bytes | None, key: str | None = None) -> dict[str, Any]:
        """Send ``payload`` as it is to queryable ``name`` (or to ``key``); return the decoded reply, ok or not.

        Raises
        ------
        BusError
            No reply (the cell is down, or the ACL dropped the query), a
            timeout, or a reply that is not a JSON reply object.
        """
        key = key or self.key(name)
        while True:
            try:
                errors = []
                for reply in self.session.get(key, payload=payload, timeout=self.timeout):
                    if reply.ok is not None:
                        return _decode_reply(reply.ok.payload.to_bytes(), key)
                    errors.append(_describe_reply_error(reply))
            except zenoh.ZError as exc:
                raise BusError(f"{key}: {exc}") from exc
            # Nobody took the query: on a fresh session the cell's queryables
            # may not have been announced yet; otherwise it is an answer.
            if errors or time.monotonic() > self._settle_until:
                break
            time.sleep(_SETTLE_STEP)
        if errors:
            raise BusError(f"{key}: no answer within {self.timeout:g} s ({'; '.join(errors)})")
        raise BusError(f"{key}: no reply (is the cell running, and may this user send {name}?)")

    def request(self, name: str, message: Mapping[str, Any] | None = None, key: str | None = None) -> dict[str, Any]:
        """Send ``message`` to queryable ``name`` (or to ``key``); return the reply of an accepted request.

        Raises
        ------
        JobError
            The cell refused the request; ``field`` and ``reason`` are the cell's.
        BusError
            See :meth:`request_raw`.
        """
        reply = self.request_raw(name, encode(message) if message else None, key)
        if reply["ok"]:
            return reply
        error = reply.get("error")
        if not isinstance(error, dict):
            raise BusError(f"{key or self.key(name)}: refused without an error object: {describe(error)}")
        raise JobError(str(error.get("field", "")), str(error.get("reason", "refused")))

    def submit(self, message: Mapping[str, Any]) -> dict[str, Any]:
        """Submit a job message (``{"kind": ..., ...}``), validated here first; returns submit-reply."""
        parse_submit(encode(message))
        return self.request("submit", message)

    def status(self, job: str | None = None) -> dict[str, Any]:
        """The cell's status-reply, or with ``job`` that job's record (job-reply ``record``)."""
        if job is None:
            return self.request("status")
        return dict(self.request("status", {"job": job})["record"])

    def cancel(self, job: str, reason: str = "") -> dict[str, Any]:
        """Cancel ``job``; returns cancel-reply (the job's state after the request)."""
        message: dict[str, Any] = {"job": job}
        if reason:
            message["reason"] = reason
        return self.request("cancel", message)

    def list(self, limit: int = 50, state: str | None = None, kind: str | None = None) -> list[dict[str, Any]]:
        """Job records from the journal, newest first."""
        message: dict[str, Any] = {"limit": limit}
        if state:
            message["state"] = state
        if kind:
            message["kind"] = kind
        return list(self.request("list", message)["jobs"])

    def accept(self, job: str, force: bool = False) -> dict[str, Any]:
        """Make calibrate job ``job``'s result current (``force``: despite a failed quality verdict); returns accept-reply."""
        return self.request("accept", {"job": job, "force": True} if force else {"job": job})

    def robot(self, action: str) -> dict[str, Any]:
        """Send an operator's recovery command (unlock, power-on, brake-release, close-popup); returns robot-reply.

        The cell refuses it while a job runs, and passes on the controller's
        refusal (e.g. a protective stop unlocked too early) as a JobError.
        """
        return self.request("robot", {"action": action})

    def calibration(self) -> dict[str, Any] | None:
        """The current calibration, or None."""
        value = self.request("calibration")["calibration"]
        return None if value is None else dict(value)

    def result(self, job: str) -> dict[str, Any]:
        """A finished job's result-reply: ``result`` (the document, or None), ``files`` left on the cell, ..."""
        return self.request("result", key=self.keys.result(job, self.user))

    # -- publications -----------------------------------------------------------------

    def watch_progress(self, job: str | None = None) -> ProgressWatch:
        """Subscribe to the progress events of ``job`` (all jobs if None). Use as a context manager."""
        return ProgressWatch(self, job)

    def submit_and_wait(
        self,
        message: Mapping[str, Any],
        on_event: Callable[[dict[str, Any]], None] | None = None,
        timeout: float | None = None,
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Submit and wait for the job to end; returns (submit-reply, final job record)."""
        with self.watch_progress() as events:
            reply = self.submit(message)
            return reply, events.wait(reply["job"], on_event, timeout)

    def subscribe_state(self, stream: str, callback: Callable[[dict[str, Any]], None]) -> Any:
        """Call ``callback`` with each ``robot`` or ``tactile`` state sample (on a zenoh thread).

        Returns the subscriber; undeclare it (or close the client) to stop.
        """
        key = {"robot": self.keys.state_robot, "tactile": self.keys.state_tactile}.get(stream)
        if key is None:
            raise BusError(f"unknown state stream {stream!r}: expected robot or tactile")

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(json.loads(sample.payload.to_bytes()))
            except (ValueError, RecursionError):
                pass  # a malformed sample is skipped, not fatal to zenoh's thread

        return self.session.declare_subscriber(key, on_sample)


class ProgressWatch:
    """Progress events of one cell, buffered from a subscription (see :meth:`CellClient.watch_progress`)."""

    def __init__(self, client: CellClient, job: str | None = None) -> None:
        self.client = client
        self.job = job
        self.dropped = 0
        self._queue: queue.Queue[dict[str, Any]] = queue.Queue(_EVENT_BACKLOG)
        key = client.keys.progress(job) if job else client.keys.progress_all
        self._subscriber = client.session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # on a zenoh thread
        try:
            event = json.loads(sample.payload.to_bytes())
        except (ValueError, RecursionError):
            return
        if not isinstance(event, dict):
            return
        try:
            self._queue.put_nowait(event)
        except queue.Full:
            self.dropped += 1

    def close(self) -> None:
        try:
            self._subscriber.undeclare()
        except zenoh.ZError:
            pass

    def __enter__(self) -> ProgressWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def next(self, timeout: float | None = None) -> dict[str, Any] | None:
        """The next event, or None after ``timeout`` seconds."""
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def __iter__(self) -> Iterator[dict[str, Any]]:
        while True:
            yield self._queue.get()

    def wait(
        self,
        job: str,
        on_event: Callable[[dict[str, Any]], None] | None = None,
        timeout: float | None = None,
    ) -> dict[str, Any]:
        """Wait until ``job`` ends; returns its final record from the journal.

        Events of ``job`` go to ``on_event`` as they come. With no event for a
        second the cell is asked for the job's state, so a dropped final event
        does not hang the wait.

        Raises
        ------
        BusError
            ``timeout`` seconds passed first.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise BusError(f"job {job} did not end within {timeout:g} s")
            wait = _STATUS_POLL if left is None else min(_STATUS_POLL, left)
            event = self.next(wait)
            if event is not None and event.get("job") != job:
                continue
            if event is not None and on_event is not None:
                on_event(event)
            if event is None or event.get("state") in TERMINAL_STATES:
                record = self.client.status(job)
                if record.get("state") in TERMINAL_STATES:
                    return record

    def wait_stage(self, job: str, stage: str, timeout: float) -> dict[str, Any]:
        """Wait for a progress event of ``job`` in ``stage``; returns it.

        Raises
        ------
        BusError
            The job ended first (the message says how), or ``timeout`` seconds passed.
        """
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            event = self.next(min(_STATUS_POLL, max(0.0, deadline - time.monotonic())))
            if event is not None and event.get("job") == job and event.get("stage") == stage:
                return event
            if event is None or event.get("state") in TERMINAL_STATES:
                record = self.client.status(job)
                if record.get("state") in TERMINAL_STATES:
                    raise BusError(f"job {job} {record['state']} before its {stage} stage: {record.get('reason', '')}")
        raise BusError(f"job {job}: no {stage} event within {timeout:g} s")


def discover_cells(
    bus: BusConfig,
    *,
    session: zenoh.Session | None = None,
    timeout: float = DISCOVERY_TIMEOUT,
    user: str | None = None,
    password: str | None = None,
) -> list[str]:
    """Names of the cells whose liveliness token is visible under ``bus.prefix``, sorted.

    Parameters
    ----------
    session : zenoh.Session, optional
        An open session to use; otherwise one is opened and closed here.
    timeout : float
        How long to wait for liveliness replies, s.
    """
    own = session is None
    s = open_client(bus, user, password) if session is None else session
    try:
        cells = set()
        for reply in s.liveliness().get(alive_all(bus.prefix), timeout=timeout):
            if reply.ok is not None:
                cell = cell_of_alive_key(bus.prefix, str(reply.ok.key_expr))
                if cell is not None:
                    cells.add(cell)
        return sorted(cells)
    except zenoh.ZError as exc:
        raise BusError(f"liveliness query on {alive_all(bus.prefix)} failed: {exc}") from exc
    finally:
        if own:
            s.close()
