"""The camera process's loop: tare, one sample per frame, every failure a status, never zero."""

from __future__ import annotations

import math
import uuid

import numpy as np
import pytest

from celld import sealed
from celld.config import TactileConfig, ToolConfig
from celld.errors import DeviceError
from celld.shm import SeqlockSlot
from celld.sim.srm import SimSrm, SimSrmCamera, SrmSimParams, Wall
from celld.tactile.camera import COUNTERS_DTYPE, FrameEstimator, OpenCvCamera, run_camera
from celld.tactile.process import REST_KIND, TactileProcess, load_reference, save_reference
from celld.tactile.sample import TACTILE_DTYPE, ContactState, TactileStatus, from_record

# A wall along +x at y = 0 of a horizontal plane; the default tool faces +x
# with its TCP z down, the wall on its left.
T_PLANE = np.eye(4)
WALL = Wall(np.array([[-0.05, 0.0], [0.05, 0.0]]), free=-1.0)


def _pose(y: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[1, 3] = y
    return T


class FakeClock:
    """Simulated time for the camera: sleeping advances it."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns

    def sleep(self, s: float) -> None:
        self.ns += int(s * 1e9)


class Rig:
    """The sim camera on a fake clock, the estimator and real shared-memory slots."""

    def __init__(self, y: float = -0.002) -> None:
        self.cfg = TactileConfig(tare_frames=10)
        self.clock = FakeClock()
        self.y = y
        srm = SimSrm(self.cfg, ToolConfig(), WALL, T_PLANE, SrmSimParams(seed=3, lighting_swing=0.1))
        self.camera = SimSrmCamera(srm, lambda stamp: (_pose(self.y), np.zeros(6)), self.clock, self.clock.sleep)
        self.camera.open()
        tag = uuid.uuid4().hex[:8]
        self.samples = SeqlockSlot.create(f"t-{tag}-s", TACTILE_DTYPE)
        self.counters = SeqlockSlot.create(f"t-{tag}-c", COUNTERS_DTYPE)
        self.est = FrameEstimator(self.cfg, ToolConfig())
        self.written = []
        orig = self.samples.write

        def write(rec):
            self.written.append(from_record(rec))
            orig(rec)

        self.samples.write = write  # record every sample the loop publishes

    def run(self, frames: int) -> None:
        """Run the loop until ``frames`` more samples are published (a tare may publish a few more)."""
        target = len(self.written) + frames
        run_camera(self.camera, self.est, self.samples, self.counters, lambda: len(self.written) >= target)

    def close(self) -> None:
        for s in (self.samples, self.counters):
            s.close()
            s.unlink()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_tares_then_publishes_valid_samples_stamped_at_capture(rig: Rig) -> None:
    rig.run(40)
    tare_frames = rig.cfg.tare_frames
    assert all(s.status == TactileStatus.NOT_TARED for s in rig.written[:tare_frames])
    assert rig.est.rest is not None
    after = rig.written[tare_frames:]
    assert after and all(s.valid and s.status == TactileStatus.OK for s in after)
    # Free finger: no contact, deformation within micrometres of zero.
    assert all(s.contact == ContactState.NONE for s in after)
    assert max(np.abs(s.delta_tool[:2]).max() for s in after) < 20e-6
    # Stamps are the capture times: one frame period apart.
    stamps = np.diff([s.stamp_ns for s in after])
    assert np.all(stamps == int(round(1e9 / 60.0)))
    c = rig.counters.read()[0]
    assert c["frames"] == 40 and c["tared"]
    assert c["by_status"][int(TactileStatus.OK)] == 40 - tare_frames


def test_contact_reads_the_wall(rig: Rig) -> None:
    rig.run(11)
    rig.y = 0.0005  # the undeformed tip 1.5 mm into the wall (tip radius 1 mm)
    rig.run(5)
    s = rig.written[-1]
    assert s.valid and s.contact == ContactState.CONTACT
    assert s.delta_tool[1] == pytest.approx(0.0015, abs=20e-6)


@pytest.mark.parametrize(
    ("fault", "status"),
    [("wrong_id", TactileStatus.WRONG_ID), ("no_tag", TactileStatus.NO_TAG), ("blur", TactileStatus.BLURRED)],
)
def test_failed_detections_are_flagged_never_zero(rig: Rig, fault: str, status: TactileStatus) -> None:
    rig.run(11)
    rig.camera.srm.fault = fault
    rig.run(5)
    bad = rig.written[-5:]
    assert all(not s.valid and s.status == status for s in bad)
    assert all(np.all(np.isnan(s.delta_tool)) for s in bad)
    assert rig.counters.read()[0]["by_status"][int(status)] == 5


def test_an_unplugged_camera_gives_camera_lost_samples(rig: Rig) -> None:
    rig.run(11)
    rig.camera.unplug()
    rig.run(3)
    assert [s.status for s in rig.written[-3:]] == [TactileStatus.CAMERA_LOST] * 3
    assert all(math.isnan(s.delta_tool[0]) for s in rig.written[-3:])


def test_a_moving_finger_fails_the_tare_and_stays_untared() -> None:
    r = Rig()
    try:
        # The finger is pushed into the wall while taring: 0.1 mm more each frame.
        r.camera.pose_at = lambda stamp: (_pose(-0.0009 + (stamp - 1_000_000_000) * 6e-3 / 1e9), np.zeros(6))
        r.run(r.cfg.tare_frames)
        assert r.est.rest is None
        assert all(not s.valid for s in r.written)
    finally:
        r.close()


def test_a_finger_pressed_at_start_is_not_tared_until_it_is_free(tmp_path) -> None:
    # The start-up tare is taken but is no reference; the daemon's tare (the
    # finger known free) is, and is kept.
    free = Rig()
    kept = []
    try:
        free.run(free.cfg.tare_frames + 2)
        assert free.est.rest is not None and free.est.reference is None
        asked = iter([True])
        target = len(free.written) + free.cfg.tare_frames + 2
        run_camera(
            free.camera,
            free.est,
            free.samples,
            free.counters,
            lambda: len(free.written) >= target,
            lambda: next(asked, False),
            on_reference=kept.append,
        )
        assert len(kept) == 1 and free.est.reference is not None
        save_reference(tmp_path / "rest.json", kept[0])
    finally:
        free.close()
    reference = load_reference(tmp_path / "rest.json")
    np.testing.assert_allclose(reference, kept[0].p_cam_rest)

    # A restarted camera process with the tip held 1.5 mm into the wall (still: the spread is fine).
    r = Rig(y=0.0005)
    try:
        r.est = FrameEstimator(r.cfg, ToolConfig(), reference=reference)
        r.run(3 * r.cfg.tare_frames)
        assert r.est.rest is None and all(s.status == TactileStatus.NOT_TARED for s in r.written)
        c = r.counters.read()[0]
        assert not c["tared"] and c["tare_refused"]
        assert c["tare_offset"] == pytest.approx(0.0015, abs=0.1e-3)
        # Freed: the next tare is taken, next to the reference, which stays as it was.
        r.y = -0.002
        r.run(3 * r.cfg.tare_frames)
        c = r.counters.read()[0]
        assert r.est.rest is not None and c["tared"] and not c["tare_refused"]
        assert c["tare_offset"] < 0.02e-3
        np.testing.assert_array_equal(r.est.reference, reference)
        assert r.written[-1].status == TactileStatus.OK
    finally:
        r.close()


def test_an_unreadable_reference_is_ignored_and_replaced_by_the_next_tare(tmp_path) -> None:
    path = tmp_path / "rest.json"
    sealed.write_sealed(path, {"p_cam_rest_m": [0.0, "x", 0.02]}, REST_KIND)
    assert load_reference(path) is None
    sealed.write_sealed(path, {"p_cam_rest_m": [0.0, 0.001, 0.02]}, REST_KIND)
    assert load_reference(path) == pytest.approx([0.0, 0.001, 0.02])
    path.write_text(path.read_text().replace("0.001", "0.002"))  # edited: its checksum refuses it
    assert load_reference(path) is None
    path.write_text("not json")
    assert load_reference(path) is None
    assert load_reference(tmp_path / "absent.json") is None


def test_opencv_camera_that_is_absent_is_refused_then_reads_as_lost() -> None:
    cfg = TactileConfig(kind="opencv", device="/dev/celld-no-such-camera", fps=200.0)
    cam = OpenCvCamera(cfg)
    with pytest.raises(DeviceError, match="cannot open"):
        cam.open()
    assert cam.read() is None


@pytest.mark.process
def test_tactile_process_refuses_to_start_without_its_camera() -> None:
    cfg = TactileConfig(kind="opencv", device="/dev/celld-no-such-camera")
    proc = TactileProcess(cfg, ToolConfig(), f"t-{uuid.uuid4().hex[:8]}")
    try:
        with pytest.raises(DeviceError, match="exited at start"):
            proc.start(timeout=20.0)
    finally:
        proc.stop()


def test_preview_writer_shares_frames_at_most_every_period_with_the_tag_outline() -> None:
    import uuid

    from celld.config import TactileConfig
    from celld.shm import SeqlockSlot
    from celld.tactile.camera import PREVIEW_PERIOD, PreviewWriter, preview_dtype

    cfg = TactileConfig(width_px=64, height_px=48)
    slot = SeqlockSlot.create(f"test-preview-{uuid.uuid4().hex[:8]}", preview_dtype(cfg))
    try:
        writer = PreviewWriter(slot, cfg)
        img = np.full((48, 64), 7, np.uint8)
        corners = np.array([[1.0, 2.0], [3.0, 2.0], [3.0, 4.0], [1.0, 4.0]])
        writer.offer(1_000, img, corners)
        writer.offer(1_000 + int(PREVIEW_PERIOD * 1e9) - 1, np.zeros((48, 64), np.uint8), None)  # too soon: dropped
        rec, _ = slot.read()
        assert int(rec["stamp_ns"]) == 1_000 and bool(rec["has_tag"]) and np.all(rec["image"] == 7)
        np.testing.assert_array_equal(rec["corners_px"], corners)
        writer.offer(1_000 + int(PREVIEW_PERIOD * 1e9), np.zeros((48, 64, 3), np.uint8), None)  # BGR: made grey
        rec, _ = slot.read()
        assert not bool(rec["has_tag"]) and np.all(rec["image"] == 0)
        writer.offer(10**12, np.zeros((10, 10), np.uint8), None)  # another size than configured: not shared
        assert int(slot.read()[0]["stamp_ns"]) == 1_000 + int(PREVIEW_PERIOD * 1e9)
    finally:
        slot.close()
        slot.unlink()


@pytest.mark.process
def test_a_killed_tactile_process_restarts_on_the_same_slots(sim_robot) -> None:
    import os
    import signal
    import time

    from celld.sim.srm import SimSrmSource

    cfg = TactileConfig(fps=30.0, tare_frames=5)
    far_wall = np.array([[100.0, 100.0], [101.0, 100.0]])  # the finger touches nothing
    proc = TactileProcess(cfg, ToolConfig(), f"t-{uuid.uuid4().hex[:8]}", SimSrmSource(sim_robot.host, far_wall, -1.0, np.eye(4)))

    def tared_by(pid_not: int) -> int:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            c = proc.read_counters()
            if c is not None and int(c["pid"]) not in (0, pid_not) and bool(c["tared"]):
                return int(c["pid"])
            time.sleep(0.05)
        raise AssertionError("no tared camera process within 30 s")

    try:
        proc.start(timeout=30.0)
        first = tared_by(0)
        os.kill(first, signal.SIGKILL)
        deadline = time.monotonic() + 5.0
        while proc.alive() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not proc.alive()
        with_slot = proc.slot_name
        assert proc.restart(timeout=30.0) == -signal.SIGKILL
        second = tared_by(first)
        assert second != first and proc.slot_name == with_slot and proc.restarts == 1
        seq = proc.latest().seq
        time.sleep(0.3)
        assert proc.latest().seq > seq, "the new process writes the slot the motion process reads"
        with pytest.raises(DeviceError, match="running"):
            proc.restart()
    finally:
        proc.stop()
