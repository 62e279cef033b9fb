"""The mapping from a batch of motion-state records to recording columns (pure).

The motion process appends one record per cycle to a shared-memory ring
(:class:`celld.shm.Ring`) of a numpy structured dtype. The recorder reads
batches of those records outside the loop and sends them as columns. This
module says, in one table, which ring field becomes which entity, with which
series names and which scale; it takes arrays and returns arrays.

The mapping is by exact field name and tolerant: a field the batch lacks is
skipped, a field the table does not name is reported in
:attr:`StateColumns.ignored`. Only ``stamp_ns`` is required.

Default field names (the ring dtype should use them, or the caller passes its
own table):

==============  ==========  ===============================  =============
field           shape       entity                           recorded as
==============  ==========  ===============================  =============
stamp_ns        ()          the ``time`` timeline            s since t0
T_base_tcp      (4, 4)      /world/tcp                       transform
tcp_pose        (6,)        /world/tcp (UR pose, if no       transform
                            T_base_tcp)
v_tcp           (6,)        /robot/v_tcp                     m/s, rad/s
delta_tool      (2,)/(3,)   /servo/delta                     m
v_r             (2,)/(3,)   /servo/v_r                       m/s
omega           ()          /servo/omega                     rad/s
late_ns         ()          /motion/loop/late_ms             ms
exec_ns         ()          /motion/loop/exec_ms             ms
period_ns       ()          /motion/loop/period_ms           ms
status          ()          /motion/status                   ControlStatus
==============  ==========  ===============================  =============
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from celld.errors import InputError
from celld.recording import layout

# The field that carries each record's time.monotonic_ns() stamp.
STAMP_FIELD = "stamp_ns"
# Pose fields, in order of preference: a (4, 4) transform, else a UR pose.
POSE_MATRIX_FIELD = "T_base_tcp"
POSE_UR_FIELD = "tcp_pose"


class Series(NamedTuple):
    """One ring field recorded as a time series.

    Attributes
    ----------
    field : str
        Field name in the ring dtype.
    entity : str
        Entity path of the series.
    names : tuple of str
        One legend name per component (the field's trailing size).
    scale : float
        Recorded value = field value * scale (e.g. 1e-6 for ns to ms).
    """

    field: str
    entity: str
    names: tuple[str, ...]
    scale: float = 1.0


DEFAULT_SERIES: tuple[Series, ...] = (
    Series("v_tcp", layout.ROBOT_V_TCP, ("vx", "vy", "vz", "wx", "wy", "wz")),
    Series("delta_tool", layout.SERVO_DELTA, ("tangential", "normal", "out of plane")),
    Series("v_r", layout.SERVO_V_R, ("x", "y", "z")),
    Series("omega", layout.SERVO_OMEGA, ("omega",)),
    Series("late_ns", f"{layout.MOTION_LOOP}/late_ms", ("late",), 1e-6),
    Series("exec_ns", f"{layout.MOTION_LOOP}/exec_ms", ("exec",), 1e-6),
    Series("period_ns", f"{layout.MOTION_LOOP}/period_ms", ("period",), 1e-6),
    Series("status", layout.MOTION_STATUS, ("status",)),
)


class SeriesColumn(NamedTuple):
    """The values of one series over a batch: ``values`` (n, k), float64."""

    entity: str
    names: tuple[str, ...]
    values: np.ndarray


class StateColumns(NamedTuple):
    """A batch of state records split into columns.

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
        (n,) structured array of ring records; must have ``stamp_ns``.
    series : tuple of Series
        The field table; :data:`DEFAULT_SERIES` unless the ring names its fields otherwise.

    Returns
    -------
    StateColumns
        Fresh arrays; ``batch`` is not modified.

    Raises
    ------
    InputError
        ``batch`` is not a 1-D structured array with ``stamp_ns``, or a mapped
        field has a shape the table cannot record (more than one trailing axis,
        a pose of the wrong shape).
    """
    if not isinstance(batch, np.ndarray) or batch.dtype.names is None or batch.ndim != 1:
        got = getattr(batch, "dtype", type(batch).__name__)
        raise InputError(f"state batch: expected a 1-D numpy structured array of ring records, got {got}")
    fields = batch.dtype.names
    if STAMP_FIELD not in fields:
        raise InputError(f"state batch: expected a {STAMP_FIELD!r} field, the record has {', '.join(fields)}")
    stamp_ns = batch[STAMP_FIELD].astype(np.int64)
    used = {STAMP_FIELD}

    T_base_tcp = None
    if POSE_MATRIX_FIELD in fields:
        T = np.asarray(batch[POSE_MATRIX_FIELD], dtype=np.float64)
        if T.shape[1:] != (4, 4):
            raise InputError(f"state batch: {POSE_MATRIX_FIELD} must be (4, 4) per record, got {T.shape[1:]}")
        T_base_tcp = T.copy()
        used.add(POSE_MATRIX_FIELD)
    elif POSE_UR_FIELD in fields:
        pose = np.asarray(batch[POSE_UR_FIELD], dtype=np.float64)
        if pose.shape[1:] != (6,):
            raise InputError(f"state batch: {POSE_UR_FIELD} must be [x, y, z, rx, ry, rz] per record, got shape {pose.shape[1:]}")
        T_base_tcp = np.tile(np.eye(4), (len(batch), 1, 1))
        T_base_tcp[:, :3, :3] = Rotation.from_rotvec(pose[:, 3:]).as_matrix()
        T_base_tcp[:, :3, 3] = pose[:, :3]
        used.add(POSE_UR_FIELD)

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
        columns.append(SeriesColumn(spec.entity, _component_names(spec, values.shape[1]), values * spec.scale))

    # A pose field that lost to T_base_tcp still counts as known.
    ignored = tuple(f for f in fields if f not in used and f not in (POSE_MATRIX_FIELD, POSE_UR_FIELD))
    return StateColumns(stamp_ns, T_base_tcp, tuple(columns), ignored)
