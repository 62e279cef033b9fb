"""Each job kind's result schema: a hand-made minimal document passes, a wrong one is refused at its field; the
bundle ``celld bus schema`` exports is the one the daemon's results are checked against."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from celld import sealed
from celld.bus import messages
from celld.bus.checker import validate
from celld.calib import quality, toolcal
from celld.cli import main
from celld.daemon.results import BUNDLE, CALIBRATION_SCHEMA, RESULTS
from celld.errors import JobError
from tests.weld.test_plan import FINGER

I4 = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
NONE3 = [None, None, None]
QUALITY = {
    "verdict": "ok",
    "passed": True,
    "reasons": [],
    "warnings": [],
    "pairs": [{"id": "p000", "residual_mm": None, "used": False, "outlier": False, "reason": "no flange centre"}],
    "outliers": [],
    "n_used": 0,
    "rms_mm": None,
    "sigma_mm": None,
    "sigma_source": "floor",
    "workspace_centre": [0.6, 0.0, 0.45],
    "translation_std_mm": NONE3,
    "rotation_std_deg": NONE3,
    "rotation_axes": [],
    "e_icp": {"ok": False, "reason": "no correspondences", "fitness": 0.0},
    "e_icp_tilt_deg": None,
    "e_icp_turn_deg": None,
    "range_bias_mm": None,
    "range_bias_std_mm": None,
    "range_bias_source": "",
}
REPORT = {
    "T_base_cam": I4,
    "stored": "estimate",
    "T_base_cam_estimate": I4,
    "method": "robust",
    "pairs": [],
    "residuals_mm": [],
    "rejected": [],
    "rejected_detail": [],
    "rms_mm": 0.0,
    "uncertainty": {
        "sigma_mm": None,
        "dof": 0,
        "translation_std_mm": NONE3,
        "rotation_std_deg": NONE3,
        "translation_error_mm": None,
        "rotation_error_deg": None,
    },
    "n_pairs": 0,
    "e_icp": None,
    "T_base_cam_compensated": None,
    "quality": QUALITY,
    "range_bias": {"mode": "none", "bias_mm": 0.0},
}
CALIBRATION = {
    "job": "20260101-000000-abcdef",
    "T_base_cam": I4,
    "stored": "estimate",
    "cost_mm": None,
    "pairs": 0,
    "dataset": "/var/lib/celld/jobs/j/dataset",
    "method": "robust",
    "quality": QUALITY,
    "range_bias": "none",
    "range_bias_mm": 0.0,
    "range_bias_std_mm": None,
}
CALIBRATE = {
    "dry_run": False,
    "calibration": CALIBRATION,
    "report": REPORT,
    "early_stop": False,
    "poses_captured": 0,
    "poses_planned": 6,
    "dataset": "/var/lib/celld/jobs/j/dataset",
}
PLAN = {"verification_pose": [0.6, 0.0, 0.45, 0.0, 3.14, 0.0], "poses": [], "joints": [[0.0] * 6], "refused": []}
ROBOT2_ENTRY = {
    "T_base2_cam": I4,
    "T_base1_base2": I4,
    "quality": QUALITY,
    "translation_std_mm": [0.1, 0.1, 0.1],
    "rotation_std_deg": [0.01, 0.01, 0.01],
    "from_drawing_mm": 3.0,
    "from_drawing_deg": 0.2,
    "cost_mm": None,
    "pairs": 0,
    "dataset": "/var/lib/celld/jobs/j/dataset-robot2",
    "stored": "estimate",
}
FIT = {
    "verdict": "ok",
    "passed": True,
    "reasons": [],
    "warnings": [],
    "poses": [{"id": "000", "residual_mm": 0.02, "used": True, "outlier": False, "reason": ""}],
    "outliers": [],
    "n_used": 1,
    "rms_mm": 0.02,
    "sigma_mm": 0.05,
    "sigma_source": "floor",
    "spread_deg": 20.0,
    "spread_axis_tcp": [1.0, 0.0, 0.0],
    "tip_std_mm": [0.01, 0.01, 0.02],
    "offset_base_mm": [0.0, 0.0, 0.0],
    "offset_std_mm": [0.01, 0.01, 0.01],
    "missed": [],
}
TORCH_UNSOLVED = {"verdict": "poor_data", "passed": False, "reasons": ["only 2 of 12 captures showed it"], "warnings": [], "missed": []}
TOOL = {
    "job": "20260101-000000-abcdef",
    "tip_tcp_mm": [0.8, -1.1, 200.9],
    "tip_std_mm": [0.01, 0.01, 0.02],
    "nominal_tip_tcp_mm": [0.0, 0.0, 200.0],
    "delta_mm": [0.8, -1.1, 0.9],
    "calibration_job": "20251231-000000-abcdef",
    "poses": 12,
    "quality": {**FIT, "verdict": "poor_data", "passed": False, "reasons": ["torch: only 2 of 12"], "torch": TORCH_UNSOLVED},
    "torch_measured": False,
    "torch_tcp_mm": [-9.2, -1.1, 200.9],
}
TOOL_CALIBRATE = {"dry_run": False, "tool": TOOL, "poses_planned": 12, "poses_detected": 12, "torch_detected": 2, "dataset": "toolcal.json"}
FIGURES = {
    "duration_s": 14.2,
    "tracked_mm": 140.0,
    "arc_on_s": 12.0,
    "delta_n_error_rms_mm": 0.05,
    "correction_rms_mm": None,
    "correction_max_mm": None,
    "omega_peak": 0.01,
    "loop_late_p99_ms": 0.2,
    "loop_late_max_ms": 0.9,
    "loop_cycles_late_2ms": 0,
    "loop_cycles": 7100,
    "frame_to_command_median_ms": None,
    "frame_to_command_p99_ms": None,
    "wall_offset_mm": 2.1,
    "wall_offset_used_mm": [2.0, 2.2],
    "seam_length_mm": 150.0,
}
WELD = {
    "dry_run": False,
    "figures": FIGURES,
    "paths": "/var/lib/celld/jobs/j/paths.json",
    "refined_path": [[0.6, 0.0, 0.1]],
    "torch_path": [],
    "planned_path": [[0.6, 0.0, 0.1], [0.7, 0.0, 0.1]],
    "workpiece": "v-groove",
    "calibration_job": "20251231-000000-abcdef",
    "tool_calibration_job": "",
    "torch": {"measured": False, "torch_offset_mm": 10.0, "yaw_from_config_deg": 0.0, "height_from_tip_mm": 0.0, "tip_height_mm": 4.0},
    "height_probe": {"probed": False, "why": "weld.probe_height is off"},
}
WELD_DRY = {
    "dry_run": True,
    "workpiece": "v-groove",
    "calibration_job": "j",
    "tool_calibration_job": "",
    "planned_path": [],
    "tcp_path": [[0.6, 0.0, 0.2, 0.0, 3.14, 0.0]],
    "min_clearance_mm": 12.5,
    "seam_length_mm": 150.0,
}
STORAGE = {
    "ok": True,
    "free_mb": 1000.0,
    "floor_mb": 0.0,
    "fault": "",
    "last_error": None,
    "pending_writes": 0,
    "budget_mb": 0.0,
    "used_mb": None,
    "over_budget": False,
    "pruned": 0,
    "pruned_mb": 0.0,
}
HEALTH_ROBOT = {
    "link": "running",
    "pid": 4242,
    "realtime": False,
    "cpu": -1,
    "restarts": 0,
    "last_exit": "",
    "cycles": 1000,
    "lost_records": 0,
    "period_error_p50_ms": 0.01,
    "period_error_p99_ms": 0.1,
    "period_error_p999_ms": 0.2,
    "period_error_max_ms": None,
    "late_max_ms": None,
    "late_over_1ms": 0,
    "overruns": 0,
    "tactile_torn": 0,
    "heartbeat_age_ms": 2.0,
}
CONDITION = {"ready": True, "state": "ready", "reason": "", "remedy": ""}

# Per kind: documents its schema takes, and wrong ones with the field the refusal names.
GOOD: dict[str, list[dict[str, Any]]] = {
    "calibrate": [
        CALIBRATE,
        {"dry_run": True, "plan": PLAN, "recording": "/var/lib/celld/recordings/j.rrd"},
        {"dry_run": True, "plan": PLAN, "robot2_plan": PLAN},
        {
            **CALIBRATE,
            "calibration": {**CALIBRATION, "robot2": ROBOT2_ENTRY},
            "robot2": {k: CALIBRATE[k] for k in ("report", "early_stop", "poses_captured", "poses_planned", "dataset")},
        },
        # A scanner on the arm: the transforms named in its link's frame.
        {
            **CALIBRATE,
            "calibration": {
                **{k: v for k, v in CALIBRATION.items() if k != "T_base_cam"},
                "mount": "link1",
                "dh": {"d": [0.0] * 6, "a": [0.0] * 6, "alpha": [0.0] * 6},
                "T_link1_cam": I4,
            },
            "report": {
                **{k: v for k, v in REPORT.items() if not k.startswith("T_base_cam")},
                "T_link1_cam": I4,
                "T_link1_cam_estimate": I4,
                "T_link1_cam_compensated": None,
            },
        },
    ],
    "tool-calibrate": [
        TOOL_CALIBRATE,
        {"dry_run": True, "plan": {"tip_position": [0.6, 0.0, 0.45], "poses": [], "joints": [], "refused": []}},
    ],
    "weld": [
        WELD,
        {
            **WELD,
            "height_probe": {
                "probed": True,
                "joint_width_mm": 4.1,
                "scan_width_mm": 4.0,
                "height_mm": 2.9,
                "height_correction_mm": 0.1,
                "touch_check": {
                    "across_mm": 0.12,
                    "height_mm": -0.1,
                    "error_mm": 0.156,
                    "tip_height_mm": 3.0,
                    "at_base": [0.6, 0.0, 0.05],
                    "across": [0.0, 1.0, 0.0],
                    "up": [0.0, 0.0, 1.0],
                    "bound_mm": 0.4,
                    "within_bound": True,
                    "verdict": "ok",
                },
                "finger": FINGER,
            },
            "retract_error": "link lost",
        },
        WELD_DRY,
    ],
    "move": [
        {"space": "joint", "q": [0.0] * 6, "joint_error_deg": [0.001] * 6, "tcp_pose": [0.6, 0.0, 0.45, 0.0, 3.14, 0.0]},
        {"space": "cartesian", "tcp_pose": [0.6, 0.0, 0.45, 0.0, 3.14, 0.0], "error_mm": 0.01, "error_deg": 0.001},
    ],
    "health": [
        {"problems": [], "storage": STORAGE},
        {
            "robot": {**HEALTH_ROBOT, "condition": CONDITION},
            "robot2": HEALTH_ROBOT,
            "arc_interlock": {"verified": False, "missing_seen": False, "detail": "", "note": "cannot be read"},
            "scanner": {"ok": False, "error": "timeout"},
            "tactile": {"ok": False, "error": "no tactile sensor configured"},
            "problems": ["scanner: timeout"],
            "storage": STORAGE,
            "recording": "/var/lib/celld/recordings/j.rrd",
        },
    ],
}


def _with(doc: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """A copy of ``doc`` with the member at ``path`` (dotted) set to ``value``, or removed when ``value`` is ``...``."""
    out = json.loads(json.dumps(doc))  # no member shared with another
    *parents, last = path.split(".")
    node = out
    for key in parents:
        node = node[key]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return out


BAD: list[tuple[str, dict[str, Any], str]] = [
    ("calibrate", _with(CALIBRATE, "report.quality.verdict", "fine"), "$.report.quality.verdict"),
    ("calibrate", _with(CALIBRATE, "report.quality.verdict", "too_few_poses"), "$.report.quality.verdict"),  # a tool's verdict
    ("calibrate", _with(CALIBRATE, "calibration.T_base_camera", I4), "$.calibration.T_base_camera"),
    ("calibrate", _with(CALIBRATE, "report.e_icp", {"ok": True}), "$.report.e_icp.translation_mm"),
    ("calibrate", _with(CALIBRATE, "report.range_bias", {"mode": "estimate", "bias_mm": 1.0}), "$.report.range_bias.std_mm"),
    ("calibrate", _with(CALIBRATE, "early_stop", ...), "$.early_stop"),
    ("calibrate", {"dry_run": True}, "$.plan"),
    ("calibrate", {"dry_run": "yes", "plan": PLAN}, "$.dry_run"),
    ("calibrate", {**CALIBRATE, "calibration": {**CALIBRATION, "robot2": {"T_base2_cam": I4}}}, "$.calibration.robot2.T_base1_base2"),
    ("tool-calibrate", _with(TOOL_CALIBRATE, "tool.quality.torch", ...), "$.tool.quality.torch"),
    ("tool-calibrate", _with(TOOL_CALIBRATE, "tool.quality.verdict", "too_few_pairs"), "$.tool.quality.verdict"),  # a calibration's
    ("tool-calibrate", _with(TOOL_CALIBRATE, "tool.torch_tcp_mm", ...), "$.tool.torch_tcp_mm"),
    ("weld", _with(WELD, "height_probe", {"probed": True}), "$.height_probe.joint_width_mm"),
    ("weld", _with(WELD, "figures.arc_on", 1.0), "$.figures.arc_on"),
    ("weld", _with(WELD, "torch_path", [[0.6, 0.0]]), "$.torch_path[0]"),
    ("weld", _with(WELD_DRY, "tcp_path", ...), "$.tcp_path"),
    ("move", {"space": "joint", "tcp_pose": [0.0] * 6, "error_mm": 0.1}, "$.error_mm"),
    ("move", {"tcp_pose": [0.0] * 6}, "$.space"),
    ("health", {"problems": []}, "$.storage"),
    ("health", {"problems": [], "storage": STORAGE, "robot": HEALTH_ROBOT}, "$.robot.condition"),
    (
        "health",
        {"problems": [], "storage": STORAGE, "robot": {**HEALTH_ROBOT, "condition": {**CONDITION, "state": "fine"}}},
        "$.robot.condition.state",
    ),
]


@pytest.mark.parametrize(("kind", "doc"), [(k, d) for k, docs in GOOD.items() for d in docs])
def test_a_minimal_result_passes_its_kinds_schema_and_the_result_reply(kind: str, doc: dict[str, Any]) -> None:
    validate(RESULTS[kind], doc)
    reply = {"ok": True, "job": "j1", "kind": kind, "state": "succeeded", "reason": "", "result": doc, "too_large": False, "files": []}
    messages.check_message("result-reply", reply, BUNDLE)
    messages.check_message("result-reply", {**reply, "state": "cancelled", "result": None}, BUNDLE)


@pytest.mark.parametrize(("kind", "doc", "field"), BAD)
def test_a_wrong_result_is_refused_at_its_field(kind: str, doc: dict[str, Any], field: str) -> None:
    with pytest.raises(JobError) as err:
        validate(RESULTS[kind], doc)
    assert err.value.field == field, err.value


def test_one_kinds_result_is_refused_as_another_kinds() -> None:
    reply = {"ok": True, "job": "j1", "kind": "weld", "state": "succeeded", "reason": "", "too_large": False, "files": []}
    with pytest.raises(JobError) as err:
        messages.check_message("result-reply", {**reply, "result": GOOD["move"][0]}, BUNDLE)
    assert err.value.field == "$.result.dry_run"


def test_the_verdicts_are_the_quality_gates_own() -> None:
    report = RESULTS["calibrate"]["oneOf"][1]["properties"]["report"]
    assert report["properties"]["quality"]["properties"]["verdict"]["enum"] == list(quality.VERDICTS)
    tool = RESULTS["tool-calibrate"]["oneOf"][1]["properties"]["tool"]
    assert tool["properties"]["quality"]["properties"]["verdict"]["enum"] == list(toolcal.VERDICTS)
    assert tool["properties"]["quality"]["properties"]["torch"]["properties"]["verdict"]["enum"] == list(toolcal.VERDICTS)


def test_the_current_calibrations_are_the_candidates_accepted() -> None:
    # As the store keeps them: sealed (celld.sealed), and so sent.
    accepted = sealed.seal({**CALIBRATION, "robot2": ROBOT2_ENTRY, "accepted": "2026-01-01T00:00:00Z", "forced": True}, "calibration")
    messages.check_message("accept-reply", {"ok": True, "job": "j1", "kind": "calibrate", "calibration": accepted}, BUNDLE)
    messages.check_message("calibration-reply", {"ok": True, "calibration": accepted, "tool": None}, BUNDLE)
    tool = sealed.seal({**TOOL, "accepted": "2026-01-01T00:00:00Z"}, "tool-calibration")
    messages.check_message("accept-reply", {"ok": True, "job": "j2", "kind": "tool-calibrate", "tool": tool}, BUNDLE)
    messages.check_message("calibration-reply", {"ok": True, "calibration": None, "tool": tool}, BUNDLE)
    for reply, field in (
        ({"ok": True, "job": "j1", "kind": "calibrate", "calibration": CALIBRATION}, "$.calibration.accepted"),
        ({"ok": True, "job": "j1", "kind": "calibrate", "tool": tool}, "$.tool"),
        ({"ok": True, "job": "j2", "kind": "tool-calibrate", "tool": _with(tool, "quality.verdict", "fine")}, "$.tool.quality.verdict"),
    ):
        with pytest.raises(JobError) as err:
            messages.check_message("accept-reply", reply, BUNDLE)
        assert err.value.field == field
    assert set(CALIBRATION_SCHEMA["properties"]) >= set(accepted) - {"accepted", "forced", "format", "sha256"}


def test_celld_bus_schema_exports_the_bundle(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bus", "schema", "--out", str(tmp_path)]) == 0
    written = {Path(line).name for line in capsys.readouterr().out.split()}
    assert written == {f"{name}.schema.json" for name in BUNDLE} | {"asyncapi.json"}
    for name, schema in BUNDLE.items():
        assert json.loads((tmp_path / f"{name}.schema.json").read_text()) == schema
    submit = json.loads((tmp_path / "submit.schema.json").read_text())
    assert [b["properties"]["kind"]["const"] for b in submit["oneOf"]] == [
        "calibrate",
        "weld",
        "move",
        "health",
        "tool-calibrate",
        "verify",
    ]
    doc = json.loads((tmp_path / "asyncapi.json").read_text())
    assert doc["components"]["schemas"] == {f"result-{k}": {"$ref": f"result-{k}.schema.json"} for k in messages.JOB_KINDS}


@pytest.mark.parametrize("name", sorted(BUNDLE))
def test_the_bundle_is_valid_json_schema(name: str) -> None:
    jsonschema = pytest.importorskip("jsonschema", reason="the reference validator is only a test aid")
    jsonschema.Draft202012Validator.check_schema(BUNDLE[name])


@pytest.mark.parametrize(("kind", "doc"), [(k, d) for k, docs in GOOD.items() for d in docs])
def test_the_reference_validator_agrees(kind: str, doc: dict[str, Any]) -> None:
    jsonschema = pytest.importorskip("jsonschema", reason="the reference validator is only a test aid")
    assert jsonschema.Draft202012Validator(BUNDLE[f"result-{kind}"]).is_valid(doc)
    bad = [d for k, d, _ in BAD if k == kind]
    assert not any(jsonschema.Draft202012Validator(BUNDLE[f"result-{kind}"]).is_valid(d) for d in bad)
