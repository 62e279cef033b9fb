"""A job recording written, closed and read back with the rerun SDK."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rerun_cli

from celld import se3
from celld.config import RecordingConfig, parse
from celld.errors import ConfigError, InputError, RecordingError
from celld.recording import (
    JobRecording,
    layout,
    read_component,
    read_entities,
    read_recording_id,
    read_scalars,
    read_views,
    recording_path,
)
from celld.tactile.sample import TACTILE_DTYPE

# One second of the 500 Hz loop.
N_CYCLES = 500
PERIOD_NS = 2_000_000
# The motion ring's fields the recording maps (celld.motion.channels.STATE_DTYPE has more).
STATE_DTYPE = np.dtype(
    [
        ("cycle", np.uint64),
        ("t_ns", np.int64),
        ("late_ns", np.int64),
        ("period_ns", np.int64),
        ("work_ns", np.int64),
        ("tcp_pose", np.float64, (6,)),
        ("tcp_speed", np.float64, (6,)),
        ("status", np.int16),
        ("twist", np.float64, (6,)),
    ]
)


def _state_batch(t0_ns: int) -> np.ndarray:
    b = np.zeros(N_CYCLES, STATE_DTYPE)
    k = np.arange(N_CYCLES)
    b["cycle"] = k
    b["t_ns"] = t0_ns + 10_000_000 + k * PERIOD_NS
    b["tcp_pose"][:, 0] = 0.5 + 0.01 * k * PERIOD_NS * 1e-9  # 10 mm/s along x
    b["tcp_pose"][:, 2] = 0.2
    b["tcp_pose"][:, 3] = np.pi  # tool pointing down
    b["tcp_speed"][:, 0] = 0.01
    b["twist"][:, 0] = 0.01
    b["twist"][:, 5] = 0.05 * np.sin(k / 50.0)  # omega about the base z axis
    b["late_ns"] = 20_000 + (k % 7) * 1_000
    b["period_ns"] = PERIOD_NS
    b["work_ns"] = 150_000
    return b


def _tactile_batch(t0_ns: int, rng: np.random.Generator) -> np.ndarray:
    """Two seconds of the SRM camera at 60 fps."""
    b = np.zeros(120, TACTILE_DTYPE)
    b["stamp_ns"] = t0_ns + np.arange(120) * 16_666_667
    b["delta_tool"][:, 1] = 0.0015 + 1e-5 * rng.standard_normal(120)
    b["valid"] = True
    return b


def _full_recording(path: Path, rng: np.random.Generator, config: RecordingConfig | None = None) -> dict:
    """Write one recording with every kind of data; return what went in."""
    rec = JobRecording(path, "job-7", "weld", config)
    t0 = rec.t0_ns
    P_scan = rng.uniform(-0.2, 0.2, (3000, 3)) + [0.6, 0.0, 0.05]
    organized = rng.uniform(0.5, 1.0, (40, 50, 3)).astype(np.float32)
    organized[:10] = np.nan  # 500 pixels without a return
    T_base_cam = np.array(parse({}).scanner.T_base_cam)
    planned = np.column_stack([np.linspace(0.5, 0.7, 20), np.zeros(20), np.full(20, 0.05)])
    rec.log_camera_pose(T_base_cam, stamp_ns=t0)
    rec.log_cloud_base("scan", P_scan, colors=(200, 200, 200), stamp_ns=t0)
    n_cam = rec.log_cloud_cam("capture", organized, stamp_ns=t0)
    rec.log_circle_cam("flange", [0.01, -0.02, 0.6], [0.0, 0.0, -1.0], 0.0315, stamp_ns=t0)
    rec.log_tcp(se3.from_ur_pose([0.5, 0.0, 0.2, np.pi, 0.0, 0.0]), stamp_ns=t0)
    for name in ("planned", "refined", "torch"):
        rec.log_path_base(name, planned + [0.0, 0.001 * len(name), 0.0], stamp_ns=t0)
    image = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    corners = np.array([[40.0, 30.0], [90.0, 30.0], [90.0, 80.0], [40.0, 80.0]])
    rec.log_camera_image(image, corners, stamp_ns=t0 + 5_000_000)
    rec.log_camera_image(image, None, stamp_ns=t0 + 6_000_000)  # the tag lost in the next frame
    batch = _state_batch(t0)
    # Two ring reads, as the recorder would make them: one sent here, one handed to the feed thread (the
    # daemon's way), which close() waits for.
    sent = rec.log_state_batch(batch[:200]) + len(batch[200:])
    rec.feed_state_batch(batch[200:])
    tactile = _tactile_batch(t0, rng)
    rec.log_state_batch(tactile)
    e_icp = [0.004, 0.0021, 0.0009, float("inf"), 0.0004]
    for i, e in enumerate(e_icp):
        rec.log_e_icp(i, e, stamp_ns=t0 + i * 1_000_000_000)
    rec.log_event("weld done")
    rec.close()
    return {
        "batch": batch,
        "tactile": tactile,
        "sent": sent,
        "n_cam": n_cam,
        "planned": planned,
        "e_icp": e_icp,
        "corners": corners,
        "t0": t0,
    }


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    path = tmp_path_factory.mktemp("rec") / "recordings" / "job-7.rrd"
    return path, _full_recording(path, np.random.default_rng(0))


def test_the_file_holds_every_entity_of_the_layout(written: tuple[Path, dict]) -> None:
    path, _ = written
    assert path.is_file()
    assert read_recording_id(path) == "job-7"
    assert read_entities(path) == {
        "/world",
        "/world/camera",
        "/world/camera/clouds/capture",
        "/world/camera/circles/flange",
        "/world/camera/circles/flange/normal",
        "/world/clouds/scan",
        "/world/tcp",
        "/world/paths/planned",
        "/world/paths/refined",
        "/world/paths/torch",
        "/srm/camera",
        "/srm/camera/tag",
        "/servo/delta",
        "/servo/v_r",
        "/servo/omega",
        "/robot/v_tcp",
        "/motion/loop/late_ms",
        "/motion/loop/period_ms",
        "/motion/loop/work_ms",
        "/motion/status",
        "/weld/contact",  # the tactile samples' contact state
        "/calib/e_icp",
        "/events",
    }


def test_the_blueprint_has_the_3d_2d_and_time_series_views(written: tuple[Path, dict]) -> None:
    views = read_views(written[0])
    assert ("3D", "/world") in views and ("2D", "/srm/camera") in views
    for origin in (
        layout.SERVO_DELTA_N,
        layout.WELD,
        layout.SERVO_DELTA,
        layout.SERVO_V_R,
        layout.SERVO_OMEGA,
        layout.MOTION_LOOP,
        layout.CALIB_E_ICP,
    ):
        assert ("TimeSeries", origin) in views


def test_the_weld_timeline_has_the_deformation_its_target_the_contact_and_the_arc(tmp_path: Path) -> None:
    """The motion ring's own records (celld.motion.channels.STATE_DTYPE): delta_n against delta_d,
    the contact state, the phase and the arc output, each a series on the loop's clock."""
    from celld.motion.channels import STATE_DTYPE as RING_DTYPE

    path = tmp_path / "weld.rrd"
    rec = JobRecording(path, "weld-1", "weld")
    n = 300
    b = np.zeros(n, RING_DTYPE)
    b["t_ns"] = rec.t0_ns + np.arange(n) * PERIOD_NS
    b["delta_n"] = np.where(np.arange(n) < 50, np.nan, 0.0015 + 1e-5 * np.sin(np.arange(n)))
    b["delta_d"] = np.where(np.arange(n) < 20, np.nan, 0.0015)
    b["delta_tool"] = np.nan
    b["delta_tool"][50:, 1] = b["delta_n"][50:]
    b["contact"] = np.where(np.arange(n) < 50, 0, 1)
    b["servo_phase"] = np.where(np.arange(n) < 50, 0, 1)
    b["process_on"] = (np.arange(n) >= 60) & (np.arange(n) < 250)
    assert rec.log_state_batch(b) == n
    rec.close()
    _, dn = read_scalars(path, f"{layout.SERVO_DELTA_N}/delta_n")
    _, dd = read_scalars(path, f"{layout.SERVO_DELTA_N}/delta_d")
    _, contact = read_scalars(path, layout.WELD_CONTACT)
    _, arc = read_scalars(path, layout.WELD_ARC)
    _, phase = read_scalars(path, layout.SERVO_PHASE)
    np.testing.assert_allclose(dn[:, 0], b["delta_n"], equal_nan=True)
    np.testing.assert_allclose(dd[:, 0], b["delta_d"], equal_nan=True)
    np.testing.assert_array_equal(contact[:, 0], b["contact"])
    np.testing.assert_array_equal(phase[:, 0], b["servo_phase"])
    np.testing.assert_array_equal(arc[:, 0], b["process_on"].astype(float))
    # The arc on for exactly the cycles the loop asked for it: 190 cycles, 0.38 s.
    assert int(arc[:, 0].sum()) == 190


