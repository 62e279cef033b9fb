"""Real scanner drivers: a clean DriverUnavailable without their SDK or device, and their
conversion code run against fakes of the SDK objects."""

from __future__ import annotations

import contextlib
import importlib.util
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import open3d as o3d
import pytest

from celld.errors import DeviceError, DriverUnavailable, InputError
from celld.scanner import Scanner
from celld.scanner.open3d_sensors import AzureKinectScanner, RealSenseScanner, k4a_available
from celld.scanner.photoneo import PhotoneoScanner, find_producer

HAVE_HARVESTERS = importlib.util.find_spec("harvesters") is not None
HAVE_K4A = k4a_available()[0]
REALSENSE_DEVICES = o3d.t.io.RealSenseSensor.enumerate_devices() if hasattr(o3d.t.io, "RealSenseSensor") else []
INTRINSICS = (504.0, 504.0, 319.5, 287.5)


# -- Photoneo -----------------------------------------------------------------


@pytest.mark.skipif(HAVE_HARVESTERS, reason="harvesters is installed here")
def test_photoneo_without_harvesters_names_the_package() -> None:
    with pytest.raises(DriverUnavailable, match="'harvesters' is not installed"):
        PhotoneoScanner()


def test_the_gentl_producer_comes_from_the_config_or_the_gentl_path(tmp_path: Path) -> None:
    with pytest.raises(DriverUnavailable, match=r"producer .*missing.cti not found"):
        find_producer(str(tmp_path / "missing.cti"))
    with pytest.raises(DriverUnavailable, match="GENICAM_GENTL64_PATH is not set"):
        find_producer("", environ={})
    empty, full = tmp_path / "empty", tmp_path / "full"
    empty.mkdir()
    full.mkdir()
    (full / "photoneo.cti").write_bytes(b"")
    with pytest.raises(DriverUnavailable, match="no GenTL producer"):
        find_producer("", environ={"GENICAM_GENTL64_PATH": str(empty)})
    assert find_producer("", environ={"GENICAM_GENTL64_PATH": f"{empty}:{full}"}) == full / "photoneo.cti"


class _Node:
    def __init__(self, value: Any = None, symbolics: tuple[str, ...] = ()) -> None:
        self.value = value
        self.symbolics = symbolics
        self.executed = 0

    def execute(self) -> None:
        self.executed += 1


class _PerComponent:
    """A GenICam feature selected by ComponentSelector: one value per component."""

    def __init__(self, selector: _Node, values: dict[str, Any]) -> None:
        self._selector = selector
        self.values = values

    @property
    def value(self) -> Any:
        return self.values[self._selector.value]

    @value.setter
    def value(self, v: Any) -> None:
        self.values[self._selector.value] = v


class _FakeAcquirer:
    """The parts of harvesters' ImageAcquirer the driver uses, serving one Range grid in mm."""

    def __init__(self, grid_mm: np.ndarray, fail_fetch: bool = False) -> None:
        self.grid_mm = grid_mm
        self.fail_fetch = fail_fetch
        names = ("Intensity", "Range", "Normal", "Confidence")
        selector = _Node("Intensity", names)
        self.node_map = SimpleNamespace(
            DeviceSerialNumber=_Node("DVJ-104"),
            DeviceModelName=_Node("PhoXi3DScanner-M"),
            Width=_Node(grid_mm.shape[1]),
            Height=_Node(grid_mm.shape[0]),
            TriggerSelector=_Node("FrameStart"),
            TriggerMode=_Node("Off"),
            TriggerSource=_Node("Line1"),
            ComponentSelector=selector,
            ComponentEnable=_PerComponent(selector, {n: True for n in names}),
            Scan3dOutputMode=_Node("ProjectedC"),
            Scan3dDistanceUnit=_Node("Millimeter"),
            TriggerSoftware=_Node(),
        )
        self.remote_device = SimpleNamespace(node_map=self.node_map)
        self.started = self.stopped = self.destroyed = False

    def start(self) -> None:
        self.started = True

    @contextlib.contextmanager
    def fetch(self, timeout: float) -> Iterator[Any]:
        if self.fail_fetch:
            raise RuntimeError("GenTL timeout")
        h, w, _ = self.grid_mm.shape
        component = SimpleNamespace(data=self.grid_mm.reshape(-1).copy(), width=w, height=h)
        yield SimpleNamespace(payload=SimpleNamespace(components=[component]))

    def stop(self) -> None:
        self.stopped = True

    def destroy(self) -> None:
        self.destroyed = True


class _FakeHarvester:
    def __init__(self, acquirer: _FakeAcquirer, serials: tuple[str, ...] = ("DVJ-104",)) -> None:
        self.acquirer = acquirer
        self.device_info_list: list[Any] = []
        self._serials = serials
        self.files: list[str] = []
        self.was_reset = False

    def add_file(self, path: str, check_existence: bool = False, check_validity: bool = False) -> None:
        self.files.append(path)

    def update(self) -> None:
        self.device_info_list = [SimpleNamespace(serial_number=s) for s in self._serials]

    def create(self, search_key: Any = None) -> _FakeAcquirer:
        return self.acquirer

    def reset(self) -> None:
        self.was_reset = True


