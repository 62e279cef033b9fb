"""The requests as values: frozen dataclasses built from checked messages, and a job back to its message.

Each queryable's payload is loaded (:func:`celld.bus.wire.load_json`),
checked against its schema (:data:`celld.bus.messages.SCHEMAS`) and built
into a frozen value:

========================  ===========================
queryable                 parsed into
========================  ===========================
``submit``                :data:`Job` (:class:`CalibrateJob`, :class:`WeldJob`, :class:`MoveJob`,
                          :class:`HealthJob`, :class:`ToolCalibrateJob`, :class:`VerifyJob`)
``status``                :class:`StatusRequest`
``cancel``                :class:`CancelRequest`
``list``                  :class:`ListRequest`
``accept``                :class:`AcceptRequest`
``calibration``           :class:`CalibrationRequest`
``robot``                 :class:`RobotRequest`
``result/<job>``          :class:`ResultRequest`
========================  ===========================

Messages use the config's units (``e_required_mm``, ``delta_d_mm``,
``v_const_mm_s``, ``max_tilt_deg``); the values hold SI (metres, m/s, rad).
:func:`job_to_message` turns a job back into its submit message (the
journal keeps it), and :func:`parse_submit` of that gives the job back.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from celld.bus.checker import validate
from celld.bus.messages import JOB_ID, SCHEMAS
from celld.bus.wire import load_json

Pose6 = tuple[float, float, float, float, float, float]


# -- values ------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrateJob:
    """Eye-on-base calibration. ``None`` means "the cell config's value"."""

    n_poses: int | None = None
    e_required: float | None = None  # m
    k_max: int | None = None
    poses: tuple[Pose6, ...] = ()  # UR poses, base frame
    verification_pose: Pose6 | None = None
    compensate: bool = False
    seed: int | None = None
    dry_run: bool = False
    robot2: bool = False  # calibrate the second robot too, and T_base1_base2
    arm_poses: int | None = None  # wide poses for the arm's kinematic calibration after the hand-eye one (0: none)
    ref: str = ""
    request_id: str = ""  # the client's id of the submit
    kind: ClassVar[str] = "calibrate"


@dataclass(frozen=True)
class WeldJob:
    """Scan, find, touch and track one seam. ``None`` means "the cell config's value"."""

    workpiece: str = ""  # "": the cell's weld.workpiece
    delta_d: float | None = None  # m
    k_p: float | None = None  # 1/s
    v_const: float | None = None  # m/s
    torch_offset: float | None = None  # m
    arc: bool = True
    procedure: str = ""  # "": the cell's weld.procedure
    dry_run: bool = False
    ref: str = ""
    request_id: str = ""  # the client's id of the submit
    kind: ClassVar[str] = "weld"


@dataclass(frozen=True)
class MoveJob:
    """A move to joint positions (``space="joint"``, rad) or a TCP pose (``"cartesian"``) of robot ``robot``
    (1, or 2: the cell's second robot, its TCP pose in its own base frame)."""

    space: str
    target: Pose6
    speed_scale: float = 0.5
    robot: int = 1
    ref: str = ""
    request_id: str = ""  # the client's id of the submit
    kind: ClassVar[str] = "move"


@dataclass(frozen=True)
class HealthJob:
    """Health check of ``check``: all, robot, scanner or tactile."""

    check: str = "all"
    ref: str = ""
    request_id: str = ""  # the client's id of the submit
    kind: ClassVar[str] = "health"


@dataclass(frozen=True)
class ToolCalibrateJob:
    """Measure the SRM tip in the TCP frame. ``None`` means "the default"."""

    n_poses: int | None = None
    max_tilt: float | None = None  # rad
    tip_position: tuple[float, float, float] | None = None  # m, base frame
    seed: int | None = None
    dry_run: bool = False
    ref: str = ""
    request_id: str = ""  # the client's id of the submit
    kind: ClassVar[str] = "tool-calibrate"


@dataclass(frozen=True)
class VerifyJob:
    """Verify the current calibration against the cell now (:mod:`celld.daemon.verify`)."""

    ref: str = ""
    request_id: str = ""  # the client's id of the submit
    kind: ClassVar[str] = "verify"


Job = CalibrateJob | WeldJob | MoveJob | HealthJob | ToolCalibrateJob | VerifyJob


@dataclass(frozen=True)
class StatusRequest:
    job: str | None = None


@dataclass(frozen=True)
class CancelRequest:
    job: str
    reason: str = ""


@dataclass(frozen=True)
class ListRequest:
    limit: int = 50
    state: str | None = None
    kind: str | None = None


@dataclass(frozen=True)
class AcceptRequest:
    job: str
    force: bool = False  # accept despite a failed quality verdict


@dataclass(frozen=True)
class CalibrationRequest:
    pass


@dataclass(frozen=True)
class RobotRequest:
    action: str  # one of celld.bus.messages.ROBOT_ACTIONS


@dataclass(frozen=True)
class ResultRequest:
    job: str


Request = Job | StatusRequest | CancelRequest | ListRequest | AcceptRequest | CalibrationRequest | RobotRequest | ResultRequest


# -- building values from checked messages --------------------------------------------


def _mm(value: float | None) -> float | None:
    return None if value is None else float(value) * 1e-3


def _int_or_none(value: Any) -> int | None:
    return None if value is None else int(value)


def _pose6(values: Any) -> Pose6:
    return tuple(float(v) for v in values)  # type: ignore[return-value]


def _build_calibrate(m: Mapping[str, Any]) -> CalibrateJob:
    # "poses or n_poses, not both" is the schema's own rule (not/required): checked before this.
    return CalibrateJob(
        n_poses=_int_or_none(m.get("n_poses")),
        e_required=_mm(m.get("e_required_mm")),
        k_max=_int_or_none(m.get("k_max")),
        poses=tuple(_pose6(p) for p in m.get("poses", ())),
        verification_pose=_pose6(m["verification_pose"]) if "verification_pose" in m else None,
        compensate=bool(m.get("compensate", False)),
        seed=_int_or_none(m.get("seed")),
        dry_run=bool(m.get("dry_run", False)),
        robot2=bool(m.get("robot2", False)),
        arm_poses=_int_or_none(m.get("arm_poses")),
        ref=m.get("ref", ""),
        request_id=m.get("request_id", ""),
    )


def _build_weld(m: Mapping[str, Any]) -> WeldJob:
    k_p = m.get("k_p")
    return WeldJob(
        workpiece=m.get("workpiece", ""),
        delta_d=_mm(m.get("delta_d_mm")),
        k_p=None if k_p is None else float(k_p),
        v_const=_mm(m.get("v_const_mm_s")),
        torch_offset=_mm(m.get("torch_offset_mm")),
        arc=bool(m.get("arc", True)),
        procedure=m.get("procedure", ""),
        dry_run=bool(m.get("dry_run", False)),
        ref=m.get("ref", ""),
        request_id=m.get("request_id", ""),
    )


def _build_move(m: Mapping[str, Any]) -> MoveJob:
    target = m["target"]
    values = target["q"] if target["space"] == "joint" else target["pose"]
    return MoveJob(
        space=target["space"],
        target=_pose6(values),
        speed_scale=float(m.get("speed_scale", 0.5)),
        robot=int(m.get("robot", 1)),
        ref=m.get("ref", ""),
        request_id=m.get("request_id", ""),
    )


def _build_health(m: Mapping[str, Any]) -> HealthJob:
    return HealthJob(check=m.get("check", "all"), ref=m.get("ref", ""), request_id=m.get("request_id", ""))


def _build_tool_calibrate(m: Mapping[str, Any]) -> ToolCalibrateJob:
    tilt = m.get("max_tilt_deg")
    tip = m.get("tip_position")
    return ToolCalibrateJob(
        n_poses=_int_or_none(m.get("n_poses")),
        max_tilt=None if tilt is None else math.radians(float(tilt)),
        tip_position=None if tip is None else (float(tip[0]), float(tip[1]), float(tip[2])),
        seed=_int_or_none(m.get("seed")),
        dry_run=bool(m.get("dry_run", False)),
        ref=m.get("ref", ""),
        request_id=m.get("request_id", ""),
    )


def _build_verify(m: Mapping[str, Any]) -> VerifyJob:
    return VerifyJob(ref=m.get("ref", ""), request_id=m.get("request_id", ""))


_JOB_BUILDERS: dict[str, Callable[[Mapping[str, Any]], Job]] = {
    "calibrate": _build_calibrate,
    "weld": _build_weld,
    "move": _build_move,
    "health": _build_health,
    "tool-calibrate": _build_tool_calibrate,
    "verify": _build_verify,
}


def _build_submit(m: Mapping[str, Any]) -> Job:
    return _JOB_BUILDERS[m["kind"]](m)


_BUILDERS: dict[str, Callable[[Mapping[str, Any]], Any]] = {
    "submit": _build_submit,
    "status": lambda m: StatusRequest(job=m.get("job")),
    "cancel": lambda m: CancelRequest(job=m["job"], reason=m.get("reason", "")),
    "list": lambda m: ListRequest(limit=int(m.get("limit", 50)), state=m.get("state"), kind=m.get("kind")),
    "accept": lambda m: AcceptRequest(job=m["job"], force=bool(m.get("force", False))),
    "calibration": lambda m: CalibrationRequest(),
    "robot": lambda m: RobotRequest(action=m["action"]),
    "result": lambda m: ResultRequest(job=""),  # the job comes from the key: parse_result
}


def parse(request: str, raw: bytes | bytearray | memoryview) -> Any:
    """Validate the payload of one request and build its value.

    Parameters
    ----------
    request : str
        The queryable's name, one of :data:`celld.bus.messages.REQUESTS`.
    raw : bytes
        The payload as it came off the bus.

    Returns
    -------
    Job or StatusRequest or CancelRequest or ListRequest or AcceptRequest or CalibrationRequest or ResultRequest

    Raises
    ------
    JobError
        With the JSON path of the offending field and the reason.
    KeyError
        ``request`` is not a request name (a programming error, not input).
    """
    build = _BUILDERS[request]
    value = load_json(raw)
    validate(SCHEMAS[request], value)
    return build(value)


def parse_result(job: str, raw: bytes | bytearray | memoryview) -> ResultRequest:
    """:func:`parse` for ``result/<job>``: the payload must be empty (or ``{}``); ``job`` is the key's last chunk."""
    validate(SCHEMAS["result"], load_json(raw))
    validate(JOB_ID, job, "$.job")
    return ResultRequest(job=job)


def parse_submit(raw: bytes | bytearray | memoryview) -> Job:
    """:func:`parse` for ``submit``: bytes in, a frozen job value out."""
    job: Job = parse("submit", raw)
    return job


# -- a job back to its message --------------------------------------------------------


def _to_mm(value: float) -> float:
    # Round away the float noise of m -> mm (0.0003 * 1e3 = 0.30000000000000004).
    return round(value * 1e3, 9)


def job_to_message(job: Job) -> dict[str, Any]:
    """The submit message of ``job``, in message units; ``parse_submit`` of it gives ``job`` back."""
    m: dict[str, Any] = {"kind": job.kind}
    if isinstance(job, CalibrateJob):
        if job.n_poses is not None:
            m["n_poses"] = job.n_poses
        if job.e_required is not None:
            m["e_required_mm"] = _to_mm(job.e_required)
        if job.k_max is not None:
            m["k_max"] = job.k_max
        if job.poses:
            m["poses"] = [list(p) for p in job.poses]
        if job.verification_pose is not None:
            m["verification_pose"] = list(job.verification_pose)
        if job.compensate:
            m["compensate"] = True
        if job.dry_run:
            m["dry_run"] = True
        if job.seed is not None:
            m["seed"] = job.seed
        if job.robot2:
            m["robot2"] = True
        if job.arm_poses is not None:
            m["arm_poses"] = job.arm_poses
    elif isinstance(job, WeldJob):
        if job.workpiece:
            m["workpiece"] = job.workpiece
        for key, value in (("delta_d_mm", job.delta_d), ("v_const_mm_s", job.v_const), ("torch_offset_mm", job.torch_offset)):
            if value is not None:
                m[key] = _to_mm(value)
        if job.k_p is not None:
            m["k_p"] = job.k_p
        if not job.arc:
            m["arc"] = False
        if job.procedure:
            m["procedure"] = job.procedure
        if job.dry_run:
            m["dry_run"] = True
    elif isinstance(job, MoveJob):
        key = "q" if job.space == "joint" else "pose"
        m["target"] = {"space": job.space, key: list(job.target)}
        m["speed_scale"] = job.speed_scale
        if job.robot != 1:
            m["robot"] = job.robot
    elif isinstance(job, HealthJob):
        m["check"] = job.check
    elif isinstance(job, ToolCalibrateJob):
        if job.n_poses is not None:
            m["n_poses"] = job.n_poses
        if job.max_tilt is not None:
            m["max_tilt_deg"] = round(math.degrees(job.max_tilt), 9)
        if job.tip_position is not None:
            m["tip_position"] = list(job.tip_position)
        if job.seed is not None:
            m["seed"] = job.seed
        if job.dry_run:
            m["dry_run"] = True
    if job.ref:
        m["ref"] = job.ref
    if job.request_id:
        m["request_id"] = job.request_id
    return m
