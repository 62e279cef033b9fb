"""Delivery period of the simulated UR10e's 500 Hz RTDE stream, and the simulator's CPU use.

The simulator runs as its own process (``celld.sim.robot.launch``). A client in
this process subscribes to the recipe ur-rtde's RTDEReceiveInterface asks for
at 500 Hz and stamps the arrival of every data package with
``time.monotonic_ns()``; the delivery period is the difference of consecutive
arrivals. Two scenarios:

- ``stream``: the receiving client alone;
- ``control``: the same, while another process drives ur-rtde's
  RTDEControlInterface with speedL at 500 Hz (a slow sinusoid), as the motion
  process does; the simulator then also runs the control script and the
  inverse kinematics every cycle.

Figures per scenario: period p50 / p99 / max (ms), share of periods above
2.5 ms, packages lost (controller timestamps skipped), the simulator's CPU use
(% of one core, from /proc) and its own count of late cycles.
Target: p99 of the period at most 2.5 ms.

``--quick`` runs 10 s per scenario (< 1 min); the full run 60 s each and
writes a table and plots to bench/out/rtde_stream/. ``--realtime`` runs the
simulator, and the receiving client, at SCHED_FIFO where allowed (the motion
process runs so on the cell); without it both are ordinary processes, and on a
loaded machine the receiver's own wake-ups dominate the figures. ``--json`` prints one JSON object of
the figures as the last line. Exit code 1 when the ``control`` scenario's
speedL client failed (it exits non-zero: the scenario ran without its load),
named on stderr and in the JSON's ``failed``; 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import Failures, pyplot

from celld.sim.robot import launch
from celld.sim.robot import rtde_protocol as P
from celld.sim.robot.options import RTDE_PORT

# A loopback address of its own, clear of the tests' and the demo's.
HOST = "127.0.9.2"
TARGET_P99_MS = 2.5
OUT_DIR = Path(__file__).resolve().parent / "out" / "rtde_stream"

# The output recipe of ur-rtde 1.6.5's RTDEReceiveInterface against a 5.11 controller.
RECEIVE_RECIPE = (
    "timestamp,target_q,target_qd,target_qdd,target_current,target_moment,actual_q,actual_qd,actual_current,"
    "joint_control_output,actual_TCP_pose,actual_TCP_speed,actual_TCP_force,target_TCP_pose,target_TCP_speed,"
    "actual_digital_input_bits,joint_temperatures,actual_execution_time,robot_mode,joint_mode,safety_mode,"
    "actual_tool_accelerometer,speed_scaling,target_speed_fraction,actual_momentum,actual_main_voltage,"
    "actual_robot_voltage,actual_robot_current,actual_joint_voltage,actual_digital_output_bits,runtime_state,"
    "standard_analog_input0,standard_analog_input1,standard_analog_output0,standard_analog_output1,"
    "robot_status_bits,safety_status_bits,ft_raw_wrench,payload,payload_cog,payload_inertia,output_int_register_2,"
    + ",".join(f"output_int_register_{i}" for i in range(12, 20))
    + ","
    + ",".join(f"output_double_register_{i}" for i in range(12, 20))
)


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def receive_stream(host: str, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Arrival times (ns) and controller timestamps (s) of every data package for ``seconds``."""
    sock = socket.create_connection((host, RTDE_PORT), timeout=5.0)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    reader = P.PackageReader()

    def request(msg_type: int, payload: bytes) -> bytes:
        sock.sendall(P.package(msg_type, payload))
        while True:
            for t, body in reader.packages():
                if t == msg_type:
                    return body
            reader.feed(sock.recv(65536))

    assert request(P.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
    reply = request(P.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 500.0) + RECEIVE_RECIPE.encode())
    if reply[0] == 0:
        raise RuntimeError(f"output recipe refused: {reply[1:].decode()}")
    sock.sendall(P.package(P.CONTROL_PACKAGE_START))
    n_max = int(seconds * 600) + 1000
    arrivals = np.zeros(n_max, np.int64)
    stamps = np.zeros(n_max)
    n = 0
    end = time.monotonic_ns() + int(seconds * 1e9)
    while n < n_max:
        data = sock.recv(65536)
        now = time.monotonic_ns()
        if not data:
            break
        reader.feed(data)
        for t, body in reader.packages():
            if t == P.DATA_PACKAGE and n < n_max:
                arrivals[n] = now
                stamps[n] = struct.unpack_from(">d", body, 1)[0]
                n += 1
        if now > end:
            break
    sock.sendall(P.package(P.CONTROL_PACKAGE_PAUSE))
    sock.close()
    return arrivals[:n], stamps[:n]


def load_client(host: str, seconds: float) -> None:
    """ur-rtde speedL at 500 Hz for ``seconds`` (runs in its own process)."""
    import rtde_control

    c = rtde_control.RTDEControlInterface(host)
    k = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t = c.initPeriod()
        phase = 2 * math.pi * k / 2500.0
        c.speedL([0.03 * math.sin(phase), 0.03 * math.cos(phase), 0.0, 0.0, 0.0, 0.0], 0.5, 0.0)
        c.waitPeriod(t)
        k += 1
    c.speedStop(0.5)
    c.stopScript()
    c.disconnect()


def _set_fifo(priority: int) -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (PermissionError, OSError):
        return False