@pytest.fixture
def producer(tmp_path: Path) -> Path:
    cti = tmp_path / "photoneo.cti"
    cti.write_bytes(b"")
    return cti


def test_photoneo_captures_metres_with_nan_for_no_return_through_a_fake_harvester(producer: Path) -> None:
    grid = np.zeros((3, 4, 3), dtype=np.float32)
    grid[1, 2] = [12.0, -30.0, 650.0]  # mm
    grid[2, 3] = [0.0, 0.0, 700.0]
    acquirer = _FakeAcquirer(grid)
    harvester = _FakeHarvester(acquirer)
    scanner = PhotoneoScanner("DVJ-104", str(producer), timeout=1.0, harvester=lambda: harvester, clock=lambda: 42)
    assert isinstance(scanner, Scanner)
    nm = acquirer.node_map
    assert (nm.TriggerMode.value, nm.TriggerSource.value, nm.Scan3dOutputMode.value) == ("On", "Software", "CalibratedABC_Grid")
    assert nm.ComponentEnable.values == {"Intensity": False, "Range": True, "Normal": False, "Confidence": False}
    assert harvester.files == [str(producer)] and acquirer.started
    cloud = scanner.capture()
    assert nm.TriggerSoftware.executed == 1 and cloud.stamp_ns == 42
    np.testing.assert_allclose(cloud.points[1, 2], [0.012, -0.030, 0.650], rtol=1e-6)
    np.testing.assert_allclose(cloud.points[2, 3], [0.0, 0.0, 0.700], rtol=1e-6)
    assert cloud.valid_count() == 2
    assert scanner.info()["device"] == "DVJ-104" and scanner.info()["width_px"] == 4
    scanner.close()
    assert acquirer.stopped and acquirer.destroyed and harvester.was_reset
    scanner.close()  # twice is fine
    with pytest.raises(DeviceError, match="after close"):
        scanner.capture()


def test_photoneo_errors_are_translated(producer: Path) -> None:
    grid = np.ones((2, 2, 3), dtype=np.float32)
    with pytest.raises(DriverUnavailable, match="scanner 'XYZ-1' not found; found DVJ-104"):
        PhotoneoScanner("XYZ-1", str(producer), harvester=lambda: _FakeHarvester(_FakeAcquirer(grid)))
    with pytest.raises(DriverUnavailable, match="no GenICam device"):
        PhotoneoScanner("", str(producer), harvester=lambda: _FakeHarvester(_FakeAcquirer(grid), serials=()))
    scanner = PhotoneoScanner("", str(producer), timeout=0.5, harvester=lambda: _FakeHarvester(_FakeAcquirer(grid, fail_fetch=True)))
    with pytest.raises(DeviceError, match="no frame within 0.5 s: GenTL timeout"):
        scanner.capture()
    assert scanner.health()["failures"] == 1 and "GenTL timeout" in scanner.health()["last_error"]


# -- Azure Kinect -------------------------------------------------------------


