"""The daemon under hostile job messages: every one refused, the daemon up, the journal intact.

``celld run`` runs as its own process next to the simulated UR10e (the
``daemon`` fixture of :mod:`tests.daemon.test_daemon_e2e`); the test talks to
it only over zenoh, sending raw payloads to the ``submit`` queryable as a
broken or hostile MES would: random bytes, text that is not UTF-8, oversized
payloads, deep nesting, NaN and infinities, duplicate keys, wrong types,
out-of-range numbers, arrays of the wrong length, unknown kinds and fields,
missing fields. Every payload is first refused locally by
:func:`celld.bus.requests.parse_submit` (so none is a job the arm would run), and
the daemon must give the same field and reason. Afterwards the daemon still
answers, runs a valid job, and its journal holds that job only.
"""

from __future__ import annotations

import collections
import functools
import json
import math
import signal
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import pytest
from hypothesis import HealthCheck, given, reject, settings
from hypothesis import strategies as st

from celld.bus import messages, requests, wire
from celld.bus.client import CellClient
from celld.errors import BusError, JobError
from celld.journal import Journal
from tests.daemon.test_daemon_e2e import daemon  # noqa: F401  (the fixture: sim UR10e + `celld run`)

pytestmark = pytest.mark.cell

# Hostile payloads sent to the daemon.
N_EXAMPLES = 200
# Longest a refusal may take to arrive, s (the server answers in milliseconds).
REPLY_TIMEOUT = 5.0
# Placeholder that a literal token (NaN, a 5000-digit integer, deep nesting) replaces in JSON text.
_HOLE = "@@HOLE@@"
_TAU = 2 * math.pi


# -- building blocks ------------------------------------------------------------------


def _text(message: Any) -> str:
    return json.dumps(message, separators=(",", ":"))


def _fill(message: Any, token: str) -> bytes:
    """``message`` as JSON text with the string ``_HOLE`` replaced by the raw text ``token``."""
    text = _text(message)
    assert text.count(json.dumps(_HOLE)) == 1, text
    return text.replace(json.dumps(_HOLE), token).encode("utf-8")


def _set(message: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """A copy of ``message`` with the dotted ``path`` (``target.q``) set to ``value``."""
    out = json.loads(json.dumps(message))
    *parents, last = path.split(".")
    node = out
    for key in parents:
        node = node[key]
    node[last] = value
    return out


def _object_text(pairs: list[tuple[str, str]]) -> str:
    """A JSON object from (key, value text) pairs, kept as given: duplicates stay."""
    return "{" + ",".join(f"{json.dumps(k)}:{v}" for k, v in pairs) + "}"


_pose = st.tuples(*[st.floats(-1.0, 1.0)] * 3, *[st.floats(-3.0, 3.0)] * 3).map(list)
_joints = st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6)

MOVE_JOINT = {"kind": "move", "target": {"space": "joint", "q": [0.1, -1.2, 1.5, -1.9, 1.6, 0.0]}}
MOVE_CARTESIAN = {"kind": "move", "target": {"space": "cartesian", "pose": [0.6, 0.0, 0.45, 0.0, 3.1, 0.0]}}
# Valid jobs of every kind: the raw material that the strategies break. Never sent as they are.
VALID = [
    {"kind": "health", "check": "robot"},
    {"kind": "health"},
    {"kind": "calibrate", "seed": 3, "n_poses": 6, "e_required_mm": 0.5},
    {"kind": "calibrate", "verification_pose": [0.6, 0.0, 0.4, 0.0, 3.1, 0.0], "compensate": True},
    {"kind": "weld", "workpiece": "t-joint", "delta_d_mm": 1.5, "arc": False, "ref": "order-17"},
    MOVE_JOINT,
    {**MOVE_CARTESIAN, "speed_scale": 0.3},
]
_valid = st.sampled_from(VALID)
_valid_bytes = _valid.map(lambda m: _text(m).encode("utf-8"))


