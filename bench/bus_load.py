"""Bus load: submit round trip on loopback, and 1000 status queries per second for 30 s.

Figures (each against its target, written to bench/out/bus_load/):

1. ``submit_rtt_ms``: round trip of ``submit`` from the client API (local
   validation, zenoh query, the cell's validation, its journal commits,
   reply), sequential, on loopback. The issue sets no number: reported as
   p50 / p99 / max.
2. ``status_rtt_ms``: the same for ``status``, sequential (the baseline of 3).
2b. ``result_rtt_ms``: the same for ``result/<job>`` (the MES fetching a
   finished job's result over the bus: the journal lookup, the result file
   read and sent), sequential, for a finished health job.
3. ``status_load``: open-loop ``status`` queries at 1000 Hz for 30 s (``--quick``:
   5 s) while a weld job runs and the cell publishes its progress and state.
   Target (issue): the rate is sustained and every query is answered;
   achieved rate >= 990 Hz, no query lost or refused. The latency
   distribution under load is reported (p50 / p99 / p99.9 / max).

Against what:

- by default a dummy cell (``tests/standin.py``: the real bus server,
  journal and queueing, jobs that only wait) is started in a child process on
  127.0.0.5, fed made-up robot and tactile samples at 100 Hz (published at
  the bus's 20 Hz), and given a 'weld' that lasts the whole load phase;
- with ``--sim-cell`` the real daemon on the simulated cell
  (``configs/sim-cell.toml`` on 127.0.0.6, :func:`celld.sim.cell.run_cell`):
  it is calibrated (6 half-resolution poses, accepted), then a real weld
  runs (V_const slowed so the track outlasts the load phase) and the load
  phase starts once the weld tracks. The weld's own result then says how
  late the motion loop woke while it ran: target (issue) no cycle more
  than 2 ms late (``motion_loop``);
- with ``--config FILE`` (``--cell NAME``) a running cell instead. Then
  nothing is submitted unless ``--submits N`` is given (a real cell moves a
  robot for a job); start the weld on the cell yourself for figure 3.

``--quick`` finishes in well under a minute; ``--json`` prints one JSON
object of the figures as the last line of stdout. Exit code 1 when a job
failed (a submitted health job, the calibration, or the weld: the dummy
cell's ends failed before the load phase is over, the simulated cell's does
not succeed), each named on stderr and in the JSON's ``failed``; 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
from _common import Failures, pyplot

from celld import config
from celld.bus.client import CellClient
from celld.bus.session import open_client

OUT = Path(__file__).resolve().parent / "out" / "bus_load"
# The dummy cell's address: loopback, clear of the tests' 127.0.x.y (x >= 0, y >= 12) and the demo's .2.
HOST = "127.0.0.5"
# Target of the load phase, queries per second, and the accepted shortfall.
LOAD_HZ = 1000.0
MIN_RATE_HZ = 990.0
# Samples per second the dummy cell offers to its (decimating) state publications.
STATE_HZ = 100.0


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _percentiles(ms: np.ndarray) -> dict[str, float]:
    if ms.size == 0:
        return {"n": 0}
    return {
        "n": int(ms.size),
        "p50": round(float(np.percentile(ms, 50)), 3),
        "p99": round(float(np.percentile(ms, 99)), 3),
        "p999": round(float(np.percentile(ms, 99.9)), 3),
        "max": round(float(ms.max()), 3),
    }


# -- the cell under test -------------------------------------------------------------


class DummyCellProcess:
    """A dummy cell in a child process, on its own port."""

    def __init__(self, workdir: Path, job_duration: float, weld_duration: float) -> None:
        port = _free_port(HOST)
        self.config_path = workdir / "cell.toml"
        self.config_path.write_text(
            f'[cell]\nname = "bench-cell"\nstate_dir = "{workdir / "state"}"\n\n'
            f'[bus]\nmode = "peer"\nlisten = ["tcp/{HOST}:{port}"]\nstate_rate_hz = 20.0\n'
        )
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "tests.standin",
                "--config",
                str(self.config_path),
                "--state-dir",
                str(workdir / "state"),
                "--job-duration",
                str(job_duration),
                "--weld-duration",
                str(weld_duration),
                "--progress-hz",
                "10",
                "--state-hz",
                str(STATE_HZ),
                "--log-level",
                "warning",
                # The submit phase measures round trips: jobs that end at once may
                # still fall behind sequential submits on a loaded machine.
                "--max-queue",
                "1000",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            cwd=ROOT,  # the stand-in cell is tests.standin, in the repository
        )
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        if not line.startswith("ready"):
            self.proc.kill()
            raise RuntimeError(f"the dummy cell did not start: {line!r}")

    def cpu_seconds(self) -> float:
        with open(f"/proc/{self.proc.pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


# -- measurements -------------------------------------------------------------------


def sequential_rtt(client: CellClient, n: int, call: Any) -> np.ndarray:
    """Round trips of ``n`` sequential calls, ms."""
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter_ns()
        call()
        out[i] = (time.perf_counter_ns() - t0) * 1e-6
    return out


def status_load(client: CellClient, rate_hz: float, duration: float) -> dict[str, Any]:
    """Open-loop status queries at ``rate_hz`` for ``duration`` s; replies recorded by callbacks."""
    n = int(rate_hz * duration)
    sent_ns = np.zeros(n, dtype=np.int64)
    got_ns = np.zeros(n, dtype=np.int64)
    ok = np.zeros(n, dtype=bool)
    key = client.key("status")
    lock = threading.Lock()

    def on_reply(i: int):
        def callback(reply: Any) -> None:
            t = time.perf_counter_ns()
            good = reply.ok is not None and json.loads(reply.ok.payload.to_bytes()).get("ok") is True
            with lock:
                if got_ns[i] == 0:
                    got_ns[i] = t
                    ok[i] = good

        return callback

    period_ns = int(1e9 / rate_hz)
    start = time.perf_counter_ns()
    for i in range(n):
        due = start + i * period_ns
        while True:  # sleep to ~0.3 ms before the slot, then spin
            left = due - time.perf_counter_ns()
            if left <= 0:
                break
            if left > 300_000:
                time.sleep((left - 300_000) * 1e-9)
        sent_ns[i] = time.perf_counter_ns()
        client.session.get(key, on_reply(i), timeout=client.timeout)
    send_end = time.perf_counter_ns()
    deadline = time.monotonic() + client.timeout + 1.0
    while time.monotonic() < deadline:
        with lock:
            if np.count_nonzero(got_ns) == n:
                break
        time.sleep(0.01)
    answered = got_ns > 0
    latency_ms = (got_ns[answered] - sent_ns[answered]) * 1e-6
    return {
        "target_hz": rate_hz,
        "duration_s": round((send_end - start) * 1e-9, 3),
        "achieved_hz": round(n / ((send_end - start) * 1e-9), 1),
        "sent": n,
        "answered": int(answered.sum()),
        "refused": int((answered & ~ok).sum()),
        "lost": int((~answered).sum()),
        "latency_ms": _percentiles(latency_ms),
        "_t_s": (sent_ns[answered] - start) * 1e-9,
        "_latency_ms": latency_ms,
    }


# -- report -------------------------------------------------------------------------


def result_rtt(client: CellClient, job: str, n: int) -> tuple[np.ndarray, int]:
    """Round trips of ``n`` sequential result queries of the finished ``job``, ms; and the reply's size, bytes."""
    deadline = time.monotonic() + 30.0
    while client.status(job)["state"] in ("queued", "running"):
        if time.monotonic() > deadline:
            raise RuntimeError(f"job {job} did not end for the result round trip")
        time.sleep(0.05)
    size = len(json.dumps(client.result(job)))
    return sequential_rtt(client, n, lambda: client.result(job)), size


