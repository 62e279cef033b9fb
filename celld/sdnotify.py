"""systemd notifications (sd_notify): READY, WATCHDOG, STOPPING, STATUS.

systemd passes ``NOTIFY_SOCKET`` to a ``Type=notify`` service: a path, or an
abstract socket name starting with ``@``. A notification is one datagram of
``KEY=VALUE`` lines. Without ``NOTIFY_SOCKET`` (a shell, a test, a container
without systemd) every call is a no-op that returns False.

The daemon's part of the protocol:

- ``READY=1`` once the daemon serves its bus, its devices there or not (:meth:`Notifier.ready`);
- ``WATCHDOG=1`` at about half of ``WatchdogSec``, and **only while the
  motion process's heartbeat is fresh**: :func:`run_watchdog` asks a health
  predicate before every kick, so a stuck RT loop lets systemd restart the
  service instead of being masked by a healthy asyncio loop;
- ``STOPPING=1`` when it begins to shut down (after SIGTERM);
- ``STATUS=...``: a line for ``systemctl status``.

A send that fails (systemd gone, queue full) is never fatal: the call returns
False and the first failure is logged.
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Callable

from celld.log import get_logger

log = get_logger(__name__)

# Environment variables systemd sets.
_SOCKET_ENV = "NOTIFY_SOCKET"
_WATCHDOG_USEC_ENV = "WATCHDOG_USEC"
_WATCHDOG_PID_ENV = "WATCHDOG_PID"


def socket_address(name: str) -> str:
    """The address of ``NOTIFY_SOCKET`` for ``sendto``: ``@name`` is the abstract ``\\0name``."""
    return "\0" + name[1:] if name.startswith("@") else name


def watchdog_interval(environ: dict[str, str] | None = None, pid: int | None = None) -> float | None:
    """Seconds between WATCHDOG=1 kicks (half of ``WATCHDOG_USEC``), or None if no watchdog applies.

    ``WATCHDOG_PID``, when set, must be this process (it is for a forked helper otherwise).
    """
    env = os.environ if environ is None else environ
    usec = env.get(_WATCHDOG_USEC_ENV, "")
    if not usec.isdigit() or int(usec) == 0:
        return None
    owner = env.get(_WATCHDOG_PID_ENV, "")
    if owner and owner != str(os.getpid() if pid is None else pid):
        return None
    return int(usec) / 2e6


class Notifier:
    """Sends notifications to systemd.

    Parameters
    ----------
    address : str, optional
        The notify socket (path or ``@abstract``); default ``$NOTIFY_SOCKET``.
        Empty: notifications are disabled.
    """

    def __init__(self, address: str | None = None) -> None:
        name = os.environ.get(_SOCKET_ENV, "") if address is None else address
        self.address = socket_address(name) if name else ""
        self._sock: socket.socket | None = None
        self._warned = False
        self.failures = 0
        if self.address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, *lines: str) -> bool:
        """Send ``KEY=VALUE`` lines as one datagram; returns whether it was sent."""
        if self._sock is None:
            return False
        for line in lines:
            if "=" not in line or "\n" in line:
                raise ValueError(f"expected KEY=VALUE on one line, got {line!r}")
        try:
            self._sock.sendto("\n".join(lines).encode("utf-8"), socket.MSG_DONTWAIT, self.address)
        except OSError as exc:
            self.failures += 1
            if not self._warned:
                self._warned = True
                log.warning("sd_notify_failed", socket=self.address.replace("\0", "@"), error=str(exc))
            return False
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str = "") -> bool:
        return self.notify("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text.replace(chr(10), ' ')}")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


async def run_watchdog(
    notifier: Notifier,
    healthy: Callable[[], bool],
    interval: float | None = None,
    on_unhealthy: Callable[[], None] | None = None,
) -> None:
    """Kick the watchdog every ``interval`` seconds while ``healthy()`` says so; runs until cancelled.

    Parameters
    ----------
    healthy : callable
        True while the daemon and its supervision are alive (the daemon: the
        motion process is supervised, link up or not). It must be quick: it
        runs on the loop, so a hung loop also leaves the watchdog unkicked.
    interval : float, optional
        Default: half of ``WATCHDOG_USEC``. Without a watchdog this returns at once.
    on_unhealthy : callable, optional
        Called on each skipped kick (to log or to set STATUS).
    """
    period = watchdog_interval() if interval is None else interval
    if period is None or not notifier.enabled:
        return
    while True:
        if healthy():
            notifier.watchdog()
        elif on_unhealthy is not None:
            on_unhealthy()
        await asyncio.sleep(period)
