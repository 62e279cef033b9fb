"""The bus's messages as JSON Schema documents, and the bundle the cell exports.

Every message on the bus is a UTF-8 JSON object. Its schema (JSON Schema draft
2020-12) is a plain dict made here (:func:`message_schemas`), exported for
other languages by ``celld bus schema --out DIR``
(:func:`celld.bus.asyncapi.export_schemas`), and the checker of
:mod:`celld.bus.checker` enforces it, so the exported contract and the
enforced one are the same object.

Requests (what a client sends, keyed by the queryable's name; each is built
into a value by :mod:`celld.bus.requests`):

========================  ============================================
queryable                 payload
========================  ============================================
``submit``                ``{"kind": "calibrate" | "tool-calibrate" |
                          "weld" | "move" | "health" | "tool-calibrate" | "verify", ...}``
``status``                ``{}`` or ``{"job": ID}``
``cancel``                ``{"job": ID}``
``list``                  ``{"limit": N, "state": S, "kind": K}``
``accept``                ``{"job": ID, "force": B}`` (a calibrate or
                          tool-calibrate job)
``calibration``           ``{}``
``robot``                 ``{"action": "unlock" | "power-on" |
                          "brake-release" | "close-popup"}``
``result/<job>``          ``{}`` (the job is in the key)
========================  ============================================

An empty payload counts as ``{}``. Every rule a request must follow is in its
schema (the "poses or n_poses, not both" rule of a calibrate job is a
``not``/``required`` there), so a client that validates against the exported
schemas is refused by the cell only for the cell's own reasons (a full queue,
an unknown workpiece, a storage fault, its role). Replies are ``{"ok": true, ...}`` or
``{"ok": false, "error": {"field": PATH, "reason": TEXT}}``; publications are
progress events per job and the robot and tactile state. Their schemas are
made here too (``*-reply``, ``progress``, ``state-robot``,
``state-tactile``); :func:`check_message` validates one.

What the bus carries but others build (:class:`Documents`): each job kind's
result (the ``result-reply``'s ``result``, chosen by the job's ``kind``; also
exported alone as ``result-<kind>``), the current calibration and the current
tool calibration (``accept-reply``, ``calibration-reply``). Their schemas live
beside the code that builds them, above the bus; the daemon passes them in
(:data:`celld.daemon.results.BUNDLE`, what ``celld bus schema`` exports).
:data:`SCHEMAS`, the bus's own, has them as objects of any shape: the requests
in it are the exported ones, and the replies' envelopes too.

Units: messages use the units of the config file (``e_required_mm``,
``delta_d_mm``, ``v_const_mm_s``); poses are UR poses ``[x, y, z, rx, ry, rz]``
in metres and a rotation vector in radians, in the robot base frame; joint
positions are radians.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from celld.bus.checker import check_schema, validate
from celld.config.tactile import SERVO_BOUNDS, servo_key
from celld.robot.dashboard import ACTIONS, CONDITION_SCHEMA, CONDITIONS
from celld.schemadoc import free, integer, nullable, number, obj, text, vector, with_properties

# Most calibration poses one job may give.
MAX_POSES = 1000
# Job ids are one zenoh key chunk: letters, digits, '-' and '_'.
JOB_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$"
# Dialect of every exported schema.
DIALECT = "https://json-schema.org/draft/2020-12/schema"
# A client's id of a submit: letters, digits and '_', '.', ':', '-' (a UUID fits).
REQUEST_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,63}$"
# Largest result sent inline by the result queryable, bytes of JSON.
MAX_RESULT_BYTES = 1024 * 1024

JOB_KINDS = ("calibrate", "weld", "move", "health", "tool-calibrate", "verify")
JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled", "interrupted")
TERMINAL_STATES = ("succeeded", "failed", "cancelled", "interrupted")
HEALTH_CHECKS = ("all", "robot", "scanner", "tactile")
# Most poses one tool calibration may visit.
MAX_TOOL_POSES = 100
# The operator's recovery commands, and what the robot's condition may be (celld.robot.dashboard's).
ROBOT_ACTIONS = tuple(ACTIONS)
ROBOT_CONDITIONS = CONDITIONS
# Requests, by queryable name.
REQUESTS = ("submit", "status", "cancel", "list", "accept", "calibration", "robot", "result")


# -- schema building blocks ---------------------------------------------------------


def _servo_number(name: str, desc: str) -> dict[str, Any]:
    """A job's override of a servo (or tool) value: the config's key, unit and bound (celld.config.SERVO_BOUNDS)."""
    key, scale = servo_key(name)
    b = SERVO_BOUNDS[name]
    section = "tool" if name == "torch_offset" else "servo"
    return number(f"{desc} (default: {section}.{key}).", b.lo / scale, b.hi / scale, open_lo=b.open_lo)


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


# A job id (the result request checks the one in its key against it, celld.bus.requests).
JOB_ID = {"type": "string", "pattern": JOB_ID_PATTERN, "description": "A job id, as returned by submit."}
_REF = text("The client's own reference for the job (an order number); echoed in status.", 128)
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
_JOINTS = vector("Joint positions, rad.", 6, -2 * math.pi, 2 * math.pi)


def _submit_branch(kind: str, desc: str, properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    props = {"kind": {"const": kind, "description": "The job kind."}, **properties, "ref": _REF, "request_id": _REQUEST_ID}
    return obj(desc, props, ("kind", *required))


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
        "n_poses": integer("How many calibration poses to generate (default: calibration.n_poses).", 4, MAX_POSES),
        "e_required_mm": number("Cost at which Algorithm 1 stops, mm (default: calibration.e_required_mm).", 0.0, 100.0),
        "k_max": integer("Most iterations of Algorithm 1 (default: calibration.k_max).", 1, 10_000),
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
        "seed": integer("Seed of the pose generator (default: a fresh one).", 0, 2**32 - 1),
        "robot2": {
            "type": "boolean",
            "default": False,
            "description": "Calibrate the cell's second robot ([robot2]) through the same scanner in the same job, after robot 1, "
            "and give T_base1_base2 (Eq. 5-6 with the camera fixed); its poses are generated (no poses).",
        },
        "arm_poses": integer(
            "After the hand-eye calibration, calibrate the arm's kinematics too from this many wide poses, fitted with "
            "T_base_cam (0: none; default: calibration.arm_poses). Needs a scanner on the base, not with robot2.",
            0,
            MAX_POSES,
        ),
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
        "n_poses": integer("How many orientations to present the tool at (default 12).", 3, MAX_TOOL_POSES),
        "max_tilt_deg": number("Largest tilt of the finger from the pose facing the scanner, deg (default 20).", 2.0, 45.0),
        "tip_position": vector(
            "Where the tip is presented, base frame, m (default: the position of calibration.verification_pose, which the scanner sees).",
            3,
            -2.5,
            2.5,
        ),
        "seed": integer("Seed of the orientation generator (default 0).", 0, 2**32 - 1),
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
        "procedure": {
            "type": "string",
            "pattern": r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$",
            "description": "The weld procedure (a file <name>.toml in the cell's procedures directory) the power source "
            "welds with: set points, travel speed, the arc's sequence and the current and voltage windows; absent: the "
            "cell's weld.procedure. Needed by a cell with a [power_source] when the arc is on.",
        },
        "dry_run": _DRY_RUN,
    },
)

_MOVE_TARGET = {
    "type": "object",
    "description": "Where to move: joint positions, or a TCP pose in the base frame.",
    "oneOf": [
        obj("A joint target.", {"space": {"const": "joint"}, "q": _JOINTS}, ("space", "q")),
        obj("A Cartesian target of the TCP.", {"space": {"const": "cartesian"}, "pose": _pose("The TCP pose.")}, ("space", "pose")),
    ],
}

_MOVE = _submit_branch(
    "move",
    "A jerk-limited move to a joint or Cartesian target (checked against the cell's workspace).",
    {
        "target": _MOVE_TARGET,
        "speed_scale": number("Fraction of the configured speed limits.", 0.0, 1.0, open_lo=True),
        "robot": {
            "enum": [1, 2],
            "default": 1,
            "description": "The robot that moves: 1, or 2 on a cell with a second robot ([robot2]), whose TCP pose is in its "
            "own base frame and whose moves are checked against robot 1 where it stands.",
        },
    },
    ("target",),
)

_HEALTH = _submit_branch(
    "health",
    "Health check of the scanner, the robot link or the tactile camera.",
    {"check": {"enum": list(HEALTH_CHECKS), "default": "all", "description": "What to check."}},
)

_VERIFY = _submit_branch(
    "verify",
    "Verify the current calibration now: the flange seen at a few poses against where the calibration puts it. "
    "Failed, with the figure, when it does not hold; welds are then refused until a new calibration is accepted.",
    {},
)

_SUBMIT = {
    "type": "object",
    "description": "A job for the cell. The reply is submit-reply or error-reply.",
    "oneOf": [_CALIBRATE, _WELD, _MOVE, _HEALTH, _TOOL_CALIBRATE, _VERIFY],
}

_ERROR = obj(
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
    return obj(desc, {**ok, **properties}, ("ok", *required))


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
_LOOP = obj(
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


_JOB_RECORD = obj(
    "One job as the journal keeps it. Times are UTC wall clock, ISO 8601. A user who may not see "
    "the job in full (a viewer, or an operator looking at another user's job) gets it redacted: no "
    "params, ref, request_id, owner or result, and redacted: true.",
    {
        "id": JOB_ID,
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

# The state directory's storage (celld.daemon.storage): in the status reply and a health job's result.
STORAGE = obj(
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
        "budget_mb": {
            "type": "number",
            "minimum": 0,
            "description": "cell.storage_budget_mb: the most the state directory may hold (0: no budget).",
        },
        "used_mb": {
            "type": ["number", "null"],
            "description": "What the state directory held after the last job, MiB (null: not measured yet).",
        },
        "over_budget": {"type": "boolean", "description": "Still over the budget after pruning everything that may go."},
        "pruned": {"type": "integer", "minimum": 0, "description": "Artefacts the budget deleted since the daemon started."},
        "pruned_mb": {"type": "number", "minimum": 0, "description": "What they held, MiB."},
    },
    ("ok", "free_mb", "floor_mb", "fault", "last_error", "pending_writes", "budget_mb", "used_mb", "over_budget", "pruned", "pruned_mb"),
)

_FILE = obj(
    "A file a job left in the cell's state directory.",
    {
        "path": {"type": "string", "description": "Relative to the state directory (jobs/<job>/..., recordings/<job>.rrd)."},
        "bytes": {"type": "integer", "minimum": 0},
    },
    ("path", "bytes"),
)

# When a publication's event or sample happened, on the cell PC's clock (keep it synchronised: chrony or PTP).
WALL_TIME = {
    "type": "string",
    "pattern": r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\.\d{3}Z$",
    "description": "UTC wall clock, ISO 8601 to the millisecond (2026-12-04T13:25:41.423Z): when the event or the sample happened.",
}

_PROGRESS = obj(
    "Progress of one job, published on progress/<job>. seq counts from 0 without gaps at "
    "the sender; a gap at the receiver means dropped events (ask status).",
    {
        "job": JOB_ID,
        "kind": {"enum": list(JOB_KINDS)},
        "seq": {"type": "integer", "minimum": 0},
        "time": WALL_TIME,
        "state": {"enum": list(JOB_STATES)},
        "stage": {
            "type": "string",
            "description": "What the job is doing: verify, pair, solve, scan, seam, approach, touch, track, retract, ...",
        },
        "fraction": {"type": ["number", "null"], "minimum": 0.0, "maximum": 1.0, "description": "Done so far, 0..1, if known."},
        "message": {"type": "string"},
        "data": {"type": "object", "description": 'Stage figures, e.g. {"pair": 3, "cost_mm": 0.41}.'},
    },
    ("job", "seq", "time", "state", "stage"),
)

_ROBOT_CONDITION = with_properties(
    CONDITION_SCHEMA,
    {
        "link": {"enum": ["up", "down", "unknown"], "description": "The RTDE link."},
        "robot2_link": {"enum": ["up", "down", "unknown"], "description": "The second robot's RTDE link, when the cell has one."},
        "robot2_held": {
            "type": ["string", "null"],
            "description": "The other program that keeps the second robot (celld did not take it over), null when none.",
        },
        "mode": {"type": ["string", "null"], "description": "Dashboard robot mode (RUNNING, IDLE, POWER_OFF, ...), null when not read."},
        "safety": {
            "type": ["string", "null"],
            "description": "Dashboard safety status (NORMAL, PROTECTIVE_STOP, ...), null when not read.",
        },
        "dashboard": {"type": "string", "description": "reachable, or why the dashboard server was not."},
    },
    desc="Whether the robot can move and, if not, why and what clears it (dashboard server, RTDE link, the motion process's last exit).",
)

_STATE_ROBOT = obj(
    "The robot state, decimated to bus.state_rate_hz.",
    {
        "t_ns": {"type": "integer", "minimum": 0, "description": "Sample time, monotonic clock of the cell, ns."},
        "time": WALL_TIME,
        "link": {"enum": ["up", "down"]},
        "q": vector("Joint positions, rad.", 6),
        "qd": vector("Joint speeds, rad/s.", 6),
        "tcp_pose": vector("TCP pose in the base frame [x, y, z, rx, ry, rz], m and rad.", 6),
        "tcp_speed": vector("TCP twist in the base frame, m/s and rad/s.", 6),
        "mode": {"type": "string", "description": "Robot mode as the controller reports it."},
        "safety": {"type": "string", "description": "Safety mode as the controller reports it."},
    },
    ("t_ns", "time", "link"),
)

_STATE_TACTILE = obj(
    "The SRM deformation, decimated to bus.state_rate_hz.",
    {
        "t_ns": {"type": "integer", "minimum": 0, "description": "Sample time, monotonic clock of the cell, ns."},
        "time": WALL_TIME,
        "valid": {"type": "boolean", "description": "The tag was found in the frame."},
        "contact": {"type": "boolean"},
        "delta": vector("Deformation of the SRM tip in the tool frame, m.", 3),
    },
    ("t_ns", "time", "valid"),
)


@dataclass(frozen=True)
class Documents:
    """The schemas of what the bus carries but others build (module docstring).

    Attributes
    ----------
    results : mapping of job kind to schema
        The result document a job of each kind writes (every kind of :data:`JOB_KINDS`).
    calibration : schema
        The current calibration, as accept and the calibration request give it.
    tool : schema
        The current tool calibration.
    """

    results: Mapping[str, Mapping[str, Any]]
    calibration: Mapping[str, Any] = field(default_factory=lambda: free("A calibration of the scanner (its shape: the exported bundle's)."))
    tool: Mapping[str, Any] = field(default_factory=lambda: free("A tool calibration (its shape: the exported bundle's)."))


# What the bus knows of them alone: objects of any shape.
UNTYPED = Documents(
    {kind: free(f"The result document of a {kind} job (its shape: result-{kind} of the exported bundle).") for kind in JOB_KINDS}
)


def _result_reply(results: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The result reply: one branch per job kind, whose result is that kind's document (or null)."""

    def branch(kind: str) -> dict[str, Any]:
        return _reply(
            f"A finished {kind} job's result.",
            {
                "job": JOB_ID,
                "kind": {"const": kind},
                "state": {"enum": list(TERMINAL_STATES)},
                "reason": {"type": "string"},
                "result": nullable(
                    results[kind],
                    f"The result document the job wrote (result-{kind}); null if it wrote none (it failed, was cancelled or "
                    "interrupted before its end), or if it is larger than the inline limit (too_large).",
                ),
                "bytes": {"type": "integer", "minimum": 0, "description": "Size of the result file."},
                "too_large": {"type": "boolean", "description": f"The result is over {MAX_RESULT_BYTES} bytes and was not sent."},
                "path": {"type": ["string", "null"], "description": "The result file on the cell PC."},
                "files": {"type": "array", "items": _FILE, "description": "Files the job left on the cell PC (not sent)."},
            },
            ("job", "kind", "state", "reason", "result", "too_large", "files"),
        )

    return {
        "type": "object",
        "description": "A finished job's result. result is the JSON the job wrote, of its kind's shape (null if it wrote none, or if "
        "it is larger than the inline limit: then too_large is true and the file stays on the cell PC at path). "
        "Bulky arrays (a calibration's clouds, the recording) are files of the job (files), not sent here.",
        "oneOf": [branch(kind) for kind in JOB_KINDS],
    }


