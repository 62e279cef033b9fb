"""Real-time set-up of a library's threads: the ones a connect started, raised to SCHED_FIFO, or the refusal named."""

from __future__ import annotations

import os
import threading

from celld.realtime import make_threads_fifo, thread_ids


def test_threads_started_after_a_snapshot_are_raised_and_a_gone_one_is_skipped() -> None:
    before = thread_ids()
    started = threading.Event()
    release = threading.Event()

    def work() -> None:
        started.set()
        release.wait(10)

    t = threading.Thread(target=work)
    t.start()
    started.wait(10)
    try:
        new = thread_ids() - before
        assert new == {t.native_id}
        refused = make_threads_fifo(new | {2**22 + 7}, 1)  # a thread id no process has: skipped, not refused
        if refused:  # without root, CAP_SYS_NICE or an RLIMIT_RTPRIO: the refusal names the thread
            assert f"thread {t.native_id} SCHED_FIFO 1" in refused
            assert os.sched_getscheduler(t.native_id) == os.SCHED_OTHER
        else:
            assert os.sched_getscheduler(t.native_id) == os.SCHED_FIFO
            assert os.sched_getparam(t.native_id).sched_priority == 1
        assert os.sched_getscheduler(threading.main_thread().native_id) == os.SCHED_OTHER  # the caller is left alone
    finally:
        release.set()
        t.join(10)
