"""The job journal: transitions, recovery after a crash, integrity, and kill -9 of a writer."""

from __future__ import annotations

import hashlib
import signal
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from celld import fsutil
from celld.errors import JournalDamagedError, JournalError
from celld.journal import INTERRUPTED_RUNNING, Journal, new_job_id


@pytest.fixture
def journal(tmp_path: Path):
    with Journal(tmp_path / "state" / "jobs.sqlite3") as j:
        yield j


def test_a_job_goes_queued_running_succeeded_with_stamps(journal: Journal) -> None:
    r = journal.create("calibrate", {"kind": "calibrate", "n_poses": 12}, ref="order-7")
    assert (r.state, r.started, r.ended, r.ref) == ("queued", None, None, "order-7")
    assert r.params == {"kind": "calibrate", "n_poses": 12}
    r = journal.start(r.id)
    assert r.state == "running" and r.started is not None
    r = journal.finish(r.id, "succeeded", result="/var/lib/celld/results/x.json")
    assert (r.state, r.result) == ("succeeded", "/var/lib/celld/results/x.json") and r.ended >= r.started
    assert r.terminal and journal.active() == []


def test_a_job_can_be_created_running(journal: Journal) -> None:
    r = journal.create("move", {"kind": "move"}, start=True)
    assert r.state == "running" and r.started == r.created
    assert journal.finish(r.id, "succeeded").state == "succeeded"


def test_illegal_transitions_are_refused(journal: Journal) -> None:
    r = journal.create("weld", {"kind": "weld"})
    with pytest.raises(JournalError, match="terminal state"):
        journal.finish(r.id, "running")
    journal.finish(r.id, "cancelled", "operator")
    with pytest.raises(JournalError, match="is cancelled; it cannot become running"):
        journal.start(r.id)
    with pytest.raises(JournalError, match="no job"):
        journal.start("nope")
    with pytest.raises(JournalError, match="not JSON"):
        journal.create("move", {"x": float("nan")})


def test_list_is_newest_first_and_filters(journal: Journal) -> None:
    ids = [journal.create(k, {"kind": k}).id for k in ("health", "weld", "weld", "move")]
    journal.start(ids[1])
    journal.finish(ids[1], "failed", "seam not found")
    assert [r.id for r in journal.jobs()] == ids[::-1]
    assert [r.id for r in journal.jobs(kind="weld")] == [ids[2], ids[1]]
    assert [r.id for r in journal.jobs(state="failed")] == [ids[1]]
    assert [r.id for r in journal.jobs(limit=2)] == ids[:1:-1]
    assert [r.id for r in journal.active()] == [ids[0], ids[2], ids[3]]
    message = journal.get(ids[1]).to_message()
    assert message["reason"] == "seam not found" and message["params"] == {"kind": "weld"}


def test_reopening_marks_running_and_queued_jobs_interrupted(tmp_path: Path) -> None:
    path = tmp_path / "jobs.sqlite3"
    with Journal(path) as j:
        done = j.create("health", {})
        j.start(done.id)
        j.finish(done.id, "succeeded")
        running = j.start(j.create("weld", {}).id)
        queued = j.create("move", {})
    with Journal(path) as j:
        assert [r.id for r in j.recovered] == [running.id, queued.id]
        assert j.get(running.id).state == "interrupted" and "while the job was running" in j.get(running.id).reason
        assert j.get(queued.id).state == "interrupted" and "before the job started" in j.get(queued.id).reason
        assert j.get(done.id).state == "succeeded"
        assert j.check() == []
    with Journal(path) as j:
        assert j.recovered == ()
        # What the previous daemon's children saw end it is added to the reason; only an interrupted job's.
        why = "motion process: the daemon's heartbeat is 262 ms old (it hangs)"
        assert j.explain_interruption(running.id, why).reason == f"{INTERRUPTED_RUNNING}: {why}"
        with pytest.raises(JournalError, match="interrupted while running"):
            j.explain_interruption(done.id, why)
        with pytest.raises(JournalError, match="interrupted while running"):
            j.explain_interruption(queued.id, why)  # it never ran: nothing of the children's to say
        # A note (its recording finalised) goes after the reason, and stays after an explanation.
        assert j.note(queued.id, "its recording was cut short").reason.endswith("before the job started; its recording was cut short")
        assert j.note(done.id, "x").reason == "x"
        with pytest.raises(JournalError, match="no ended job"):
            j.note(j.create("move", {}).id, "x")


