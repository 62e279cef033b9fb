"""The celld daemon: start-up, supervision, the bus, systemd, shutdown.

Start-up, in order, each step refusing to go on when it fails:

1. the config is loaded and validated (before any device is opened);
2. the state directory and the job journal: jobs a previous process left
   running are marked interrupted, the recordings it left open are listed
   (merged into readable files once the daemon serves; their jobs' reasons
   say so), and the journal's integrity is checked; a damaged journal is a
   storage fault the status names with its way out (``celld journal
   set-aside``): the daemon serves, and refuses jobs;
3. the motion process (it owns the robot link; :class:`MotionHandle`
   supervises and restarts it) and the tactile camera process;
4. the scanner (one that does not open is tried again in the background);
5. the zenoh session, the bus server and the cell's liveliness token;
6. ``READY=1`` to systemd as soon as the bus is served, with or without the
   robot, the scanner or the camera: a cell PC that boots before its robot
   is not restarted again and again. Until they are there, status (and
   systemd's STATUS) says what the cell waits for ("robot link down:
   waiting (...)"), and a job that needs a missing device is refused at
   once with that reason. ``WATCHDOG=1`` follows while the event loop runs
   and the motion process is supervised (its supervisor makes progress),
   link up or not: a protective stop or a lost link is the supervisor's to
   handle, a hung daemon is systemd's.

SIGTERM or SIGINT: the robot stops first (jerk-limited), queued and running
jobs end as cancelled, then the bus, the devices and the motion process close.
"""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from celld import fsutil, preflight, sdnotify
from celld.bus.keys import CellKeys
from celld.bus.server import BusServer
from celld.bus.session import callers, open_server
from celld.config import Config
from celld.daemon.devices import CellDevices, DeviceFactories
from celld.daemon.jobs import JobManager, Runner
from celld.daemon.loopwatch import LoopWatch
from celld.daemon.runners import build_runners
from celld.daemon.statedir import open_state
from celld.errors import JournalError
from celld.journal import INTERRUPTED_RUNNING, Journal
from celld.log import get_logger
from celld.recording.job import JobRecording, finalise_parts, leftover_parts

log = get_logger(__name__)

# The motion heartbeat counts as fresh below this age, s.
HEARTBEAT_FRESH = 0.5
# How often the daemon says again what it waits for (systemd's STATUS, the log when it changes), s.
WAIT_REPORT_PERIOD = 1.0
# How often robot state goes to the bus (the server decimates further), s.
STATE_PERIOD = 0.05
# How many of the newest interrupted jobs an exit note of the previous daemon's children is matched against.
_RECENT_INTERRUPTED = 10


