"""The field table that turns ring records (motion state, tactile samples) into recording columns."""

from __future__ import annotations

import numpy as np
import pytest

from celld import se3
from celld.errors import InputError
from celld.recording import layout
from celld.recording.state import DEFAULT_SERIES, Series, state_columns
from celld.tactile.sample import TACTILE_DTYPE

# The fields of the motion state ring the table maps (a subset of its record).
MOTION = [
    ("cycle", np.uint64),
    ("t_ns", np.int64),
    ("late_ns", np.int64),
    ("period_ns", np.int64),
    ("work_ns", np.int64),
    ("tcp_pose", np.float64, (6,)),
    ("tcp_speed", np.float64, (6,)),
    ("status", np.int16),
    ("twist", np.float64, (6,)),
]


def _batch(dtype: list, n: int = 4, stamp: str = "t_ns") -> np.ndarray:
    b = np.zeros(n, np.dtype(dtype))
    b[stamp] = 1_000_000_000 + np.arange(n) * 2_000_000
    return b


def test_motion_fields_map_to_their_entities_with_scale() -> None:
    b = _batch(MOTION)
    b["late_ns"] = [10_000, 20_000, 30_000, 1_500_000]
    b["twist"] = [[0.01, 0.0, -0.002, 0.0, 0.0, 0.3]] * 4
    cols = state_columns(b)
    by_entity = {c.entity: c for c in cols.series}
    assert set(by_entity) == {
        layout.ROBOT_V_TCP,
        layout.SERVO_V_R,
        layout.SERVO_OMEGA,
        f"{layout.MOTION_LOOP}/late_ms",
        f"{layout.MOTION_LOOP}/period_ms",
        f"{layout.MOTION_LOOP}/work_ms",
        layout.MOTION_STATUS,
    }
    # ns -> ms at the recording boundary.
    np.testing.assert_allclose(by_entity[f"{layout.MOTION_LOOP}/late_ms"].values[:, 0], [0.01, 0.02, 0.03, 1.5])
    # The sent twist splits into Algorithm 2's V_r and omega.
    np.testing.assert_allclose(by_entity[layout.SERVO_V_R].values, [[0.01, 0.0, -0.002]] * 4)
    np.testing.assert_allclose(by_entity[layout.SERVO_OMEGA].values, [[0.0, 0.0, 0.3]] * 4)
    assert by_entity[layout.SERVO_OMEGA].names == ("wx", "wy", "wz")
    np.testing.assert_array_equal(cols.stamp_ns, b["t_ns"])
    assert cols.ignored == ("cycle",)


def test_a_tactile_sample_batch_gives_the_deformation() -> None:
    b = np.zeros(3, TACTILE_DTYPE)
    b["stamp_ns"] = [5, 6, 7]
    b["delta_tool"] = [[0.0, 0.0015, 0.0], [np.nan] * 3, [0.0001, 0.0014, 0.0]]
    cols = state_columns(b)
    (delta,) = [c for c in cols.series if c.entity == layout.SERVO_DELTA]
    assert delta.names == ("tangential", "normal", "out of plane")
    np.testing.assert_allclose(delta.values[:, 1], [0.0015, np.nan, 0.0014])  # no tag: a gap, not a zero
    np.testing.assert_array_equal(cols.stamp_ns, [5, 6, 7])
    assert "seq" in cols.ignored and cols.T_base_tcp is None


def test_a_ur_pose_becomes_the_same_transform_as_se3() -> None:
    b = _batch(MOTION, n=2)
    b["tcp_pose"] = [[0.5, -0.1, 0.3, 0.1, -2.0, 0.4], [0.6, 0.0, 0.2, 3.0, 0.0, 0.0]]
    cols = state_columns(b)
    for i in range(2):
        np.testing.assert_allclose(cols.T_base_tcp[i], se3.from_ur_pose(b["tcp_pose"][i]), atol=1e-12)


def test_a_matrix_pose_is_preferred_and_the_ur_pose_is_not_reported_unmapped() -> None:
    T = se3.from_xyz_rpy([0.1, 0.2, 0.3], [0.0, 0.5, 0.0])
    b = _batch([("t_ns", np.int64), ("T_base_tcp", np.float64, (4, 4)), ("tcp_pose", np.float64, (6,))], n=1)
    b["T_base_tcp"][0] = T
    cols = state_columns(b)
    np.testing.assert_array_equal(cols.T_base_tcp[0], T)
    assert cols.ignored == ()


def test_a_narrower_field_takes_the_first_names_and_a_wider_one_gets_indexed_names() -> None:
    b = _batch([("t_ns", np.int64), ("delta_tool", np.float64, (2,)), ("status", np.int16, (2,))])
    cols = {c.entity: c for c in state_columns(b).series}
    assert cols[layout.SERVO_DELTA].names == ("tangential", "normal")
    assert cols[layout.MOTION_STATUS].names == ("status[0]", "status[1]")


def test_a_custom_table_renames_fields() -> None:
    b = _batch([("t_ns", np.int64), ("dn", np.float64)])
    b["dn"] = 2.0
    table = (Series("dn", layout.SERVO_DELTA, ("normal",), 1e-3),)
    (col,) = state_columns(b, table).series
    np.testing.assert_allclose(col.values, 2e-3)


def test_batches_without_stamps_or_with_bad_shapes_are_refused() -> None:
    with pytest.raises(InputError, match="t_ns or stamp_ns"):
        state_columns(np.zeros(3, [("t", np.int64)]))
    with pytest.raises(InputError, match="structured"):
        state_columns(np.zeros((3, 2)))
    with pytest.raises(InputError, match="tcp_pose"):
        state_columns(_batch([("t_ns", np.int64), ("tcp_pose", np.float64, (7,))]))
    with pytest.raises(InputError, match="tcp_speed"):
        state_columns(_batch([("t_ns", np.int64), ("tcp_speed", np.float64, (2, 3))]))
    with pytest.raises(InputError, match="'twist' has 3 components, the table reads 3:6"):
        state_columns(_batch([("t_ns", np.int64), ("twist", np.float64, (3,))]))


def test_the_input_batch_is_not_modified() -> None:
    b = _batch(MOTION)
    b["late_ns"] = 5
    before = b.copy()
    state_columns(b, DEFAULT_SERIES)
    np.testing.assert_array_equal(b, before)
