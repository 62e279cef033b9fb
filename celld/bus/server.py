"""The cell's side of the bus: queryables that answer every request, and publications.

:class:`BusServer` declares the queryables of one cell (``submit``, ``status``,
``cancel``, ``list``, ``accept``, ``calibration``, ``result/<job>``), its
liveliness token, and publishes progress events and decimated robot and
tactile state. It owns no job logic: the daemon gives it an object with one
coroutine per request.

Who asks (:mod:`celld.bus.security`): on an open bus the queryables sit at
``<prefix>/<cell>/<name>`` and every request comes from
:data:`~celld.bus.security.OPEN`. With ``callers`` (the config's users) the
server declares, for each user, the queryables its role may use at
``<prefix>/<cell>/u/<user>/<name>``; zenoh's ACL (:func:`celld.bus.session.acl_config`)
lets a link query only its own user's keys, so the queryable a request
reached names its user, and the handler gets that :class:`Caller`. A query
whose key expression is not exactly the queryable's own (a wildcard) is
refused on a bus with users.

Handler interface (:class:`CellHandlers`; the daemon's job manager implements it)::

    async def on_submit(self, job: Job, caller: Caller) -> dict            # -> submit-reply body
    async def on_status(self, req: StatusRequest, caller: Caller) -> dict  # -> status-reply or job-reply body
    async def on_cancel(self, req: CancelRequest, caller: Caller) -> dict  # -> cancel-reply body
    async def on_list(self, req: ListRequest, caller: Caller) -> dict      # -> list-reply body
    async def on_accept(self, req: AcceptRequest, caller: Caller) -> dict  # -> accept-reply body
    async def on_calibration(self, req: CalibrationRequest, caller: Caller) -> dict  # -> calibration-reply body
    async def on_robot(self, req: RobotRequest, caller: Caller) -> dict    # -> robot-reply body
    async def on_result(self, req: ResultRequest, caller: Caller) -> dict  # -> result-reply body

- A handler receives a request already validated and built into a frozen value
  (:mod:`celld.bus.requests`); it never sees raw bytes.
- It returns the reply body without ``ok``; the server sends
  ``{"ok": true, **body}``. The bodies' schemas are ``SCHEMAS["<name>-reply"]``
  (:func:`celld.bus.messages.check_message` checks one in tests). Values may be
  numpy scalars or arrays; they are sent as JSON numbers and lists.
- To refuse, it raises :class:`~celld.errors.JobError` ``(field, reason)``
  (e.g. ``JobError("$.job", "no such job")``; a full queue is
  ``JobError("$", "refused: a job is running and the queue is full (8)")``);
  any other :class:`~celld.errors.CelldError` becomes an error with an empty
  field; anything else is logged with its traceback and answered as an
  internal error. Either way the client gets ``{"ok": false, "error":
  {"field": ..., "reason": ...}}`` and the server stays up.
- Handlers run on the daemon's asyncio loop, one task per request; they must
  not block it. A handler slower than ``reply_timeout`` is answered with an
  error saying that the request may still take effect, and is left to finish.

Ordering the daemon keeps: record a job's end in the journal before it
publishes the job's final progress event, so a client that sees the event
and asks ``status`` reads the final record.

Threads: zenoh calls the queryable callbacks on its own threads. The callback
only copies the payload and hops to the loop with ``call_soon_threadsafe``;
parsing, the handler and the reply happen on the loop. More than
``max_pending`` requests in flight are answered "busy" from the zenoh thread
without touching the loop, so a flood cannot grow memory or starve the loop.
Publishing never blocks: state and progress use zenoh's drop-on-congestion, so
a receiver may miss an event; progress events carry a per-job ``seq`` so a gap
is visible (the client then asks ``status``).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import zenoh

from celld.bus.keys import QUERYABLES, CellKeys
from celld.bus.messages import TERMINAL_STATES
from celld.bus.requests import (
    AcceptRequest,
    CalibrationRequest,
    CancelRequest,
    Job,
    ListRequest,
    ResultRequest,
    RobotRequest,
    StatusRequest,
    parse,
    parse_result,
)
from celld.bus.security import OPEN, Caller
from celld.bus.wire import MAX_PAYLOAD_BYTES, encode, error_reply
from celld.errors import BusError, CelldError, JobError
from celld.journal import utc_at, utc_now
from celld.log import get_logger

log = get_logger(__name__)

# Replies are JSON.
_JSON = zenoh.Encoding.APPLICATION_JSON
# Default: longest a handler may take before the client is told, s.
REPLY_TIMEOUT = 10.0
# Default: most requests in flight before new ones are answered "busy": a second
# of the 1000 Hz status load the bus is sized for, so a stall of the loop of up
# to a second is absorbed; a flood beyond it is refused, not buffered.
MAX_PENDING = 1024


class CellHandlers(Protocol):
    """What the daemon provides to answer the bus (see the module docstring)."""

    async def on_submit(self, job: Job, caller: Caller) -> Mapping[str, Any]: ...
    async def on_status(self, req: StatusRequest, caller: Caller) -> Mapping[str, Any]: ...
    async def on_cancel(self, req: CancelRequest, caller: Caller) -> Mapping[str, Any]: ...
    async def on_list(self, req: ListRequest, caller: Caller) -> Mapping[str, Any]: ...
    async def on_accept(self, req: AcceptRequest, caller: Caller) -> Mapping[str, Any]: ...
    async def on_calibration(self, req: CalibrationRequest, caller: Caller) -> Mapping[str, Any]: ...
    async def on_robot(self, req: RobotRequest, caller: Caller) -> Mapping[str, Any]: ...
    async def on_result(self, req: ResultRequest, caller: Caller) -> Mapping[str, Any]: ...


@dataclass
class ServerStats:
    """Counters of one server, for logs, status and benchmarks."""

    requests: int = 0  # queries received
    refused: int = 0  # answered with an error (validation, handler refusal, busy, ...)
    busy: int = 0  # answered "busy" without reaching the loop
    internal_errors: int = 0  # handler raised something outside the error tree
    timeouts: int = 0  # handler slower than reply_timeout
    reply_failures: int = 0  # zenoh could not send a reply (client gone)
    published: int = 0  # progress and state samples sent
    decimated: int = 0  # state samples skipped by the rate limit


@dataclass(frozen=True)
class _Request:
    """One query on its way from zenoh's thread to the loop."""

    name: str
    caller: Caller
    key: str  # where the reply goes
    job: str  # the job of a result request
    query: zenoh.Query
    raw: bytes


