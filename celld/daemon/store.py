"""What the state directory keeps of the cell's calibrations: the current ones, and the candidates jobs left.

:class:`CalibrationStore` holds the current calibration
(``<state_dir>/calibration.json``) and the candidates finished calibrate jobs
left (``<state_dir>/calibrations/<job>.json``); :func:`tool_store` the same for
the tool (``tool.json``, ``tool-calibrations/``). An accept makes a
candidate current, refusing a failed quality verdict unless forced. Every
file is sealed (:mod:`celld.sealed`: format, the job that made it, a
checksum) and checked where it is read: a damaged one is refused with
"the stored calibration is damaged: <why>", never taken for absent.
:func:`current_calibration` and :func:`current_tool` read the current ones as
a job uses them, refusing what is missing or unusable with the reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from celld import sealed
from celld.calib.mount import Placement, placement_of
from celld.config import ToolConfig
from celld.errors import CalibrationError, DamagedStateError, InputError, JobError
from celld.journal import utc_now
from celld.log import get_logger
from celld.robot import primary
from celld.schemadoc import boolean, string, with_properties
from celld.tactile.fingermap import FingerGain
from celld.tactile.tool import with_measured_torch

log = get_logger(__name__)

# A calibration's range bias beyond this is not a scanner's (mm): refused as corrupt.
MAX_RANGE_BIAS_MM = 100.0
# A measured tip farther than this from the TCP is not a tool's (m): refused as corrupt.
MAX_TIP_DISTANCE = 1.0


class CalibrationStore:
    """The current calibration, and the candidates finished calibrate jobs left.

    The current one is ``<state_dir>/calibration.json``; a candidate is
    ``<state_dir>/calibrations/<job>.json``. Both are written atomically and
    sealed as ``kind`` (:mod:`celld.sealed`); ``what`` names them in refusals.
    A candidate whose quality verdict (``quality.verdict``) is not ``ok`` is
    accepted only with ``force``, and is then marked ``forced``; a candidate
    without a verdict (written before the gate existed) is accepted as before.

    The same store keeps the tool calibration (:func:`tool_store`:
    ``tool.json`` and ``tool-calibrations/``): one accept, one verdict rule,
    for whatever a job measured.
    """

    def __init__(
        self,
        state_dir: Path,
        current: str = "calibration.json",
        candidates: str = "calibrations",
        kind: str = "calibrate",
        sealed_as: str = "calibration",
        what: str = "calibration",
    ) -> None:
        self.current_path = state_dir / current
        self.candidates = state_dir / candidates
        self.kind = kind
        self.sealed_as = sealed_as
        self.what = what
        self.candidates.mkdir(parents=True, exist_ok=True)

    def current(self) -> dict[str, Any] | None:
        """The current calibration, None when there is none.

        Raises
        ------
        DamagedStateError
            It is there but cannot be trusted (unreadable, cut short, edited, of an unknown format).
        """
        return sealed.read_sealed(self.current_path, self.sealed_as, self.what)

    def damage(self) -> str:
        """Why the current calibration cannot be used, "" when it can (or there is none)."""
        try:
            self.current()
        except DamagedStateError as exc:
            return str(exc)
        return ""

    def add_candidate(self, job_id: str, calibration: Mapping[str, Any]) -> Path:
        path = self.candidates / f"{job_id}.json"
        sealed.write_sealed(path, calibration, self.sealed_as, job_id)
        return path

    def accept(self, job_id: str, force: bool = False) -> dict[str, Any]:
        path = self.candidates / f"{job_id}.json"
        candidate = sealed.read_sealed(path, self.sealed_as, f"{self.what} of job {job_id}")
        if candidate is None:
            raise JobError("$.job", f"job {job_id} left no calibration to accept (not a finished {self.kind} job)")
        calibration = {k: v for k, v in candidate.items() if k not in (sealed.FORMAT_KEY, sealed.CHECKSUM_KEY)}
        # Its own verdict, and a second robot's (a calibrate job with robot2) when it has one.
        robot2 = calibration.get("robot2")
        gates = [("the ", calibration.get("quality")), ("robot 2's ", robot2.get("quality") if isinstance(robot2, dict) else None)]
        failed = [(who, q) for who, q in gates if isinstance(q, dict) and q.get("verdict") not in (None, "ok")]
        if failed:
            if not force:
                who, quality = failed[0]
                reasons = "; ".join(str(r) for r in quality.get("reasons", []))
                raise JobError(
                    "$.job",
                    f"{who}calibration of job {job_id} failed its quality gate ({quality['verdict']}: {reasons}); "
                    "accept it with force to override",
                )
            calibration["forced"] = True
        calibration["accepted"] = utc_now()
        return sealed.write_sealed(self.current_path, calibration, self.sealed_as, job_id)


def accepted_schema(candidate: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON shape of a current calibration (or tool calibration): its candidate's, ``candidate``, with what
    :meth:`CalibrationStore.accept` adds: when it was accepted, and whether with force."""
    return with_properties(
        candidate,
        {
            "accepted": string("When it became current, UTC ISO 8601."),
            "forced": boolean("Accepted with force despite a failed quality verdict."),
            sealed.FORMAT_KEY: string("The stored file's format and its version, celld.<kind>/<version>."),
            sealed.CHECKSUM_KEY: string("SHA-256 of the stored file without this key, serialised canonically (celld.sealed)."),
        },
        ("accepted", sealed.FORMAT_KEY, sealed.CHECKSUM_KEY),
    )