class Daemon:
    """One cell's daemon. ``devices`` opens and closes the cell's devices.

    Parameters
    ----------
    config : Config
    devices : celld.daemon.devices.CellDevices
        The robot (motion handle), the tactile sensor and the scanner, real or
        simulated, behind one interface.
    runners : mapping of job kind to Runner
        Built by :func:`celld.daemon.runners.build_runners` from the devices.
    """

    def __init__(self, config: Config, devices: Any, runners: Mapping[str, Runner]) -> None:
        self.config = config
        self.devices = devices
        self.runners = runners
        self.state_dir = Path(config.cell.state_dir)
        self.notifier = sdnotify.Notifier()
        self.manager: JobManager | None = None
        self.bus: BusServer | None = None
        self._session: Any = None
        self._journal: Journal | None = None
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        # How late the event loop runs, and why (every stall over 50 ms logged, counted in the status).
        self.loop_watch = LoopWatch()

    # -- life cycle ---------------------------------------------------------------

    def _explain_interruptions(self, journal: Journal) -> None:
        """Say why the job the previous daemon left running ended, as its motion process noted it when it took
        the daemon for gone (hung, killed), not as an operator's stop: the job interrupted while running that
        started before the note and was marked interrupted after it (by this daemon's journal, or by a tool
        that opened the journal first)."""
        notes = self.devices.life.exit_notes
        if not notes or journal.damage:
            return
        why = "; ".join(f"{n['role']} process: {n['reason']}" for n in notes)
        for record in journal.jobs(limit=_RECENT_INTERRUPTED, state="interrupted"):
            explained = record.reason.startswith(INTERRUPTED_RUNNING + ":")
            if (
                record.reason.startswith(INTERRUPTED_RUNNING)
                and not explained
                and any((record.started or "") <= n["at"] <= (record.ended or "") for n in notes)
            ):
                journal.explain_interruption(record.id, why)
                log.warning("job_interrupted_by_children_note", job=record.id, why=why)

    async def _finalise_recordings(self, journal: Journal, parts: list[Path]) -> None:
        """Merge the recordings a dead daemon left open (``parts``, listed before any job ran) into readable ``.rrd``
        files, and say so in their jobs; after READY, as a task: a large one takes seconds."""
        for done in await asyncio.to_thread(finalise_parts, parts):
            if done.error:
                note = f"its recording was left unfinished and could not be merged ({done.error}): the streams are in {done.path}"
            else:
                note = f"its recording was cut short when the daemon stopped: what was written is in {done.path}"
            try:
                if journal.get(done.job) is not None:
                    journal.note(done.job, note)
            except JournalError as exc:  # a damaged journal is said elsewhere; the file is finalised anyway
                log.error("recording_finalised_not_noted", job=done.job, error=str(exc))

    async def start(self) -> None:
        cfg = self.config
        self.loop_watch.install()
        self._tasks.append(asyncio.get_running_loop().create_task(self.loop_watch.run(), name="celld-loop-watch"))
        self.state_dir.mkdir(parents=True, exist_ok=True)
        fresh = not (self.state_dir / "journal.db").exists()
        # The journal's lock first: a second daemon on this state directory is refused before it touches
        # anything in it (the temporaries below may be a running daemon's writes in flight).
        self._journal = Journal(self.state_dir / "journal.db", keep_damaged=True)
        # Then the directory's format: refused when newer than this release, migrated when older.
        open_state(self.state_dir, fresh)
        problems = self._journal.check()
        if problems:
            self._journal.mark_damaged("; ".join(problems[:3]) + (f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""))
            log.error("job_journal_damaged", why=self._journal.damage_report())
        fsutil.remove_stale_temporaries(self.state_dir)
        leftovers = leftover_parts(self.state_dir)  # before any job opens a recording of its own
        for record in self._journal.recovered:
            log.warning("job_interrupted_by_previous_stop", job=record.id, kind=record.kind)
        self.notifier.status("opening devices")
        await self.devices.open(lambda: self.loop_watch.last_tick)
        self._explain_interruptions(self._journal)
        keys = CellKeys.of(cfg.bus.prefix, cfg.cell.name)
        self._session = open_server(cfg.bus, keys)
        self.manager = JobManager(
            self._journal,
            self.state_dir,
            self.runners,
            self._publish_progress,
            self.devices.stop_robot,
            cell=cfg.cell.name,
            recording_factory=self._open_recording if cfg.recording.enabled else None,
            link_state=self.devices.link_state,
            auto_accept=cfg.calibration.auto_accept,
            robot_report=self.devices.robot_report,
            robot_action=self.devices.robot_action,
            loop_report=self.loop_watch.report,
            min_free_mb=cfg.cell.min_free_mb,
            storage_retry_s=cfg.cell.storage_retry_s,
            storage_budget_mb=cfg.cell.storage_budget_mb,
            result_retention_days=cfg.cell.result_retention_days,
            unready=self.devices.unready,
        )
        self._update_fault()  # said from the first status on
        self.bus = BusServer(self._session.session, keys, self.manager, state_rate_hz=cfg.bus.state_rate_hz, callers=callers(cfg.bus))
        await self.bus.start()
        self.manager.start()
        loop = asyncio.get_running_loop()
        self._tasks.append(loop.create_task(self._publish_state(), name="celld-state"))
        self._tasks.append(
            loop.create_task(
                sdnotify.run_watchdog(self.notifier, self.devices.supervised, on_unhealthy=self._unsupervised),
                name="celld-watchdog",
            )
        )
        # READY once the bus is served; the devices that are not there yet are waited for, and said.
        self.notifier.ready()
        log.info("celld_serving", cell=cfg.cell.name, state_dir=str(self.state_dir))
        self._tasks.append(loop.create_task(self._report_waiting(), name="celld-waiting"))
        self._tasks.append(loop.create_task(self._supervise_scanner(), name="celld-scanner"))
        if leftovers:
            self._tasks.append(loop.create_task(self._finalise_recordings(self._journal, leftovers), name="celld-recordings"))

    async def run(self) -> None:
        """Start, serve until SIGTERM/SIGINT (or :meth:`request_stop`), then shut down."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                loop.add_signal_handler(sig, self.request_stop)
            except (NotImplementedError, RuntimeError):  # not the main thread (tests)
                pass
        try:
            await self.start()
            await self._stop.wait()
        finally:
            await self.shutdown()

    def request_stop(self) -> None:
        self._stop.set()

    async def shutdown(self) -> None:
        """Robot first, then jobs, bus, devices; safe to call more than once."""
        self.notifier.stopping()
        log.info("celld_stopping")
        try:
            await self.devices.stop_robot()
        except Exception as exc:  # the shutdown goes on whatever stopped the robot  # noqa: BLE001
            log.error("robot_stop_at_shutdown_failed", error=str(exc))
        if self.manager is not None:
            await self.manager.close()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        if self.bus is not None:
            await self.bus.close()
            self.bus = None
        if self._session is not None:
            self._session.close()
            self._session = None
        await self.devices.close()
        if self._journal is not None:
            self._journal.close()
            self._journal = None
        log.info("celld_stopped")

    # -- helpers -----------------------------------------------------------------------

    def _publish_progress(self, job: str, kind: str, state: str, stage: str, **kw: Any) -> None:
        if self.bus is not None:
            self.bus.publish_progress(job, kind, state, stage, **kw)

    def _open_recording(self, job_id: str, kind: str) -> JobRecording:
        rec_kind = {"calibrate": "calibration", "weld": "weld"}.get(kind, "other")
        recording = JobRecording.for_job(self.state_dir, job_id, rec_kind, self.config.recording)
        self.devices.attach_recording(recording)
        return recording

    def _update_fault(self) -> None:
        """The cell's fault in status: robot 1's link down (with what it waits for), robot 2 held by another
        program, or none."""
        if self.manager is not None:
            age = self.devices.heartbeat_age()
            up = age is not None and age < HEARTBEAT_FRESH
            fine = up and not self.devices.held2
            self.manager.set_fault("" if fine else self.devices.unready("move") or "the motion loop stalled")

    async def _report_waiting(self) -> None:
        """Say what the cell waits for: systemd's STATUS every period, the log when it changes."""
        said: list[str] | None = None
        name = self.config.cell.name
        while True:
            waiting = self.devices.waiting()
            problem = self.manager.storage.problem() if self.manager is not None else ""
            self.notifier.status(f"cell {name}: " + ("; ".join(w for w in (*waiting, problem) if w) or "ready"))
            devices = [w.partition(":")[0] for w in waiting]  # the log says it again when what is waited for changes
            if devices != said:
                if waiting:
                    log.warning("cell_waits", waiting=waiting)
                else:
                    log.info("celld_ready", cell=name)
                said = devices
            await asyncio.sleep(WAIT_REPORT_PERIOD)

    async def _supervise_scanner(self) -> None:
        """Open the scanner again while it is not open (an open may take seconds: its own task)."""
        while True:
            await asyncio.sleep(WAIT_REPORT_PERIOD)
            await self.devices.scanner.supervise()

    def _unsupervised(self) -> None:
        self.notifier.status("the motion process is not supervised: watchdog not kicked")

    async def _publish_state(self) -> None:
        while True:
            await asyncio.sleep(STATE_PERIOD)
            if self.bus is None:
                continue
            robot = self.devices.robot_state_message()
            if robot is not None:
                self.bus.publish_robot_state(robot)
            tactile = self.devices.tactile.state_message()
            if tactile is not None:
                self.bus.publish_tactile_state(tactile)
            await self.devices.tactile.supervise()
            self._update_fault()


def serve(config: Config, factories: DeviceFactories, take_over: bool = False) -> None:
    """Run the daemon of ``config`` on the devices ``factories`` open, until SIGTERM or SIGINT; with ``take_over``
    robot 1 is taken even from another program running on it (:class:`~celld.daemon.devices.CellDevices`).

    Raises
    ------
    ConfigError
        What the config names is missing or unusable here (:mod:`celld.preflight`).
    """
    preflight.require(config)
    devices = CellDevices(config, factories, take_over)
    asyncio.run(Daemon(config, devices, build_runners(config, devices)).run())
