"""The tactile process: its entry point and its handle in the daemon.

:func:`tactile_main` runs in its own process (``multiprocessing`` spawn):
it asks for real time (:mod:`celld.realtime`), builds its camera with the
picklable frame-source factory it was given (the cell's OpenCV camera, or
the simulated cell's), and runs the camera loop of
:mod:`celld.tactile.camera` into the shared-memory slots until told to stop.
:class:`TactileProcess` starts and stops it from the daemon, owns the slots,
restarts it on the same slots after it died, and asks it to tare.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from multiprocessing.synchronize import Event
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from celld import sealed
from celld.config import TactileConfig, ToolConfig
from celld.errors import DamagedStateError, DeviceError
from celld.log import get_logger, run_child, settings
from celld.realtime import RealtimeOptions, make_realtime
from celld.shm import SeqlockSlot
from celld.supervision import ChildRecords, ParentWatch
from celld.tactile.camera import (
    COUNTERS_DTYPE,
    FrameEstimator,
    FrameSourceFactory,
    PreviewWriter,
    opencv_camera,
    preview_dtype,
    run_camera,
)
from celld.tactile.deformation import Tare
from celld.tactile.sample import TACTILE_DTYPE, TactileSample, from_record

log = get_logger(__name__)

# How long the parent waits for the process to come up, s.
_START_TIMEOUT = 20.0
# How the finger's reference rest is sealed (celld.sealed).
REST_KIND = "finger-rest"
# The daemon's camera process: SCHED_FIFO below the motion loop (80) and the
# simulated controller (50), any CPU; best effort at nice -10 where refused.
CAMERA_REALTIME = RealtimeOptions(priority=40, cpu=None, lock_memory=False, nice=-10)


def tactile_main(
    cfg: TactileConfig,
    tool: ToolConfig,
    slot_name: str,
    counters_name: str,
    stop: Event,
    tare_request: Event,
    ready: Event,
    source_factory: FrameSourceFactory = opencv_camera,
    realtime: RealtimeOptions = CAMERA_REALTIME,
    preview_slot: str = "",
    parent_pid: int = 0,
    heartbeat: str = "",
    parent_timeout_ns: int = 3_000_000_000,
    rest_file: str = "",
) -> None:
    """Entry point of the tactile process (``multiprocessing`` spawn target).

    The process ends when told to (``stop``) and when its daemon is gone or
    hangs (:class:`~celld.supervision.ParentWatch`): a camera without its
    daemon has nobody to serve. ``rest_file`` keeps the finger's reference
    rest (:mod:`celld.tactile.camera`) across restarts.
    """
    parent = ParentWatch(parent_pid, heartbeat, parent_timeout_ns) if parent_pid else None
    cv2.setNumThreads(1)
    rt = make_realtime(realtime)
    if rt.refused:
        log.warning("tactile_process_not_fully_real_time", refused=rt.refused, fifo=rt.fifo)
    samples = SeqlockSlot.attach(slot_name, TACTILE_DTYPE)
    counters = SeqlockSlot.attach(counters_name, COUNTERS_DTYPE)
    preview_shm = SeqlockSlot.attach(preview_slot, preview_dtype(cfg)) if preview_slot else None
    preview = PreviewWriter(preview_shm, cfg) if preview_shm is not None else None
    source = source_factory(cfg)
    try:
        source.open()
        est = FrameEstimator(cfg, tool, reference=load_reference(rest_file) if rest_file else None)
        est.counters[0]["pid"] = os.getpid()
        est.counters[0]["tare_offset"] = np.nan
        ready.set()

        def requested() -> bool:
            if tare_request.is_set():
                tare_request.clear()
                return True
            return False

        def stopped() -> bool:
            if stop.is_set():
                return True
            why = parent.check() if parent is not None else ""
            if why:
                log.warning("tactile_process_ends", reason=why)
            return bool(why)

        def keep(rest: Tare) -> None:
            if rest_file:
                save_reference(rest_file, rest)

        run_camera(source, est, samples, counters, stopped, requested, preview, keep)
    finally:
        source.close()
        samples.close()
        counters.close()
        if preview_shm is not None:
            preview_shm.close()
        if parent is not None:
            parent.close()


def load_reference(path: str | Path) -> np.ndarray | None:
    """The finger's reference rest kept in ``path`` (camera frame, m), or None when there is none.

    A file that cannot be read as one is logged and ignored: the next tare
    then becomes the reference (and replaces the file).
    """
    try:
        data = sealed.read_sealed(path, REST_KIND, "finger rest")
        if data is None:
            return None
        ref = np.asarray(data["p_cam_rest_m"], dtype=np.float64)
        if ref.shape != (3,) or not np.all(np.isfinite(ref)) or float(np.linalg.norm(ref)) > 1.0:
            raise ValueError(f"p_cam_rest_m: expected 3 finite numbers within 1 m, got {data['p_cam_rest_m']!r}")
    except (DamagedStateError, ValueError, KeyError, TypeError) as exc:
        log.error("srm_reference_rest_unusable", path=str(path), error=str(exc))
        return None
    return ref


def save_reference(path: str | Path, rest: Tare) -> None:
    """Keep ``rest`` as the finger's reference rest (atomic write)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    body = {
        "p_cam_rest_m": rest.p_cam_rest.tolist(),
        "spread_m": rest.spread,
        "frames": rest.n_frames,
        "taken": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    try:
        sealed.write_sealed(p, body, REST_KIND)
    except OSError as exc:
        log.error("srm_reference_rest_not_kept", path=str(p), error=str(exc))