def tool_store(state_dir: Path) -> CalibrationStore:
    """The current tool calibration (``<state_dir>/tool.json``) and the candidates tool-calibrate jobs left."""
    return CalibrationStore(state_dir, "tool.json", "tool-calibrations", "tool-calibrate", "tool-calibration", "tool calibration")


class CurrentCalibration(NamedTuple):
    """The accepted calibration as a job uses it (:func:`current_calibration`)."""

    placement: Placement  # the scanner's (T_base_cam, or its pose on its link of the arm)
    range_bias: float  # m, the scanner's on metal
    job: str  # the job that made it
    site_bound: float | None  # m, its own bound on its error at the weld (:func:`site_bound`)


def current_calibration(state_dir: Path, mount: str = "base") -> CurrentCalibration:
    """The accepted calibration, read once (:func:`required_calibration`, :func:`placed`, :func:`site_bound`)."""
    cal = required_calibration(state_dir)
    placement, range_bias = placed(cal, mount)
    return CurrentCalibration(placement, range_bias, str(cal.get("job", "")), site_bound(cal))


def site_bound(cal: Mapping[str, Any]) -> float | None:
    """A stored calibration's own 95 % bound on its error away from where it was calibrated (m): its arm fit's
    away from its poses when it has one, else its quality's within the work radius; None when it stores none."""
    arm = cal.get("arm")
    try:
        mm = arm["bound"]["away_mm"] if isinstance(arm, Mapping) else cal["quality"]["bound"]["work_radius_mm"]
    except (KeyError, TypeError):
        return None
    if isinstance(mm, bool) or not isinstance(mm, (int, float)) or not 0.0 <= mm < math.inf:
        return None
    return float(mm) * 1e-3


def for_controller(placement: Placement, kinematics: Callable[[], primary.ControllerKinematics]) -> Placement:
    """``placement`` once it is known to hold on the controller as it computes now: its arm corrections, when it
    has them, are to the table the controller computes with (``kinematics``: the arm's
    :meth:`~celld.daemon.arm.Arm.require_kinematics`). Every job that reads or sends poses through the
    corrections takes its placement through here.

    Raises
    ------
    CalibrationError
        The corrections are to another table (the robot recalibrated, or another robot in its place).
    DeviceError
        The controller's table is not read yet.
    """
    if placement.arm is not None:
        made_on, now = primary.table_id(placement.arm.nominal), kinematics().id
        if made_on != now:
            raise CalibrationError(
                f"the arm calibration's corrections are to the controller kinematics {made_on}; the controller now "
                f"computes with {now}: calibrate again (calibrate job with arm_poses)"
            )
    return placement