def test_state_batches_become_time_series_on_the_loop_clock(written: tuple[Path, dict]) -> None:
    path, sent = written
    batch = sent["batch"]
    assert sent["sent"] == N_CYCLES
    t, omega = read_scalars(path, layout.SERVO_OMEGA)
    assert omega.shape == (N_CYCLES, 3)
    np.testing.assert_allclose(omega, batch["twist"][:, 3:], atol=1e-12)
    # Times are seconds since the recording opened: 10 ms, then one cycle apart.
    np.testing.assert_allclose(t[0], 0.010, atol=1e-9)
    np.testing.assert_allclose(np.diff(t), PERIOD_NS * 1e-9, atol=1e-9)
    _, v_r = read_scalars(path, layout.SERVO_V_R)
    np.testing.assert_allclose(v_r, batch["twist"][:, :3], atol=1e-12)
    t_delta, delta = read_scalars(path, layout.SERVO_DELTA)
    assert delta.shape == (120, 3)
    np.testing.assert_allclose(delta[:, 1], sent["tactile"]["delta_tool"][:, 1], atol=1e-12)
    np.testing.assert_allclose(t_delta[-1], 119 * 16_666_667e-9, atol=1e-9)
    _, late = read_scalars(path, f"{layout.MOTION_LOOP}/late_ms")
    np.testing.assert_allclose(late[:, 0], batch["late_ns"] * 1e-6, rtol=1e-12)
    _, v_tcp = read_scalars(path, layout.ROBOT_V_TCP)
    assert v_tcp.shape == (N_CYCLES, 6)