class Field(NamedTuple):
    """What the schema wants in one field: a JSON type (``pose``/``poses``: UR poses) and a range."""

    type: str
    lo: float | None = None
    hi: float | None = None
    open_lo: bool = False


# Every field of every job kind, as celld.bus.messages describes it; a path with a
# dot is inside the move target.
FIELDS: dict[str, dict[str, Field]] = {
    "calibrate": {
        "n_poses": Field("integer", 4, messages.MAX_POSES),
        "e_required_mm": Field("number", 0.0, 100.0),
        "k_max": Field("integer", 1, 10_000),
        "poses": Field("poses"),
        "verification_pose": Field("pose"),
        "compensate": Field("boolean"),
        "seed": Field("integer", 0, 2**32 - 1),
        "ref": Field("string"),
    },
    "weld": {
        "workpiece": Field("string"),
        "delta_d_mm": Field("number", 0.0, 20.0, open_lo=True),
        "k_p": Field("number", 0.0, 1000.0, open_lo=True),
        "v_const_mm_s": Field("number", 0.0, 500.0, open_lo=True),
        "torch_offset_mm": Field("number", 0.0, 500.0, open_lo=True),
        "arc": Field("boolean"),
        "ref": Field("string"),
    },
    "move": {
        "target": Field("object"),
        "target.space": Field("string"),
        "target.q": Field("pose"),
        "target.pose": Field("pose"),
        "speed_scale": Field("number", 0.0, 1.0, open_lo=True),
        "ref": Field("string"),
    },
    "health": {"check": Field("string"), "ref": Field("string")},
}
_FIELD_LIST = [(kind, path, f) for kind, fields in FIELDS.items() for path, f in fields.items()]
_NUMERIC = [(k, p, f) for k, p, f in _FIELD_LIST if f.type in ("integer", "number")]


def _base(kind: str, path: str) -> dict[str, Any]:
    """A minimal valid message of ``kind`` that has ``path``'s parent."""
    if kind == "move":
        return dict(MOVE_CARTESIAN if path == "target.pose" else MOVE_JOINT)
    return {"kind": kind}


# One strategy per JSON type, for "a value of any type but this one".
_BY_TYPE = {
    "null": st.none(),
    "boolean": st.booleans(),
    "integer": st.integers(-(2**40), 2**40),
    "number": st.floats(allow_nan=False, allow_infinity=False).filter(lambda x: not x.is_integer()),
    "string": st.text(max_size=16),
    "array": st.lists(st.integers(-5, 5), max_size=8),
    "object": st.dictionaries(st.text(max_size=6), st.integers(-5, 5), max_size=3),
}
# JSON types a field of each kind accepts (2.0 is an integer, an integer is a number).
_ACCEPTS = {
    "integer": {"integer"},
    "number": {"integer", "number"},
    "boolean": {"boolean"},
    "string": {"string"},
    "pose": {"array"},
    "poses": {"array"},
    "object": {"object"},
}


def _wrong_type(f: Field) -> st.SearchStrategy[Any]:
    return st.one_of(*[s for name, s in _BY_TYPE.items() if name not in _ACCEPTS[f.type]])


def _out_of_range(f: Field) -> st.SearchStrategy[Any]:
    if f.type == "integer":
        return st.integers(max_value=int(f.lo) - 1, min_value=-(10**19)) | st.integers(min_value=int(f.hi) + 1, max_value=10**19)
    below = st.floats(max_value=f.lo, exclude_max=not f.open_lo, allow_nan=False, allow_infinity=False)
    above = st.floats(min_value=f.hi, exclude_min=True, allow_nan=False, allow_infinity=False)
    return below | above


# -- the hostile payloads, by category -----------------------------------------------------


_BAD_UTF8 = [
    b"\xff",
    b"\xfe\xff",
    b"\x80",
    b"\xc3\x28",
    b"\xc0\xaf",
    b"\xed\xa0\x80",
    b"\xf8\x88\x80\x80\x80",
    b"\xe2\x82",
    b"\xf4\x90\x80\x80",
]