def write_report(
    figures: dict[str, Any], submit_ms: np.ndarray, status_ms: np.ndarray, load: dict[str, Any], result_ms: np.ndarray | None = None
) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    lines = ["# bus_load", "", "| figure | p50 ms | p99 ms | p99.9 ms | max ms | n |", "|---|---|---|---|---|---|"]
    for name in ("submit_rtt_ms", "status_rtt_ms", "result_rtt_ms"):
        f = figures.get(name, {})
        if f.get("n"):
            lines.append(f"| {name} | {f['p50']} | {f['p99']} | {f['p999']} | {f['max']} | {f['n']} |")
    if load:
        f = load["latency_ms"]
        lines.append(f"| status under load | {f['p50']} | {f['p99']} | {f['p999']} | {f['max']} | {f['n']} |")
        lines += [
            "",
            f"Load: {load['sent']} queries at {load['target_hz']:.0f} Hz target, {load['achieved_hz']} Hz achieved over "
            f"{load['duration_s']} s; answered {load['answered']}, refused {load['refused']}, lost {load['lost']}; "
            f"weld running throughout: {figures.get('weld_running')}; server CPU {figures.get('server_cpu_percent')} %; "
            f"host 1-min load average before/after {figures.get('host_load_avg_1min')} (2 cores).",
            f"Target: >= {MIN_RATE_HZ:.0f} Hz, none lost or refused -> {'met' if figures.get('load_target_met') else 'MISSED'}.",
        ]
    (OUT / "results.md").write_text("\n".join(lines) + "\n")
    plt = pyplot("bus_load")
    if plt is None:
        return
    fig, axes = plt.subplots(1, 2 if load else 1, figsize=(12 if load else 6, 4), squeeze=False)
    ax = axes[0][0]
    curves = (
        (submit_ms, "submit"),
        (status_ms, "status"),
        (result_ms if result_ms is not None else np.empty(0), "result"),
        (load.get("_latency_ms", np.empty(0)), "status under load"),
    )
    for data, label in curves:
        if data.size:
            x = np.sort(data)
            ax.step(x, np.arange(1, x.size + 1) / x.size, where="post", label=f"{label} (n={data.size})")
    ax.axhline(0.99, color="grey", lw=0.5, ls="--")
    ax.set_xscale("log")
    ax.set_xlabel("round trip, ms")
    ax.set_ylabel("fraction of requests answered within")
    ax.legend(loc="lower right")
    ax.set_title("bus round trips, loopback (dashed: p99)")
    if load:
        ax = axes[0][1]
        ax.plot(load["_t_s"], load["_latency_ms"], ",", alpha=0.5)
        ax.set_yscale("log")
        ax.set_xlabel("time since start of load, s")
        ax.set_ylabel("status round trip, ms")
        ax.set_title(f"status at {load['target_hz']:.0f} Hz during a weld")
    fig.tight_layout()
    fig.savefig(OUT / "round_trips.png", dpi=120)
    plt.close(fig)


