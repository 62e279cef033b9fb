"""Config loading: good files load into frozen values, bad ones name file, key and reason."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

from celld import config
from celld.errors import ConfigError

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", ["sim-cell.toml", "cell.toml"])
def test_shipped_configs_load(name: str) -> None:
    cfg = config.load(CONFIGS / name)
    assert cfg.robot.frequency_hz == 500.0
    assert cfg.motion.max_linear_speed == pytest.approx(0.25)


def test_units_are_converted_at_the_boundary() -> None:
    cfg = config.parse({"calibration": {"e_required_mm": 0.3, "max_tilt_deg": 18.0}, "tactile": {"delta_d_mm": 1.5}})
    assert cfg.calibration.e_required == pytest.approx(0.0003)
    assert cfg.calibration.max_tilt == pytest.approx(math.radians(18.0))
    assert cfg.tactile.delta_d == pytest.approx(0.0015)


def test_dataset_retention_keys() -> None:
    cal = config.parse({"calibration": {"keep_sessions": 3, "keep_days": 14}}).calibration
    assert (cal.keep_sessions, cal.keep_days) == (3, 14.0)
    default = config.parse({}).calibration
    assert (default.keep_sessions, default.keep_days) == (10, 0.0)


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
        ({"tactile": {"intrinsics_px": [1, 2, 3]}}, "tactile.intrinsics_px", "list of 4"),
        ({"bus": {"users": [{"name": "a", "password": "b", "role": "admin"}]}}, "bus.users[0].role", "operator"),
        ({"cell": {"name": "a/b"}}, "cell.name", "zenoh key"),
        ({"calibration": {"keep_sessions": -1}}, "calibration.keep_sessions", "0 <= value"),
        ({"calibration": {"keep_days": -0.5}}, "calibration.keep_days", "0.0 <= value"),
        ({"calibration": {"keep_days": "a week"}}, "calibration.keep_days", "expected a number"),
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
