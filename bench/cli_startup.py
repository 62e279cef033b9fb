"""Start-up of the command line: wall time and peak memory of ``celld --help`` and ``celld status``.

Each command runs as a fresh process, ``python -m celld.cli ...`` from the
repository root (what ``.venv/bin/celld`` runs), one at a time:

- ``help``: ``celld --help``, which builds the parser of every subcommand;
- ``status``: ``celld status --config FILE``: the config loaded, the bus
  opened, one status query answered by a running cell.

Against what: a dummy cell (``tests/standin.py``: the real bus server
and journal, jobs that only wait) started in a child process on 127.0.0.10;
with ``--config FILE`` a running cell instead.

Figures per command: wall time from start to exit (median, max, s), its
CPU time (user + system, median, s: what the command costs whatever else
the machine runs), the process's peak resident memory (max RSS, MB, as the
kernel counts it), and which heavy modules it imported (numpy, scipy, Open3D, OpenCV, rerun,
zenoh, structlog; from one more run that lists them). A first untimed run
of each may write Python's bytecode caches (``PYTHONDONTWRITEBYTECODE``
unset for it), as the first run of an installed celld does: the figures do
not count compiling celld's modules (some 0.07 s of CPU here).

Targets (the structure-and-speed issue): each at most 0.5 s and 150 MB.

``--quick``: 5 runs of each (a few seconds); the full run 20 of each and
writes results.md (and a plot where matplotlib is installed) to
bench/out/cli_startup/. ``--json`` prints one JSON object of the figures as
the last line. Exit code 1 when a run failed (the command exited non-zero:
the status query got no reply), named on stderr and in the JSON's
``failed``; 0 otherwise (a missed target included).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import Failures, pyplot

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "cli_startup"
# The dummy cell's address: loopback, clear of the tests' 127.0.X.N (X >= 1), the demo's .2 and the other benchmarks'.
HOST = "127.0.0.10"
TARGET_S = 0.5
TARGET_MB = 150.0
# The modules that would blow the budget, by top-level name.
HEAVY = ("numpy", "scipy", "open3d", "cv2", "rerun", "zenoh", "structlog")

# Runs celld's main on argv in a fresh interpreter and prints which of HEAVY it had imported.
_PROBE = """
import json, sys
from celld.cli import main
try:
    main(sys.argv[2:])
except SystemExit:
    pass
print(json.dumps(sorted({m.split(".")[0] for m in sys.modules} & set(sys.argv[1].split(",")))))
"""


def run_once(argv: list[str], env: dict[str, str] | None = None) -> tuple[float, float, float, int, str]:
    """``celld argv`` in a fresh process: wall and CPU time (s), max RSS (MB), exit code and the end of its stderr."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "celld.cli", *argv], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    proc.returncode = os.waitstatus_to_exitcode(status)
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, proc.returncode, err.strip()[-300:]


def imported(argv: list[str]) -> list[str]:
    """Which of HEAVY ``celld argv`` imports."""
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, ",".join(HEAVY), *argv], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False
    )
    return list(json.loads(out.stdout.strip().splitlines()[-1])) if out.stdout.strip() else []


