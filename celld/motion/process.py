"""The motion process: its entry point, real-time set-up and robot link construction.

The supervisor starts :func:`main` in a fresh interpreter (multiprocessing's
``spawn`` start method: a forked child of a threaded parent, or of one that
imported ur-rtde, can deadlock). The process

1. attaches to the shared-memory channels and reports ``CONNECTING``;
2. constructs ur-rtde's control, receive and IO interfaces (they hold the GIL
   while they wait, which is why they live here, under the supervisor's
   connect timeout) and sets the RTDE watchdog;
3. imports the servo laws it may be asked to run, so the loop never imports;
4. raises itself to SCHED_FIFO, pins its loop thread to one CPU and locks its
   memory where the OS allows it, raises ur-rtde's receive threads to just
   below the loop through the watchdog handshake (:data:`LINK_BELOW_LOOP`),
   and says once in the log when any of it is refused;
5. disables the garbage collector and runs the loop until the link is lost or
   a shutdown completes, then reports why in the status slot, switches the
   process output (the welding arc) off if the loop may have left it on, ends
   the control script on a graceful shutdown, and exits at once with a code
   the supervisor reads (:data:`EXIT_CODES`): the sockets close with the
   process, so ur-rtde's own disconnect (its receive threads joined, 1 s) and
   the interpreter's shutdown (1 s more) would only keep a stopping daemon,
   or the next one, waiting.

Only the thread that runs the loop is pinned: ur-rtde's receive threads,
created while connecting, keep the process's CPUs, so the loop spinning on
its CPU never stands between them and the state it waits for.
"""

from __future__ import annotations

import gc
import importlib
import os
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from celld.config.power_source import PowerSourceConfig
from celld.errors import LinkLost, MotionError
from celld.log import configure, get_logger
from celld.motion.channels import STATUS_DTYPE, ChannelNames, Channels, Phase, encode_reason
from celld.motion.core import CoreParams, MotionCore
from celld.motion.loop import LoopExit, LoopParams, MotionLoop
from celld.motion.types import ControlStatus, ServoFactory
from celld.realtime import RealtimeOptions, RealtimeReport, make_realtime, schedule_threads
from celld.supervision import ParentWatch, write_exit_note

# ur-rtde's receive threads poll their sockets (100 us sleeps): about a fifth of a core each, idle or not.
# Every command ur-rtde sends (speedL, speedJ, the watchdog kick) first spins until the control script's
# state, which those threads receive, says "ready"; it stops saying so after each command ur-rtde waits on
# (setWatchdog at start; the loop sends no other). Starved at best effort on a busy machine, they held
# the loop past the robot's watchdog right after setWatchdog. So they run at SCHED_FIFO this far below
# the loop through that handshake, and then best effort at ``motion.link_nice``: at SCHED_FIFO for good,
# four of them (two robots) took the two-core simulated cell's best-effort work a core, and a two-robot
# job ran 2.4 times as long (bench/README.md).
LINK_BELOW_LOOP = 1

# Exit code of the process for each way the loop ends; anything else is a crash.
EXIT_CODES = {
    ControlStatus.OK: 0,
    ControlStatus.LINK_LOST: 3,
    ControlStatus.SAFETY: 4,
    ControlStatus.FAULT: 5,
}


@dataclass(frozen=True)
class MotionSpec:
    """Everything the motion process needs; picklable, built by the supervisor."""

    host: str
    channels: ChannelNames
    core: CoreParams
    loop: LoopParams
    frequency_hz: float = 500.0
    watchdog_hz: float = 10.0  # the robot's program stops 1/watchdog_hz s after the writes stop
    realtime: RealtimeOptions = RealtimeOptions()
    # Servo laws this process can run: plan name -> "module:attribute" of a ServoFactory.
    servo_laws: tuple[tuple[str, str], ...] = ()
    log_level: str = "info"
    log_json: bool = False
    # The daemon this process must not outlive (celld.supervision.ParentWatch):
    # its pid, its heartbeat slot ("" for none) and the heartbeat's timeout, ns.
    parent_pid: int = 0
    heartbeat: str = ""
    parent_timeout_ns: int = 3_000_000_000
    # The daemon's name for this process in its child records (robot 1's "motion", robot 2's "motion2"), and
    # the file where the process says why it took its daemon for gone ("" for none): the next daemon reads
    # it, so the journal says why a job ended when its daemon hung or died (celld.supervision.exit_notes).
    role: str = "motion"
    exit_note: str = ""
    # Niceness of ur-rtde's receive threads after the watchdog handshake (motion.link_nice).
    link_nice: int = -10
    # The welding power source's wiring ([power_source]); None: the cell has none.
    source: PowerSourceConfig | None = None


def load_factories(servo_laws: tuple[tuple[str, str], ...]) -> dict[str, ServoFactory]:
    """Import each ``"module:attribute"`` servo factory; raise MotionError naming the one that fails."""
    out: dict[str, ServoFactory] = {}
    for name, path in servo_laws:
        module, _, attr = path.partition(":")
        try:
            out[name] = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise MotionError(f"servo law {name!r}: cannot import {path!r}: {exc}") from exc
    return out


def _report(
    ch: Channels, phase: Phase, rt: RealtimeReport | None = None, exit_status: ControlStatus = ControlStatus.OK, reason: str = ""
) -> None:
    rec = np.zeros(1, STATUS_DTYPE)
    rec["phase"] = int(phase)
    rec["pid"] = os.getpid()
    rec["phase_ns"] = time.monotonic_ns()
    rec["realtime"] = bool(rt.fifo) if rt else False
    rec["cpu"] = rt.cpu if rt else -1
    rec["exit_status"] = int(exit_status)
    rec["reason"] = encode_reason(reason or (rt.refused if rt else ""))
    ch.status.write(rec)


