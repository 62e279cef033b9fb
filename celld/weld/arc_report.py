"""What the arc did in one weld, from the motion loop's records of it (pure).

The records (:data:`celld.motion.channels.STATE_DTYPE`) carry, every cycle,
the power source's sequence (``arc_phase``, :class:`celld.motion.arc.ArcPhase`),
its inputs (``source_bits``: the arc stable signal among them), its current
and voltage. From them:

- the sequence's events: failed starts (a strike that timed out), re-strikes,
  arc losses mid-seam, and the phase the weld ended in; how far the longest
  re-strike's scratch took the torch ahead of the point it struck at;
- the weld data of :func:`celld.weld.weld_data.summarize` against the
  procedure's windows;
- the seam's welded length: the torch's positions while the source said the
  arc was stable, projected onto the seam as the weld found it, as a union of
  intervals (a back-off and its re-strike weld a stretch twice: it counts
  once); the unwelded length is the rest of the seam, and its stretches of a
  millimetre or more are listed (where a weld that ended early must be
  finished).

The seam as the weld found it (:func:`known_seam`) is the planned seam up to
where the finger first touched it, then the refined path (the seam as the
finger found it), then, for a weld that stopped before the finger found the
joint's end, the planned seam on from there: the finger finds where the
part's joint truly ends, which a part shorter than its model puts short of
the planned end.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from celld import polyline
from celld.motion.arc import ArcParams, ArcPhase
from celld.motion.source_io import BIT_ROLES
from celld.schemadoc import array, boolean, enum, integer, number, obj, string, vector
from celld.weld.procedure import WeldProcedure
from celld.weld.weld_data import WELD_DATA_SCHEMA, summarize

_ARC_STABLE_BIT = 1 << BIT_ROLES.index("arc_stable")
# Two arc-on samples this far apart along the seam or more are not one stretch (a jump, not travel), m.
_MAX_STEP = 0.002
# Unwelded stretches shorter than this are not listed (the torch's start and end within the plan's), m.
LISTED_GAP = 0.001


def sequence_of(procedure: WeldProcedure) -> ArcParams:
    """The motion process's arc sequence (:class:`celld.motion.arc.ArcParams`) of a weld procedure."""
    return ArcParams(
        preflow=procedure.preflow,
        strike_timeout=procedure.strike_timeout,
        restrikes=procedure.restrikes,
        restrike_pause=procedure.restrike_pause,
        arc_loss=procedure.arc_loss,
        backoff=procedure.backoff,
        scratch=procedure.scratch,
        crater=procedure.crater,
        burnback=procedure.burnback,
        postflow=procedure.postflow,
        wire_feed=procedure.wire_feed,
        voltage=procedure.voltage,
        crater_wire_feed=procedure.crater_wire_feed,
        crater_voltage=procedure.crater_voltage,
    )


def known_seam(seam_base: NDArray[np.float64], refined_base: NDArray[np.float64], found_end: bool) -> NDArray[np.float64]:
    """The seam as a weld found it (module docstring): ``seam_base`` (m, 3) planned, ``refined_base`` (k, 3) found,
    ``found_end`` whether the finger found the joint's end (the law finished the seam) or the weld stopped before."""
    if len(refined_base) < 2:
        return seam_base
    s0, s1 = (float(a) for a in polyline.project(refined_base[[0, -1]], seam_base).arc)
    s_plan = polyline.arc_length(seam_base)
    parts = [seam_base[s_plan < s0 - 1e-6], refined_base]
    if not found_end:
        parts.append(seam_base[s_plan > s1 + 1e-6])
    return np.concatenate([p for p in parts if len(p)])


def _transitions(phase: NDArray[np.int64], a: ArcPhase, b: ArcPhase) -> int:
    return int(np.count_nonzero((phase[:-1] == a) & (phase[1:] == b))) if len(phase) > 1 else 0


def welded_intervals(s: NDArray[np.float64], on: NDArray[np.bool_], max_step: float = _MAX_STEP) -> list[tuple[float, float]]:
    """The union of the stretches ``[s_k, s_k+1]`` of consecutive arc-on samples (``s``: arc length along the seam, m)."""
    if len(s) < 2:
        return []
    both = on[:-1] & on[1:] & (np.abs(np.diff(s)) < max_step)
    if not both.any():
        return []
    lo = np.minimum(s[:-1], s[1:])[both]
    hi = np.maximum(s[:-1], s[1:])[both]
    order = np.argsort(lo)
    out: list[tuple[float, float]] = []
    for a, b in zip(lo[order], hi[order]):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], float(b)))
        else:
            out.append((float(a), float(b)))
    return out


def _scratch_max(phase: NDArray[np.int64], s: NDArray[np.float64]) -> float:
    """The farthest a re-strike's scratch start took the torch ahead of where it struck (m along the seam; 0 with no
    re-strike): from each PAUSE -> STRIKE to the end of its STRIKE and RETURN."""
    out = 0.0
    striking = np.isin(phase, (ArcPhase.STRIKE, ArcPhase.RETURN))
    for i in np.flatnonzero((phase[:-1] == ArcPhase.PAUSE) & (phase[1:] == ArcPhase.STRIKE)) + 1:
        after = np.flatnonzero(~striking[i:])
        j = i + (int(after[0]) if len(after) else len(phase) - i)
        out = max(out, float(np.max(s[i:j]) - s[i]))
    return out


