"""The simulator's TCP connections: RTDE sessions, dashboard, primary interface, script ports, control endpoint.

Each :class:`Link` owns one non-blocking socket and its buffers; the server in
:mod:`celld.sim.robot.server` multiplexes them. Nothing here blocks.
"""

from __future__ import annotations

import collections
import json
import socket
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from celld.errors import InputError
from celld.log import get_logger
from celld.sim.robot import dashboard, primary
from celld.sim.robot import rtde_protocol as P
from celld.sim.robot.script import find_programs

if TYPE_CHECKING:
    from celld.sim.robot.controller import Controller, InputPlan

log = get_logger(__name__)

# Bytes queued for a client that does not read before data packages are dropped.
MAX_TX_BACKLOG = 256 * 1024
# A script connection that sends this much without a complete program is cut.
MAX_SCRIPT_BUFFER = 4 * 1024 * 1024
# A dashboard or control line longer than this is refused and the connection cut.
MAX_LINE = 64 * 1024
_RECV_SIZE = 65536


class Link:
    """One accepted connection."""

    kind = "link"

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.tx = bytearray()
        self.closed = False
        host, port = sock.getpeername()[:2]
        self.peer = f"{host}:{port}"

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, data: bytes) -> None:
        if self.closed:
            return
        if self.tx:
            self.tx += data
            return
        try:
            n = self.sock.send(data)
        except BlockingIOError:
            n = 0
        except OSError:
            self.close()
            return
        if n < len(data):
            self.tx += data[n:]

    def flush(self) -> None:
        if not self.tx or self.closed:
            return
        try:
            n = self.sock.send(self.tx)
        except BlockingIOError:
            return
        except OSError:
            self.close()
            return
        del self.tx[:n]

    def read(self) -> bytes | None:
        """What the socket holds: None if nothing yet, b"" when the peer closed (the link then closes)."""
        try:
            data = self.sock.recv(_RECV_SIZE)
        except BlockingIOError:
            return None
        except OSError:
            data = b""
        if not data:
            self.close()
        return data

    def on_data(self, data: bytes) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        """Mark the link closed; the server unregisters and closes its socket."""
        self.closed = True


class OutputStream:
    """One output recipe of an RTDE session and how to fill it."""

    __slots__ = ("every", "getters", "recipe")

    def __init__(self, recipe: P.Recipe, every: int, getters: list[Callable[[], Any]]) -> None:
        self.recipe = recipe
        self.every = every
        self.getters = getters

    def package(self) -> bytes:
        values: list[Any] = []
        for get in self.getters:
            values.extend(get())
        return P.data_package(self.recipe, tuple(values))