random_bytes = st.binary(max_size=1024)

not_utf8 = st.one_of(
    # A valid job with a byte sequence that UTF-8 forbids spliced in anywhere.
    st.tuples(_valid_bytes, st.sampled_from(_BAD_UTF8), st.integers(0, 1000)).map(
        lambda t: t[0][: t[2] % (len(t[0]) + 1)] + t[1] + t[0][t[2] % (len(t[0]) + 1) :]
    ),
    # A valid job in another encoding.
    st.tuples(_valid, st.sampled_from(["utf-16", "utf-32", "utf-16-be"])).map(lambda t: _text(t[0]).encode(t[1])),
    st.text(alphabet="äöüßéñ°µ", min_size=1, max_size=20).map(
        lambda s: json.dumps({"kind": "health", "ref": s}, ensure_ascii=False).encode("latin-1")
    ),
)

huge = st.one_of(
    st.integers(129, 400_000).map(lambda n: _text({"kind": "health", "ref": "x" * n}).encode()),
    st.tuples(_valid_bytes, st.integers(wire.MAX_PAYLOAD_BYTES + 1, 2 * wire.MAX_PAYLOAD_BYTES)).map(
        lambda t: b" " * (t[1] - len(t[0])) + t[0]  # valid JSON, but too large
    ),
    st.integers(messages.MAX_POSES + 1, 3000).map(
        lambda n: _text({"kind": "calibrate", "poses": [[0.5, 0.0, 0.5, 0.0, 3.1, 0.0]] * n}).encode()
    ),
    st.tuples(st.sampled_from(["seed", "n_poses", "k_max"]), st.integers(wire.MAX_INT_DIGITS + 1, 6000)).map(
        lambda t: _fill({"kind": "calibrate", t[0]: _HOLE}, "7" * t[1])
    ),
    st.integers(1_000, 300_000).map(lambda n: _text({"kind": "health" * n}).encode()),
    st.integers(1_000, 300_000).map(lambda n: _text({"kind": "health", "k" * n: 1}).encode()),
)


def _nest(depth: int, shape: str) -> str:
    return "[" * depth + "]" * depth if shape == "array" else '{"a":' * depth + "0" + "}" * depth


_depth = st.integers(wire.MAX_DEPTH + 1, 50_000)
_shape = st.sampled_from(["array", "object"])
deep = st.one_of(
    st.tuples(_depth, _shape).map(lambda t: _nest(*t).encode()),
    st.tuples(st.sampled_from(_FIELD_LIST), _depth, _shape).map(
        lambda t: _fill(_set(_base(t[0][0], t[0][1]), t[0][1], _HOLE), _nest(t[1], t[2]))
    ),
    st.tuples(_depth, _shape).map(lambda t: _fill({"kind": "calibrate", "poses": [[0.5, 0.0, 0.5, 0.0, 3.1, _HOLE]]}, _nest(*t))),
)

_NOT_FINITE = ["NaN", "Infinity", "-Infinity", "1e400", "-1E999999", "nan", "inf", "-inf", "+1.0", "0x10", ".5", "1.", "01"]
_numeric_places = [(k, p) for k, p, _ in _NUMERIC] + [("calibrate", "verification_pose"), ("move", "target.q"), ("move", "target.pose")]


def _numeric_hole(place: tuple[str, str], index: int) -> dict[str, Any]:
    kind, path = place
    if path in ("verification_pose", "target.q", "target.pose"):
        values: list[Any] = [0.5, 0.0, 0.5, 0.0, 3.1, 0.0]
        values[index] = _HOLE
        return _set(_base(kind, path), path, values)
    return _set(_base(kind, path), path, _HOLE)


nan_inf = st.tuples(st.sampled_from(_numeric_places), st.integers(0, 5), st.sampled_from(_NOT_FINITE)).map(
    lambda t: _fill(_numeric_hole(t[0], t[1]), t[2])
)


