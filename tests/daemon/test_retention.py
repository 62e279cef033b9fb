"""Retention of calibration datasets: the newest N and the last D days are kept, the current calibration's always."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from celld.daemon.retention import prune_sessions
from celld.errors import InputError

NOW = 1_800_000_000.0  # s since the epoch
DAY = 86_400.0


def make_jobs(jobs: Path, ages_days: dict[str, float]) -> None:
    """One calibrate job per entry, its dataset last written that many days before NOW, plus a result file."""
    for job, age in ages_days.items():
        d = jobs / job / "dataset"
        d.mkdir(parents=True)
        (d / "p000.depth.png").write_bytes(b"x" * 1000)
        (d / "poses.json").write_text("{}")
        os.utime(d / "poses.json", (NOW - age * DAY, NOW - age * DAY))
        (jobs / job / "plan.json").write_text("{}")


def left(jobs: Path) -> list[str]:
    return sorted(p.parent.name for p in jobs.glob("*/dataset"))


AGES = {"j1": 40.0, "j2": 30.0, "j3": 20.0, "j4": 2.0, "j5": 1.0, "j6": 0.5}


def test_the_newest_are_kept(tmp_path: Path) -> None:
    make_jobs(tmp_path, AGES)
    pruned = prune_sessions(tmp_path, 2, 0, now=NOW)
    assert left(tmp_path) == ["j5", "j6"]
    assert sorted(p.job for p in pruned) == ["j1", "j2", "j3", "j4"]
    assert all(p.reason == "not among the newest 2" and p.bytes == 1002 for p in pruned)
    # Only the dataset goes: the job's other files stay.
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(AGES)
    assert (tmp_path / "j1" / "plan.json").is_file()


def test_the_last_days_are_kept(tmp_path: Path) -> None:
    make_jobs(tmp_path, AGES)
    pruned = prune_sessions(tmp_path, 0, 25, now=NOW)
    assert left(tmp_path) == ["j3", "j4", "j5", "j6"]
    assert {p.job: p.reason for p in pruned} == {"j1": "written 40.0 days ago, over 25", "j2": "written 30.0 days ago, over 25"}


def test_either_rule_keeps_a_dataset(tmp_path: Path) -> None:
    make_jobs(tmp_path, AGES)
    prune_sessions(tmp_path, 3, 1.5, now=NOW)  # the newest 3 (j4-j6), and those under 1.5 days (j5, j6)
    assert left(tmp_path) == ["j4", "j5", "j6"]
    prune_sessions(tmp_path, 1, 1.5, now=NOW)
    assert left(tmp_path) == ["j5", "j6"]


def test_the_current_calibration_and_the_running_job_are_never_deleted(tmp_path: Path) -> None:
    make_jobs(tmp_path, AGES)
    pruned = prune_sessions(tmp_path, 1, 0, protect=("j1", "j3", None), now=NOW)
    assert left(tmp_path) == ["j1", "j3", "j6"]
    assert sorted(p.job for p in pruned) == ["j2", "j4", "j5"]


def test_no_rule_keeps_everything(tmp_path: Path) -> None:
    make_jobs(tmp_path, AGES)
    assert prune_sessions(tmp_path, 0, 0, now=NOW) == []
    assert left(tmp_path) == sorted(AGES)
    assert prune_sessions(tmp_path / "absent", 1, 1) == []


def test_a_dataset_without_poses_is_aged_by_its_directory(tmp_path: Path) -> None:
    make_jobs(tmp_path, {"old": 10.0, "new": 0.1})
    (tmp_path / "old" / "dataset" / "poses.json").unlink()  # a job killed before its first capture
    os.utime(tmp_path / "old" / "dataset", (NOW - 10 * DAY, NOW - 10 * DAY))
    (tmp_path / "weld-job").mkdir()  # a job without a dataset is not a candidate
    prune_sessions(tmp_path, 0, 5, now=NOW)
    assert left(tmp_path) == ["new"]
    assert (tmp_path / "weld-job").is_dir()


def test_a_dataset_that_cannot_be_deleted_is_skipped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    make_jobs(tmp_path, AGES)
    rmtree = shutil.rmtree

    def refuse_j2(path, *args, **kwargs):
        if Path(path).parent.name == "j2":
            raise PermissionError(13, "Permission denied", str(path))
        rmtree(path, *args, **kwargs)

    monkeypatch.setattr(shutil, "rmtree", refuse_j2)
    pruned = prune_sessions(tmp_path, 2, 0, now=NOW)
    assert sorted(p.job for p in pruned) == ["j1", "j3", "j4"]
    assert left(tmp_path) == ["j2", "j5", "j6"]


@pytest.mark.parametrize(
    ("keep_last", "keep_days", "match"), [(-1, 0, "keep_last"), (1.5, 0, "keep_last"), (1, -2, "keep_days"), (1, float("nan"), "keep_days")]
)
def test_bad_rules_are_refused(tmp_path: Path, keep_last, keep_days, match: str) -> None:
    with pytest.raises(InputError, match=match):
        prune_sessions(tmp_path, keep_last, keep_days)
