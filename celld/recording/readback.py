"""Read a job recording back: entities, series, components and the stored views.

For tests, acceptance checks and offline tools. It uses the chunk reader of
rerun-sdk 0.41 (:class:`rerun.chunk.RrdReader`) and pyarrow, both installed
with the SDK; no DataFusion and no catalog extra. The read-back API of rerun
moves between versions, which is why ``rerun-sdk`` is pinned.

A file still being written has no footer yet; these functions stream the
chunks and so also read such a file, but a test should close the recording
before it asserts on it.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from rerun.chunk import Chunk, RrdReader

from celld.errors import InputError
from celld.recording import layout

# Entity paths rerun itself writes; not part of a job's data.
_RESERVED_PREFIX = "/__"


def _reader(path: str | Path) -> RrdReader:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"recording {p}: no such file")
    try:
        with warnings.catch_warnings():
            # A file still being written (or saved by a viewer) has no footer; streaming reads it.
            warnings.filterwarnings("ignore", message="RRD file has no footer")
            return RrdReader(p)
    except (OSError, RuntimeError, ValueError) as exc:
        raise InputError(f"recording {p}: not a readable .rrd file: {exc}") from exc


def _chunks(path: str | Path, blueprint: bool = False) -> list[Chunk]:
    reader = _reader(path)
    stores = reader.blueprints() if blueprint else reader.recordings()
    if not stores:
        raise InputError(f"recording {path}: holds no {'blueprint' if blueprint else 'recording'} store")
    return list(reader.stream(store=stores[0]).to_chunks())


def read_recording_id(path: str | Path) -> str:
    """The ``recording_id`` of the file's recording (the job id)."""
    stores = _reader(path).recordings()
    if not stores:
        raise InputError(f"recording {path}: holds no recording store")
    return stores[0].recording_id


def read_entities(path: str | Path) -> set[str]:
    """Entity paths holding data in the recording (rerun's own ``/__*`` left out)."""
    return {c.entity_path for c in _chunks(path) if not c.entity_path.startswith(_RESERVED_PREFIX)}


def _index_seconds_or_ticks(column: pa.Array) -> np.ndarray:
    """Duration indexes in seconds, sequence indexes as int64, timestamps in ns since the epoch."""
    if pa.types.is_duration(column.type):
        return column.cast(pa.int64()).to_numpy(zero_copy_only=False) * 1e-9
    if pa.types.is_timestamp(column.type):
        return column.cast(pa.int64()).to_numpy(zero_copy_only=False)
    return column.to_numpy(zero_copy_only=False)


def read_component(path: str | Path, entity: str, component: str, timeline: str = layout.TIME) -> tuple[np.ndarray, list[Any]]:
    """Every logged value of one component of one entity, ordered by ``timeline``.

    Parameters
    ----------
    path : str or Path
        The ``.rrd`` file.
    entity : str
        Entity path, e.g. ``"/world/clouds/scan"``.
    component : str
        Column name as rerun stores it, ``"<Archetype>:<field>"``, e.g.
        ``"Points3D:positions"``, ``"Scalars:scalars"``,
        ``"Transform3D:translation"``.
    timeline : str
        Index to order by: ``"time"`` (seconds since the recording opened),
        ``"iteration"``, or ``""`` for static data (times are then row numbers).

    Returns
    -------
    times : numpy.ndarray
        (n,) index values.
    values : list
        n values, each a numpy array when the cell is a numeric list (points,
        scalars) and a Python value otherwise; None for a cleared cell.
    """
    times: list[np.ndarray] = []
    values: list[Any] = []
    found = False
    for chunk in _chunks(path):
        if chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if component not in names:
            continue
        if timeline and timeline not in names:
            continue
        found = True
        col = batch.column(component)
        times.append(_index_seconds_or_ticks(batch.column(timeline)) if timeline else np.arange(len(col)))
        for cell in col.to_pylist():
            if cell is None:
                values.append(None)
                continue
            arr = np.asarray(cell)
            values.append(arr if arr.dtype.kind in "fiub" else cell)
    if not found:
        raise InputError(f"recording {path}: no component {component!r} on {entity!r} indexed by {timeline!r}")
    t = np.concatenate(times)
    order = np.argsort(t, kind="stable")
    return t[order], [values[i] for i in order]


def read_scalars(path: str | Path, entity: str, timeline: str = layout.TIME) -> tuple[np.ndarray, np.ndarray]:
    """A time series: ``times`` (n,) and ``values`` (n, k) of ``Scalars`` on ``entity``."""
    t, vals = read_component(path, entity, "Scalars:scalars", timeline)
    return t, np.array([np.atleast_1d(v).astype(np.float64) for v in vals])


def read_views(path: str | Path) -> set[tuple[str, str]]:
    """The views of the stored blueprint as ``(class, origin)``: ``("3D", "/world")``, ``("TimeSeries", ...)``."""
    views = set()
    for chunk in _chunks(path, blueprint=True):
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if "ViewBlueprint:class_identifier" in names and "ViewBlueprint:space_origin" in names:
            for cls, origin in zip(
                batch.column("ViewBlueprint:class_identifier").to_pylist(),
                batch.column("ViewBlueprint:space_origin").to_pylist(),
            ):
                views.add((cls[0], origin[0]))
    return views
