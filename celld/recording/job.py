"""One rerun recording per job: an ``.rrd`` file, optionally streamed live.

:class:`JobRecording` owns one :class:`rerun.RecordingStream` whose
``recording_id`` is the job id. It writes ``<state_dir>/recordings/<job_id>.rrd``
with the default blueprint of :mod:`celld.recording.layout`, and can at the
same time serve the stream on a loopback gRPC port or push it to a viewer
address from :class:`celld.config.RecordingConfig`.

Every method takes values in the package's frames and units and logs them at
the given ``time.monotonic_ns()`` stamp. Nothing here belongs in the 500 Hz
loop: motion state arrives in batches from the state ring through
:meth:`JobRecording.log_state_batch`, which sends columns.

The stream is thread safe; the current time of a rerun stream is per thread,
so each method sets it before it logs.

The file is written by this module, not by rerun's file sink: rerun encodes
into a memory stream (:class:`rerun.BinaryStream`) and a small thread moves
the bytes into ``<job>.rrd.part`` with plain ``os.write`` every
:data:`_DRAIN_PERIOD` s. rerun's own file sink, on a full disk, printed the
error in its log only, then made ``flush`` time out and ``disconnect`` hang
for good; here a failed write is an ``OSError`` that the recording keeps
(:attr:`JobRecording.write_error`, visible while the job runs) and that
:meth:`JobRecording.close` raises as
:class:`~celld.errors.RecordingWriteError` (a StorageError): the job that
owned the recording then fails with the reason.

Each read of a rerun 0.41 memory stream is a whole RRD stream with its own
footer, and a file of several such streams is refused by rerun's reader
("More than one RRD manifest", a CRC error). So :meth:`JobRecording.close`
merges the part file into one stream with the rerun CLI that comes with the
SDK (``rerun rrd merge``: 1.5 s and about the file's size in memory for 360
MB), then renames it into place; the part file is removed. A merge that
fails (the disk full again) keeps the part file and says how to merge it by
hand.

A process that died mid-job leaves its part file; the daemon lists them at
start (:func:`leftover_parts`) and :func:`finalise_parts` merges each into
its ``.rrd`` the same way
(rerun's merge reads a stream cut mid-write up to the cut and drops the
rest), so every recording opens in rerun's viewer and reader.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple
from urllib.parse import urlsplit

import numpy as np
import rerun as rr
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from celld import se3
from celld.config import RecordingConfig
from celld.errors import CelldError, InputError, RecordingError, RecordingWriteError
from celld.log import get_logger
from celld.recording import layout
from celld.recording.state import DEFAULT_SERIES, Series, state_columns

log = get_logger(__name__)

# rerun's application id: the viewer groups all job recordings under it.
APPLICATION_ID = "celld"
# Job ids and entity names become file names and entity path parts.
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
# Segments of a logged circle ring.
_CIRCLE_SEGMENTS = 96
# Length of the drawn axes of the TCP and camera frames, m.
_AXIS_LENGTH = 0.05
# Length of a circle's drawn normal, in radii.
_NORMAL_LENGTH_RADII = 1.0
# How long close() waits for the sinks to take the last data, s.
_FLUSH_TIMEOUT = 5.0
# How long opening a recording waits to see whether a viewer listens, s.
_PROBE_TIMEOUT = 0.5
# Calibration residual arrows are drawn this many times their length.
_RESIDUAL_SCALE = 20.0
# Longest a recording's merge may take at close, s (360 MB: 1.5 s).
_MERGE_TIMEOUT = 300.0
# How often encoded bytes move from rerun's memory stream into the file, s.
_DRAIN_PERIOD = 0.2
# State batches waiting for the recording's feed thread (:meth:`JobRecording.feed_state_batch`); beyond
# this (about 30 s of 500 Hz state in 0.1 s batches) a batch is dropped and counted.
_FEED_DEPTH = 300
# The feed thread sends the motion state it was handed at most this often, s: every send_columns call
# costs the GIL a fixed time in rerun's Python conversion, so many small batches cost the daemon more
# than a few large ones.
_STATE_FLUSH_PERIOD = 0.5


def _idle() -> None:
    """What the feed thread runs when nothing was queued for a while."""


def recording_path(state_dir: str | Path, job_id: str) -> Path:
    """Where the recording of ``job_id`` lives: ``<state_dir>/recordings/<job_id>.rrd``."""
    return Path(state_dir) / "recordings" / f"{_check_name(job_id, 'job_id')}.rrd"


def _check_name(name: str, what: str) -> str:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise InputError(f"{what}: expected 1-128 letters, digits, '_', '-' or '.', not starting with a symbol, got {name!r}")
    return name


def _port_free(host: str, port: int) -> bool:
    """Whether ``host:port`` can be bound now (a busy port would fail inside rerun, silently)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def _viewer_listening(url: str, timeout: float = _PROBE_TIMEOUT) -> bool:
    """Whether something accepts TCP connections at the host and port of a rerun viewer URL."""
    parts = urlsplit(url)
    default_port = 80 if parts.scheme == "rerun+http" else 443
    try:
        with socket.create_connection((parts.hostname or "127.0.0.1", parts.port or default_port), timeout=timeout):
            return True
    except (OSError, ValueError):
        return False


