"""The bus's message schemas: draft 2020-12, exported as enforced, the reference validator agrees; the result reply
chooses its result's schema by the job's kind."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from celld.bus import messages
from celld.bus.asyncapi import export_schemas
from celld.bus.requests import parse_submit
from celld.errors import JobError
from celld.schemadoc import const, integer, obj, one_of
from tests.bus.strategies import json_values, valid_jobs


def test_every_schema_is_draft_2020_12_and_exported(tmp_path) -> None:
    paths = export_schemas(tmp_path / "schemas", messages.SCHEMAS)
    assert {p.name for p in paths} == {f"{n}.schema.json" for n in messages.SCHEMAS} | {"asyncapi.json"}
    for p in paths[:-1]:
        data = json.loads(p.read_text())
        assert data["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert data == messages.SCHEMAS[p.name.removesuffix(".schema.json")]


@pytest.mark.parametrize("name", sorted(messages.SCHEMAS))
def test_schemas_are_valid_json_schema(name: str) -> None:
    jsonschema = pytest.importorskip("jsonschema", reason="the reference validator is only a test aid")
    jsonschema.Draft202012Validator.check_schema(messages.SCHEMAS[name])


@settings(max_examples=150, deadline=None)
@given(
    st.one_of(
        valid_jobs,
        st.builds(lambda m, k, v: {**m, k: v}, valid_jobs, st.sampled_from(["n_poses", "poses", "target", "arc", "zz"]), json_values),
    )
)
def test_checker_agrees_with_the_reference_validator(message: dict) -> None:
    """Same verdict as jsonschema on the same schema (cross-field checks aside)."""
    jsonschema = pytest.importorskip("jsonschema", reason="the reference validator is only a test aid")
    reference = jsonschema.Draft202012Validator(messages.SCHEMAS["submit"]).is_valid(message)
    try:
        parse_submit(json.dumps(message).encode())
        ours = True
    except JobError as exc:
        ours = False
        if exc.reason.startswith("give either"):
            return  # the one rule outside the schema
    assert ours == reference


# -- what others build: each job kind's result, the calibrations ---------------------------------

# A move result's shape, for these tests (the real one is the daemon's: celld.daemon.results).
_MOVED = one_of(
    "Where a move ended.",
    obj("Joint.", {"space": const("joint"), "n": integer(lo=0)}, ("space", "n")),
    obj("Cartesian.", {"space": const("cartesian")}, ("space",)),
)
_TYPED = messages.message_schemas(messages.Documents({**messages.UNTYPED.results, "move": _MOVED}))


def _reply(kind: str, result: object, state: str = "succeeded") -> dict:
    return {"ok": True, "job": "j1", "kind": kind, "state": state, "reason": "", "result": result, "too_large": False, "files": []}


def test_the_result_reply_chooses_the_results_schema_by_the_jobs_kind() -> None:
    messages.check_message("result-reply", _reply("move", {"space": "joint", "n": 3}), _TYPED)
    messages.check_message("result-reply", _reply("move", None, "cancelled"), _TYPED)  # no result written
    messages.check_message("result-reply", _reply("health", {"space": "joint", "n": -1}), _TYPED)  # health's is untyped here
    with pytest.raises(JobError) as wrong:
        messages.check_message("result-reply", _reply("move", {"space": "joint", "n": -1}), _TYPED)
    assert wrong.value.field == "$.result.n"
    with pytest.raises(JobError) as unknown:
        messages.check_message("result-reply", _reply("move", {"space": "polar"}), _TYPED)
    assert unknown.value.field == "$.result.space"
    with pytest.raises(JobError) as no_kind:
        messages.check_message("result-reply", {k: v for k, v in _reply("move", None).items() if k != "kind"}, _TYPED)
    assert no_kind.value.field == "$.kind" and "expected one of" in no_kind.value.reason
    # Each kind's result is exported alone too.
    messages.check_message("result-move", {"space": "cartesian"}, _TYPED)
    assert _TYPED["result-move"]["$id"] == "urn:celld:bus:result-move"


def test_the_reference_validator_agrees_on_the_result_reply() -> None:
    jsonschema = pytest.importorskip("jsonschema", reason="the reference validator is only a test aid")
    validator = jsonschema.Draft202012Validator(_TYPED["result-reply"])
    for reply, ok in (
        (_reply("move", {"space": "joint", "n": 3}), True),
        (_reply("move", None, "failed"), True),
        (_reply("move", {"space": "joint", "n": -1}), False),
        (_reply("move", {"space": "joint"}), False),
        (_reply("weld", [1, 2]), False),
        (_reply("paint", None), False),
    ):
        try:
            messages.check_message("result-reply", reply, _TYPED)
            ours = True
        except JobError:
            ours = False
        assert ours == validator.is_valid(reply) == ok, reply


def test_the_requests_are_the_same_in_every_bundle() -> None:
    """What the cell enforces (the requests) does not depend on the result schemas it is given."""
    for name in messages.REQUESTS:
        assert _TYPED[name] == messages.SCHEMAS[name]


def test_a_bundle_needs_every_job_kinds_result_and_only_keywords_the_checker_enforces() -> None:
    results = dict(messages.UNTYPED.results)
    del results["weld"]
    with pytest.raises(ValueError, match="weld"):
        messages.message_schemas(messages.Documents(results))
    with pytest.raises(ValueError, match="unsupported keywords"):
        messages.message_schemas(messages.Documents({**messages.UNTYPED.results, "move": {"type": "object", "anyOf": []}}))