def _duplicated(message: dict[str, Any], index: int, value: Any, nested: bool) -> bytes:
    """``message`` as text with one of its keys given twice (in the move target if ``nested``)."""

    def pairs(obj: dict[str, Any]) -> list[tuple[str, str]]:
        return [(k, _text(v)) for k, v in obj.items()]

    if nested and "target" in message:
        inner = pairs(message["target"])
        key = inner[index % len(inner)][0]
        inner.insert(index % (len(inner) + 1), (key, _text(value)))
        outer = [(k, _object_text(inner) if k == "target" else v) for k, v in pairs(message)]
        return _object_text(outer).encode()
    outer = pairs(message)
    key = outer[index % len(outer)][0]
    outer.insert(index % (len(outer) + 1), (key, _text(value)))
    return _object_text(outer).encode()


def _duplicated_same(message: dict[str, Any], index: int, nested: bool) -> bytes:
    """:func:`_duplicated` with the key's own value again."""
    obj = message["target"] if nested and "target" in message else message
    key = list(obj)[index % len(obj)]
    return _duplicated(message, index, obj[key], nested)


_any_json = st.recursive(
    st.none() | st.booleans() | st.integers(-1000, 1000) | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=10),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
    max_leaves=8,
)

duplicate_key = st.one_of(
    # The same key twice, with the same value: still refused (a parser that keeps the last would not see it).
    st.tuples(_valid, st.integers(0, 10), st.booleans()).map(lambda t: _duplicated_same(*t)),
    st.tuples(_valid, st.integers(0, 10), _any_json, st.booleans()).map(lambda t: _duplicated(t[0], t[1], t[2], t[3])),
)


wrong_type = st.sampled_from(_FIELD_LIST).flatmap(
    lambda kpf: _wrong_type(kpf[2]).map(lambda v: _text(_set(_base(kpf[0], kpf[1]), kpf[1], v)).encode())
)


def _pose_out_of_range(index: int) -> st.SearchStrategy[float]:
    limit = 2.5 if index < 3 else _TAU
    return st.floats(min_value=limit, exclude_min=True, allow_infinity=False) | st.floats(
        max_value=-limit, exclude_max=True, allow_infinity=False
    )


def _pose_with(values: list[Any], index: int, value: Any) -> list[Any]:
    """A copy of ``values`` with item ``index`` replaced."""
    out = list(values)
    out[index] = value
    return out


def _place_pose(where: str, pose: list[Any]) -> dict[str, Any]:
    """A job with ``pose`` in ``where``: a calibrate job's poses or verification pose, a move target."""
    if where == "poses":
        return {"kind": "calibrate", "poses": [[0.5, 0.0, 0.5, 0.0, 3.1, 0.0]] * 3 + [pose]}
    if where == "verification_pose":
        return {"kind": "calibrate", "verification_pose": pose}
    return _set(_base("move", where), where, pose)


out_of_range = st.one_of(
    st.sampled_from(_NUMERIC).flatmap(
        lambda kpf: _out_of_range(kpf[2]).map(lambda v: _text(_set(_base(kpf[0], kpf[1]), kpf[1], v)).encode())
    ),
    # A pose component outside the 2.5 m box or beyond 2 pi, in each place a pose goes.
    st.tuples(st.integers(0, 5), _pose, st.sampled_from(["verification_pose", "poses", "target.pose", "target.q"])).flatmap(
        lambda t: (_pose_out_of_range(t[0]) if t[2] != "target.q" else _pose_out_of_range(3)).map(
            lambda v: _text(_place_pose(t[2], _pose_with(t[1], t[0], v))).encode()
        )
    ),
    # Strings outside their enum or pattern, control characters, lone surrogates.
    st.text(max_size=12).map(lambda s: _text({"kind": "health", "check": s}).encode()),
    st.sampled_from(["", "../../etc/passwd", "a b", "x" * 65, "-lead", "t-joint/1", "*", "ü"]).map(
        lambda s: _text({"kind": "weld", "workpiece": s}).encode()
    ),
    st.sampled_from(["a\u0000b", "line\nbreak", "tab\there", "\u007f", "x" * 129]).map(
        lambda s: _text({"kind": "health", "ref": s}).encode()
    ),
    st.sampled_from(['"\\ud800"', '"a\\udfff"', '"\\ud83d\\u0041"']).map(lambda tok: _fill({"kind": "health", "ref": _HOLE}, tok)),
    # A lone surrogate in a key.
    st.sampled_from([b'"\\ud800"', b'"\\udc00x"']).map(lambda key: b'{"kind":"health",' + key + b":1}"),
)


