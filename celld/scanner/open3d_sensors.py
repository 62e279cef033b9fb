"""Azure Kinect and RealSense depth cameras through Open3D's sensor classes.

- :class:`AzureKinectScanner` uses ``open3d.io.AzureKinectSensor``, which loads
  the Azure Kinect SDK (``libk4a.so``) at run time. Open3D cannot be asked
  whether the library is there: a sensor object created without it aborts
  the whole process when it is destroyed (measured with Open3D 0.20: "Cannot
  load libk4a.so", then ``std::terminate``). So the library is probed with
  ``ctypes`` first, and no sensor object exists unless it loads. Open3D's
  legacy sensor does not report intrinsics: they come from the config
  (``scanner.depth_intrinsics_px``, the depth camera's factory calibration,
  e.g. from ``k4arecorder``/the SDK's calibration API).
- :class:`RealSenseScanner` uses ``open3d.t.io.RealSenseSensor`` (librealsense
  is built into Open3D's wheels). Devices are enumerated first; depth is
  aligned to the colour camera, whose intrinsics the sensor reports, so the
  cloud is in the colour camera's optical frame.

Both unproject depth with :func:`celld.scanner.depth.depth_to_points`.
"""

from __future__ import annotations

import ctypes
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import open3d as o3d

from celld.errors import DeviceError, DriverUnavailable, InputError
from celld.log import get_logger
from celld.scanner.base import CaptureStats, OrganizedCloud
from celld.scanner.depth import depth_to_points, intrinsic_matrix

log = get_logger(__name__)

# The Azure Kinect SDK library Open3D loads (same name, same dlopen search).
K4A_LIBRARY = "libk4a.so"
# Azure Kinect depth is in millimetres.
_K4A_UNITS_PER_METRE = 1000.0
# Pause between polls of a sensor that has no frame yet, s.
_POLL = 0.005


def k4a_available(library: str = K4A_LIBRARY) -> tuple[bool, str]:
    """Whether the Azure Kinect SDK library loads in this process, and the loader's message if not."""
    try:
        ctypes.CDLL(library)
    except OSError as exc:
        return False, str(exc)
    return True, ""


class AzureKinectScanner:
    """A Microsoft Azure Kinect DK as a scanner (depth camera frame, NFOV unbinned by default).

    Parameters
    ----------
    device_index : int
        Index of the device (0 for the first).
    intrinsics_px : tuple of float
        fx, fy, cx, cy of the depth camera in the configured depth mode, pixels.
    depth_min, depth_max : float
        Kept depth range, metres.
    timeout : float
        Longest wait for one frame, seconds.
    sensor_config : dict, optional
        Open3D ``AzureKinectSensorConfig`` entries (``depth_mode``, ``camera_fps``, ...).
    sensor : callable, optional
        Factory ``(config) -> sensor`` replacing ``open3d.io.AzureKinectSensor`` (tests).

    Raises
    ------
    DriverUnavailable
        The SDK library is missing or no device answers at ``device_index``.
    InputError
        The intrinsics are not four positive-focal values.
    """

    def __init__(
        self,
        device_index: int = 0,
        intrinsics_px: tuple[float, ...] = (),
        depth_min: float = 0.1,
        depth_max: float = 6.0,
        timeout: float = 10.0,
        *,
        sensor_config: dict[str, str] | None = None,
        sensor: Callable[[Any], Any] | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if len(intrinsics_px) != 4:
            raise InputError(
                "Azure Kinect: the depth camera intrinsics fx, fy, cx, cy are needed (scanner.depth_intrinsics_px); "
                f"got {tuple(intrinsics_px)}"
            )
        self.K = intrinsic_matrix(*intrinsics_px)
        self.device_index = int(device_index)
        self.depth_min, self.depth_max, self.timeout = float(depth_min), float(depth_max), float(timeout)
        self._clock = clock
        self._lock = threading.Lock()
        self._stats = CaptureStats()
        self._sensor: Any = None
        self._size: tuple[int, int] | None = None  # (W, H) of the last frame
        if sensor is None:
            ok, why = k4a_available()
            if not ok:
                raise DriverUnavailable(
                    f"Azure Kinect: the Azure Kinect SDK is not installed ({why}); install libk4a "
                    "(Microsoft's Azure Kinect Sensor SDK 1.4) so that Open3D can load it"
                )
            sensor = o3d.io.AzureKinectSensor
        cfg = o3d.io.AzureKinectSensorConfig(sensor_config) if sensor_config else o3d.io.AzureKinectSensorConfig()
        dev = sensor(cfg)
        try:
            connected = dev.connect(self.device_index)
        except RuntimeError as exc:
            raise DriverUnavailable(f"Azure Kinect: device {self.device_index} cannot be opened: {exc}") from exc
        if not connected:
            raise DriverUnavailable(f"Azure Kinect: no device answers at index {self.device_index}")
        self._sensor = dev
        log.info("azure_kinect_open", device=self.device_index)

    def capture(self) -> OrganizedCloud:
        """Wait for the next depth frame and unproject it."""
        with self._lock:
            if self._sensor is None:
                raise DeviceError("Azure Kinect: capture after close")
            started = time.monotonic_ns()
            deadline = time.monotonic() + self.timeout
            try:
                frame = None
                while frame is None:
                    frame = self._sensor.capture_frame(False)  # depth stays in the depth camera's geometry
                    if frame is None:
                        if time.monotonic() > deadline:
                            raise DeviceError(f"Azure Kinect {self.device_index}: no frame within {self.timeout} s")
                        time.sleep(_POLL)
                stamp = int(self._clock())
                depth = np.asarray(frame.depth)
                if depth.ndim == 3:
                    depth = depth[:, :, 0]
                points = depth_to_points(depth, self.K, _K4A_UNITS_PER_METRE, self.depth_min, self.depth_max)
                self._size = (depth.shape[1], depth.shape[0])
            except (DeviceError, InputError) as exc:
                self._stats.failure(exc)
                raise
            self._stats.success(stamp, started)
            return OrganizedCloud(points=points, stamp_ns=stamp)

    def info(self) -> dict[str, Any]:
        return {
            "kind": "azure-kinect",
            "model": "azure-kinect",
            "device": str(self.device_index),
            # Open3D does not report the depth mode's size: known after the first capture.
            "width_px": self._size[0] if self._size else None,
            "height_px": self._size[1] if self._size else None,
            "intrinsics_px": (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]),
            "depth_range": (self.depth_min, self.depth_max),
        }

    def health(self) -> dict[str, Any]:
        return self._stats.as_dict(self._sensor is not None)

    def close(self) -> None:
        sensor, self._sensor = self._sensor, None
        if sensor is not None:
            try:
                sensor.disconnect()
            except RuntimeError as exc:
                log.warning("azure_kinect_close_failed", error=str(exc))


