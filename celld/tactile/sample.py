"""One SRM tactile sample: the finger's deformation read from the ArUco tag.

A sample travels from the camera process to the motion process through a
:class:`celld.shm.SeqlockSlot` of :data:`TACTILE_DTYPE`. The deformation is in
the tool frame, metres: ``delta_tool = [tangential, normal, out_of_plane]``,
the first two in the welding plane (the paper's delta^{t_s}, delta^{n_s}).
The sign is that of Eq. 15, ``P_r = P_s + delta``: the undeformed tip position
minus the deformed one, so pressing a wall on the tool's +y side reads as a
positive normal deformation (frames in :mod:`celld.tactile.tool`).

A failed detection is a sample with ``valid = False`` and a
:class:`TactileStatus` that says why; its deformation is NaN, never zero, so
no consumer can mistake "no tag" for "no deformation".
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


class TactileStatus(IntEnum):
    """Why a sample is (not) valid."""

    OK = 0
    NO_TAG = 1  # no tag in the frame
    WRONG_ID = 2  # tags in the frame, none with the configured id
    BLURRED = 3  # the tag's edges are too soft to trust its corners
    BAD_POSE = 4  # the pose fit was refused (reprojection error, degenerate corners)
    CAMERA_LOST = 5  # the camera gave no frame (unplugged, driver failure)
    NOT_TARED = 6  # no rest pose yet


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
    status : TactileStatus
        ``OK`` for a valid sample, otherwise why it is not.
    """

    stamp_ns: int
    seq: int
    delta_tool: np.ndarray
    contact: ContactState
    confidence: float
    valid: bool
    detect_ns: int
    status: TactileStatus = TactileStatus.OK


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
        ("status", np.int8),
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
    rec["status"] = int(sample.status)
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
        status=TactileStatus(int(r["status"])),
    )
