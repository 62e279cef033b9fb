"""What the benchmarks share (this file is not a benchmark): plots where matplotlib is, and failed jobs named.

- :func:`pyplot`: matplotlib's pyplot on the Agg backend, or None where
  matplotlib is not installed. It comes with the ``bench`` extra, not with
  the README's ``pip install -e '.[test]'``: a benchmark then writes its
  tables and figures, draws no plot and says so.
- :class:`Failures`: the jobs of a run that failed (a seed whose calibration
  or weld failed, a trial that never reached its fault, a detection that
  found the wrong centre). Each is named with its reason on stderr as it
  happens and again at the end, goes into the JSON line as ``failed``, and
  makes the exit code 1. A missed target is a figure, not a failed job: a
  benchmark's docstring says where it also sets the exit code.
- :class:`JobFailed`: raised where a run cannot go on after a failed job;
  ``main`` adds it to its :class:`Failures` and still prints its figures.
"""

from __future__ import annotations

import sys
from typing import Any

# How to get matplotlib where it is missing.
_INSTALL = "pip install -e '.[bench]'"


class JobFailed(Exception):
    """A job whose failure ends the run: ``job`` names it, ``reason`` says why."""

    def __init__(self, job: str, reason: str) -> None:
        super().__init__(f"{job}: {reason}")
        self.job = job
        self.reason = reason


class Failures:
    """The failed jobs of one benchmark run, in the order they failed."""

    def __init__(self, bench: str) -> None:
        self.bench = bench
        self.jobs: list[dict[str, str]] = []

    def add(self, job: str, reason: str) -> None:
        """Record that ``job`` failed and say so on stderr now."""
        self.jobs.append({"job": job, "reason": reason})
        print(f"{self.bench}: FAILED {job}: {reason}", file=sys.stderr, flush=True)

    def __bool__(self) -> bool:
        return bool(self.jobs)

    def exit_code(self) -> int:
        """1, after naming every failed job on stderr once more; 0 when none failed."""
        if not self.jobs:
            return 0
        print(f"{self.bench}: {len(self.jobs)} job(s) failed:", file=sys.stderr)
        for j in self.jobs:
            print(f"  {j['job']}: {j['reason']}", file=sys.stderr)
        sys.stderr.flush()
        return 1


def pyplot(bench: str) -> Any | None:
    """matplotlib.pyplot on the Agg backend; None, and a line on stderr, where matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError:
        print(f"{bench}: plots skipped: matplotlib is not installed ({_INSTALL} adds it)", file=sys.stderr, flush=True)
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
