"""The bus messages: JSON Schemas as data, and the validator that turns bytes into jobs.

Every message on the bus is a UTF-8 JSON object. Its schema (JSON Schema draft
2020-12) lives here as a plain dict in :data:`SCHEMAS`, is exported for other
languages by ``celld bus schema --out DIR`` (:func:`celld.bus.asyncapi.export_schemas`), and
drives the checker of :mod:`celld.bus.checker`, so the exported contract and
the enforced one are the same object.

Requests (what a client sends, keyed by the queryable's name):

========================  ============================================  ===========================
queryable                 payload                                       parsed into
========================  ============================================  ===========================
``submit``                ``{"kind": "calibrate" | "tool-calibrate" |   :data:`Job`
                          "weld" | "move" | "health", ...}``
``status``                ``{}`` or ``{"job": ID}``                     :class:`StatusRequest`
``cancel``                ``{"job": ID}``                               :class:`CancelRequest`
``list``                  ``{"limit": N, "state": S, "kind": K}``       :class:`ListRequest`
``accept``                ``{"job": ID, "force": B}`` (a calibrate or   :class:`AcceptRequest`
                          tool-calibrate job)
``calibration``           ``{}``                                        :class:`CalibrationRequest`
``robot``                 ``{"action": "unlock" | "power-on" |          :class:`RobotRequest`
                          "brake-release" | "close-popup"}``
``result/<job>``          ``{}`` (the job is in the key)                :class:`ResultRequest`
========================  ============================================  ===========================

An empty payload counts as ``{}``. Every rule a request must follow is in its
schema (the "poses or n_poses, not both" rule of a calibrate job is a
``not``/``required`` there), so a client that validates against the exported
schemas is refused by the cell only for the cell's own reasons (a full queue,
an unknown workpiece, a storage fault, its role). Replies are ``{"ok": true, ...}`` or
``{"ok": false, "error": {"field": PATH, "reason": TEXT}}``; publications are
progress events per job and the robot and tactile state. Their schemas are in
:data:`SCHEMAS` too (``*-reply``, ``progress``, ``state-robot``,
``state-tactile``); :func:`check_message` validates one.

Units: messages use the units of the config file (``e_required_mm``,
``delta_d_mm``, ``v_const_mm_s``); poses are UR poses ``[x, y, z, rx, ry, rz]``
in metres and a rotation vector in radians, in the robot base frame; joint
positions are radians. The job dataclasses hold SI values (metres, m/s).

Hostile input is refused before it is interpreted (:func:`load_json`): more
than :data:`MAX_PAYLOAD_BYTES`, not UTF-8, not JSON, NaN or infinities,
duplicate keys, integers of more than 20 digits, nesting deeper than
:data:`MAX_DEPTH`, lone surrogates in strings. Every refusal is a
:class:`~celld.errors.JobError` with the JSON path of the field (``$`` for the
whole message) and the reason.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from celld.bus.checker import check_schema, describe, validate
from celld.config import SCANNER_MOUNTS
from celld.config.tactile import SERVO_BOUNDS, servo_key
from celld.errors import JobError

# Largest request payload accepted, bytes (1000 calibration poses fit in ~130 KiB).
MAX_PAYLOAD_BYTES = 256 * 1024
# Deepest nesting of arrays and objects in a request (a pose list is 3).
MAX_DEPTH = 6
# Longest integer literal accepted, digits (an int64 has 19).
MAX_INT_DIGITS = 20
# Most calibration poses one job may give.
MAX_POSES = 1000
# Job ids are one zenoh key chunk: letters, digits, '-' and '_'.
JOB_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$"
# Free text: printable, no control characters.
TEXT_PATTERN = r"^[^\u0000-\u001f\u007f]*$"
# Dialect of every exported schema.
DIALECT = "https://json-schema.org/draft/2020-12/schema"
# A client's id of a submit: letters, digits and '_', '.', ':', '-' (a UUID fits).
REQUEST_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,63}$"
# Largest result sent inline by the result queryable, bytes of JSON.
MAX_RESULT_BYTES = 1024 * 1024

JOB_KINDS = ("calibrate", "weld", "move", "health", "tool-calibrate")
JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled", "interrupted")
TERMINAL_STATES = ("succeeded", "failed", "cancelled", "interrupted")
HEALTH_CHECKS = ("all", "robot", "scanner", "tactile")
# Verdicts of the calibration quality gate (celld.calib.quality.VERDICTS; only "ok" passes).
CALIBRATION_VERDICTS = ("ok", "too_few_pairs", "poor_data", "insufficient_rotation", "insufficient_range_bias")
# Verdicts of a tool calibration (celld.calib.toolcal.VERDICTS; only "ok" passes).
TOOL_VERDICTS = ("ok", "too_few_poses", "poor_orientation_spread", "poor_data")
# Most poses one tool calibration may visit.
MAX_TOOL_POSES = 100

Pose6 = tuple[float, float, float, float, float, float]


# -- schema building blocks ---------------------------------------------------------


def _number(desc: str, lo: float | None = None, hi: float | None = None, *, open_lo: bool = False) -> dict[str, Any]:
    s: dict[str, Any] = {"type": "number", "description": desc}
    if lo is not None:
        s["exclusiveMinimum" if open_lo else "minimum"] = lo
    if hi is not None:
        s["maximum"] = hi
    return s


def _servo_number(name: str, desc: str) -> dict[str, Any]:
    """A job's override of a servo (or tool) value: the config's key, unit and bound (celld.config.SERVO_BOUNDS)."""
    key, scale = servo_key(name)
    b = SERVO_BOUNDS[name]
    section = "tool" if name == "torch_offset" else "servo"
    return _number(f"{desc} (default: {section}.{key}).", b.lo / scale, b.hi / scale, open_lo=b.open_lo)


def _integer(desc: str, lo: int | None = None, hi: int | None = None) -> dict[str, Any]:
    s: dict[str, Any] = {"type": "integer", "description": desc}
    if lo is not None:
        s["minimum"] = lo
    if hi is not None:
        s["maximum"] = hi
    return s


def _text(desc: str, max_length: int = 200) -> dict[str, Any]:
    return {"type": "string", "maxLength": max_length, "pattern": TEXT_PATTERN, "description": desc}


def _vector(desc: str, n: int, lo: float | None = None, hi: float | None = None) -> dict[str, Any]:
    items: dict[str, Any] = {"type": "number"}
    if lo is not None:
        items["minimum"] = lo
    if hi is not None:
        items["maximum"] = hi
    return {"type": "array", "items": items, "minItems": n, "maxItems": n, "description": desc}


def _object(desc: str, properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    return {
        "type": "object",
        "description": desc,
        "properties": properties,
        "required": list(required),
        "additionalProperties": False,
    }


def _pose(desc: str) -> dict[str, Any]:
    """A UR pose: metres in a 2.5 m box around the base, then a rotation vector."""
    metres = {"type": "number", "minimum": -2.5, "maximum": 2.5}
    radians = {"type": "number", "minimum": -2 * math.pi, "maximum": 2 * math.pi}
    return {
        "type": "array",
        "prefixItems": [metres, metres, metres, radians, radians, radians],
        "minItems": 6,
        "maxItems": 6,
        "description": desc + " UR pose [x, y, z, rx, ry, rz]: metres and a rotation vector (rad), base frame.",
    }


_JOB_ID = {"type": "string", "pattern": JOB_ID_PATTERN, "description": "A job id, as returned by submit."}
_REF = _text("The client's own reference for the job (an order number); echoed in status.", 128)
_REQUEST_ID = {
    "type": "string",
    "pattern": REQUEST_ID_PATTERN,
    "description": (
        "The client's id of this submit (a UUID, an MES order step). Submitting again with the same id and "
        "the same body returns the job the first submit made (replayed: true) instead of making a second; "
        "the same id with a different body is refused. Ids are kept per bus user, in the journal."
    ),
}
_NULLABLE_TEXT = {"type": ["string", "null"]}
_JOINTS = _vector("Joint positions, rad.", 6, -2 * math.pi, 2 * math.pi)


def _submit_branch(kind: str, desc: str, properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    props = {"kind": {"const": kind, "description": "The job kind."}, **properties, "ref": _REF, "request_id": _REQUEST_ID}
    return _object(desc, props, ("kind", *required))


_DRY_RUN = {
    "type": "boolean",
    "default": False,
    "description": "Plan everything and check it against the cell without moving the robot; the plan (poses, "
    "joints, paths, what was refused and why) is in the result and the job's recording.",
}

_CALIBRATE: dict[str, Any] = _submit_branch(
    "calibrate",
    "Eye-on-base calibration of the scanner from the robot's flange (Algorithm 1): the "
    "verification pose first, then calibration poses, a progress event per pair, an early "
    "stop at e_required. The result becomes current only on an accept request or when the "
    "config says so. Give either poses or n_poses, not both.",
    {
        "n_poses": _integer("How many calibration poses to generate (default: calibration.n_poses).", 4, MAX_POSES),
        "e_required_mm": _number("Cost at which Algorithm 1 stops, mm (default: calibration.e_required_mm).", 0.0, 100.0),
        "k_max": _integer("Most iterations of Algorithm 1 (default: calibration.k_max).", 1, 10_000),
        "poses": {
            "type": "array",
            "items": _pose("A calibration pose."),
            "minItems": 4,
            "maxItems": MAX_POSES,
            "description": "Calibration poses to visit instead of generated ones.",
        },
        "verification_pose": _pose("Where the verification cloud is taken (default: calibration.verification_pose)."),
        "compensate": {
            "type": "boolean",
            "default": False,
            "description": "Store the estimate compensated by Eq. 21 (it is then what accept makes current); the calibration's stored field says which was stored.",
        },
        "seed": _integer("Seed of the pose generator (default: a fresh one).", 0, 2**32 - 1),
        "robot2": {
            "type": "boolean",
            "default": False,
            "description": "Calibrate the cell's second robot ([robot2]) through the same scanner in the same job, after robot 1, "
            "and give T_base1_base2 (Eq. 5-6 with the camera fixed); its poses are generated (no poses).",
        },
        "dry_run": _DRY_RUN,
    },
)
_CALIBRATE["not"] = {"required": ["poses", "n_poses"], "description": "Give either poses or n_poses, not both."}

_TOOL_CALIBRATE = _submit_branch(
    "tool-calibrate",
    "Measure the welding tool's SRM tip and its torch (the welding wire's end) in the TCP frame: the tool is "
    "presented to the scanner at n_poses orientations, turned about the tip, the tip ball and the wire's end "
    "are found in each capture with the current calibration, and each is solved by least squares with its "
    "residuals, outliers, 1-sigma and a verdict. "
    "Needs a current calibration. The result becomes the current tool calibration only on an accept "
    "request (a failed verdict only with force) or when the config says so.",
    {
        "n_poses": _integer("How many orientations to present the tool at (default 12).", 3, MAX_TOOL_POSES),
        "max_tilt_deg": _number("Largest tilt of the finger from the pose facing the scanner, deg (default 20).", 2.0, 45.0),
        "tip_position": _vector(
            "Where the tip is presented, base frame, m (default: the position of calibration.verification_pose, which the scanner sees).",
            3,
            -2.5,
            2.5,
        ),
        "seed": _integer("Seed of the orientation generator (default 0).", 0, 2**32 - 1),
        "dry_run": _DRY_RUN,
    },
)

_WELD = _submit_branch(
    "weld",
    "Scan, find the seam, move it to the base frame with the current calibration, approach, "
    "touch until delta_d, track it with Algorithm 2 (arc on and off by digital output), retract. "
    "Results: the refined path and the torch path.",
    {
        "workpiece": {
            "type": "string",
            "pattern": r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
            "description": "A workpiece model known to the cell (an example or a model in weld.workpiece_dir); absent: the cell's weld.workpiece.",
        },
        "delta_d_mm": _servo_number(
            "delta_d", "Desired normal deformation of the SRM, mm; between the sensor's contact and overload levels"
        ),
        "k_p": _servo_number("k_p", "Normal gain of Eq. 16, 1/s"),
        "v_const_mm_s": _servo_number("v_const", "Tangential speed V_const, mm/s"),
        "torch_offset_mm": _servo_number("torch_offset", "|d| of Eq. 14, mm"),
        "arc": {"type": "boolean", "default": True, "description": "Switch the arc on while tracking; false: track without it."},
        "dry_run": _DRY_RUN,
    },
)

_MOVE_TARGET = {
    "type": "object",
    "description": "Where to move: joint positions, or a TCP pose in the base frame.",
    "oneOf": [
        _object("A joint target.", {"space": {"const": "joint"}, "q": _JOINTS}, ("space", "q")),
        _object("A Cartesian target of the TCP.", {"space": {"const": "cartesian"}, "pose": _pose("The TCP pose.")}, ("space", "pose")),
    ],
}

_MOVE = _submit_branch(
    "move",
    "A jerk-limited move to a joint or Cartesian target (checked against the cell's workspace).",
    {
        "target": _MOVE_TARGET,
        "speed_scale": _number("Fraction of the configured speed limits.", 0.0, 1.0, open_lo=True),
    },
    ("target",),
)

_HEALTH = _submit_branch(
    "health",
    "Health check of the scanner, the robot link or the tactile camera.",
    {"check": {"enum": list(HEALTH_CHECKS), "default": "all", "description": "What to check."}},
)

_SUBMIT = {
    "type": "object",
    "description": "A job for the cell. The reply is submit-reply or error-reply.",
    "oneOf": [_CALIBRATE, _WELD, _MOVE, _HEALTH, _TOOL_CALIBRATE],
}

_ERROR = _object(
    "Why a request was refused.",
    {
        "field": {
            "type": "string",
            "description": "JSON path of the offending field ($ for the whole message, empty when no field is at fault).",
        },
        "reason": {"type": "string", "description": "What was expected and what came."},
    },
    ("field", "reason"),
)


def _reply(desc: str, properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    ok = {"ok": {"const": True}}
    return _object(desc, {**ok, **properties}, ("ok", *required))


_STALL = {
    "type": ["object", "null"],
    "description": "The worst stall of its kind so far (null: none).",
    "properties": {
        "late_ms": {"type": "number", "minimum": 0, "description": "How much later than asked the loop woke."},
        "kind": {"enum": ["busy", "unscheduled"]},
        "callback": {"type": "string", "description": "The longest callback in the gap (its task and coroutine), or empty."},
        "callback_ms": {"type": "number", "minimum": 0},
        "callback_cpu_ms": {
            "type": "number",
            "minimum": 0,
            "description": "The CPU that callback had (less than its time: it waited for the GIL).",
        },
        "workers_cpu_ms": {"type": "number", "description": "The CPU the daemon's other threads had in the gap."},
        "where": {"type": "string", "description": "Where the long callback was when the watcher looked (file:line function), or empty."},
        "others": {
            "type": "string",
            "description": "Where the daemon's other threads were while the loop waited (thread: file:line function; ...).",
        },
    },
    "additionalProperties": False,
}
_LOOP = _object(
    "How late the daemon's event loop ran: stalls over threshold_ms counted by kind (busy: a callback ran that long; "
    "unscheduled: the loop was ready but did not run: the daemon's worker threads or other processes had the CPU).",
    {
        "threshold_ms": {"type": "number", "minimum": 0},
        "busy": {"type": "integer", "minimum": 0},
        "unscheduled": {"type": "integer", "minimum": 0},
        "worst_busy": _STALL,
        "worst_unscheduled": _STALL,
    },
    ("threshold_ms", "busy", "unscheduled"),
)


_JOB_RECORD = _object(
    "One job as the journal keeps it. Times are UTC wall clock, ISO 8601. A user who may not see "
    "the job in full (a viewer, or an operator looking at another user's job) gets it redacted: no "
    "params, ref, request_id, owner or result, and redacted: true.",
    {
        "id": _JOB_ID,
        "kind": {"enum": list(JOB_KINDS)},
        "state": {"enum": list(JOB_STATES)},
        "reason": {"type": "string", "description": "Why the job failed, was cancelled (the canceller's reason) or interrupted."},
        "ref": {"type": "string"},
        "params": {"type": "object", "description": "The job as submitted (the submit message, without request_id)."},
        "created": {"type": "string"},
        "started": _NULLABLE_TEXT,
        "ended": _NULLABLE_TEXT,
        "result": {
            "type": ["string", "null"],
            "description": "Path of the result file on the cell PC (read it over the bus: <req>/result/<job>).",
        },
        "owner": {"type": "string", "description": "The bus user who submitted the job (empty on an open bus)."},
        "request_id": {"type": ["string", "null"], "description": "The submit's request_id, if it had one."},
        "redacted": {"const": True, "description": "Present when params, ref, request_id, owner and result are withheld."},
    },
    ("id", "kind", "state", "reason", "created", "started", "ended"),
)

_STORAGE = _object(
    "The state directory: free space against the floor, and storage faults.",
    {
        "ok": {"type": "boolean", "description": "No storage fault and free space above the floor: jobs are taken."},
        "free_mb": {"type": ["number", "null"], "description": "Free space of the state directory's file system, MiB."},
        "floor_mb": {"type": "number", "minimum": 0, "description": "cell.min_free_mb: below it new jobs are refused."},
        "fault": {"type": "string", "description": "The storage fault now (empty when none); jobs are refused and the queue waits."},
        "last_error": {
            "type": ["object", "null"],
            "description": "The most recent failed write, kept after recovery: {what, path, reason, at}.",
            "properties": {
                "what": {"type": "string", "description": "journal, result, job files, recording, calibration or probe."},
                "path": {"type": "string"},
                "reason": {"type": "string"},
                "at": {"type": "string", "description": "UTC, ISO 8601."},
            },
        },
        "pending_writes": {"type": "integer", "minimum": 0, "description": "Writes owed, made once there is room."},
    },
    ("ok", "free_mb", "floor_mb", "fault", "last_error", "pending_writes"),
)

_FILE = _object(
    "A file a job left in the cell's state directory.",
    {
        "path": {"type": "string", "description": "Relative to the state directory (jobs/<job>/..., recordings/<job>.rrd)."},
        "bytes": {"type": "integer", "minimum": 0},
    },
    ("path", "bytes"),
)

_NUMBER_OR_NULL = {"type": ["number", "null"]}
_TEXTS = {"type": "array", "items": {"type": "string"}}

_QUALITY = _object(
    "The quality gate's view of a calibration (celld.calib.quality): a verdict and why, per-pair "
    "residuals and outliers, the uncertainty at the workspace centre, e_icp of the estimate.",
    {
        "verdict": {"enum": list(CALIBRATION_VERDICTS), "description": "Only ok passes; accept refuses the others unless forced."},
        "passed": {"type": "boolean"},
        "reasons": {**_TEXTS, "description": "Why the verdict is not ok."},
        "warnings": {**_TEXTS, "description": "What does not fail the gate but should be known."},
        "pairs": {
            "type": "array",
            "description": "Every pair: residual against the estimate, used, outlier, and why.",
            "items": _object(
                "One pair.",
                {
                    "id": {"type": "string"},
                    "residual_mm": {**_NUMBER_OR_NULL, "description": "Null when the pair has no flange centre."},
                    "used": {"type": "boolean"},
                    "outlier": {"type": "boolean"},
                    "reason": {"type": "string", "description": "Why it is an outlier, not used, or without a centre."},
                },
                ("id", "residual_mm", "used", "outlier", "reason"),
            ),
        },
        "outliers": {"type": "array", "items": {"type": "string"}, "description": "Ids of the outliers."},
        "n_used": {"type": "integer", "minimum": 0},
        "rms_mm": {**_NUMBER_OR_NULL, "description": "RMS residual of the pairs used."},
        "sigma_mm": {**_NUMBER_OR_NULL, "description": "Noise per axis the uncertainty uses."},
        "sigma_source": {"enum": ["residuals", "floor"]},
        "workspace_centre": _vector("Centroid of the positions used, base frame, m.", 3),
        "translation_std_mm": {
            "type": "array",
            "items": _NUMBER_OR_NULL,
            "minItems": 3,
            "maxItems": 3,
            "description": "1-sigma at the workspace centre, base x, y, z.",
        },
        "rotation_std_deg": {
            "type": "array",
            "items": _NUMBER_OR_NULL,
            "minItems": 3,
            "maxItems": 3,
            "description": "1-sigma about base x, y, z.",
        },
        "rotation_axes": {
            "type": "array",
            "description": "Principal axes of the rotation covariance, the worst fixed first.",
            "items": _object(
                "One axis.",
                {"axis": {"type": "string"}, "direction": _vector("Unit direction, base frame.", 3), "std_deg": _NUMBER_OR_NULL},
                ("axis", "direction", "std_deg"),
            ),
        },
        "e_icp": {"type": ["object", "null"], "description": "e_icp (Eq. 13) of the estimate; null without a verification cloud."},
        "e_icp_tilt_deg": {**_NUMBER_OR_NULL, "description": "e_icp's rotation across the verification flange's axis."},
        "e_icp_turn_deg": {
            **_NUMBER_OR_NULL,
            "description": "e_icp's rotation about the verification flange's axis (fixed only by its holes).",
        },
        "range_bias_mm": {
            **_NUMBER_OR_NULL,
            "description": "The scanner's range bias on bare metal estimated with T_base_cam; null when not estimated.",
        },
        "range_bias_std_mm": {**_NUMBER_OR_NULL, "description": "Its 1-sigma."},
        "range_bias_source": {
            "type": "string",
            "description": "What fixed it: steps (the metal face over the painted shoulder), pairs (the spread of the rays), or both; empty when not estimated.",
        },
    },
    ("verdict", "passed", "reasons", "warnings", "pairs"),
)

_MATRIX4 = {
    "type": "array",
    "items": _vector("A row.", 4),
    "minItems": 4,
    "maxItems": 4,
    "description": "4x4 homogeneous transform, rows, metres.",
}

_ROBOT2_CALIBRATION = _object(
    "The cell's second robot calibrated through the same scanner (a calibrate job with robot2): Eq. 6b for each "
    "robot with the camera fixed, and Eq. 6c, T_base1_base2 = T_base1_cam T_base2_cam^-1.",
    {
        "T_base2_cam": _MATRIX4,
        "T_base1_base2": _MATRIX4,
        "quality": _QUALITY,
        "translation_std_mm": _vector(
            "1-sigma of robot 2's verification position placed in base 1 by T_base1_base2 (where the robots meet), along "
            "robot 1's base axes, mm: the scanner's noise through both calibrations, not the arms' absolute error.",
            3,
        ),
        "rotation_std_deg": _vector("Its rotation 1-sigma about robot 1's base axes, deg.", 3),
        "from_drawing_mm": {"type": "number", "description": "How far the calibrated base 2 lies from robot2.base_pose, mm."},
        "from_drawing_deg": {"type": "number", "description": "The angle between them, deg."},
        "cost_mm": {"type": ["number", "null"], "description": "Final cost of robot 2's Algorithm 1, mm."},
        "pairs": {"type": "integer", "minimum": 0, "description": "Robot 2's pairs in the final pool."},
        "dataset": {"type": "string", "description": "Path of robot 2's saved dataset."},
        "stored": {"enum": ["estimate", "compensated"], "description": "T_base2_cam is the estimate or Eq. 21's."},
    },
    ("T_base2_cam", "T_base1_base2", "quality"),
)

_CALIBRATION = _object(
    "A calibration of the scanner: T_base_cam, the pose of the camera in the robot base frame; for a scanner on "
    "the arm (mount link1-3, Eq. 8) T_linkN_cam, its pose in that link's frame, with the robot's DH table.",
    {
        "job": _JOB_ID,
        "T_base_cam": _MATRIX4,
        "mount": {"enum": list(SCANNER_MOUNTS), "description": "Where the scanner is fixed (absent: the base)."},
        "dh": _object(
            "The robot's DH table the link frame is computed with (m, rad).",
            {k: _vector(k, 6) for k in ("d", "a", "alpha")},
            ("d", "a", "alpha"),
        ),
        **{f"T_{m}_cam": _MATRIX4 for m in SCANNER_MOUNTS[1:]},
        "cost_mm": {"type": ["number", "null"], "description": "Final cost of Algorithm 1, mm."},
        "pairs": {"type": "integer", "minimum": 0, "description": "Pairs in the final pool."},
        "accepted": {"type": "string", "description": "When it became current, UTC ISO 8601."},
        "dataset": {"type": "string", "description": "Path of the saved dataset."},
        "method": {"type": "string", "description": "The estimator that gave T_base_cam (robust, svd, algorithm1)."},
        "stored": {
            "enum": ["estimate", "compensated"],
            "description": "T_base_cam is the estimate, or the estimate compensated by Eq. 21.",
        },
        "quality": _QUALITY,
        "forced": {"type": "boolean", "description": "Accepted with force despite a failed quality verdict."},
        "range_bias": {
            "enum": ["estimate", "none"],
            "description": "Whether the scanner's range bias on metal was estimated (calibration.range_bias).",
        },
        "range_bias_mm": {
            "type": "number",
            "description": "The scanner's range bias on bare metal, mm (0 when not estimated): every scan placed with this "
            "calibration has its points moved back along their rays by it.",
        },
        "range_bias_std_mm": {**_NUMBER_OR_NULL, "description": "Its 1-sigma, mm; null when not estimated."},
        "robot2": _ROBOT2_CALIBRATION,
    },
    ("job", "accepted"),
)

_TOOL_QUALITY = _object(
    "The verdict on a tool calibration (celld.calib.toolcal): why, each pose's residual and whether it is an "
    "outlier, the noise, the orientation spread and the tip's 1-sigma.",
    {
        "verdict": {"enum": list(TOOL_VERDICTS), "description": "Only ok passes; accept refuses the others unless forced."},
        "passed": {"type": "boolean"},
        "reasons": {**_TEXTS, "description": "Why the verdict is not ok."},
        "warnings": {**_TEXTS, "description": "What does not fail the verdict but should be known."},
        "poses": {
            "type": "array",
            "description": "Every pose with a tip measurement: residual against the fit, used, outlier, and why.",
            "items": _object(
                "One pose.",
                {
                    "id": {"type": "string"},
                    "residual_mm": _NUMBER_OR_NULL,
                    "used": {"type": "boolean"},
                    "outlier": {"type": "boolean"},
                    "reason": {"type": "string"},
                },
                ("id", "residual_mm", "used", "outlier", "reason"),
            ),
        },
        "outliers": {"type": "array", "items": {"type": "string"}, "description": "Ids of the outliers."},
        "n_used": {"type": "integer", "minimum": 0},
        "rms_mm": {**_NUMBER_OR_NULL, "description": "RMS residual of the poses used."},
        "sigma_mm": {**_NUMBER_OR_NULL, "description": "Noise per axis the uncertainty uses."},
        "sigma_source": {"enum": ["residuals", "floor"]},
        "spread_deg": {
            **_NUMBER_OR_NULL,
            "description": "Orientation spread of the poses used along the worst-fixed direction of the tip.",
        },
        "spread_axis_tcp": _vector("That direction, TCP frame.", 3),
        "tip_std_mm": {
            "type": "array",
            "items": _NUMBER_OR_NULL,
            "minItems": 3,
            "maxItems": 3,
            "description": "1-sigma of the tip along TCP x, y, z.",
        },
        "offset_base_mm": _vector("Where the scanner and the arm disagree at the tool's place (solved with the tip), base frame, mm.", 3),
        "offset_std_mm": {"type": "array", "items": _NUMBER_OR_NULL, "minItems": 3, "maxItems": 3},
        "missed": {"type": "array", "items": {"type": "object"}, "description": "Poses whose capture showed no tip, and why."},
        "torch": {
            "type": "object",
            "description": "The torch's own report in the same keys (verdict, reasons, poses, tip_std_mm for its 1-sigma, missed); "
            "its reasons are the job's, prefixed 'torch:', when the tip's verdict is ok and the torch's is not.",
        },
    },
    ("verdict", "passed", "reasons", "warnings", "poses"),
)

_TOOL_CALIBRATION = _object(
    "A tool calibration: the SRM tip (and the torch) measured in the TCP frame; it overrides tool.tip_tcp_mm "
    "(and, with torch_measured, the torch offset and the tool's x axis) once current.",
    {
        "job": _JOB_ID,
        "tip_tcp_mm": _vector("The tip's centre in the TCP frame, mm.", 3),
        "tip_std_mm": {"type": "array", "items": _NUMBER_OR_NULL, "minItems": 3, "maxItems": 3, "description": "Its 1-sigma, mm."},
        "nominal_tip_tcp_mm": _vector("The config's tool.tip_tcp_mm when it was measured.", 3),
        "delta_mm": _vector("Measured minus configured tip, TCP frame, mm.", 3),
        "torch_tcp_mm": _vector(
            "The torch point (the wire's end), TCP frame, mm: measured when torch_measured, else torch_offset along -x of the tool frame.",
            3,
        ),
        "torch_measured": {
            "type": "boolean",
            "description": "The torch was measured: a weld takes torch_offset and the tool's x axis from the tip and this point.",
        },
        "torch_std_mm": {"type": "array", "items": _NUMBER_OR_NULL, "minItems": 3, "maxItems": 3, "description": "Its 1-sigma, mm."},
        "nominal_torch_tcp_mm": _vector("Where the config put the torch when it was measured, TCP frame, mm.", 3),
        "torch_delta_mm": _vector("Measured minus configured torch, TCP frame, mm.", 3),
        "calibration_job": {"type": "string", "description": "The hand-eye calibration the tips were placed with."},
        "poses": {"type": "integer", "minimum": 0, "description": "Poses with a tip measurement."},
        "quality": _TOOL_QUALITY,
        "accepted": {"type": "string", "description": "When it became current, UTC ISO 8601."},
        "forced": {"type": "boolean", "description": "Accepted with force despite a failed verdict."},
    },
    ("job", "tip_tcp_mm", "quality"),
)

_PROGRESS = _object(
    "Progress of one job, published on progress/<job>. seq counts from 0 without gaps at "
    "the sender; a gap at the receiver means dropped events (ask status).",
    {
        "job": _JOB_ID,
        "kind": {"enum": list(JOB_KINDS)},
        "seq": {"type": "integer", "minimum": 0},
        "state": {"enum": list(JOB_STATES)},
        "stage": {
            "type": "string",
            "description": "What the job is doing: verify, pair, solve, scan, seam, approach, touch, track, retract, ...",
        },
        "fraction": {"type": ["number", "null"], "minimum": 0.0, "maximum": 1.0, "description": "Done so far, 0..1, if known."},
        "message": {"type": "string"},
        "data": {"type": "object", "description": 'Stage figures, e.g. {"pair": 3, "cost_mm": 0.41}.'},
    },
    ("job", "seq", "state", "stage"),
)

# The operator's recovery commands (celld.robot.dashboard.ACTIONS).
ROBOT_ACTIONS = ("unlock", "power-on", "brake-release", "close-popup")
ROBOT_CONDITIONS = ("ready", "protective_stop", "emergency_stop", "safety_fault", "power_off", "brakes", "booting", "link_lost", "unknown")

_ROBOT_CONDITION = _object(
    "Whether the robot can move and, if not, why and what clears it (dashboard server, RTDE link, the motion process's last exit).",
    {
        "ready": {"type": "boolean"},
        "state": {"enum": list(ROBOT_CONDITIONS)},
        "reason": {"type": "string", "description": "Why the robot cannot move; empty when ready."},
        "remedy": {"type": "string", "description": "What clears it, e.g. `celld robot unlock`."},
        "link": {"enum": ["up", "down", "unknown"], "description": "The RTDE link."},
        "robot2_link": {"enum": ["up", "down", "unknown"], "description": "The second robot's RTDE link, when the cell has one."},
        "mode": {"type": ["string", "null"], "description": "Dashboard robot mode (RUNNING, IDLE, POWER_OFF, ...), null when not read."},
        "safety": {
            "type": ["string", "null"],
            "description": "Dashboard safety status (NORMAL, PROTECTIVE_STOP, ...), null when not read.",
        },
        "dashboard": {"type": "string", "description": "reachable, or why the dashboard server was not."},
    },
    ("ready", "state", "reason", "remedy"),
)

_STATE_ROBOT = _object(
    "The robot state, decimated to bus.state_rate_hz.",
    {
        "t_ns": {"type": "integer", "minimum": 0, "description": "Sample time, monotonic clock of the cell, ns."},
        "link": {"enum": ["up", "down"]},
        "q": _vector("Joint positions, rad.", 6),
        "qd": _vector("Joint speeds, rad/s.", 6),
        "tcp_pose": _vector("TCP pose in the base frame [x, y, z, rx, ry, rz], m and rad.", 6),
        "tcp_speed": _vector("TCP twist in the base frame, m/s and rad/s.", 6),
        "mode": {"type": "string", "description": "Robot mode as the controller reports it."},
        "safety": {"type": "string", "description": "Safety mode as the controller reports it."},
    },
    ("t_ns", "link"),
)

_STATE_TACTILE = _object(
    "The SRM deformation, decimated to bus.state_rate_hz.",
    {
        "t_ns": {"type": "integer", "minimum": 0, "description": "Sample time, monotonic clock of the cell, ns."},
        "valid": {"type": "boolean", "description": "The tag was found in the frame."},
        "contact": {"type": "boolean"},
        "delta": _vector("Deformation of the SRM tip in the tool frame, m.", 3),
    },
    ("t_ns", "valid"),
)

_BODIES: dict[str, dict[str, Any]] = {
    # requests
    "submit": _SUBMIT,
    "status": _object("Cell status, or one job's record when job is given.", {"job": _JOB_ID}),
    "cancel": _object("Cancel a queued or running job; the robot stops first.", {"job": _JOB_ID, "reason": _text("Why.")}, ("job",)),
    "list": _object(
        "Jobs in the journal, newest first.",
        {
            "limit": _integer("How many.", 1, 1000),
            "state": {"enum": list(JOB_STATES)},
            "kind": {"enum": list(JOB_KINDS)},
        },
    ),
    "accept": _object(
        "Make a finished calibrate job's result the current calibration, or a finished tool-calibrate job's the "
        "current tool calibration. A result whose verdict is not ok is refused unless force is true.",
        {
            "job": _JOB_ID,
            "force": {"type": "boolean", "default": False, "description": "Accept even though the quality verdict is not ok."},
        },
        ("job",),
    ),
    "calibration": _object("The current calibration.", {}),
    "robot": _object(
        "An operator's recovery command through the robot's dashboard server; refused while a job runs.",
        {
            "action": {
                "enum": list(ROBOT_ACTIONS),
                "description": "unlock a protective stop, power the arm on, release its brakes, close the safety pop-up.",
            }
        },
        ("action",),
    ),
    "result": _object(
        "A finished job's result. The job id is the last chunk of the key (<req>/result/<job>); the payload is empty or {}.", {}
    ),
    # replies
    "error-reply": _object("A refused request.", {"ok": {"const": False}, "error": _ERROR}, ("ok", "error")),
    "submit-reply": _reply(
        "A job was taken: it runs now (position 0) or waits in the queue. A replayed request_id "
        "gives the original job in its state now (it may have ended) and replayed: true.",
        {
            "job": _JOB_ID,
            "state": {"enum": list(JOB_STATES)},
            "position": {"type": "integer", "minimum": 0, "description": "0: runs now (or no longer waits); n: n-th in the queue."},
            "replayed": {"type": "boolean", "description": "True when the request_id named a job already made."},
        },
        ("job", "state", "position"),
    ),
    "status-reply": _reply(
        "The state of the cell.",
        {
            "cell": {"type": "string"},
            "state": {"enum": ["starting", "idle", "running", "fault", "stopping"]},
            "running": {"type": ["string", "null"], "description": "Id of the running job."},
            "queued": {"type": "array", "items": _JOB_ID, "description": "Ids of waiting jobs, next first."},
            "robot_link": {"enum": ["up", "down", "unknown"]},
            "robot": _ROBOT_CONDITION,
            "calibration": {"type": ["string", "null"], "description": "Job id of the current calibration."},
            "uptime_s": {"type": "number", "minimum": 0},
            "version": {"type": "string"},
            "message": {"type": "string", "description": "Why the cell is in fault (robot link, storage), else empty."},
            "storage": _STORAGE,
            "loop": _LOOP,
        },
        ("cell", "state", "running", "queued"),
    ),
    "job-reply": _reply("One job's record (status with a job id).", {"record": _JOB_RECORD}, ("record",)),
    "cancel-reply": _reply("The job's state after the request.", {"job": _JOB_ID, "state": {"enum": list(JOB_STATES)}}, ("job", "state")),
    "result-reply": _reply(
        "A finished job's result. result is the JSON the job wrote (null if it wrote none, or if it is "
        "larger than the inline limit: then too_large is true and the file stays on the cell PC at path). "
        "Bulky arrays (a weld's paths, a calibration's clouds) are files of the job (files), not sent here.",
        {
            "job": _JOB_ID,
            "kind": {"enum": list(JOB_KINDS)},
            "state": {"enum": list(TERMINAL_STATES)},
            "reason": {"type": "string"},
            "result": {"type": ["object", "null"], "description": "The result document."},
            "bytes": {"type": "integer", "minimum": 0, "description": "Size of the result file."},
            "too_large": {"type": "boolean", "description": f"The result is over {MAX_RESULT_BYTES} bytes and was not sent."},
            "path": {"type": ["string", "null"], "description": "The result file on the cell PC."},
            "files": {"type": "array", "items": _FILE, "description": "Files the job left on the cell PC (not sent)."},
        },
        ("job", "kind", "state", "reason", "result", "too_large", "files"),
    ),
    "list-reply": _reply("Jobs, newest first.", {"jobs": {"type": "array", "items": _JOB_RECORD}}, ("jobs",)),
    "accept-reply": _reply(
        "The new current calibration (calibration, for a calibrate job) or tool calibration (tool, for a tool-calibrate job).",
        {"job": _JOB_ID, "kind": {"enum": ["calibrate", "tool-calibrate"]}, "calibration": _CALIBRATION, "tool": _TOOL_CALIBRATION},
        ("job",),
    ),
    "calibration-reply": _reply(
        "The current calibration, null if there is none; and the current tool calibration (tool), null if there is none.",
        {
            "calibration": {"type": ["object", "null"], **{k: v for k, v in _CALIBRATION.items() if k != "type"}},
            "tool": {"type": ["object", "null"], **{k: v for k, v in _TOOL_CALIBRATION.items() if k != "type"}},
        },
        ("calibration",),
    ),
    "robot-reply": _reply(
        "The dashboard's reply and the robot's condition after the command.",
        {"action": {"enum": list(ROBOT_ACTIONS)}, "reply": {"type": "string"}, "robot": _ROBOT_CONDITION},
        ("action", "reply", "robot"),
    ),
    # publications
    "progress": _PROGRESS,
    "state-robot": _STATE_ROBOT,
    "state-tactile": _STATE_TACTILE,
}


def _exported(name: str, body: dict[str, Any]) -> dict[str, Any]:
    return {"$schema": DIALECT, "$id": f"urn:celld:bus:{name}", "title": f"celld {name}", **body}


def _checked(schemas: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    # The checker enforces exactly what is exported: refuse a keyword it would skip.
    for name, s in schemas.items():
        check_schema(s, f"{name}#")
    return schemas


SCHEMAS: Mapping[str, dict[str, Any]] = _checked({name: _exported(name, body) for name, body in _BODIES.items()})

# Requests, by queryable name.
REQUESTS = ("submit", "status", "cancel", "list", "accept", "calibration", "robot", "result")


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
    dry_run: bool = False
    ref: str = ""
    request_id: str = ""  # the client's id of the submit
    kind: ClassVar[str] = "weld"


@dataclass(frozen=True)
class MoveJob:
    """A move to joint positions (``space="joint"``, rad) or a TCP pose (``"cartesian"``)."""

    space: str
    target: Pose6
    speed_scale: float = 0.5
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


Job = CalibrateJob | WeldJob | MoveJob | HealthJob | ToolCalibrateJob


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
    action: str  # one of ROBOT_ACTIONS


@dataclass(frozen=True)
class ResultRequest:
    job: str


Request = Job | StatusRequest | CancelRequest | ListRequest | AcceptRequest | CalibrationRequest | RobotRequest | ResultRequest


# -- decoding ------------------------------------------------------------------------


def _refuse_constant(name: str) -> Any:
    raise JobError("$", f"expected finite numbers, got {name} (not JSON)")


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise JobError("$", f"expected finite numbers, got {describe(text)} (overflows a double)")
    return value


def _parse_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise JobError("$", f"expected integers of at most {MAX_INT_DIGITS} digits, got one of {len(text)}")
    return int(text)


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise JobError("$", f"duplicate field {key!a}")
        out[key] = value
    return out


def _check_tree(value: Any) -> None:
    """Refuse nesting deeper than MAX_DEPTH and strings that are not valid Unicode."""
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, (dict, list)):
            if depth >= MAX_DEPTH:
                raise JobError("$", f"expected at most {MAX_DEPTH} levels of nesting, got more")
            if isinstance(node, dict):
                for k, v in node.items():
                    _check_unicode(k)
                    stack.append((v, depth + 1))
            else:
                stack.extend((v, depth + 1) for v in node)
        elif isinstance(node, str):
            _check_unicode(node)


def _check_unicode(text: str) -> None:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as exc:
        raise JobError("$", f"expected valid Unicode text, got a lone surrogate in {describe(text)}") from exc


def load_json(raw: bytes | bytearray | memoryview) -> Any:
    """Decode one request payload into JSON values, refusing hostile input.

    An empty payload is ``{}``.

    Raises
    ------
    JobError
        ``field`` is ``"$"``; the reason names the problem (too large, not
        UTF-8, not JSON, NaN, duplicate key, too deep, ...).
    """
    if not isinstance(raw, (bytes, bytearray, memoryview)):
        raise JobError("$", f"expected bytes, got {type(raw).__name__}")
    size = len(raw)
    if size > MAX_PAYLOAD_BYTES:
        raise JobError("$", f"expected at most {MAX_PAYLOAD_BYTES} bytes, got {size}")
    if size == 0:
        return {}
    try:
        text = bytes(raw).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise JobError("$", f"expected UTF-8 text, got byte 0x{exc.object[exc.start]:02x} at offset {exc.start}") from exc
    try:
        value = json.loads(
            text,
            parse_constant=_refuse_constant,
            parse_float=_parse_float,
            parse_int=_parse_int,
            object_pairs_hook=_no_duplicates,
        )
    except json.JSONDecodeError as exc:
        raise JobError("$", f"expected JSON, got an error at line {exc.lineno} column {exc.colno}: {exc.msg}") from exc
    except RecursionError as exc:
        raise JobError("$", f"expected at most {MAX_DEPTH} levels of nesting, got far more") from exc
    except ValueError as exc:  # e.g. a number the int parser refuses
        raise JobError("$", f"expected JSON numbers, got {describe(str(exc))}") from exc
    _check_tree(value)
    return value


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


_JOB_BUILDERS: dict[str, Callable[[Mapping[str, Any]], Job]] = {
    "calibrate": _build_calibrate,
    "weld": _build_weld,
    "move": _build_move,
    "health": _build_health,
    "tool-calibrate": _build_tool_calibrate,
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
        The queryable's name, one of :data:`REQUESTS`.
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
    validate(_JOB_ID, job, "$.job")
    return ResultRequest(job=job)


def parse_submit(raw: bytes | bytearray | memoryview) -> Job:
    """:func:`parse` for ``submit``: bytes in, a frozen job value out."""
    job: Job = parse("submit", raw)
    return job


def check_message(name: str, value: Any) -> None:
    """Validate a decoded message (a reply, an event) against ``SCHEMAS[name]``.

    Raises
    ------
    JobError
        With the JSON path of the offending field and the reason.
    """
    validate(SCHEMAS[name], value)


# -- encoding ------------------------------------------------------------------------


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
        if job.dry_run:
            m["dry_run"] = True
    elif isinstance(job, MoveJob):
        key = "q" if job.space == "joint" else "pose"
        m["target"] = {"space": job.space, key: list(job.target)}
        m["speed_scale"] = job.speed_scale
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


def _numpy_to_json(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def encode(message: Mapping[str, Any]) -> bytes:
    """A message as compact UTF-8 JSON; numpy arrays and scalars become lists and numbers.

    Raises
    ------
    ValueError
        NaN or an infinity (they are not JSON).
    TypeError
        A value JSON cannot represent.
    """
    return json.dumps(message, separators=(",", ":"), allow_nan=False, default=_numpy_to_json).encode("utf-8")


def error_reply(field: str, reason: str) -> dict[str, Any]:
    """The reply to a refused request."""
    return {"ok": False, "error": {"field": field, "reason": reason}}