def required_calibration(state_dir: Path) -> dict[str, Any]:
    """The accepted calibration as stored; refused without one, or when it is damaged (:mod:`celld.sealed`)."""
    cal = _read_current(CalibrationStore(state_dir))
    if cal is None:
        raise JobError("$", "the cell has no current calibration: run a calibrate job and accept it first")
    return cal


def placed(cal: Mapping[str, Any], mount: str) -> tuple[Placement, float]:
    """A stored calibration's placement of the scanner and its range bias on metal (m).

    Refused when either value is unusable, or when it was made for a scanner
    mounted elsewhere than the config's ``mount``. A calibration without a
    range bias (structured light, or written before it existed) has none: 0.
    """
    try:
        placement = placement_of(cal)
    except InputError as exc:
        raise JobError("$", f"the current calibration is unusable: {exc}") from exc
    if placement.mount.name != mount:
        raise JobError(
            "$",
            f"the current calibration is of a scanner on {placement.mount.name}, and scanner.mount is {mount!r}: "
            "calibrate the scanner where it is mounted now",
        )
    bias_mm = cal.get("range_bias_mm", 0.0)
    if isinstance(bias_mm, bool) or not isinstance(bias_mm, (int, float)) or not abs(bias_mm) <= MAX_RANGE_BIAS_MM:
        raise JobError(
            "$", f"the current calibration is unusable: range_bias_mm must be a number within +-{MAX_RANGE_BIAS_MM:g} mm, got {bias_mm!r}"
        )
    return placement, float(bias_mm) * 1e-3


# The record of the current calibration's last verification (celld.daemon.verify), and how it is sealed.
VERIFICATION = "verification.json"
VERIFICATION_KIND = "verification"


def last_verification(state_dir: Path) -> dict[str, Any] | None:
    """The record of the last verification; None when there is none or it cannot be trusted (the next weld then
    verifies again, and its new record replaces it)."""
    try:
        return sealed.read_sealed(state_dir / VERIFICATION, VERIFICATION_KIND, "verification record")
    except DamagedStateError:
        return None


FINGER = "finger.json"
FINGER_KIND = "finger"


class StoredFinger(NamedTuple):
    """The finger's gain the last probed weld measured (:func:`stored_finger`)."""

    finger: FingerGain
    gain_sigma: float
    job: str  # the weld that measured it
    at: str  # when (UTC)


def store_finger(state_dir: Path, job: str, tool_job: str, reading: Mapping[str, Any]) -> None:
    """Keep a weld's measured finger gain (``reading``: :data:`celld.weld.plan.FINGER_SCHEMA`'s measured branch),
    for the tool calibration ``tool_job`` it was measured with, sealed in ``<state_dir>/finger.json``."""
    body = {
        "gain": reading["gain"],
        "cubic_per_mm2": reading["cubic_per_mm2"],
        "gain_sigma": reading["gain_sigma"],
        "tool_calibration_job": tool_job,
        "at": utc_now(),
    }
    sealed.write_sealed(state_dir / FINGER, body, FINGER_KIND, job)


def stored_finger(state_dir: Path, tool_job: str, delta_d: float) -> tuple[StoredFinger | None, str]:
    """The finger's gain the last probed weld measured with the tool calibration ``tool_job``, checked as a plan's
    gain is where the servo holds ``delta_d`` (m); or None and why there is none to use (none kept, kept for
    another tool calibration, damaged or unusable: a weld then takes the tag's deformation as the tip's)."""
    try:
        doc = sealed.read_sealed(state_dir / FINGER, FINGER_KIND, "finger gain")
    except DamagedStateError as exc:
        return None, str(exc)
    if doc is None:
        return None, "no probed weld has measured it yet"
    if doc.get("tool_calibration_job") != tool_job:
        return None, f"the one kept was measured with tool calibration {doc.get('tool_calibration_job')!r}, not the current {tool_job!r}"
    try:
        values = [doc.get(k) for k in ("gain", "cubic_per_mm2", "gain_sigma")]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            raise InputError(f"finger gain: expected numbers, got {values}")
        finger = FingerGain.of_reading(doc).check(delta_d)
    except InputError as exc:
        return None, f"the one kept in {state_dir / FINGER} is unusable: {exc}"
    return StoredFinger(finger, float(doc["gain_sigma"]), str(doc.get(sealed.JOB_KEY, "")), str(doc.get("at", ""))), ""