_wrong_length = st.lists(st.floats(-1.0, 1.0), max_size=12).filter(lambda v: len(v) != 6)
wrong_length = st.one_of(
    st.tuples(_wrong_length, st.sampled_from(["verification_pose", "target.pose", "target.q"])).map(
        lambda t: _text(_place_pose(t[1], t[0])).encode()
    ),
    st.lists(_pose, max_size=3).map(lambda poses: _text({"kind": "calibrate", "poses": poses}).encode()),
    st.tuples(st.lists(_pose, min_size=4, max_size=8), _wrong_length, st.integers(0, 7)).map(
        lambda t: _text({"kind": "calibrate", "poses": _pose_with(t[0], t[2] % len(t[0]), t[1])}).encode()
    ),
    st.sampled_from([[], [[]], [[[]]], [[0.5, 0.0, 0.5, 0.0, 3.1, 0.0]]]).map(
        lambda q: _text({"kind": "move", "target": {"space": "joint", "q": q}}).encode()
    ),
)

unknown_kind = st.one_of(
    st.text(max_size=20).filter(lambda s: s not in messages.JOB_KINDS).map(lambda s: _text({"kind": s}).encode()),
    st.sampled_from(["HEALTH", "Health", "health ", " move", "calibrate\u0000", "weld\n", "heal th", "moves"]).map(
        lambda s: _text({"kind": s, "check": "robot"}).encode()
    ),
    _BY_TYPE["null"].map(lambda v: _text({"kind": v}).encode()),
    st.one_of(_BY_TYPE["integer"], _BY_TYPE["array"], _BY_TYPE["object"], _BY_TYPE["boolean"]).map(lambda v: _text({"kind": v}).encode()),
    # A job's fields without its kind.
    _valid.map(lambda m: _text({k: v for k, v in m.items() if k != "kind"}).encode()),
)

_job_keys = {p.split(".")[0] for fields in FIELDS.values() for p in fields} | {"kind", "space", "q", "pose"}
unknown_field = st.one_of(
    st.tuples(_valid, st.text(min_size=1, max_size=30).filter(lambda k: k not in _job_keys), _any_json).map(
        lambda t: _text({**t[0], t[1]: t[2]}).encode()
    ),
    st.tuples(
        st.sampled_from([MOVE_JOINT, MOVE_CARTESIAN]), st.sampled_from(["speed", "frame", "q_deg", "pose_mm", "kind"]), _any_json
    ).map(lambda t: _text(_set(t[0], f"target.{t[1]}", t[2])).encode()),
    # Fields of other messages: a record's state, an id, a reply's ok.
    st.tuples(
        _valid,
        st.sampled_from([("state", "succeeded"), ("id", "20250101-000000-abcdef"), ("ok", True), ("job", "x"), ("result", "/etc/passwd")]),
    ).map(lambda t: _text({**t[0], t[1][0]: t[1][1]}).encode()),
    # A field of another kind.
    st.sampled_from(
        [
            {"kind": "health", "seed": 3},
            {"kind": "move", "target": MOVE_JOINT["target"], "check": "robot"},
            {"kind": "calibrate", "arc": False},
            {"kind": "weld", "n_poses": 6},
            {"kind": "health", "target": MOVE_JOINT["target"]},
        ]
    ).map(lambda m: _text(m).encode()),
)

