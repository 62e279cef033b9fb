"""`celld sim world`: every error source of a drawn world by name, its budget, what was drawn, its anchor."""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import pytest

from celld.cli import main
from celld.sim.world import ERROR_KEYS, SOURCES, ErrorBudget
from celld.sim.worldreport import ANCHORS, SOURCE_BUDGET

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "sim-cell.toml"


def test_every_source_has_an_anchor_and_every_magnitude_of_the_budget_one_source() -> None:
    assert set(SOURCE_BUDGET) == set(SOURCES) == set(ANCHORS)
    assert all(len(a) > 20 for a in ANCHORS.values())
    named = [m for s in SOURCES for m in SOURCE_BUDGET[s]]
    magnitudes = [f.name for f in fields(ErrorBudget) if f.name != "enabled"]
    assert sorted(named) == sorted(magnitudes) and len(set(named)) == len(named)
    assert set(named) <= set(ERROR_KEYS)


def test_the_world_is_printed_source_by_source_as_drawn_for_its_seed(capsys: pytest.CaptureFixture[str]) -> None:
    def report(*args: str) -> dict:
        assert main(["sim", "world", "--config", str(CONFIG), "--json", *args]) == 0
        return json.loads(capsys.readouterr().out)

    ideal = report("--preset", "ideal", "--world-seed", "3")
    assert [s["name"] for s in ideal["sources"]] == list(SOURCES) and not any(s["on"] for s in ideal["sources"])
    by = {s["name"]: s for s in ideal["sources"]}
    assert by["tag_map"]["drawn"] == {"tag_gain_xy": [1.0, 1.0], "tag_softening_mm": None}
    assert by["scanner_mount"]["drawn"] == {"translation_mm": 0.0, "rotation_deg": 0.0}
    real = report("--preset", "realistic", "--world-seed", "3", "--without", "hose_pull")
    by = {s["name"]: s for s in real["sources"]}
    assert by["tag_map"]["on"] and not by["hose_pull"]["on"] and by["hose_pull"]["drawn"]["force_n"] == [0.0, 0.0, 0.0]
    assert by["tag_map"]["budget"] == {"tag_position": [0.9, 1.0], "tag_anisotropy": 0.02, "tag_softening_mm": [6.0, 12.0]}
    assert all(0.8 < g < 1.0 for g in by["tag_map"]["drawn"]["tag_gain_xy"])
    assert 0.0 < by["scanner_mount"]["drawn"]["translation_mm"] < 20.0
    assert report("--preset", "realistic", "--world-seed", "3") != report("--preset", "realistic", "--world-seed", "4")
    # As text: one line per source, on or off.
    assert main(["sim", "world", "--config", str(CONFIG), "--preset", "realistic", "--world-seed", "3"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("world: preset realistic, seed 3") and "  on  tag_map: " in text
