"""A message's bytes: the hostile-JSON loader, the encoder, and the reply to a refused request.

Hostile input is refused before it is interpreted (:func:`load_json`): more
than :data:`MAX_PAYLOAD_BYTES`, not UTF-8, not JSON, NaN or infinities,
duplicate keys, integers of more than :data:`MAX_INT_DIGITS` digits, nesting
deeper than :data:`MAX_DEPTH`, lone surrogates in strings. Every refusal is a
:class:`~celld.errors.JobError` with the JSON path of the field (``$`` for
the whole message) and the reason. What a loaded request must look like is
its schema's (:mod:`celld.bus.messages`); :mod:`celld.bus.requests` checks it
and builds the request's value.

:func:`encode` is the other way: a message (a reply, an event) as compact
UTF-8 JSON, numpy arrays and scalars as JSON lists and numbers;
:func:`error_reply` is the reply to a refused request.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

from celld.bus.checker import describe
from celld.errors import JobError

# Largest request payload accepted, bytes (1000 calibration poses fit in ~130 KiB).
MAX_PAYLOAD_BYTES = 256 * 1024
# Deepest nesting of arrays and objects in a request (a pose list is 3).
MAX_DEPTH = 6
# Longest integer literal accepted, digits (an int64 has 19).
MAX_INT_DIGITS = 20


def _refuse_constant(name: str) -> Any:
    raise JobError("$", f"expected finite numbers, got {name} (not JSON)")


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise JobError("$", f"expected finite numbers, got {describe(text)} (overflows a double)")
    return value


def _parse_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise JobError("$", f"expected integers of at most {MAX_INT_DIGITS} digits, got one of {len(text)}")
    return int(text)


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise JobError("$", f"duplicate field {key!a}")
        out[key] = value
    return out


def _check_tree(value: Any) -> None:
    """Refuse nesting deeper than MAX_DEPTH and strings that are not valid Unicode."""
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, (dict, list)):
            if depth >= MAX_DEPTH:
                raise JobError("$", f"expected at most {MAX_DEPTH} levels of nesting, got more")
            if isinstance(node, dict):
                for k, v in node.items():
                    _check_unicode(k)
                    stack.append((v, depth + 1))
            else:
                stack.extend((v, depth + 1) for v in node)
        elif isinstance(node, str):
            _check_unicode(node)


def _check_unicode(text: str) -> None:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as exc:
        raise JobError("$", f"expected valid Unicode text, got a lone surrogate in {describe(text)}") from exc


def load_json(raw: bytes | bytearray | memoryview) -> Any:
    """Decode one request payload into JSON values, refusing hostile input.

    An empty payload is ``{}``.

    Raises
    ------
    JobError
        ``field`` is ``"$"``; the reason names the problem (too large, not
        UTF-8, not JSON, NaN, duplicate key, too deep, ...).
    """
    if not isinstance(raw, (bytes, bytearray, memoryview)):
        raise JobError("$", f"expected bytes, got {type(raw).__name__}")
    size = len(raw)
    if size > MAX_PAYLOAD_BYTES:
        raise JobError("$", f"expected at most {MAX_PAYLOAD_BYTES} bytes, got {size}")
    if size == 0:
        return {}
    try:
        text = bytes(raw).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise JobError("$", f"expected UTF-8 text, got byte 0x{exc.object[exc.start]:02x} at offset {exc.start}") from exc
    try:
        value = json.loads(
            text,
            parse_constant=_refuse_constant,
            parse_float=_parse_float,
            parse_int=_parse_int,
            object_pairs_hook=_no_duplicates,
        )
    except json.JSONDecodeError as exc:
        raise JobError("$", f"expected JSON, got an error at line {exc.lineno} column {exc.colno}: {exc.msg}") from exc
    except RecursionError as exc:
        raise JobError("$", f"expected at most {MAX_DEPTH} levels of nesting, got far more") from exc
    except ValueError as exc:  # e.g. a number the int parser refuses
        raise JobError("$", f"expected JSON numbers, got {describe(str(exc))}") from exc
    _check_tree(value)
    return value


# -- encoding ------------------------------------------------------------------------


def _numpy_to_json(value: Any) -> Any:
    # A numpy array or scalar (tolist gives lists and Python numbers), without importing numpy here.
    if hasattr(value, "tolist") and hasattr(value, "dtype"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def encode(message: Mapping[str, Any]) -> bytes:
    """A message as compact UTF-8 JSON; numpy arrays and scalars become lists and numbers.

    Raises
    ------
    ValueError
        NaN or an infinity (they are not JSON).
    TypeError
        A value JSON cannot represent.
    """
    return json.dumps(message, separators=(",", ":"), allow_nan=False, default=_numpy_to_json).encode("utf-8")


def error_reply(field: str, reason: str) -> dict[str, Any]:
    """The reply to a refused request."""
    return {"ok": False, "error": {"field": field, "reason": reason}}
