"""``kill -9`` mid-weld, the arc on, of the daemon, its camera process or its motion process; a hung daemon.

bench/safety.py kills a small stand-in that owns the motion process; this
kills the processes of ``celld sim run`` itself, tracking a seam by touch at
10 mm/s with the arc on. The cell is ``configs/sim-cell.toml`` in the ideal
world (half-resolution scans): it is calibrated once, then each trial

1. submits a weld and waits for the arc;
2. sends SIGKILL (SIGSTOP for ``hang``) to the target, noting the time;
3. reads the simulator's record of the true arm and outputs: when the arc
   output went low and when the TCP came to rest (below 0.1 mm/s);
4. goes on: after the daemon's death a new daemon is started (the motion
   process's exit line says when and why it took its daemon for gone);
   after a child's, the weld job ends with its reason (it retracts the
   tool when the robot can still move) and the daemon restarts the child. The tool then moves off the part to the scan pose.

Targets:

- ``daemon`` (a process of some 0.6 GB and 30-odd threads): the orphaned
  motion process stops the arm jerk-limited and switches the arc off
  itself: arc off within 0.1 s, at rest within 0.5 s (issue 12). A large
  process takes a while to die: the kernel frees its memory and closes its
  files before it re-parents its children and sends them the parent-death
  signal, so the motion process also reads the daemon's ``/proc/<pid>/stat``
  (celld.supervision.exiting), which shows the kill at once.
- ``tactile`` (the SRM camera process): the servo stops when the newest
  sample is older than ``motion.tactile_stale``; the arc goes off within
  0.1 s of that stop beginning.
- ``motion``: nothing of celld's can act; the robot's RTDE watchdog stops
  the program within one period (``motion.rtde_watchdog_hz``), the outputs
  low with it.
- ``hang``: the daemon stopped (SIGSTOP) rather than killed. While the arm
  moves or the arc is on, its motion process takes it for hung once its
  heartbeat is ``motion.hang_stop`` (0.25 s) old and stops as for its death:
  arc off within 0.3 s, at rest within 0.5 s of the hang (issue 23); the
  millimetres welded unsupervised meanwhile are ``welded_mm``. The bench
  then kills it, as systemd's watchdog would, and the next daemon journals
  the weld interrupted with what its motion process noted (``journal``).

``--trials N`` per target (default 10; about 45 s each after a 2-minute
calibration); ``--targets`` a subset. ``--quick``: one trial per target
after a 6-pose calibration (about 4 minutes: this benchmark cannot be quicker
than a calibration and a weld). ``--json`` prints the figures as one JSON
object on the last line. Exit code 1 when a job failed (the calibration; a
weld whose arc never came on or that did not end; the robot link not back,
or the tool not moved off the part, after a trial: the run stops there),
each failure named on stderr and in the JSON's ``failed``; a missed target
is a figure, not a failure: 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Failures, JobFailed  # noqa: E402

from celld.errors import BusError  # noqa: E402
from celld.sim.cell import run_cell, start_daemon, stop_daemon  # noqa: E402
from celld.sim.score import after_fault, orphaned_after  # noqa: E402

HOST = "127.0.0.7"
ARC = 0  # the arc's digital output in configs/sim-cell.toml
WINDOW = 1.5  # s of the simulator's truth read after each kill
TARGET_ARC_OFF_S = 0.1
TARGET_REST_S = 0.5
# A hung daemon: the arc off and the arm at rest within these of the hang, s (issue 23).
TARGET_HANG_ARC_OFF_S = 0.3
TARGET_HANG_REST_S = 0.5


def _config(workdir: Path) -> Path:
    path = workdir / "cell.toml"
    path.write_text(
        f"""
include = ["{ROOT / "configs" / "sim-cell.toml"}"]
[cell]
name = "daemon-kill"
state_dir = "{workdir / "state"}"
[robot]
host = "{HOST}"
[bus]
listen = ["tcp/{HOST}:7447"]
[sim]
preset = "ideal"
seed = 3
[sim.scanner]
resolution_scale = 0.5
"""
    )
    return path


def _after_kill(robot: Any, t_kill_ns: int, window: float = WINDOW) -> dict[str, float]:
    """The simulator's truth ``window`` s after the kill (celld.sim.score.after_fault)."""
    time.sleep(max(0.0, window - (time.monotonic_ns() - t_kill_ns) * 1e-9))
    history = robot.truth_history()
    seen = after_fault(history, t_kill_ns, ARC)
    # The torch's (TCP's) path with the arc still on after the kill: what was welded unsupervised.
    after = history[history["stamp_ns"].astype(np.int64) >= t_kill_ns]
    burning = after[(after["digital_out"].astype(np.int64) >> ARC) & 1 == 1]
    p = burning["T_base_tcp"][:, :3, 3]
    welded = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0
    return {
        "speed_at_kill_mm_s": seen.speed_at_fault * 1e3,
        "rest_s": seen.stopped_s,
        "arc_off_s": seen.arc_off_s,
        "travel_mm": seen.travel * 1e3,
        "welded_mm": welded * 1e3,
    }


