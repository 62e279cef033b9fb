"""What the daemon's supervision of its child processes shares: the restart back-off.

The motion process (:mod:`celld.motion.supervisor`) and the tactile camera
process (:mod:`celld.daemon.devices`) are restarted when they die, each after
the delay :class:`Backoff` gives for its run of failures: quickly at first,
then less and less often, and from the start again once a process has run
long enough to count as stable.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Backoff:
    """Delays between restarts, s: each failure in a row takes the next, up to the last."""

    delays: tuple[float, ...] = (0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
    # A process that ran this long (s) resets the sequence.
    stable_after: float = 10.0

    def delay(self, failures: int) -> float:
        """The wait before the restart that follows ``failures`` failures in a row (the first restart: 1)."""
        return self.delays[min(max(failures - 1, 0), len(self.delays) - 1)]

    def failures_after(self, failures: int, ran_for: float) -> int:
        """The count of failures in a row after a process that ran ``ran_for`` s ended."""
        return 0 if ran_for >= self.stable_after else failures + 1