@pytest.mark.process
@pytest.mark.skipif(HAVE_K4A, reason="the Azure Kinect SDK is installed here")
def test_azure_kinect_without_its_sdk_is_a_clean_driver_unavailable_not_an_abort() -> None:
    """In a child process: an Open3D sensor object made without libk4a aborts the process when it
    is destroyed, which would take pytest down. The driver must never make one."""
    code = (
        "from celld.scanner.open3d_sensors import AzureKinectScanner\n"
        "from celld.errors import DriverUnavailable\n"
        "try:\n"
        f"    AzureKinectScanner(0, {INTRINSICS!r})\n"
        "except DriverUnavailable as exc:\n"
        "    print('DriverUnavailable:', exc)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "DriverUnavailable: Azure Kinect: the Azure Kinect SDK is not installed (libk4a.so" in done.stdout


def test_azure_kinect_needs_its_depth_intrinsics() -> None:
    with pytest.raises(InputError, match="depth_intrinsics_px"):
        AzureKinectScanner(0, ())


class _FakeK4a:
    """open3d.io.AzureKinectSensor's interface: connect, capture_frame (None until a frame), disconnect."""

    def __init__(self, config: Any, frames: list[Any], connects: bool = True) -> None:
        self.frames = frames
        self.connects = connects
        self.disconnected = False

    def connect(self, index: int) -> bool:
        return self.connects

    def capture_frame(self, align: bool) -> Any:
        return self.frames.pop(0) if self.frames else None

    def disconnect(self) -> None:
        self.disconnected = True


def test_azure_kinect_unprojects_its_depth_in_millimetres() -> None:
    depth = np.full((576, 640), 1000, dtype=np.uint16)
    depth[0, 0] = 0
    frame = SimpleNamespace(depth=o3d.geometry.Image(depth))
    fake = _FakeK4a(None, [None, frame])
    scanner = AzureKinectScanner(0, INTRINSICS, 0.25, 3.0, sensor=lambda cfg: fake, clock=lambda: 5)
    cloud = scanner.capture()
    assert cloud.points.shape == (576, 640, 3) and cloud.stamp_ns == 5
    np.testing.assert_allclose(cloud.points[287, 319], [-0.5 / 504.0, -0.5 / 504.0, 1.0], atol=1e-6)
    assert np.isnan(cloud.points[0, 0]).all() and cloud.valid_count() == 576 * 640 - 1
    assert scanner.info()["width_px"] == 640
    scanner.close()
    assert fake.disconnected


def test_azure_kinect_errors_no_device_and_no_frame() -> None:
    with pytest.raises(DriverUnavailable, match="no device answers at index 1"):
        AzureKinectScanner(1, INTRINSICS, sensor=lambda cfg: _FakeK4a(cfg, [], connects=False))
    scanner = AzureKinectScanner(0, INTRINSICS, timeout=0.05, sensor=lambda cfg: _FakeK4a(cfg, []))
    with pytest.raises(DeviceError, match="no frame within 0.05 s"):
        scanner.capture()


# -- RealSense ----------------------------------------------------------------


@pytest.mark.skipif(bool(REALSENSE_DEVICES), reason="a RealSense camera is connected")
def test_realsense_without_a_camera_is_a_clean_driver_unavailable() -> None:
    with pytest.raises(DriverUnavailable, match="no RealSense camera is connected"):
        RealSenseScanner()


class _FakeRealSenseApi:
    """The parts of open3d.t.io the RealSense driver uses."""

    def __init__(self, serials: tuple[str, ...], depth_mm: np.ndarray) -> None:
        api = self
        self.started = self.stopped = False
        self.config: dict[str, str] = {}

        class RealSenseSensor:
            @staticmethod
            def enumerate_devices() -> list[Any]:
                return [SimpleNamespace(serial=s, name="D435") for s in serials]

            def init_sensor(self, config: Any, index: int, filename: str) -> bool:
                return True

            def start_capture(self, record: bool) -> bool:
                api.started = True
                return True

            def get_metadata(self) -> Any:
                h, w = depth_mm.shape
                intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, 600.0, 600.0, (w - 1) / 2, (h - 1) / 2)
                return SimpleNamespace(intrinsics=intrinsic, depth_scale=1000.0, width=w, height=h)

            def capture_frame(self, wait: bool, align: bool) -> Any:
                return SimpleNamespace(depth=o3d.t.geometry.Image(o3d.core.Tensor(depth_mm)))

            def stop_capture(self) -> None:
                api.stopped = True

        self.RealSenseSensor = RealSenseSensor
        self.RealSenseSensorConfig = lambda cfg: api.config.update(cfg) or cfg


def test_realsense_unprojects_aligned_depth_with_the_reported_intrinsics() -> None:
    depth = np.full((48, 64), 800, dtype=np.uint16)
    api = _FakeRealSenseApi(("123",), depth)
    scanner = RealSenseScanner(sensor_api=api)
    assert api.started and api.config["serial"] == "123"
    cloud = scanner.capture()
    np.testing.assert_allclose(cloud.points[..., 2], 0.8, rtol=1e-6)
    np.testing.assert_allclose(cloud.points[0, 0, :2], [-31.5 * 0.8 / 600.0, -23.5 * 0.8 / 600.0], rtol=1e-5)
    scanner.close()
    assert api.stopped
    with pytest.raises(DriverUnavailable, match="camera '999' not found; connected: 123"):
        RealSenseScanner("999", sensor_api=_FakeRealSenseApi(("123",), depth))
    with pytest.raises(DriverUnavailable, match="no RealSense support"):
        RealSenseScanner(sensor_api=SimpleNamespace())


# -- real hardware ------------------------------------------------------------


@pytest.mark.hardware
@pytest.mark.skipif(not REALSENSE_DEVICES, reason="no RealSense camera connected")
def test_a_connected_realsense_gives_an_organized_cloud() -> None:
    scanner = RealSenseScanner()
    try:
        cloud = scanner.capture()
    finally:
        scanner.close()
    assert cloud.points.ndim == 3 and cloud.valid_count() > 0


@pytest.mark.hardware
@pytest.mark.skipif(not HAVE_HARVESTERS, reason="harvesters is not installed")
def test_a_connected_photoneo_gives_an_organized_cloud() -> None:
    try:
        scanner = PhotoneoScanner()
    except DriverUnavailable as exc:
        pytest.skip(str(exc))
    try:
        cloud = scanner.capture()
    finally:
        scanner.close()
    assert cloud.points.ndim == 3 and cloud.valid_count() > 0
