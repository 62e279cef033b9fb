"""Job recordings to rerun: one ``.rrd`` file per job, live on request.

- :mod:`celld.recording.layout`: entity paths, timelines, the default blueprint.
- :mod:`celld.recording.state`: which motion-state ring field is recorded where (pure).
- :mod:`celld.recording.job`: :class:`JobRecording`, the writer.
- :mod:`celld.recording.readback`: reading a finished file back (tests, tools).
"""

from __future__ import annotations

from celld.recording.job import JobRecording, recording_path
from celld.recording.readback import read_component, read_entities, read_recording_id, read_scalars, read_views
from celld.recording.state import DEFAULT_SERIES, Series, state_columns

__all__ = [
    "DEFAULT_SERIES",
    "JobRecording",
    "Series",
    "read_component",
    "read_entities",
    "read_recording_id",
    "read_scalars",
    "read_views",
    "recording_path",
    "state_columns",
]