def test_tcp_poses_from_the_ring_and_from_log_tcp_are_all_there(written: tuple[Path, dict]) -> None:
    path, sent = written
    _t, translation = read_component(path, layout.TCP, "Transform3D:translation")
    assert len(translation) == N_CYCLES + 1
    xyz = np.array([np.asarray(v).reshape(3) for v in translation])
    # The last ring record: 10 mm/s for 998 ms from x = 0.5 m.
    np.testing.assert_allclose(xyz[-1], sent["batch"]["tcp_pose"][-1, :3], atol=1e-6)


def test_e_icp_is_indexed_by_iteration_and_a_failed_icp_is_a_gap(written: tuple[Path, dict]) -> None:
    path, sent = written
    it, e = read_scalars(path, layout.CALIB_E_ICP, timeline=layout.ITERATION)
    np.testing.assert_array_equal(it, np.arange(5))
    expected = np.array(sent["e_icp"])
    expected[~np.isfinite(expected)] = np.nan
    np.testing.assert_allclose(e[:, 0], expected, equal_nan=True)
    _, events = read_component(path, layout.EVENTS, "TextLog:text")
    assert any("ICP failed" in str(v) for v in events)


def test_clouds_drop_points_without_return_and_circles_have_their_radius(written: tuple[Path, dict]) -> None:
    path, sent = written
    _, clouds = read_component(path, "/world/camera/clouds/capture", "Points3D:positions")
    assert sent["n_cam"] == 40 * 50 - 10 * 50 and len(clouds[0]) == sent["n_cam"]
    assert np.all(np.isfinite(clouds[0]))
    _, rings = read_component(path, "/world/camera/circles/flange", "LineStrips3D:strips")
    ring = np.asarray(rings[0][0])
    np.testing.assert_allclose(np.linalg.norm(ring - [0.01, -0.02, 0.6], axis=1), 0.0315, atol=1e-6)
    np.testing.assert_allclose(ring[:, 2], 0.6, atol=1e-6)


