"""Photoneo PhoXi scanners through GenICam (GigE Vision) with harvesters.

The scanner is opened through a GenTL producer (a ``.cti`` file: the one that
ships with PhoXi Control, or Balluff's mvGenTL producer that Photoneo's
examples use), set to software trigger with only the ``Range`` component in
``CalibratedABC_Grid`` mode: each capture is one (H, W) grid of X, Y, Z in
the camera frame, in ``Scan3dDistanceUnit`` (millimetres on PhoXi), with
(0, 0, 0) where there is no return. This driver converts both at the edge.

``harvesters`` (``pip install harvesters``, with its ``genicam`` package) is
not a dependency of celld; without it, or without a producer or a device,
opening the scanner raises :class:`~celld.errors.DriverUnavailable` that says
which is missing.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from celld.errors import DeviceError, DriverUnavailable
from celld.log import get_logger
from celld.scanner.base import CaptureStats, OrganizedCloud, check_organized

log = get_logger(__name__)

# Where GenTL consumers look for producers (GenTL standard).
GENTL_PATH_ENV = "GENICAM_GENTL64_PATH"
# Metres per Scan3dDistanceUnit value.
_DISTANCE_UNITS = {"Millimeter": 1e-3, "Meter": 1.0, "Inch": 0.0254}
# The component holding the point cloud, and the output mode that makes it X, Y, Z.
_RANGE_COMPONENT = "Range"
_OUTPUT_MODE = "CalibratedABC_Grid"


def find_producer(configured: str = "", environ: dict[str, str] | None = None) -> Path:
    """The GenTL producer to load: ``configured`` if given, else the first ``.cti`` on GENICAM_GENTL64_PATH.

    Raises
    ------
    DriverUnavailable
        The configured file does not exist, or no producer is found.
    """
    if configured:
        path = Path(configured)
        if not path.is_file():
            raise DriverUnavailable(f"Photoneo: GenTL producer {path} not found (scanner.gentl_producer)")
        return path
    env = os.environ if environ is None else environ
    dirs = [d for d in env.get(GENTL_PATH_ENV, "").split(os.pathsep) if d]
    for d in dirs:
        candidates = sorted(Path(d).glob("*.cti")) if Path(d).is_dir() else []
        if candidates:
            return candidates[0]
    where = f"{GENTL_PATH_ENV}={':'.join(dirs)}" if dirs else f"{GENTL_PATH_ENV} is not set"
    raise DriverUnavailable(
        f"Photoneo: no GenTL producer (.cti) found ({where}); install PhoXi Control or the mvGenTL producer, or set scanner.gentl_producer"
    )


def _import_harvester() -> Callable[[], Any]:
    try:
        from harvesters.core import Harvester
    except ImportError as exc:
        raise DriverUnavailable(
            f"Photoneo: the Python package 'harvesters' is not installed ({exc}); install it with "
            "'pip install harvesters' into celld's environment"
        ) from exc
    return Harvester


def _set(node_map: Any, name: str, value: Any) -> None:
    try:
        getattr(node_map, name).value = value
    except Exception as exc:  # genicam raises its own types; translated here
        raise DeviceError(f"Photoneo: cannot set {name} = {value!r}: {exc}") from exc


class PhotoneoScanner:
    """A Photoneo PhoXi (or MotionCam-3D) scanner on GigE Vision.

    Parameters
    ----------
    device : str
        Serial number of the scanner (``"DVJ-104"``); ``""`` for the only one found.
    producer : str
        Path of the GenTL producer; ``""`` searches ``GENICAM_GENTL64_PATH``.
    timeout : float
        Longest wait for one frame, seconds.
    harvester : callable, optional
        Factory of a ``harvesters.core.Harvester``; the real one by default
        (tests pass a fake).
    clock : callable
        Source of capture stamps, ``time.monotonic_ns`` by default.

    Raises
    ------
    DriverUnavailable
        harvesters, the producer or the device is missing.
    DeviceError
        The device refused its configuration.
    """

    def __init__(
        self,
        device: str = "",
        producer: str = "",
        timeout: float = 10.0,
        *,
        harvester: Callable[[], Any] | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        factory = _import_harvester() if harvester is None else harvester
        self.producer = find_producer(producer)
        self.device = device
        self.timeout = float(timeout)
        self._clock = clock
        self._lock = threading.Lock()
        self._stats = CaptureStats()
        self.serial = device
        self.model = "PhoXi"
        self.distance_unit: str | None = None
        self._metres_per_unit = 1e-3
        self._h = factory()
        self._ia: Any = None
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        try:
            self._h.add_file(str(self.producer), check_existence=True, check_validity=True)
            self._h.update()
        except Exception as exc:
            raise DriverUnavailable(f"Photoneo: the GenTL producer {self.producer} cannot be loaded: {exc}") from exc
        found = [getattr(i, "serial_number", "?") for i in self._h.device_info_list]
        if not found:
            raise DriverUnavailable(f"Photoneo: no GenICam device found through {self.producer.name}")
        if self.device and self.device not in found:
            raise DriverUnavailable(f"Photoneo: scanner {self.device!r} not found; found {', '.join(map(str, found))}")
        try:
            self._ia = self._h.create({"serial_number": self.device} if self.device else None)
        except Exception as exc:
            raise DriverUnavailable(f"Photoneo: cannot open scanner {self.device or found[0]!r}: {exc}") from exc
        nm = self._ia.remote_device.node_map
        self.serial = str(getattr(getattr(nm, "DeviceSerialNumber", None), "value", self.device or found[0]))
        self.model = str(getattr(getattr(nm, "DeviceModelName", None), "value", "PhoXi"))
        _set(nm, "TriggerSelector", "FrameStart")
        _set(nm, "TriggerMode", "On")
        _set(nm, "TriggerSource", "Software")
        try:
            components = list(nm.ComponentSelector.symbolics)
        except Exception as exc:  # not a multipart 3D device
            raise DeviceError(f"Photoneo: the device has no ComponentSelector ({exc}); is it a PhoXi?") from exc
        for component in components:
            _set(nm, "ComponentSelector", component)
            _set(nm, "ComponentEnable", component == _RANGE_COMPONENT)
        _set(nm, "ComponentSelector", _RANGE_COMPONENT)
        _set(nm, "Scan3dOutputMode", _OUTPUT_MODE)
        # PhoXi firmware reports millimetres; a node map without the feature is taken to mean the same.
        unit = str(nm.Scan3dDistanceUnit.value) if hasattr(nm, "Scan3dDistanceUnit") else "Millimeter"
        if unit not in _DISTANCE_UNITS:
            raise DeviceError(f"Photoneo: Scan3dDistanceUnit {unit!r} not understood (expected {', '.join(_DISTANCE_UNITS)})")
        self.distance_unit = unit
        self._metres_per_unit = _DISTANCE_UNITS[unit]
        try:
            self._ia.start()
        except Exception as exc:
            raise DeviceError(f"Photoneo {self.serial}: acquisition does not start: {exc}") from exc
        log.info("photoneo_open", serial=self.serial, model=self.model, producer=str(self.producer), unit=unit)

    def capture(self) -> OrganizedCloud:
        """Trigger one scan and return its cloud in metres."""
        with self._lock:
            if self._ia is None:
                raise DeviceError("Photoneo: capture after close")
            started = time.monotonic_ns()
            try:
                nm = self._ia.remote_device.node_map
                stamp = int(self._clock())
                try:
                    nm.TriggerSoftware.execute()
                    with self._ia.fetch(timeout=self.timeout) as buffer:
                        component = buffer.payload.components[0]
                        h, w = int(component.height), int(component.width)
                        raw = np.array(component.data, dtype=np.float32, copy=True)
                except Exception as exc:
                    raise DeviceError(f"Photoneo {self.serial}: no frame within {self.timeout} s: {exc}") from exc
                if raw.size != h * w * 3:
                    raise DeviceError(f"Photoneo {self.serial}: Range component of {raw.size} values for a {w} x {h} grid")
                points = check_organized(raw.reshape(h, w, 3), f"Photoneo {self.serial}", self._metres_per_unit)
            except DeviceError as exc:
                self._stats.failure(exc)
                raise
            self._stats.success(stamp, started)
            return OrganizedCloud(points=points, stamp_ns=stamp)

    def info(self) -> dict[str, Any]:
        nm = self._ia.remote_device.node_map if self._ia is not None else None
        size = (getattr(getattr(nm, "Width", None), "value", None), getattr(getattr(nm, "Height", None), "value", None))
        return {
            "kind": "phoxi",
            "model": self.model,
            "device": self.serial,
            "width_px": size[0],
            "height_px": size[1],
            "producer": str(self.producer),
            "distance_unit": self.distance_unit,
        }

    def health(self) -> dict[str, Any]:
        return self._stats.as_dict(self._ia is not None)

    def close(self) -> None:
        """Stop acquisition and release the device and the producer; safe to call twice."""
        ia, self._ia = self._ia, None
        harvester, self._h = self._h, None
        steps = [("stop", ia.stop), ("destroy", ia.destroy)] if ia is not None else []
        if harvester is not None:
            steps.append(("reset", harvester.reset))
        for name, step in steps:
            try:
                step()
            except Exception as exc:  # closing must not raise; the device may already be gone  # noqa: BLE001
                log.warning("photoneo_close_failed", step=name, error=str(exc))