def failed_verification(record: Mapping[str, Any] | None, calibration: Mapping[str, Any]) -> str:
    """Why welds are refused when ``record`` is a failed verification of ``calibration`` (the current one,
    by its checksum), "" otherwise."""
    if record is None or record.get("passed") or record.get("calibration_sha256") != calibration.get(sealed.CHECKSUM_KEY):
        return ""
    return (
        f"the current calibration (job {calibration.get('job')}) failed its verification by job {record.get('job')} at "
        f"{record.get('at')}: {record.get('reason')}; calibrate again and accept the result"
    )


class CurrentTool(NamedTuple):
    """The tool a weld runs with (:func:`current_tool`)."""

    tool: ToolConfig
    job: str  # the tool-calibrate job that measured it, "" for none
    sensor_yaw: float = 0.0  # rad, Algorithm2Params.sensor_yaw
    torch_measured: bool = False
    torch_height: float = 0.0  # m, the measured torch's end above the tip along the finger (0: as configured)


def current_tool(state_dir: Path, tool: ToolConfig) -> CurrentTool:
    """``tool`` with the current tool calibration's tip and, when it measured it, its torch.

    A measured torch sets the tool's x axis (from the torch to the tip, across
    the configured finger axis) and ``torch_offset``
    (:func:`celld.tactile.tool.with_measured_torch`). Refused without a current
    tool calibration unless ``tool.measured`` is ``"nominal"``, and when the
    stored tip or torch is unusable.
    """
    current = _read_current(tool_store(state_dir))
    if current is None:
        if tool.measured == "nominal":
            return CurrentTool(tool, "")
        raise JobError(
            "$",
            "the tool's tip is not measured: run a tool-calibrate job and accept it first, or set "
            'tool.measured = "nominal" in the config to weld with tool.tip_tcp_mm as typed',
        )
    job = str(current.get("job", ""))
    tip = _stored_point(current, "tip_tcp_mm")
    tool = replace(tool, tip_tcp=(float(tip[0]), float(tip[1]), float(tip[2])))
    if current.get("torch_measured") is not True:
        return CurrentTool(tool, job)  # a calibration of the tip alone: the torch as configured
    try:
        measured = with_measured_torch(tool, _stored_point(current, "torch_tcp_mm"))
    except InputError as exc:
        raise JobError("$", f"the current tool calibration {job} is unusable: {exc}") from exc
    return CurrentTool(measured.tool, job, measured.sensor_yaw, True, measured.height)


def _read_current(store: CalibrationStore) -> dict[str, Any] | None:
    try:
        return store.current()
    except DamagedStateError as exc:
        raise JobError("$", f"{exc}: calibrate again and accept the result") from exc


def _stored_point(current: Mapping[str, Any], key: str) -> np.ndarray:
    value = current.get(key)
    try:
        p = np.asarray(value, dtype=np.float64) * 1e-3
    except (TypeError, ValueError) as exc:
        raise JobError("$", f"the current tool calibration is unusable: {key} {value!r}") from exc
    if p.shape != (3,) or not np.all(np.isfinite(p)) or np.linalg.norm(p) > MAX_TIP_DISTANCE:
        raise JobError(
            "$",
            f"the current tool calibration is unusable: {key} must be 3 finite numbers within "
            f"{MAX_TIP_DISTANCE * 1e3:g} mm of the TCP, got {value!r}",
        )
    return p