def test_paths_and_the_tag_outline_keep_their_coordinates(written: tuple[Path, dict]) -> None:
    path, sent = written
    _, strips = read_component(path, "/world/paths/planned", "LineStrips3D:strips")
    np.testing.assert_allclose(np.asarray(strips[0][0]), sent["planned"] + [0.0, 0.007, 0.0], atol=1e-6)
    t_outline, outline = read_component(path, layout.SRM_TAG, "LineStrips2D:strips")
    # The first frame has the closed outline, the second (no tag) clears it.
    np.testing.assert_allclose(np.asarray(outline[0][0]), np.vstack([sent["corners"], sent["corners"][:1]]))
    t_clear, _ = read_component(path, layout.SRM_TAG, "Clear:is_recursive")
    np.testing.assert_allclose([t_outline[0], t_clear[0]], [0.005, 0.006], atol=1e-9)
    _, blobs = read_component(path, layout.SRM_CAMERA, "EncodedImage:blob")
    assert len(blobs) == 2
    jpeg = np.asarray(blobs[0], dtype=np.uint8).ravel()
    assert jpeg.size > 100 and jpeg[:2].tolist() == [0xFF, 0xD8]  # a JPEG start-of-image marker


def test_clouds_are_thinned_to_the_configured_size(tmp_path: Path, rng: np.random.Generator) -> None:
    with JobRecording(tmp_path / "a.rrd", "job-thin", "scan", RecordingConfig(max_cloud_points=1000)) as rec:
        assert rec.log_cloud_base("scan", rng.random((25_000, 3))) == 1000
    _, clouds = read_component(tmp_path / "a.rrd", "/world/clouds/scan", "Points3D:positions")
    assert len(clouds[0]) == 1000


def test_a_disabled_recording_writes_nothing_and_accepts_every_call(tmp_path: Path) -> None:
    path = tmp_path / "off.rrd"
    rec = JobRecording(path, "job-off", "weld", RecordingConfig(enabled=False))
    rec.log_cloud_base("scan", np.zeros((3, 3)))
    assert rec.log_state_batch(np.zeros(3, STATE_DTYPE)) == 0
    rec.log_e_icp(0, 0.001)
    rec.close()
    assert not path.exists() and rec.path is None


def test_logging_after_close_is_ignored(tmp_path: Path) -> None:
    rec = JobRecording(tmp_path / "a.rrd", "job-late", "weld")
    rec.close()
    rec.log_e_icp(0, 0.001)
    assert rec.log_state_batch(np.zeros(2, STATE_DTYPE)) == 0
    rec.close()
    assert read_entities(tmp_path / "a.rrd") == {"/world"}  # the axes logged at open, nothing after


def test_bad_ids_kinds_paths_and_inputs_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="job_id"):
        recording_path(tmp_path, "../escape")
    with pytest.raises(InputError, match="kind"):
        JobRecording(tmp_path / "a.rrd", "job-1", "party")
    (tmp_path / "file").write_text("not a directory")
    with pytest.raises(RecordingError, match="cannot create"):
        JobRecording(tmp_path / "file" / "a.rrd", "job-1")
    with JobRecording(tmp_path / "b.rrd", "job-2") as rec:
        with pytest.raises(InputError, match="path name"):
            rec.log_path_base("dream", np.zeros((3, 3)))
        with pytest.raises(InputError, match="uint8"):
            rec.log_camera_image(np.zeros((4, 4), np.float32))
        with pytest.raises(InputError, match="tag corners"):
            rec.log_camera_image(np.zeros((4, 4), np.uint8), corners_px=[[0, 0], [1, 1]])
        with pytest.raises(InputError, match="radius"):
            rec.log_circle_base("flange", [0, 0, 0], [0, 0, 1], -0.01)
        with pytest.raises(InputError, match="rotation"):
            rec.log_tcp(np.diag([1.0, 1.0, -1.0, 1.0]))


