"""The JSON Schema subset checker: what it enforces, and that it refuses what it cannot."""

from __future__ import annotations

import pytest

from celld.bus.checker import check_schema, describe, validate
from celld.errors import JobError

SHAPE = {
    "type": "object",
    "oneOf": [
        {
            "type": "object",
            "properties": {"shape": {"const": "circle"}, "r": {"type": "number", "exclusiveMinimum": 0}},
            "required": ["shape", "r"],
            "additionalProperties": False,
        },
        {
            "type": "object",
            "properties": {
                "shape": {"const": "box"},
                "size": {"type": "array", "prefixItems": [{"type": "number"}, {"type": "integer"}], "minItems": 2, "maxItems": 2},
            },
            "required": ["shape"],
            "additionalProperties": False,
        },
    ],
}


def error(schema: dict, value: object) -> JobError:
    with pytest.raises(JobError) as err:
        validate(schema, value)
    return err.value


def test_discriminated_one_of_reports_the_branch_field() -> None:
    validate(SHAPE, {"shape": "circle", "r": 1.5})
    validate(SHAPE, {"shape": "box", "size": [1.5, 2]})
    assert (e := error(SHAPE, {"shape": "circle", "r": 0})).field == "$.r" and "> 0" in e.reason
    assert error(SHAPE, {"shape": "box", "size": [1.5, 2.5]}).field == "$.size[1]"
    assert error(SHAPE, {"shape": "box", "r": 1}).field == "$.r"
    assert error(SHAPE, {"shape": "star"}).reason == 'expected one of "circle", "box"; got string \'star\''
    assert error(SHAPE, {"r": 1}).field == "$.shape"


def test_a_one_of_with_a_null_branch_takes_null_and_its_objects_only() -> None:
    nullable = {"oneOf": [{"type": "null"}, *SHAPE["oneOf"]]}
    check_schema(nullable)
    validate(nullable, None)
    validate(nullable, {"shape": "circle", "r": 1.5})
    assert error(nullable, {"shape": "circle", "r": 0}).field == "$.r"
    assert error(nullable, [1]).reason == "expected an object or null, got an array of 1"
    assert error(SHAPE, None).reason == "expected an object, got null"
    jsonschema = pytest.importorskip("jsonschema", reason="the reference validator is only a test aid")
    for value in (None, {"shape": "circle", "r": 1.5}, {"shape": "circle", "r": 0}, [1], "box", {"shape": "star"}):
        try:
            validate(nullable, value)
            ours = True
        except JobError:
            ours = False
        assert ours == jsonschema.Draft202012Validator(nullable).is_valid(value), value


def test_booleans_are_not_numbers_and_numbers_are_not_booleans() -> None:
    assert error({"type": "number"}, True).reason == "expected a number, got true"
    assert error({"type": "boolean"}, 1).reason == "expected true or false, got 1"
    assert error({"const": 1}, True).reason == "expected 1, got true"
    assert error({"enum": [False]}, 0).field == "$"
    validate({"type": ["string", "null"]}, None)


def test_long_values_are_quoted_short_and_ascii() -> None:
    text = describe("\u00e9" * 1000)
    assert text.isascii() and len(text) < 60
    assert describe([1, 2]) == "an array of 2" and describe({"a": 1}) == "an object with 1 fields"


@pytest.mark.parametrize(
    "schema",
    [
        {"type": "object", "patternProperties": {}},
        {"type": "object", "additionalProperties": {"type": "string"}},
        {"type": "string", "format": "date-time"},
        {"type": "object", "required": ["a"], "properties": {}},
        {"type": "decimal"},
        {"oneOf": [{"type": "object", "properties": {"a": {"type": "string"}}}]},
        {"oneOf": [{"type": "null"}, {"type": "null"}, *SHAPE["oneOf"]]},
        {"oneOf": [{"type": "string"}, *SHAPE["oneOf"]]},
        {"anyOf": [{"type": "string"}]},
        {"type": "array", "items": {"type": "number", "multipleOf": 2}},
    ],
)
def test_schemas_with_unenforced_keywords_are_refused(schema: dict) -> None:
    with pytest.raises(ValueError):
        check_schema(schema)


def test_a_long_unknown_key_is_shortened_in_the_error_path() -> None:
    from celld.bus.checker import field_path

    path = field_path("$", "k" * 200_000)
    assert len(path) < 60 and path.startswith("$['kkk") and path.endswith("...']")
    assert len(field_path("$", "\U0001f600" * 50_000)) < 60
    assert field_path("$", "n_poses") == "$.n_poses"
