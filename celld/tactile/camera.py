"""The camera loop of the tactile process: SRM camera -> tag detection -> deformation -> shared memory.

The loop reads frames from a :class:`FrameSource` that a picklable factory
builds inside the tactile process (:func:`opencv_camera` on the cell; the
simulated cell hands its own), detects the tag (:mod:`celld.tactile.aruco`), turns it into a
:class:`~celld.tactile.sample.TactileSample` (:mod:`celld.tactile.deformation`)
stamped with the frame's capture time, and writes it into a seqlock slot that
the motion process reads every cycle. Every frame gives a sample: a failed
detection is written as an invalid sample whose status says why (no tag,
another id, blurred, bad pose), a camera that gives no frame as
``CAMERA_LOST``; none of them ever reads as zero deformation. Counters of each
outcome go to a second slot (:data:`COUNTERS_DTYPE`).

At start (and on request) the process tares: it averages ``tare_frames``
detections with the finger free; until a tare succeeds it writes
``NOT_TARED`` samples. "Free" is checked, not assumed. A tare the daemon
asks for is taken where it knows the finger is free (the weld's approach
pose, clear of the part): it is accepted and becomes the finger's reference
rest (kept across restarts). The process's own tare when it starts (or
restarts, e.g. in the middle of a weld) is accepted only within
``tare_max_offset`` of that reference: a camera restarted while the finger
is pressed against the part stays ``NOT_TARED``, the counters say how far
off the rest was, and the tare is retried until the finger is free. Without
a reference yet, the start-up tare is taken but not kept as one.

The process around the loop (its entry point, real-time set-up and its
handle in the daemon) is :mod:`celld.tactile.process`. OpenCV runs
single-threaded in it, so detection does not take the second core from the
motion loop.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, Protocol

import cv2
import numpy as np

from celld.config import TactileConfig, ToolConfig
from celld.errors import DeviceError, TactileError
from celld.log import get_logger
from celld.shm import SeqlockSlot
from celld.tactile.aruco import TagDetector
from celld.tactile.deformation import DeformationParams, Tare, TareRefused, estimate, invalid_sample, tare
from celld.tactile.sample import ContactState, TactileSample, TactileStatus, to_record

log = get_logger(__name__)

# Seconds between attempts to reopen a camera that stopped delivering.
_REOPEN_INTERVAL = 1.0
# Frames a tare may look at before it gives up and starts again.
_TARE_PATIENCE = 3

# Counters the process publishes: frames per outcome (index = TactileStatus).
COUNTERS_DTYPE = np.dtype(
    [
        ("frames", np.int64),
        ("by_status", np.int64, (len(TactileStatus),)),
        ("tared", np.bool_),
        ("p_cam_rest", np.float64, (3,)),
        ("tare_spread", np.float64),
        ("detect_ns", np.int64),  # of the last frame
        ("pid", np.int64),
        ("tares", np.int64),  # tares completed since the process started
        ("tare_refused", np.bool_),  # the last tare found the finger not free
        ("tare_offset", np.float64),  # its rest from the reference rest, m; NaN without a reference
    ]
)


class FrameSource(Protocol):
    """A camera: ``read()`` returns ``(capture stamp_ns, image)`` or None when it gives no frame."""

    def open(self) -> None: ...

    def read(self) -> tuple[int, np.ndarray] | None: ...

    def close(self) -> None: ...


class OpenCvCamera:
    """The SRM camera through ``cv2.VideoCapture`` (device, resolution and fps from the config).

    A frame's capture time is the time ``grab()`` returned minus the
    configured ``capture_latency`` (exposure and transfer), on the
    ``time.monotonic_ns()`` clock the motion process uses. A failed grab (the
    camera unplugged) returns None; the camera is reopened at most once a
    second after that.
    """

    def __init__(self, cfg: TactileConfig, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.cfg = cfg
        self._clock = clock
        self._cap: Any = None
        self._retry_at = 0.0

    def _device(self) -> int | str:
        d = self.cfg.device
        return int(d) if d.isdigit() else d

    def open(self) -> None:
        cap = cv2.VideoCapture(self._device())
        if not cap.isOpened():
            cap.release()
            raise DeviceError(f"SRM camera {self.cfg.device!r}: cannot open it (is it connected, and readable by this user?)")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.cfg.width_px)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.cfg.height_px)
        cap.set(cv2.CAP_PROP_FPS, self.cfg.fps)
        # Keep no queue of old frames: each grab should be the newest.
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (w, h) != (self.cfg.width_px, self.cfg.height_px):
            cap.release()
            raise DeviceError(
                f"SRM camera {self.cfg.device!r}: expected {self.cfg.width_px} x {self.cfg.height_px} px "
                f"(the intrinsics are for that size), the camera gives {w} x {h}"
            )
        self._cap = cap

    def read(self) -> tuple[int, np.ndarray] | None:
        if self._cap is None:
            if time.monotonic() < self._retry_at:
                time.sleep(1.0 / self.cfg.fps)
                return None
            try:
                self.open()
            except DeviceError:
                self._retry_at = time.monotonic() + _REOPEN_INTERVAL
                return None
        if not self._cap.grab():
            self._cap.release()
            self._cap = None
            self._retry_at = time.monotonic() + _REOPEN_INTERVAL
            return None
        stamp = self._clock() - int(self.cfg.capture_latency * 1e9)
        ok, image = self._cap.retrieve()
        if not ok or image is None:
            return None
        return stamp, image

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FrameEstimator:
    """Turns frames into samples and counts the outcomes (the camera process's state).

    Parameters
    ----------
    cfg : TactileConfig
    tool : ToolConfig
        Where the camera sits in the tool (the deformation is in the tool frame).
    rest : Tare or None
        The tared rest position; None until a tare.
    reference : (3,) array or None
        The finger's reference rest in the camera frame, m (module
        docstring); None: the next successful tare becomes it.
    """

    def __init__(self, cfg: TactileConfig, tool: ToolConfig, rest: Tare | None = None, reference: np.ndarray | None = None) -> None:
        self.cfg = cfg
        self.reference = None if reference is None else np.asarray(reference, dtype=np.float64)
        self.new_reference = False  # the last tare set the reference (the caller keeps it)
        self.detector = TagDetector.from_config(cfg)
        self.params = DeformationParams.from_config(cfg, tool)
        self.rest = rest
        self.seq = 0
        self.contact = ContactState.NONE
        self.counters = np.zeros(1, COUNTERS_DTYPE)
        self.last_corners: np.ndarray | None = None  # (4, 2) px of the last frame's tag, None without

    def process(self, stamp_ns: int, image: np.ndarray) -> tuple[TactileSample, np.ndarray]:
        """The sample of one frame, and the tag position in the camera frame (NaN when not found)."""
        t0 = time.perf_counter_ns()
        det = self.detector.detect(image)
        detect_ns = time.perf_counter_ns() - t0
        self.seq += 1
        sample = estimate(det, self.rest, self.params, stamp_ns, self.seq, self.contact, detect_ns)
        self.last_corners = det.corners_px if det.status == TactileStatus.OK else None
        if sample.valid:
            self.contact = sample.contact
        self._count(sample)
        return sample, det.p_cam if det.status == TactileStatus.OK else np.full(3, np.nan)

    def lost(self, stamp_ns: int) -> TactileSample:
        """The sample of a frame that never came."""
        self.seq += 1
        sample = invalid_sample(stamp_ns, self.seq, TactileStatus.CAMERA_LOST)
        self._count(sample)
        return sample

    def _count(self, sample: TactileSample) -> None:
        c = self.counters[0]
        c["frames"] += 1
        c["by_status"][int(sample.status)] += 1
        c["detect_ns"] = sample.detect_ns
        c["tared"] = self.rest is not None
        if self.rest is not None:
            c["p_cam_rest"] = self.rest.p_cam_rest
            c["tare_spread"] = self.rest.spread


# Frames shared for viewing (recordings, a live viewer), at most this often, s.
PREVIEW_PERIOD = 0.2


def preview_dtype(cfg: TactileConfig) -> np.dtype:
    """A frame for viewing: capture stamp, the grey image and the detected tag's corners."""
    return np.dtype(
        [
            ("stamp_ns", np.int64),
            ("has_tag", np.bool_),
            ("corners_px", np.float64, (4, 2)),
            ("image", np.uint8, (cfg.height_px, cfg.width_px)),
        ]
    )


