"""The MES interface: results over the bus, idempotent submits, cancel reasons, every rule in
the schema, the key table in the README and in an AsyncAPI document, and an example client
that uses only zenoh and the exported schemas."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from celld.bus import messages, requests
from celld.bus.asyncapi import channel_name, export_schemas
from celld.bus.client import CellClient
from celld.bus.keys import KEY_TABLE
from celld.errors import JobError

ROOT = Path(__file__).resolve().parents[2]
POSES = [[0.4, 0.0, 0.5, 0.0, 3.14, 0.0]] * 4


@pytest.fixture
def cell(serve_cell):
    return serve_cell(job_duration=0.05)


@pytest.fixture
def client(cell):
    with CellClient(cell.client_bus(), cell.keys.cell) as c:
        yield c


# -- results --------------------------------------------------------------------------------


def test_a_jobs_result_comes_back_over_the_bus(cell, client) -> None:
    reply, record = client.submit_and_wait({"kind": "calibrate", "n_poses": 6}, timeout=10.0)
    assert record["state"] == "succeeded"
    result = client.result(reply["job"])
    messages.check_message("result-reply", result)
    assert result["state"] == "succeeded" and result["too_large"] is False
    assert result["result"]["calibration"]["job"] == reply["job"]
    assert result["bytes"] == Path(record["result"]).stat().st_size
    with pytest.raises(JobError) as unknown:
        client.result("20990101-000000-abcdef")
    assert unknown.value.field == "$.job" and "no such job" in unknown.value.reason


def test_a_running_jobs_result_is_refused_and_a_large_one_stays_on_the_cell(serve_cell) -> None:
    cell = serve_cell(job_duration=3.0)
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        job = client.submit({"kind": "health"})["job"]
        with pytest.raises(JobError, match="its result comes when it ends"):
            client.result(job)
        client.cancel(job, "enough")
        quick = serve_cell("cell-b", job_duration=0.0)
    with CellClient(quick.client_bus(), quick.keys.cell) as client:
        _, record = client.submit_and_wait({"kind": "health"}, timeout=10.0)
        Path(record["result"]).write_text(json.dumps({"path": [0.001] * 200_000}))  # over the inline limit
        result = client.result(record["id"])
        assert result["too_large"] is True and result["result"] is None and result["path"] == record["result"]
        assert result["bytes"] > messages.MAX_RESULT_BYTES


def test_a_result_key_must_name_one_job(cell, client) -> None:
    reply = client.request_raw("result", None, key=f"{cell.keys.base}/result/*")
    assert reply["ok"] is False and "name one job" in reply["error"]["reason"]


# -- idempotent submits ----------------------------------------------------------------------


def test_a_replayed_submit_returns_the_original_job(cell, client) -> None:
    message = {"kind": "calibrate", "n_poses": 6, "ref": "order-9", "request_id": "order-9-step-1"}
    first = client.submit(message)
    again = client.submit(message)
    assert again["job"] == first["job"] and again["replayed"] is True and "replayed" not in first
    messages.check_message("submit-reply", again)
    assert len(cell.journal.jobs()) == 1
    record = client.status(first["job"])
    assert record["request_id"] == "order-9-step-1" and "request_id" not in record["params"]
    client.watch_progress().wait(first["job"], timeout=10.0)
    late = client.submit(message)  # after the job ended: still the same job, in its state now
    assert late["job"] == first["job"] and late["state"] == "succeeded"
    with pytest.raises(JobError) as changed:
        client.submit({**message, "n_poses": 7})
    assert changed.value.field == "$.request_id" and first["job"] in changed.value.reason
    assert len(cell.journal.jobs()) == 1


def test_a_bad_request_id_is_refused_by_the_schema() -> None:
    with pytest.raises(JobError) as bad:
        requests.parse_submit(b'{"kind": "health", "request_id": "has space"}')
    assert bad.value.field == "$.request_id"


# -- cancel reasons ---------------------------------------------------------------------------


def test_a_running_jobs_cancel_reason_is_kept(serve_cell) -> None:
    cell = serve_cell(job_duration=5.0)
    with CellClient(cell.client_bus(), cell.keys.cell) as client:
        job = client.submit({"kind": "weld", "arc": False})["job"]
        deadline = time.monotonic() + 5.0
        while client.status(job)["state"] != "running":
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert client.cancel(job, "wrong part on the fixture")["state"] == "cancelled"
        record = client.status(job)
        assert (record["state"], record["reason"]) == ("cancelled", "wrong part on the fixture")
        assert cell.journal.get(job).reason == "wrong part on the fixture"


# -- every rule in the schema ------------------------------------------------------------------


def test_poses_and_n_poses_together_are_refused_by_the_exported_schema_itself() -> None:
    jsonschema = pytest.importorskip("jsonschema", reason="the reference validator checks the exported contract")
    both = {"kind": "calibrate", "poses": POSES, "n_poses": 5}
    validator = jsonschema.Draft202012Validator(messages.SCHEMAS["submit"])
    assert not validator.is_valid(both), "a client validating against the export must see this rule"
    assert validator.is_valid({"kind": "calibrate", "poses": POSES})
    with pytest.raises(JobError) as refused:
        requests.parse_submit(json.dumps(both).encode())
    assert (refused.value.field, refused.value.reason) == ("$.n_poses", "give either poses or n_poses, not both")


# -- documentation ------------------------------------------------------------------------------


def test_the_bundle_has_an_asyncapi_document_of_every_key(tmp_path: Path) -> None:
    paths = export_schemas(tmp_path, messages.SCHEMAS)
    doc = json.loads((tmp_path / "asyncapi.json").read_text())
    assert doc["asyncapi"] == "2.6.0" and paths[-1].name == "asyncapi.json"
    assert list(doc["channels"]) == [channel_name(s) for s in KEY_TABLE]
    for spec in KEY_TABLE:
        channel = doc["channels"][channel_name(spec)]
        assert channel["x-zenoh"] == spec.kind
        assert ("publish" in channel) == (spec.kind == "queryable")
    for message in doc["components"]["messages"].values():
        assert (tmp_path / message["payload"]["$ref"]).is_file()
    for name in messages.REQUESTS:
        assert name in doc["components"]["messages"]


def test_the_readme_documents_every_key_and_the_mes_interface() -> None:
    readme = (ROOT / "README.md").read_text()
    for spec in KEY_TABLE:
        assert f"`{spec.key}`" in readme, f"README lacks the key {spec.key}"
    for words in ("request_id", "result/<job>", "celld bus schema", "asyncapi.json", "u/<user>", "supervisor", "min_free_mb", "[bus.tls]"):
        assert words in readme, words


# -- the example MES client ---------------------------------------------------------------------


EXAMPLE = ROOT / "examples" / "mes_client.py"


def test_the_example_mes_client_imports_only_zenoh_the_standard_library_and_jsonschema() -> None:
    tree = ast.parse(EXAMPLE.read_text())
    names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module and n.level == 0}
    assert names - set(sys.stdlib_module_names) <= {"zenoh", "jsonschema"}, names


@pytest.mark.process
def test_the_example_mes_client_runs_a_job_end_to_end(cell, tmp_path: Path) -> None:
    bundle = tmp_path / "bundle"
    export_schemas(bundle, messages.SCHEMAS)  # the stand-in cell's results are of no kind's shape
    endpoint = cell.bus.listen[0]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run(
        [
            sys.executable,
            "-I",
            str(EXAMPLE),
            "--endpoint",
            endpoint,
            "--cell",
            cell.keys.cell,
            "--schemas",
            str(bundle),
            "--request-id",
            "example-1",
            "--job",
            '{"kind": "health", "ref": "example"}',
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert lines[-1]["state"] == "succeeded" and lines[-1]["result"] is not None
    assert len(cell.journal.jobs()) == 1