TARGETS = ("daemon", "tactile", "motion", "hang")


def _weld_until_the_arc(client: Any, robot: Any, ref: str) -> str:
    with client.watch_progress() as events:
        job = client.submit({"kind": "weld", "ref": ref})["job"]
        try:
            events.wait_stage(job, "track", timeout=240)
        except BusError as exc:  # it ended (or hung) before it tracked: a failed job, not a figure
            raise JobFailed(f"weld job {job} ({ref})", str(exc)) from exc
    deadline = time.monotonic() + 60
    while not int(robot.status()["digital_out"]) & (1 << ARC):
        if time.monotonic() > deadline:
            raise JobFailed(f"weld job {job} ({ref})", "the arc never came on")
        time.sleep(0.02)
    time.sleep(0.5)
    return str(job)


def _wait_end(client: Any, job: str, timeout: float = 120.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        record = client.status(job)
        if record["state"] not in ("queued", "running"):
            return dict(record)
        time.sleep(0.2)
    raise JobFailed(f"job {job}", f"it did not end within {timeout:g} s")


def bounds(cfg: Any) -> dict[str, tuple[float, float]]:
    """Per target: (arc off, at rest) bounds from the kill, s, as issue 12 sets them for this cell's settings.

    - the daemon: arc off within 0.1 s and at rest within 0.5 s of its death;
    - the camera process: the servo stops when the newest sample is older than
      ``motion.tactile_stale``, at most a frame period after the last one; the
      arc goes off within 0.1 s of that stop beginning;
    - the motion process: only the robot can act, when its RTDE watchdog
      (``motion.rtde_watchdog_hz``) stops the program: within one period;
    - a hung daemon (SIGSTOP) mid-weld: arc off within 0.3 s, at rest within
      0.5 s of the hang (``motion.hang_stop`` is bounded so that it can be).
    """
    stop_begins = cfg.motion.tactile_stale + 1.0 / cfg.tactile.fps
    watchdog = 1.0 / cfg.motion.rtde_watchdog_hz
    return {
        "daemon": (TARGET_ARC_OFF_S, TARGET_REST_S),
        "hang": (TARGET_HANG_ARC_OFF_S, TARGET_HANG_REST_S),
        "tactile": (stop_begins + TARGET_ARC_OFF_S, stop_begins + TARGET_REST_S),
        "motion": (watchdog + 0.01, watchdog + TARGET_REST_S),
    }


def _summary(rows: list[dict[str, Any]], bound: tuple[float, float]) -> dict[str, Any]:
    fig: dict[str, Any] = {"trials": len(rows)}
    for key in ("arc_off_s", "rest_s", "travel_mm", "welded_mm", "seen_s", "reaped_s"):
        vals = [r[key] for r in rows if key in r]
        if vals:
            fig[key] = {"median": statistics.median(vals), "max": max(vals)}
    fig["why"] = {why: sum(r["why"] == why for r in rows) for why in sorted({r["why"] for r in rows})}
    fig["bounds_s"] = {"arc_off": bound[0], "rest": bound[1]}
    fig["met"] = fig["arc_off_s"]["max"] <= bound[0] and fig["rest_s"]["max"] <= bound[1]
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=10, help="trials per target")
    ap.add_argument("--targets", nargs="*", default=list(TARGETS), choices=TARGETS)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.trials < 1:
        ap.error("--trials: expected at least 1")
    trials, n_poses = (1, 6) if args.quick else (args.trials, 8)
    rows: dict[str, list[dict[str, Any]]] = {t: [] for t in args.targets}
    failures = Failures("daemon_kill")
    with tempfile.TemporaryDirectory(prefix="celld-daemon-kill-") as tmp:
        workdir = Path(tmp)
        cfg_path = _config(workdir)
        log_path = workdir / "daemon.log"
        with run_cell(cfg_path, log_path, timeout=120) as cell:
            robot, cfg = cell.robot, cell.config
            client, proc = cell.client, cell.daemon
            run_dir = Path(cfg.cell.state_dir) / "run"
            try:
                _, cal = client.submit_and_wait({"kind": "calibrate", "seed": 5, "n_poses": n_poses}, timeout=900)
                if cal["state"] != "succeeded":
                    raise JobFailed(f"calibrate job {cal['id']}", f"{cal['state']}: {cal['reason']}")
                client.accept(cal["id"])
                print(f"kill -9 mid-weld (arc on, tracking at 10 mm/s); {trials} trial(s) per target")
                print(
                    f"{'target':<8} {'trial':>5} {'arc off ms':>10} {'at rest ms':>10} {'travel mm':>9} {'seen ms':>8} {'reaped ms':>9}  why"
                )
                for target in args.targets:
                    for i in range(trials):
                        job = _weld_until_the_arc(client, robot, f"kill {target} {i}")
                        row: dict[str, Any] = {}
                        if target in ("daemon", "hang"):
                            status = Path(f"/proc/{proc.pid}/status").read_text()
                            row["rss_gb"] = int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) / 1e6  # type: ignore[union-attr]
                            row["threads"] = int(re.search(r"Threads:\s+(\d+)", status).group(1))  # type: ignore[union-attr]
                            pid = proc.pid
                        else:
                            pid = int(json.loads((run_dir / f"{target}.json").read_text())["pid"])
                        log_from = log_path.stat().st_size
                        t_kill = time.monotonic_ns()
                        os.kill(pid, signal.SIGSTOP if target == "hang" else signal.SIGKILL)
                        if target == "daemon":
                            proc.wait(10)
                            row["reaped_s"] = (time.monotonic_ns() - t_kill) * 1e-9
                        row.update(_after_kill(robot, t_kill))
                        if target in ("daemon", "hang"):
                            time.sleep(1.0)  # the motion process has logged its end
                            row["seen_s"], row["why"] = orphaned_after(log_path.read_bytes()[log_from:].decode(errors="replace"), t_kill)
                            if target == "hang":  # the hung daemon is ended for good, as systemd's watchdog would
                                proc.kill()
                                proc.wait(10)
                            client.close()
                            with open(log_path, "ab") as log:
                                daemon = start_daemon(cfg_path, log, timeout=120)
                            proc, client = daemon.process, daemon.client
                            row["journal"] = client.status(job)["reason"]  # why the next daemon says the weld ended
                        else:
                            record = _wait_end(client, job)
                            row["why"] = f"the weld {record['state']}: {record['reason'][:70]}"
                            deadline = time.monotonic() + 60
                            while client.status().get("robot_link") != "up":
                                if time.monotonic() > deadline:
                                    raise JobFailed(f"{target} trial {i + 1}", "the robot link did not come back")
                                time.sleep(0.5)
                        rows[target].append(row)
                        seen = f"{row['seen_s'] * 1e3:8.1f}" if "seen_s" in row else f"{'-':>8}"
                        reaped = f"{row['reaped_s'] * 1e3:9.1f}" if "reaped_s" in row else f"{'-':>9}"
                        travel = f"{row['travel_mm']:9.2f}" if "travel_mm" in row else f"{'-':>9}"
                        print(
                            f"{target:<8} {i + 1:>5} {row['arc_off_s'] * 1e3:>10.1f} {row['rest_s'] * 1e3:>10.1f} "
                            f"{travel} {seen} {reaped}  {row['why']}",
                            flush=True,
                        )
                        target_pose = {"space": "cartesian", "pose": list(cfg.weld.scan_pose)}
                        _, moved = client.submit_and_wait({"kind": "move", "target": target_pose}, timeout=120)
                        if moved["state"] != "succeeded":
                            raise JobFailed(f"move job {moved['id']} after {target} trial {i + 1}", f"{moved['state']}: {moved['reason']}")
            except JobFailed as exc:
                failures.add(exc.job, exc.reason)
            finally:
                client.close()
                stop_daemon(proc)
    limits = bounds(cfg)
    figures = {t: _summary(r, limits[t]) for t, r in rows.items() if r}
    for t, fig in figures.items():
        line = (
            f"{t}: arc off {fig['arc_off_s']['median'] * 1e3:.1f} / {fig['arc_off_s']['max'] * 1e3:.1f} ms, "
            f"at rest {fig['rest_s']['median'] * 1e3:.1f} / {fig['rest_s']['max'] * 1e3:.1f} ms (median / max)"
        )
        if "seen_s" in fig:
            line += f"; seen {fig['seen_s']['median'] * 1e3:.1f} / {fig['seen_s']['max'] * 1e3:.1f} ms"
        print(line)
        print(f"   {fig['why']}")
        b = fig["bounds_s"]
        print(
            f"   target: arc off within {b['arc_off']:.3f} s, at rest within {b['rest']:.3f} s of the kill: {'met' if fig['met'] else 'MISSED'}"
        )
    if args.json:
        print(json.dumps({"rows": rows, "figures": figures, "failed": failures.jobs}))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
