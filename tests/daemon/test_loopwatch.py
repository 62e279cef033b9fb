"""The loop watch tells a callback that held the loop from a loop that was ready but not run.

How worker threads that hold the GIL show depends on the machine's load; the rule that sorts them is tested
with its inputs given (classify).
"""

from __future__ import annotations

import asyncio
import threading
import time

from celld.daemon.loopwatch import LoopWatch, blocked_in, classify


async def _hold_the_loop(seconds: float) -> None:
    time.sleep(seconds)  # a callback that blocks the loop itself


async def _watched(body) -> LoopWatch:  # type: ignore[no-untyped-def]
    watch = LoopWatch(threshold=0.05)
    watch.install()
    ticker = asyncio.get_running_loop().create_task(watch.run())
    await asyncio.sleep(0.05)
    await body()
    await asyncio.sleep(0.05)
    ticker.cancel()
    await asyncio.gather(ticker, return_exceptions=True)
    return watch


def _spin_for(seconds: float) -> None:
    """Pure Python in a worker thread."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def test_a_callback_that_blocks_the_loop_is_a_busy_stall_and_is_named() -> None:
    async def body() -> None:
        # The watcher looks once, past the threshold (50 ms): the hold lasts long enough that a watcher
        # thread left unscheduled for a while on a loaded machine still finds the loop's thread asleep.
        worker = threading.Thread(target=_spin_for, args=(0.5,), name="spinner")
        worker.start()
        await asyncio.get_running_loop().create_task(_hold_the_loop(0.4), name="holder")
        await asyncio.to_thread(worker.join)

    watch = asyncio.run(_watched(body))
    report = watch.report()
    assert report["busy"] == 1 and report["unscheduled"] == 0, report
    worst = report["worst_busy"]
    assert worst["late_ms"] >= 100 and "holder" in worst["callback"] and "_hold_the_loop" in worst["callback"], worst
    assert worst["callback_ms"] >= 390 and worst["callback_cpu_ms"] < 50, worst  # it slept: no CPU
    # The watcher saw where it was: in this test's function (its sleep has no Python frame).
    assert worst["where"].startswith("test_loopwatch.py:") and "_hold_the_loop" in worst["where"], worst
    # And what the daemon's other threads were doing meanwhile: the spinning worker, not the idle ones.
    assert "spinner: test_loopwatch.py:" in worst["others"] and "_spin_for" in worst["others"], worst


def test_a_short_sleep_on_the_loop_is_no_stall() -> None:
    async def body() -> None:
        await asyncio.get_running_loop().create_task(_hold_the_loop(0.005))

    report = asyncio.run(_watched(body)).report()
    assert report["busy"] == 0 and report["worst_busy"] is None, report


def test_a_long_callback_is_busy_when_it_computed_or_blocked_and_unscheduled_when_it_waited() -> None:
    assert classify(0.05, 0.04, 0.04, True) == "unscheduled"  # nothing ran long
    assert classify(0.05, 0.2, 0.19, False) == "busy"  # computed on the loop
    assert classify(0.05, 0.2, 0.001, True) == "busy"  # slept or blocked on a file: the loop was held
    assert classify(0.05, 0.2, 0.001, False) == "unscheduled"  # waited for the GIL (or the CPU)
    assert blocked_in("230") and blocked_in("7") and not blocked_in("running") and not blocked_in("")
