"""The mapping from batches of ring records to recording columns (pure).

The motion process appends one record per cycle to its state ring, the
tactile process one per frame to its sample channel (numpy structured
dtypes, :mod:`celld.shm`). The recorder reads batches of those records
outside the loop and sends them as columns. This module says, in one table,
which field becomes which entity, with which series names and which scale;
it takes arrays and returns arrays.

The mapping is by exact field name and tolerant: a field the batch lacks is
skipped, a field the table does not name is reported in
:attr:`StateColumns.ignored`. Only a stamp field is required: ``t_ns`` (the
motion state) or ``stamp_ns`` (a tactile sample), ``time.monotonic_ns()``.

Default table (the motion ring's names, :data:`celld.motion.channels.STATE_DTYPE`,
and the tactile sample's, :data:`celld.tactile.sample.TACTILE_DTYPE`):

==============  ========  ================================  ===================
field           shape     entity                            recorded as
==============  ========  ================================  ===================
t_ns/stamp_ns   ()        the ``time`` timeline             s since t0
T_base_tcp      (4, 4)    /world/tcp                        transform
tcp_pose        (6,)      /world/tcp (if no T_base_tcp)     transform (UR pose)
tcp_speed       (6,)      /robot/v_tcp                      m/s, rad/s
q               (6,)      /robot/q                          rad
twist[0:3]      (6,)      /servo/v_r                        m/s
twist[3:6]      (6,)      /servo/omega                      rad/s
delta_tool      (3,)      /servo/delta                      m
delta_n         ()        /servo/delta_n                    m
delta_d         ()        /servo/delta_n (its target)       m
servo_phase     ()        /servo/phase                      the law's phase
contact         ()        /weld/contact                     ContactState
process_on      ()        /weld/arc                         0 off, 1 on
arc_phase       ()        /weld/arc_phase                   ArcPhase of the source's sequence
weld_current    ()        /arc/current                      A
weld_voltage    ()        /arc/voltage                      V
late_ns         ()        /motion/loop/late_ms              ms
period_ns       ()        /motion/loop/period_ms            ms
work_ns         ()        /motion/loop/work_ms              ms
overruns        ()        /motion/loop/overruns             count
state_age_ns    ()        /motion/state_age_ms              ms
tactile_age_ns  ()        /motion/tactile_age_ms            ms
status          ()        /motion/status                    ControlStatus
==============  ========  ================================  ===================

``twist`` is the twist the loop sent: during a seam-tracking servo it is
Algorithm 2's command (V_r, omega) after the jerk limiter (lines 8, 13, 14),
during a move it is the move's.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from celld.errors import InputError
from celld.recording import layout

# Fields that carry a record's time.monotonic_ns() stamp, in order of preference.
STAMP_FIELDS = ("t_ns", "stamp_ns")
# Pose fields, in order of preference: a (4, 4) transform, else a UR pose.
POSE_MATRIX_FIELD = "T_base_tcp"
POSE_UR_FIELD = "tcp_pose"


class Series(NamedTuple):
    """One ring field (or a slice of its components) recorded as a time series.

    Attributes
    ----------
    field : str
        Field name in the ring dtype.
    entity : str
        Entity path of the series.
    names : tuple of str
        One legend name per recorded component.
    scale : float
        Recorded value = field value * scale (e.g. 1e-6 for ns to ms).
    components : tuple of int or None
        ``(start, stop)`` of the components to record; None for all.
    """

    field: str
    entity: str
    names: tuple[str, ...]
    scale: float = 1.0
    components: tuple[int, int] | None = None


_MS = 1e-6  # ms per ns
DEFAULT_SERIES: tuple[Series, ...] = (
    Series("tcp_speed", layout.ROBOT_V_TCP, ("vx", "vy", "vz", "wx", "wy", "wz")),
    Series("q", layout.ROBOT_Q, ("q1", "q2", "q3", "q4", "q5", "q6")),
    Series("twist", layout.SERVO_V_R, ("x", "y", "z"), components=(0, 3)),
    Series("twist", layout.SERVO_OMEGA, ("wx", "wy", "wz"), components=(3, 6)),
    Series("delta_tool", layout.SERVO_DELTA, ("tangential", "normal", "out of plane")),
    Series("delta_n", f"{layout.SERVO_DELTA_N}/delta_n", ("delta_n",)),
    Series("delta_d", f"{layout.SERVO_DELTA_N}/delta_d", ("delta_d",)),
    Series("servo_phase", layout.SERVO_PHASE, ("phase",)),
    Series("contact", layout.WELD_CONTACT, ("contact",)),
    Series("process_on", layout.WELD_ARC, ("arc",)),
    Series("arc_phase", layout.WELD_ARC_PHASE, ("phase",)),
    Series("weld_current", layout.WELD_CURRENT, ("current",)),
    Series("weld_voltage", layout.WELD_VOLTAGE, ("voltage",)),
    Series("late_ns", f"{layout.MOTION_LOOP}/late_ms", ("late",), _MS),
    Series("period_ns", f"{layout.MOTION_LOOP}/period_ms", ("period",), _MS),
    Series("work_ns", f"{layout.MOTION_LOOP}/work_ms", ("work",), _MS),
    Series("overruns", f"{layout.MOTION_LOOP}/overruns", ("overruns",)),
    Series("state_age_ns", "/motion/state_age_ms", ("robot state age",), _MS),
    Series("tactile_age_ns", "/motion/tactile_age_ms", ("tactile age",), _MS),
    Series("status", layout.MOTION_STATUS, ("status",)),
)


class SeriesColumn(NamedTuple):
    """The values of one series over a batch: ``values`` (n, k), float64."""

    entity: str
    names: tuple[str, ...]
    values: np.ndarray


class StateColumns(NamedTuple):
    """A batch of records split into columns.

    Attributes
    ----------
    stamp_ns : numpy.ndarray
        (n,) int64, ``time.monotonic_ns()`` of each record.
    T_base_tcp : numpy.ndarray or None
        (n, 4, 4) TCP poses in the base frame, None when the batch has no pose field.
    series : tuple of SeriesColumn
        The series present in the batch, in table order.
    ignored : tuple of str
        Fields of the batch that the table does not map.
    """

    stamp_ns: np.ndarray
    T_base_tcp: np.ndarray | None
    series: tuple[SeriesColumn, ...]
    ignored: tuple[str, ...]


def _component_names(spec: Series, width: int) -> tuple[str, ...]:
    if width == len(spec.names):
        return spec.names
    if width < len(spec.names):
        return spec.names[:width]
    return tuple(f"{spec.field}[{i}]" for i in range(width))


def state_columns(batch: np.ndarray, series: tuple[Series, ...] = DEFAULT_SERIES) -> StateColumns:
    """Split a batch of ring records into a pose column and series columns.

    Parameters
    ----------
    batch : numpy.ndarray
        (n,) structured array of ring records with a stamp field (``t_ns`` or ``stamp_ns``).
    series : tuple of Series
        The field table; :data:`DEFAULT_SERIES` unless the ring names its fields otherwise.

    Returns
    -------
    StateColumns
        Fresh arrays; ``batch`` is not modified.

    Raises
    ------
    InputError
        ``batch`` is not a 1-D structured array with a stamp field, or a
        mapped field has a shape the table cannot record (more than one
        trailing axis, too few components, a pose of the wrong shape).
    """
    if not isinstance(batch, np.ndarray) or batch.dtype.names is None or batch.ndim != 1:
        got = getattr(batch, "dtype", type(batch).__name__)
        raise InputError(f"state batch: expected a 1-D numpy structured array of ring records, got {got}")
    fields = batch.dtype.names
    stamp_field = next((f for f in STAMP_FIELDS if f in fields), None)
    if stamp_field is None:
        raise InputError(f"state batch: expected a stamp field ({' or '.join(STAMP_FIELDS)}), the record has {', '.join(fields)}")
    stamp_ns = batch[stamp_field].astype(np.int64)
    used = {stamp_field, POSE_MATRIX_FIELD, POSE_UR_FIELD}

    T_base_tcp = None
    if POSE_MATRIX_FIELD in fields:
        T = np.asarray(batch[POSE_MATRIX_FIELD], dtype=np.float64)
        if T.shape[1:] != (4, 4):
            raise InputError(f"state batch: {POSE_MATRIX_FIELD} must be (4, 4) per record, got {T.shape[1:]}")
        T_base_tcp = T.copy()
    elif POSE_UR_FIELD in fields:
        pose = np.asarray(batch[POSE_UR_FIELD], dtype=np.float64)
        if pose.shape[1:] != (6,):
            raise InputError(f"state batch: {POSE_UR_FIELD} must be [x, y, z, rx, ry, rz] per record, got shape {pose.shape[1:]}")
        T_base_tcp = np.tile(np.eye(4), (len(batch), 1, 1))
        T_base_tcp[:, :3, :3] = Rotation.from_rotvec(pose[:, 3:]).as_matrix()
        T_base_tcp[:, :3, 3] = pose[:, :3]

    columns = []
    for spec in series:
        if spec.field not in fields:
            continue
        used.add(spec.field)
        values = np.asarray(batch[spec.field], dtype=np.float64)
        if values.ndim == 1:
            values = values[:, None]
        if values.ndim != 2:
            raise InputError(f"state batch: field {spec.field!r} must be a scalar or a vector per record, got shape {values.shape[1:]}")
        if spec.components is not None:
            start, stop = spec.components
            if values.shape[1] < stop:
                raise InputError(f"state batch: field {spec.field!r} has {values.shape[1]} components, the table reads {start}:{stop}")
            values = values[:, start:stop]
        columns.append(SeriesColumn(spec.entity, _component_names(spec, values.shape[1]), values * spec.scale))

    ignored = tuple(f for f in fields if f not in used)
    return StateColumns(stamp_ns, T_base_tcp, tuple(columns), ignored)
