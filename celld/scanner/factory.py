"""Open the scanner a :class:`~celld.config.ScannerConfig` names.

``kind`` chooses the driver: ``replay``, ``phoxi``, ``azure-kinect`` or
``realsense``. Real drivers import their SDK only here, when chosen, so a
cell without one of them never loads it. ``sim`` is the simulated cell's
scanner: the simulator builds it and hands it to the daemon (``celld sim
run``); it is never opened from a config here.
"""

from __future__ import annotations

from celld.config import ScannerConfig
from celld.errors import ConfigError
from celld.scanner.base import Scanner

# The source named in ConfigErrors raised here (the config file is validated already).
_SOURCE = "scanner config"


def open_scanner(config: ScannerConfig) -> Scanner:
    """Open the scanner of ``config``, ready to capture.

    Parameters
    ----------
    config : ScannerConfig
        The validated scanner section.

    Raises
    ------
    ConfigError
        A value the chosen driver needs is missing (``replay_dir``,
        ``depth_intrinsics_px``, a numeric Azure Kinect ``device``), or
        ``kind = "sim"`` (only the simulated cell opens that one).
    DriverUnavailable
        A real driver's SDK, producer or device is absent.
    DeviceError
        The device refused to open.
    """
    kind = config.kind
    if kind == "sim":
        raise ConfigError(
            _SOURCE,
            "scanner.kind",
            "'sim' is the simulated cell's scanner: run this config with `celld sim run`, or name a real driver",
        )
    if kind == "replay":
        from celld.scanner.replay import ReplayScanner

        if not config.replay_dir:
            raise ConfigError(_SOURCE, "scanner.replay_dir", "kind = 'replay' needs the directory of the clouds")
        return ReplayScanner(config.replay_dir, units=config.replay_units, loop=config.replay_loop)
    if kind == "phoxi":
        from celld.scanner.photoneo import PhotoneoScanner

        return PhotoneoScanner(config.device, config.gentl_producer, config.capture_timeout)
    if kind == "azure-kinect":
        from celld.scanner.open3d_sensors import AzureKinectScanner

        if not config.depth_intrinsics_px:
            raise ConfigError(_SOURCE, "scanner.depth_intrinsics_px", "kind = 'azure-kinect' needs the depth camera's fx, fy, cx, cy")
        if config.device and not config.device.isdigit():
            raise ConfigError(_SOURCE, "scanner.device", f"expected the device index (0, 1, ...), got {config.device!r}")
        return AzureKinectScanner(
            int(config.device or 0),
            config.depth_intrinsics_px,
            config.depth_min,
            config.depth_max,
            config.capture_timeout,
        )
    if kind == "realsense":
        from celld.scanner.open3d_sensors import RealSenseScanner

        return RealSenseScanner(config.device, config.depth_min, config.depth_max)
    raise ConfigError(_SOURCE, "scanner.kind", f"no driver for {kind!r}")