def test_one_process_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / "jobs.sqlite3"
    with Journal(path):
        with pytest.raises(JournalError, match="held by another process"):
            Journal(path)
    Journal(path).close()


def test_wal_mode_and_a_damaged_file(tmp_path: Path) -> None:
    path = tmp_path / "jobs.sqlite3"
    Journal(path).close()
    assert sqlite3.connect(path).execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    bad = tmp_path / "bad.sqlite3"
    bad.write_bytes(b"this is not a database" * 100)
    with pytest.raises(
        JournalDamagedError, match="bad.sqlite3 is damaged: file is not a database; stop celld and run `celld journal set-aside`"
    ):
        Journal(bad)


def test_check_reports_broken_promises(journal: Journal) -> None:
    a = journal.start(journal.create("weld", {}).id)
    b = journal.create("weld", {})
    # A second running job can only come from outside the journal's API.
    journal._db.execute("UPDATE jobs SET state = 'running', started = ? WHERE id = ?", (a.started, b.id))
    assert journal.check() == ["2 jobs are running; at most one may be"]


def test_job_ids_are_key_chunks_and_sort_by_time() -> None:
    ids = [new_job_id() for _ in range(50)]
    assert len(set(ids)) == 50
    assert all(len(i) == 22 and i.replace("-", "").isalnum() for i in ids)


# -- kill -9 ----------------------------------------------------------------------------

_WRITER = textwrap.dedent(
    """
    import sys, time
    from celld.journal import Journal
    from celld import fsutil
    path, result, mode = sys.argv[1:4]
    j = Journal(path)
    job = j.start(j.create("calibrate", {"kind": "calibrate"}).id)
    with fsutil.atomic_open(result) as f:
        f.write(b"a" * 1_000_000)
        if mode == "mid-write":
            print(job.id, flush=True)
            time.sleep(60)
        f.write(b"b" * 1_000_000)
    print(job.id, flush=True)
    time.sleep(60)
    """
)


@pytest.mark.parametrize("mode", ["mid-write", "after-write"])
@pytest.mark.process
def test_kill_9_during_a_job_leaves_it_interrupted_and_no_half_file(tmp_path: Path, mode: str) -> None:
    path, result = tmp_path / "jobs.sqlite3", tmp_path / "result.bin"
    child = subprocess.Popen([sys.executable, "-c", _WRITER, str(path), str(result), mode], stdout=subprocess.PIPE, text=True)
    try:
        job_id = child.stdout.readline().strip()
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(10)
    assert job_id and child.returncode == -signal.SIGKILL
    with Journal(path) as j:
        assert [r.id for r in j.recovered] == [job_id]
        assert j.get(job_id).state == "interrupted"
        assert j.check() == []
    if mode == "mid-write":
        assert not result.exists()
        assert len(fsutil.remove_stale_temporaries(tmp_path)) == 1
    else:
        assert result.read_bytes() == b"a" * 1_000_000 + b"b" * 1_000_000
        assert fsutil.remove_stale_temporaries(tmp_path) == []


_CHURN = textwrap.dedent(
    """
    import hashlib, sys
    from celld.journal import Journal
    from celld import fsutil
    path, results = sys.argv[1:3]
    j = Journal(path)
    while True:
        job = j.start(j.create("weld", {"kind": "weld"}).id)
        data = job.id.encode() * 20_000
        out = fsutil.write_bytes(f"{results}/{job.id}.bin", data)
        j.finish(job.id, "succeeded", result=hashlib.sha256(data).hexdigest() + " " + str(out))
    """
)


