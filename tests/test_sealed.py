"""Stored state checked where it is read: a sealed file that was edited, cut short, mislabelled or unsealed is refused with why."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from celld import sealed
from celld.daemon.store import CalibrationStore, current_calibration
from celld.errors import DamagedStateError, JobError


def _calibration(T: np.ndarray) -> dict:
    return {"job": "j1", "T_base_cam": T.tolist(), "range_bias_mm": 0.0, "rms_mm": 0.04}


def test_a_sealed_file_reads_back_with_its_format_job_and_checksum(tmp_path: Path) -> None:
    path = tmp_path / "c.json"
    body = _calibration(np.eye(4))
    written = sealed.write_sealed(path, body, "calibration", "j7")
    read = sealed.read_sealed(path, "calibration", "calibration")
    assert read == written
    assert read["format"] == "celld.calibration/1" and read["job"] == "j7"
    assert read["sha256"] == sealed.checksum(read) and len(read["sha256"]) == 64
    assert {k: read[k] for k in body if k != "job"} == {k: v for k, v in body.items() if k != "job"}
    assert sealed.read_sealed(tmp_path / "absent.json", "calibration", "calibration") is None


def test_a_calibration_moved_by_hand_is_refused_by_its_checksum(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, 3] = [0.6, 0.0, 1.0]
    path = tmp_path / "calibration.json"
    sealed.write_sealed(path, _calibration(T), "calibration")
    current = current_calibration(tmp_path)
    assert current.job == "j1" and np.allclose(current.placement.T_base_cam(None), T)
    # Well-formed and wrong: the scanner moved 50 mm in x by an editor.
    doc = json.loads(path.read_text())
    doc["T_base_cam"][0][3] += 0.05
    path.write_text(json.dumps(doc, indent=2))
    with pytest.raises(JobError, match=r"the stored calibration is damaged: its checksum does not match .*calibration.json"):
        current_calibration(tmp_path)
    # Only whitespace changed: the same content, still trusted.
    sealed.write_sealed(path, _calibration(T), "calibration")
    path.write_text(json.dumps(json.loads(path.read_text()), indent=None))
    assert current_calibration(tmp_path).job == "j1"


@pytest.mark.parametrize(
    ("mangle", "why"),
    [
        (lambda text: text[: len(text) // 2], "not JSON \\(cut short\\)"),
        (lambda text: "", "not JSON"),
        (lambda text: "[1, 2]", "not a JSON object but list"),
        (lambda text: text.replace('"celld.calibration/1"', '"celld.calibration/9"'), "newer than this celld reads"),
        (lambda text: text.replace('"celld.calibration/1"', '"celld.tool-calibration/1"'), "is not a calibration"),
        (lambda text: json.dumps({k: v for k, v in json.loads(text).items() if k != "sha256"}), "no format and checksum"),
        (lambda text: "\udcff", "not JSON"),
    ],
)
def test_a_damaged_calibration_is_refused_naming_what_is_wrong(tmp_path: Path, mangle, why: str) -> None:
    path = tmp_path / "calibration.json"
    sealed.write_sealed(path, _calibration(np.eye(4)), "calibration")
    path.write_bytes(mangle(path.read_text()).encode("utf-8", "surrogateescape"))
    with pytest.raises(DamagedStateError, match=why) as info:
        CalibrationStore(tmp_path).current()
    assert str(info.value).startswith("the stored calibration is damaged: ")
    assert CalibrationStore(tmp_path).damage() == str(info.value)


def test_a_file_larger_than_any_stored_state_is_refused_unread(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    with open(path, "wb") as f:
        f.truncate(sealed.MAX_BYTES + 1)
    with pytest.raises(DamagedStateError, match=f"more than the {sealed.MAX_BYTES}"):
        CalibrationStore(tmp_path).current()


def test_an_accept_seals_the_current_calibration_and_refuses_an_edited_candidate(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.add_candidate("j2", {**_calibration(np.eye(4)), "quality": {"verdict": "ok", "reasons": []}})
    current = store.accept("j2")
    assert current["job"] == "j2" and "accepted" in current and store.current() == current
    candidate = store.candidates / "j2.json"
    candidate.write_text(candidate.read_text().replace('"verdict": "ok"', '"verdict": "ok "'))
    with pytest.raises(DamagedStateError, match="the stored calibration of job j2 is damaged: its checksum"):
        store.accept("j2")


def test_status_says_the_stored_calibration_is_damaged(tmp_path: Path) -> None:
    import asyncio

    from celld.bus.requests import StatusRequest
    from tests.daemon.test_jobs import Harness

    sealed.write_sealed(tmp_path / "calibration.json", _calibration(np.eye(4)), "calibration")
    (tmp_path / "tool.json").write_text('{"job": "t1", "tip_tcp_mm": [0, 0, 200]}')  # by hand: no seal

    async def status() -> dict:
        h = Harness(tmp_path)
        try:
            return dict(await h.manager.on_status(StatusRequest()))
        finally:
            h.journal.close()

    got = asyncio.run(status())
    assert got["calibration"] == "j1" and got["state"] == "idle"
    assert got["message"].startswith("the stored tool calibration is damaged: it carries no format and checksum")
    (tmp_path / "calibration.json").write_text("{")
    got = asyncio.run(status())
    assert got["calibration"] is None and "the stored calibration is damaged: not JSON (cut short)" in got["message"]
