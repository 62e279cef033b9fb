"""Calibration pairs: each capture becomes a (flange position, flange centre) pair or a rejection with its reason.

:class:`PairCollector` is the one place where a calibration capture meets
the detector; every path that gathers a session (the daemon's calibrate job,
the simulated cell's offline calibration, a saved session solved again, the
calibration benchmark) feeds it through
:class:`celld.calib.session.CalibrationSession`. A
pair is the robot's flange position ``p_base`` (the paper's Base p_i, the
TCP with a zero TCP offset) and the flange centre ``p_cam`` found in the
cloud (Cam p_i); a capture whose flange is not found is kept as a
:class:`~celld.calib.robust.RejectedPair` whose reason names the detector's
stage, so a report can say which poses gave nothing and why.

The collector stores each capture first when it is given a session writer,
so a dataset holds every capture, found or not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld.calib.detect import FlangeDetection, detect_flange
from celld.calib.detect_params import DetectParams
from celld.calib.flange import FlangeModel
from celld.calib.mount import ScannerMount
from celld.calib.rangebias import FinishStep
from celld.calib.robust import RejectedPair
from celld.errors import DetectionError, InputError
from celld.log import get_logger

log = get_logger(__name__)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Detections:
    """The pairs of a session (ids, flange positions and centres, (n, 3) m) and the captures rejected.

    ``steps`` holds each pair's finish step (the metal face over the painted
    shoulder, :class:`~celld.calib.rangebias.FinishStep`), None for a pair
    without one (a recorded centre, no painted shoulder in view).
    """

    ids: tuple[str, ...]
    P_base: Array
    P_cam: Array
    rejected: tuple[RejectedPair, ...]
    steps: tuple[FinishStep | None, ...] = ()


@dataclass(frozen=True)
class PairOutcome:
    """What became of one capture: a pair (``detection`` set, unless its centre was recorded) or a rejection."""

    id: str
    index: int
    detection: FlangeDetection | None
    rejected: RejectedPair | None

    @property
    def kept(self) -> bool:
        return self.rejected is None


class PairCollector:
    """Turns captures into calibration pairs.

    Parameters
    ----------
    flange : FlangeModel or None
        The flange to find; None when every pair brings its recorded centre.
    detect_params : DetectParams, optional
        The detector's parameters (the scanner's preset).
    writer : celld.calib.dataset.SessionWriter, optional
        Stores each capture (pose and cloud) before it is detected; the
        writer names the pair.
    mount : ScannerMount, optional
        Where the scanner is fixed: on the arm, a pair's robot side is the
        flange in the scanner's link frame (the writer's mount when not given).
    """

    def __init__(
        self, flange: FlangeModel | None, detect_params: DetectParams | None = None, writer: Any = None, mount: ScannerMount | None = None
    ) -> None:
        self.flange = flange
        self.detect_params = detect_params
        self.writer = writer
        self.mount = mount if mount is not None else (writer.mount if writer is not None else ScannerMount())
        if writer is not None and writer.mount != self.mount:
            raise InputError(f"pairs: the writer's scanner mount ({writer.mount.name}) is not the collector's ({self.mount.name})")
        self._ids: list[str] = []
        self._P_base: list[Array] = []
        self._P_cam: list[Array] = []
        self._steps: list[FinishStep | None] = []
        self._rejected: list[RejectedPair] = []
        self._count = 0

    def capture(self, T_base_flange: ArrayLike, cloud: ArrayLike, q: ArrayLike | None = None) -> PairOutcome:
        """A capture at the flange pose ``T_base_flange`` (4, 4): detected, then stored (with a writer).

        The writer gets the detection, so a compact dataset keeps exact the
        pixels the detector read (:mod:`celld.calib.dataset`). With the scanner
        on the arm, ``q`` are the joints of the capture and the pair's robot
        side is the flange in the scanner's link frame (Eq. 8).
        """
        T = np.asarray(T_base_flange, dtype=np.float64)
        found = self._detect(cloud) if self.flange is not None else None
        pair_id = self.writer.add_pair(T, cloud, detection=found, q=q) if self.writer is not None else str(self._count)
        T = self.mount.to_link(T, q)
        if found is None:
            return self.add(pair_id, T[:3, 3], cloud=cloud)
        return self._outcome(pair_id, T[:3, 3], found)

    def _detect(self, cloud: ArrayLike) -> FlangeDetection | DetectionError:
        assert self.flange is not None
        try:
            return detect_flange(np.asarray(cloud), self.flange, self.detect_params)
        except DetectionError as exc:
            return exc

    def _outcome(self, pair_id: str, p_base: ArrayLike, found: FlangeDetection | DetectionError) -> PairOutcome:
        index = self._count
        self._count += 1
        if isinstance(found, DetectionError):
            log.info("calib_detection_failed", pair=pair_id, stage=found.stage, reason=found.reason)
            return self.reject(pair_id, f"detection failed at {found.stage}: {found.reason}", index)
        return self._keep(pair_id, index, p_base, found.center, found)

    def add(self, pair_id: str, p_base: ArrayLike, cloud: ArrayLike | None = None, p_cam: ArrayLike | None = None) -> PairOutcome:
        """One pair: its recorded centre ``p_cam`` if given, else the flange found in ``cloud``.

        Raises
        ------
        InputError
            The flange must be detected but no flange model was given.
        """
        if p_cam is None:
            if cloud is None:
                return self.reject(pair_id, "no flange centre recorded and no cloud to detect it in")
            if self.flange is None:
                raise InputError(f"pair {pair_id!r}: a flange preset is needed to detect the centre in its cloud")
            return self._outcome(pair_id, p_base, self._detect(cloud))
        index = self._count
        self._count += 1
        return self._keep(pair_id, index, p_base, p_cam, None)

    def _keep(self, pair_id: str, index: int, p_base: ArrayLike, p_cam: ArrayLike, detection: FlangeDetection | None) -> PairOutcome:
        self._ids.append(pair_id)
        self._P_base.append(np.asarray(p_base, dtype=np.float64).reshape(3))
        self._P_cam.append(np.asarray(p_cam, dtype=np.float64).reshape(3))
        self._steps.append(None if detection is None else detection.finish_step)
        return PairOutcome(pair_id, index, detection, None)

    def reject(self, pair_id: str, reason: str, index: int | None = None) -> PairOutcome:
        """Count a capture that gives no pair, with the reason."""
        if index is None:
            index = self._count
            self._count += 1
        rejected = RejectedPair(pair_id, index, math.nan, reason)
        self._rejected.append(rejected)
        return PairOutcome(pair_id, index, None, rejected)

    @property
    def n_pairs(self) -> int:
        return len(self._ids)

    @property
    def n_captures(self) -> int:
        return self._count

    def detections(self) -> Detections:
        """The pairs kept so far and the captures rejected."""
        return Detections(
            tuple(self._ids), np.reshape(self._P_base, (-1, 3)), np.reshape(self._P_cam, (-1, 3)), tuple(self._rejected), tuple(self._steps)
        )
