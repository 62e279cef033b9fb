"""Building blocks of JSON Schema documents (draft 2020-12) for the JSON that celld sends and writes.

A module that builds a JSON document (a report's ``as_dict``, a job's
result) describes its shape beside the code that builds it, with these
functions; the bus gathers the shapes into the schemas it exports
(:mod:`celld.bus.messages`, and with every job kind's result
:mod:`celld.daemon.results`). Each function returns a new plain dict and
uses only the keywords the bus's checker enforces (:mod:`celld.bus.checker`):
``type``, ``const``, ``enum``, number and string bounds, ``items`` and
``prefixItems``, ``properties``, ``required``, ``additionalProperties: false``,
``oneOf`` told apart by a ``const`` property (with at most one ``null``
branch), and annotations.

Objects whose shape is known are closed (:func:`obj`:
``additionalProperties: false``); :func:`free` is an object of any shape, for
what is not described (a progress event's stage figures).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

# Free text: printable, no control characters.
TEXT_PATTERN = r"^[^\u0000-\u001f\u007f]*$"


def number(
    desc: str = "", lo: float | None = None, hi: float | None = None, *, open_lo: bool = False, null: bool = False
) -> dict[str, Any]:
    """A number in ``[lo, hi]`` (``(lo, hi]`` with ``open_lo``); ``null`` also allows null (a value that was not finite)."""
    s = _described({"type": ["number", "null"] if null else "number"}, desc)
    return _bounded(s, "exclusiveMinimum" if open_lo else "minimum", lo, "maximum", hi)


def integer(desc: str = "", lo: int | None = None, hi: int | None = None, *, null: bool = False) -> dict[str, Any]:
    """An integer in ``[lo, hi]``; ``null`` also allows null."""
    s = _described({"type": ["integer", "null"] if null else "integer"}, desc)
    return _bounded(s, "minimum", lo, "maximum", hi)


def string(desc: str = "", *, null: bool = False) -> dict[str, Any]:
    """Any string; ``null`` also allows null."""
    return _described({"type": ["string", "null"] if null else "string"}, desc)


def text(desc: str, max_length: int = 200) -> dict[str, Any]:
    """Free text from outside: at most ``max_length`` characters, no control characters."""
    return {"type": "string", "maxLength": max_length, "pattern": TEXT_PATTERN, "description": desc}


def boolean(desc: str = "") -> dict[str, Any]:
    return _described({"type": "boolean"}, desc)


def const(value: Any, desc: str = "") -> dict[str, Any]:
    """Exactly ``value`` (a ``oneOf``'s branches are told apart by one)."""
    return _described({"const": value}, desc)


def enum(values: Iterable[Any], desc: str = "") -> dict[str, Any]:
    """One of ``values`` (a vocabulary: pass the tuple its module defines, never a copy)."""
    return _described({"enum": list(values)}, desc)


def array(items: Mapping[str, Any], desc: str = "", min_items: int | None = None, max_items: int | None = None) -> dict[str, Any]:
    """A list of ``items``."""
    s = _described({"type": "array", "items": dict(items)}, desc)
    return _bounded(s, "minItems", min_items, "maxItems", max_items)


def vector(desc: str, n: int, lo: float | None = None, hi: float | None = None, *, null_items: bool = False) -> dict[str, Any]:
    """Exactly ``n`` numbers (each null where not finite, with ``null_items``)."""
    return {**array(number(lo=lo, hi=hi, null=null_items), desc), "minItems": n, "maxItems": n}


def texts(desc: str = "") -> dict[str, Any]:
    """A list of strings (reasons, warnings, ids)."""
    return array({"type": "string"}, desc)


def matrix4(desc: str = "4x4 homogeneous transform, rows, metres.") -> dict[str, Any]:
    """A 4x4 homogeneous transform as a list of rows."""
    return {**array(vector("A row.", 4), desc), "minItems": 4, "maxItems": 4}


def obj(desc: str, properties: Mapping[str, Mapping[str, Any]], required: Iterable[str] = ()) -> dict[str, Any]:
    """An object of exactly ``properties`` (none other), of which ``required`` must be there."""
    return {
        "type": "object",
        "description": desc,
        "properties": {k: dict(v) for k, v in properties.items()},
        "required": list(required),
        "additionalProperties": False,
    }


def free(desc: str) -> dict[str, Any]:
    """An object of any shape."""
    return {"type": "object", "description": desc}


def one_of(desc: str, *branches: Mapping[str, Any]) -> dict[str, Any]:
    """Exactly one of ``branches``: objects that share a required property with a different ``const`` in each."""
    return {"description": desc, "oneOf": [dict(b) for b in branches]}


def nullable(schema: Mapping[str, Any], desc: str = "") -> dict[str, Any]:
    """``schema`` or null: null added to its ``type``, or a ``null`` branch added to its ``oneOf``.

    Raises
    ------
    ValueError
        ``schema`` has neither a ``type`` nor a ``oneOf``.
    """
    s = dict(schema)
    if desc:
        s["description"] = desc
    if "oneOf" in s:
        s["oneOf"] = [{"type": "null"}, *(b for b in s["oneOf"] if b != {"type": "null"})]
    elif "type" in s:
        names = [s["type"]] if isinstance(s["type"], str) else list(s["type"])
        s["type"] = names if "null" in names else [*names, "null"]
    else:
        raise ValueError(f"nullable: expected a schema with a type or a oneOf, got keys {sorted(s)}")
    return s


def with_properties(
    schema: Mapping[str, Any], properties: Mapping[str, Mapping[str, Any]], required: Iterable[str] = (), desc: str = ""
) -> dict[str, Any]:
    """``schema`` (an object, or a ``oneOf`` of objects: each branch) with ``properties`` added or replaced.

    A new dict; ``schema`` is not changed.
    """
    if "oneOf" in schema:
        out = dict(schema)
        out["oneOf"] = [b if b == {"type": "null"} else with_properties(b, properties, required) for b in schema["oneOf"]]
    else:
        out = {**schema, "properties": {**schema.get("properties", {}), **{k: dict(v) for k, v in properties.items()}}}
        out["required"] = [*schema.get("required", []), *(r for r in required if r not in schema.get("required", []))]
    if desc:
        out["description"] = desc
    return out


def _described(s: dict[str, Any], desc: str) -> dict[str, Any]:
    if desc:
        s["description"] = desc
    return s


def _bounded(s: dict[str, Any], lo_key: str, lo: float | None, hi_key: str, hi: float | None) -> dict[str, Any]:
    """``s`` with its lower and upper bound keywords, each only when given."""
    if lo is not None:
        s[lo_key] = lo
    if hi is not None:
        s[hi_key] = hi
    return s
