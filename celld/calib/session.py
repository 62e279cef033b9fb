"""One calibration session, capture by capture: Algorithm 1 online, its early stop and the final solve.

Owns everything a calibration decides between two captures, for every path
that gathers a session: the daemon's calibrate job (which only moves, settles,
captures, reports and records around it), the simulated cell's offline
calibration and a saved session solved again
(:func:`calibrate_session`). It is fed the verification
capture, then one capture at a time (the flange pose the robot reports, the
cloud and the joints), and answers each with a :class:`CaptureStep`: the pair
or why the capture gave none, Algorithm 1's step, and whether to go on or stop.

With ``online`` (the daemon's use):

- Algorithm 1 starts once four pairs are in (line 2) and takes each new pair
  until its cost reaches ``e_required`` or ``k_max`` pairs were taken;
- with ``range_bias = "estimate"`` it starts with the bias the first four
  captures' finish steps say (the verification cloud's metal points, and the
  centres on metal, corrected by it);
- once Algorithm 1 is done and the quality gate's minimum of pairs is in, the
  session stops early only when the pairs so far make a calibration that
  passes its gate as the estimator left it: a realistic arm's pose-dependent
  error can leave a handful of pairs disagreeing although the cost is low,
  and the remaining captures then go on (the step says why).

Without ``online`` every capture is collected and nothing stops early. Either
way :meth:`CalibrationSession.finish` gives the result: the early stop's solve,
or :func:`~celld.calib.solve.solve_pairs` over every pair (the robust
estimate, Algorithm 1 over the pairs in order, e_icp, the quality gate).

Poses are in the base frame with the joints of each capture; a scanner on the
arm has each flange pose moved into its link's frame (Eq. 8) by the session's
mount. A saved session, whose poses are already in that frame, is fed with the
base mount.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from celld.calib.algorithm1 import Algorithm1, Algorithm1Result, Algorithm1Step
from celld.calib.dataset import Session
from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
from celld.calib.flange import FlangeModel
from celld.calib.metrics import IcpVerifier, cost_function
from celld.calib.mount import ScannerMount
from celld.calib.pairs import Detections, PairCollector, PairOutcome
from celld.calib.rangebias import bias_from_steps, correct_range_bias
from celld.calib.solve import CalibrationResult, SolveParams, range_bias_data, solve_pairs, verifier_from_cloud
from celld.errors import CalibrationError
from celld.log import get_logger

log = get_logger(__name__)

# Pairs Algorithm 1's first pool takes (line 2), and the fewest any solve takes.
_FIRST_POOL = 4


@dataclass(frozen=True)
class CaptureStep:
    """What one capture did to the session.

    Attributes
    ----------
    pair : PairOutcome
        The pair it gave, or its rejection with the reason.
    algorithm1 : Algorithm1Step | None
        Algorithm 1's step on this pair (None before four pairs, once it is
        done, without ``online``, or for a rejected capture).
    stop : bool
        The session is complete: stop capturing (:meth:`CalibrationSession.finish`
        gives the early stop's result).
    held : str
        Why the session goes on although Algorithm 1 is done (the quality
        gate's reason), else "".
    """

    pair: PairOutcome
    algorithm1: Algorithm1Step | None = None
    stop: bool = False
    held: str = ""

    def progress(self) -> tuple[str, dict[str, Any]]:
        """The step as a progress message and its data (radius and cost in mm)."""
        pid, det = self.pair.id, self.pair.detection
        if self.pair.rejected is not None or det is None:
            reason = self.pair.rejected.reason if self.pair.rejected is not None else "no detection"
            return f"pair {pid}: no flange ({reason})", {"pair": pid, "detected": False}
        data: dict[str, Any] = {"pair": pid, "detected": True, "radius_mm": det.radius * 1e3, "inliers": det.inliers}
        if det.finish_step is not None:
            data["range_bias_mm"] = det.finish_step.bias * 1e3
        step = self.algorithm1
        if step is not None:
            data["cost_mm"] = step.cost_optimal * 1e3 if math.isfinite(step.cost_optimal) else None
            data["pool"] = list(step.pool_ids)
        return f"pair {pid}", data


class CalibrationSession:
    """One eye-on-base (or eye-on-arm) calibration session, fed one capture at a time.

    Parameters
    ----------
    flange : FlangeModel or None
        The flange to find; None when every pair brings its recorded centre
        (then no verification cloud can be read either).
    params : SolveParams
    detect_params : DetectParams, optional
        The detector's parameters (the scanner's preset).
    planned : int
        Captures the session plans: the last one never stops early.
    mount : ScannerMount, optional
        Where the scanner is fixed (the writer's when not given, else the base).
    writer : celld.calib.dataset.SessionWriter, optional
        Stores every capture, found or not, before it is detected.
    online : bool
        Run Algorithm 1 as the pairs come and stop early (module docstring).
    verifier : IcpVerifier, optional
        e_icp against a verification cloud already read (else :meth:`verify`).
    """

    def __init__(
        self,
        flange: FlangeModel | None,
        params: SolveParams,
        detect_params: DetectParams | None = None,
        *,
        planned: int,
        mount: ScannerMount | None = None,
        writer: Any = None,
        online: bool = True,
        verifier: IcpVerifier | None = None,
    ) -> None:
        self.flange = flange
        self.params = params
        self.detect_params = detect_params
        self.planned = int(planned)
        self.online = online
        self._pairs = PairCollector(flange, detect_params, writer, mount)
        self.mount = self._pairs.mount
        self._writer = writer
        self.verifier = verifier
        self._alg: Algorithm1 | None = None
        self._bias = 0.0  # the range bias Algorithm 1 runs with, m
        self._result: CalibrationResult | None = None  # the early stop's

    # -- state ---------------------------------------------------------------

    @property
    def n_pairs(self) -> int:
        return self._pairs.n_pairs

    @property
    def n_captures(self) -> int:
        return self._pairs.n_captures

    @property
    def stopped_early(self) -> bool:
        """The session stopped before its last planned capture (its result is the early stop's)."""
        return self._result is not None

    @property
    def reached(self) -> bool:
        """Algorithm 1's cost reached ``e_required``."""
        return self._alg is not None and self._alg.reached

    def detections(self) -> Detections:
        return self._pairs.detections()

    def algorithm1(self) -> Algorithm1Result | None:
        """Algorithm 1 as it ran online (None before its first pool, or without ``online``)."""
        return self._alg.result() if self._alg is not None and self._alg.started else None

    # -- feeding ---------------------------------------------------------------

    def verify(self, T_base_flange: ArrayLike, cloud: ArrayLike, q: ArrayLike | None = None) -> IcpVerifier:
        """The verification capture: stored, and its flange cropped for e_icp (Eq. 13).

        Raises
        ------
        CalibrationError
            The flange is not found in the verification cloud, or none is known.
        """
        if self.flange is None:
            raise CalibrationError("a verification cloud needs the flange preset to find the flange in it")
        T = np.asarray(T_base_flange, dtype=np.float64)
        if self._writer is not None:
            self._writer.set_verification(T, cloud, q=q)
        self.verifier = verifier_from_cloud(cloud, self.mount.to_link(T, q), self.flange, self.params, self.detect_params)
        return self.verifier

    def capture(self, T_base_flange: ArrayLike, cloud: ArrayLike, q: ArrayLike | None = None) -> CaptureStep:
        """One capture at the flange pose the robot reports, ``T_base_flange`` (4, 4), with its joints ``q``."""
        return self._step(self._pairs.capture(T_base_flange, cloud, q))

    def add(self, pair_id: str, p_ref: ArrayLike, cloud: ArrayLike | None = None, p_cam: ArrayLike | None = None) -> CaptureStep:
        """A saved pair: the flange position ``p_ref`` in the frame the scanner is fixed in, with its recorded
        centre ``p_cam``, else its cloud to detect the centre in."""
        return self._step(self._pairs.add(pair_id, p_ref, cloud=cloud, p_cam=p_cam))

    def _step(self, got: PairOutcome) -> CaptureStep:
        if self._result is not None:
            raise CalibrationError("the session has stopped: it takes no more captures")
        if not self.online or not got.kept:
            return CaptureStep(got)
        step = self._algorithm1_step(got)
        alg = self._alg
        if alg is None or not alg.done or self.n_pairs < self.params.quality.min_pairs or self.n_captures >= self.planned:
            return CaptureStep(got, step)
        result, why = self._gated_solve()
        if result is None:
            return CaptureStep(got, step, held=why)
        self._result = result
        return CaptureStep(got, step, stop=True)

    def _algorithm1_step(self, got: PairOutcome) -> Algorithm1Step | None:
        """Algorithm 1 on the new pair: its first pool at four pairs, one step per pair after, until done."""
        found = self._pairs.detections()
        on_metal = self.flange is not None and self.flange.circle_on_metal
        if self.n_pairs == _FIRST_POOL:
            if self.verifier is None:
                raise CalibrationError("Algorithm 1 online needs the verification capture first")
            verifier = self.verifier
            if self.params.range_bias == "estimate":
                # The first four finish steps fix the bias to about 0.1 mm: Algorithm 1
                # scores with the verification cloud's metal corrected by it.
                self._bias = bias_from_steps(found.steps) or 0.0
                verifier = verifier.with_range_bias(self._bias)
            self._alg = Algorithm1(
                verifier,
                cost_function(self.params.cost, self.params.work_radius),
                e_required=self.params.e_required,
                k_max=self.params.k_max or self.planned,
            )
            P_cam = correct_range_bias(found.P_cam, self._bias) if on_metal else found.P_cam
            return self._alg.start(list(found.ids), found.P_base, P_cam)
        if self._alg is None or self._alg.done:
            return None
        p_cam = correct_range_bias(found.P_cam[-1:], self._bias)[0] if on_metal else found.P_cam[-1]
        return self._alg.add(got.id, found.P_base[-1], p_cam)

    def _gated_solve(self) -> tuple[CalibrationResult | None, str]:
        """The calibration from the pairs so far if it passes its quality gate as the estimator left it, else None and why not."""
        try:
            result = self._solve()
        except CalibrationError as exc:
            return None, str(exc)
        if result.quality.verdict != "ok":
            return None, f"the quality gate says {result.quality.verdict} ({'; '.join(result.quality.reasons)})"
        if result.gated:
            # An early stop wants a session the gate passes as the estimator left it; the
            # final solve may still leave the gate's outliers out (solve_pairs).
            return None, f"the quality gate found the pairs {', '.join(result.gated)} to be outliers"
        return result, ""

    def _solve(self) -> CalibrationResult:
        found = self._pairs.detections()
        return solve_pairs(
            found.ids,
            found.P_base,
            found.P_cam,
            self.params,
            self.verifier,
            found.rejected,
            self.n_captures,
            range_bias_data(self.params, self.flange, found),
        )

    # -- result ------------------------------------------------------------------

    def finish(self) -> CalibrationResult:
        """The session's calibration: the early stop's, else the solve over every pair.

        Raises
        ------
        CalibrationError
            Fewer than four captures gave a pair (the first reasons named), or the solve's own reasons.
        """
        if self._result is not None:
            return self._result
        if self.n_pairs < _FIRST_POOL:
            rejected = self._pairs.detections().rejected
            reasons = "; ".join(f"{r.id}: {r.reason}" for r in rejected[:4])
            raise CalibrationError(
                f"only {self.n_pairs} of {self.n_captures} captures showed the flange; at least {_FIRST_POOL} are needed"
                + (f" ({reasons})" if reasons else "")
            )
        return self._solve()


def calibrate_session(
    session: Session,
    flange: FlangeModel | None,
    params: SolveParams = SolveParams(),
    detect_params: DetectParams | None = None,
    redetect: bool = False,
) -> CalibrationResult:
    """Solve a saved session again: its pairs through a :class:`CalibrationSession` (without ``online``), then
    the chosen method, Algorithm 1 and e_icp against its verification capture when it has one.

    Each pair brings its recorded centre (reference sessions) unless ``redetect``, else the flange is found
    in its cloud; its flange position is in the frame the scanner is fixed in
    (:meth:`~celld.calib.dataset.Session.flange_position`: the base, or the scanner's link on the arm).
    ``detect_params`` default to the session scanner's (:data:`~celld.calib.detect_params.PARAMS_BY_SCANNER`),
    else the paper's.
    """
    if detect_params is None and session.scanner in PARAMS_BY_SCANNER:
        detect_params = PARAMS_BY_SCANNER[session.scanner]
    calibration = CalibrationSession(flange, params, detect_params, planned=len(session.pairs), online=False)
    for rec in session.pairs:
        p_cam = None if redetect else rec.p_cam
        cloud = session.cloud(rec) if p_cam is None and rec.cloud_path is not None else None
        calibration.add(rec.id, session.flange_position(rec), cloud=cloud, p_cam=p_cam)
    if calibration.n_pairs < _FIRST_POOL:
        calibration.finish()  # refuses, naming the first reasons
    v = session.verification
    if flange is not None and v is not None and v.cloud_path is not None and v.T_base_flange is not None:
        calibration.verify(session.flange_pose(v), session.cloud(v))
    result = calibration.finish()
    log.info(
        "calib_solved",
        method=result.method,
        pairs=len(result.pair_ids),
        rejected=len(result.rejected),
        rms_mm=round(float(np.sqrt(np.mean(result.residuals**2))) * 1e3, 4),
        verdict=result.quality.verdict,
        stored=result.stored,
    )
    for warning in result.quality.warnings:
        log.warning("calib_quality", warning=warning)
    return result