missing = st.sampled_from(
    [
        b"",
        b"{}",
        b" ",
        b"\n\t ",
        b"null",
        b"[]",
        b'""',
        b"0",
        b'{"kind":"move"}',
        b'{"kind":"move","target":{}}',
        b'{"kind":"move","target":null}',
        b'{"kind":"move","target":{"space":"joint"}}',
        b'{"kind":"move","target":{"space":"cartesian"}}',
        b'{"kind":"move","target":{"q":[0,0,0,0,0,0]}}',
        b'{"kind":"move","target":{"space":"cartesian","q":[0,0,0,0,0,0]}}',
        b'{"kind":"move","target":{"space":"joint","pose":[0.5,0,0.5,0,3.1,0]}}',
        b'{"kind":"move","target":{"space":"joint","q":[0,0,0,0,0,0],"pose":[0.5,0,0.5,0,3.1,0]}}',
        b'{"kind":"move","target":{"space":"","q":[0,0,0,0,0,0]}}',
        b'{"kind":""}',
        b'{"kind":"health","check":""}',
        b'{"kind":"health","check":null}',
        b'{"kind":"calibrate","poses":[]}',
        b'{"kind":"weld","workpiece":""}',
        b'{"":""}',
    ]
)

not_an_object = st.one_of(
    _any_json.filter(lambda v: not isinstance(v, dict)).map(lambda v: _text(v).encode()),
    _valid.map(lambda m: _text([m]).encode()),
    _valid.map(lambda m: json.dumps(_text(m)).encode()),  # the job as a JSON string
    # A valid job cut short, doubled, with trailing bytes, a BOM, comments, single quotes.
    st.tuples(_valid_bytes, st.integers(0, 10_000)).map(lambda t: t[0][: t[1] % len(t[0])]),
    _valid_bytes.map(lambda b: b + b),
    st.tuples(_valid_bytes, st.sampled_from([b",", b"]", b"}", b"x", b"\x00", b"//c", b"\xef\xbb\xbf"])).map(lambda t: t[0] + t[1]),
    _valid_bytes.map(lambda b: b"\xef\xbb\xbf" + b),
    _valid_bytes.map(lambda b: b"/* job */" + b),
    _valid_bytes.map(lambda b: b.replace(b'"', b"'")),
    _valid_bytes.map(lambda b: b[:-1] + b",}"),  # a trailing comma
)

conflicting = st.tuples(st.integers(4, 20), st.lists(_pose, min_size=4, max_size=6)).map(
    lambda t: _text({"kind": "calibrate", "n_poses": t[0], "poses": t[1]}).encode()
)

CATEGORIES: dict[str, st.SearchStrategy[bytes]] = {
    "random_bytes": random_bytes,
    "not_utf8": not_utf8,
    "huge": huge,
    "deep": deep,
    "nan_inf": nan_inf,
    "duplicate_key": duplicate_key,
    "wrong_type": wrong_type,
    "out_of_range": out_of_range,
    "wrong_length": wrong_length,
    "unknown_kind": unknown_kind,
    "unknown_field": unknown_field,
    "missing": missing,
    "not_an_object": not_an_object,
    "conflicting": conflicting,
}


def _quotas(total: int) -> dict[str, int]:
    """``total`` examples shared as evenly as possible between the categories."""
    n, extra = divmod(total, len(CATEGORIES))
    return {name: n + (i < extra) for i, name in enumerate(CATEGORIES)}


def _fuzzer(strategy: st.SearchStrategy[bytes], quota: int, send: Callable[[bytes], None]) -> Callable[[], None]:
    """A hypothesis run of ``quota`` payloads from ``strategy``, each given to ``send``."""

    @settings(
        max_examples=quota,
        deadline=None,
        derandomize=True,
        database=None,
        print_blob=False,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example],
    )
    @given(payload=strategy)
    def run(payload: bytes) -> None:
        send(payload)

    return run


def _local_refusal(payload: bytes) -> JobError | None:
    """The refusal celld's own parser gives ``payload``; None if it is a valid job.

    Anything but a JobError propagates: the daemon would answer it as an
    internal error, which is a bug this test should report with its payload.
    """
    try:
        requests.parse_submit(payload)
    except JobError as exc:
        return exc
    return None


