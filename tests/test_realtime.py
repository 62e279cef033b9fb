"""Real-time set-up: the CPU a loop is pinned to, counted from the last one the process may use."""

from __future__ import annotations

import os
import threading

from celld.realtime import RealtimeOptions, make_realtime


def _pinned(cpu: int) -> tuple[int, set[int]]:
    """make_realtime in a thread of its own (affinity is per thread): what it reports and what the OS says."""
    got: dict[str, object] = {}

    def run() -> None:
        report = make_realtime(RealtimeOptions(priority=0, cpu=cpu, lock_memory=False))
        got["cpu"], got["affinity"] = report.cpu, os.sched_getaffinity(0)

    t = threading.Thread(target=run)
    t.start()
    t.join()
    return got["cpu"], got["affinity"]  # type: ignore[return-value]


def test_a_negative_cpu_counts_from_the_last_and_two_robots_get_two_cores() -> None:
    allowed = sorted(os.sched_getaffinity(0))
    assert _pinned(-1) == (allowed[-1], {allowed[-1]})
    second = allowed[-2] if len(allowed) > 1 else allowed[0]
    assert _pinned(-2) == (second, {second})
    # Further back than there are CPUs: the first one.
    assert _pinned(-len(allowed) - 3) == (allowed[0], {allowed[0]})
    assert os.sched_getaffinity(0) == set(allowed), "the test's own thread is left as it was"