def run_scenario(name: str, seconds: float, realtime: bool, failures: Failures) -> dict[str, Any]:
    with launch(HOST, realtime=realtime) as sim:
        load = None
        if name == "control":
            load = subprocess.Popen([sys.executable, __file__, "--load-client", HOST, str(seconds + 3.0)])
            time.sleep(2.0)  # let it construct and start its loop
        status0 = sim.status()
        cpu0, wall0 = _cpu_seconds(sim.process.pid), time.monotonic()
        fifo = realtime and _set_fifo(40)
        try:
            arrivals, stamps = receive_stream(HOST, seconds)
        finally:
            if fifo:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        cpu = (_cpu_seconds(sim.process.pid) - cpu0) / (time.monotonic() - wall0)
        status1 = sim.status()
        if load is not None and load.wait(30) != 0:
            failures.add(f"{name} scenario", f"the speedL client (ur-rtde) exited with {load.returncode}: see its output above")
    periods_ms = np.diff(arrivals[50:]) * 1e-6  # skip the first 0.1 s
    lost = int(np.sum(np.round(np.diff(stamps[50:]) / 0.002) - 1))
    return {
        "scenario": name,
        "seconds": seconds,
        "packages": int(len(arrivals)),
        "period_p50_ms": float(np.percentile(periods_ms, 50)),
        "period_p99_ms": float(np.percentile(periods_ms, 99)),
        "period_max_ms": float(periods_ms.max()),
        "share_over_2_5_ms": float(np.mean(periods_ms > TARGET_P99_MS)),
        "packages_lost": lost,
        "sim_cpu_percent": 100.0 * cpu,
        "sim_late_cycles": int(status1["late_cycles"] - status0["late_cycles"]),
        "sim_skipped_cycles": int(status1["skipped_cycles"] - status0["skipped_cycles"]),
        "sim_max_lateness_ms": float(status1["max_lateness_ms"]),
        "_periods_ms": periods_ms,
    }


def write_report(results: list[dict[str, Any]], realtime: bool) -> None:
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    lines = [
        f"# RTDE stream of the simulated UR10e ({'SCHED_FIFO' if realtime else 'SCHED_OTHER'})",
        "",
        "| scenario | s | p50 ms | p99 ms | max ms | >2.5 ms | lost | sim CPU % | sim late cycles |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['scenario']} | {r['seconds']:.0f} | {r['period_p50_ms']:.3f} | {r['period_p99_ms']:.3f} | "
            f"{r['period_max_ms']:.2f} | {100 * r['share_over_2_5_ms']:.2f} % | {r['packages_lost']} | "
            f"{r['sim_cpu_percent']:.1f} | {r['sim_late_cycles']} |"
        )
    lines.append(f"\nTarget: p99 <= {TARGET_P99_MS} ms.")
    (OUT_DIR / "results.md").write_text("\n".join(lines) + "\n")
    plt = pyplot("rtde_stream")
    if plt is None:
        return
    fig, axes = plt.subplots(len(results), 2, figsize=(12, 3.5 * len(results)), squeeze=False)
    for row, r in zip(axes, results):
        p = r["_periods_ms"]
        row[0].plot(np.arange(len(p)) * 0.002, p, lw=0.4)
        row[0].axhline(TARGET_P99_MS, color="r", lw=0.8)
        row[0].set(title=f"{r['scenario']}: delivery period", xlabel="s", ylabel="ms")
        row[1].hist(p, bins=np.linspace(0, max(8.0, float(p.max())), 200), log=True)
        row[1].axvline(TARGET_P99_MS, color="r", lw=0.8)
        row[1].set(title=f"{r['scenario']}: histogram", xlabel="ms")
    fig.tight_layout()
    fig.savefig(OUT_DIR / "periods.png", dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="10 s per scenario instead of 60 s")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON object, last line")
    parser.add_argument("--realtime", action="store_true", help="run the simulator at SCHED_FIFO where allowed")
    parser.add_argument("--scenarios", default="stream,control")
    parser.add_argument("--load-client", nargs=2, metavar=("HOST", "SECONDS"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.load_client:
        load_client(args.load_client[0], float(args.load_client[1]))
        return 0
    seconds = 10.0 if args.quick else 60.0
    failures = Failures("rtde_stream")
    results = [run_scenario(name, seconds, args.realtime, failures) for name in args.scenarios.split(",")]
    for r in results:
        print(
            f"{r['scenario']:8s} period p50 {r['period_p50_ms']:.3f} ms  p99 {r['period_p99_ms']:.3f} ms  "
            f"max {r['period_max_ms']:.2f} ms  >2.5 ms {100 * r['share_over_2_5_ms']:.2f} %  lost {r['packages_lost']}  "
            f"sim CPU {r['sim_cpu_percent']:.1f} %  late cycles {r['sim_late_cycles']}"
        )
    if not args.quick:
        write_report(results, args.realtime)
        print(f"table and plots in {OUT_DIR}")
    if args.json:
        figures: dict[str, Any] = {"realtime": args.realtime, "target_p99_ms": TARGET_P99_MS}
        for r in results:
            for key, value in r.items():
                if not key.startswith("_") and key != "scenario":
                    figures[f"{r['scenario']}_{key}"] = value
        figures["meets_target"] = all(r["period_p99_ms"] <= TARGET_P99_MS for r in results)
        figures["failed"] = failures.jobs
        print(json.dumps(figures))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