class RealSenseScanner:
    """An Intel RealSense depth camera as a scanner (colour camera frame, depth aligned to it).

    Parameters
    ----------
    serial : str
        Serial number of the camera; ``""`` for the first found.
    depth_min, depth_max : float
        Kept depth range, metres.
    sensor_config : dict, optional
        Open3D ``RealSenseSensorConfig`` entries (``depth_resolution``, ``depth_fps``, ...).
    sensor_api : object, optional
        Replacement of ``open3d.t.io`` providing ``RealSenseSensor`` and
        ``RealSenseSensorConfig`` (tests).

    Raises
    ------
    DriverUnavailable
        Open3D has no RealSense support, no camera is connected, or the camera
        refuses the configuration.
    """

    def __init__(
        self,
        serial: str = "",
        depth_min: float = 0.1,
        depth_max: float = 6.0,
        *,
        sensor_config: dict[str, str] | None = None,
        sensor_api: Any = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        api = o3d.t.io if sensor_api is None else sensor_api
        if not hasattr(api, "RealSenseSensor"):
            raise DriverUnavailable("RealSense: this Open3D build has no RealSense support (open3d.t.io.RealSenseSensor)")
        self.depth_min, self.depth_max = float(depth_min), float(depth_max)
        self._clock = clock
        self._lock = threading.Lock()
        self._stats = CaptureStats()
        self._sensor: Any = None
        devices = list(api.RealSenseSensor.enumerate_devices())
        serials = [str(getattr(d, "serial", "")) for d in devices]
        if not devices:
            raise DriverUnavailable("RealSense: no RealSense camera is connected")
        if serial and serial not in serials:
            raise DriverUnavailable(f"RealSense: camera {serial!r} not found; connected: {', '.join(serials)}")
        self.serial = serial or serials[0]
        config = dict(sensor_config or {})
        config.setdefault("serial", self.serial)
        sensor = api.RealSenseSensor()
        try:
            sensor.init_sensor(api.RealSenseSensorConfig(config), 0, "")
            sensor.start_capture(False)
        except RuntimeError as exc:
            raise DriverUnavailable(f"RealSense {self.serial}: cannot start: {exc}") from exc
        metadata = sensor.get_metadata()
        self.K = np.asarray(metadata.intrinsics.intrinsic_matrix, dtype=np.float64)
        self.units_per_metre = float(metadata.depth_scale)
        self.size = (int(metadata.width), int(metadata.height))
        self._sensor = sensor
        log.info("realsense_open", serial=self.serial, width=self.size[0], height=self.size[1])

    def capture(self) -> OrganizedCloud:
        """Wait for the next frame set and unproject its aligned depth."""
        with self._lock:
            if self._sensor is None:
                raise DeviceError("RealSense: capture after close")
            started = time.monotonic_ns()
            try:
                try:
                    frame = self._sensor.capture_frame(True, True)  # wait, align depth to colour
                except RuntimeError as exc:
                    raise DeviceError(f"RealSense {self.serial}: capture failed: {exc}") from exc
                stamp = int(self._clock())
                depth = frame.depth.as_tensor().numpy()
                if depth.ndim == 3:
                    depth = depth[:, :, 0]
                points = depth_to_points(depth, self.K, self.units_per_metre, self.depth_min, self.depth_max)
            except (DeviceError, InputError) as exc:
                self._stats.failure(exc)
                raise
            self._stats.success(stamp, started)
            return OrganizedCloud(points=points, stamp_ns=stamp)

    def info(self) -> dict[str, Any]:
        return {
            "kind": "realsense",
            "model": "realsense",
            "device": self.serial,
            "width_px": self.size[0],
            "height_px": self.size[1],
            "intrinsics_px": (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]),
            "depth_range": (self.depth_min, self.depth_max),
        }

    def health(self) -> dict[str, Any]:
        return self._stats.as_dict(self._sensor is not None)

    def close(self) -> None:
        sensor, self._sensor = self._sensor, None
        if sensor is not None:
            try:
                sensor.stop_capture()
            except RuntimeError as exc:
                log.warning("realsense_close_failed", error=str(exc))
