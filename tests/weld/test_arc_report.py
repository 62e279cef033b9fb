"""What the arc did in a weld, from synthetic motion records with a known answer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from celld.bus.checker import validate
from celld.motion.arc import ArcPhase, params_of, plan_keys
from celld.motion.channels import STATE_DTYPE
from celld.motion.source_io import BIT_ROLES
from celld.weld.arc_report import ARC_SCHEMA, arc_report, known_seam, sequence_of, welded_intervals
from celld.weld.procedure import load_procedure

PROCEDURES = Path(__file__).resolve().parents[2] / "configs" / "procedures"
PERIOD = 0.002
STABLE = 1 << BIT_ROLES.index("arc_stable")
READY = 1 << BIT_ROLES.index("ready")


def _weld(phases: list[tuple[ArcPhase, float, bool, float]], current: float = 140.0, voltage: float = 18.0):
    """Records of a weld along x: (phase, seconds, arc stable, torch speed m/s) per stretch; the torch from x = 0."""
    rows = []
    x = 0.0
    for phase, seconds, stable, v in phases:
        for _ in range(int(round(seconds / PERIOD))):
            rows.append((phase, stable, x))
            x += v * PERIOD
    rec = np.zeros(len(rows), STATE_DTYPE)
    rec["t_ns"] = (np.arange(len(rows)) * PERIOD * 1e9).astype(np.int64)
    rec["arc_phase"] = [r[0] for r in rows]
    rec["source_bits"] = [READY | (STABLE if r[1] else 0) for r in rows]
    rec["weld_current"] = [current if r[1] else 0.0 for r in rows]
    rec["weld_voltage"] = [voltage if r[1] else 0.0 for r in rows]
    torch = np.column_stack([[r[2] for r in rows], np.zeros(len(rows)), np.zeros(len(rows))])
    return rec, torch


SEAM = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]])


def test_a_clean_weld_covers_its_seam_and_ends_done() -> None:
    proc = load_procedure(PROCEDURES, "steel-1.0mm-mag-short")
    rec, torch = _weld(
        [
            (ArcPhase.PREFLOW, 0.3, False, 0.0),
            (ArcPhase.STRIKE, 0.06, False, 0.0),
            (ArcPhase.WELD, 50e-3 / 0.006, True, 0.006),
            (ArcPhase.CRATER, 0.4, True, 0.0),
            (ArcPhase.BURNBACK, 0.04, False, 0.0),
            (ArcPhase.POSTFLOW, 1.0, False, 0.0),
            (ArcPhase.DONE, 0.01, False, 0.0),
        ]
    )
    r = arc_report(rec, torch, SEAM, proc)
    assert r["completed"] and r["ended_in"] == "done" and r["procedure"] == "steel-1.0mm-mag-short@2"
    assert (r["failed_starts"], r["restrikes"], r["arc_losses"]) == (0, 0, 0)
    assert r["welded_mm"] == pytest.approx(50.0, abs=0.05) and r["unwelded_mm"] == pytest.approx(0.0, abs=0.05)
    assert r["unwelded_stretches_mm"] == [] and not r["flagged"]
    assert r["weld_data"]["arc_breaks"] == 0 and r["weld_data"]["arc_time_s"] == pytest.approx(50 / 6 + 0.4, abs=0.01)
    validate(ARC_SCHEMA, r)


def test_a_loss_with_a_backoff_counts_the_overlap_once_and_a_retract_reports_the_rest_unwelded() -> None:
    proc = load_procedure(PROCEDURES, "steel-1.0mm-mag-short")
    rec, torch = _weld(
        [
            (ArcPhase.STRIKE, 0.2, False, 0.0),
            (ArcPhase.PAUSE, 0.5, False, 0.0),  # a failed start
            (ArcPhase.STRIKE, 0.06, False, 0.0),
            (ArcPhase.WELD, 3.0, True, 0.006),  # 18 mm
            (ArcPhase.LOST, 0.1, False, 0.002),  # braking: 0.2 mm without the arc
            (ArcPhase.BACKOFF, 1.0, False, -0.003),  # 3 mm back
            (ArcPhase.PAUSE, 0.5, False, 0.0),
            (ArcPhase.STRIKE, 0.06, False, 0.0),
            (ArcPhase.WELD, 2.0, True, 0.006),  # 12 mm from 15.2 mm: welded to 27.2 mm
            (ArcPhase.LOST, 0.1, False, 0.0),
            (ArcPhase.FAILED, 0.1, False, 0.0),
        ]
    )
    r = arc_report(rec, torch, SEAM, proc)
    assert not r["completed"] and r["ended_in"] == "failed"
    assert (r["failed_starts"], r["restrikes"], r["arc_losses"]) == (1, 2, 2)
    # Welded [0, 18] and [15.2, 27.2] mm: 27.2 mm once; 0.2 mm of braking lies inside the second stretch.
    assert r["welded_mm"] == pytest.approx(27.2, abs=0.05)
    assert r["unwelded_mm"] == pytest.approx(50.0 - 27.2, abs=0.05)
    assert len(r["unwelded_stretches_mm"]) == 1 and r["unwelded_stretches_mm"][0] == pytest.approx([27.2, 50.0], abs=0.05)
    assert r["weld_data"]["arc_breaks"] == 2
    validate(ARC_SCHEMA, r)


def test_a_scratch_start_is_measured_from_where_it_struck_and_its_return_welds() -> None:
    proc = load_procedure(PROCEDURES, "steel-1.0mm-mag-short")
    rec, torch = _weld(
        [
            (ArcPhase.STRIKE, 0.2, False, 0.0),
            (ArcPhase.PAUSE, 0.5, False, 0.0),  # a failed start at rest
            (ArcPhase.STRIKE, 0.3, False, 0.006),  # the re-strike scratches 1.8 mm
            (ArcPhase.RETURN, 0.3, True, -0.006),  # the arc caught: back to the strike point, arc on
            (ArcPhase.WELD, 50e-3 / 0.006, True, 0.006),
            (ArcPhase.CRATER, 0.1, True, 0.0),
            (ArcPhase.DONE, 0.01, False, 0.0),
        ]
    )
    r = arc_report(rec, torch, SEAM, proc)
    assert r["completed"] and (r["failed_starts"], r["restrikes"], r["arc_losses"]) == (1, 1, 0)
    assert r["scratch_max_mm"] == pytest.approx(1.8, abs=0.01)
    assert r["welded_mm"] == pytest.approx(50.0, abs=0.05)  # from the strike point on: the scratch is no travel
    clean = arc_report(*_weld([(ArcPhase.WELD, 1.0, True, 0.006), (ArcPhase.DONE, 0.01, False, 0.0)]), SEAM, proc)
    assert clean["scratch_max_mm"] == 0.0
    validate(ARC_SCHEMA, r)


def test_a_weld_outside_its_window_is_flagged() -> None:
    proc = load_procedure(PROCEDURES, "steel-1.0mm-mag-short")
    rec, torch = _weld(
        [(ArcPhase.WELD, 2.0, True, 0.006), (ArcPhase.CRATER, 0.1, True, 0.0), (ArcPhase.DONE, 0.01, False, 0.0)], current=220.0
    )
    r = arc_report(rec, torch, SEAM, proc)
    assert r["flagged"] and r["weld_data"]["outside_s"] > 1.5


def test_the_welded_intervals_join_overlaps_and_drop_jumps() -> None:
    s = np.array([0.0, 0.001, 0.002, 0.0015, 0.0025, 0.01, 0.011])
    on = np.array([True, True, True, True, True, True, True])
    assert welded_intervals(s, on) == [(0.0, 0.0025), (0.01, 0.011)]
    assert welded_intervals(s, np.zeros(7, bool)) == []


def test_a_procedure_maps_onto_the_motion_process_sequence_and_through_the_plan() -> None:
    proc = load_procedure(PROCEDURES, "steel-1.2mm-mag-spray")
    seq = sequence_of(proc)
    assert seq.wire_feed == proc.wire_feed and seq.arc_loss == proc.arc_loss and seq.restrikes == proc.restrikes
    assert params_of(plan_keys(seq)) == seq


def test_the_seam_as_found_is_the_plan_to_the_first_touch_then_the_refined_path() -> None:
    plan = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0], [0.05, 0.0, 0.0]])
    refined = np.column_stack([np.linspace(0.015, 0.048, 34), np.full(34, 1e-4), np.zeros(34)])
    seam = known_seam(plan, refined, found_end=True)
    assert np.allclose(seam[:2], plan[:2]) and np.allclose(seam[2:], refined)
    # A part 2 mm shorter than its model: the found seam ends where the finger found the joint's end.
    assert float(np.linalg.norm(np.diff(seam, axis=0), axis=1).sum()) == pytest.approx(0.048, abs=1e-4)
    assert np.array_equal(known_seam(plan, refined[:1], found_end=True), plan)
    # A weld that stopped at 30 mm: the rest of the seam is the plan's.
    stopped = known_seam(plan, refined[:16], found_end=False)
    assert np.allclose(stopped[-1], plan[-1]) and float(np.linalg.norm(np.diff(stopped, axis=0), axis=1).sum()) == pytest.approx(
        0.05, abs=2e-4
    )


def test_the_demo_says_what_the_arc_did() -> None:
    from celld.sim.demo import _arc_lines

    proc = load_procedure(PROCEDURES, "steel-1.0mm-mag-short")
    rec, torch = _weld(
        [(ArcPhase.WELD, 2.0, True, 0.006), (ArcPhase.CRATER, 0.1, True, 0.0), (ArcPhase.DONE, 0.01, False, 0.0)], current=220.0
    )
    lines = _arc_lines(arc_report(rec, torch, SEAM, proc))
    assert lines[0].startswith("arc (steel-1.0mm-mag-short@2): done, 0 failed starts") and "welded 12.0 of 50.0 mm" in lines[0]
    assert "current 220 A" in lines[1] and lines[1].endswith("(flagged)")
    assert _arc_lines(None) == []