def _accept_reply(docs: Documents) -> dict[str, Any]:
    return {
        "type": "object",
        "description": "The new current calibration (calibration, for a calibrate job) or tool calibration (tool, for a tool-calibrate job).",
        "oneOf": [
            _reply(
                "A calibrate job accepted.",
                {"job": JOB_ID, "kind": {"const": "calibrate"}, "calibration": docs.calibration},
                ("job", "kind", "calibration"),
            ),
            _reply(
                "A tool-calibrate job accepted.",
                {"job": JOB_ID, "kind": {"const": "tool-calibrate"}, "tool": docs.tool},
                ("job", "kind", "tool"),
            ),
        ],
    }


def _bodies(docs: Documents) -> dict[str, dict[str, Any]]:
    return {
        # requests
        "submit": _SUBMIT,
        "status": obj("Cell status, or one job's record when job is given.", {"job": JOB_ID}),
        "cancel": obj("Cancel a queued or running job; the robot stops first.", {"job": JOB_ID, "reason": text("Why.")}, ("job",)),
        "list": obj(
            "Jobs in the journal, newest first.",
            {
                "limit": integer("How many.", 1, 1000),
                "state": {"enum": list(JOB_STATES)},
                "kind": {"enum": list(JOB_KINDS)},
            },
        ),
        "accept": obj(
            "Make a finished calibrate job's result the current calibration, or a finished tool-calibrate job's the "
            "current tool calibration. A result whose verdict is not ok is refused unless force is true.",
            {
                "job": JOB_ID,
                "force": {"type": "boolean", "default": False, "description": "Accept even though the quality verdict is not ok."},
            },
            ("job",),
        ),
        "calibration": obj("The current calibration.", {}),
        "robot": obj(
            "An operator's recovery command through the robot's dashboard server; refused while a job runs.",
            {
                "action": {
                    "enum": list(ROBOT_ACTIONS),
                    "description": "unlock a protective stop, power the arm on, release its brakes, close the safety pop-up.",
                }
            },
            ("action",),
        ),
        "result": obj(
            "A finished job's result. The job id is the last chunk of the key (<req>/result/<job>); the payload is empty or {}.", {}
        ),
        # replies
        "error-reply": obj("A refused request.", {"ok": {"const": False}, "error": _ERROR}, ("ok", "error")),
        "submit-reply": _reply(
            "A job was taken: it runs now (position 0) or waits in the queue. A replayed request_id "
            "gives the original job in its state now (it may have ended) and replayed: true.",
            {
                "job": JOB_ID,
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
                "queued": {"type": "array", "items": JOB_ID, "description": "Ids of waiting jobs, next first."},
                "robot_link": {"enum": ["up", "down", "unknown"]},
                "robot": _ROBOT_CONDITION,
                "calibration": {"type": ["string", "null"], "description": "Job id of the current calibration."},
                "uptime_s": {"type": "number", "minimum": 0},
                "version": {"type": "string"},
                "message": {"type": "string", "description": "Why the cell is in fault (robot link, storage), else empty."},
                "storage": STORAGE,
                "loop": _LOOP,
            },
            ("cell", "state", "running", "queued"),
        ),
        "job-reply": _reply("One job's record (status with a job id).", {"record": _JOB_RECORD}, ("record",)),
        "cancel-reply": _reply(
            "The job's state after the request.", {"job": JOB_ID, "state": {"enum": list(JOB_STATES)}}, ("job", "state")
        ),
        "result-reply": _result_reply(docs.results),
        "list-reply": _reply("Jobs, newest first.", {"jobs": {"type": "array", "items": _JOB_RECORD}}, ("jobs",)),
        "accept-reply": _accept_reply(docs),
        "calibration-reply": _reply(
            "The current calibration, null if there is none; and the current tool calibration (tool), null if there is none.",
            {
                "calibration": nullable(docs.calibration, "The current calibration, null if there is none."),
                "tool": nullable(docs.tool, "The current tool calibration, null if there is none."),
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
        # what the result reply carries, alone
        **{f"result-{kind}": dict(docs.results[kind]) for kind in JOB_KINDS},
    }


def _exported(name: str, body: dict[str, Any]) -> dict[str, Any]:
    return {"$schema": DIALECT, "$id": f"urn:celld:bus:{name}", "title": f"celld {name}", **body}


def message_schemas(docs: Documents = UNTYPED) -> dict[str, dict[str, Any]]:
    """The exported schema of every message by name, with ``docs``'s results and calibrations in them.

    Also ``result-<kind>``: each kind's result document alone (the result
    reply's ``result`` when its ``kind`` is that kind). Every schema is
    checked: the checker enforces exactly what is exported, so a keyword it
    would skip is refused here.

    Raises
    ------
    ValueError
        ``docs`` misses a job kind's result or names one that is not a job
        kind, or a schema uses a keyword the checker does not enforce.
    """
    if set(docs.results) != set(JOB_KINDS):
        raise ValueError(f"expected a result schema for each of {', '.join(JOB_KINDS)}, got {', '.join(sorted(docs.results))}")
    schemas = {name: _exported(name, body) for name, body in _bodies(docs).items()}
    for name, s in schemas.items():
        check_schema(s, f"{name}#")
    return schemas


# The bus's own: every job result and calibration an object of any shape (what the
# bus itself enforces, the requests, is the same in every bundle).
SCHEMAS: Mapping[str, dict[str, Any]] = message_schemas()


def check_message(name: str, value: Any, schemas: Mapping[str, Mapping[str, Any]] = SCHEMAS) -> None:
    """Validate a decoded message (a reply, an event) against ``schemas[name]``.

    ``schemas`` is the bus's own by default; the exported bundle
    (:data:`celld.daemon.results.BUNDLE`) checks each job kind's result too.

    Raises
    ------
    JobError
        With the JSON path of the offending field and the reason.
    KeyError
        No message of that name.
    """
    validate(schemas[name], value)