def test_recording_paths_live_under_the_state_directory(tmp_path: Path) -> None:
    assert recording_path(tmp_path, "job-9") == tmp_path / "recordings" / "job-9.rrd"
    with JobRecording.for_job(tmp_path, "job-9", "calibration") as rec:
        assert rec.path == tmp_path / "recordings" / "job-9.rrd"
    assert read_recording_id(tmp_path / "recordings" / "job-9.rrd") == "job-9"


def test_the_config_refuses_a_viewer_url_rerun_would_refuse() -> None:
    with pytest.raises(ConfigError, match="connect_url"):
        parse({"recording": {"connect_url": "http://127.0.0.1:9876"}})
    with pytest.raises(ConfigError, match="serve_grpc_host"):
        parse({"recording": {"serve_grpc_host": "localhost"}})


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _rerun_cli(tmp_path: Path, args: list[str]) -> subprocess.Popen:
    """Start the rerun CLI (the SDK's viewer binary) with a private config home and analytics off,
    so that it talks to nothing but loopback."""
    config_home = tmp_path / "config"
    (config_home / "rerun").mkdir(parents=True, exist_ok=True)
    (config_home / "rerun" / "analytics.json").write_text(
        json.dumps(
            {
                "analytics_enabled": False,
                "analytics_id": "0",
                "metadata": {},
                "config_file_path": str(config_home / "rerun" / "analytics.json"),
                "data_dir_path": str(tmp_path / "data" / "rerun" / "analytics"),
            }
        )
    )
    env = dict(os.environ, XDG_CONFIG_HOME=str(config_home), XDG_DATA_HOME=str(tmp_path / "data"))
    # The binary itself, not the `rerun` script: the script runs it as a child that
    # would outlive a kill of the script.
    binary = Path(rerun_cli.__file__).parent / "rerun"
    return subprocess.Popen([str(binary), *args], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _wait_for_entity(path: Path, entity: str, deadline: float) -> set[str]:
    got: set[str] = set()
    while time.monotonic() < deadline and entity not in got:
        time.sleep(0.3)
        if path.exists():
            try:
                got = read_entities(path)
            except InputError:
                pass  # the viewer has not written its first message yet
    return got


def test_a_busy_serve_port_leaves_the_file_recording(tmp_path: Path, loopback_host: str) -> None:
    with socket.socket() as busy:
        busy.bind((loopback_host, 0))
        busy.listen()
        port = busy.getsockname()[1]
        cfg = RecordingConfig(serve_grpc_port=port, serve_grpc_host=loopback_host)
        with JobRecording(tmp_path / "a.rrd", "job-busy", "weld", cfg) as rec:
            assert rec.serve_url is None
            rec.log_e_icp(0, 0.001)
    assert layout.CALIB_E_ICP in read_entities(tmp_path / "a.rrd")


@pytest.mark.process
def test_a_viewer_connected_to_the_served_stream_receives_the_job(tmp_path: Path, loopback_host: str) -> None:
    """The rerun CLI connects to the served gRPC stream and saves what it receives."""
    port = _free_port(loopback_host)
    cfg = RecordingConfig(serve_grpc_port=port, serve_grpc_host=loopback_host)
    saved = tmp_path / "viewer.rrd"
    with JobRecording(tmp_path / "job.rrd", "job-live", "weld", cfg) as rec:
        assert rec.serve_url == f"rerun+http://{loopback_host}:{port}/proxy"
        viewer = _rerun_cli(tmp_path, [rec.serve_url, "--save", str(saved)])
        try:
            rec.log_e_icp(0, 0.0021)
            rec.log_e_icp(1, 0.0007)
            got = _wait_for_entity(saved, layout.CALIB_E_ICP, deadline=time.monotonic() + 30.0)
        finally:
            viewer.kill()
            viewer.wait(timeout=10)
    assert layout.CALIB_E_ICP in got
    assert read_recording_id(saved) == "job-live"
    _, e = read_scalars(saved, layout.CALIB_E_ICP, timeline=layout.ITERATION)
    np.testing.assert_allclose(e[:, 0], [0.0021, 0.0007])


def test_a_viewer_that_is_not_listening_is_skipped_and_close_stays_quick(tmp_path: Path, loopback_host: str) -> None:
    url = f"rerun+http://{loopback_host}:{_free_port(loopback_host)}/proxy"
    rec = JobRecording(tmp_path / "a.rrd", "job-alone", "weld", RecordingConfig(connect_url=url))
    assert rec.connect_url is None
    rec.log_e_icp(0, 0.001)
    started = time.monotonic()
    rec.close()
    assert time.monotonic() - started < 2.0
    _, e = read_scalars(tmp_path / "a.rrd", layout.CALIB_E_ICP, timeline=layout.ITERATION)
    np.testing.assert_allclose(e[:, 0], [0.001])


@pytest.mark.process
def test_a_job_is_pushed_to_a_listening_viewer(tmp_path: Path, loopback_host: str) -> None:
    """connect_url: the rerun CLI listens as a viewer would and saves what arrives."""
    port = _free_port(loopback_host)
    url = f"rerun+http://{loopback_host}:{port}/proxy"
    saved = tmp_path / "viewer.rrd"
    viewer = _rerun_cli(tmp_path, ["--serve-grpc", "--bind", loopback_host, "--port", str(port), "--save", str(saved)])
    try:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            try:
                socket.create_connection((loopback_host, port), timeout=0.5).close()
                break
            except OSError:
                time.sleep(0.2)
        with JobRecording(tmp_path / "job.rrd", "job-push", "calibration", RecordingConfig(connect_url=url)) as rec:
            assert rec.connect_url == url
            rec.log_e_icp(0, 0.0013)
        got = _wait_for_entity(saved, layout.CALIB_E_ICP, deadline=time.monotonic() + 30.0)
    finally:
        viewer.kill()
        viewer.wait(timeout=10)
    assert layout.CALIB_E_ICP in got and read_recording_id(saved) == "job-push"
    # The job's own file is complete regardless of the viewer.
    _, e = read_scalars(tmp_path / "job.rrd", layout.CALIB_E_ICP, timeline=layout.ITERATION)
    np.testing.assert_allclose(e[:, 0], [0.0013])


def test_a_full_disk_fails_the_recording_and_close_returns(tmp_path: Path, small_disk, rng: np.random.Generator) -> None:
    """rerun's own file sink hung in close() once the disk was full, and said so only in its log."""
    import threading

    from celld.errors import StorageError

    disk = small_disk(1 * 2**20)
    outcome: dict = {}

    def record() -> None:
        rec = JobRecording(disk / "recordings" / "job-full.rrd", "job-full", "scan")
        try:
            for i in range(20):
                rec.log_cloud_base(f"c{i}", rng.random((20_000, 3)))
            rec.close()
            outcome["closed"] = "without an error"
        except StorageError as exc:
            outcome["closed"] = exc

    t = threading.Thread(target=record, daemon=True)
    t.start()
    t.join(30)
    assert not t.is_alive(), "close() hung on a full disk"
    assert isinstance(outcome["closed"], StorageError), outcome["closed"]
    assert "No space left on device" in str(outcome["closed"]) and "job-full.rrd" in str(outcome["closed"])


def test_a_solved_calibration_places_every_capture_in_the_base_frame_with_its_residuals(tmp_path: Path) -> None:
    """The calibration recording: captures logged in the camera frame during the job, the solved
    T_base_cam logged static at the end (it then places them all), the flange model carried by the
    TCP, the residual of each pair as an arrow and a bar."""
    from celld.calib.flange import preset

    path = tmp_path / "cal.rrd"
    rec = JobRecording(path, "cal-1", "calibration")
    mesh = preset("ur10e").mesh()
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    rec.log_mesh(layout.FLANGE, V, F, static=True)
    rec.log_cloud_cam("pair", np.array([[0.0, 0.0, 0.8], [0.01, 0.0, 0.8]]))
    T = se3.from_ur_pose([0.6, 0.0, 1.0, np.pi, 0.0, 0.0])
    P_robot = np.array([[0.5, 0.0, 0.2], [0.6, 0.1, 0.25], [0.7, -0.1, 0.3]])
    P_scanner = P_robot + [[1e-4, 0.0, 0.0], [0.0, -2e-4, 0.0], [0.0, 0.0, 3e-3]]
    rec.log_camera_pose(T, static=True)
    rec.log_residuals(["p000", "p001", "p002"], P_robot, P_scanner, [False, False, True])
    # A robot-robot calibration: the second robot's base, for the whole recording; a matrix that is no
    # rigid transform is refused.
    T_base1_base2 = se3.from_ur_pose([1.2, 0.05, 0.0, 0.0, 0.0, np.pi])
    rec.log_robot2_base(T_base1_base2)
    with pytest.raises(InputError, match="T_base1_base2"):
        rec.log_robot2_base(np.diag([2.0, 1.0, 1.0, 1.0]))
    rec.close()

    entities = read_entities(path)
    assert {layout.FLANGE, layout.RESIDUALS, layout.CALIB_RESIDUALS, layout.CAMERA, layout.ROBOT2} <= entities
    _, base2 = read_component(path, layout.ROBOT2, "Transform3D:translation", timeline="")
    np.testing.assert_allclose(np.asarray(base2[0]).reshape(3), T_base1_base2[:3, 3])
    # Static: no time on any timeline, so it holds for the captures logged before it.
    _, translation = read_component(path, layout.CAMERA, "Transform3D:translation", timeline="")
    np.testing.assert_allclose(np.asarray(translation[0]).reshape(3), T[:3, 3])
    _, vertices = read_component(path, layout.FLANGE, "Mesh3D:vertex_positions", timeline="")
    assert len(vertices[0]) == len(V)
    _, bars = read_component(path, layout.CALIB_RESIDUALS, "BarChart:values")
    np.testing.assert_allclose(np.asarray(bars[0][0]["buffer"]), [0.1, 0.2, 3.0], rtol=1e-6)  # a tensor
    _, vectors = read_component(path, layout.RESIDUALS, "Arrows3D:vectors")
    np.testing.assert_allclose(np.asarray(vectors[0]).reshape(-1, 3), (P_scanner - P_robot) * 20.0, atol=1e-9)


def test_bad_meshes_and_residuals_are_refused_with_the_reason(tmp_path: Path) -> None:
    rec = JobRecording(tmp_path / "bad.rrd", "bad-1", "calibration")
    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(InputError, match="indices into 3 vertices"):
        rec.log_mesh(layout.WORKPIECE, V, [[0, 1, 3]])
    with pytest.raises(InputError, match="under /world"):
        rec.log_mesh("/workpiece", V, [[0, 1, 2]])
    with pytest.raises(InputError, match="matching ids"):
        rec.log_residuals(["a"], V, V, [False, False, False])
    rec.close()


@pytest.mark.process
def test_a_recording_drained_many_times_is_one_readable_stream(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each drain of rerun's memory stream is a whole RRD stream; close merges them into one file
    that rerun's own verifier accepts (several streams in one file are refused), and the part file goes."""
    import celld.recording.job as job_mod

    monkeypatch.setattr(job_mod, "_DRAIN_PERIOD", 0.01)
    path = tmp_path / "recordings" / "long-1.rrd"
    rec = JobRecording(path, "long-1", "calibration")
    rng = np.random.default_rng(1)
    for i in range(6):
        rec.log_cloud_cam("pair", rng.uniform(0.5, 1.0, (2000, 3)))
        rec.log_e_icp(i, 1e-3 / (i + 1))
        time.sleep(0.05)  # several drains between the logs
    assert rec._writer is not None and rec._writer.written > 0  # drained before close
    rec.close()
    assert path.is_file() and not path.with_name("long-1.rrd.part").exists()
    verify = subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "verify", str(path)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr[-500:]
    it, e = read_scalars(path, layout.CALIB_E_ICP, timeline=layout.ITERATION)
    np.testing.assert_array_equal(it, np.arange(6))
    np.testing.assert_allclose(e[:, 0], 1e-3 / np.arange(1, 7))


_DIES_MID_JOB = """
import os, sys, time
import numpy as np
import celld.recording.job as job_mod
from celld.recording.job import JobRecording

job_mod._DRAIN_PERIOD = 0.01
rec = JobRecording.for_job(sys.argv[1], sys.argv[2], "calibration")
for i in range(6):
    rec.log_e_icp(i, 1e-3 / (i + 1))
    rec._rec.flush(timeout_sec=1.0)  # encoded now: each drain below writes it as a stream of its own
    time.sleep(0.05)
time.sleep(0.1)
os._exit(9)  # killed mid-job: the part file is left as it was written
"""


def test_a_recording_a_dead_process_left_open_is_finalised_into_a_readable_file(tmp_path: Path) -> None:
    from celld.recording.job import finalise_parts, leftover_parts

    state = tmp_path / "state"
    for job in ("20260101-000000-aaaaaa", "20260101-000001-bbbbbb"):
        subprocess.run([sys.executable, "-c", _DIES_MID_JOB, str(state), job], check=False, timeout=60)
    recordings = state / "recordings"
    whole, cut = (recordings / f"{j}.rrd.part" for j in ("20260101-000000-aaaaaa", "20260101-000001-bbbbbb"))
    assert whole.is_file() and cut.is_file() and not list(recordings.glob("*.rrd"))
    # The second one cut mid-write (a stream without its end), as a power cut leaves it.
    data = cut.read_bytes()
    last = data.rfind(data[:12])  # where the last stream begins: each drain is a whole stream with its header
    assert last > 0
    with open(cut, "r+b") as f:
        f.truncate(last + (len(data) - last) // 2)
    with pytest.raises(InputError):  # as it was left, rerun's reader does not give the job's data back
        read_scalars(whole, layout.CALIB_E_ICP, timeline=layout.ITERATION)
    (recordings / "garbage.rrd.part").write_bytes(np.random.default_rng(0).bytes(5000))
    (recordings / "merged.rrd").write_bytes(b"x")  # a merge that finished but did not remove its part
    (recordings / "merged.rrd.part").write_bytes(b"y")

    done = {d.job: d for d in finalise_parts(leftover_parts(state))}
    assert set(done) == {"20260101-000000-aaaaaa", "20260101-000001-bbbbbb", "garbage"}
    for job in ("20260101-000000-aaaaaa", "20260101-000001-bbbbbb"):
        path = recordings / f"{job}.rrd"
        assert done[job] == (job, path, "") and not path.with_name(path.name + ".part").exists()
        verify = subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "verify", str(path)], capture_output=True, text=True)
        assert verify.returncode == 0, verify.stderr[-500:]
        it, _ = read_scalars(path, layout.CALIB_E_ICP, timeline=layout.ITERATION)
        assert len(it) >= (6 if job.endswith("a") else 1)  # the cut one keeps what came before the cut
    assert done["garbage"].error and done["garbage"].path.is_file()  # not an RRD stream: kept, with why
    assert (recordings / "merged.rrd").read_bytes() == b"x" and not (recordings / "merged.rrd.part").exists()


def test_a_close_while_the_feed_thread_is_starting_waits_for_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The event loop hands a batch over (which starts the feed thread) while a worker thread closes the
    recording: close must not find a feed thread that is not started yet (it joined one, and raised)."""
    import threading

    import celld.recording.job as job_mod

    rec = JobRecording(tmp_path / "race.rrd", "job-race", "other")
    in_start, closed = threading.Event(), threading.Event()
    real_start = threading.Thread.start

    def slow_start(self: threading.Thread) -> None:
        if self.name.startswith("rrd-feed-"):
            in_start.set()
            closed.wait(0.5)  # give close() its chance in the window between creating and starting the thread
        real_start(self)

    monkeypatch.setattr(job_mod.threading.Thread, "start", slow_start)
    errors: list[BaseException] = []

    def close() -> None:
        in_start.wait(5.0)
        try:
            rec.close()
        except BaseException as exc:  # noqa: BLE001 (the race's RuntimeError is the failure)
            errors.append(exc)
        closed.set()

    closer = threading.Thread(target=close)
    closer.start()
    rec.event_later("a progress line from the event loop")
    closer.join(10.0)
    assert not closer.is_alive() and errors == [], errors
    assert rec.closed and (tmp_path / "race.rrd").exists()
