"""The 500 Hz loop of the motion process: wait, read, step, send, record.

Each cycle:

1. wait for the deadline: sleep until ``spin`` (300 µs) before it, then spin,
   so the wake-up does not depend on the timer slack of the kernel;
2. check the link (``isConnected`` and the freshness of the state: ur-rtde's
   return values do not say when the link is dead) and read the robot;
3. read the latest tactile sample and streaming setpoint (seqlocks: a torn
   read keeps the last good sample and is counted), the control slot (stop,
   shutdown) and at most one command from the mailbox;
4. step :class:`~celld.motion.core.MotionCore` and send what it says
   (speedL, speedJ in a joint move, or a watchdog kick while it holds still: after a motion, only once
   the controller has run on its zero speeds), then switch the process
   output (the welding arc) when the core's ``process_on`` changed;
5. append one record to the state ring.

The process output (``LoopParams.process_output``, a standard digital output;
-1: none) is written only on a change, and once at the first cycle (off), so
a process that starts after a crash of its predecessor does not leave the arc
as it found it. A write that fails is retried every cycle and reported once
in the events ring (command id 0: it ends no command). When the loop has
ended, :meth:`MotionLoop.release_output` switches the output off; the motion
process calls it on every way out, after it has reported why the loop ended
(on a dead link ur-rtde's IO interface tries to reconnect first). Where the
link is gone for good, only the robot's own I/O set-up (outputs off at
program stop) can switch the arc off.

Nothing in the cycle logs, waits on anything but the period, or grows a
container; Python still creates small temporary objects, which is why the
process runs with the garbage collector disabled. A lost link ends the loop
with its reason; the supervisor restarts the process.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from celld.errors import InputError
from celld.motion import so3
from celld.motion.arc import ArcOutput
from celld.motion.channels import CONTROL_DTYPE, EVENT_DTYPE, SETPOINT_DTYPE, STATE_DTYPE, Channels, encode_reason
from celld.motion.commands import Command, decode
from celld.motion.core import Action, CycleInput, Mode, MotionCore
from celld.motion.safety import describe, robot_faults
from celld.motion.source_io import SourceIO
from celld.motion.types import ControlStatus, RobotState
from celld.robot.link import RUNTIME_PLAYING, RobotPort
from celld.supervision import ParentWatch
from celld.tactile.sample import TACTILE_DTYPE, TactileSample, from_record

_INF = float("inf")
# The start of the loop's event when it finds the process output left on (the arc interlock is not set up).
INTERLOCK_MISSING = "arc interlock missing"
# Controller time (s) the zero speeds that end a motion are sent for before the loop kicks instead:
# three controller cycles, so one has read them whatever came back to back.
_ZERO_CONFIRM = 0.006
# The loop looks for its daemon every this many cycles (10 ms at 500 Hz).
_PARENT_CHECK_CYCLES = 5


class LoopParams(NamedTuple):
    """Timing and link bounds of the loop (nanoseconds where the clock is read)."""

    period_ns: int
    speed_accel: float  # speedL's own ramp, m/s^2 (and rad/s^2); above what the limiter uses
    joint_speed_accel: float = 8.0  # speedJ's own ramp, rad/s^2; above what a joint move uses
    spin_ns: int = 300_000  # sleep to this long before the deadline, then spin
    link_timeout_ns: int = 100_000_000  # no fresh robot state this long: the link is lost
    program_grace_ns: int = 100_000_000  # the robot's program not running this long: exit
    process_output: int = -1  # standard digital output of the process (welding arc), 0..7; -1: none
    # While the arm moves or the process is on, the daemon counts as hung once its heartbeat is this old
    # (0: the parent watch's own timeout, as at rest): a hung daemon can cancel nothing, so the arm and
    # the arc must not go on without it.
    hang_timeout_ns: int = 0


class LoopExit(NamedTuple):
    """Why the loop ended: OK on a shutdown, LINK_LOST or SAFETY otherwise."""

    status: ControlStatus
    reason: str


class MotionLoop:
    """Runs :class:`MotionCore` against a :class:`~celld.robot.link.RobotPort` (module docstring).

    Parameters
    ----------
    port : RobotPort
        The robot (ur-rtde in the cell).
    core : MotionCore
    channels : Channels
        Attached shared-memory channels.
    params : LoopParams
    clock : callable returning int ns
        ``time.monotonic_ns`` except in tests.
    parent : ParentWatch, optional
        The daemon this loop must not outlive: when it is gone (or hangs) the
        loop stops the robot (jerk-limited, the process output off at once)
        and ends, as on a shutdown request.
    source : SourceIO, optional
        The welding power source's signals (attached to the port's link): read
        every cycle into the core's input, its outputs written when the core's
        arc output changes, every one off in :meth:`release_output`.
    """

    def __init__(
        self,
        port: RobotPort,
        core: MotionCore,
        channels: Channels,
        params: LoopParams,
        clock: Callable[[], int] = time.monotonic_ns,
        parent: ParentWatch | None = None,
        source: SourceIO | None = None,
    ) -> None:
        self.port = port
        self.source = source
        self._source_checked = False  # the arc_start output's interlock check was made
        self._source_failed = False  # a failed source write was reported; cleared by the next success
        self.parent = parent
        self.orphaned = ""  # why the loop took its daemon for gone, "" while it is there
        self.orphaned_ns = 0  # when it did (the cycle's wake-up, monotonic ns), 0 while it is there
        self._busy = False  # the last cycle moved the arm or had the process on (LoopParams.hang_timeout_ns)
        self.core = core
        self.ch = channels
        self.params = params
        self.clock = clock
        self.cycles = 0
        self.overruns = 0
        self._last_stamp = _INF
        self._fresh_ns = clock()
        self._not_playing_since = -1
        self._prev_wake = 0
        # Reused buffers: one record per channel, read into and written from.
        self._rec = np.zeros(1, STATE_DTYPE)
        # The tactile sample's fields of the record change only with a new sample (set where it is read).
        self._rec["delta_tool"] = np.nan
        self._rec["contact"] = -1
        self._rec["arc_phase"] = -1
        self._rec["weld_current"] = np.nan
        self._rec["weld_voltage"] = np.nan
        self._evt = np.zeros(1, EVENT_DTYPE)
        self._tac = np.zeros(1, TACTILE_DTYPE)
        self._sp = np.zeros(1, SETPOINT_DTYPE)
        self._ctl = np.zeros(1, CONTROL_DTYPE)
        self._tactile: TactileSample | None = None
        self._tactile_seq = -1
        self._setpoint = np.zeros(6)
        self._setpoint_t = 0
        # The speed command whose zero the robot has not been seen to run on yet (_confirm_zero), and
        # the robot's stamp when the first zero went out (inf: not yet).
        self._unconfirmed: Action | None = None
        self._zero_from = _INF
        # The process output as last written: None until the first write succeeds.
        self._output_on: bool | None = None
        self._output_failed = False  # a failed write was reported; cleared by the next success
        # A process starting after a restart must not act on what its predecessor left.
        self.ch.control.read_into(self._ctl)
        self._stop_epoch = int(self._ctl["stop_epoch"][0])
        self._stop_posted = int(self._ctl["stop_posted"][0])
        self._drain_stale_commands()

    def _drain_stale_commands(self) -> None:
        mb = self.ch.commands
        while mb.pending():
            cid = mb.taken + 1
            mb.take()
            self._event(cid, ControlStatus.STOPPED, "cancelled: the motion process restarted before running it")

    def _event(self, command_id: int, status: ControlStatus, reason: str) -> None:
        e = self._evt
        e["t_ns"] = self.clock()
        e["command_id"] = command_id
        e["status"] = int(status)
        e["reason"] = encode_reason(reason)
        self.ch.events.append(e)

    # -- the process output ----------------------------------------------------

    def _switch_output(self, on: bool) -> bool:
        idx = self.params.process_output
        try:
            ok = bool(self.port.set_digital_out(idx, on))
        except Exception:  # a port must not take the loop down; RtdeLink never raises here  # noqa: BLE001
            ok = False
        if ok:
            self._output_on = on
            self._output_failed = False
        elif not self._output_failed:
            self._output_failed = True
            self._event(
                0,
                ControlStatus.FAULT,
                f"process output {idx}: switching it {'on' if on else 'off'} failed; retrying every cycle",
            )
        return ok

    def _check_interlock(self) -> None:
        """At the first write: was the process output left on by whatever ran before this process?

        A motion process that ended without switching it off (killed, or its
        link lost) leaves that to the robot's own I/O set-up: the output must
        go low when the program stops (the RTDE watchdog stops it). Finding it
        on here means the set-up does not do it; say so, loudly, once.
        """
        idx = self.params.process_output
        try:
            left_on = bool(self.port.digital_outputs() >> idx & 1)
        except Exception:  # a port must not take the loop down  # noqa: BLE001
            return
        if left_on:
            self._event(
                0,
                ControlStatus.FAULT,
                f"{INTERLOCK_MISSING}: process output {idx} was still on when this motion process started; set it to "
                "go low when the program stops (robot Installation > I/O Setup)",
            )

    @property
    def output_on(self) -> bool | None:
        """The process output as last written (None: not written yet, or no process output)."""
        return self._output_on

    def release_output(self) -> bool:
        """Switch the process output off unless it is known to be off; True when it is off (or absent).

        Call after the loop has ended (module docstring); never raises.
        """
        source_off = self.source.release() if self.source is not None else True
        if self.params.process_output < 0 or self._output_on is False:
            return source_off
        self._output_failed = False  # a failure here is news, whatever happened in the loop
        return self._switch_output(False) and source_off

    def _write_source(self, arc: ArcOutput) -> None:
        """Write the power source's outputs that changed; a failure is reported once and retried every cycle."""
        src = self.source
        if src is None:
            return
        if not self._source_checked:
            self._source_checked = True
            try:
                left_on = src.left_on(self.port.digital_outputs())
            except Exception:  # a port must not take the loop down  # noqa: BLE001
                left_on = False
            if left_on:
                self._event(
                    0,
                    ControlStatus.FAULT,
                    f"{INTERLOCK_MISSING}: the power source's arc_start output was still on when this motion process "
                    "started; set it to go low when the program stops (robot Installation > I/O Setup)",
                )
        if src.write(arc):
            self._source_failed = False
        elif not self._source_failed:
            self._source_failed = True
            self._event(0, ControlStatus.FAULT, f"{src.write_error or 'a power source output could not be written'}; retrying every cycle")

    # -- waiting -------------------------------------------------------------

    def wait_until(self, deadline_ns: int) -> int:
        """Sleep to ``spin_ns`` before ``deadline_ns``, then spin; return the wake-up time."""
        clock = self.clock
        remaining = deadline_ns - clock() - self.params.spin_ns
        if remaining > 0:
            time.sleep(remaining * 1e-9)
        now = clock()
        while now < deadline_ns:
            now = clock()
        return now

    def run(self, max_cycles: int = 0) -> LoopExit:
        """Run until the link is lost, a shutdown completes, or ``max_cycles`` (0: no bound)."""
        period = self.params.period_ns
        deadline = self.clock() + period
        while True:
            t_wake = self.wait_until(deadline)
            end = self.cycle(t_wake, deadline)
            if end is not None:
                return end
            if max_cycles and self.cycles >= max_cycles:
                return LoopExit(ControlStatus.OK, f"ran {max_cycles} cycles")
            deadline += period
            now = self.clock()
            if now > deadline:
                self.overruns += 1
                if now > deadline + period:
                    # More than a whole period behind: skip the missed deadlines, keep the phase.
                    deadline += ((now - deadline) // period) * period

    def _confirm_zero(self, action: Action, twist: np.ndarray, stamp: float) -> Action:
        """The command to send for the core's ``action``: the zero speeds that end a motion, until the robot ran on them.

        The robot keeps the speeds it was last sent. Its control script reads the
        command registers once a cycle, so a write that another follows within
        the same controller cycle (two loop cycles back to back after a late
        one, or a stalled controller taking in what queued) is never seen. The
        kick after a motion's final zero speeds must not be the write that hides
        them, or the arm creeps on at its last small speed: the zero speeds go
        on, in place of kicks, until the controller's clock has run
        :data:`_ZERO_CONFIRM` past the first of them.
        """
        if action == Action.SPEED or action == Action.SPEED_J:
            if twist.any():
                self._unconfirmed, self._zero_from = action, _INF
            elif self._unconfirmed is not None and self._zero_from == _INF:
                self._zero_from = stamp
            return action
        if self._unconfirmed is None:
            return action
        if self._zero_from == _INF:
            self._zero_from = stamp
        if stamp - self._zero_from < _ZERO_CONFIRM:
            return self._unconfirmed  # the core's twist is zero whenever it kicks
        self._unconfirmed = None
        return action

    # -- one cycle -------------------------------------------------------------

    def cycle(self, t_wake: int, deadline: int) -> LoopExit | None:
        """One cycle at wake-up time ``t_wake`` (module docstring); a LoopExit ends the loop."""
        p = self.params
        port = self.port
        if not port.connected():
            return LoopExit(ControlStatus.LINK_LOST, "the RTDE link reports it is disconnected")
        raw = port.read()
        if raw.stamp != self._last_stamp:
            self._last_stamp = raw.stamp
            self._fresh_ns = t_wake
        age_ns = t_wake - self._fresh_ns
        if age_ns > p.link_timeout_ns:
            return LoopExit(ControlStatus.LINK_LOST, f"no fresh robot state for {age_ns / 1e6:.0f} ms")
        if raw.runtime_state != RUNTIME_PLAYING:
            if self._not_playing_since < 0:
                self._not_playing_since = t_wake
            elif t_wake - self._not_playing_since > p.program_grace_ns:
                faults = robot_faults(raw.safety_bits)
                if faults:
                    return LoopExit(ControlStatus.SAFETY, f"the robot program stopped: {describe(faults)}")
                return LoopExit(ControlStatus.LINK_LOST, f"the robot program stopped (runtime state {raw.runtime_state})")
        else:
            self._not_playing_since = -1

        pose = raw.tcp_pose
        T = np.eye(4)
        T[:3, :3] = so3.exp(pose[3:])
        T[0, 3], T[1, 3], T[2, 3] = pose[0], pose[1], pose[2]
        state = RobotState(t_wake, np.array(raw.q), np.array(raw.qd), T, np.array(raw.tcp_speed))

        ch = self.ch
        tactile_age = _INF
        if ch.tactile.read_into(self._tac):
            seq = int(self._tac["seq"][0])
            if seq != self._tactile_seq:
                self._tactile_seq = seq
                self._tactile = from_record(self._tac[0])
                self._rec["delta_tool"] = self._tac["delta_tool"]
                self._rec["contact"] = self._tac["contact"]
            tactile_age = (t_wake - int(self._tac["stamp_ns"][0])) * 1e-9
        setpoint_age = _INF
        if ch.setpoint.read_into(self._sp):
            self._setpoint = self._sp["twist"][0]
            setpoint_age = (t_wake - int(self._sp["t_ns"][0])) * 1e-9

        reading = self.source.read() if self.source is not None else None

        stop = False
        shutdown = False
        if self.parent is not None and not self.orphaned and self.cycles % _PARENT_CHECK_CYCLES == 0:
            busy = self._busy and p.hang_timeout_ns > 0
            self.orphaned = self.parent.check(t_wake, p.hang_timeout_ns if busy else None)
            if self.orphaned:
                self.orphaned_ns = t_wake
        if ch.control.read_into(self._ctl):
            epoch = int(self._ctl["stop_epoch"][0])
            if epoch != self._stop_epoch:
                self._stop_epoch = epoch
                self._stop_posted = int(self._ctl["stop_posted"][0])
                stop = True
            shutdown = bool(self._ctl["shutdown"][0])
            stop = stop or shutdown
        if self.orphaned:
            stop = shutdown = True

        command: Command | None = None
        command_error = ""
        command_id = 0
        mb = ch.commands
        if mb.pending():
            command_id = mb.taken + 1
            payload = mb.take()
            if command_id <= self._stop_posted:
                self._event(command_id, ControlStatus.STOPPED, "cancelled by a stop request")
                command_id = 0
            elif shutdown:
                self._event(command_id, ControlStatus.STOPPED, "cancelled: the motion process is shutting down")
                command_id = 0
            else:
                try:
                    command = decode(payload or b"")
                except InputError as exc:
                    command_error = str(exc)

        out = self.core.step(
            CycleInput(
                state,
                age_ns * 1e-9,
                raw.safety_bits,
                self._tactile,
                tactile_age,
                self._setpoint,
                setpoint_age,
                command,
                command_id,
                command_error,
                stop,
                f"stopped: {self.orphaned}" if self.orphaned else "",
                reading.signals if reading is not None else None,
                reading.collision if reading is not None else False,
            )
        )
        action = self._confirm_zero(out.action, out.twist, raw.stamp)
        if action == Action.SPEED:
            port.speed(out.twist.tolist(), p.speed_accel)
        elif action == Action.SPEED_J:
            port.speed_joints(out.twist.tolist(), p.joint_speed_accel)
        else:
            port.kick()
        t_sent = self.clock()
        if p.process_output >= 0 and out.process_on != self._output_on:
            if self._output_on is None:
                self._check_interlock()
            self._switch_output(out.process_on)
        if self.source is not None and out.arc is not None:
            self._write_source(out.arc)

        if out.event:
            self._event(out.event_id, out.event_status, out.event)
        self._busy = out.mode != Mode.IDLE or out.process_on
        self.cycles += 1
        r = self._rec
        r["cycle"] = self.cycles
        r["t_ns"] = t_wake
        r["late_ns"] = t_wake - deadline
        r["period_ns"] = t_wake - self._prev_wake if self._prev_wake else 0
        r["work_ns"] = t_sent - t_wake
        r["robot_stamp"] = raw.stamp
        r["state_age_ns"] = age_ns
        r["q"] = raw.q
        r["qd"] = raw.qd
        r["tcp_pose"] = pose
        r["tcp_speed"] = raw.tcp_speed
        r["safety_bits"] = raw.safety_bits
        r["runtime_state"] = raw.runtime_state
        r["mode"] = int(out.mode)
        r["action"] = int(action)
        r["guarded"] = out.guarded
        r["status"] = int(out.status)
        r["faults"] = int(out.faults)
        r["command_id"] = out.command_id
        r["twist"] = out.twist
        r["tactile_seq"] = self._tactile_seq
        r["tactile_age_ns"] = int(tactile_age * 1e9) if tactile_age != _INF else -1
        r["tactile_torn"] = ch.tactile.torn_count
        r["overruns"] = self.overruns
        tel = out.telemetry
        r["servo_phase"] = tel.phase
        r["delta_n"] = tel.delta_n
        r["refined_base"] = tel.refined_base
        r["process_on"] = out.process_on
        r["delta_d"] = tel.delta_d
        if reading is not None and out.arc is not None:
            r["arc_phase"] = int(out.arc.phase)
            r["source_bits"] = reading.bits
            r["weld_current"] = reading.current
            r["weld_voltage"] = reading.voltage
        ch.state.append(r)
        self._prev_wake = t_wake

        if shutdown and out.mode == Mode.IDLE:
            if self.orphaned:
                return LoopExit(ControlStatus.OK, f"{self.orphaned}: the robot is stopped, the motion process ends")
            return LoopExit(ControlStatus.OK, "shutdown requested")
        return None
