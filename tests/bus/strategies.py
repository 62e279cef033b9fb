"""Hypothesis strategies and fixed payloads for bus messages, valid and hostile.

Shared by the bus tests and by daemon-level tests that fuzz a running cell:
``from tests.bus.strategies import hostile_jobs, HOSTILE_PAYLOADS``.
"""

from __future__ import annotations

import json

from hypothesis import strategies as st

from celld.bus import messages

finite = st.floats(allow_nan=False, allow_infinity=False)
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | finite | st.text(max_size=30),
    lambda children: st.lists(children, max_size=6) | st.dictionaries(st.text(max_size=12), children, max_size=6),
    max_leaves=30,
)

poses = st.lists(st.tuples(*[st.floats(-2.5, 2.5)] * 3, *[st.floats(-6.28, 6.28)] * 3).map(list), min_size=4, max_size=8)
valid_jobs = st.one_of(
    st.builds(
        lambda n, e, k, c, s: {"kind": "calibrate", "n_poses": n, "e_required_mm": e, "k_max": k, "compensate": c, "seed": s},
        st.integers(4, 1000),
        st.floats(0, 100),
        st.integers(1, 10_000),
        st.booleans(),
        st.integers(0, 2**32 - 1),
    ),
    st.builds(lambda p: {"kind": "calibrate", "poses": p}, poses),
    st.builds(
        lambda d, v, k, a: {"kind": "weld", "delta_d_mm": d, "v_const_mm_s": v, "k_p": k, "arc": a},
        st.floats(0.01, 20),
        st.floats(0.01, 500),
        st.floats(0.01, 1000),
        st.booleans(),
    ),
    st.builds(
        lambda q, s, r: {"kind": "move", "target": {"space": "joint", "q": q}, "speed_scale": s, "robot": r},
        st.lists(st.floats(-6.28, 6.28), min_size=6, max_size=6),
        st.floats(0.01, 1.0),
        st.sampled_from([1, 2]),
    ),
    st.builds(lambda c: {"kind": "health", "check": c}, st.sampled_from(messages.HEALTH_CHECKS)),
    st.builds(
        lambda n, t, p, s, d: {"kind": "tool-calibrate", "n_poses": n, "max_tilt_deg": t, "tip_position": p, "seed": s, "dry_run": d},
        st.integers(3, messages.MAX_TOOL_POSES),
        st.floats(2.0, 45.0),
        st.lists(st.floats(-2.5, 2.5), min_size=3, max_size=3),
        st.integers(0, 2**32 - 1),
        st.booleans(),
    ),
)
_kinds = st.sampled_from(["calibrate", "weld", "move", "health", "Weld", "", "x"])
_fields = st.sampled_from(["n_poses", "poses", "target", "arc", "check", "k_p", "ref", "kind", "zz"])


@st.composite
def hostile_jobs(draw: st.DrawFn) -> bytes:
    """Submit payloads that are mostly wrong: raw bytes, any JSON, job-shaped messages with a bad field."""
    choice = draw(st.integers(0, 3))
    if choice == 0:
        return draw(st.binary(max_size=200))
    if choice == 1:
        return json.dumps(draw(json_values)).encode()
    message = {"kind": draw(_kinds), draw(_fields): draw(json_values)}
    if choice == 3:
        message["extra_" + draw(st.text(max_size=5))] = draw(json_values)
    return json.dumps(message).encode()


# Payloads each of which a cell must refuse with an error reply.
HOSTILE_PAYLOADS = [
    b"\xff\xfe\x00garbage",
    b"[1, 2, 3]",
    b'"a string"',
    b"null",
    b'{"kind": "calibrate", "n_poses": NaN}',
    b'{"kind": "calibrate", "e_required_mm": 1e999}',
    b'{"kind": "weld", "kind": "move"}',
    b'{"kind": "move"}',
    b'{"kind": "move", "target": {"space": "joint", "q": [0, 0, 0, 0, 0]}}',
    b'{"kind": "calibrate", "poses": [[0, 0, 0, 0, 0, 0]]}',
    b'{"kind": "health", "check": "everything"}',
    b'{"kind": "health", "extra": {}}',
    b'{"kind": "calibrate", "seed": 123456789012345678901234567890}',
    b"[" * 50_000 + b"]" * 50_000,
    b'{"kind": "health", "ref": "' + b"x" * 300_000 + b'"}',
    b'{"kind": "health", "ref": "\\ud800"}',
]
