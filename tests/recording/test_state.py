"""The field table that turns motion-state ring records into recording columns."""

from __future__ import annotations

import numpy as np
import pytest

from celld import se3
from celld.errors import InputError
from celld.recording import layout
from celld.recording.state import DEFAULT_SERIES, Series, state_columns


def _batch(dtype: list, n: int = 4) -> np.ndarray:
    b = np.zeros(n, np.dtype(dtype))
    b["stamp_ns"] = 1_000_000_000 + np.arange(n) * 2_000_000
    return b


def test_known_fields_map_to_their_entities_with_scale() -> None:
    b = _batch([("stamp_ns", np.int64), ("late_ns", np.int64), ("omega", np.float64), ("delta_tool", np.float64, (3,))])
    b["late_ns"] = [10_000, 20_000, 30_000, 1_500_000]
    b["omega"] = [0.1, 0.2, 0.3, 0.4]
    b["delta_tool"][:, 1] = 0.0015
    cols = state_columns(b)
    by_entity = {c.entity: c for c in cols.series}
    assert set(by_entity) == {layout.SERVO_OMEGA, layout.SERVO_DELTA, f"{layout.MOTION_LOOP}/late_ms"}
    # ns -> ms at the recording boundary.
    np.testing.assert_allclose(by_entity[f"{layout.MOTION_LOOP}/late_ms"].values[:, 0], [0.01, 0.02, 0.03, 1.5])
    np.testing.assert_allclose(by_entity[layout.SERVO_OMEGA].values[:, 0], [0.1, 0.2, 0.3, 0.4])
    assert by_entity[layout.SERVO_DELTA].values.shape == (4, 3)
    assert by_entity[layout.SERVO_DELTA].names == ("tangential", "normal", "out of plane")
    np.testing.assert_array_equal(cols.stamp_ns, b["stamp_ns"])
    assert cols.T_base_tcp is None and cols.ignored == ()


def test_a_ur_pose_becomes_the_same_transform_as_se3() -> None:
    b = _batch([("stamp_ns", np.int64), ("tcp_pose", np.float64, (6,))], n=2)
    b["tcp_pose"] = [[0.5, -0.1, 0.3, 0.1, -2.0, 0.4], [0.6, 0.0, 0.2, 3.0, 0.0, 0.0]]
    cols = state_columns(b)
    for i in range(2):
        np.testing.assert_allclose(cols.T_base_tcp[i], se3.from_ur_pose(b["tcp_pose"][i]), atol=1e-12)


def test_a_matrix_pose_is_preferred_and_the_ur_pose_is_not_reported_unmapped() -> None:
    T = se3.from_xyz_rpy([0.1, 0.2, 0.3], [0.0, 0.5, 0.0])
    b = _batch([("stamp_ns", np.int64), ("T_base_tcp", np.float64, (4, 4)), ("tcp_pose", np.float64, (6,))], n=1)
    b["T_base_tcp"][0] = T
    cols = state_columns(b)
    np.testing.assert_array_equal(cols.T_base_tcp[0], T)
    assert cols.ignored == ()


def test_unknown_fields_are_reported_not_recorded() -> None:
    b = _batch([("stamp_ns", np.int64), ("seq", np.uint64), ("q", np.float64, (6,)), ("omega", np.float64)])
    cols = state_columns(b)
    assert cols.ignored == ("seq", "q")
    assert [c.entity for c in cols.series] == [layout.SERVO_OMEGA]


def test_a_two_component_field_takes_the_first_names_and_a_wide_one_gets_indexed_names() -> None:
    b = _batch([("stamp_ns", np.int64), ("delta_tool", np.float64, (2,)), ("omega", np.float64, (2,))])
    cols = {c.entity: c for c in state_columns(b).series}
    assert cols[layout.SERVO_DELTA].names == ("tangential", "normal")
    assert cols[layout.SERVO_OMEGA].names == ("omega[0]", "omega[1]")


def test_a_custom_table_renames_fields() -> None:
    b = _batch([("stamp_ns", np.int64), ("dn", np.float64)])
    b["dn"] = 2.0
    table = (Series("dn", layout.SERVO_DELTA, ("normal",), 1e-3),)
    (col,) = state_columns(b, table).series
    np.testing.assert_allclose(col.values, 2e-3)


def test_batches_without_stamps_or_with_bad_shapes_are_refused() -> None:
    with pytest.raises(InputError, match="stamp_ns"):
        state_columns(np.zeros(3, [("t", np.int64)]))
    with pytest.raises(InputError, match="structured"):
        state_columns(np.zeros((3, 2)))
    with pytest.raises(InputError, match="tcp_pose"):
        state_columns(_batch([("stamp_ns", np.int64), ("tcp_pose", np.float64, (7,))]))
    with pytest.raises(InputError, match="v_tcp"):
        state_columns(_batch([("stamp_ns", np.int64), ("v_tcp", np.float64, (2, 3))]))


def test_the_input_batch_is_not_modified() -> None:
    b = _batch([("stamp_ns", np.int64), ("late_ns", np.int64)])
    b["late_ns"] = 5
    before = b.copy()
    state_columns(b, DEFAULT_SERIES)
    np.testing.assert_array_equal(b, before)