class PreviewWriter:
    """Writes every frame at most every :data:`PREVIEW_PERIOD` to a preview slot (outside the estimate)."""

    def __init__(self, slot: SeqlockSlot, cfg: TactileConfig) -> None:
        self.slot = slot
        self.rec = np.zeros(1, preview_dtype(cfg))
        self.shape = (cfg.height_px, cfg.width_px)
        self._next_ns = 0

    def offer(self, stamp_ns: int, image: np.ndarray, corners: np.ndarray | None) -> None:
        if stamp_ns < self._next_ns:
            return
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if grey.shape != self.shape:
            return  # a frame of another size than configured is not shared (the detector counts it)
        self._next_ns = stamp_ns + int(PREVIEW_PERIOD * 1e9)
        r = self.rec
        r["stamp_ns"] = stamp_ns
        r["has_tag"] = corners is not None
        r["corners_px"] = corners if corners is not None else 0.0
        r["image"][0] = grey
        self.slot.write(r)


def run_tare(source: FrameSource, est: FrameEstimator, publish: Callable[[TactileSample], None], known_free: bool = False) -> Tare:
    """Tare: average ``tare_frames`` detections.

    Every frame read meanwhile is still published (as ``NOT_TARED`` or the
    detection's failure), so the motion process sees a live camera. With
    ``known_free`` (the daemon asked, the finger is clear of everything) the
    rest is taken and becomes the reference; otherwise it must lie within
    ``tare_max_offset`` of the reference (module docstring).

    Raises
    ------
    TactileError
        Too few detections in ``_TARE_PATIENCE`` times the frames asked for,
        or the tag moved during the tare.
    """
    cfg = est.cfg
    positions = []
    saved, est.rest = est.rest, None
    try:
        for _ in range(_TARE_PATIENCE * cfg.tare_frames):
            frame = source.read()
            if frame is None:
                publish(est.lost(time.monotonic_ns()))
                continue
            sample, p_cam = est.process(*frame)
            publish(sample)
            if np.all(np.isfinite(p_cam)):
                positions.append(p_cam)
            if len(positions) >= cfg.tare_frames:
                break
        reference = None if known_free else est.reference
        rest = tare(np.array(positions).reshape(-1, 3), cfg.tare_max_spread, cfg.tare_frames, reference, cfg.tare_max_offset)
    except TareRefused as exc:
        est.rest = saved
        est.counters[0]["tare_refused"] = True
        est.counters[0]["tare_offset"] = exc.offset
        raise
    except TactileError:
        est.rest = saved
        raise
    est.rest = rest
    est.counters[0]["tare_refused"] = False
    offset = math.nan if est.reference is None else float(np.linalg.norm(rest.p_cam_rest - est.reference))
    est.counters[0]["tare_offset"] = offset
    if known_free:
        est.reference = rest.p_cam_rest.copy()
        est.new_reference = True
    est.counters[0]["tared"] = True
    est.counters[0]["tares"] += 1
    est.counters[0]["p_cam_rest"] = rest.p_cam_rest
    est.counters[0]["tare_spread"] = rest.spread
    return rest