# -- main ---------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short run (< 1 min)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON on the last line")
    parser.add_argument("--config", help="measure a running cell with this config instead of a dummy cell")
    parser.add_argument("--cell", help="cell name (default: cell.name of --config)")
    parser.add_argument("--submits", type=int, help="sequential submits (default 300, quick 50; 0 against --config)")
    parser.add_argument("--duration", type=float, help="load phase, s (default 30, quick 5)")
    parser.add_argument("--rate", type=float, default=LOAD_HZ, help="status queries per second in the load phase")
    parser.add_argument("--sim-cell", action="store_true", help="the real daemon on the simulated cell, with a real weld")
    args = parser.parse_args(argv)
    if args.sim_cell:
        return main_sim_cell(args)

    duration = args.duration or (5.0 if args.quick else 30.0)
    n_submits = args.submits if args.submits is not None else (0 if args.config else (50 if args.quick else 300))
    n_status = 200 if args.quick else 1000
    figures: dict[str, Any] = {"server": "daemon" if args.config else "dummy", "quick": args.quick}
    failures = Failures("bus_load")

    with ExitStack() as stack:
        cell_proc = None
        if args.config:
            cfg = config.load(args.config)
            bus, cell_name = cfg.bus, args.cell or cfg.cell.name
        else:
            workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bus-load-")))
            # Submitted health jobs end at once; the weld lasts the whole load phase
            # and publishes progress at 10 Hz.
            cell_proc = DummyCellProcess(workdir, job_duration=0.0, weld_duration=duration + 5.0)
            stack.callback(cell_proc.close)
            cfg = config.load(cell_proc.config_path)
            bus, cell_name = cfg.bus, cfg.cell.name
        session = open_client(bus)
        stack.callback(session.close)
        client = CellClient(bus, cell_name, session=session)

        client.status()  # warm-up: links, declarations, first-call costs
        submit_ms = np.empty(0)
        result_ms = None
        last: list[str] = []
        if n_submits:
            submit_ms = sequential_rtt(client, n_submits, lambda: last.append(client.submit({"kind": "health", "ref": "bus-load"})["job"]))
            figures["submit_rtt_ms"] = _percentiles(submit_ms)
            result_ms, size = result_rtt(client, last[-1], n_status)
            figures["result_rtt_ms"] = {**_percentiles(result_ms), "reply_bytes": size}
        status_ms = sequential_rtt(client, n_status, client.status)
        figures["status_rtt_ms"] = _percentiles(status_ms)

        weld_id = None
        if not args.config:
            weld_id = client.submit({"kind": "weld", "ref": "bus-load"})["job"]
            time.sleep(0.5)  # the short jobs ahead of it drain, the weld starts
        before = client.status()
        cpu0 = cell_proc.cpu_seconds() if cell_proc else None
        load_avg0 = os.getloadavg()[0]
        load = status_load(client, args.rate, duration)
        figures["host_load_avg_1min"] = [round(load_avg0, 2), round(os.getloadavg()[0], 2)]
        cpu1 = cell_proc.cpu_seconds() if cell_proc else None
        after = client.status(weld_id) if weld_id else None
        figures["weld_running"] = bool(weld_id and before.get("running") == weld_id and after and after["state"] == "running")
        if cpu0 is not None and cpu1 is not None:
            figures["server_cpu_percent"] = round(100 * (cpu1 - cpu0) / load["duration_s"], 1)
        figures["status_load"] = {k: v for k, v in load.items() if not k.startswith("_")}
        figures["load_target_met"] = bool(load["achieved_hz"] >= MIN_RATE_HZ and load["lost"] == 0 and load["refused"] == 0)
        if after is not None and after["state"] in ("failed", "cancelled", "interrupted"):
            failures.add(f"weld job {weld_id}", f"{after['state']} during the load phase: {after['reason']}")
        if weld_id:
            client.cancel(weld_id, "end of the load test")
        for job in last:
            record = client.status(job)
            if record["state"] != "succeeded":
                failures.add(f"health job {job}", f"{record['state']}: {record['reason']}")

    write_report(figures, submit_ms, status_ms, load, result_ms)
    summary = figures.get("submit_rtt_ms", {})
    print(f"submit round trip: {summary}")
    print(f"status round trip: {figures['status_rtt_ms']}")
    print(f"result round trip: {figures.get('result_rtt_ms')}")
    print(f"status load: {figures['status_load']} weld running: {figures['weld_running']}")
    print(f"load target met: {figures['load_target_met']}; results in {OUT}")
    figures["failed"] = failures.jobs
    if args.json:
        print(json.dumps(figures))
    return failures.exit_code()