def _same_reason(daemon_reason: str, local_reason: str) -> bool:
    """The daemon gave the reason the local parser gives.

    One allowed difference: deep nesting is refused either by json's own
    recursion limit ("got far more") or by the depth check after it ("got
    more"), depending on how deep the caller's stack already is: the daemon
    parses inside an asyncio task, this test at the top of a thread.
    """
    nesting = f"expected at most {wire.MAX_DEPTH} levels of nesting, got "
    if daemon_reason.startswith(nesting) and local_reason.startswith(nesting):
        return True
    return daemon_reason == local_reason


# -- the test ---------------------------------------------------------------------------


def test_hostile_submits_are_all_refused_and_the_daemon_stays_up_with_an_intact_journal(daemon, tmp_path: Path) -> None:  # noqa: F811
    proc, cfg = daemon.daemon, daemon.config
    log_path = tmp_path / "daemon.log"
    journal_path = Path(cfg.cell.state_dir) / "journal.db"
    sent: collections.Counter[str] = collections.Counter()

    def log_tail() -> str:
        return log_path.read_text(errors="replace")[-3000:]

    with CellClient(cfg.bus, "e2e", timeout=REPLY_TIMEOUT) as client:

        def refused(category: str, payload: bytes) -> None:
            expected = _local_refusal(payload)
            if expected is None:
                reject()  # a valid job is not hostile: the arm would run it
            assert proc.poll() is None, f"the daemon died before this payload:\n{log_tail()}"
            try:
                reply = client.request_raw("submit", payload)
            except BusError as exc:
                raise AssertionError(f"{category}: no refusal within {REPLY_TIMEOUT} s for {payload[:200]!r}: {exc}\n{log_tail()}") from exc
            sent[category] += 1
            assert reply["ok"] is False, f"{category}: the daemon took {payload[:200]!r}: {reply}"
            messages.check_message("error-reply", reply)
            error = reply["error"]
            assert error["field"].startswith("$") and error["reason"].strip(), reply
            # The daemon refuses it for the reason celld's own parser gives, not as busy or an internal error.
            assert error["field"] == expected.field, (category, payload[:200], error)
            assert _same_reason(error["reason"], expected.reason), (category, payload[:200], error)

        quotas = _quotas(N_EXAMPLES)
        t0 = time.monotonic()
        for category, strategy in CATEGORIES.items():
            _fuzzer(strategy, quotas[category], functools.partial(refused, category))()
        fuzz_s = time.monotonic() - t0

        assert sent == quotas and sum(sent.values()) == N_EXAMPLES, sent
        assert fuzz_s < 60, f"{N_EXAMPLES} refusals took {fuzz_s:.1f} s"

        # Still up, still answering, and not one job was created.
        assert proc.poll() is None, log_tail()
        status = client.status()
        assert status["state"] == "idle" and status["running"] is None and status["queued"] == [], status
        assert client.list() == []

        # A valid job still runs.
        reply, record = client.submit_and_wait({"kind": "health", "check": "robot"}, timeout=60)
        assert record["state"] == "succeeded", record["reason"]
        assert [j["id"] for j in client.list()] == [reply["job"]]

    # The journal, read beside the running daemon: intact, and the valid job is its only row.
    db = sqlite3.connect(f"file:{journal_path}?mode=ro", uri=True)
    try:
        assert db.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        rows = db.execute("SELECT id, kind, state, params FROM jobs").fetchall()
    finally:
        db.close()
    assert [(i, k, s, json.loads(p)) for i, k, s, p in rows] == [
        (reply["job"], "health", "succeeded", {"kind": "health", "check": "robot"})
    ]

    # And it still stops cleanly, leaving a journal that passes its own check.
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 0, log_tail()
    with Journal(journal_path) as journal:
        assert journal.check() == []
        assert [r.id for r in journal.jobs()] == [reply["job"]]
