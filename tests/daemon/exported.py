"""A real daemon's replies and results, checked against the bundle ``celld bus schema`` exports.

The bundle is exported once per test run, when this module is imported (at
collection, before any simulated cell starts: the export's imports take CPU
that the simulated cell's real-time processes need), and read back from its
files; every check is celld's checker on those files. A job's result is
fetched over the bus as a client fetches it (``<req>/result/<job>``), checked
against the exported result reply and against its kind's result schema alone
(``result-<kind>``).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from celld.bus.asyncapi import export_schemas
from celld.bus.checker import validate
from celld.daemon.results import BUNDLE


def _exported() -> dict[str, dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="celld-bundle-") as out:
        export_schemas(out, BUNDLE)
        return {p.name.removesuffix(".schema.json"): json.loads(p.read_text()) for p in Path(out).glob("*.schema.json")}


# The cell's exported bundle, by message name, as read back from the files.
EXPORTED = _exported()


def check_exported(name: str, message: Mapping[str, Any]) -> None:
    """Validate a reply the daemon sent against the exported schema ``name`` (JobError naming the field if not)."""
    validate(EXPORTED[name], message)


def checked_result(client: Any, record: Mapping[str, Any] | str) -> dict[str, Any] | None:
    """The result of the finished job ``record`` (its record, or its id) over the bus, checked; None when it wrote none.

    A succeeded job has a result; it is checked against the result reply
    (which chooses the schema by the job's kind) and against ``result-<kind>``.
    """
    job = record if isinstance(record, str) else record["id"]
    reply = client.result(job)
    check_exported("result-reply", reply)
    assert not reply["too_large"], f"the result of {job} is over the inline limit: {reply['bytes']} bytes"
    result = reply["result"]
    if reply["state"] == "succeeded":
        assert result is not None, f"job {job} succeeded without a result"
    if result is not None:
        check_exported(f"result-{reply['kind']}", result)
    return result