class TactileProcess:
    """Starts and stops the tactile process; owns its sample and counter slots.

    Parameters
    ----------
    cfg : TactileConfig
    tool : ToolConfig
    name : str
        Prefix of the shared-memory names (unique per cell instance).
    source_factory : FrameSourceFactory
        Builds the camera inside the process (picklable); the cell's OpenCV
        camera unless the simulated cell hands its own.
    heartbeat : str
        The daemon's heartbeat slot the process watches ("" for none); it
        also watches this process, its parent.
    parent_timeout : float
        s the heartbeat may stand still before the process ends.
    records : ChildRecords, optional
        Where the daemon records its children.
    rest_file : path, optional
        Where the finger's reference rest is kept (the daemon's
        ``state_dir/tactile/rest.json``); "" keeps none, so every tare is taken.
    realtime : RealtimeOptions
        How the process asks for real time (:data:`CAMERA_REALTIME` unless
        given): SCHED_FIFO below the motion loop's priority (the process
        sleeps between frames, so it takes what detection costs, but gets it
        on time), else a negative niceness ahead of best-effort work. A
        camera frame must be read within its period, so on a busy cell PC
        the tactile process should not queue behind the main process's scan
        processing.
    """

    def __init__(
        self,
        cfg: TactileConfig,
        tool: ToolConfig,
        name: str,
        source_factory: FrameSourceFactory = opencv_camera,
        realtime: RealtimeOptions = CAMERA_REALTIME,
        heartbeat: str = "",
        parent_timeout: float = 3.0,
        records: ChildRecords | None = None,
        rest_file: str | Path = "",
    ) -> None:
        self.cfg = cfg
        self.slot_name = f"{name}-tactile"
        self.counters_name = f"{name}-tactile-counters"
        self.samples = SeqlockSlot.create(self.slot_name, TACTILE_DTYPE)
        self.counters = SeqlockSlot.create(self.counters_name, COUNTERS_DTYPE)
        self.preview_name = f"{name}-tactile-preview"
        self.preview = SeqlockSlot.create(self.preview_name, preview_dtype(cfg))
        ctx = mp.get_context("spawn")
        self._ctx = ctx
        self._stop = ctx.Event()
        self._tare = ctx.Event()
        self._ready = ctx.Event()
        self._args = (
            cfg,
            tool,
            self.slot_name,
            self.counters_name,
            self._stop,
            self._tare,
            self._ready,
            source_factory,
            realtime,
            self.preview_name,
            os.getpid(),
            heartbeat,
            int(parent_timeout * 1e9),
            str(rest_file),
        )
        self._records = records
        self._proc = self._new_process()
        self.restarts = 0

    def _new_process(self) -> Any:
        return self._ctx.Process(target=run_child, args=(settings(), tactile_main, *self._args), name="celld-tactile", daemon=True)

    def restart(self, timeout: float = _START_TIMEOUT) -> int | None:
        """Start a new process on the same slots after this one died; returns the dead one's exit code.

        The motion process keeps reading the same sample slot, so it sees the
        new camera process's samples (after its tare) without a restart of its own.
        """
        if self._proc.is_alive():
            raise DeviceError("the tactile process is running; stop it before a restart")
        code = self._proc.exitcode
        self._stop.clear()
        self._ready.clear()
        self._proc = self._new_process()
        self.restarts += 1
        self.start(timeout)
        return code

    def start(self, timeout: float = _START_TIMEOUT) -> None:
        self._proc.start()
        if self._records is not None and self._proc.pid is not None:
            self._records.add("tactile", self._proc.pid, [self.slot_name, self.counters_name, self.preview_name])
        deadline = time.monotonic() + timeout
        while not self._ready.wait(0.1):
            if not self._proc.is_alive():
                raise DeviceError(f"the tactile process exited at start (exit code {self._proc.exitcode})")
            if time.monotonic() > deadline:
                # End the process, keep the slots: a restart may use them (stop() releases them).
                self._proc.terminate()
                self._proc.join(1.0)
                if self._proc.is_alive():
                    self._proc.kill()
                    self._proc.join(1.0)
                raise DeviceError(f"the tactile process did not come up within {timeout} s")

    def request_tare(self) -> None:
        self._tare.set()

    def tare(self, timeout: float = 10.0) -> None:
        """Tare now (the finger must be free) and wait until it is done (blocking).

        Raises
        ------
        DeviceError
            The process is not running, or no tare succeeded within ``timeout``.
        """
        if not self.alive():
            raise DeviceError("the tactile process is not running")
        before = self.read_counters()
        done = int(before["tares"]) if before is not None else 0
        self.request_tare()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            c = self.read_counters()
            if c is not None and int(c["tares"]) > done:
                return
            time.sleep(0.02)
        raise DeviceError(f"the SRM did not tare within {timeout:g} s (is the tag in view and the finger free?)")

    def latest(self) -> TactileSample | None:
        rec, _ = self.samples.read()
        return None if rec is None or int(rec["seq"]) == 0 else from_record(rec)

    def latest_preview(self) -> tuple[int, np.ndarray, np.ndarray | None] | None:
        """The latest frame shared for viewing: (capture stamp, grey image, tag corners or None), or None."""
        rec, _ = self.preview.read()
        if rec is None or int(rec["stamp_ns"]) <= 0:
            return None
        corners = np.array(rec["corners_px"]) if bool(rec["has_tag"]) else None
        return int(rec["stamp_ns"]), np.array(rec["image"]), corners

    def read_counters(self) -> np.void | None:
        rec, _ = self.counters.read()
        return rec

    @property
    def exitcode(self) -> int | None:
        return self._proc.exitcode

    def running(self) -> bool:
        """Started and reading its camera (not merely alive: a process starting may still fail)."""
        return self._proc.is_alive() and self._ready.is_set()

    def alive(self) -> bool:
        return self._proc.is_alive()

    def stop(self, timeout: float = 5.0) -> int | None:
        """Stop the process (if it was started) and release the slots."""
        self._stop.set()
        if self._records is not None:
            self._records.remove("tactile")
        if self._proc.pid is not None:
            self._proc.join(timeout)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(1.0)
        for slot in (self.samples, self.counters, self.preview):
            slot.close()
            slot.unlink()
        return self._proc.exitcode
