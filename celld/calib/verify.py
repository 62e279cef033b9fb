"""A stored calibration checked against the cell: the flange seen again, compared with where the calibration puts it.

The scanner's mount can be knocked, the table moved, a calibration file copied
from another cell: a calibration that no longer matches the cell still reads
as valid. A verification shows the robot's flange to the scanner at a few
poses (two or more, apart, so that a turn of the scanner shows as well as a
shift) and compares, at each, the flange centre the scanner sees
(camera frame, corrected by the calibration's range bias) mapped by the
calibration with the flange centre the robot reports. The first pose is
captured twice: the difference of the two centres is the verification's own
repeatability.

The bound a verification is held to is, by default, the calibration's own
plus the repeatability measured now, so that a drift that matters is caught
and the scanner's noise is not. The calibration's own is what it reports of
itself: the largest residual of the pairs it was solved from (where the
flange landed against where the fit put it: one detection's noise and the
arm's kinematic error at a pose) plus three times its reported 1-sigma of a
point at the workspace centre (how far the fit itself may be off). A
configured bound replaces the rule.

Pure: the daemon's verify step (:mod:`celld.daemon.verify`) moves, captures and
detects; this module only compares.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from celld import se3
from celld.errors import CalibrationError
from celld.schemadoc import array, boolean, number, obj, string

Array = np.ndarray


@dataclass(frozen=True)
class Sighting:
    """The flange at one verification pose: what the robot reports and what the scanner saw.

    ``center_cam``/``normal_cam`` are None when the flange was not found
    where the calibration puts it (``why`` says why).
    """

    id: str
    T_base_flange: Array  # reported by the robot
    T_base_cam: Array  # where the calibration puts the scanner at this pose's joints
    center_cam: Array | None  # m, camera frame, range bias corrected
    normal_cam: Array | None  # unit, camera frame
    why: str = ""

    def errors(self) -> tuple[float, float]:
        """Distance of the seen flange centre from the reported one (m) and angle between their normals (rad),
        in the base frame; NaN when the flange was not seen."""
        if self.center_cam is None or self.normal_cam is None:
            return math.nan, math.nan
        R, t = self.T_base_cam[:3, :3], self.T_base_cam[:3, 3]
        d = float(np.linalg.norm(R @ self.center_cam + t - self.T_base_flange[:3, 3]))
        cos = float(np.clip(np.dot(R @ self.normal_cam, self.T_base_flange[:3, 2]), -1.0, 1.0))
        return d, math.acos(cos)


@dataclass(frozen=True)
class Verification:
    """A calibration held against the cell (module docstring); SI units. ``error`` is over the poses where
    the flange was seen."""

    sightings: tuple[Sighting, ...]
    repeatability: float  # m, between the two captures at the first pose
    calibration_bound: float  # m, the largest residual of the calibration's pairs
    bound: float  # m, what the error is held to
    error: float  # m, the largest distance of a seen flange from the reported one (inf when one was not seen)
    passed: bool
    reason: str  # why it failed, "" when it passed

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, mm and deg (:data:`SCHEMA`)."""

        def mm(x: float) -> float | None:
            return None if not math.isfinite(x) else x * 1e3

        poses = []
        for s in self.sightings:
            d, a = s.errors()
            poses.append(
                {
                    "id": s.id,
                    "error_mm": mm(d),
                    "normal_deg": None if math.isnan(a) else math.degrees(a),
                    "seen": s.center_cam is not None,
                    "why": s.why,
                }
            )
        return {
            "passed": self.passed,
            "reason": self.reason,
            "error_mm": mm(self.error),
            "bound_mm": self.bound * 1e3,
            "calibration_bound_mm": self.calibration_bound * 1e3,
            "repeatability_mm": self.repeatability * 1e3,
            "poses": poses,
        }


