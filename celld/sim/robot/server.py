"""The simulator process: sockets on one loopback address and the 500 Hz cycle.

One thread. Between cycles it waits for socket events with ``select`` (its
timeout has microsecond resolution, unlike epoll's milliseconds) until about
:data:`SPIN_NS` before the next deadline, then spins to the deadline and runs
the cycle: controller tick, truth record, text messages, data packages. A cycle
that starts late is run anyway, after taking in the input that arrived
meanwhile, so simulated time keeps pace with the clock; more than
:data:`MAX_CATCHUP` cycles behind, the schedule is reset rather than replayed.
Input writes are stamped with the monotonic clock on arrival and the RTDE
watchdog measures silence on it, so a stall of this process is not taken for a
silent client. ``--realtime`` raises the process to SCHED_FIFO where allowed.

Ports on the host: dashboard 29999, primary interface 30001 (script in, robot
state with the controller's kinematics out), script 30002-30003, RTDE 30004, and the
simulator's own control endpoint 30100 (opened last: when it answers, every
other port is bound).
"""

from __future__ import annotations

import gc
import os
import selectors
import signal
import socket
import struct
import time
from typing import Any

from celld.errors import InputError
from celld.log import get_logger
from celld.realtime import RealtimeOptions, make_realtime
from celld.robot import kinematics as kin
from celld.robot.primary import PRIMARY_PORT
from celld.sim.robot import geometry as g
from celld.sim.robot import links as L
from celld.sim.robot import rtde_protocol as P
from celld.sim.robot.controller import (
    PERIOD,
    ROBOT_MODE_NAMES,
    RUNTIME_NAMES,
    SAFETY_NAMES,
    Controller,
)
from celld.sim.robot.faults import parse_fault
from celld.sim.robot.options import CONTROL_PORT, DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORTS, SimOptions
from celld.sim.robot.truth import TruthPublisher

log = get_logger(__name__)

PERIOD_NS = int(PERIOD * 1e9)
# Wake up this long before a deadline and spin the rest. With a 1 us timer slack the
# sleep itself is rarely later than this on an idle machine; on a loaded one spinning
# longer would only burn the process's share of the CPU.
SPIN_NS = 100_000
# Timer slack of the process, ns (the kernel's default is 50 us).
_TIMER_SLACK_NS = 1_000
# SCHED_FIFO priority of the simulated controller where allowed.
_FIFO_PRIORITY = 50
# More cycles behind than this (0.5 s) and the schedule is reset instead of caught up:
# below it, simulated time keeps pace with the clock even when the OS stalls the process.
MAX_CATCHUP = 250
# Housekeeping (parent check, reopening listeners, young-generation GC) every this many cycles.
_HOUSEKEEPING_EVERY = 250


class FaultState:
    """Faults in force that the links consult."""

    def __init__(self) -> None:
        self.latency_ns = 0
        self.stall_until_ns = 0
        self.down_until_ns: dict[int, int] = {}  # listener port -> reopen time


