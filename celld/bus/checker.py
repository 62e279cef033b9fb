"""A small JSON Schema checker for the subset of draft 2020-12 that celld's bus uses.

The bus messages are described by JSON Schema dicts (:mod:`celld.bus.messages`);
they are exported for clients in other languages and drive this checker, so
what a client reads and what the cell enforces cannot drift apart. The checker
understands only the keywords below and refuses a schema that uses any other
(:func:`check_schema`), so a keyword is never silently ignored:

- ``type`` (one name or a list of names), ``enum``, ``const``;
- numbers: ``minimum``, ``maximum``, ``exclusiveMinimum``, ``exclusiveMaximum``;
- strings: ``minLength``, ``maxLength``, ``pattern`` (searched, as JSON Schema
  says; celld's patterns are anchored with ``^...$``);
- arrays: ``prefixItems`` (a schema per position), ``items``, ``minItems``,
  ``maxItems``;
- objects: ``properties``, ``required``, ``additionalProperties`` (``false``,
  or absent for a free-form object);
- ``oneOf`` whose branches are objects told apart by one property with a
  ``const`` (a discriminator such as ``kind``), so the error can name the
  branch's own field instead of "matches none of the alternatives"; one
  branch may be ``{"type": "null"}`` (the value may also be null);
- ``not`` whose schema is ``{"required": [a, b, ...]}`` (fields that must not
  all be given together): the error names the last of them and says "give
  either a or b, not both";
- annotations, which do not constrain: ``$schema``, ``$id``, ``$comment``,
  ``title``, ``description``, ``default``, ``examples``.

Errors are :class:`~celld.errors.JobError` with the JSON path of the offending
value (``$.poses[3][2]``) and a reason that says what was expected and what
came. Values from outside are quoted with :func:`ascii` and truncated, so a
reason is always short, printable ASCII.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from functools import lru_cache
from typing import Any

from celld.errors import JobError

# Keywords that constrain a value.
_ASSERTIONS = frozenset(
    {
        "type",
        "enum",
        "const",
        "minimum",
        "maximum",
        "exclusiveMinimum",
        "exclusiveMaximum",
        "minLength",
        "maxLength",
        "pattern",
        "prefixItems",
        "items",
        "minItems",
        "maxItems",
        "properties",
        "required",
        "additionalProperties",
        "oneOf",
        "not",
    }
)
# Keywords that only describe.
_ANNOTATIONS = frozenset({"$schema", "$id", "$comment", "title", "description", "default", "examples"})
_TYPES = frozenset({"object", "array", "string", "number", "integer", "boolean", "null"})
# Longest quoted value in an error reason, characters.
_QUOTE_MAX = 40


def describe(value: Any) -> str:
    """A short, ASCII description of a value from outside, for error reasons."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        text = repr(value)
        return text if len(text) <= _QUOTE_MAX else text[: _QUOTE_MAX - 3] + "..."
    if isinstance(value, str):
        text = ascii(value)
        return f"string {text}" if len(text) <= _QUOTE_MAX else f"string {text[: _QUOTE_MAX - 4]}...'"
    if isinstance(value, list):
        return f"an array of {len(value)}"
    if isinstance(value, dict):
        return f"an object with {len(value)} fields"
    return type(value).__name__


def literal(value: Any) -> str:
    """A schema constant as JSON text (ASCII), for "expected one of ..." reasons."""
    return json.dumps(value)


def field_path(path: str, key: str) -> str:
    """The JSON path of member ``key`` of the object at ``path`` (a long key is shortened, as quoted values are)."""
    if key.isidentifier() and key.isascii() and len(key) <= _QUOTE_MAX:
        return f"{path}.{key}"
    text = ascii(key)
    if len(text) > _QUOTE_MAX:
        text = text[: _QUOTE_MAX - 4] + "...'"
    return f"{path}[{text}]"


def _matches_type(value: Any, name: str) -> bool:
    if name == "object":
        return isinstance(value, dict)
    if name == "array":
        return isinstance(value, list)
    if name == "string":
        return isinstance(value, str)
    if name == "boolean":
        return isinstance(value, bool)
    if name == "null":
        return value is None
    if isinstance(value, bool):
        return False
    if name == "number":
        return isinstance(value, (int, float))
    # integer: JSON Schema counts 2.0 as an integer.
    return isinstance(value, int) or (isinstance(value, float) and math.isfinite(value) and value.is_integer())


_TYPE_WORDS = {
    "object": "an object",
    "array": "an array",
    "string": "a string",
    "number": "a number",
    "integer": "an integer",
    "boolean": "true or false",
    "null": "null",
}


@lru_cache(maxsize=256)
def _regex(pattern: str) -> re.Pattern[str]:
    return re.compile(pattern)