def arc_report(
    records: np.ndarray, torch_base: NDArray[np.float64], seam_base: NDArray[np.float64], procedure: WeldProcedure
) -> dict[str, Any]:
    """The arc's report of one weld (module docstring); JSON-ready, lengths in mm.

    Parameters
    ----------
    records : structured array
        The motion records of the weld's servo command, in order.
    torch_base : (n, 3)
        The torch's position at each record, base frame, m.
    seam_base : (m, 3)
        The seam as the weld found it (:func:`known_seam`), base frame, m.
    procedure : WeldProcedure
        The procedure the weld ran with (its windows and grace).
    """
    phase = records["arc_phase"].astype(np.int64)
    on = (records["source_bits"].astype(np.int64) & _ARC_STABLE_BIT) != 0
    t = (records["t_ns"] - records["t_ns"][0]) * 1e-9 if len(records) else np.zeros(0)
    ended = np.flatnonzero((phase[:-1] == ArcPhase.CRATER) & (phase[1:] == ArcPhase.BURNBACK)) if len(phase) > 1 else np.zeros(0, np.int64)
    data = summarize(
        t,
        on,
        records["weld_current"],
        records["weld_voltage"],
        procedure.current_window,
        procedure.voltage_window,
        procedure.window_grace,
        ended_at_s=float(t[ended[0] + 1]) if len(ended) else None,
    )
    seam_length = float(polyline.arc_length(seam_base)[-1])
    welded: list[tuple[float, float]] = []
    s = polyline.project(torch_base, seam_base).arc if len(torch_base) else np.zeros(0)
    if on.any():
        welded = welded_intervals(np.clip(s, 0.0, seam_length), on)
    welded_length = float(sum(b - a for a, b in welded))
    gaps: list[tuple[float, float]] = []
    edge = 0.0
    for a, b in [*welded, (seam_length, seam_length)]:
        if a - edge >= LISTED_GAP:
            gaps.append((edge, a))
        edge = max(edge, b)
    final = ArcPhase(int(phase[-1])) if len(phase) and phase[-1] >= 0 else ArcPhase.OFF
    return {
        "procedure": procedure.ident,
        "ended_in": final.name.lower(),
        "completed": final == ArcPhase.DONE,
        "failed_starts": _transitions(phase, ArcPhase.STRIKE, ArcPhase.PAUSE),
        "restrikes": _transitions(phase, ArcPhase.PAUSE, ArcPhase.STRIKE),
        "arc_losses": _transitions(phase, ArcPhase.WELD, ArcPhase.LOST) + _transitions(phase, ArcPhase.RETURN, ArcPhase.LOST),
        "scratch_max_mm": round(_scratch_max(phase, s) * 1e3, 2),
        "seam_length_mm": round(seam_length * 1e3, 2),
        "welded_mm": round(welded_length * 1e3, 2),
        "unwelded_mm": round(max(seam_length - welded_length, 0.0) * 1e3, 2),
        "unwelded_stretches_mm": [[round(a * 1e3, 2), round(b * 1e3, 2)] for a, b in gaps],
        "weld_data": data.as_dict(),
        "flagged": bool(data.flagged),
    }


# The JSON shape of arc_report's answer.
ARC_SCHEMA = obj(
    "What the arc did in the weld: the power source's sequence, the seam's welded and unwelded lengths (the torch's "
    "positions while the source said the arc was stable, on the planned seam), and the weld data.",
    {
        "procedure": string("The procedure's name@version."),
        "ended_in": enum([p.name.lower() for p in ArcPhase], "The sequence's phase at the end (done: completed)."),
        "completed": boolean("The sequence closed the seam: crater, burn-back, the wire free, post-flow."),
        "failed_starts": integer("Strikes with no stable arc within the procedure's strike timeout.", lo=0),
        "restrikes": integer("Strikes after the first.", lo=0),
        "arc_losses": integer("Arcs that went out mid-seam.", lo=0),
        "scratch_max_mm": number(
            "The farthest a re-strike's scratch start took the torch along the seam ahead of the point it struck at "
            "(0 without a re-strike).",
            lo=0.0,
        ),
        "seam_length_mm": number(lo=0.0),
        "welded_mm": number("Along the seam with the arc stable, counted once.", lo=0.0),
        "unwelded_mm": number(lo=0.0),
        "unwelded_stretches_mm": array(vector("From, to: mm along the seam.", 2), "Unwelded stretches of a millimetre or more."),
        "weld_data": WELD_DATA_SCHEMA,
        "flagged": boolean("The current or the voltage left the procedure's window."),
    },
    (
        "procedure",
        "ended_in",
        "completed",
        "failed_starts",
        "restrikes",
        "arc_losses",
        "scratch_max_mm",
        "seam_length_mm",
        "welded_mm",
        "unwelded_mm",
        "unwelded_stretches_mm",
        "weld_data",
        "flagged",
    ),
)
