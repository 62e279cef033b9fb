"""The state directory's format version (refused when newer, migrated when older) and its backup."""

from __future__ import annotations

import json
import sqlite3
import tarfile
from pathlib import Path

import pytest

from celld.daemon import statedir
from celld.daemon.statedir import MARKER, STATE_FORMAT, open_state, read_format, write_backup
from celld.errors import DamagedStateError, StateFormatError
from celld.journal import Journal


def test_a_new_cell_is_marked_with_this_releases_format(tmp_path: Path) -> None:
    assert open_state(tmp_path, fresh=True) == STATE_FORMAT
    assert json.loads((tmp_path / MARKER).read_text())["format"] == STATE_FORMAT
    assert open_state(tmp_path, fresh=False) == STATE_FORMAT, "a marked directory opens again as it is"


def test_state_from_before_the_marker_is_format_1(tmp_path: Path) -> None:
    Journal(tmp_path / "journal.db").close()
    assert open_state(tmp_path, fresh=False) == 1
    assert read_format(tmp_path) == 1


def test_a_newer_state_directory_is_refused_and_left_as_it_is(tmp_path: Path) -> None:
    (tmp_path / MARKER).write_text(json.dumps({"format": STATE_FORMAT + 1}))
    with pytest.raises(StateFormatError, match=rf"format {STATE_FORMAT + 1}, newer than celld .* reads \({STATE_FORMAT}\)"):
        open_state(tmp_path, fresh=False)
    assert read_format(tmp_path) == STATE_FORMAT + 1


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("{not json", "not JSON"),
        ('{"format": "2"}', "positive integer"),
        ('{"format": true}', "positive integer"),
        ('{"format": 0}', "positive integer"),
        ("[1]", "positive integer"),
        (" " * 5000, "larger than"),
    ],
)
def test_a_marker_that_is_not_one_is_damaged_state_naming_the_file(tmp_path: Path, text: str, why: str) -> None:
    (tmp_path / MARKER).write_text(text)
    with pytest.raises(DamagedStateError, match=why) as info:
        open_state(tmp_path, fresh=False)
    assert info.value.path == str(tmp_path / MARKER)


def test_an_older_directory_is_migrated_step_by_step_and_an_interrupted_migration_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(statedir, "STATE_FORMAT", 3)
    (tmp_path / MARKER).write_text(json.dumps({"format": 1}))
    ran: list[int] = []

    def step(n: int, fail: bool = False):  # type: ignore[no-untyped-def]
        def run(state: Path) -> None:
            if fail:
                raise OSError(f"step {n} cut short")
            ran.append(n)
            (state / f"migrated-{n}").write_text("")

        return run

    with pytest.raises(OSError, match="step 2 cut short"):
        open_state(tmp_path, fresh=False, migrations={1: step(1), 2: step(2, fail=True)})
    assert read_format(tmp_path) == 2 and ran == [1], "the marker says how far it came"
    assert open_state(tmp_path, fresh=False, migrations={1: step(1), 2: step(2)}) == 2
    assert ran == [1, 2] and read_format(tmp_path) == 3
    (tmp_path / MARKER).write_text(json.dumps({"format": 1}))
    with pytest.raises(StateFormatError, match="no migration from it"):
        open_state(tmp_path, fresh=False, migrations={})


def _state(tmp_path: Path) -> tuple[Path, str]:
    state = tmp_path / "state"
    for name, text in {
        "calibration.json": '{"job": "c1"}',
        "tool.json": "{}",
        "finger.json": "{}",
        "tactile/rest.json": "{}",
        "calibrations/c1.json": "{}",
        "tool-calibrations/t1.json": "{}",
        "results/c1.json": '{"ok": true}',
        "jobs/c1/dataset.json": "{}",
        "recordings/c1.rrd": "rrd",
    }.items():
        (state / name).parent.mkdir(parents=True, exist_ok=True)
        (state / name).write_text(text)
    open_state(state, fresh=True)
    with Journal(state / "journal.db") as journal:
        job = journal.create("calibrate", {"kind": "calibrate"}).id
        # The backup while the journal is open, as with a running daemon.
        write_backup(state, tmp_path / "open.tar.gz")
    return state, job


def test_a_backup_holds_the_state_and_a_readable_journal_but_no_recordings(tmp_path: Path) -> None:
    state, job = _state(tmp_path)
    done = write_backup(state, tmp_path / "out" / "b.tar.gz")
    assert done.journal and done.path.exists() and done.bytes == done.path.stat().st_size
    with tarfile.open(done.path) as tar:
        names = set(tar.getnames())
        assert names == {
            MARKER,
            "calibration.json",
            "tool.json",
            "finger.json",
            "tactile/rest.json",
            "calibrations/c1.json",
            "tool-calibrations/t1.json",
            "results/c1.json",
            "journal.db",
        }
        assert done.files == len(names)
        tar.extractall(tmp_path / "restored", filter="data")
    with sqlite3.connect(tmp_path / "restored" / "journal.db") as db:
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    with Journal(tmp_path / "restored" / "journal.db") as restored:
        assert restored.get(job) is not None
    assert open_state(tmp_path / "restored", fresh=False) == STATE_FORMAT
    with tarfile.open(tmp_path / "open.tar.gz") as tar:
        assert "journal.db" in tar.getnames()
    with_data = write_backup(state, tmp_path / "d.tar.gz", datasets=True)
    with tarfile.open(with_data.path) as tar:
        assert "jobs/c1/dataset.json" in tar.getnames() and "recordings/c1.rrd" not in tar.getnames()


def test_a_backup_of_what_is_no_state_directory_is_refused_and_writes_nothing(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(StateFormatError, match="not a cell's state directory"):
        write_backup(tmp_path / "empty", tmp_path / "b.tar.gz")
    assert not (tmp_path / "b.tar.gz").exists()


def test_celld_backup_writes_the_cells_state_and_says_where(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from celld.cli import main

    state, _ = _state(tmp_path)
    cfg = tmp_path / "cell.toml"
    cfg.write_text(f'[cell]\nname = "c"\nstate_dir = "{state}"\n')
    out = tmp_path / "cli.tar.gz"
    assert main(["backup", "--config", str(cfg), "--out", str(out), "--json"]) == 0
    reply = json.loads(capsys.readouterr().out)
    assert reply["path"] == str(out) and reply["journal"] and reply["files"] == 9 and out.exists()
