"""A message's bytes: hostile input refused before it is interpreted, with the reason; numpy values encoded."""

from __future__ import annotations

import json

import numpy as np
import pytest

from celld.bus import wire
from celld.errors import JobError


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b"\xff\xfe", "expected UTF-8 text, got byte 0xff at offset 0"),
        (b'{"kind": "health"', "expected JSON, got an error at line 1"),
        (b'{"kind": "calibrate", "n_poses": NaN}', "got NaN"),
        (b'{"kind": "calibrate", "e_required_mm": Infinity}', "got Infinity"),
        (b'{"kind": "calibrate", "e_required_mm": 1e400}', "overflows a double"),
        (b'{"kind": "calibrate", "seed": 1' + b"0" * 40 + b"}", "at most 20 digits"),
        (b'{"kind": "health", "kind": "weld"}', "duplicate field 'kind'"),
        (b'{"kind": "health", "ref": "\\udc00"}', "lone surrogate"),
        (b"[" * 7 + b"]" * 7, "at most 6 levels of nesting"),
        (b"[" * 100_000, "levels of nesting"),
        (b" " * (wire.MAX_PAYLOAD_BYTES + 1), f"expected at most {wire.MAX_PAYLOAD_BYTES} bytes"),
    ],
)
def test_hostile_bytes_are_refused_before_interpretation(raw: bytes, reason: str) -> None:
    with pytest.raises(JobError) as err:
        wire.load_json(raw)
    assert err.value.field == "$"
    assert reason in err.value.reason, err.value.reason
    assert err.value.reason.isascii() and len(err.value.reason) < 200


def test_an_empty_payload_is_an_empty_object() -> None:
    assert wire.load_json(b"") == {}


def test_numpy_arrays_and_scalars_are_encoded_as_json_lists_and_numbers() -> None:
    message = {"q": np.array([0.5, -1.0]), "n": np.int64(3), "x": np.float32(0.25), "flag": np.bool_(True)}
    assert json.loads(wire.encode(message)) == {"q": [0.5, -1.0], "n": 3, "x": 0.25, "flag": True}
    with pytest.raises(TypeError, match="object is not JSON serialisable"):
        wire.encode({"x": object()})
    with pytest.raises(ValueError):
        wire.encode({"x": float("nan")})


def test_an_error_reply_names_the_field_and_the_reason() -> None:
    assert wire.error_reply("$.job", "no such job") == {"ok": False, "error": {"field": "$.job", "reason": "no such job"}}
