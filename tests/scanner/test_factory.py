"""open_scanner: the driver a config names, and the scanner options of the config file."""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from celld.config import ScannerConfig, parse
from celld.errors import ConfigError, DriverUnavailable
from celld.scanner import Scanner, open_scanner
from celld.scanner.open3d_sensors import k4a_available
from celld.scanner.replay import ReplayScanner, write_cloud_file


def test_scanner_options_are_read_with_units_converted() -> None:
    cfg = parse(
        {
            "scanner": {
                "kind": "azure-kinect",
                "model": "azure-kinect",
                "depth_intrinsics_px": [504.0, 504.5, 319.5, 287.5],
                "depth_min_mm": 250,
                "depth_max_mm": 3860,
                "capture_timeout_s": 2.5,
                "replay_units": "mm",
            }
        }
    ).scanner
    assert cfg.depth_intrinsics_px == (504.0, 504.5, 319.5, 287.5)
    assert (cfg.depth_min, cfg.depth_max) == pytest.approx((0.25, 3.86))
    assert (cfg.capture_timeout, cfg.replay_units) == (2.5, "mm")


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"depth_min_mm": 500, "depth_max_mm": 400}, "scanner.depth_max_mm"),
        ({"depth_intrinsics_px": [0.0, 500.0, 1.0, 1.0]}, "scanner.depth_intrinsics_px"),
        ({"depth_intrinsics_px": [500.0, 500.0]}, "scanner.depth_intrinsics_px"),
        ({"replay_units": "inch"}, "scanner.replay_units"),
        # The simulated scanner's image scale and noise belong to the simulator's world now.
        ({"resolution_scale": 0.25}, "scanner.resolution_scale"),
        ({"seed": 1}, "scanner.seed"),
    ],
)
def test_bad_scanner_options_are_refused_with_their_key(table: dict, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse({"scanner": table})
    assert info.value.key == key


def test_replay_needs_its_directory_and_opens_it(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="replay_dir"):
        open_scanner(ScannerConfig(kind="replay"))
    write_cloud_file(tmp_path / "0000.npy", np.ones((2, 3, 3), np.float32), "mm")
    scanner = open_scanner(ScannerConfig(kind="replay", replay_dir=str(tmp_path), replay_units="mm", replay_loop=True))
    assert isinstance(scanner, ReplayScanner) and isinstance(scanner, Scanner)
    np.testing.assert_allclose(scanner.capture().points, 1.0)
    np.testing.assert_allclose(scanner.capture().points, 1.0)  # loops


def test_azure_kinect_config_errors_come_before_the_sdk_is_touched() -> None:
    base = ScannerConfig(kind="azure-kinect", model="azure-kinect")
    with pytest.raises(ConfigError, match="depth_intrinsics_px"):
        open_scanner(base)
    with pytest.raises(ConfigError, match="device index"):
        open_scanner(replace(base, depth_intrinsics_px=(504.0, 504.0, 319.5, 287.5), device="front"))


@pytest.mark.skipif(importlib.util.find_spec("harvesters") is not None, reason="harvesters is installed here")
def test_phoxi_without_its_sdk_is_driver_unavailable() -> None:
    with pytest.raises(DriverUnavailable, match="harvesters"):
        open_scanner(ScannerConfig(kind="phoxi"))


@pytest.mark.skipif(k4a_available()[0], reason="the Azure Kinect SDK is installed here")
def test_azure_kinect_without_its_sdk_is_driver_unavailable() -> None:
    # Safe in-process: the driver probes libk4a before Open3D makes a sensor object.
    with pytest.raises(DriverUnavailable, match="libk4a"):
        open_scanner(ScannerConfig(kind="azure-kinect", depth_intrinsics_px=(504.0, 504.0, 319.5, 287.5)))


def test_the_simulated_scanner_is_not_opened_from_a_config() -> None:
    # Only the simulated cell builds its scanner (celld sim run); a production
    # daemon given kind = "sim" says so instead of simulating a device.
    with pytest.raises(ConfigError, match=r"scanner\.kind.*celld sim run"):
        open_scanner(ScannerConfig(kind="sim"))
