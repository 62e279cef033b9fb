"""Config loading: good files load into frozen values, bad ones name file, key and reason."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import pytest

from celld import config
from celld.errors import ConfigError

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", ["sim-cell.toml", "sim-cell-power-source.toml", "cell.toml"])
def test_shipped_configs_load(name: str) -> None:
    cfg = config.load(CONFIGS / name)
    assert cfg.robot.frequency_hz == 500.0
    assert cfg.motion.max_linear_speed == pytest.approx(0.25)


def test_units_are_converted_at_the_boundary() -> None:
    cfg = config.parse({"calibration": {"e_required_mm": 0.3, "max_tilt_deg": 18.0, "settle_s": 0.5}, "servo": {"delta_d_mm": 1.5}})
    assert cfg.calibration.e_required == pytest.approx(0.0003)
    assert cfg.calibration.max_tilt == pytest.approx(math.radians(18.0))
    assert cfg.calibration.settle == pytest.approx(0.5)
    assert cfg.servo.delta_d == pytest.approx(0.0015)


@pytest.mark.parametrize(
    ("data", "key", "new"),
    [
        ({"calibration": {"settle": 0.3}}, "calibration.settle", "calibration.settle_s"),
        ({"robot": {"connect_timeout": 3}}, "robot.connect_timeout", "robot.connect_timeout_s"),
        ({"scanner": {"capture_timeout": 3}}, "scanner.capture_timeout", "scanner.capture_timeout_s"),
        ({"bus": {"query_timeout": 3}}, "bus.query_timeout", "bus.query_timeout_s"),
        ({"tactile": {"delta_d_mm": 1.5}}, "tactile.delta_d_mm", "[servo] delta_d_mm"),
        ({"tactile": {"tip_tcp_mm": [0, 0, 200]}}, "tactile.tip_tcp_mm", "[tool] tip_tcp_mm"),
        ({"seam": {"finger_wall": "left"}}, "seam.finger_wall", "[tool] wall_side"),
    ],
)
def test_renamed_and_moved_keys_are_refused_naming_the_new_key(data: dict, key: str, new: str) -> None:
    with pytest.raises(ConfigError) as info:
        config.parse(data, "old.toml")
    assert info.value.key == key
    assert f"this key is now {new}" in info.value.reason


def test_the_seam_finder_takes_the_scanner_preset_and_the_tool_wall() -> None:
    cfg = config.parse({"scanner": {"model": "azure-kinect"}, "tool": {"wall_side": "right"}, "seam": {"spacing_mm": 2}})
    assert cfg.seam.finger_wall == "right"
    assert cfg.seam.spacing == pytest.approx(0.002)
    assert cfg.seam.registration.voxel == pytest.approx(0.005)  # the Azure Kinect preset
    assert config.parse({}).seam.registration.voxel == pytest.approx(0.004)


def test_dataset_retention_keys() -> None:
    cal = config.parse({"calibration": {"keep_sessions": 3, "keep_days": 14}}).calibration
    assert (cal.keep_sessions, cal.keep_days) == (3, 14.0)
    default = config.parse({}).calibration
    assert (default.keep_sessions, default.keep_days) == (10, 0.0)


@pytest.mark.parametrize(
    ("scanner", "expected"),
    [
        ({}, "none"),  # the simulated PhoXi M: structured light
        ({"kind": "phoxi", "model": "phoxi-s"}, "none"),
        ({"model": "azure-kinect"}, "estimate"),  # a simulated Azure Kinect
        ({"kind": "azure-kinect", "model": "azure-kinect"}, "estimate"),
        ({"kind": "realsense"}, "estimate"),
    ],
)
def test_the_range_bias_is_estimated_by_default_for_time_of_flight_scanners(scanner: dict, expected: str) -> None:
    assert config.parse({"scanner": scanner}).calibration.range_bias == expected
    # The config's choice wins either way.
    other = "none" if expected == "estimate" else "estimate"
    assert config.parse({"scanner": scanner, "calibration": {"range_bias": other}}).calibration.range_bias == other


@pytest.mark.parametrize("value", ["auto", "yes", 1, True])
def test_a_range_bias_setting_that_is_not_a_mode_is_refused_with_the_choices(value: object) -> None:
    with pytest.raises(ConfigError) as info:
        config.parse({"scanner": {"model": "azure-kinect"}, "calibration": {"range_bias": value}}, "cell.toml")
    assert info.value.key == "calibration.range_bias"
    if isinstance(value, str):
        assert info.value.reason == f"expected one of estimate, none, got {value!r}"
    else:
        assert info.value.reason.startswith("expected a string")


def test_the_seam_region_of_interest_can_be_narrowed_and_is_checked() -> None:
    cfg = config.parse({"scanner": {"model": "azure-kinect"}, "seam": {"roi_min": [0.3, -0.35, -0.05], "roi_max": [0.9, 0.35, 0.3]}})
    assert cfg.seam.roi_min == (0.3, -0.35, -0.05) and cfg.seam.roi_max == (0.9, 0.35, 0.3)
    assert config.parse({}).seam.roi_min == (-0.2, -1.0, -0.1)  # the preset's
    with pytest.raises(ConfigError) as info:
        config.parse({"seam": {"roi_min": [0.3, -0.35, -0.05], "roi_max": [0.9, -0.4, 0.3]}})
    assert info.value.key == "seam.roi_max" and "above roi_min" in info.value.reason
    with pytest.raises(ConfigError) as info:
        config.parse({"seam": {"roi_min": [300, -350, -50]}})  # millimetres
    assert info.value.key == "seam.roi_min" and "within +-5" in info.value.reason


def test_values_are_frozen() -> None:
    cfg = config.parse({})
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.robot.host = "10.0.0.1"  # type: ignore[misc]


@pytest.mark.parametrize(
    ("data", "key", "reason"),
    [
        ({"robot": {"hots": "x"}}, "robot.hots", "unknown key"),
        ({"robt": {}}, "robt", "unknown key"),
        ({"robot": {"frequency_hz": "fast"}}, "robot.frequency_hz", "expected a number"),
        ({"robot": {"frequency_hz": 2000}}, "robot.frequency_hz", "<= 500"),
        ({"motion": {"max_linear_speed": 0}}, "motion.max_linear_speed", "0.0 < value"),
        ({"robot": {"workspace_min": [0, 0, 0], "workspace_max": [1, -1, 1]}}, "robot.workspace_max", "above"),
        ({"scanner": {"kind": "kinect"}}, "scanner.kind", "expected one of"),
        ({"scanner": {"T_base_cam": [[1, 0], [0, 1]]}}, "scanner.T_base_cam", "4x4"),
        ({"scanner": {"mount": "wrist"}}, "scanner.mount", "expected one of"),
        ({"tactile": {"intrinsics_px": [1, 2, 3]}}, "tactile.intrinsics_px", "list of 4"),
        ({"bus": {"users": [{"name": "a", "password": "b", "role": "admin"}]}}, "bus.users[0].role", "operator"),
        ({"cell": {"name": "a/b"}}, "cell.name", "zenoh key"),
        # Semantics: what a cell can physically be.
        ({"robot": {"workspace_min": [-1e9, -1, 0], "workspace_max": [1, 1, 1]}}, "robot.workspace_min", "within +-5 m"),
        ({"robot": {"home_q": [0, 0, 100, 0, 0, 0]}}, "robot.home_q", "+-360 deg"),
        ({"robot": {"tcp_offset": [0, 0, 2.5, 0, 0, 0]}}, "robot.tcp_offset", "within 1 m of the flange"),
        ({"robot": {"host": "robot controller"}}, "robot.host", "IP address or a host name"),
        ({"robot": {"host": "999.1.1.1"}}, "robot.host", "IP address or a host name"),
        ({"cell": {"state_dir": ""}}, "cell.state_dir", "empty path"),
        ({"cell": {"state_dir": "/proc/celld"}}, "cell.state_dir", "kernel file system"),
        ({"calibration": {"verification_pose": [3.0, 0, 0.45, 0, 0, 0]}}, "calibration.verification_pose", "inside the workspace box"),
        ({"weld": {"scan_pose": [0.5, 0.0, 1.9, 0, 0, 0]}}, "weld.scan_pose", "inside the workspace box"),
        ({"servo": {"v_const_mm_s": 300}}, "servo.v_const_mm_s", "motion.max_linear_speed (250 mm/s)"),
        ({"calibration": {"keep_sessions": -1}}, "calibration.keep_sessions", "0 <= value"),
        ({"calibration": {"keep_days": -0.5}}, "calibration.keep_days", "0.0 <= value"),
        ({"calibration": {"keep_days": "a week"}}, "calibration.keep_days", "expected a number"),
        # A hung daemon stops a weld within 0.3 s; at rest its children wait at most 5 s for it.
        ({"motion": {"parent_timeout_ms": 10_000}}, "motion.parent_timeout_ms", "<= 5000"),
        ({"motion": {"hang_stop_ms": 2000}}, "motion.hang_stop_ms", "<= 270"),
    ],
)
def test_bad_values_are_refused_with_key_and_reason(data: dict, key: str, reason: str) -> None:
    with pytest.raises(ConfigError) as info:
        config.parse(data, "test.toml")
    assert info.value.key == key
    assert reason in info.value.reason
    assert str(info.value).startswith(f"test.toml: {key}:")


def test_bad_toml_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[robot\nhost = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML") as info:
        config.load(bad)
    assert info.value.source == str(bad)


def test_missing_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        config.load(tmp_path / "absent.toml")


def test_includes_merge_and_cycles_are_refused(tmp_path: Path) -> None:
    (tmp_path / "base.toml").write_text('[robot]\nhost = "127.0.0.9"\nfrequency_hz = 125\n')
    (tmp_path / "top.toml").write_text('include = ["base.toml"]\n[robot]\nfrequency_hz = 250\n')
    cfg = config.load(tmp_path / "top.toml")
    assert cfg.robot.host == "127.0.0.9"
    assert cfg.robot.frequency_hz == 250.0
    (tmp_path / "a.toml").write_text('include = ["b.toml"]\n')
    (tmp_path / "b.toml").write_text('include = ["a.toml"]\n')
    with pytest.raises(ConfigError, match="include cycle"):
        config.load(tmp_path / "a.toml")
    # A symlink loop is a ConfigError, not a crash.
    (tmp_path / "l1.toml").symlink_to(tmp_path / "l2.toml")
    (tmp_path / "l2.toml").symlink_to(tmp_path / "l1.toml")
    (tmp_path / "loop.toml").write_text('include = ["l1.toml"]\n')
    with pytest.raises(ConfigError) as info:
        config.load(tmp_path / "loop.toml")
    assert info.value.key == "include"
    # The config file itself a symlink loop: refused, naming it.
    with pytest.raises(ConfigError, match="symlink loop") as info:
        config.load(tmp_path / "l1.toml")
    assert info.value.source == str(tmp_path / "l1.toml")


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom"])
def test_an_include_of_a_device_is_refused_before_a_byte_is_read(tmp_path: Path, device: str) -> None:
    (tmp_path / "top.toml").write_text(f'include = ["{device}"]\n')
    with pytest.raises(ConfigError, match="not a regular file") as info:
        config.load(tmp_path / "top.toml")
    assert info.value.source == device


def test_a_config_file_too_large_or_empty_is_refused(tmp_path: Path) -> None:
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (config.cell.MAX_FILE_BYTES + 10) + "\n")
    with pytest.raises(ConfigError, match=r"bytes: a config file is at most"):
        config.load(big)
    (tmp_path / "top.toml").write_text('include = ["big.toml"]\n[robot]\nhost = "127.0.0.9"\n')
    with pytest.raises(ConfigError, match=r"bytes: a config file is at most") as info:
        config.load(tmp_path / "top.toml")
    assert info.value.source == str(big)
    (tmp_path / "empty.toml").write_text("")
    with pytest.raises(ConfigError, match="the config is empty"):
        config.load(tmp_path / "empty.toml")
    (tmp_path / "comments.toml").write_text("# nothing but a comment\n")
    with pytest.raises(ConfigError, match="the config is empty"):
        config.load(tmp_path / "comments.toml")


def test_preflight_names_unknown_presets_and_unwritable_state(tmp_path: Path) -> None:
    from celld.preflight import preflight

    good = config.parse({"cell": {"state_dir": str(tmp_path / "state")}, "robot": {"host": "127.0.0.9"}})
    assert preflight(good) == []
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    bad = config.parse(
        {
            "cell": {"state_dir": str(ro / "state")},
            "calibration": {"flange": "ur99"},
            "tactile": {"kind": "opencv", "tag_dictionary": "DICT_9X9_7"},
        }
    )
    found = {f.key: f.reason for f in preflight(bad)}
    assert "known presets" in found["calibration.flange"]
    assert "DICT_9X9_7" in found["tactile.tag_dictionary"]
    if os.getuid() != 0:  # root writes anywhere
        assert "not writable" in found["cell.state_dir"]
    (tmp_path / "afile").write_text("")
    on_file = config.parse({"cell": {"state_dir": str(tmp_path / "afile" / "state")}, "robot": {}})
    assert [f.key for f in preflight(on_file)] == ["cell.state_dir"]
    assert "is not a directory" in preflight(on_file)[0].reason


def test_a_daemon_needs_its_robot_and_its_tls_files_and_a_client_needs_no_robot(tmp_path: Path) -> None:
    from celld.preflight import preflight

    client = config.parse({"cell": {"name": "cell-7", "state_dir": str(tmp_path / "state")}, "bus": {"connect": ["tcp/127.0.0.9:7447"]}})
    assert preflight(client, daemon=False) == []
    found = preflight(client)
    assert [f.key for f in found] == ["robot"] and "no [robot] table" in found[0].reason
    tls = {
        "root_ca_certificate": str(tmp_path / "ca.pem"),
        "listen_certificate": str(tmp_path / "cell.pem"),
        "listen_private_key": str(tmp_path / "cell.key"),
    }
    (tmp_path / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\n")
    with_tls = config.parse(
        {"cell": {"state_dir": str(tmp_path / "state")}, "robot": {}, "bus": {"listen": ["tls/127.0.0.9:7447"], "tls": tls}}
    )
    found = {f.key: f.reason for f in preflight(with_tls)}
    assert sorted(found) == ["bus.tls.listen_certificate", "bus.tls.listen_private_key"]
    assert "cannot read" in found["bus.tls.listen_certificate"] and str(tmp_path / "cell.pem") in found["bus.tls.listen_certificate"]


def test_a_tool_of_kilometres_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"tip_tcp_mm.*within 1000 mm of the TCP") as info:
        config.parse({"tool": {"tip_tcp_mm": [2e6, 0.0, 0.0]}})
    assert info.value.key == "tool.tip_tcp_mm"
    with pytest.raises(ConfigError, match="within 1 m of the tool frame") as info:
        config.parse({"tool": {"T_tool_cam": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2000.0], [0, 0, 0, 1]]}})
    assert info.value.key == "tool.T_tool_cam"
    with pytest.raises(ConfigError, match="tcp_offset"):
        config.parse({"robot": {"tcp_offset": [0.0, 0.0, 2000.0, 0.0, 0.0, 0.0]}})


def test_a_jobs_servo_overrides_are_held_to_the_configs_rules() -> None:
    cfg = config.parse({})
    servo, tool = config.with_overrides(cfg.servo, cfg.tactile, cfg.tool, "weld job", delta_d=0.002, v_const=None, torch_offset=0.04)
    assert (servo.delta_d, servo.v_const, tool.torch_offset) == (0.002, cfg.servo.v_const, 0.04)
    # 20 mm is inside the field's own range but beyond the sensor's 4 mm overload level.
    with pytest.raises(ConfigError, match="delta_d_mm < tactile.overload_mm") as info:
        config.with_overrides(cfg.servo, cfg.tactile, cfg.tool, "weld job", delta_d=0.020)
    assert info.value.key == "servo.delta_d_mm"
    with pytest.raises(ConfigError, match="0 < value <= 500") as info:
        config.with_overrides(cfg.servo, cfg.tactile, cfg.tool, "weld job", v_const=0.0)
    assert info.value.key == "servo.v_const_mm_s"
    # Within the field's range, above the cell's motion limit.
    with pytest.raises(ConfigError, match=r"at most motion.max_linear_speed \(250 mm/s\)") as info:
        config.with_overrides(cfg.servo, cfg.tactile, cfg.tool, "weld job", cfg.motion.max_linear_speed, v_const=0.3)
    assert info.value.key == "servo.v_const_mm_s"


ROBOT2 = {"host": "127.0.0.3", "base_pose": [1.25, 0.0, 0.0, 0.0, 0.0, math.pi], "home_q": [1.6, -1.1, 2.3, -2.8, 1.57, 0.0]}


def test_a_second_robot_is_read_with_its_own_link_and_checked() -> None:
    assert config.parse({}).robot2 is None
    r2 = config.parse({"robot2": ROBOT2}).robot2
    assert r2 is not None and r2.robot.host == "127.0.0.3" and r2.robot.arc_output == -1 and r2.base_pose[0] == 1.25
    assert r2.robot.home_q == tuple(ROBOT2["home_q"]) and r2.flange == ""
    bad = [
        ({k: v for k, v in ROBOT2.items() if k != "base_pose"}, "robot2.base_pose", "base in robot 1's base frame"),
        ({**ROBOT2, "host": "127.0.0.1"}, "robot2.host", "own address"),
        ({**ROBOT2, "arc_output": 0}, "robot2.arc_output", "no welding tool"),
        ({**ROBOT2, "tcp_offset": [0.0, 0.0, 0.1, 0.0, 0.0, 0.0]}, "robot2.tcp_offset", "must be zero"),
        ({**ROBOT2, "verification_pose": [3.0, 0.0, 0.45, 0.0, 0.0, 0.0]}, "robot2.verification_pose", "workspace box"),
        ({**ROBOT2, "speed": 1}, "robot2.speed", ""),
    ]
    for table, key, why in bad:
        with pytest.raises(ConfigError, match=key.replace(".", r"\.") + ".*" + why):
            config.parse({"robot2": table}, "two.toml")
    with pytest.raises(ConfigError, match=r"robot2: two robots are calibrated through a scanner fixed in the cell"):
        config.parse({"robot2": ROBOT2, "scanner": {"mount": "link1"}})


def test_the_shipped_two_robot_cell_places_its_second_robot_across_the_table() -> None:
    from celld.daemon.arm import robot2_config

    cfg = config.load(Path(__file__).resolve().parents[1] / "configs" / "sim-cell-two-robots.toml")
    assert cfg.robot2 is not None
    seen = robot2_config(cfg)
    assert seen.robot == cfg.robot2.robot and seen.robot2 is None and seen.cell_model.tool == ()
    assert seen.calibration.verification_pose == cfg.robot2.verification_pose
    # The table, 0.6 m in front of robot 1, lies 0.65 m in front of robot 2 (its base 1.25 m away, turned round).
    table = next(o for o in seen.cell_model.objects if o.name == "table")
    assert table.T_base_obj[:3, 3] == pytest.approx([0.65, 0.0, -0.4], abs=1e-6)


_SOURCE = {"arc_start": "do0", "ready": "di0", "arc_stable": "di1"}


def test_a_power_source_is_read_by_role_and_its_analog_ranges_in_si() -> None:
    c = config.parse(
        {"power_source": {**_SOURCE, "gas": "ireg18.1", "wire_stuck": "oreg12.3", "current": "ai0", "current_range": [0, 400]}}
    )
    ps = c.power_source
    assert ps.enabled and str(ps.signal("gas")) == "ireg18.1" and str(ps.signal("wire_stuck")) == "oreg12.3"
    assert ps.range("current") == (0.0, 400.0) and ps.range("voltage") == (0.0, 50.0)
    assert ps.signal("collision") is None
    assert not config.parse({}).power_source.enabled


@pytest.mark.parametrize(
    ("table", "key", "reason"),
    [
        ({"arc_start": "do0", "ready": "di0"}, "power_source.arc_stable", "needs its arc_stable signal"),
        ({**_SOURCE, "arc_start": "di3"}, "power_source.arc_start", "this role takes do, cdo, tdo, ireg"),
        ({**_SOURCE, "arc_stable": "di0"}, "power_source.arc_stable", "already ready's signal"),
        ({**_SOURCE, "gas": "do8"}, "power_source.gas", "do numbers run 0-7"),
        ({**_SOURCE, "gas": "ireg30.0"}, "power_source.gas", "ireg numbers run 18-22"),
        ({**_SOURCE, "fault": "oreg12"}, "power_source.fault", "names its bit"),
        ({**_SOURCE, "fault": "di2.1"}, "power_source.fault", "only ireg and oreg signals have a bit"),
        ({**_SOURCE, "current": "ai0", "current_range": [5, 5]}, "power_source.current_range", "two different values"),
        ({**_SOURCE, "wirefeed": "ao0"}, "power_source.wirefeed", "unknown key"),
    ],
)
def test_a_bad_power_source_is_refused_naming_its_key(table: dict, key: str, reason: str) -> None:
    with pytest.raises(ConfigError) as err:
        config.parse({"power_source": table})
    assert err.value.key == key and reason in err.value.reason


def test_the_arc_has_one_switch() -> None:
    with pytest.raises(ConfigError) as err:
        config.parse({"robot": {"arc_output": 0}, "power_source": _SOURCE})
    assert err.value.key == "robot.arc_output" and "power_source.arc_start" in err.value.reason


@pytest.mark.parametrize(
    "name", ["sim-cell.toml", "sim-cell-power-source.toml", "sim-cell-two-robots.toml", "sim-cell-eye-on-arm.toml", "cell.toml"]
)
def test_config_check_json_is_a_config_file_that_loads_into_the_same_config(name: str, capsys) -> None:
    from celld.cli import main
    from celld.config_cli import plain

    assert main(["config", "check", "--json", str(CONFIGS / name)]) == 0
    printed = json.loads(capsys.readouterr().out)
    loaded = config.load(CONFIGS / name)
    # By the file's own keys and units: every key the parse accepts, and the same config out of it.
    assert printed["calibration"]["e_required_mm"] == pytest.approx(loaded.calibration.e_required * 1e3)
    assert "e_required" not in printed["calibration"]
    assert plain(config.parse(printed, source=str(CONFIGS / name))) == plain(loaded)