@pytest.mark.process
def test_kill_9_at_random_moments_never_damages_journal_or_results(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    path, results = tmp_path / "jobs.sqlite3", tmp_path / "results"
    results.mkdir()
    finished = 0
    for delay in rng.uniform(0.4, 0.9, size=4):
        child = subprocess.Popen([sys.executable, "-c", _CHURN, str(path), str(results)])
        try:
            child.wait(delay)
        except subprocess.TimeoutExpired:
            pass
        child.send_signal(signal.SIGKILL)
        child.wait(10)
        with Journal(path) as j:
            assert j.check() == []
            assert len(j.recovered) <= 1 and all(r.state == "interrupted" for r in j.recovered)
            for r in j.jobs(limit=10_000, state="succeeded"):
                digest, out = r.result.split(" ", 1)
                assert hashlib.sha256(Path(out).read_bytes()).hexdigest() == digest
            finished = len(j.jobs(limit=10_000, state="succeeded"))
        fsutil.remove_stale_temporaries(results)
        for p in results.iterdir():  # every result under its final name is whole
            assert p.suffix == ".bin" and p.read_bytes() == p.stem.encode() * 20_000
    assert finished > 0


def test_a_layout_1_journal_gains_owner_and_request_id(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite3"
    db = sqlite3.connect(path)
    db.executescript(
        """
        PRAGMA journal_mode = WAL;
        CREATE TABLE jobs (seq INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT NOT NULL UNIQUE, kind TEXT NOT NULL,
            params TEXT NOT NULL, ref TEXT NOT NULL DEFAULT '', state TEXT NOT NULL, reason TEXT NOT NULL DEFAULT '',
            created TEXT NOT NULL, started TEXT, ended TEXT, result TEXT);
        INSERT INTO jobs (id, kind, params, state, created, ended) VALUES ('20250101-000000-aaaaaa', 'health', '{}', 'succeeded', 'x', 'y');
        PRAGMA user_version = 1;
        """
    )
    db.close()
    with Journal(path) as j:
        old = j.get("20250101-000000-aaaaaa")
        assert old is not None and (old.owner, old.request_id) == ("", None)
        new = j.create("health", {"kind": "health"}, owner="olga", request_id="r-1")
        assert j.find_request("olga", "r-1") == new and j.find_request("oscar", "r-1") is None
        assert j.check() == []


def test_a_request_id_names_one_job_per_owner(journal: Journal) -> None:
    a = journal.create("health", {"kind": "health"}, owner="olga", request_id="step-1")
    journal.create("health", {"kind": "health"}, owner="oscar", request_id="step-1")
    journal.create("health", {"kind": "health"})  # no request id: any number of these
    journal.create("health", {"kind": "health"})
    with pytest.raises(JournalError, match="names a job already"):
        journal.create("health", {"kind": "health"}, owner="olga", request_id="step-1")
    assert journal.find_request("olga", "step-1") == a


def test_a_write_the_disk_cannot_take_is_a_storage_error_and_the_journal_stays_usable(journal: Journal) -> None:
    from celld.errors import JournalWriteError, StorageError

    job = journal.create("health", {"kind": "health"}).id
    real = journal._db

    class Full:
        def execute(self, sql: str, *args):
            if sql == "COMMIT":
                exc = sqlite3.OperationalError("database or disk is full")
                exc.sqlite_errorname = "SQLITE_FULL"  # type: ignore[attr-defined]
                raise exc
            return real.execute(sql, *args)

        def __getattr__(self, name: str):
            return getattr(real, name)

    journal._db = Full()  # type: ignore[assignment]
    with pytest.raises(JournalWriteError) as err:
        journal.start(job)
    assert isinstance(err.value, StorageError) and err.value.what == "journal"
    assert "database or disk is full" in str(err.value) and "SQLITE_FULL" in str(err.value)
    journal._db = real
    assert journal.get(job).state == "queued", "the failed change was rolled back"
    assert journal.start(job).state == "running"
    assert journal.set_result(job, "/x/result.json").result == "/x/result.json"


def test_a_record_without_details_keeps_only_what_a_viewer_may_see(journal: Journal) -> None:
    r = journal.create("weld", {"kind": "weld", "ref": "order-1"}, ref="order-1", owner="olga", request_id="q")
    full, redacted = r.to_message(), r.to_message(details=False)
    assert full["params"] == {"kind": "weld", "ref": "order-1"} and full["owner"] == "olga" and full["request_id"] == "q"
    assert redacted["redacted"] is True and not {"params", "ref", "owner", "request_id", "result"} & set(redacted)
    assert {k: full[k] for k in redacted if k != "redacted"} == {k: v for k, v in redacted.items() if k != "redacted"}


# A page of garbage in a journal of 300 jobs: page 3 is an index SQLite reads only in the integrity check,
# page 20 one of the table's the recovery at open reads (both found so for every draw of job ids).
DAMAGED_PAGE = {"found by the check": 3, "found at open": 20}


def damaged_journal(path: Path, page: int) -> None:
    """A journal of 300 jobs with one 4 KiB page of garbage."""
    with Journal(path) as j:
        for _ in range(300):
            j.create("health", {"kind": "health", "pad": "x" * 200})
    with open(path, "r+b") as f:
        f.seek(page * 4096)
        f.write(np.random.default_rng(page).bytes(4096))


@pytest.mark.parametrize("where", DAMAGED_PAGE)
def test_a_damaged_page_refuses_every_call_with_the_way_out(tmp_path: Path, where: str) -> None:
    path = tmp_path / "journal.db"
    damaged_journal(path, DAMAGED_PAGE[where])
    if where == "found at open":
        with pytest.raises(JournalDamagedError, match="database disk image is malformed"):
            Journal(path)
    with Journal(path, keep_damaged=True) as j:  # as the daemon opens it: damaged, held, every call refused
        problems = j.check()
        assert problems and (j.damage != "") == (where == "found at open")
        j.mark_damaged(problems[0])
        for call in (lambda: j.jobs(), lambda: j.create("health", {}), lambda: j.get("x")):
            with pytest.raises(JournalDamagedError, match=r"journal.db is damaged: .*`celld journal set-aside`"):
                call()
        with pytest.raises(JournalError, match="held by another process"):
            Journal(path)


def test_celld_journal_set_aside_keeps_the_damaged_one_and_starts_anew(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from celld.cli import main

    state = tmp_path / "state"
    config = tmp_path / "cell.toml"
    config.write_text(f'[cell]\nstate_dir = "{state}"\n[robot]\nhost = "127.0.0.9"\n')
    damaged_journal(state / "journal.db", DAMAGED_PAGE["found at open"])
    with Journal(state / "journal.db", keep_damaged=True):  # a daemon runs on it: refused, nothing moved
        assert main(["journal", "set-aside", "--config", str(config)]) == 2
        assert "held by another process" in capsys.readouterr().err
    assert main(["journal", "check", "--config", str(config)]) == 1
    assert "damaged" in capsys.readouterr().out
    assert main(["journal", "set-aside", "--config", str(config)]) == 0
    aside = list(state.glob("journal-set-aside-*.db"))
    assert len(aside) == 1
    with pytest.raises(JournalDamagedError):  # the damaged one kept beside, not repaired or emptied
        Journal(aside[0]).close()
    with Journal(state / "journal.db") as fresh:
        assert fresh.check() == [] and fresh.jobs() == []
    assert main(["journal", "check", "--config", str(config)]) == 0
    # An intact journal is not set aside unless asked.
    assert main(["journal", "set-aside", "--config", str(config)]) == 1
    assert len(list(state.glob("journal-set-aside-*.db"))) == 1