class RtdeLink(Link):
    """One RTDE client (port 30004)."""

    kind = "rtde"

    def __init__(self, sock: socket.socket, ctrl: Controller, owners: dict[str, RtdeLink], faults: Any) -> None:
        super().__init__(sock)
        self.ctrl = ctrl
        self.owners = owners
        self.faults = faults
        self.reader = P.PackageReader()
        self.protocol = 1
        self.outputs: list[OutputStream] = []
        self.input_recipes: dict[int, P.Recipe] = {}
        self.input_plans: dict[int, InputPlan] = {}
        self.started = False
        self.dropped_packages = 0
        # Packages held back by the latency fault: (due ns, type, payload) in, (due ns, bytes) out.
        self.held_in: collections.deque[tuple[int, int, bytes]] = collections.deque()
        self.held_out: collections.deque[tuple[int, bytes]] = collections.deque()

    def on_data(self, data: bytes) -> None:
        self.reader.feed(data)
        try:
            for msg_type, payload in self.reader.packages():
                delay = self.faults.latency_ns
                if delay or self.held_in:
                    self.held_in.append((time.monotonic_ns() + delay, msg_type, payload))
                else:
                    self.handle(msg_type, payload)
        except P.RtdeProtocolError as exc:
            self.reply(P.text_message(f"RTDE: {exc}; closing the connection", level=P.LEVEL_ERROR))
            self.flush()
            log.warning("rtde_protocol_error", peer=self.peer, error=str(exc))
            self.close()

    def reply(self, data: bytes) -> None:
        delay = self.faults.latency_ns
        if delay or self.held_out:
            self.held_out.append((time.monotonic_ns() + delay, data))
        else:
            self.send(data)

    def release_held(self, now_ns: int) -> None:
        """Deliver the packages the latency fault held until ``now_ns``."""
        while self.held_in and self.held_in[0][0] <= now_ns:
            _, msg_type, payload = self.held_in.popleft()
            self.handle(msg_type, payload)
        while self.held_out and self.held_out[0][0] <= now_ns:
            self.send(self.held_out.popleft()[1])

    def stream(self, tick: int) -> None:
        """Send the data packages due at controller cycle ``tick``."""
        if not self.started or self.closed:
            return
        for out in self.outputs:
            if tick % out.every == 0:
                if len(self.tx) > MAX_TX_BACKLOG:
                    self.dropped_packages += 1
                    continue
                self.reply(out.package())

    def handle(self, msg_type: int, payload: bytes) -> None:
        try:
            if msg_type == P.DATA_PACKAGE:
                recipe, values = P.parse_data(payload, self.input_recipes)
                self.ctrl.write_inputs(self.input_plans[recipe.recipe_id], values, time.monotonic())
            elif msg_type == P.REQUEST_PROTOCOL_VERSION:
                version = P.parse_protocol_version(payload)
                ok = 1 <= version <= P.PROTOCOL_VERSION
                if ok:
                    self.protocol = version
                self.reply(P.reply_protocol_version(ok))
            elif msg_type == P.GET_URCONTROL_VERSION:
                self.reply(P.reply_controller_version(*self.ctrl.options.version))
            elif msg_type == P.CONTROL_PACKAGE_SETUP_OUTPUTS:
                self._setup_outputs(payload)
            elif msg_type == P.CONTROL_PACKAGE_SETUP_INPUTS:
                self._setup_inputs(payload)
            elif msg_type == P.CONTROL_PACKAGE_START:
                self.started = True
                self.reply(P.reply_flag(msg_type, True))
            elif msg_type == P.CONTROL_PACKAGE_PAUSE:
                self.started = False
                self.reply(P.reply_flag(msg_type, True))
            elif msg_type == P.TEXT_MESSAGE:
                message, source, level = P.parse_text_message(payload)
                log.info("rtde_client_message", peer=self.peer, message=message, source=source, level=level)
            else:
                raise P.RtdeProtocolError(f"unknown package type {msg_type}")
        except P.RtdeProtocolError as exc:
            self.reply(P.text_message(f"RTDE: {exc}", level=P.LEVEL_ERROR))

    def _setup_outputs(self, payload: bytes) -> None:
        if self.protocol >= 2:
            frequency, names = P.parse_setup_outputs(payload)
        else:
            frequency, names = 125.0, P.parse_setup_inputs(payload)
        types = P.resolve(names, P.OUTPUT_FIELDS)
        if P.NOT_FOUND in types:
            self.reply(P.reply_setup(P.CONTROL_PACKAGE_SETUP_OUTPUTS, 0, types))
            return
        if not P.MIN_FREQUENCY_HZ <= frequency <= P.MAX_FREQUENCY_HZ:
            self.reply(P.text_message(f"RTDE: output frequency {frequency} Hz outside [1, 500]", level=P.LEVEL_ERROR))
            self.reply(P.reply_setup(P.CONTROL_PACKAGE_SETUP_OUTPUTS, 0, types))
            return
        recipe = P.make_recipe(len(self.outputs) + 1, names, types)
        every = max(1, round(P.MAX_FREQUENCY_HZ / frequency))
        self.outputs.append(OutputStream(recipe, every, [self.ctrl.output_getter(n) for n in names]))
        self.reply(P.reply_setup(P.CONTROL_PACKAGE_SETUP_OUTPUTS, recipe.recipe_id, types))

    def _setup_inputs(self, payload: bytes) -> None:
        names = P.parse_setup_inputs(payload)
        types = list(P.resolve(names, P.INPUT_FIELDS))
        for i, name in enumerate(names):
            owner = self.owners.get(name)
            if types[i] != P.NOT_FOUND and owner is not None and owner is not self:
                types[i] = P.IN_USE
        if P.NOT_FOUND in types or P.IN_USE in types:
            self.reply(P.reply_setup(P.CONTROL_PACKAGE_SETUP_INPUTS, 0, tuple(types)))
            return
        for name in names:
            self.owners[name] = self
        recipe = P.make_recipe(len(self.input_recipes) + 1, names, tuple(types))
        self.input_recipes[recipe.recipe_id] = recipe
        self.input_plans[recipe.recipe_id] = self.ctrl.input_plan(names)
        self.reply(P.reply_setup(P.CONTROL_PACKAGE_SETUP_INPUTS, recipe.recipe_id, tuple(types)))

    def close(self) -> None:
        if not self.closed:
            for name in [n for n, owner in self.owners.items() if owner is self]:
                del self.owners[name]
        super().close()


