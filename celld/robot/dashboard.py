"""The robot's dashboard server (port 29999): why the robot is down, and the operator's way to clear it.

:class:`Dashboard` reads the robot mode, the safety status and the program
state through ur-rtde's ``DashboardClient``, and sends the recovery commands
an operator may give from the cell PC: unlock a protective stop, power on,
release the brakes, close the safety pop-up. The calls block on the
controller, and ur-rtde releases the GIL while they do (measured), so they run
on one worker thread of their own: the event loop never waits on the robot,
and the calls to one connection never interleave. A call that fails drops
the connection; the next one reconnects.

:func:`robot_condition` is pure: from the link state, the last reading and
the motion process's last exit it says whether the robot can move and, when
it cannot, why and what clears it. The protective stop's own cause (a joint
limit, a collision) is on the teach pendant: neither RTDE nor the dashboard
report it; the condition says what celld saw when the motion ended.

Commands that move or power the arm are the operator's: the daemon refuses
them while a job runs (:mod:`celld.daemon.jobs`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

from celld.errors import InputError, RobotError
from celld.log import get_logger
from celld.schemadoc import boolean, enum, obj, string

log = get_logger(__name__)

DASHBOARD_PORT = 29999
# What the operator may ask, and the DashboardClient method that does it.
ACTIONS: dict[str, str] = {
    "unlock": "unlockProtectiveStop",
    "power-on": "powerOn",
    "brake-release": "brakeRelease",
    "close-popup": "closeSafetyPopup",
}
# What robot_condition may say of the robot (RobotCondition.state): ready, or why not.
CONDITIONS = (
    "ready",
    "protective_stop",
    "emergency_stop",
    "safety_fault",
    "local_control",
    "power_off",
    "brakes",
    "booting",
    "link_lost",
    "unknown",
)
# Robot modes (dashboard ``robotmode``) in which the arm can move.
_MOVING_MODE = "RUNNING"


class DashboardReading(NamedTuple):
    """One reading of the dashboard server; empty strings when it was not reachable."""

    reachable: bool
    robot_mode: str  # e.g. RUNNING, IDLE, POWER_OFF, BOOTING, NO_CONTROLLER
    safety: str  # e.g. NORMAL, PROTECTIVE_STOP, ROBOT_EMERGENCY_STOP, FAULT, VIOLATION
    program: str  # e.g. "PLAYING rtde_control"
    error: str  # why it was not reachable
    t: float  # time.monotonic() of the reading
    remote: bool = True  # the teach pendant in Remote Control (dashboard ``is in remote control``)


class RobotCondition(NamedTuple):
    """Whether the robot can move and, if not, why and what clears it."""

    ready: bool
    state: str  # one of CONDITIONS
    reason: str
    remedy: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (:data:`CONDITION_SCHEMA`)."""
        return self._asdict()


# The JSON shape of RobotCondition.as_dict.
CONDITION_SCHEMA = obj(
    "Whether the robot can move and, if not, why and what clears it.",
    {
        "ready": boolean(),
        "state": enum(CONDITIONS),
        "reason": string("Why the robot cannot move; empty when ready."),
        "remedy": string("What clears it, e.g. `celld robot unlock`."),
    },
    ("ready", "state", "reason", "remedy"),
)


def reply_value(reply: str, prefix: str) -> str:
    """The value of a dashboard reply ``"Prefix: VALUE"`` (``VALUE`` alone when the prefix is absent)."""
    text = reply.strip()
    head = prefix.lower() + ":"
    if text.lower().startswith(head):
        text = text[len(head) :]
    return text.strip()


def foreign_program(reading: DashboardReading | None) -> str:
    """The program the robot runs or holds paused (its dashboard's ``programState``, e.g. ``PLAYING weld.urp``),
    "" when none does or the dashboard could not be read."""
    if reading is None or not reading.reachable:
        return ""
    state = reading.program.partition(" ")[0].upper()
    return reading.program if state in ("PLAYING", "PAUSED") else ""


