"""One SRM tactile sample: the finger's deformation read from the ArUco tag.

A sample travels from the camera process to the motion process through a
:class:`celld.shm.SeqlockSlot` of :data:`TACTILE_DTYPE`. The deformation is in
the tool frame, metres: ``delta_tool = [tangential, normal, out_of_plane]``,
the first two in the welding plane (the paper's delta^{t_s}, delta^{n_s}).

A failed detection is a sample with ``valid = False``; its deformation is NaN,
never zero, so no consumer can mistake "no tag" for "no deformation".
"""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

import numpy as np


class ContactState(IntEnum):
    """What the finger touches, judged from the normal deformation."""

    NONE = 0
    CONTACT = 1
    OVERLOAD = 2


class TactileSample(NamedTuple):
    """One deformation estimate.

    Attributes
    ----------
    stamp_ns : int
        Capture time of the frame, ``time.monotonic_ns()`` clock.
    seq : int
        Frame counter of the camera process.
    delta_tool : np.ndarray, shape (3,)
        Tag displacement from its tared rest pose in the tool frame, metres:
        tangential, normal, out of the welding plane. NaN when not valid.
    contact : ContactState
    confidence : float
        0 to 1; 0 for an invalid sample.
    valid : bool
        False when the tag was not detected (or was the wrong id).
    detect_ns : int
        Time the detection took, nanoseconds.
    """

    stamp_ns: int
    seq: int
    delta_tool: np.ndarray
    contact: ContactState
    confidence: float
    valid: bool
    detect_ns: int


# The shared-memory layout of a TactileSample.
TACTILE_DTYPE = np.dtype(
    [
        ("stamp_ns", np.int64),
        ("seq", np.int64),
        ("delta_tool", np.float64, (3,)),
        ("contact", np.int8),
        ("valid", np.bool_),
        ("confidence", np.float32),
        ("detect_ns", np.int64),
        ("publish_ns", np.int64),
    ]
)


def to_record(sample: TactileSample, publish_ns: int = 0) -> np.ndarray:
    """Return a 1-element array of :data:`TACTILE_DTYPE` holding ``sample``."""
    rec = np.zeros(1, TACTILE_DTYPE)
    rec["stamp_ns"] = sample.stamp_ns
    rec["seq"] = sample.seq
    rec["delta_tool"] = sample.delta_tool
    rec["contact"] = int(sample.contact)
    rec["valid"] = sample.valid
    rec["confidence"] = sample.confidence
    rec["detect_ns"] = sample.detect_ns
    rec["publish_ns"] = publish_ns
    return rec


def from_record(rec: np.ndarray | np.void) -> TactileSample:
    """Return the TactileSample held by a :data:`TACTILE_DTYPE` record."""
    r = rec[0] if isinstance(rec, np.ndarray) and rec.shape == (1,) else rec
    return TactileSample(
        stamp_ns=int(r["stamp_ns"]),
        seq=int(r["seq"]),
        delta_tool=np.array(r["delta_tool"], dtype=np.float64),
        contact=ContactState(int(r["contact"])),
        confidence=float(r["confidence"]),
        valid=bool(r["valid"]),
        detect_ns=int(r["detect_ns"]),
    )