class DashboardLink(Link):
    """One dashboard client (port 29999)."""

    kind = "dashboard"

    def __init__(self, sock: socket.socket, ctrl: Controller) -> None:
        super().__init__(sock)
        self.ctrl = ctrl
        self.buf = bytearray()
        self.send((dashboard.WELCOME + "\n").encode())

    def on_data(self, data: bytes) -> None:
        self.buf += data
        if len(self.buf) > MAX_LINE and b"\n" not in self.buf:
            self.send(b"could not understand: line too long\n")
            self.close()
            return
        while b"\n" in self.buf and not self.closed:
            line, _, rest = bytes(self.buf).partition(b"\n")
            self.buf = bytearray(rest)
            reply = dashboard.handle(self.ctrl, line.decode("utf-8", "replace"))
            self.send((reply.text + "\n").encode())
            if reply.close:
                self.flush()
                self.close()


class ScriptLink(Link):
    """One client of a script port (30001-30003): programs in, nothing out."""

    kind = "script"

    def __init__(self, sock: socket.socket, ctrl: Controller) -> None:
        super().__init__(sock)
        self.ctrl = ctrl
        self.buf = b""

    def on_data(self, data: bytes) -> None:
        self.buf += data
        programs, self.buf = find_programs(self.buf)
        for program in programs:
            log.info("program_received", name=program.name, control_script=program.is_control_script, peer=self.peer)
            self.ctrl.receive_program(program)
        stripped = self.buf.lstrip()
        if stripped and not stripped.startswith((b"def", b"sec")) and b"\n" in stripped:
            # Statements outside a program: the controller would run each as a one-line program.
            line, _, self.buf = stripped.partition(b"\n")
            self.ctrl.message(f"script statement not simulated: {line[:80].decode('utf-8', 'replace')}")
        if len(self.buf) > MAX_SCRIPT_BUFFER:
            self.ctrl.message("script port: no complete program in 4 MB, connection closed", P.LEVEL_ERROR)
            self.close()


class PrimaryLink(ScriptLink):
    """One client of the primary interface (30001): programs in, as any script port; the version message
    when it connects and robot state at 10 Hz out (:mod:`celld.sim.robot.primary`)."""

    kind = "primary"

    def __init__(self, sock: socket.socket, ctrl: Controller) -> None:
        super().__init__(sock, ctrl)
        # The controller's table does not change while it runs: its robot state is encoded once.
        self._state = primary.robot_state_message(ctrl.kinematics)
        self.send(primary.version_message(ctrl.options.version) + self._state)

    def stream(self, tick: int) -> None:
        """Robot state on every :data:`~celld.sim.robot.primary.STATE_EVERY`-th cycle (a client that does not
        read loses it, as data packages are lost)."""
        if tick % primary.STATE_EVERY == 0 and len(self.tx) < MAX_TX_BACKLOG:
            self.send(self._state)


class ControlLink(Link):
    """A client of the simulator's own control endpoint: JSON objects, one per line."""

    kind = "control"

    def __init__(self, sock: socket.socket, dispatch: Callable[[dict[str, Any]], dict[str, Any]]) -> None:
        super().__init__(sock)
        self.dispatch = dispatch
        self.buf = bytearray()

    def on_data(self, data: bytes) -> None:
        self.buf += data
        if len(self.buf) > MAX_LINE and b"\n" not in self.buf:
            self.send((json.dumps({"ok": False, "error": f"request longer than {MAX_LINE} bytes"}) + "\n").encode())
            self.close()
            return
        while b"\n" in self.buf and not self.closed:
            line, _, rest = bytes(self.buf).partition(b"\n")
            self.buf = bytearray(rest)
            try:
                request = json.loads(line)
                if not isinstance(request, dict) or not isinstance(request.get("op"), str):
                    raise InputError('expected a JSON object with a string "op"')
                reply = {"ok": True, **self.dispatch(request)}
            except (InputError, ValueError) as exc:
                reply = {"ok": False, "error": str(exc)}
            self.send((json.dumps(reply) + "\n").encode())