SCHEMA = obj(
    "A verification of the current calibration: the flange seen at a few poses against where the calibration puts it.",
    {
        "passed": boolean("The flange was seen at two poses or more, and the largest error is within the bound."),
        "reason": string("Why it failed; empty when it passed."),
        "error_mm": number(
            "The largest distance of a seen flange centre from the one the robot reports; null when none was seen.", null=True
        ),
        "bound_mm": number("What the error is held to.", lo=0.0),
        "calibration_bound_mm": number(
            "The calibration's own bound: the largest residual of the pairs it was solved from, plus three times its "
            "reported 1-sigma at the workspace centre.",
            lo=0.0,
        ),
        "repeatability_mm": number("The distance between two captures of the flange at the first pose.", lo=0.0),
        "poses": array(
            obj(
                "One verification pose.",
                {
                    "id": string("v0 (captured twice), v1, ..."),
                    "error_mm": number("Distance of the seen flange centre from the reported one, base frame.", null=True),
                    "normal_deg": number("Angle between the seen flange normal and the reported one.", null=True),
                    "seen": boolean("The flange was found in the cloud (near where the calibration puts it, or, failing that, anywhere)."),
                    "why": string("Why it was not found; empty when it was."),
                },
                ("id", "error_mm", "normal_deg", "seen", "why"),
            ),
            "Every pose, in the order visited.",
        ),
    },
    ("passed", "reason", "error_mm", "bound_mm", "calibration_bound_mm", "repeatability_mm", "poses"),
)
# How many poses a verification visits by default (the first twice).
POSES = 3


def calibration_bound(calibration: Mapping[str, Any]) -> float:
    """The stored calibration's own bound (m): the largest residual of the pairs it used (``quality.pairs``;
    else three times their RMS, ``quality.rms_mm``), plus three times the norm of its reported 1-sigma at
    the workspace centre (``quality.translation_std_mm``, when it reports one).

    Raises
    ------
    CalibrationError
        The calibration reports neither.
    """
    quality = calibration.get("quality")
    quality = quality if isinstance(quality, Mapping) else {}
    residuals = [
        float(r)
        for p in quality.get("pairs", ()) or ()
        if isinstance(p, Mapping) and p.get("used") and isinstance(r := p.get("residual_mm"), (int, float)) and math.isfinite(r)
    ]
    rms = quality.get("rms_mm")
    if residuals:
        spread = max(residuals)
    elif isinstance(rms, (int, float)) and not isinstance(rms, bool) and math.isfinite(rms):
        spread = 3.0 * float(rms)
    else:
        raise CalibrationError("the current calibration reports no pair residuals to hold a verification to: calibrate again")
    std = quality.get("translation_std_mm")
    try:
        sigma = float(np.linalg.norm(np.asarray(std, dtype=np.float64))) if std is not None else 0.0
    except (TypeError, ValueError):
        sigma = 0.0
    return (spread + (3.0 * sigma if math.isfinite(sigma) else 0.0)) * 1e-3


def verify_placement(
    sightings: Sequence[Sighting], repeat_center_cam: ArrayLike | None, calibration_bound_m: float, bound: float = 0.0
) -> Verification:
    """Hold ``sightings`` to the bound: ``bound`` (m) when > 0, else ``calibration_bound_m`` plus the repeatability
    (the distance of ``repeat_center_cam``, the first pose's second capture, from the first's centre).

    A pose where the flange was not found in the cloud at all (a view it does not show well; far from where
    the calibration puts it, it is still found and counts with its distance) is left out, as a calibration
    leaves such a capture out; fewer than two seen fail.

    Raises
    ------
    CalibrationError
        Fewer than two sightings: a turn of the scanner would not show.
    """
    if len(sightings) < 2:
        raise CalibrationError(f"a verification needs two poses or more, got {len(sightings)}")
    seen = [s for s in sightings if s.center_cam is not None]
    for s in sightings:
        se3.check_transform(s.T_base_flange, f"{s.id}.T_base_flange")
        se3.check_transform(s.T_base_cam, f"{s.id}.T_base_cam")
    first = sightings[0].center_cam
    if first is not None and repeat_center_cam is not None:
        repeatability = float(np.linalg.norm(np.asarray(repeat_center_cam, dtype=np.float64) - first))
    else:
        repeatability = math.nan
    held_to = bound if bound > 0 else calibration_bound_m + (0.0 if math.isnan(repeatability) else repeatability)
    error = max((s.errors()[0] for s in seen), default=math.inf)
    if len(seen) < 2:
        whys = "; ".join(f"{s.id}: {s.why}" for s in sightings if s.center_cam is None)
        reason = f"the flange was seen at {len(seen)} of {len(sightings)} poses, too few to verify ({whys})"
    elif error > held_to:
        worst = max(sightings, key=lambda s: s.errors()[0])
        reason = (
            f"the flange is {error * 1e3:.2f} mm (at {worst.id}) from where the calibration puts it, beyond the bound of "
            f"{held_to * 1e3:.2f} mm"
        )
    else:
        reason = ""
    return Verification(
        tuple(sightings), 0.0 if math.isnan(repeatability) else repeatability, calibration_bound_m, held_to, error, not reason, reason
    )
