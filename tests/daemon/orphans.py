"""What happens to the arm and the arc after the daemon is killed: measured on the simulator's truth."""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from celld.log import read_events
from celld.sim.score import after_fault, orphaned_after


class AfterKill(NamedTuple):
    moving_at_kill: float  # TCP speed when the daemon died, m/s
    at_rest_s: float  # from the kill until the TCP stopped for good, s (inf: never within the window)
    arc_off_s: float  # from the kill until the arc output is off, s (0: it was off already; inf: never)


def tcp_speed(robot) -> float:  # type: ignore[no-untyped-def]
    h = robot.truth_history()[-5:]
    dt = (int(h["stamp_ns"][-1]) - int(h["stamp_ns"][0])) * 1e-9
    return float(np.linalg.norm(h["T_base_tcp"][-1][:3, 3] - h["T_base_tcp"][0][:3, 3]) / dt) if dt > 0 else 0.0


def wait_moving(robot, min_speed: float = 0.005, timeout: float = 60.0) -> None:  # type: ignore[no-untyped-def]
    """Wait until the simulated arm's TCP moves faster than ``min_speed`` (m/s)."""
    deadline = time.monotonic() + timeout
    while tcp_speed(robot) < min_speed:
        if time.monotonic() > deadline:
            raise AssertionError(f"the arm did not move faster than {min_speed} m/s within {timeout} s")
        time.sleep(0.01)


def after_kill(robot, t_kill_ns: int, arc_output: int, window: float = 1.5) -> AfterKill:  # type: ignore[no-untyped-def]
    """Read the truth of the ``window`` s after the kill (within the simulator's ~2 s history)."""
    time.sleep(max(0.0, window - (time.monotonic_ns() - t_kill_ns) * 1e-9))
    seen = after_fault(robot.truth_history(), t_kill_ns, arc_output)
    return AfterKill(seen.speed_at_fault, seen.stopped_s, seen.arc_off_s)


def motion_exits(log_path) -> list[dict]:  # type: ignore[no-untyped-def]
    """The daemon log's ``motion_loop_ended`` events (why and when each motion process saw its daemon go)."""
    with open(log_path, "rb") as f:
        return list(read_events(f.read().decode(errors="replace"), "motion_loop_ended"))


def seen_after(log_path, host: str, t_kill_ns: int) -> float:  # type: ignore[no-untyped-def]
    """How long after ``t_kill_ns`` the motion process of the robot at ``host`` saw its daemon go, s (nan: not seen)."""
    with open(log_path, "rb") as f:
        return orphaned_after(f.read().decode(errors="replace"), t_kill_ns, host)[0]
