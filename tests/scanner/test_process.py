"""A scanner in a process of its own gives the clouds it would give in the daemon's, and its errors as such."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from celld.calib.flange import preset
from celld.errors import DeviceError, InputError
from celld.scanner.process import ScannerProcess
from celld.se3 import transform_from
from celld.sim.scanner import SimulatedScanner
from celld.sim.scene import robot_scene

pytestmark = pytest.mark.process

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])


def _scene() -> list:  # type: ignore[type-arg]
    return list(robot_scene(transform_from(np.eye(3), [0.6, 0.0, 0.45]), preset("ur10e")))


def small_scanner(seed: int = 3) -> SimulatedScanner:
    return SimulatedScanner("phoxi-m", T_BASE_CAM, _scene, seed=seed, resolution_scale=0.1)


def refused() -> SimulatedScanner:
    raise DeviceError("no such scanner: serial 1234 not found")


class _Broken:
    """A scanner whose capture raises InputError."""

    def capture(self):  # type: ignore[no-untyped-def]
        raise InputError("replay: frame 3 is malformed")

    def info(self) -> dict:  # type: ignore[type-arg]
        return {"kind": "broken", "model": "x", "device": "x", "width_px": 4, "height_px": 2}

    def health(self) -> dict:  # type: ignore[type-arg]
        return {"ok": False}

    def close(self) -> None:
        pass


def broken() -> _Broken:
    return _Broken()


def test_the_process_gives_the_clouds_the_scanner_gives_in_process() -> None:
    here = small_scanner()
    there = ScannerProcess(partial(small_scanner, 3), name="test-scanner")
    try:
        for _ in range(2):
            a, b = here.capture(), there.capture()
            assert a.points.shape == b.points.shape and a.points.dtype == b.points.dtype == np.float32
            np.testing.assert_array_equal(a.points, b.points)  # NaN where no return, in the same pixels
        assert there.info() == here.info() and there.health()["captures"] == 2
    finally:
        there.close()
    with pytest.raises(DeviceError, match="after close"):
        there.capture()
    there.close()  # twice is fine


def test_its_errors_come_back_as_themselves_and_a_dead_child_is_a_device_error() -> None:
    with pytest.raises(DeviceError, match="serial 1234 not found"):
        ScannerProcess(refused, name="test-refused")
    scanner = ScannerProcess(broken, name="test-broken")
    try:
        with pytest.raises(InputError, match="frame 3 is malformed"):
            scanner.capture()
        scanner._proc.kill()
        scanner._proc.join(5)
        with pytest.raises(DeviceError, match="scanner process: it ended"):
            scanner.capture()
    finally:
        scanner.close()