class _Decimator:
    """Lets one sample through per period; thread-safe."""

    def __init__(self, rate_hz: float) -> None:
        self.period_ns = int(1e9 / rate_hz)
        self._next_ns = 0
        self._lock = threading.Lock()

    def admit(self, now_ns: int) -> bool:
        with self._lock:
            if now_ns < self._next_ns:
                return False
            self._next_ns = now_ns + self.period_ns
            return True


class BusServer:
    """Answers one cell's queryables and publishes its progress and state.

    Parameters
    ----------
    session : zenoh.Session
        An open session (:func:`celld.bus.session.open_server`).
    cell : CellKeys
        The keys of this cell.
    handlers : CellHandlers
        The daemon's request handlers.
    state_rate_hz : float
        Most robot and tactile state samples published per second, each.
    reply_timeout : float
        Longest a handler may take before the client gets an error, s.
    max_pending : int
        Most requests in flight; more are answered "busy".
    callers : iterable of Caller, optional
        The bus's users (:func:`celld.bus.session.callers`); none: an open bus.
    """

    def __init__(
        self,
        session: zenoh.Session,
        cell: CellKeys,
        handlers: CellHandlers,
        *,
        state_rate_hz: float = 20.0,
        reply_timeout: float = REPLY_TIMEOUT,
        max_pending: int = MAX_PENDING,
        callers: Iterable[Caller] = (),
    ) -> None:
        if state_rate_hz <= 0 or reply_timeout <= 0 or max_pending < 1:
            raise BusError(
                f"expected state_rate_hz > 0, reply_timeout > 0, max_pending >= 1; got {state_rate_hz}, {reply_timeout}, {max_pending}"
            )
        self.session = session
        self.keys = cell
        self.handlers = handlers
        self.reply_timeout = reply_timeout
        self.max_pending = max_pending
        self.stats = ServerStats()
        self.callers = tuple(callers)
        self._handlers: dict[str, Callable[[Any, Caller], Awaitable[Mapping[str, Any]]]] = {
            "submit": handlers.on_submit,
            "status": handlers.on_status,
            "cancel": handlers.on_cancel,
            "list": handlers.on_list,
            "accept": handlers.on_accept,
            "calibration": handlers.on_calibration,
            "robot": handlers.on_robot,
            "result": handlers.on_result,
        }
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()
        self._pending = 0
        self._tasks: set[asyncio.Task[None]] = set()
        self._queryables: list[Any] = []
        self._token: Any = None
        self._publishers: dict[str, Any] = {}
        self._decimators = {"robot": _Decimator(state_rate_hz), "tactile": _Decimator(state_rate_hz)}
        self._seq: dict[str, int] = {}
        self._warned: set[str] = set()
        self._closing = False

    # -- life cycle --------------------------------------------------------------

    async def start(self) -> None:
        """Declare queryables, publishers and the liveliness token (call on the daemon's loop)."""
        if self._loop is not None:
            raise BusError("the bus server is already started")
        self._loop = asyncio.get_running_loop()
        try:
            for caller in self.callers or (OPEN,):
                for name in (*QUERYABLES, "result"):
                    if not caller.may(name):
                        continue
                    key = self.keys.results(caller.user) if name == "result" else self.keys.query(name, caller.user)
                    self._queryables.append(self.session.declare_queryable(key, self._callback(name, caller, key)))
            for stream, key in (("robot", self.keys.state_robot), ("tactile", self.keys.state_tactile)):
                self._publishers[stream] = self.session.declare_publisher(
                    key, encoding=_JSON, congestion_control=zenoh.CongestionControl.DROP
                )
            self._token = self.session.liveliness().declare_token(self.keys.alive)
        except zenoh.ZError as exc:
            await self.close()
            raise BusError(f"cannot declare the bus entities of {self.keys.base}: {exc}") from exc
        log.info("bus_server_up", cell=self.keys.cell, base=self.keys.base)

    async def close(self) -> None:
        """Stop answering, withdraw the token, and answer what is in flight with an error."""
        self._closing = True
        for q in self._queryables:
            self._undeclare(q)
        self._queryables.clear()
        if self._token is not None:
            self._undeclare(self._token)
            self._token = None
        for p in self._publishers.values():
            self._undeclare(p)
        self._publishers.clear()
        tasks = list(self._tasks)
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)

    @staticmethod
    def _undeclare(entity: Any) -> None:
        try:
            entity.undeclare()
        except zenoh.ZError as exc:  # the session may already be closed
            log.debug("undeclare_failed", error=str(exc))

    async def __aenter__(self) -> BusServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- requests ----------------------------------------------------------------

    def _callback(self, name: str, caller: Caller, declared: str) -> Callable[[zenoh.Query], None]:
        result_head = declared[: -len("*")] if name == "result" else ""

        def on_query(query: zenoh.Query) -> None:  # on a zenoh thread
            try:
                key = str(query.key_expr)
                job = ""
                if name == "result":
                    job = key[len(result_head) :] if key.startswith(result_head) else ""
                    exact = bool(job) and not set(job) & set("*$?#/")  # one literal job id
                    reply_key = result_head + job if exact else declared
                else:
                    reply_key, exact = declared, key == declared
                if not exact and (caller.user or name == "result"):
                    # A wildcard reached a user's queryable (a router without the
                    # ACL let it through) or names no one job: not this user's request.
                    self._count("requests")
                    what = "name one job: <req>/result/<job>" if name == "result" else f"query your own key {declared}"
                    self._reply_now(reply_key, query, error_reply("$", f"refused: {what}, not {key!r}"))
                    return
                self._enqueue(name, caller, reply_key, job, query)
            except Exception as exc:  # nothing a client sends may kill zenoh's thread  # noqa: BLE001
                log.error("bus_callback_failed", request=name, error=repr(exc))

        return on_query

    def _count(self, counter: str) -> None:
        # Counters move on zenoh's threads and on the loop.
        with self._lock:
            setattr(self.stats, counter, getattr(self.stats, counter) + 1)

    def _enqueue(self, name: str, caller: Caller, key: str, job: str, query: zenoh.Query) -> None:
        self._count("requests")
        payload = query.payload
        if payload is not None and len(payload) > MAX_PAYLOAD_BYTES:
            self._reply_now(key, query, error_reply("$", f"expected at most {MAX_PAYLOAD_BYTES} bytes, got {len(payload)}"))
            return
        raw = payload.to_bytes() if payload is not None else b""
        with self._lock:
            busy = self._pending >= self.max_pending or self._closing
            if not busy:
                self._pending += 1
        if busy:
            self._count("busy")
            reason = "the cell is shutting down" if self._closing else f"busy: {self.max_pending} requests in flight, try again"
            self._reply_now(key, query, error_reply("", reason))
            return
        loop = self._loop
        request = _Request(name, caller, key, job, query, raw)
        try:
            if loop is None:
                raise RuntimeError("not started")
            loop.call_soon_threadsafe(self._spawn, request)
        except RuntimeError:  # the loop is closed
            self._release()
            self._reply_now(key, query, error_reply("", "the cell is shutting down"))

    def _spawn(self, request: _Request) -> None:
        if self._closing:  # close() began after this request was handed over
            self._release()
            self._reply_now(request.key, request.query, error_reply("", "the cell is shutting down"))
            return
        task = asyncio.get_running_loop().create_task(self._answer(request))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _release(self) -> None:
        with self._lock:
            self._pending -= 1

    async def _answer(self, request: _Request) -> None:
        """Handle one request and reply once: with the handler's answer, or, if it
        is slower than ``reply_timeout``, with an error while it goes on."""
        replied = False
        name = request.name

        def reply_once(reply: Mapping[str, Any]) -> bool:
            nonlocal replied
            if replied:
                return False
            replied = True
            self._release()
            self._reply_now(request.key, request.query, reply)
            return True

        def too_slow() -> None:
            self._count("timeouts")
            reply_once(error_reply("", f"no answer within {self.reply_timeout:g} s; the request may still take effect (ask status)"))

        # A timer instead of wait_for(shield(...)): one task per request, and a
        # slow handler is reported, not torn in half.
        timer = asyncio.get_running_loop().call_later(self.reply_timeout, too_slow)
        try:
            reply = await self._handle(request)
        except asyncio.CancelledError:
            timer.cancel()
            reply_once(error_reply("", "the cell is shutting down"))
            raise
        timer.cancel()
        if not reply_once(reply) and reply.get("ok") is not True:
            log.error("bus_handler_failed_after_reply", request=name, error=reply.get("error"))

    async def _handle(self, request: _Request) -> Mapping[str, Any]:
        name = request.name
        try:
            value = parse_result(request.job, request.raw) if name == "result" else parse(name, request.raw)
            body = await self._handlers[name](value, request.caller)
            if not isinstance(body, Mapping):
                raise TypeError(f"handler on_{name} returned {type(body).__name__}, expected a mapping")
            return {"ok": True, **body}
        except JobError as exc:
            return error_reply(exc.field, exc.reason)
        except CelldError as exc:
            return error_reply("", str(exc))
        except asyncio.CancelledError:
            raise
        except Exception:  # a handler's own bug gets an internal-error reply, the bus stays up
            self._count("internal_errors")
            log.exception("bus_handler_failed", request=name)
            return error_reply("", f"internal error while handling {name}")

    def _reply_now(self, key: str, query: zenoh.Query, reply: Mapping[str, Any]) -> None:
        if reply.get("ok") is not True:
            self._count("refused")
        try:
            payload = encode(reply)
        except (TypeError, ValueError) as exc:
            self._count("internal_errors")
            log.error("bus_reply_not_encodable", error=str(exc))
            payload = encode(error_reply("", "internal error: the reply was not valid JSON"))
        try:
            # The queryable's own key (a query may have come in on a wildcard),
            # or the one result it names.
            query.reply(key, payload, encoding=_JSON)
        except zenoh.ZError as exc:
            self._count("reply_failures")
            log.debug("bus_reply_failed", error=str(exc))
        finally:
            query.drop()  # sends the final message: the client stops waiting

    # -- publications ------------------------------------------------------------

    def publish_progress(
        self,
        job: str,
        kind: str,
        state: str,
        stage: str,
        *,
        fraction: float | None = None,
        message: str = "",
        data: Mapping[str, Any] | None = None,
    ) -> bool:
        """Publish one progress event of ``job`` on ``progress/<job>``; returns whether it was sent.

        The server numbers the events of each job (``seq`` from 0); an event
        with a terminal state ends the numbering of that job.
        """
        with self._lock:
            seq = self._seq.get(job, 0)
            if state in TERMINAL_STATES:
                self._seq.pop(job, None)
            else:
                self._seq[job] = seq + 1
        event: dict[str, Any] = {"job": job, "kind": kind, "seq": seq, "state": state, "stage": stage, "time": utc_now()}
        if fraction is not None:
            event["fraction"] = fraction
        if message:
            event["message"] = message
        if data:
            event["data"] = dict(data)
        return self._put(self.keys.progress(job), event)

    def publish_robot_state(self, state: Mapping[str, Any], now_ns: int | None = None) -> bool:
        """Publish a robot state sample (``state-robot``) unless the rate limit drops it."""
        return self._publish_state("robot", state, now_ns)

    def publish_tactile_state(self, state: Mapping[str, Any], now_ns: int | None = None) -> bool:
        """Publish a tactile state sample (``state-tactile``) unless the rate limit drops it."""
        return self._publish_state("tactile", state, now_ns)

    def _publish_state(self, stream: str, state: Mapping[str, Any], now_ns: int | None) -> bool:
        if not self._decimators[stream].admit(time.monotonic_ns() if now_ns is None else now_ns):
            self._count("decimated")
            return False
        publisher = self._publishers.get(stream)
        if publisher is None:
            return False
        # The sample's own time on the wall clock (a sample without one, t_ns 0: the link is down, is sent now).
        t_ns = int(state.get("t_ns", 0))
        stamped = {**state, "time": utc_at(t_ns) if t_ns > 0 else utc_now()}
        try:
            publisher.put(encode(stamped))
        except (TypeError, ValueError, zenoh.ZError) as exc:
            if stream not in self._warned:  # once per stream: samples come at the state rate
                self._warned.add(stream)
                log.warning("state_not_published", stream=stream, error=str(exc))
            return False
        self._count("published")
        return True

    def _put(self, key: str, message: Mapping[str, Any]) -> bool:
        if self._closing:
            return False
        try:
            self.session.put(key, encode(message), encoding=_JSON, congestion_control=zenoh.CongestionControl.DROP)
        except (TypeError, ValueError, zenoh.ZError) as exc:
            log.warning("event_not_published", key=key, error=str(exc))
            return False
        self._count("published")
        return True