def measure(name: str, argv: list[str], n: int, failures: Failures) -> dict[str, Any]:
    run_once(argv, {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"})  # untimed: the bytecode caches
    walls, cpus, rss = [], [], []
    for k in range(n):
        wall, cpu, mb, code, err = run_once(argv)
        if code != 0:
            failures.add(f"{name} run {k + 1}", f"celld {' '.join(argv)} exited with {code}: {err}")
            continue
        walls.append(wall)
        cpus.append(cpu)
        rss.append(mb)
    fig: dict[str, Any] = {"command": "celld " + " ".join(argv), "runs": len(walls), "imports": imported(argv)}
    if walls:
        fig.update(
            wall_s={"median": round(statistics.median(walls), 3), "max": round(max(walls), 3)},
            cpu_s={"median": round(statistics.median(cpus), 3)},
            max_rss_mb={"median": round(statistics.median(rss), 1), "max": round(max(rss), 1)},
            target_met=bool(statistics.median(walls) <= TARGET_S and max(rss) <= TARGET_MB),
            _walls=walls,
        )
    return fig


class DummyCell:
    """A dummy cell in a child process, on its own port; its config file in ``workdir``."""

    def __init__(self, workdir: Path) -> None:
        with socket.socket() as s:
            s.bind((HOST, 0))
            port = int(s.getsockname()[1])
        self.config_path = workdir / "cell.toml"
        self.config_path.write_text(
            f'[cell]\nname = "cli-startup"\nstate_dir = "{workdir / "state"}"\n\n[bus]\nmode = "peer"\nlisten = ["tcp/{HOST}:{port}"]\n'
        )
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.standin", "--config", str(self.config_path), "--state-dir", str(workdir / "state")]
            + ["--log-level", "warning"],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        if not line.startswith("ready"):
            self.close()
            raise RuntimeError(f"the dummy cell did not start: {line!r}")

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def write_outputs(figures: dict[str, Any], results: dict[str, dict[str, Any]]) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    lines = [
        "# cli_startup",
        "",
        f"Targets: <= {TARGET_S} s and <= {TARGET_MB:.0f} MB each; load average {figures['load_average_1min']}.",
        "",
        "| command | runs | wall median / max s | CPU median s | max RSS median / max MB | heavy imports | target |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results.values():
        if not r["runs"]:
            lines.append(f"| `{r['command']}` | 0 | - | - | - | - | - |")
            continue
        lines.append(
            f"| `{r['command']}` | {r['runs']} | {r['wall_s']['median']} / {r['wall_s']['max']} | {r['cpu_s']['median']} | "
            f"{r['max_rss_mb']['median']} / {r['max_rss_mb']['max']} | {', '.join(r['imports']) or 'none'} | "
            f"{'met' if r['target_met'] else 'missed'} |"
        )
    (OUT / "results.md").write_text("\n".join(lines) + "\n")
    plt = pyplot("cli_startup")
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    for i, (name, r) in enumerate(results.items()):
        ax.plot([i] * len(r.get("_walls", [])), r.get("_walls", []), "o", alpha=0.5, label=name)
    ax.axhline(TARGET_S, color="k", ls="--", lw=0.8, label=f"target {TARGET_S} s")
    ax.set_xticks(range(len(results)), list(results))
    ax.set_ylabel("wall time, s")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / "cli_startup.png", dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5 runs of each command")
    ap.add_argument("--json", action="store_true", help="print one JSON object of the figures last")
    ap.add_argument("--runs", type=int, default=20, help="runs of each command (full run)")
    ap.add_argument("--config", help="query a running cell with this config instead of a dummy cell")
    args = ap.parse_args(argv)
    n = 5 if args.quick else args.runs
    failures = Failures("cli_startup")
    figures: dict[str, Any] = {
        "quick": args.quick,
        "target_s": TARGET_S,
        "target_mb": TARGET_MB,
    }
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="cli-startup-") as tmp:
        cell = None if args.config else DummyCell(Path(tmp))
        try:
            config = args.config if cell is None else str(cell.config_path)
            load0 = os.getloadavg()[0]
            results["help"] = measure("help", ["--help"], n, failures)
            results["status"] = measure("status", ["status", "--config", config], n, failures)
        finally:
            if cell is not None:
                cell.close()
    figures["load_average_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    for name, r in results.items():
        if r["runs"]:
            print(
                f"{name:7s} wall median {r['wall_s']['median']:.3f} s (max {r['wall_s']['max']:.3f}), CPU {r['cpu_s']['median']:.3f} s, max RSS median "
                f"{r['max_rss_mb']['median']:.0f} MB (max {r['max_rss_mb']['max']:.0f}), imports {', '.join(r['imports']) or 'none'}: "
                f"target {'met' if r['target_met'] else 'missed'}"
            )
    if not args.quick:
        write_outputs(figures, results)
    figures.update({name: {k: v for k, v in r.items() if not k.startswith("_")} for name, r in results.items()})
    figures["failed"] = failures.jobs
    if args.json:
        print(json.dumps(figures))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