class SimServer:
    """The simulated controller's process state and loop."""

    def __init__(self, options: SimOptions) -> None:
        self.options = options
        self.host = options.host
        self.ctrl = Controller(options)
        self.faults = FaultState()
        self.selector = selectors.SelectSelector()
        self.listeners: dict[int, socket.socket] = {}
        self.links: set[L.Link] = set()
        self.owners: dict[str, L.RtdeLink] = {}
        self.truth: TruthPublisher | None = None
        self.running = False
        self.late_cycles = 0
        self.skipped_cycles = 0
        self.max_lateness_ns = 0

    # --- sockets ------------------------------------------------------------------

    def _listen(self, port: int) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((self.host, port))
        sock.listen(16)
        sock.setblocking(False)
        self.listeners[port] = sock
        self.selector.register(sock, selectors.EVENT_READ, ("listen", port))

    def _unlisten(self, port: int) -> None:
        sock = self.listeners.pop(port, None)
        if sock is not None:
            self.selector.unregister(sock)
            sock.close()

    def _accept(self, port: int) -> None:
        try:
            sock, _ = self.listeners[port].accept()
        except (BlockingIOError, KeyError):
            return
        if port in SCRIPT_PORTS and not self.ctrl.options.remote_control:
            # Local Control: the controller takes no script from the network and drops the connection.
            log.info("script_link_refused", port=port, reason="the teach pendant is in local control")
            sock.close()
            return
        link: L.Link
        if port == RTDE_PORT:
            link = L.RtdeLink(sock, self.ctrl, self.owners, self.faults)
        elif port == DASHBOARD_PORT:
            link = L.DashboardLink(sock, self.ctrl)
        elif port == CONTROL_PORT:
            link = L.ControlLink(sock, self.dispatch)
        elif port == PRIMARY_PORT:
            link = L.PrimaryLink(sock, self.ctrl)
        else:
            link = L.ScriptLink(sock, self.ctrl)
        self.links.add(link)
        self.selector.register(sock, selectors.EVENT_READ, ("link", link))
        log.debug("link_open", kind=link.kind, peer=link.peer)

    def _drop(self, link: L.Link, reset: bool = False) -> None:
        """Close ``link``; with ``reset`` abortively (RST), as a link that breaks rather than ends."""
        if link in self.links:
            self.links.discard(link)
            try:
                self.selector.unregister(link.sock)
            except (KeyError, ValueError):
                pass
            link.close()
            try:
                if reset:
                    link.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                link.sock.close()
            except OSError:
                pass
            log.debug("link_closed", kind=link.kind, peer=link.peer)

    def _poll(self, timeout: float) -> None:
        for link in [lk for lk in self.links if lk.closed]:
            self._drop(link)
        for key, _ in self.selector.select(timeout):
            what, obj = key.data
            if what == "listen":
                self._accept(obj)
                continue
            peer: L.Link = obj
            data = peer.read()
            if data:
                peer.on_data(data)
            if peer.closed:
                self._drop(peer)
        for link in [lk for lk in self.links if lk.tx or lk.closed]:
            link.flush()
            if link.closed:
                self._drop(link)

    # --- the cycle ----------------------------------------------------------------

    def start(self) -> None:
        """Bind every port (the control endpoint last) and create the truth segments."""
        if self.options.truth:
            self.truth = TruthPublisher(self.host)
        for port in (DASHBOARD_PORT, *SCRIPT_PORTS, RTDE_PORT, CONTROL_PORT):
            self._listen(port)
        self.running = True
        log.info("sim_robot_listening", host=self.host, version=".".join(map(str, self.options.version)))

    def run(self) -> None:
        """Run cycles until :meth:`dispatch` gets ``shutdown``, a signal arrives or the parent dies."""
        gc.collect()
        gc.freeze()
        gc.disable()
        self._publish_truth(time.monotonic_ns())
        next_ns = time.monotonic_ns() + PERIOD_NS
        try:
            while self.running:
                now = time.monotonic_ns()
                if now >= next_ns:
                    late = now - next_ns
                    if late > PERIOD_NS:
                        self._poll(0.0)  # take in what arrived while this process was stalled
                    if late > MAX_CATCHUP * PERIOD_NS:
                        skipped = late // PERIOD_NS
                        self.skipped_cycles += skipped
                        next_ns += skipped * PERIOD_NS
                    if late > PERIOD_NS // 4:
                        self.late_cycles += 1
                    self.max_lateness_ns = max(self.max_lateness_ns, late)
                    self._cycle(next_ns)
                    next_ns += PERIOD_NS
                    continue
                self._release_held(now)
                remaining = next_ns - now
                if remaining > SPIN_NS:
                    self._poll((remaining - SPIN_NS) * 1e-9)
                else:
                    while time.monotonic_ns() < next_ns:
                        pass
        finally:
            gc.enable()
            self.close()

    def _cycle(self, stamp_ns: int) -> None:
        ctrl = self.ctrl
        # The watchdog measures the client's silence on the clock the links stamp writes with.
        ctrl.tick(time.monotonic())
        self._publish_truth(stamp_ns)
        if ctrl.outbox:
            for text, level in ctrl.outbox:
                package = P.text_message(text, "celld-sim", level)
                for link in self.links:
                    if isinstance(link, L.RtdeLink) and link.protocol >= 2:
                        link.reply(package)
            ctrl.outbox.clear()
        if stamp_ns >= self.faults.stall_until_ns:
            for link in self.links:
                if link.kind in ("rtde", "primary"):
                    link.stream(ctrl.ticks)  # type: ignore[attr-defined]
        if ctrl.ticks % _HOUSEKEEPING_EVERY == 0:
            self._housekeeping(stamp_ns)

    def _publish_truth(self, stamp_ns: int) -> None:
        if self.truth is not None:
            c = self.ctrl
            arm = c.arm
            src = c.source
            # The physical arm (its joints and true TCP), not the controller's belief; the arc as it truly burns.
            self.truth.publish(
                stamp_ns, c.q_true, arm.qd, c.T_tcp_true, arm.T_tcp, arm.T_flange_tcp, c.digital_out,
                (c.robot_mode, c.safety_mode, c.runtime_state),
                src is not None and src.arc_on, src.current if src is not None else 0.0,
                src is not None and src.wire_stuck,
            )  # fmt: skip

    def _release_held(self, now_ns: int) -> None:
        for link in self.links:
            if link.kind == "rtde" and (link.held_in or link.held_out):  # type: ignore[attr-defined]
                link.release_held(now_ns)  # type: ignore[attr-defined]

    def _housekeeping(self, now_ns: int) -> None:
        if self.options.parent_pid and os.getppid() != self.options.parent_pid:
            log.info("sim_robot_parent_gone", parent=self.options.parent_pid)
            self.running = False
        for port, until in list(self.faults.down_until_ns.items()):
            if now_ns >= until:
                del self.faults.down_until_ns[port]
                self._listen(port)
        gc.collect(0)

    def close(self) -> None:
        for link in list(self.links):
            self._drop(link)
        for port in list(self.listeners):
            self._unlisten(port)
        if self.truth is not None:
            self.truth.close()
            self.truth = None
        log.info("sim_robot_stopped", host=self.host, late_cycles=self.late_cycles, skipped_cycles=self.skipped_cycles)

    # --- control endpoint ---------------------------------------------------------

    def dispatch(self, request: dict[str, Any]) -> dict[str, Any]:
        """Answer one control request; raise InputError for a bad one."""
        op = request["op"]
        args = {k: v for k, v in request.items() if k != "op"}
        if op == "ping":
            return {"host": self.host, "pid": os.getpid()}
        if op == "status":
            return self.status()
        if op == "inject":
            fault = parse_fault(str(args.pop("fault", "")), args)
            self._inject(fault.name, fault.args)
            log.info("fault_injected", fault=fault.name, **fault.args)
            return {}
        if op == "clear":
            self._clear()
            return {}
        if op == "set_q":
            q = args.get("q")
            if not isinstance(q, list) or len(q) != 6:
                raise InputError(f"set_q: expected 6 joint angles (rad), got {q!r}")
            q_checked = kin.check_q(q)
            if not kin.within_limits(q_checked):
                raise InputError(f"set_q: joints {q} outside the joint range [-2 pi, 2 pi]")
            self.ctrl.arm.set_q(q_checked.tolist())
            self.ctrl.sense()
            return {}
        if op == "set_digital_in":
            bits = args.get("bits")
            if not isinstance(bits, int) or not 0 <= bits < 1 << 18:
                raise InputError(f"set_digital_in: expected an integer of 18 bits, got {bits!r}")
            self.ctrl.digital_in = bits
            return {}
        if op == "shutdown":
            self.running = False
            return {}
        raise InputError(f"unknown op {op!r}: expected ping, status, inject, clear, set_q, set_digital_in or shutdown")

    def status(self) -> dict[str, Any]:
        c = self.ctrl
        arm = c.arm
        return {
            "time": c.time,
            "q": list(arm.q),
            "tcp_pose": g.pose_from_rows(arm.T_tcp),
            "robot_mode": ROBOT_MODE_NAMES.get(c.robot_mode, str(c.robot_mode)),
            "safety_mode": SAFETY_NAMES.get(c.safety_mode, str(c.safety_mode)),
            "runtime_state": RUNTIME_NAMES.get(c.runtime_state, str(c.runtime_state)),
            "program": c.program_name if c.program is not None else "",
            "last_stop_reason": c.last_stop_reason,
            "digital_out": c.digital_out,
            "links": sorted(link.kind for link in self.links if link.kind != "control"),
            "late_cycles": self.late_cycles,
            "skipped_cycles": self.skipped_cycles,
            "max_lateness_ms": self.max_lateness_ns * 1e-6,
            "power_source": c.source.status() if c.source is not None else None,
        }

    def _inject(self, name: str, args: dict[str, float]) -> None:
        now = time.monotonic_ns()
        if name in ("drop_rtde", "drop_all"):
            kinds = ("rtde",) if name == "drop_rtde" else ("rtde", "dashboard", "script")
            for link in [lk for lk in self.links if lk.kind in kinds]:
                self._drop(link, reset=True)
            down_ns = int(args.get("down_ms", 0.0) * 1e6)
            if down_ns:
                ports = (RTDE_PORT,) if name == "drop_rtde" else (RTDE_PORT, DASHBOARD_PORT, *SCRIPT_PORTS)
                for port in ports:
                    self._unlisten(port)
                    self.faults.down_until_ns[port] = now + down_ns
        elif name == "stall":
            self.faults.stall_until_ns = now + int(args["ms"] * 1e6)
        elif name == "latency":
            self.faults.latency_ns = int(args["ms"] * 1e6)
        elif name == "protective_stop":
            self.ctrl.protective_stop("injected fault")
        elif name == "estop":
            self.ctrl.emergency_stop()
        elif name == "power_off":
            self.ctrl.power_off()
        elif name == "refuse_upload":
            self.ctrl.refuse_upload = True

    def _clear(self) -> None:
        self.faults.latency_ns = 0
        self.faults.stall_until_ns = 0
        for port in list(self.faults.down_until_ns):
            del self.faults.down_until_ns[port]
            self._listen(port)
        self.ctrl.refuse_upload = False
        self.ctrl.clear_protective_stop()
        self.ctrl.release_emergency_stop()


def serve(options: SimOptions) -> int:
    """Run the simulator until it is told to stop; return the exit code."""
    server = SimServer(options)
    try:
        server.start()
    except OSError as exc:
        log.error("sim_robot_bind_failed", host=options.host, error=str(exc))
        server.close()
        return 3

    def _stop(signum: int, frame: Any) -> None:
        server.running = False

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    # Below the motion loop (80), above the tactile process (40); memory and CPU left as they are.
    rt = make_realtime(
        RealtimeOptions(priority=_FIFO_PRIORITY if options.realtime else 0, cpu=None, lock_memory=False, timer_slack_ns=_TIMER_SLACK_NS)
    )
    if options.realtime:
        if rt.fifo:
            log.info("sim_robot_realtime", policy="SCHED_FIFO", priority=_FIFO_PRIORITY)
        else:
            log.warning("sim_robot_realtime_refused", error=rt.refused)
    server.run()
    return 0