def run(spec: MotionSpec, hold: list[object]) -> LoopExit:
    """Connect, set up and run the loop; return why it ended.

    The link goes into ``hold``, to outlive this call: its ur-rtde objects disconnect when they are
    destroyed (their receive threads joined: 1 s), which the process's exit (:func:`main`) skips.
    """
    from celld.motion.source_io import SourceIO
    from celld.robot.link import RtdeLink

    log = get_logger(__name__).bind(host=spec.host, pid=os.getpid())
    # Watch the daemon from the start: a SIGTERM while connecting is remembered, not fatal.
    parent = ParentWatch(spec.parent_pid, spec.heartbeat, spec.parent_timeout_ns) if spec.parent_pid else None
    ch = Channels.attach(spec.channels)
    link = None
    loop: MotionLoop | None = None
    end: LoopExit | None = None
    try:
        _report(ch, Phase.CONNECTING)
        try:
            source = SourceIO(spec.source) if spec.source is not None else None
            link = RtdeLink.connect(spec.host, spec.frequency_hz, source.variables() if source is not None else ())
            hold.append(link)
            if source is not None:
                source.attach(link.receive, link.io)
        except LinkLost as exc:
            log.warning("robot_link_not_established", reason=str(exc))
            end = LoopExit(ControlStatus.LINK_LOST, str(exc))
            return end
        factories = load_factories(spec.servo_laws)
        core = MotionCore(spec.core, factories)
        loop = MotionLoop(link, core, ch, spec.loop, parent=parent, source=source)
        rt = make_realtime(spec.realtime)
        link_priority = spec.realtime.priority - LINK_BELOW_LOOP if rt.fifo else 0
        if link_priority > 0:
            # ur-rtde's receive threads were started above, before the loop's thread was pinned: any CPU.
            refused = schedule_threads(link.threads, link_priority)
            if refused:
                rt = rt._replace(refused="; ".join(filter(None, (rt.refused, refused))))
        if rt.refused:
            log.warning(
                "motion_loop_not_fully_real_time",
                refused=rt.refused,
                fifo=rt.fifo,
                cpu=rt.cpu,
                memory_locked=rt.memory_locked,
            )
        else:
            log.info(
                "motion_loop_real_time",
                fifo_priority=spec.realtime.priority,
                cpu=rt.cpu,
                link_threads=len(link.threads),
                link_handshake_priority=link_priority,
                link_nice=spec.link_nice,
            )
        _report(ch, Phase.RUNNING, rt)
        gc.collect()
        gc.freeze()
        gc.disable()
        try:
            # Last, so the set-up above (mlockall can take a while) cannot outlast the watchdog.
            link.set_watchdog(spec.watchdog_hz)
            # The first kick waits inside ur-rtde for the script to be ready again: then the handshake is over.
            link.kick()
            if link_priority > 0:
                settled = schedule_threads(link.threads, 0, spec.link_nice)
                if settled:
                    log.warning("rtde_receive_threads_not_best_effort", nice=spec.link_nice, refused=settled)
            end = loop.run()
        except LinkLost as exc:
            end = LoopExit(ControlStatus.LINK_LOST, str(exc))
        finally:
            gc.enable()
        # Say why at once: closing the link below can take a while.
        _report(ch, Phase.EXITED, rt, end.status, end.reason)
        if loop.orphaned and spec.exit_note:
            write_exit_note(spec.exit_note, spec.role, loop.orphaned)
        log.info(
            "motion_loop_ended",
            status=end.status.name,
            reason=end.reason,
            cycles=loop.cycles,
            overruns=loop.overruns,
            orphaned_ns=loop.orphaned_ns,  # monotonic: when the loop took its daemon for gone (0: it did not)
        )
        return end
    finally:
        if loop is not None and not loop.release_output():
            # After the exit report: on a dead link ur-rtde tries to reconnect first.
            log.error(
                "process_output_not_switched_off",
                advice="the robot's I/O set-up must switch it off at a program stop",
                output=spec.loop.process_output,
                power_source=str(spec.source.signal("arc_start")) if spec.source is not None else "",
            )
        if link is not None and end is not None and end.status == ControlStatus.OK and not (loop is not None and loop.orphaned):
            # A graceful end stops the robot's program; otherwise the robot's watchdog does.
            link.stop_script()
        ch.close()
        # The arm is at rest and the output off: the process ends at once (main). ur-rtde's disconnect (its
        # receive threads joined, 1 s) and the interpreter's shutdown (1 s more) are owed to no one: the
        # sockets close with the process. Without its daemon the next one may be starting, and a stopping
        # daemon waits for this exit.


def main(spec: MotionSpec) -> None:
    """Process entry point (spawned by the supervisor); exits with :data:`EXIT_CODES`."""
    configure(spec.log_level, json=spec.log_json)
    ch = Channels.attach(spec.channels)
    _report(ch, Phase.STARTING)
    hold: list[object] = []  # the robot link, alive until the exit below
    try:
        end = run(spec, hold)
    except Exception as exc:  # report any crash to the supervisor before dying  # noqa: BLE001
        end = LoopExit(ControlStatus.FAULT, f"motion process failed: {exc!r}")
        get_logger(__name__).exception("motion_process_failed")
    _report(ch, Phase.EXITED, None, end.status, end.reason)
    ch.close()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(EXIT_CODES.get(end.status, 5))


def servo_laws_from(mapping: Mapping[str, str]) -> tuple[tuple[str, str], ...]:
    """The picklable form of a ``{name: "module:attribute"}`` registry."""
    return tuple(sorted(mapping.items()))
