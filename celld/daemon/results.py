"""What each job kind's result looks like, and the cell's bus bundle made with it.

A job's result is the JSON document its runner returns and the job manager
writes (``results/<job>.json``, the ``result`` of a result reply). Its JSON
Schema is defined beside the code that builds it; this module only gathers
them by job kind:

================  ==========================================================================
kind              the result's schema
================  ==========================================================================
calibrate         robot 1's calibration or dry run (:mod:`celld.daemon.calibrate`: the
                  calibration, the solve's report of :mod:`celld.calib.solve` in the scanner
                  mount's frame, the quality gate's of :mod:`celld.calib.quality`), with what
                  a job with ``robot2`` adds (:mod:`celld.daemon.two_robots`)
tool-calibrate    :data:`celld.daemon.toolcal.RESULT_SCHEMA` (the tool:
                  :data:`celld.calib.toolsession.TOOL_SCHEMA`)
weld              :data:`celld.daemon.weld.RESULT_SCHEMA` (the figures and the probe:
                  :mod:`celld.weld.plan`)
move, health      :data:`celld.daemon.runners.MOVE_RESULT_SCHEMA`,
                  :data:`~celld.daemon.runners.HEALTH_RESULT_SCHEMA`
verify            :data:`celld.daemon.verify.RESULT_SCHEMA` (:data:`celld.calib.verify.SCHEMA`)
================  ==========================================================================

each with what the job manager adds (:func:`celld.daemon.jobs.with_manager_fields`).
The current calibration and tool calibration are a calibrate and a
tool-calibrate job's candidates as the store accepts them
(:func:`celld.daemon.store.accepted_schema`).

The bus sits below the daemon and knows none of these shapes: it is given
them (:class:`celld.bus.messages.Documents`) and makes :data:`BUNDLE`, every
message's schema with the result reply choosing its result's schema by the
job's ``kind``. ``celld bus schema`` exports it; a client validates a result
against it, and the tests validate real daemon results against it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from celld.bus.messages import Documents, message_schemas
from celld.calib.toolsession import TOOL_SCHEMA
from celld.daemon import calibrate, runners, toolcal, two_robots, verify, weld
from celld.daemon.jobs import with_manager_fields
from celld.daemon.store import accepted_schema
from celld.schemadoc import one_of, with_properties

# A calibration a calibrate job makes: robot 1's, with robot 2's entry when the job had robot2.
CALIBRATION_SCHEMA = with_properties(calibrate.CALIBRATION_SCHEMA, {"robot2": two_robots.ROBOT2_ENTRY_SCHEMA})

# A calibrate job's result: robot 1's, with robot 2's plan (a dry run) or its calibration (robot2) when the job had robot2.
_CALIBRATE = one_of(
    "A calibrate job's result: the calibration, or a dry run's plan.",
    with_properties(calibrate.DRY_RUN_SCHEMA, {"robot2_plan": calibrate.PLAN_SCHEMA}),
    with_properties(calibrate.OUTPUT_SCHEMA, {"calibration": CALIBRATION_SCHEMA, "robot2": two_robots.ROBOT2_OUTPUT_SCHEMA}),
)

# Each job kind's result, as the manager writes it.
RESULTS: Mapping[str, Mapping[str, Any]] = {
    kind: with_manager_fields(kind, schema)
    for kind, schema in {
        "calibrate": _CALIBRATE,
        "tool-calibrate": toolcal.RESULT_SCHEMA,
        "weld": weld.RESULT_SCHEMA,
        "move": runners.MOVE_RESULT_SCHEMA,
        "health": runners.HEALTH_RESULT_SCHEMA,
        "verify": verify.RESULT_SCHEMA,
    }.items()
}
# The cell's bundle: every bus message, with each job kind's result and the current calibrations typed
# (message_schemas refuses a job kind without a result schema).
BUNDLE: Mapping[str, dict[str, Any]] = message_schemas(
    Documents(RESULTS, accepted_schema(CALIBRATION_SCHEMA), accepted_schema(TOOL_SCHEMA))
)