def run_camera(
    source: FrameSource,
    est: FrameEstimator,
    samples: SeqlockSlot,
    counters: SeqlockSlot | None,
    stop: Callable[[], bool],
    tare_requested: Callable[[], bool] = lambda: False,
    preview: PreviewWriter | None = None,
    on_reference: Callable[[Tare], None] | None = None,
) -> None:
    """The camera loop: read, estimate, publish, until ``stop()``; tares when asked (and at start without a rest).

    ``preview`` gets each frame after its sample is out, to share some for
    viewing; ``on_reference`` the tare that became the finger's reference rest.
    """

    def publish(sample: TactileSample) -> None:
        samples.write(to_record(sample, time.monotonic_ns()))
        if counters is not None:
            counters.write(est.counters)

    need_tare = est.rest is None
    known_free = False  # the pending tare is the daemon's (a failed one is retried as such)
    last_failure = ""
    while not stop():
        if tare_requested():
            known_free = True
        if need_tare or known_free:
            try:
                rest = run_tare(source, est, publish, known_free)
                log.info(
                    "srm_tared",
                    p_cam_rest_mm=np.round(rest.p_cam_rest * 1e3, 4).tolist(),
                    spread_um=round(rest.spread * 1e6, 2),
                    offset_mm=round(float(est.counters[0]["tare_offset"]) * 1e3, 4),
                    reference=est.new_reference,
                )
                if est.new_reference:
                    est.new_reference = False
                    if on_reference is not None:
                        on_reference(rest)
                need_tare = known_free = False
                last_failure = ""
            except TactileError as exc:
                # Logged once per kind of failure: a pressed finger retries every few frames.
                kind = type(exc).__name__
                if kind != last_failure:
                    log.warning("srm_tare_retrying", reason=str(exc))
                    last_failure = kind
                need_tare = True
            continue
        frame = source.read()
        if frame is None:
            publish(est.lost(time.monotonic_ns()))
            continue
        sample, _ = est.process(*frame)
        publish(sample)
        if preview is not None:
            preview.offer(frame[0], frame[1], est.last_corners)


# -- what the process builds its camera with --------------------------------------------


# Builds the camera inside the tactile process from the tactile config. It is
# pickled into the spawned process: a module-level function or an instance of
# a module-level class.
FrameSourceFactory = Callable[[TactileConfig], FrameSource]


def opencv_camera(cfg: TactileConfig) -> FrameSource:
    """The cell's camera: :class:`OpenCvCamera` (``tactile.kind = "opencv"``)."""
    return OpenCvCamera(cfg)
