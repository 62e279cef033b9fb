"""What the weld job checks before it moves anything: the part, the calibration, the paths' figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from celld import sealed
from celld.calib.mount import ScannerMount, mount_entry
from celld.config import parse
from celld.daemon.store import current_calibration, site_bound
from celld.daemon.weld import resolve_workpiece
from celld.errors import JobError
from celld.seam.workpiece import v_groove_butt


def test_parts_resolve_from_the_examples_or_the_workpiece_dir(tmp_path: Path) -> None:
    cfg = parse({"weld": {"workpiece": "fillet-t"}})
    assert resolve_workpiece("", cfg).name == "fillet-t"  # the cell's default
    assert resolve_workpiece("v-groove", cfg).name == "v-groove"
    with pytest.raises(JobError, match="no workpiece named"):
        resolve_workpiece("", parse({}))
    with pytest.raises(JobError, match="workpiece_dir is not set"):
        resolve_workpiece("bracket", cfg)
    d = tmp_path / "parts"
    d.mkdir()
    with_dir = parse({"weld": {"workpiece_dir": str(d), "workpiece_units": "m"}})
    with pytest.raises(JobError, match="holds no bracket"):
        resolve_workpiece("bracket", with_dir)
    with pytest.raises(JobError, match="plain model name"):
        resolve_workpiece("../etc/passwd", with_dir)
    # A user part: the V-groove's mesh written as STL with a JSON seam file, both in metres.
    import open3d as o3d

    wp = v_groove_butt()
    o3d.io.write_triangle_mesh(str(d / "bracket.stl"), wp.mesh())
    (d / "bracket.seam.json").write_text(json.dumps({"units": "m", "points": wp.seam.tolist()}))
    part = resolve_workpiece("bracket", with_dir)
    assert part.name == "bracket" and np.allclose(part.seam, wp.seam)
    # The same seam read as millimetres lies off the part: refused with the reason.
    (d / "bracket.seam.json").write_text(json.dumps({"units": "mm", "points": wp.seam.tolist()}))
    with pytest.raises(JobError, match="cannot be used"):
        resolve_workpiece("bracket", with_dir)


def test_a_weld_needs_a_usable_current_calibration(tmp_path: Path) -> None:
    with pytest.raises(JobError, match="no current calibration"):
        current_calibration(tmp_path)
    sealed.write_sealed(tmp_path / "calibration.json", {"job": "j1", "T_base_cam": [[1, 0, 0], [0, 1, 0]]}, "calibration")
    with pytest.raises(JobError, match="unusable"):
        current_calibration(tmp_path)
    T = np.eye(4)
    T[:3, 3] = [0.6, 0.0, 1.0]
    # Without a range bias (structured light, or a calibration from before it): none.
    sealed.write_sealed(tmp_path / "calibration.json", {"job": "j2", "T_base_cam": T.tolist()}, "calibration")
    placed, bias, job, bound = current_calibration(tmp_path)
    assert job == "j2" and np.allclose(placed.T_base_cam(None), T) and bias == 0.0
    assert bound is None  # it stores no bound
    # A time-of-flight calibration's range bias comes in metres.
    sealed.write_sealed(tmp_path / "calibration.json", {"job": "j3", "T_base_cam": T.tolist(), "range_bias_mm": 8.1}, "calibration")
    assert current_calibration(tmp_path)[1] == pytest.approx(0.0081)
    # A value no calibration job writes is refused, not applied to a scan, even in a file that is sealed.
    for bad in ("8", None, 1e4, True):
        sealed.write_sealed(tmp_path / "calibration.json", {"job": "j4", "T_base_cam": T.tolist(), "range_bias_mm": bad}, "calibration")
        with pytest.raises(JobError, match="range_bias_mm"):
            current_calibration(tmp_path)
    # json reads NaN too: a file holding one was not written by celld.
    (tmp_path / "calibration.json").write_text('{"format": "celld.calibration/1", "sha256": "", "job": "j5", "range_bias_mm": NaN}')
    with pytest.raises(JobError, match="the stored calibration is damaged: holds a value JSON does not"):
        current_calibration(tmp_path)


def test_a_calibration_is_used_only_with_the_scanner_mount_it_was_made_for(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, 3] = [-0.578, 0.82, 0.162]
    on_arm = ScannerMount.of("link1", "ur10e")
    sealed.write_sealed(tmp_path / "calibration.json", {"job": "j1", **mount_entry(on_arm, T)}, "calibration")
    with pytest.raises(JobError, match="a scanner on link1, and scanner.mount is 'base'"):
        current_calibration(tmp_path)
    placed = current_calibration(tmp_path, "link1").placement
    q = np.array([2.8, -1.4, 2.3, -2.5, 1.6, -1.3])
    np.testing.assert_allclose(placed.T_base_cam(q), on_arm.T_base_link(q) @ T, atol=1e-15)
    sealed.write_sealed(tmp_path / "calibration.json", {"job": "j2", "T_base_cam": T.tolist()}, "calibration")
    with pytest.raises(JobError, match="a scanner on base, and scanner.mount is 'link1'"):
        current_calibration(tmp_path, "link1")


def test_the_bound_at_the_weld_is_the_arm_fits_when_there_is_one_else_the_quality_s() -> None:
    quality = {"quality": {"bound": {"work_radius_mm": 0.9}}}
    assert site_bound(quality) == pytest.approx(0.9e-3)
    assert site_bound({**quality, "arm": {"bound": {"away_mm": 0.25}}}) == pytest.approx(0.25e-3)
    # An arm fit with no bound of its own is not covered by the hand-eye fit's: no bound, not the wrong one.
    assert site_bound({**quality, "arm": {}}) is None
    for bad in (-0.1, float("inf"), float("nan"), True, "0.9", None):
        assert site_bound({"quality": {"bound": {"work_radius_mm": bad}}}) is None
    assert site_bound({}) is None


def test_a_weld_takes_the_measured_tip_and_refuses_an_unmeasured_tool_unless_nominal(tmp_path: Path) -> None:
    from celld.config import ToolConfig
    from celld.daemon.store import current_tool, tool_store

    required = parse({"tool": {"tip_tcp_mm": [0, 0, 200]}}).tool
    assert required.measured == "required"
    with pytest.raises(JobError, match='tool.measured = "nominal"'):
        current_tool(tmp_path, required)
    nominal = parse({"tool": {"tip_tcp_mm": [0, 0, 200], "measured": "nominal"}}).tool
    assert current_tool(tmp_path, nominal) == (nominal, "", 0.0, False, 0.0)
    store = tool_store(tmp_path)
    quality = {"verdict": "poor_data", "reasons": ["RMS residual 0.5 mm exceeds 0.3 mm"]}
    store.add_candidate("t1", {"job": "t1", "tip_tcp_mm": [0.8, -1.1, 200.9], "quality": quality})
    with pytest.raises(JobError, match="poor_data: RMS residual"):
        store.accept("t1")
    store.accept("t1", force=True)
    tool, job, yaw, torch_measured, _ = current_tool(tmp_path, required)
    assert job == "t1" and tool.tip_tcp == pytest.approx((0.8e-3, -1.1e-3, 0.2009))
    assert tool == ToolConfig(tip_tcp=tool.tip_tcp) and (yaw, torch_measured) == (0.0, False)  # only the tip changes
    sealed.write_sealed(tmp_path / "tool.json", {"job": "t2", "tip_tcp_mm": [0.0, "x", 200.0]}, "tool-calibration")
    with pytest.raises(JobError, match="unusable"):
        current_tool(tmp_path, nominal)


def test_a_weld_takes_a_measured_torch_for_the_tool_x_axis_and_offset(tmp_path: Path) -> None:
    from celld.daemon.store import current_tool, tool_store

    required = parse({"tool": {"tip_tcp_mm": [0, 0, 200]}}).tool
    store = tool_store(tmp_path)
    ok = {"verdict": "ok", "reasons": []}
    # The torch 0.9 mm to the tool's -y of where the config puts it (TCP y = tool -y with the default axes).
    entry = {"job": "t3", "tip_tcp_mm": [0.0, 0.0, 200.0], "torch_measured": True, "torch_tcp_mm": [-30.0, 0.9, 200.0], "quality": ok}
    store.add_candidate("t3", entry)
    store.accept("t3")
    got = current_tool(tmp_path, required)
    assert got.job == "t3" and got.torch_measured
    assert got.tool.torch_offset == pytest.approx(np.hypot(30.0, 0.9) * 1e-3)
    np.testing.assert_allclose(got.tool.tool_x_tcp, np.array([30.0, -0.9, 0.0]) / np.hypot(30.0, 0.9))
    assert abs(got.sensor_yaw) == pytest.approx(np.arctan2(0.9, 30.0))
    # A stored torch that no tool can have is refused, naming it; one not measured leaves the torch as configured.
    sealed.write_sealed(tmp_path / "tool.json", {**entry, "torch_tcp_mm": [-30.0, 9.0, 200.0]}, "tool-calibration")
    with pytest.raises(JobError, match="t3 is unusable: measured torch: -16.7 deg"):
        current_tool(tmp_path, required)
    sealed.write_sealed(tmp_path / "tool.json", {**entry, "torch_tcp_mm": [-30.0, None, 200.0]}, "tool-calibration")
    with pytest.raises(JobError, match="torch_tcp_mm"):
        current_tool(tmp_path, required)
    sealed.write_sealed(tmp_path / "tool.json", {**entry, "torch_measured": False}, "tool-calibration")
    assert current_tool(tmp_path, required) == (required, "t3", 0.0, False, 0.0)
    # The wire's end 0.7 mm nearer the flange than the tip (the finger points down the TCP's z): 0.7 mm above it.
    sealed.write_sealed(tmp_path / "tool.json", {**entry, "torch_tcp_mm": [-30.0, 0.9, 199.3]}, "tool-calibration")
    assert current_tool(tmp_path, required).torch_height == pytest.approx(0.7e-3)


def test_a_measured_finger_gain_is_kept_sealed_for_its_tool_calibration_and_refused_when_it_cannot_be_used(tmp_path: Path) -> None:
    from celld.daemon.store import FINGER, store_finger, stored_finger
    from celld.tactile.fingermap import FingerGain

    assert stored_finger(tmp_path, "t1", 1.5e-3) == (None, "no probed weld has measured it yet")
    reading = {"measured": True, "gain": 1.104, "gain_sigma": 0.02, "cubic_per_mm2": 0.04, "residual_rms_um": 7.5, "frames": 44}
    store_finger(tmp_path, "w1", "t1", reading)
    kept, why = stored_finger(tmp_path, "t1", 1.5e-3)
    assert why == "" and kept is not None and kept.job == "w1" and kept.gain_sigma == 0.02
    assert kept.finger == FingerGain(1.104, pytest.approx(0.04e6))
    # Another tool calibration (the finger may be another): not used.
    none, why = stored_finger(tmp_path, "t2", 1.5e-3)
    assert none is None and "tool calibration 't1', not the current 't2'" in why
    # Edited on disk: damaged, said, not used.
    doc = json.loads((tmp_path / FINGER).read_text())
    doc["gain"] = 1.3
    (tmp_path / FINGER).write_text(json.dumps(doc))
    none, why = stored_finger(tmp_path, "t1", 1.5e-3)
    assert none is None and "checksum" in why
    # Sealed but no finger's: refused where it is read.
    for bad in (0.3, "1.1", None):
        sealed.write_sealed(tmp_path / FINGER, {**doc, "gain": bad}, "finger", "w2")
        none, why = stored_finger(tmp_path, "t1", 1.5e-3)
        assert none is None and "unusable" in why, why