SIM_HOST = "127.0.0.6"
ROOT = Path(__file__).resolve().parents[1]


def main_sim_cell(args: argparse.Namespace) -> int:
    """The load phase against the real daemon while it welds on the simulated cell."""
    from celld.sim.cell import run_cell

    duration = args.duration or (5.0 if args.quick else 30.0)
    n_submits = args.submits if args.submits is not None else (20 if args.quick else 100)
    n_status = 200 if args.quick else 1000
    figures: dict[str, Any] = {"server": "daemon on the simulated cell", "quick": args.quick}
    failures = Failures("bus_load")
    result_ms: np.ndarray | None = None
    with tempfile.TemporaryDirectory(prefix="bus-load-cell-") as tmp:
        work = Path(tmp)
        cfg_path = work / "cell.toml"
        cfg_path.write_text(
            f'include = ["{ROOT / "configs" / "sim-cell.toml"}"]\n[cell]\nname = "bench-cell"\nstate_dir = "{work / "state"}"\n'
            f'[robot]\nhost = "{SIM_HOST}"\n[sim]\npreset = "ideal"\n[sim.scanner]\nresolution_scale = 0.5\n[calibration]\nn_poses = 6\ne_required_mm = 0.0\n'
            f'[bus]\nlisten = ["tcp/{SIM_HOST}:7447"]\n'
        )
        with run_cell(cfg_path, work / "daemon.log", timeout=120) as cell:
            client = cell.client
            _, cal = client.submit_and_wait({"kind": "calibrate", "seed": 1}, timeout=900)
            if cal["state"] != "succeeded":
                # Nothing to weld without a calibration: no figures.
                failures.add(f"calibrate job {cal['id']}", f"{cal['state']}: {cal['reason']}")
                figures["failed"] = failures.jobs
                if args.json:
                    print(json.dumps(figures))
                return failures.exit_code()
            client.accept(cal["id"])
            client.status()
            submit_ms = (
                sequential_rtt(client, n_submits, lambda: client.submit({"kind": "health", "check": "robot", "ref": "bus-load"}))
                if n_submits
                else np.empty(0)
            )
            if n_submits:
                figures["submit_rtt_ms"] = _percentiles(submit_ms)
            status_ms = sequential_rtt(client, n_status, client.status)
            figures["status_rtt_ms"] = _percentiles(status_ms)
            # The 150 mm seam at V_const such that the track outlasts the load phase.
            v = max(1.0, min(10.0, 120.0 / (duration + 10.0)))
            with client.watch_progress() as events:
                weld_id = client.submit({"kind": "weld", "ref": "bus-load", "v_const_mm_s": v})["job"]
                events.wait_stage(weld_id, "track", timeout=600)
            time.sleep(2.0)  # past the touch
            load_avg0 = os.getloadavg()[0]
            load = status_load(client, args.rate, duration)
            figures["host_load_avg_1min"] = [round(load_avg0, 2), round(os.getloadavg()[0], 2)]
            figures["weld_running"] = client.status(weld_id)["state"] == "running"
            figures["status_load"] = {k: v for k, v in load.items() if not k.startswith("_")}
            figures["load_target_met"] = bool(load["achieved_hz"] >= MIN_RATE_HZ and load["lost"] == 0 and load["refused"] == 0)
            deadline = time.monotonic() + 600
            while client.status(weld_id)["state"] in ("queued", "running") and time.monotonic() < deadline:
                time.sleep(1.0)
            weld = client.status(weld_id)
            figures["weld"] = {"state": weld["state"], "reason": weld["reason"], "v_const_mm_s": v}
            if weld["state"] != "succeeded":
                failures.add(f"weld job {weld_id}", f"{weld['state']}: {weld['reason']}")
            else:
                result_ms, size = result_rtt(client, weld_id, 50 if args.quick else 200)
                figures["result_rtt_ms"] = {**_percentiles(result_ms), "reply_bytes": size, "job": "the weld"}
                f = client.result(weld_id)["result"]["figures"]
                figures["motion_loop"] = {
                    k: f[k] for k in ("loop_cycles", "loop_cycles_late_2ms", "loop_late_p99_ms", "loop_late_max_ms", "duration_s")
                }
                figures["motion_loop_target_met"] = f["loop_cycles_late_2ms"] == 0
    write_report(figures, submit_ms, status_ms, load, result_ms)
    print(f"submit round trip: {figures.get('submit_rtt_ms')}")
    print(f"result round trip: {figures.get('result_rtt_ms')}")
    print(f"status round trip: {figures['status_rtt_ms']}")
    print(f"status load: {figures['status_load']} weld: {figures['weld']}")
    print(f"motion loop while welding: {figures.get('motion_loop')}")
    print(f"load target met: {figures['load_target_met']}; loop target met: {figures.get('motion_loop_target_met')}; results in {OUT}")
    figures["failed"] = failures.jobs
    if args.json:
        print(json.dumps(figures))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
