"""From the tag's pose to the SRM deformation: tare, delta, contact state, confidence.

All functions here are pure. The deformation (Eq. 15) is read from the tag's
*translation* only: the tag sits at the finger tip, so its displacement from
the tared rest position is the tip's, and ``delta = P_r - P_s`` is its
negative, turned into the tool frame by the camera's mounting rotation::

    delta_tool = R_tool_cam @ (p_cam_rest - p_cam_tag)

(frames in :mod:`celld.tactile.tool`). The tag's rotation is never used: seen
face-on its two IPPE solutions swap and the angle flips.

The contact state is judged on the in-plane part of delta with hysteresis:
contact starts above ``contact_threshold`` and ends below
``_RELEASE * contact_threshold``; overload is at or above ``overload``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from celld.config import TactileConfig, ToolConfig
from celld.errors import InputError, TactileError
from celld.tactile.aruco import TagDetection
from celld.tactile.sample import ContactState, TactileSample, TactileStatus

Array = np.ndarray

# Contact ends below this fraction of the contact threshold (hysteresis).
_RELEASE = 0.7
# Sharpness at which the confidence stops growing, as a multiple of the
# blur threshold.
_SHARP_FULL = 2.0


class Tare(NamedTuple):
    """The tag's rest position, measured with the finger free.

    Attributes
    ----------
    p_cam_rest : (3,)
        Mean tag centre in the camera frame, m.
    n_frames : int
        Frames averaged.
    spread : float
        RMS distance of the frames from their mean, m.
    """

    p_cam_rest: Array
    n_frames: int
    spread: float


class DeformationParams(NamedTuple):
    """What turns a detection into a sample (from the sensor's and the tool's config)."""

    R_tool_cam: Array
    contact_threshold: float
    overload: float
    min_sharpness: float
    max_reprojection_px: float

    @classmethod
    def from_config(cls, cfg: TactileConfig, tool: ToolConfig) -> DeformationParams:
        return cls(tool.R_tool_cam(), cfg.contact_threshold, cfg.overload, cfg.min_sharpness, cfg.max_reprojection_px)


def tare(p_cam: Array, max_spread: float, min_frames: int = 1, reference: Array | None = None, max_offset: float = math.inf) -> Tare:
    """Rest position of the tag from positions seen with the finger free.

    Parameters
    ----------
    p_cam : (n, 3)
        Tag centres in the camera frame, m, from valid detections.
    max_spread : float
        Largest RMS spread accepted, m; a finger that moves or touches
        something during the tare spreads its positions.
    min_frames : int
    reference : (3,) array, optional
        The finger's reference rest (an earlier tare known free), m.
    max_offset : float
        Largest distance of the new rest from ``reference``, m: a finger held
        still but pressed (against the part, after a crash) rests elsewhere.

    Raises
    ------
    TactileError
        Too few frames, the tag moved during the tare, or it rests too far
        from the reference (:class:`TareRefused`).
    """
    P = np.asarray(p_cam, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"tare: expected (n, 3) tag positions, got shape {P.shape}")
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < max(min_frames, 1):
        raise TactileError(f"tare: expected at least {max(min_frames, 1)} valid tag positions, got {len(P)}")
    mean = P.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((P - mean) ** 2, axis=1))))
    if spread > max_spread:
        raise TactileError(
            f"tare: the tag moved during the tare (RMS spread {spread * 1e3:.4f} mm, "
            f"expected at most {max_spread * 1e3:.4f} mm); keep the finger free and still"
        )
    if reference is not None:
        offset = float(np.linalg.norm(mean - np.asarray(reference, dtype=np.float64)))
        if offset > max_offset:
            raise TareRefused(
                offset,
                f"tare refused: the tag rests {offset * 1e3:.3f} mm from the finger's reference rest (at most "
                f"{max_offset * 1e3:.3f} mm): the finger is not free (pressed or in contact); it is tared once it is free",
            )
    return Tare(mean, len(P), spread)


class TareRefused(TactileError):
    """A tare that found the finger not free: ``offset`` (m) from its reference rest."""

    def __init__(self, offset: float, message: str) -> None:
        super().__init__(message)
        self.offset = offset


def deformation_tool(p_cam: Array, rest: Tare, R_tool_cam: Array) -> Array:
    """Eq. 15's delta in the tool frame, (3,) m: ``R_tool_cam (p_rest - p_cam)``."""
    return R_tool_cam @ (rest.p_cam_rest - np.asarray(p_cam, dtype=np.float64))


def contact_state(delta_tool: Array, previous: ContactState, contact_threshold: float, overload: float) -> ContactState:
    """Contact judged on the in-plane deformation, with hysteresis.

    Parameters
    ----------
    delta_tool : (3,)
        m; only the first two (in-plane) components count.
    previous : ContactState
        The state of the previous valid sample.
    """
    d = math.hypot(float(delta_tool[0]), float(delta_tool[1]))
    if d >= overload:
        return ContactState.OVERLOAD
    if d >= contact_threshold:
        return ContactState.CONTACT
    if previous != ContactState.NONE and d >= _RELEASE * contact_threshold:
        return ContactState.CONTACT
    return ContactState.NONE


def confidence(det: TagDetection, min_sharpness: float, max_reprojection_px: float) -> float:
    """A 0..1 figure of how much the pose can be trusted.

    The product of a sharpness term (0 at the blur threshold, 1 at twice it)
    and a reprojection term (1 at zero error, 0 at the refusal threshold).
    """
    if det.status != TactileStatus.OK:
        return 0.0
    sharp = (det.sharpness - min_sharpness) / ((_SHARP_FULL - 1.0) * min_sharpness) if min_sharpness > 0 else 1.0
    reproj = 1.0 - det.reprojection_px / max_reprojection_px
    return float(np.clip(sharp, 0.0, 1.0) * np.clip(reproj, 0.0, 1.0))


def estimate(
    det: TagDetection,
    rest: Tare | None,
    params: DeformationParams,
    stamp_ns: int,
    seq: int,
    previous: ContactState,
    detect_ns: int,
) -> TactileSample:
    """Turn one detection into a :class:`TactileSample`.

    An unusable detection (or no tare yet) gives ``valid = False``, a NaN
    deformation and the status that says why; it never reads as zero.
    """
    if det.status != TactileStatus.OK or rest is None:
        status = det.status if det.status != TactileStatus.OK else TactileStatus.NOT_TARED
        return invalid_sample(stamp_ns, seq, status, detect_ns)
    delta = deformation_tool(det.p_cam, rest, params.R_tool_cam)
    return TactileSample(
        stamp_ns=stamp_ns,
        seq=seq,
        delta_tool=delta,
        contact=contact_state(delta, previous, params.contact_threshold, params.overload),
        confidence=confidence(det, params.min_sharpness, params.max_reprojection_px),
        valid=True,
        detect_ns=detect_ns,
        status=TactileStatus.OK,
    )


def invalid_sample(stamp_ns: int, seq: int, status: TactileStatus, detect_ns: int = 0) -> TactileSample:
    """A sample that says why there is no deformation: NaN delta, zero confidence."""
    return TactileSample(stamp_ns, seq, np.full(3, np.nan), ContactState.NONE, 0.0, False, detect_ns, status)