def _points(P: ArrayLike, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Return the finite rows of ``P`` (n, 3) or (H, W, 3) as float32, and their mask."""
    arr = np.asarray(P)
    if arr.ndim < 2 or arr.shape[-1] != 3:
        raise InputError(f"{name}: expected an (n, 3) or (H, W, 3) array of points, got shape {arr.shape}")
    flat = arr.reshape(-1, 3).astype(np.float32, copy=False)
    keep = np.all(np.isfinite(flat), axis=1)
    return flat[keep], keep


def _colors(colors: ArrayLike | None, n_all: int, keep: np.ndarray, name: str) -> np.ndarray | None:
    """Colours matching the kept points: uint8 RGB, or floats in [0, 1]."""
    if colors is None:
        return None
    c = np.asarray(colors)
    if c.ndim < 1 or c.size == 0 or c.shape[-1] not in (3, 4) or c.reshape(-1, c.shape[-1]).shape[0] not in (1, n_all):
        raise InputError(f"{name}: expected one RGB(A) colour or one per point ({n_all}), got shape {c.shape}")
    c = c.reshape(-1, c.shape[-1])
    if c.dtype != np.uint8:
        c = np.clip(np.asarray(c, dtype=np.float64) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return c if len(c) == 1 else c[keep]


class _FileWriter:
    """Moves rerun's encoded bytes into the ``.rrd`` file, so a failed write is an OSError here.

    After the first failed write the file is incomplete: later bytes are read
    (so nothing piles up in memory) and dropped, and :attr:`error` keeps the
    first failure.
    """

    def __init__(self, path: Path, stream: Any) -> None:
        self.path = path
        self.part = path.with_name(path.name + ".part")
        self.stream = stream
        self.error: OSError | None = None
        self.merge_error = ""
        self.written = 0
        self._lock = threading.Lock()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.part, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise RecordingWriteError("recording", str(path), f"cannot create it: {exc.strerror or exc}", exc.errno) from exc
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"rrd-writer-{path.stem}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(_DRAIN_PERIOD):
            self.drain()

    def drain(self) -> None:
        """Write what rerun has encoded so far."""
        with self._lock:
            data = self.stream.read(flush=False)
            if not data or self._fd < 0 or self.error is not None:
                return
            view = memoryview(data)
            try:
                while view:
                    n = os.write(self._fd, view)
                    view = view[n:]
                    self.written += n
            except OSError as exc:
                self.error = exc
                log.error("recording_write_failed", path=str(self.path), error=str(exc), written=self.written)

    def close(self) -> None:
        """Stop the thread, write the rest, make it durable, close the file."""
        self._stop.set()
        self._thread.join()
        self.drain()
        with self._lock:
            if self._fd < 0:
                return
            try:
                if self.error is None:
                    os.fsync(self._fd)
            except OSError as exc:
                self.error = exc
            finally:
                os.close(self._fd)
                self._fd = -1
        if self.error is None:
            self._merge()

    def _merge(self) -> None:
        """Merge the part file's streams into the one ``.rrd`` stream, then rename it into place."""
        self.merge_error = merge_part(self.part, self.path)
        if self.merge_error:
            log.error("recording_merge_failed", part=str(self.part), error=self.merge_error)


def merge_part(part: Path, path: Path) -> str:
    """Merge the RRD streams of ``part`` into one at ``path`` (rerun's ``rrd merge``), then remove ``part``;
    why not, or ""."""
    tmp = path.with_name(path.name + ".merging")
    cmd = [sys.executable, "-m", "rerun_cli", "rrd", "merge", str(part), "-o", str(tmp)]
    try:
        done = subprocess.run(cmd, capture_output=True, timeout=_MERGE_TIMEOUT, check=False)
        if done.returncode == 0 and tmp.exists():  # rerun's CLI may exit 0 having written nothing
            os.replace(tmp, path)
            part.unlink()
            return ""
        tail = done.stderr.decode(errors="replace").strip().splitlines()[-1:] or [f"exit code {done.returncode}"]
        error = tail[0]
    except (OSError, subprocess.TimeoutExpired) as exc:
        error = str(exc)
    with contextlib.suppress(OSError):
        tmp.unlink()
    return error


class Finalised(NamedTuple):
    """A recording a dead process left as a part file, finalised at start (:func:`finalise_parts`)."""

    job: str
    path: Path  # the .rrd, or the part file kept when the merge failed
    error: str  # why the merge failed, "" when it did not


def leftover_parts(state_dir: str | Path) -> list[Path]:
    """The ``<job>.rrd.part`` files under ``state_dir/recordings``: before any recording is opened, what a dead
    process left."""
    return sorted((Path(state_dir) / "recordings").glob("*.rrd.part"))


def finalise_parts(parts: Sequence[Path]) -> list[Finalised]:
    """Merge each of ``parts`` (:func:`leftover_parts`) into its ``.rrd``.

    A part beside its ``.rrd`` is the leftover of a merge that finished (the
    rename made, the removal not): it is removed. A merge that fails keeps
    the part and says why.
    """
    done: list[Finalised] = []
    for part in parts:
        path = part.with_name(part.name.removesuffix(".part"))
        job = path.stem
        if path.exists():
            with contextlib.suppress(OSError):
                part.unlink()
            log.info("recording_part_removed", job=job, path=str(path), why="its merge had finished")
            continue
        error = merge_part(part, path)
        if error:
            log.error("recording_not_finalised", job=job, part=str(part), error=error)
            done.append(Finalised(job, part, error))
        else:
            log.warning("recording_finalised", job=job, path=str(path), why="its process died before it closed it")
            done.append(Finalised(job, path, ""))
    return done


class JobRecording:
    """The rerun recording of one job.

    Parameters
    ----------
    path : str or Path or None
        The ``.rrd`` file to write (its directory is created). None records
        nothing to disk (live sinks only).
    job_id : str
        The job id; it is the rerun ``recording_id``.
    kind : str
        One of :data:`celld.recording.layout.KINDS`; chooses the first tab of
        the blueprint and is stored as a recording property.
    config : RecordingConfig, optional
        ``enabled = false`` makes every method a no-op; ``serve_grpc_port``
        serves the stream on ``serve_grpc_host``; ``connect_url`` pushes it to a
        viewer. A busy port or an unreachable viewer never fails the job: the
        file is written regardless and the problem is logged.
    t0_ns : int, optional
        ``time.monotonic_ns()`` of time zero of the ``time`` timeline; now by default.

    Raises
    ------
    InputError
        ``job_id`` or ``kind`` is not acceptable.
    RecordingWriteError
        The file cannot be created (a RecordingError and a StorageError).
    RecordingError
        rerun refused the sinks.

    Notes
    -----
    The first log of a stream pays rerun's lazy set-up (165 ms measured in the
    research notes, 35-70 ms here); the constructor pays it by logging the
    static parts (properties, axes), so a job's first real sample takes under
    a millisecond. A 500-record state batch costs about 10 ms to send.
    """

    def __init__(
        self,
        path: str | Path | None,
        job_id: str,
        kind: str = "other",
        config: RecordingConfig | None = None,
        *,
        t0_ns: int | None = None,
    ) -> None:
        config = config or RecordingConfig()
        self.job_id = _check_name(job_id, "job_id")
        if kind not in layout.KINDS:
            raise InputError(f"recording kind: expected one of {', '.join(layout.KINDS)}, got {kind!r}")
        self.kind = kind
        self.config = config
        self.t0_ns = time.monotonic_ns() if t0_ns is None else int(t0_ns)
        self.enabled = config.enabled
        self.path: Path | None = Path(path) if (path is not None and config.enabled) else None
        self.serve_url: str | None = None
        self.connect_url: str | None = None
        self._closed = False
        self._writer: _FileWriter | None = None
        self._lock = threading.Lock()
        self._named: set[str] = set()
        self._ignored_reported: set[str] = set()
        self._feed: queue.Queue[Callable[[], Any] | np.ndarray | None] = queue.Queue(_FEED_DEPTH)
        self._feeding: threading.Thread | None = None
        # Guards the feed thread's start against close(): a batch handed over from the event loop while a worker
        # thread closes the recording must not leave close() joining a thread that is not started yet.
        self._feed_lock = threading.Lock()
        self._feed_closing = False
        self.dropped_batches = 0  # state batches the feed had no room for
        self._log = log.bind(job=job_id, kind=kind)
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=job_id, default_enabled=config.enabled, send_properties=True)
        if not config.enabled:
            return
        try:
            self._rec.set_sinks(*self._sinks(), default_blueprint=layout.default_blueprint(kind))
        except RuntimeError as exc:
            if self._writer is not None:
                self._writer.close()
            raise RecordingError(f"recording {self.job_id}: rerun refused its sinks: {exc}") from exc
        self._warm_up()

    @classmethod
    def for_job(cls, state_dir: str | Path, job_id: str, kind: str = "other", config: RecordingConfig | None = None) -> JobRecording:
        """Open the recording of ``job_id`` at :func:`recording_path` under ``state_dir``."""
        return cls(recording_path(state_dir, job_id), job_id, kind, config)

    # -- set-up ---------------------------------------------------------------

    def _sinks(self) -> list[Any]:
        sinks: list[Any] = []
        if self.path is not None:
            stream = rr.binary_stream(recording=self._rec)
            self._writer = _FileWriter(self.path, stream)
            sinks.append(stream)
        cfg = self.config
        if cfg.serve_grpc_port:
            if _port_free(cfg.serve_grpc_host, cfg.serve_grpc_port):
                sinks.append(rr.GrpcServerSink(bind_ip=cfg.serve_grpc_host, port=cfg.serve_grpc_port))
                self.serve_url = f"rerun+http://{cfg.serve_grpc_host}:{cfg.serve_grpc_port}/proxy"
            else:
                self._log.warning("recording_serve_port_busy", host=cfg.serve_grpc_host, port=cfg.serve_grpc_port)
        if cfg.connect_url:
            # A viewer that is not listening now is skipped: rerun would retry in
            # the background and then hold close() for seconds; the file has it all.
            if _viewer_listening(cfg.connect_url):
                try:
                    sinks.append(rr.GrpcSink(cfg.connect_url))
                    self.connect_url = cfg.connect_url
                except RuntimeError as exc:  # the config checks the scheme; rerun may still refuse
                    self._log.warning("recording_connect_refused", url=cfg.connect_url, error=str(exc))
            else:
                self._log.warning("recording_viewer_not_listening", url=cfg.connect_url)
        if not sinks:
            raise RecordingError(f"recording {self.job_id}: no sink (no file and no live viewing)")
        return sinks

    def _warm_up(self) -> None:
        rec = self._rec
        rec.send_recording_name(f"{self.kind} {self.job_id}")
        rec.send_property("job", rr.AnyValues(job_id=self.job_id, kind=self.kind))
        rec.log(layout.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.flush(timeout_sec=0.0)

    def _active(self) -> bool:
        """False when disabled or closed: a closed rerun stream would buffer in memory forever."""
        return self.enabled and not self._closed

    # -- time -----------------------------------------------------------------

    def _at(self, stamp_ns: int | None) -> None:
        """Set this thread's time to ``stamp_ns`` (now when None) and clear other timelines."""
        ns = time.monotonic_ns() if stamp_ns is None else int(stamp_ns)
        self._rec.reset_time()
        self._rec.set_time(layout.TIME, duration=np.timedelta64(ns - self.t0_ns, "ns"))

    def _name_series(self, entity: str, names: tuple[str, ...]) -> None:
        with self._lock:
            if entity in self._named:
                return
            self._named.add(entity)
        self._rec.log(entity, rr.SeriesLines(names=list(names)), static=True)

    # -- 3D scene -------------------------------------------------------------

    def _log_cloud(self, entity: str, P: ArrayLike, colors: ArrayLike | None, stamp_ns: int | None) -> int:
        if not self._active():
            return 0
        what = entity.rsplit("/", 1)[-1]
        pts, keep = _points(P, f"cloud {what}")
        cols = _colors(colors, len(keep), keep, f"cloud {what} colours")
        limit = self.config.max_cloud_points
        if limit and len(pts) > limit:
            # An even stride keeps the cloud's coverage; the full cloud belongs in the dataset, not the log.
            idx = np.linspace(0, len(pts) - 1, limit).astype(np.int64)
            pts = pts[idx]
            if cols is not None and len(cols) > 1:
                cols = cols[idx]
        self._at(stamp_ns)
        self._rec.log(entity, rr.Points3D(pts, colors=cols, radii=rr.Radius.ui_points(1.5)))
        return len(pts)

    def log_cloud_base(self, name: str, P_base: ArrayLike, colors: ArrayLike | None = None, stamp_ns: int | None = None) -> int:
        """Log a cloud in the base frame at ``/world/clouds/<name>``.

        Parameters
        ----------
        name : str
            Entity name (``"scan"``, ``"verification"``, ...).
        P_base : array_like
            (n, 3) or organized (H, W, 3) points in the base frame, metres;
            rows with NaN (no return) are dropped.
        colors : array_like, optional
            One RGB(A) colour or one per point (same layout as ``P_base``),
            uint8 or floats in [0, 1].
        stamp_ns : int, optional
            ``time.monotonic_ns()`` of the capture; now by default.

        Returns
        -------
        int
            Number of points logged (after dropping NaN rows and thinning to
            ``config.max_cloud_points``).
        """
        return self._log_cloud(f"{layout.CLOUDS_BASE}/{_check_name(name, 'cloud name')}", P_base, colors, stamp_ns)

    def log_cloud_cam(self, name: str, P_cam: ArrayLike, colors: ArrayLike | None = None, stamp_ns: int | None = None) -> int:
        """Log a cloud in the camera frame at ``/world/camera/clouds/<name>``.

        It is drawn through the camera pose of :meth:`log_camera_pose`
        (identity until one is logged). Arguments as :meth:`log_cloud_base`.
        """
        return self._log_cloud(f"{layout.CLOUDS_CAM}/{_check_name(name, 'cloud name')}", P_cam, colors, stamp_ns)

    def _log_pose(self, entity: str, T: ArrayLike, name: str, stamp_ns: int | None, static: bool = False) -> None:
        T = se3.check_transform(T, name)
        if not self._active():
            return
        if not static:
            self._at(stamp_ns)
        self._rec.log(
            entity,
            rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]),
            rr.TransformAxes3D(_AXIS_LENGTH),
            static=static,
        )

    def log_camera_pose(self, T_base_cam: ArrayLike, stamp_ns: int | None = None, static: bool = False) -> None:
        """Log the scanner pose ``T_base_cam`` (4, 4) at ``/world/camera`` (an estimate or the nominal).

        ``static``: the pose for the whole recording (a solved calibration):
        every cloud and circle logged in the camera frame, at any time, is
        drawn through it, so they all lie in the base frame.
        """
        self._log_pose(layout.CAMERA, T_base_cam, "T_base_cam", stamp_ns, static)

    def log_robot2_base(self, T_base1_base2: ArrayLike) -> None:
        """Log a second robot's base ``T_base1_base2`` (4, 4), as a robot-robot calibration solved it, at
        ``/world/robot2`` for the whole recording (its clouds lie in the camera's frame, named ``robot2-*``)."""
        self._log_pose(layout.ROBOT2, T_base1_base2, "T_base1_base2", None, static=True)

    def log_mesh(
        self,
        entity: str,
        vertices: ArrayLike,
        triangles: ArrayLike,
        T_base_obj: ArrayLike | None = None,
        color: tuple[int, int, int] = (170, 170, 180),
        static: bool = False,
        stamp_ns: int | None = None,
    ) -> None:
        """Log a triangle mesh (a workpiece, the flange) at ``entity`` under ``/world``.

        Parameters
        ----------
        entity : str
            Entity path under ``/world`` (:data:`~celld.recording.layout.WORKPIECE`, ``/world/tcp/flange``).
        vertices, triangles : array_like
            (v, 3) vertices in the object's frame, m; (f, 3) vertex indices.
        T_base_obj : array_like, optional
            (4, 4) pose of the object's frame in its parent's frame; None logs no
            transform (the mesh follows its parent, e.g. the TCP).
        static : bool
            For the whole recording (a model), not at a time.
        """
        if not entity.startswith(layout.WORLD + "/"):
            raise InputError(f"mesh entity: expected a path under {layout.WORLD}, got {entity!r}")
        V = se3.check_points(vertices, "mesh vertices", min_points=3)
        F = np.asarray(triangles)
        if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0 or not np.issubdtype(F.dtype, np.integer) or F.min() < 0 or F.max() >= len(V):
            raise InputError(f"mesh triangles: expected (f, 3) indices into {len(V)} vertices, got shape {F.shape}")
        T = None if T_base_obj is None else se3.check_transform(T_base_obj, "T_base_obj")
        if not self._active():
            return
        if not static:
            self._at(stamp_ns)
        parts: list[Any] = [rr.Mesh3D(vertex_positions=V.astype(np.float32), triangle_indices=F.astype(np.uint32), albedo_factor=color)]
        if T is not None:
            parts.append(rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        self._rec.log(entity, *parts, static=static)

    def log_residuals(
        self, ids: list[str], P_robot_base: ArrayLike, P_scanner_base: ArrayLike, outlier: ArrayLike, stamp_ns: int | None = None
    ) -> None:
        """Log a calibration's per-pair residuals: arrows and a bar chart.

        Parameters
        ----------
        ids : list of str
            Pair ids, in order.
        P_robot_base : array_like
            (n, 3) flange centres as the robot reports them, base frame, m.
        P_scanner_base : array_like
            (n, 3) the same centres as the scanner saw them, placed with the
            solved T_base_cam, base frame, m.
        outlier : array_like
            (n,) bool: the estimator left the pair out (drawn red).
        """
        A = se3.check_points(P_robot_base, "P_robot_base", min_points=1)
        B = se3.check_points(P_scanner_base, "P_scanner_base", min_points=1)
        out = np.asarray(outlier, dtype=bool).reshape(-1)
        if len(B) != len(A) or len(out) != len(A) or len(ids) != len(A):
            raise InputError(f"residuals: expected matching ids, points and outlier flags, got {len(ids)}, {len(A)}, {len(B)}, {len(out)}")
        if not self._active():
            return
        self._at(stamp_ns)
        colors = np.where(out[:, None], np.array([[230, 40, 40]]), np.array([[0, 200, 120]])).astype(np.uint8)
        # Arrows from the robot's centre to the scanner's, drawn 20 times longer (residuals are tenths of a mm).
        self._rec.log(
            layout.RESIDUALS,
            rr.Arrows3D(origins=A, vectors=(B - A) * _RESIDUAL_SCALE, colors=colors, labels=list(ids)),
        )
        self._rec.log(layout.CALIB_RESIDUALS, rr.BarChart(np.linalg.norm(B - A, axis=1) * 1e3))

    def log_tcp(self, T_base_tcp: ArrayLike, stamp_ns: int | None = None) -> None:
        """Log one TCP pose ``T_base_tcp`` (4, 4) at ``/world/tcp``.

        For the 500 Hz stream use :meth:`log_state_batch`; this is for single
        poses (a calibration pose, a touch point).
        """
        self._log_pose(layout.TCP, T_base_tcp, "T_base_tcp", stamp_ns)

    def _log_circle(self, entity: str, center: ArrayLike, normal: ArrayLike, radius: float, stamp_ns: int | None) -> None:
        c = np.asarray(center, dtype=np.float64)
        n = np.asarray(normal, dtype=np.float64)
        if c.shape != (3,) or n.shape != (3,) or not np.all(np.isfinite(c)) or not np.all(np.isfinite(n)):
            raise InputError(f"circle: expected finite centre (3,) and normal (3,), got shapes {c.shape} and {n.shape}")
        if np.linalg.norm(n) < 1e-9:
            raise InputError("circle: the normal is zero")
        if not (np.isfinite(radius) and radius > 0.0):
            raise InputError(f"circle: expected a positive radius in metres, got {radius}")
        if not self._active():
            return
        T = se3.frame_from_z(c, n)
        a = np.linspace(0.0, 2.0 * np.pi, _CIRCLE_SEGMENTS + 1)
        ring = se3.apply(T, np.column_stack([radius * np.cos(a), radius * np.sin(a), np.zeros_like(a)]))
        self._at(stamp_ns)
        self._rec.log(entity, rr.LineStrips3D([ring], colors=[(0, 220, 120)], radii=rr.Radius.ui_points(2.0)))
        self._rec.log(
            f"{entity}/normal",
            rr.Arrows3D(origins=[c], vectors=[T[:3, 2] * radius * _NORMAL_LENGTH_RADII], colors=[(0, 220, 120)]),
        )

    def log_circle_cam(self, name: str, center_cam: ArrayLike, normal_cam: ArrayLike, radius: float, stamp_ns: int | None = None) -> None:
        """Log a detected circle in the camera frame at ``/world/camera/circles/<name>``.

        Parameters
        ----------
        name : str
            Entity name (``"flange"``, ``"wrist"``).
        center_cam, normal_cam : array_like
            (3,) centre (m) and normal of the circle's plane, camera frame.
        radius : float
            Radius, metres.
        stamp_ns : int, optional
            Capture time; now by default.
        """
        self._log_circle(f"{layout.CAMERA}/circles/{_check_name(name, 'circle name')}", center_cam, normal_cam, radius, stamp_ns)

    def log_circle_base(
        self, name: str, center_base: ArrayLike, normal_base: ArrayLike, radius: float, stamp_ns: int | None = None
    ) -> None:
        """Log a circle in the base frame at ``/world/circles/<name>``; arguments as :meth:`log_circle_cam`."""
        self._log_circle(f"{layout.CIRCLES}/{_check_name(name, 'circle name')}", center_base, normal_base, radius, stamp_ns)

    def log_path_base(self, name: str, P_base: ArrayLike, stamp_ns: int | None = None) -> None:
        """Log a path polyline in the base frame at ``/world/paths/<name>``.

        Parameters
        ----------
        name : str
            ``"planned"``, ``"refined"`` or ``"torch"``.
        P_base : array_like
            (n, 3) path points in the base frame, metres, n >= 2, in order.
        """
        if name not in layout.PATH_COLORS:
            raise InputError(f"path name: expected one of {', '.join(layout.PATH_COLORS)}, got {name!r}")
        P = se3.check_points(P_base, f"{name} path P_base", min_points=2)
        if not self._active():
            return
        self._at(stamp_ns)
        self._rec.log(
            f"{layout.PATHS}/{name}",
            rr.LineStrips3D([P.astype(np.float32)], colors=[layout.PATH_COLORS[name]], radii=rr.Radius.ui_points(2.0)),
        )

    # -- plans: the cell, the robot, poses -------------------------------------

    def log_boxes(self, name: str, T_base_box: ArrayLike, sizes: ArrayLike, stamp_ns: int | None = None) -> None:
        """Log boxes (the cell model's objects) at ``/world/cell/<name>``: poses (k, 4, 4), edge lengths (k, 3), m."""
        T = np.asarray(T_base_box, dtype=np.float64).reshape(-1, 4, 4)
        size = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
        if len(T) != len(size) or not np.all(np.isfinite(T)) or not np.all(size > 0.0):
            raise InputError(f"boxes: expected matching poses (k, 4, 4) and positive sizes (k, 3), got {T.shape}, {size.shape}")
        if not self._active():
            return
        self._at(stamp_ns)
        quats = Rotation.from_matrix(T[:, :3, :3]).as_quat()  # x, y, z, w
        self._rec.log(
            f"{layout.CELL}/{_check_name(name, 'cell object name')}",
            rr.Boxes3D(
                centers=T[:, :3, 3],
                half_sizes=size / 2.0,
                quaternions=quats,
                colors=[(150, 150, 160)],
                fill_mode=rr.components.FillMode.Solid,
            ),
        )

    def log_capsules(self, name: str, ends_base: ArrayLike, radii: ArrayLike, stamp_ns: int | None = None) -> None:
        """Log capsules (the robot's links and tool at a pose) at ``/world/robot/<name>``: ends (k, 2, 3), radii (k,), m."""
        E = np.asarray(ends_base, dtype=np.float64).reshape(-1, 2, 3)
        r = np.asarray(radii, dtype=np.float64).reshape(-1)
        if len(E) != len(r) or not np.all(np.isfinite(E)) or not np.all(r > 0.0):
            raise InputError(f"capsules: expected ends (k, 2, 3) and positive radii (k,), got {E.shape}, {r.shape}")
        if not self._active():
            return
        self._at(stamp_ns)
        axis = E[:, 1] - E[:, 0]
        length = np.linalg.norm(axis, axis=1)
        # Capsules3D run along their local +z: rotate z onto each segment.
        z = np.array([0.0, 0.0, 1.0])
        rots = []
        for a, n in zip(axis, length):
            if n < 1e-12:
                rots.append(Rotation.identity())
            else:
                rots.append(Rotation.align_vectors([a / n], [z])[0])
        quats = np.array([q.as_quat() for q in rots])
        self._rec.log(
            f"{layout.ROBOT}/{_check_name(name, 'robot name')}",
            rr.Capsules3D(lengths=length, radii=r, translations=E[:, 0], quaternions=quats, colors=[(90, 140, 230)]),
        )

    # -- SRM camera -----------------------------------------------------------

    def log_camera_image(self, image: ArrayLike, corners_px: ArrayLike | None = None, stamp_ns: int | None = None) -> None:
        """Log an SRM camera frame at ``/srm/camera`` and the tag outline at ``/srm/camera/tag``.

        Parameters
        ----------
        image : array_like
            (H, W) grey or (H, W, 3) BGR (OpenCV order) uint8 image. Stored as
            JPEG at ``config.image_jpeg_quality`` (0: raw pixels).
        corners_px : array_like, optional
            (4, 2) tag corners in pixels, in ArUco order; None clears the outline
            (no tag detected in this frame).
        stamp_ns : int, optional
            Capture time of the frame; now by default.
        """
        img = np.asarray(image)
        if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (1, 3))):
            raise InputError(f"SRM image: expected an (H, W) or (H, W, 3) uint8 array, got {img.dtype} {img.shape}")
        if not self._active():
            return
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        archetype: Any = rr.Image(img, color_model="L" if img.ndim == 2 else "BGR")
        if self.config.image_jpeg_quality:
            archetype = archetype.compress(jpeg_quality=self.config.image_jpeg_quality)
        outline: Any = rr.Clear(recursive=False)
        if corners_px is not None:
            q = np.asarray(corners_px, dtype=np.float64).reshape(-1, 2) if np.size(corners_px) == 8 else None
            if q is None or not np.all(np.isfinite(q)):
                raise InputError(f"tag corners: expected (4, 2) finite pixel coordinates, got shape {np.shape(corners_px)}")
            outline = rr.LineStrips2D([np.vstack([q, q[:1]]).astype(np.float32)], colors=[(255, 60, 60)])
        self._at(stamp_ns)
        self._rec.log(layout.SRM_CAMERA, archetype)
        self._rec.log(layout.SRM_TAG, outline)

    # -- time series ----------------------------------------------------------

    def log_state_batch(self, batch: np.ndarray, series: tuple[Series, ...] = DEFAULT_SERIES) -> int:
        """Send a batch of motion-state ring records as columns.

        Parameters
        ----------
        batch : numpy.ndarray
            (n,) structured array read from the state ring
            (:meth:`celld.shm.Ring.read_since`); the field table of
            :mod:`celld.recording.state` says what is recorded where. Fields
            the table does not know are skipped and reported once in the log.
        series : tuple of Series
            The field table, if the ring names its fields otherwise.

        Returns
        -------
        int
            Number of records sent.
        """
        cols = state_columns(batch, series)
        if not self._active():
            return 0
        n = len(cols.stamp_ns)
        new_ignored = set(cols.ignored) - self._ignored_reported
        if new_ignored:
            self._ignored_reported |= new_ignored
            self._log.info("recording_fields_not_mapped", fields=sorted(new_ignored))
        if n == 0:
            return 0
        times = rr.TimeColumn(layout.TIME, duration=(cols.stamp_ns - self.t0_ns).astype("timedelta64[ns]"))
        if cols.T_base_tcp is not None:
            ok = np.all(np.isfinite(cols.T_base_tcp.reshape(n, -1)), axis=1)
            if ok.any():
                T = cols.T_base_tcp[ok]
                t_ok = rr.TimeColumn(layout.TIME, duration=(cols.stamp_ns[ok] - self.t0_ns).astype("timedelta64[ns]"))
                self._rec.send_columns(
                    layout.TCP,
                    indexes=[t_ok],
                    columns=rr.Transform3D.columns(
                        translation=T[:, :3, 3],
                        quaternion=Rotation.from_matrix(T[:, :3, :3]).as_quat(),  # x, y, z, w
                    ),
                )
        for col in cols.series:
            self._name_series(col.entity, col.names)
            values = col.values[:, 0] if col.values.shape[1] == 1 else col.values
            self._rec.send_columns(col.entity, indexes=[times], columns=rr.Scalars.columns(scalars=values))
        return n

    def feed_state_batch(self, batch: np.ndarray) -> None:
        """Hand a batch of motion-state records to the recording's feed thread, which sends what it was handed
        every :data:`_STATE_FLUSH_PERIOD` s as one batch (:meth:`log_state_batch`); returns at once, so the
        daemon's event loop never waits for rerun. A batch the feed has no room for is dropped and counted
        (:attr:`dropped_batches`)."""
        if not self._put(batch):
            self.dropped_batches += 1

    def event_later(self, text: str, level: str = "INFO") -> None:
        """:meth:`log_event` at this moment, sent by the feed thread (a job's progress, from the event loop)."""
        self.later(self.log_event, text, level, time.monotonic_ns())

    def later(self, method: Callable[..., Any], *args: Any) -> bool:
        """Queue ``method(*args)`` (a log method of this recording) for the feed thread, in order; False when the
        feed is full or the recording closed (nothing queued)."""
        return self._put(partial(method, *args))

    def _put(self, item: Callable[[], Any] | np.ndarray) -> bool:
        if not self._active():
            return False
        if self._feeding is None:
            with self._feed_lock:
                if self._feed_closing:
                    return False
                if self._feeding is None:
                    feeding = threading.Thread(target=self._feed_forever, name=f"rrd-feed-{self.job_id}", daemon=True)
                    feeding.start()
                    self._feeding = feeding
        try:
            self._feed.put_nowait(item)
        except queue.Full:
            return False
        return True

    def _feed_forever(self) -> None:
        """Run the queued calls in order; gather the state batches and send them together now and then."""
        state: list[np.ndarray] = []
        last = time.monotonic()
        while True:
            try:
                item = self._feed.get(timeout=_STATE_FLUSH_PERIOD)
            except queue.Empty:
                item = _idle
            if item is None:
                self._send_state(state)
                return
            if isinstance(item, np.ndarray):
                state.append(item)
            else:
                self._run(item)
            if state and time.monotonic() - last >= _STATE_FLUSH_PERIOD:
                self._send_state(state)
                state = []
                last = time.monotonic()

    def _send_state(self, batches: list[np.ndarray]) -> None:
        if batches:
            self._run(partial(self.log_state_batch, np.concatenate(batches)))

    def _run(self, call: Callable[[], Any]) -> None:
        try:
            call()
        except CelldError as exc:
            self._log.warning("recording_feed_not_recorded", error=str(exc))

    def log_e_icp(self, iteration: int, e_icp: float, stamp_ns: int | None = None) -> None:
        """Log the ICP error metric of Eq. 13 (metres) for one Algorithm 1 iteration.

        Eq. 13 is +inf when ICP fails; a non-finite value is recorded as NaN
        (a gap in the plot) and an event says so.
        """
        if isinstance(iteration, bool) or not isinstance(iteration, (int, np.integer)) or iteration < 0:
            raise InputError(f"iteration: expected a non-negative integer, got {iteration!r}")
        value = float(e_icp)
        if not self._active():
            return
        self._name_series(layout.CALIB_E_ICP, ("e_icp",))
        self._at(stamp_ns)
        self._rec.set_time(layout.ITERATION, sequence=int(iteration))
        self._rec.log(layout.CALIB_E_ICP, rr.Scalars([value if np.isfinite(value) else np.nan]))
        if not np.isfinite(value):
            self._rec.log(layout.EVENTS, rr.TextLog(f"iteration {iteration}: ICP failed (e_icp = {value})", level="WARN"))

    def log_event(self, text: str, level: str = "INFO", stamp_ns: int | None = None) -> None:
        """Log a line of text (job start, refusal, stop reason) at ``/events``."""
        if not self._active():
            return
        self._at(stamp_ns)
        self._rec.log(layout.EVENTS, rr.TextLog(str(text), level=level))

    # -- end ------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def write_error(self) -> OSError | None:
        """The first write to the file that failed (the file is incomplete), or None."""
        return self._writer.error if self._writer is not None else None

    def close(self) -> None:
        """Flush every sink and close them; the file gets its footer (index).

        Safe to call twice. An unreachable viewer costs up to about
        5 s here (rerun's final connection attempt); the file is complete
        regardless.

        Raises
        ------
        RecordingWriteError
            A write to the file failed (disk full, I/O error): the file is
            incomplete. The stream is closed all the same.
        """
        if self._closed:
            return
        with self._feed_lock:  # no feed thread starts from here on
            self._feed_closing = True
            feeding, self._feeding = self._feeding, None
        if feeding is not None:  # the state handed over so far goes in first
            self._feed.put(None)
            feeding.join()
        self._closed = True
        if self.dropped_batches:
            self._log.warning("recording_state_batches_dropped", batches=self.dropped_batches)
        if not self.enabled:
            return
        try:
            self._rec.flush(timeout_sec=_FLUSH_TIMEOUT)
        except RuntimeError as exc:  # a live sink that cannot take the data; the file has it
            self._log.warning("recording_flush_incomplete", error=str(exc))
        self._rec.disconnect()
        writer = self._writer
        if writer is not None:
            writer.close()
        self._log.info("recording_closed", path=str(self.path) if self.path else None)
        error = writer.error if writer is not None else None
        if error is not None:
            raise RecordingWriteError(
                "recording", str(self.path), f"{error.strerror or error} (errno {error.errno}); the recording is incomplete", error.errno
            ) from error
        if writer is not None and writer.merge_error:
            raise RecordingWriteError(
                "recording",
                str(self.path),
                f"its streams could not be merged into one file ({writer.merge_error}); they are kept in {writer.part}: "
                f"'python -m rerun_cli rrd merge {writer.part} -o {self.path}' merges them",
            )

    def __enter__(self) -> JobRecording:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()
