"""Weld procedures read from their TOML files: the examples load in SI, every bad file or name is refused naming the key."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from typing import Any

import pytest

from celld.bus.checker import validate
from celld.errors import ConfigError
from celld.weld.procedure import (
    MAX_FILE_BYTES,
    PROCEDURE_SCHEMA,
    cell_procedures,
    list_procedures,
    load_procedure,
)

PROCEDURES = Path(__file__).resolve().parents[2] / "configs" / "procedures"
SHORT = "steel-1.0mm-mag-short"
SPRAY = "steel-1.2mm-mag-spray"


def _write(directory: Path, name: str, data: dict[str, Any]) -> Path:
    """``data`` as a flat TOML file ``<name>.toml`` (JSON's strings, numbers, booleans and lists are TOML's)."""
    path = directory / f"{name}.toml"
    path.write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in data.items()), encoding="utf-8")
    return path


def _example(name: str = SHORT) -> dict[str, Any]:
    return tomllib.loads((PROCEDURES / f"{name}.toml").read_text(encoding="utf-8"))


def test_the_examples_load_in_si() -> None:
    assert list_procedures(PROCEDURES) == [SHORT, SPRAY]
    short = load_procedure(PROCEDURES, SHORT)
    assert short.ident == f"{SHORT}@2" and short.process == "MAG"
    assert short.wire_feed == pytest.approx(5.0 / 60.0)  # 5 m/min
    assert short.travel_speed == pytest.approx(0.006)  # 6 mm/s
    assert short.backoff == pytest.approx(0.005)  # 5 mm
    assert short.voltage == 18.0 and short.current_window == (110.0, 175.0)
    assert short.crater_wire_feed == pytest.approx(3.5 / 60.0) and short.crater_voltage == 16.5
    spray = load_procedure(PROCEDURES, SPRAY)
    assert spray.wire_feed == pytest.approx(10.0 / 60.0) and spray.arc_loss == "retract"
    assert spray.current_window[0] > short.current_window[1]  # spray runs well above short arc
    assert len(spray.digest) == 64 and spray.digest != short.digest


def test_as_dict_is_the_shape_it_promises_and_json_ready() -> None:
    procedure = load_procedure(PROCEDURES, SPRAY)
    d = procedure.as_dict()
    validate(PROCEDURE_SCHEMA, d)
    assert json.loads(json.dumps(d)) == d
    assert d["ident"] == f"{SPRAY}@2"
    assert d["wire_feed_m_s"] == pytest.approx(10.0 / 60.0) and d["travel_speed_m_s"] == pytest.approx(0.009)
    assert d["current_window_a"] == [250.0, 310.0] and d["voltage_window_v"] == [26.0, 31.0]


def test_the_crater_runs_at_the_main_set_points_unless_it_names_its_own(tmp_path: Path) -> None:
    data = _example()
    del data["crater_wire_feed_m_min"], data["crater_voltage_v"]
    _write(tmp_path, SHORT, data)
    procedure = load_procedure(tmp_path, SHORT)
    assert procedure.crater_wire_feed == procedure.wire_feed and procedure.crater_voltage == procedure.voltage


def test_the_sequence_takes_its_defaults_when_left_out(tmp_path: Path) -> None:
    keep = ("name", "version", "process", "wire_feed_m_min", "voltage_v", "travel_speed_mm_s", "current_window_a", "voltage_window_v")
    _write(tmp_path, SHORT, {k: v for k, v in _example().items() if k in keep})
    procedure = load_procedure(tmp_path, SHORT)
    assert (procedure.window_grace, procedure.backoff, procedure.arc_loss) == (0.3, pytest.approx(0.005), "retract")
    assert procedure.description == ""


def test_the_digest_tells_an_edited_file_from_the_same_version(tmp_path: Path) -> None:
    data = _example()
    _write(tmp_path, SHORT, data)
    before = load_procedure(tmp_path, SHORT)
    _write(tmp_path, SHORT, {**data, "voltage_v": 18.5})
    after = load_procedure(tmp_path, SHORT)
    assert after.ident == before.ident and after.digest != before.digest


def test_values_are_frozen() -> None:
    procedure = load_procedure(PROCEDURES, SHORT)
    with pytest.raises(dataclasses.FrozenInstanceError):
        procedure.voltage = 30.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("change", "key", "reason"),
    [
        ({"wire_feed_m_min": "5"}, "wire_feed_m_min", "expected a number"),
        ({"voltage_v": True}, "voltage_v", "expected a number"),
        ({"version": 1.5}, "version", "expected an integer"),
        ({"version": 0}, "version", "expected 1 <= value"),
        ({"wire_feed_m_min": 30.0}, "wire_feed_m_min", "expected 0.5 <= value <= 25.0, got 30.0"),
        ({"wire_feed_m_min": 0.1}, "wire_feed_m_min", "expected 0.5 <= value"),
        ({"voltage_v": 55.0}, "voltage_v", "<= 50.0, got 55.0"),
        ({"travel_speed_mm_s": 40.0}, "travel_speed_mm_s", "<= 30.0"),
        ({"strike_timeout_s": 0.0}, "strike_timeout_s", "expected 0.05 <= value"),
        ({"restrikes": 6}, "restrikes", "<= 5"),
        ({"backoff_mm": 12.0}, "backoff_mm", "<= 10.0"),
        ({"window_grace_s": 3.0}, "window_grace_s", "<= 2.0"),
        ({"crater_voltage_v": 2.0}, "crater_voltage_v", "expected 5.0 <= value"),
        ({"process": "SMAW"}, "process", "expected one of MAG, MIG, TIG, got 'SMAW'"),
        ({"arc_loss": "ignore"}, "arc_loss", "expected one of restrike, retract"),
        ({"current_window_a": [175.0, 110.0]}, "current_window_a", "lo below hi"),
        ({"current_window_a": [150.0, 150.0]}, "current_window_a", "lo below hi"),
        ({"current_window_a": [5.0, 175.0]}, "current_window_a", "within 10-600 A"),
        ({"voltage_window_v": [15.0, 70.0]}, "voltage_window_v", "within 5-60 V"),
        ({"voltage_window_v": [15.0]}, "voltage_window_v", "expected a list of 2 numbers"),
        ({"name": "other"}, "name", f"expected the file's name {SHORT!r}, got 'other'"),
        ({"colour": "blue"}, "colour", "unknown key"),
        # A quantity in another unit than its key's: refused naming the key to write.
        ({"travel_speed_m_s": 0.006}, "travel_speed_m_s", "expected travel_speed_mm_s (in mm/s)"),
        ({"wire_feed": 5.0}, "wire_feed", "expected wire_feed_m_min (in m/min)"),
        ({"crater_wire_feed_m_s": 0.06}, "crater_wire_feed_m_s", "expected crater_wire_feed_m_min (in m/min)"),
        ({"preflow_ms": 300}, "preflow_ms", "expected preflow_s (in s)"),
        ({"current_window_ka": [0.11, 0.175]}, "current_window_ka", "expected current_window_a (in A)"),
    ],
)
def test_a_bad_value_is_refused_naming_the_file_and_the_key(tmp_path: Path, change: dict[str, Any], key: str, reason: str) -> None:
    path = _write(tmp_path, SHORT, {**_example(), **change})
    with pytest.raises(ConfigError) as info:
        load_procedure(tmp_path, SHORT)
    assert info.value.source == str(path)
    assert info.value.key == key
    assert reason in info.value.reason
    assert f"{path}: {key}: " in str(info.value)


@pytest.mark.parametrize("key", ["name", "version", "process", "wire_feed_m_min", "voltage_v", "current_window_a"])
def test_a_required_key_left_out_is_refused(tmp_path: Path, key: str) -> None:
    data = _example()
    del data[key]
    _write(tmp_path, SHORT, data)
    with pytest.raises(ConfigError) as info:
        load_procedure(tmp_path, SHORT)
    assert (info.value.key, info.value.reason) == (key, "required key is missing")


@pytest.mark.parametrize("name", ["../cell", "sub/steel", "/etc/passwd", "steel\\x", "..", ".hidden", "-x", "a b", "", "steel@2"])
def test_a_name_that_is_not_a_plain_file_stem_is_refused(tmp_path: Path, name: str) -> None:
    (tmp_path / "sub").mkdir()
    _write(tmp_path / "sub", "steel", {**_example(), "name": "steel"})  # a file the path would reach
    with pytest.raises(ConfigError, match="expected a plain file stem") as info:
        load_procedure(tmp_path, name)
    assert info.value.source == str(tmp_path) and repr(name) in info.value.reason


def test_a_name_given_with_its_suffix_is_refused_saying_so(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"give the name without \.toml"):
        load_procedure(PROCEDURES, f"{SHORT}.toml")


def test_a_missing_procedure_names_the_directory_and_lists_those_there() -> None:
    with pytest.raises(ConfigError) as info:
        load_procedure(PROCEDURES, "aluminium-1.2mm-mig")
    assert info.value.source == str(PROCEDURES)
    assert "no procedure 'aluminium-1.2mm-mig'" in info.value.reason
    assert f"the procedures here: {SHORT}, {SPRAY}" in info.value.reason


def test_a_missing_procedure_in_an_empty_or_absent_directory_says_which(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="there are no procedures here"):
        load_procedure(tmp_path, SHORT)
    with pytest.raises(ConfigError, match="the procedures directory does not exist"):
        load_procedure(tmp_path / "nowhere", SHORT)
    assert list_procedures(tmp_path / "nowhere") == []


def test_a_file_over_the_size_limit_is_refused_before_it_is_parsed(tmp_path: Path) -> None:
    path = tmp_path / f"{SHORT}.toml"
    path.write_bytes(b"# " + b"x" * MAX_FILE_BYTES + b"\n")
    with pytest.raises(ConfigError, match=f"a procedure file is at most {MAX_FILE_BYTES} bytes"):
        load_procedure(tmp_path, SHORT)


def test_a_directory_of_the_name_and_bad_toml_are_refused(tmp_path: Path) -> None:
    (tmp_path / "dir.toml").mkdir()
    with pytest.raises(ConfigError, match="not a regular file"):
        load_procedure(tmp_path, "dir")
    (tmp_path / "broken.toml").write_text("name = \n", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_procedure(tmp_path, "broken")
    assert list_procedures(tmp_path) == ["broken"]  # the directory named *.toml is not a procedure


def test_a_cells_procedures_sit_beside_its_config_file() -> None:
    assert cell_procedures(Path("/etc/celld/cell.toml")) == Path("/etc/celld/procedures")