def robot_condition(link: str, reading: DashboardReading | None, last_exit: str = "") -> RobotCondition:
    """Why the robot cannot move, from the link state ("up", "down", "unknown"), the dashboard and the last exit.

    ``last_exit`` is the motion process's own account of its last end (e.g.
    "the robot program stopped: protective stop"), which names what celld saw.
    """
    seen = f"; celld saw: {last_exit}" if last_exit else ""
    if reading is None or not reading.reachable:
        why = reading.error if reading is not None and reading.error else "no reading yet"
        if link == "up":
            return RobotCondition(True, "ready", "", "")
        return RobotCondition(
            False,
            "link_lost",
            f"no link to the robot: RTDE is {link} and the dashboard server does not answer ({why}){seen}",
            "check the robot is on, its network cable and robot.host; celld reconnects by itself",
        )
    safety, mode = reading.safety.upper(), reading.robot_mode.upper()
    if "EMERGENCY_STOP" in safety:
        return RobotCondition(
            False,
            "emergency_stop",
            f"emergency stop ({safety}){seen}",
            "release the emergency stop, then `celld robot power-on` and `celld robot brake-release`",
        )
    if safety in ("PROTECTIVE_STOP", "SAFEGUARD_STOP", "AUTOMATIC_MODE_SAFEGUARD_STOP", "SYSTEM_THREE_POSITION_ENABLING_STOP"):
        remedy = (
            "inspect the cause on the teach pendant, then `celld robot unlock` (a protective stop unlocks 5 s after it occurred)"
            if safety == "PROTECTIVE_STOP"
            else "close the safeguard (door, light curtain); the robot resumes"
        )
        return RobotCondition(False, "protective_stop", f"{safety.lower().replace('_', ' ')}{seen}", remedy)
    if safety not in ("NORMAL", "REDUCED", "RECOVERY", ""):
        return RobotCondition(
            False,
            "safety_fault",
            f"safety {safety}{seen}",
            "see the teach pendant; a fault or violation needs a safety restart there",
        )
    if not reading.remote:
        # An e-Series in Local Control takes no URScript from the network (ports 30001-30003): no control script,
        # no link, and the dashboard refuses power and brake commands.
        return RobotCondition(
            False,
            "local_control",
            f"the teach pendant is in Local Control: the controller takes no program from celld{seen}",
            "switch the teach pendant to Remote Control (its icon at the top right; enabled in Settings > System > Remote Control)",
        )
    if mode == "POWER_OFF":
        return RobotCondition(
            False, "power_off", f"the arm is powered off{seen}", "`celld robot power-on`, then `celld robot brake-release`"
        )
    if mode == "IDLE":
        return RobotCondition(False, "brakes", f"the arm is powered with its brakes on{seen}", "`celld robot brake-release`")
    if mode in ("BOOTING", "POWER_ON", "BACKDRIVE", "CONFIRM_SAFETY", "DISCONNECTED", "NO_CONTROLLER", "UPDATING_FIRMWARE"):
        return RobotCondition(False, "booting", f"robot mode {mode}{seen}", "wait for the controller, or see the teach pendant")
    if mode != _MOVING_MODE:
        return RobotCondition(False, "unknown", f"robot mode {mode or 'unknown'}{seen}", "see the teach pendant")
    if link != "up":
        return RobotCondition(
            False,
            "link_lost",
            f"the arm is running but the RTDE link is {link}{seen}",
            "celld reconnects by itself; if it does not, check robot.host and that the robot is in remote control",
        )
    return RobotCondition(True, "ready", "", "")


class Dashboard:
    """ur-rtde's DashboardClient on a worker thread of its own (module docstring).

    Parameters
    ----------
    host : str
    timeout : float
        s a connection attempt may take; ur-rtde bounds each reply itself.
    client_factory : callable(host, port) -> client, optional
        Builds the client; ``dashboard_client.DashboardClient`` by default.
    """

    def __init__(
        self, host: str, timeout: float = 2.0, port: int = DASHBOARD_PORT, client_factory: Callable[[str, int], Any] | None = None
    ) -> None:
        self.host = host
        self.port = port
        self.timeout = timeout
        self._factory = client_factory
        self._client: Any = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="celld-dashboard")
        self.last: DashboardReading | None = None

    # -- on the worker thread ----------------------------------------------------------

    def _connected(self) -> Any:
        if self._client is not None and self._client.isConnected():
            return self._client
        self._drop()
        if self._factory is None:
            try:
                import dashboard_client
            except ImportError as exc:  # pragma: no cover - ur-rtde is a dependency
                raise RobotError("ur-rtde's dashboard_client is not installed") from exc
            client = dashboard_client.DashboardClient(self.host, self.port)
        else:
            client = self._factory(self.host, self.port)
        client.connect(int(self.timeout * 1000))
        self._client = client
        return client

    def _drop(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            try:
                client.disconnect()
            except Exception:  # noqa: BLE001 - the connection is being dropped anyway
                pass

    def _read_blocking(self) -> DashboardReading:
        try:
            c = self._connected()
            mode = reply_value(c.robotmode(), "Robotmode")
            safety = reply_value(c.safetystatus(), "Safetystatus")
            program = c.programState().strip()
            remote = bool(c.isInRemoteControl())
        except Exception as exc:  # noqa: BLE001 - ur-rtde raises RuntimeError and its own types
            self._drop()
            return DashboardReading(False, "", "", "", f"{type(exc).__name__}: {exc}", time.monotonic())
        return DashboardReading(True, mode, safety, program, "", time.monotonic(), remote)

    def _act_blocking(self, method: str) -> str:
        try:
            c = self._connected()
            out = getattr(c, method)()
        except Exception as exc:
            self._drop()
            raise RobotError(f"robot {self.host}: {method} failed: {exc}") from exc
        return "" if out is None else str(out)

    # -- from the event loop -------------------------------------------------------------

    async def read(self) -> DashboardReading:
        """Read the robot mode, safety status and program state; never raises."""
        loop = asyncio.get_running_loop()
        self.last = await loop.run_in_executor(self._pool, self._read_blocking)
        return self.last

    async def act(self, action: str) -> str:
        """Send one of :data:`ACTIONS`; return the dashboard's reply.

        Raises
        ------
        InputError
            Not one of :data:`ACTIONS`.
        RobotError
            The dashboard refused it (the reason is the controller's, e.g. a
            protective stop unlocked too early) or could not be reached.
        """
        method = ACTIONS.get(action)
        if method is None:
            raise InputError(f"robot action: expected one of {', '.join(ACTIONS)}, got {action!r}")
        loop = asyncio.get_running_loop()
        log.info("dashboard_command", robot=self.host, action=action)
        return await loop.run_in_executor(self._pool, self._act_blocking, method)

    async def stop_program(self) -> str:
        """Stop the program the robot runs (the dashboard's ``stop``): celld takes a robot over from another program
        this way (ur-rtde replaces only its own script). Not an operator's action.

        Raises
        ------
        RobotError
            The dashboard refused it or could not be reached.
        """
        loop = asyncio.get_running_loop()
        log.warning("dashboard_command", robot=self.host, action="stop the running program")
        return await loop.run_in_executor(self._pool, self._act_blocking, "stop")

    async def close(self) -> None:
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._pool, self._drop)
        self._pool.shutdown(wait=False)
