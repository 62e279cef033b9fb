"""Requests as values: valid messages become jobs in SI, bad ones name the field and the reason; a job goes back to its message."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from celld.bus import requests, wire
from celld.bus.requests import CalibrateJob, HealthJob, MoveJob, WeldJob, parse, parse_submit
from celld.errors import JobError
from tests.bus.strategies import json_values, valid_jobs


def submit(message: object) -> requests.Job:
    return parse_submit(json.dumps(message).encode())


def refusal(message: object | bytes, request: str = "submit") -> JobError:
    raw = message if isinstance(message, bytes) else json.dumps(message).encode()
    with pytest.raises(JobError) as err:
        parse(request, raw)
    return err.value


def test_calibrate_converts_millimetres_and_keeps_config_defaults_open() -> None:
    job = submit({"kind": "calibrate", "n_poses": 12, "e_required_mm": 0.3, "compensate": True, "ref": "order-7"})
    assert isinstance(job, CalibrateJob)
    assert job.n_poses == 12 and job.e_required == pytest.approx(0.3e-3) and job.compensate
    assert (job.k_max, job.seed, job.verification_pose, job.poses) == (None, None, None, ())
    assert job.ref == "order-7"


def test_calibrate_with_given_poses() -> None:
    poses = [[0.5 + 0.01 * i, 0.0, 0.4, 0.0, math.pi, 0.0] for i in range(5)]
    job = submit({"kind": "calibrate", "poses": poses, "verification_pose": poses[0]})
    assert job.poses == tuple(tuple(p) for p in poses) and job.verification_pose == tuple(poses[0])


def test_weld_move_health() -> None:
    weld = submit({"kind": "weld", "workpiece": "t-joint-300", "delta_d_mm": 1.5, "v_const_mm_s": 10, "k_p": 4, "arc": False})
    assert weld == WeldJob(workpiece="t-joint-300", delta_d=pytest.approx(1.5e-3), k_p=4.0, v_const=pytest.approx(0.01), arc=False)
    move = submit({"kind": "move", "target": {"space": "joint", "q": [0, -1.57, 1.57, -1.57, -1.57, 0]}, "speed_scale": 0.2})
    assert move == MoveJob(space="joint", target=(0.0, -1.57, 1.57, -1.57, -1.57, 0.0), speed_scale=0.2)
    pose = submit({"kind": "move", "target": {"space": "cartesian", "pose": [0.6, 0, 0.4, 0, 3.14, 0]}})
    assert pose.space == "cartesian" and pose.speed_scale == 0.5 and pose.robot == 1
    assert submit({"kind": "health"}) == HealthJob(check="all")


def test_a_move_of_the_second_robot_names_it_and_goes_back_to_its_message() -> None:
    message = {"kind": "move", "target": {"space": "joint", "q": [0, -1.57, 1.57, -1.57, -1.57, 0]}, "speed_scale": 0.2, "robot": 2}
    job = submit(message)
    assert isinstance(job, MoveJob) and job.robot == 2
    assert submit(requests.job_to_message(job)) == job
    for robot, reason in ((3, "expected one of 1, 2"), (True, "expected one of 1, 2"), ("2", "expected one of 1, 2")):
        err = refusal({**message, "robot": robot})
        assert err.field == "$.robot" and reason in err.reason, (robot, err)


def test_integral_floats_count_as_integers() -> None:
    assert submit({"kind": "calibrate", "n_poses": 12.0}).n_poses == 12


@pytest.mark.parametrize(
    ("message", "field", "reason"),
    [
        ({}, "$.kind", "required field is missing"),
        ({"kind": "paint"}, "$.kind", 'expected one of "calibrate", "weld", "move", "health"'),
        ({"kind": "calibrate", "n_poses": "12"}, "$.n_poses", "expected an integer, got string '12'"),
        ({"kind": "calibrate", "n_poses": True}, "$.n_poses", "expected an integer, got true"),
        ({"kind": "calibrate", "n_poses": 12.5}, "$.n_poses", "expected an integer, got 12.5"),
        ({"kind": "calibrate", "n_poses": 3}, "$.n_poses", "expected a value >= 4, got 3"),
        ({"kind": "calibrate", "n_poses": 10**6}, "$.n_poses", "expected a value <= 1000"),
        ({"kind": "calibrate", "e_required_mm": -0.1}, "$.e_required_mm", "expected a value >= 0.0"),
        ({"kind": "calibrate", "poses": [[0, 0, 0, 0, 0, 0]] * 3}, "$.poses", "expected at least 4 items, got 3"),
        ({"kind": "calibrate", "poses": [[0, 0, 0, 0, 0, 0]] * 3 + [[0, 0, 0, 0, 0]]}, "$.poses[3]", "expected exactly 6 items, got 5"),
        (
            {"kind": "calibrate", "poses": [[0, 0, 0, 0, 0, 0]] * 3 + [[0, 0, 9, 0, 0, 0]]},
            "$.poses[3][2]",
            "expected a value <= 2.5, got 9",
        ),
        ({"kind": "calibrate", "poses": [[0, 0, 0, 0, 0, 0]] * 4, "n_poses": 4}, "$.n_poses", "either poses or n_poses"),
        ({"kind": "calibrate", "colour": "red"}, "$.colour", "unknown field"),
        ({"kind": "weld", "delta_d_mm": 0}, "$.delta_d_mm", "expected a value > 0.0, got 0"),
        ({"kind": "weld", "workpiece": "../etc/passwd"}, "$.workpiece", "expected a string matching"),
        ({"kind": "weld", "arc": "yes"}, "$.arc", "expected true or false"),
        ({"kind": "move"}, "$.target", "required field is missing"),
        ({"kind": "move", "target": {"space": "polar"}}, "$.target.space", 'expected one of "joint", "cartesian"'),
        ({"kind": "move", "target": {"space": "joint", "pose": [0] * 6}}, "$.target.pose", "unknown field"),
        ({"kind": "move", "target": {"space": "joint", "q": [0, 0, 0, 0, 0, 7]}}, "$.target.q[5]", "expected a value <= 6.28"),
        ({"kind": "move", "target": {"space": "joint", "q": [0] * 6}, "speed_scale": 0}, "$.speed_scale", "expected a value > 0.0"),
        ({"kind": "health", "check": "all", "ref": "a\nb"}, "$.ref", "expected a string matching"),
        ({"kind": "health", "ref": "x" * 129}, "$.ref", "expected at most 128 characters, got 129"),
        ({"kind": "health", "bad key": 1}, "$['bad key']", "unknown field"),
        ([{"kind": "health"}], "$", "expected an object, got an array of 1"),
        ("health", "$", "expected an object, got string 'health'"),
    ],
)
def test_bad_submits_name_the_field_and_the_reason(message: object, field: str, reason: str) -> None:
    err = refusal(message)
    assert err.field == field
    assert reason in err.reason, err.reason


def test_empty_payload_is_an_empty_object() -> None:
    assert parse("status", b"") == requests.StatusRequest()
    assert parse("list", b"") == requests.ListRequest(limit=50)
    assert parse("calibration", b"") == requests.CalibrationRequest()
    assert refusal(b"", "cancel").field == "$.job"


def test_other_requests() -> None:
    assert parse("status", b'{"job": "20250101-120000-abcdef"}').job == "20250101-120000-abcdef"
    assert parse("cancel", b'{"job": "j1", "reason": "wrong part"}') == requests.CancelRequest("j1", "wrong part")
    assert parse("list", b'{"limit": 5, "state": "failed", "kind": "weld"}') == requests.ListRequest(5, "failed", "weld")
    assert parse("accept", b'{"job": "j1"}') == requests.AcceptRequest("j1")
    assert parse("accept", b'{"job": "j1", "force": true}') == requests.AcceptRequest("j1", force=True)
    assert refusal({"job": "j1", "force": "yes"}, "accept").field == "$.force"
    assert refusal({"job": "a/b"}, "cancel").field == "$.job"  # not one key chunk
    assert refusal({"job": "*"}, "status").field == "$.job"
    assert refusal({"limit": 0}, "list").field == "$.limit"


# -- round trip and fuzz ------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(valid_jobs)
def test_job_to_message_round_trips(message: dict) -> None:
    job = submit(message)
    again = submit(requests.job_to_message(job))
    assert type(again) is type(job)
    for a, b in zip(json.loads(json.dumps(requests.job_to_message(job))).values(), requests.job_to_message(again).values()):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-12) if isinstance(a, float) else a == b


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_give_a_job_or_a_job_error(raw: bytes) -> None:
    try:
        parse_submit(raw)
    except JobError as exc:
        assert exc.field.startswith("$") and exc.reason.isascii()


@settings(max_examples=150, deadline=None)
@given(valid_jobs, st.sampled_from(["n_poses", "poses", "target", "arc", "check", "k_p", "ref", "kind", "extra"]), json_values)
def test_a_valid_job_with_one_field_replaced_gives_a_job_or_names_a_field(message: dict, key: str, value: object) -> None:
    message = {**message, key: value}
    try:
        parse_submit(json.dumps(message).encode())
    except JobError as exc:
        assert exc.field.startswith("$") and exc.reason.isascii()


def test_tool_calibrate_converts_degrees_and_checks_its_ranges() -> None:
    job = submit({"kind": "tool-calibrate", "n_poses": 10, "max_tilt_deg": 15, "tip_position": [0.6, 0, 0.45], "seed": 2})
    assert job == requests.ToolCalibrateJob(n_poses=10, max_tilt=pytest.approx(math.radians(15)), tip_position=(0.6, 0.0, 0.45), seed=2)
    assert submit({"kind": "tool-calibrate"}) == requests.ToolCalibrateJob()
    assert parse_submit(wire.encode(requests.job_to_message(job))) == job
    assert refusal({"kind": "tool-calibrate", "n_poses": 2}).field == "$.n_poses"
    assert refusal({"kind": "tool-calibrate", "max_tilt_deg": 60}).field == "$.max_tilt_deg"
    assert refusal({"kind": "tool-calibrate", "tip_position": [0.6, 0.0]}).field == "$.tip_position"
    assert refusal({"kind": "tool-calibrate", "poses": []}).field == "$.poses"  # not a calibrate job's field