def validate(schema: Mapping[str, Any], value: Any, path: str = "$") -> None:
    """Check ``value`` against ``schema``; raise JobError naming the first bad field.

    Parameters
    ----------
    schema : mapping
        A schema using only the supported keywords (see the module docstring).
    value : Any
        A decoded JSON value (dict, list, str, int, float, bool or None).
    path : str
        The JSON path of ``value``, used in the error.

    Raises
    ------
    JobError
        ``field`` is the JSON path of the offending value, ``reason`` what was
        expected and what came.
    """
    types = schema.get("type")
    if types is not None:
        names = (types,) if isinstance(types, str) else tuple(types)
        if not any(_matches_type(value, n) for n in names):
            expected = " or ".join(_TYPE_WORDS[n] for n in names)
            raise JobError(path, f"expected {expected}, got {describe(value)}")
    if "const" in schema and not _same(value, schema["const"]):
        raise JobError(path, f"expected {literal(schema['const'])}, got {describe(value)}")
    if "enum" in schema and not any(_same(value, e) for e in schema["enum"]):
        choices = ", ".join(literal(e) for e in schema["enum"])
        raise JobError(path, f"expected one of {choices}; got {describe(value)}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        _check_number(schema, value, path)
    elif isinstance(value, str):
        _check_string(schema, value, path)
    elif isinstance(value, list):
        _check_array(schema, value, path)
    elif isinstance(value, dict):
        _check_object(schema, value, path)
    if "oneOf" in schema:
        _check_one_of(schema, value, path)
    if "not" in schema and isinstance(value, dict):
        _check_not(schema["not"], value, path)


def _check_not(sub: Mapping[str, Any], value: dict[str, Any], path: str) -> None:
    names = list(sub["required"])
    if not all(n in value for n in names):
        return
    if len(names) == 2:
        reason = f"give either {names[0]} or {names[1]}, not both"
    else:
        reason = f"give at most {len(names) - 1} of {', '.join(names)}, not all"
    raise JobError(field_path(path, names[-1]), reason)


def _same(a: Any, b: Any) -> bool:
    # 1 == True in Python; JSON keeps booleans and numbers apart.
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    return bool(a == b)


def _check_number(schema: Mapping[str, Any], value: float, path: str) -> None:
    if not math.isfinite(value):
        raise JobError(path, f"expected a finite number, got {describe(value)}")
    lo, hi = schema.get("minimum"), schema.get("maximum")
    xlo, xhi = schema.get("exclusiveMinimum"), schema.get("exclusiveMaximum")
    if lo is not None and value < lo:
        raise JobError(path, f"expected a value >= {lo}, got {describe(value)}")
    if hi is not None and value > hi:
        raise JobError(path, f"expected a value <= {hi}, got {describe(value)}")
    if xlo is not None and value <= xlo:
        raise JobError(path, f"expected a value > {xlo}, got {describe(value)}")
    if xhi is not None and value >= xhi:
        raise JobError(path, f"expected a value < {xhi}, got {describe(value)}")


def _check_string(schema: Mapping[str, Any], value: str, path: str) -> None:
    lo, hi = schema.get("minLength"), schema.get("maxLength")
    if lo is not None and len(value) < lo:
        raise JobError(path, f"expected at least {lo} characters, got {len(value)}")
    if hi is not None and len(value) > hi:
        raise JobError(path, f"expected at most {hi} characters, got {len(value)}")
    pattern = schema.get("pattern")
    if pattern is not None and not _regex(pattern).search(value):
        raise JobError(path, f"expected a string matching {pattern}, got {describe(value)}")


def _check_array(schema: Mapping[str, Any], value: list[Any], path: str) -> None:
    lo, hi = schema.get("minItems"), schema.get("maxItems")
    if lo is not None and len(value) < lo:
        exact = lo == hi
        raise JobError(path, f"expected {'exactly' if exact else 'at least'} {lo} items, got {len(value)}")
    if hi is not None and len(value) > hi:
        exact = lo == hi
        raise JobError(path, f"expected {'exactly' if exact else 'at most'} {hi} items, got {len(value)}")
    prefix = schema.get("prefixItems", ())
    for i, (sub, item) in enumerate(zip(prefix, value)):
        validate(sub, item, f"{path}[{i}]")
    items = schema.get("items")
    if items is not None:
        for i in range(len(prefix), len(value)):
            validate(items, value[i], f"{path}[{i}]")


def _check_object(schema: Mapping[str, Any], value: dict[str, Any], path: str) -> None:
    properties: Mapping[str, Any] = schema.get("properties", {})
    if schema.get("additionalProperties") is False:
        for key in value:
            if key not in properties:
                known = ", ".join(properties) or "none"
                raise JobError(field_path(path, key), f"unknown field (known here: {known})")
    for key in schema.get("required", ()):
        if key not in value:
            raise JobError(field_path(path, key), "required field is missing")
    for key, sub in properties.items():
        if key in value:
            validate(sub, value[key], field_path(path, key))


def _is_null_branch(branch: Mapping[str, Any]) -> bool:
    """A ``oneOf`` branch that is null and nothing else: ``{"type": "null"}`` (annotations aside)."""
    return branch.get("type") == "null" and not set(branch) - _ANNOTATIONS - {"type"}


def discriminator(schema: Mapping[str, Any]) -> tuple[str, dict[Any, Mapping[str, Any]]]:
    """The discriminating property of a ``oneOf`` and its object branches by value (a null branch aside)."""
    branches = [b for b in schema["oneOf"] if not _is_null_branch(b)]
    common: set[str] | None = None
    for branch in branches:
        consts = {k for k, v in branch.get("properties", {}).items() if "const" in v and k in branch.get("required", ())}
        common = consts if common is None else common & consts
    if not common:
        raise ValueError("oneOf branches must share a required property with a const (a discriminator)")
    name = sorted(common)[0]
    by_value: dict[Any, Mapping[str, Any]] = {}
    for branch in branches:
        by_value[branch["properties"][name]["const"]] = branch
    if len(by_value) != len(branches):
        raise ValueError(f"oneOf branches repeat a value of the discriminator {name!r}")
    return name, by_value


def _check_one_of(schema: Mapping[str, Any], value: Any, path: str) -> None:
    null = any(_is_null_branch(b) for b in schema["oneOf"])
    if value is None and null:
        return
    name, by_value = discriminator(schema)
    if not isinstance(value, dict):
        raise JobError(path, f"expected {'an object or null' if null else 'an object'}, got {describe(value)}")
    choices = ", ".join(literal(v) for v in by_value)
    if name not in value:
        raise JobError(field_path(path, name), f"required field is missing (expected one of {choices})")
    tag = value[name]
    branch = next((b for v, b in by_value.items() if _same(v, tag)), None)
    if branch is None:
        raise JobError(field_path(path, name), f"expected one of {choices}; got {describe(tag)}")
    validate(branch, value, path)


def check_schema(schema: Any, where: str = "#") -> None:
    """Refuse a schema that uses a keyword or a form this checker does not enforce.

    Raises
    ------
    ValueError
        With the schema location (``#/properties/poses/items``) and the problem.
    """
    if not isinstance(schema, Mapping):
        raise ValueError(f"{where}: a schema must be an object, got {type(schema).__name__}")
    unknown = set(schema) - _ASSERTIONS - _ANNOTATIONS
    if unknown:
        raise ValueError(f"{where}: unsupported keywords {sorted(unknown)}")
    types = schema.get("type")
    if types is not None:
        names = (types,) if isinstance(types, str) else tuple(types)
        if not names or not set(names) <= _TYPES:
            raise ValueError(f"{where}: type must name JSON types, got {types!r}")
    if "additionalProperties" in schema and schema["additionalProperties"] is not False:
        raise ValueError(f"{where}: additionalProperties may only be false")
    for key in schema.get("required", ()):
        if key not in schema.get("properties", {}):
            raise ValueError(f"{where}: required {key!r} has no entry in properties")
    for key, sub in schema.get("properties", {}).items():
        check_schema(sub, f"{where}/properties/{key}")
    if "items" in schema:
        check_schema(schema["items"], f"{where}/items")
    for i, sub in enumerate(schema.get("prefixItems", ())):
        check_schema(sub, f"{where}/prefixItems/{i}")
    if "pattern" in schema:
        re.compile(schema["pattern"])
    if "not" in schema:
        sub = schema["not"]
        if not isinstance(sub, Mapping) or set(sub) - _ANNOTATIONS != {"required"} or len(sub["required"]) < 2:
            raise ValueError(f'{where}/not: only {{"required": [two or more fields]}} is supported, got {sub!r}')
        for key in sub["required"]:
            if key not in schema.get("properties", {}):
                raise ValueError(f"{where}/not: required {key!r} has no entry in properties")
    if "oneOf" in schema:
        for i, branch in enumerate(schema["oneOf"]):
            check_schema(branch, f"{where}/oneOf/{i}")
            if not _is_null_branch(branch) and branch.get("type") != "object":
                raise ValueError(f'{where}/oneOf/{i}: a branch must be an object (type "object") or {{"type": "null"}}')
        if sum(_is_null_branch(b) for b in schema["oneOf"]) > 1:
            raise ValueError(f"{where}: oneOf may have one null branch, got more")
        try:
            discriminator(schema)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc
