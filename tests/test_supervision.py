"""Supervision both ways: restart back-off, the daemon's heartbeat, a child's watch of its daemon, leftovers."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time
import uuid
from multiprocessing import resource_tracker
from pathlib import Path

import pytest

from celld.shm import SeqlockSlot
from celld.supervision import (
    HEARTBEAT_DTYPE,
    Backoff,
    BeatThread,
    ChildRecords,
    Heartbeat,
    ParentWatch,
    exit_notes,
    exiting,
    write_exit_note,
)


def test_backoff_grows_to_its_last_delay_and_a_stable_run_resets_it() -> None:
    b = Backoff(delays=(0.1, 0.5, 2.0), stable_after=10.0)
    assert [b.delay(n) for n in (1, 2, 3, 7)] == [0.1, 0.5, 2.0, 2.0]
    assert b.failures_after(3, ran_for=1.0) == 4 and b.failures_after(3, ran_for=10.0) == 0


def test_a_stale_heartbeat_means_the_daemon_hangs() -> None:
    hb = Heartbeat(f"t-hb-{uuid.uuid4().hex[:8]}")
    try:
        # This process stands in for the child: its "parent" is its real parent.
        watch = ParentWatch(os.getppid(), hb.name, timeout_ns=200_000_000, signals=False)
        now = time.monotonic_ns()
        assert watch.check(now) == ""
        assert "heartbeat is" in watch.check(now + 300_000_000) and "hangs" in watch.check(now + 300_000_000)
        hb.beat()
        assert watch.check() == ""
        # A caller that moves the robot asks for a shorter bound than the watch's own.
        now = time.monotonic_ns()
        assert watch.check(now + 100_000_000) == "" and "hangs" in watch.check(now + 100_000_000, timeout_ns=50_000_000)
        watch.close()
    finally:
        hb.close()


def test_the_beat_thread_beats_while_the_loop_runs_and_stands_still_with_it() -> None:
    hb = Heartbeat(f"t-hb-{uuid.uuid4().hex[:8]}")
    runs = [True]
    beater = BeatThread(hb, lambda: runs[0], period=0.01)
    try:
        watch = ParentWatch(os.getppid(), hb.name, timeout_ns=200_000_000, signals=False)

        def beats_within(seconds: float) -> bool:  # the beat is fresh (under 60 ms old) at some look within the time
            deadline = time.monotonic() + seconds
            while watch.check(timeout_ns=60_000_000) != "":
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.005)
            return True

        beater.start()
        assert beats_within(2.0)
        runs[0] = False  # the event loop stands still
        time.sleep(0.2)
        assert "hangs" in watch.check(timeout_ns=60_000_000)
        runs[0] = True
        assert beats_within(2.0)
        watch.close()
    finally:
        beater.stop()
        hb.close()


def test_a_childs_exit_note_is_read_once_by_the_next_daemon_and_the_reap_leaves_it(tmp_path: Path) -> None:
    write_exit_note(tmp_path / "motion.ended.json", "motion", "the daemon's heartbeat is 262 ms old (it hangs)")
    (tmp_path / "motion2.ended.json").write_text("{not json")
    assert ChildRecords(tmp_path).reap() == []  # no record of a child: the notes are not records
    notes = exit_notes(tmp_path)
    assert [(n["role"], n["reason"]) for n in notes] == [("motion", "the daemon's heartbeat is 262 ms old (it hangs)")]
    assert list(tmp_path.glob("*.ended.json")) == [] and exit_notes(tmp_path) == []


def test_another_parent_or_a_signal_means_the_daemon_is_gone() -> None:
    watch = ParentWatch(os.getppid() + 1, signals=False)
    assert f"pid {os.getppid() + 1}" in watch.check()
    watch = ParentWatch(os.getppid(), signals=False)
    watch._on_signal(signal.SIGTERM, None)
    assert watch.check() == "SIGTERM received"


def _with_fields(stat: bytes, **fields: bytes) -> bytes:
    """A /proc/<pid>/stat line with some fields (numbered as in proc(5)) replaced."""
    head, tail = stat[: stat.rindex(b")") + 1], stat[stat.rindex(b")") + 2 :].split()
    for name, value in fields.items():
        tail[int(name[1:]) - 3] = value
    return head + b" " + b" ".join(tail) + b"\n"


@pytest.mark.process
def test_the_parents_proc_entry_says_when_it_is_killed_exiting_or_a_zombie() -> None:
    # A command name with spaces and parentheses, as a process may set it.
    alive = Path("/proc/self/stat").read_bytes().replace(b"(python", b"(py (thon) x", 1)
    assert exiting(alive) == ""
    assert "SIGKILL" in exiting(_with_fields(alive, f31=b"256"))  # bit 8: signal 9 pending
    assert exiting(_with_fields(alive, f31=b"2")) == ""  # SIGINT pending is no death
    assert exiting(_with_fields(alive, f9=str(0x400000 | 0x4).encode())) == "the daemon is exiting"
    assert exiting(_with_fields(alive, f9=b"4194560")) == ""  # PF_EXITING clear
    assert exiting(_with_fields(alive, f3=b"Z")) == "the daemon has exited"
    with pytest.raises(ValueError):
        exiting(b"not a stat line")
    # A stopped process, for a caller that asks (one that moves the robot); no death for one that does not.
    assert exiting(alive, stopped=True) == "" and "SIGSTOP" in exiting(_with_fields(alive, f3=b"T"), stopped=True)
    assert "debugger" in exiting(_with_fields(alive, f3=b"t"), stopped=True) and exiting(_with_fields(alive, f3=b"S"), stopped=True) == ""
    assert exiting(_with_fields(alive, f3=b"T")) == ""

    # A real zombie (exited, not yet reaped) is seen as one, before anything is re-parented.
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        watch = ParentWatch(child.pid, signals=False)
        deadline = time.monotonic() + 10
        while watch.check() != "the daemon has exited":
            assert time.monotonic() < deadline, watch.check()
            time.sleep(0.01)
        watch.close()
    finally:
        child.wait(10)


@pytest.mark.process
def test_a_stopped_parent_is_hung_at_once_for_a_caller_that_moves_and_only_after_the_timeout_at_rest() -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        watch = ParentWatch(child.pid, signals=False)
        os.kill(child.pid, signal.SIGSTOP)
        deadline = time.monotonic() + 10
        while "SIGSTOP" not in watch.check(timeout_ns=250_000_000):
            assert time.monotonic() < deadline, watch.check(timeout_ns=250_000_000)
            time.sleep(0.01)
        # (getppid() is not the child here: a caller at rest would take it for gone on that; the
        # stopped state alone is read only for a caller that moves.)
        assert exiting(Path(f"/proc/{child.pid}/stat").read_bytes(), stopped=True) != ""
        os.kill(child.pid, signal.SIGCONT)
        watch.close()
    finally:
        child.kill()
        child.wait(10)


def _orphan(parent_ready, result, heartbeat: str) -> None:  # type: ignore[no-untyped-def]
    """A grandchild: watches its parent (which then dies) and reports how soon it saw it."""
    watch = ParentWatch(os.getppid(), heartbeat, timeout_ns=10_000_000_000)
    parent_ready.set()
    t0 = time.monotonic()
    while time.monotonic() - t0 < 5.0:
        why = watch.check()
        if why:
            result.put((why, time.monotonic()))
            return
        time.sleep(0.001)
    result.put(("", time.monotonic()))


def _middle(parent_ready, result, heartbeat: str) -> None:  # type: ignore[no-untyped-def]
    ctx = mp.get_context("spawn")
    ctx.Process(target=_orphan, args=(parent_ready, result, heartbeat)).start()
    parent_ready.wait(20)
    os._exit(0)  # dies at once, as kill -9 would leave it


@pytest.mark.process
def test_a_child_sees_its_parent_die_within_milliseconds() -> None:
    ctx = mp.get_context("spawn")
    ready, result = ctx.Event(), ctx.Queue()
    middle = ctx.Process(target=_middle, args=(ready, result, ""))
    middle.start()
    middle.join(30)
    t_dead = time.monotonic()
    why, t_seen = result.get(timeout=10)
    assert why in ("the daemon ended",) or "is gone" in why, why
    assert t_seen - t_dead < 0.1


@pytest.mark.process
def test_leftover_children_are_stopped_and_their_shared_memory_removed(tmp_path: Path) -> None:
    records = ChildRecords(tmp_path / "run")
    # A child that ignores nothing: SIGTERM ends it.
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    stubborn = subprocess.Popen(
        [sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(60)"]
    )
    name = f"t-left-{uuid.uuid4().hex[:8]}"
    slot = SeqlockSlot.create(name, HEARTBEAT_DTYPE)
    slot.close()  # left behind, not unlinked (as by a killed daemon): not this process's to clean at exit
    resource_tracker.unregister("/" + name, "shared_memory")
    try:
        time.sleep(0.3)  # let the stubborn one install its handler
        records.add("motion", child.pid, [name])
        records.add("tactile", stubborn.pid)
        # A record whose pid was reused by another process (another start time) is not touched.
        (tmp_path / "run" / "old.json").write_text(f'{{"role": "old", "pid": {os.getpid()}, "start_ticks": 1, "segments": []}}')
        done = records.reap(grace=1.0)
        assert child.wait(5) == -signal.SIGTERM and stubborn.wait(5) == -signal.SIGKILL
        assert any("stopped on SIGTERM" in d for d in done) and any("killed" in d for d in done)
        assert any(name in d for d in done)
        with pytest.raises(FileNotFoundError):
            SeqlockSlot.attach(name, HEARTBEAT_DTYPE)
        assert list((tmp_path / "run").glob("*.json")) == []
    finally:
        for p in (child, stubborn):
            if p.poll() is None:
                p.kill()
