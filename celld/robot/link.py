"""The robot link: ur-rtde's control, receive and IO interfaces behind a small port.

Only the motion process may construct a :class:`RtdeLink`: the ur-rtde
constructors hold the GIL for as long as they wait on the controller (seconds,
or forever against a controller that accepts but never answers), so they run
in the process that owns the 500 Hz loop and under the supervisor's timeout.

ur-rtde's return values are not trusted (``speedL`` returns True on a dead
link): the loop checks :meth:`RtdeLink.connected` and how fresh the state is
every cycle. The loop sends ``speedL`` (a twist) or, in a joint move,
``speedJ`` (joint speeds). ``stopL`` does not end ``speedL``; :meth:`RtdeLink.speed_stop`
uses ``speedStop``. The RTDE watchdog (:meth:`RtdeLink.set_watchdog`) stops
the robot's program when the loop stops writing, e.g. when the process is
killed. :meth:`RtdeLink.set_digital_out` switches a standard digital output
(the cell's process output, e.g. the welding arc) through the IO interface.

Third-party errors are translated here into :class:`~celld.errors.LinkLost`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol

from celld.errors import LinkLost
from celld.realtime import thread_ids

# What the receive interface subscribes to: only what the loop reads.
RECEIVE_VARIABLES = (
    "timestamp",
    "actual_q",
    "actual_qd",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "safety_status_bits",
    "runtime_state",
    "robot_mode",
    "actual_digital_output_bits",  # the arc interlock check (celld.motion.loop)
)
# UR runtime_state of a running program.
RUNTIME_PLAYING = 2
# speedStop's deceleration on a graceful shutdown, m/s^2 (the loop has already brought the TCP to rest).
_SHUTDOWN_DECEL = 1.0


class RawState(NamedTuple):
    """One read of the robot, as the controller reports it (SI, UR conventions)."""

    stamp: float  # controller time, s
    q: list[float]  # rad
    qd: list[float]  # rad/s
    tcp_pose: list[float]  # [x, y, z, rx, ry, rz], m and rad, base frame
    tcp_speed: list[float]  # [vx, vy, vz, wx, wy, wz], base frame
    safety_bits: int
    runtime_state: int


class RobotPort(Protocol):
    """What the motion loop needs from a robot; :class:`RtdeLink` is the real one.

    ``read``, ``speed``, ``speed_joints`` and ``kick`` raise :class:`~celld.errors.LinkLost` when the link is
    gone; the loop ends with it.
    """

    def connected(self) -> bool: ...

    def read(self) -> RawState: ...

    def speed(self, twist: Sequence[float], accel: float) -> bool: ...

    def speed_joints(self, qd: Sequence[float], accel: float) -> bool: ...

    def kick(self) -> None: ...

    def set_digital_out(self, index: int, value: bool) -> bool:
        """Set standard digital output ``index`` (0..7); False when it could not be sent."""
        ...

    def digital_outputs(self) -> int:
        """The controller's actual digital outputs (bits 0-7 standard, 8-15 configurable, 16-17 tool)."""
        ...

    def stop_script(self) -> None: ...

    def close(self, stop_script: bool = False) -> None: ...


class RtdeLink:
    """ur-rtde's three interfaces to one controller.

    Construct with :meth:`connect`, in the motion process only.
    """

    def __init__(self, host: str, control: object, receive: object, io: object, threads: frozenset[int] = frozenset()) -> None:
        self.host = host
        self._c = control
        self._r = receive
        self.io = io  # RTDEIOInterface, for digital outputs and registers outside the loop
        self.receive = receive  # RTDEReceiveInterface (the power source reads its inputs from it)
        # The threads ur-rtde started for these interfaces (its receive threads): the loop waits on them
        # (every command first waits for the script's state they receive), so the motion process raises
        # them to real time just below itself through the watchdog handshake (celld.realtime.schedule_threads).
        self.threads = threads

    @classmethod
    def connect(cls, host: str, frequency_hz: float = 500.0, variables: Sequence[str] = ()) -> RtdeLink:
        """Open the control, receive and IO interfaces (blocking; holds the GIL while it waits).

        ``variables``: RTDE outputs to receive beside :data:`RECEIVE_VARIABLES` (the power source's inputs).

        Raises
        ------
        LinkLost
            The controller did not answer, refused, or the script did not start.
        """
        import rtde_control
        import rtde_io
        import rtde_receive

        before = thread_ids()
        control = receive = io = None
        step = "control interface"
        try:
            control = rtde_control.RTDEControlInterface(host, frequency_hz)
            step = "receive interface"
            receive = rtde_receive.RTDEReceiveInterface(host, frequency_hz, list(dict.fromkeys((*RECEIVE_VARIABLES, *variables))))
            step = "IO interface"
            io = rtde_io.RTDEIOInterface(host)
        except RuntimeError as exc:
            for iface in (io, receive, control):
                _disconnect(iface)
            raise LinkLost(f"robot {host}: could not open the RTDE {step}: {exc}") from exc
        if not (control.isConnected() and receive.isConnected()):
            for iface in (io, receive, control):
                _disconnect(iface)
            raise LinkLost(f"robot {host}: RTDE interfaces opened but report no connection")
        return cls(host, control, receive, io, frozenset(thread_ids() - before))

    def set_watchdog(self, min_frequency_hz: float) -> None:
        """Stop the robot's program when no command or kick arrives for ``1 / min_frequency_hz`` s."""
        try:
            ok = self._c.setWatchdog(min_frequency_hz)  # type: ignore[attr-defined]
        except RuntimeError as exc:
            raise LinkLost(f"robot {self.host}: setting the RTDE watchdog failed: {exc}") from exc
        if not ok:
            raise LinkLost(f"robot {self.host}: the controller refused the RTDE watchdog")

    def connected(self) -> bool:
        return bool(self._c.isConnected() and self._r.isConnected())  # type: ignore[attr-defined]

    def read(self) -> RawState:
        r = self._r
        try:
            return RawState(
                r.getTimestamp(),  # type: ignore[attr-defined]
                r.getActualQ(),  # type: ignore[attr-defined]
                r.getActualQd(),  # type: ignore[attr-defined]
                r.getActualTCPPose(),  # type: ignore[attr-defined]
                r.getActualTCPSpeed(),  # type: ignore[attr-defined]
                r.getSafetyStatusBits(),  # type: ignore[attr-defined]
                r.getRuntimeState(),  # type: ignore[attr-defined]
            )
        except RuntimeError as exc:
            raise LinkLost(f"robot {self.host}: reading the robot state failed: {exc}") from exc

    # The commands of the loop: on a link that has just dropped, ur-rtde tries to reconnect inside the call
    # and raises RuntimeError when it cannot ("Could not connect to ..."). That is the link lost, not a
    # fault of the motion process: raised as LinkLost, the loop ends with it and the supervisor reconnects.

    def speed(self, twist: Sequence[float], accel: float) -> bool:
        """speedL: the TCP twist (base frame) the robot ramps to at ``accel`` and then keeps."""
        try:
            return bool(self._c.speedL(twist, accel, 0.0))  # type: ignore[attr-defined]
        except RuntimeError as exc:
            raise LinkLost(f"robot {self.host}: speedL failed: {exc}") from exc

    def speed_joints(self, qd: Sequence[float], accel: float) -> bool:
        """speedJ: the joint speeds (rad/s) the robot ramps to at ``accel`` (rad/s^2) and then keeps."""
        try:
            return bool(self._c.speedJ(qd, accel, 0.0))  # type: ignore[attr-defined]
        except RuntimeError as exc:
            raise LinkLost(f"robot {self.host}: speedJ failed: {exc}") from exc

    def speed_stop(self, accel: float) -> None:
        """speedStop: end speedL, decelerating at ``accel`` (stopL would not end it)."""
        self._c.speedStop(accel)  # type: ignore[attr-defined]

    def kick(self) -> None:
        """Write the watchdog register without commanding anything."""
        try:
            self._c.kickWatchdog()  # type: ignore[attr-defined]
        except RuntimeError as exc:
            raise LinkLost(f"robot {self.host}: kicking the watchdog failed: {exc}") from exc

    def set_digital_out(self, index: int, value: bool) -> bool:
        """Set standard digital output ``index`` (0..7) through the IO interface; never raises.

        Returns False when ur-rtde refused or failed (a lost link). The write
        goes out without waiting for the controller, so the loop can call it
        on the cycle the process output must change.
        """
        try:
            return bool(self.io.setStandardDigitalOut(index, value))  # type: ignore[attr-defined]
        except RuntimeError:
            return False

    def digital_outputs(self) -> int:
        """actual_digital_output_bits as the controller last reported them."""
        return int(self._r.getActualDigitalOutputBits())  # type: ignore[attr-defined]

    def stop_script(self) -> None:
        """End speedL and the control script politely; never raises.

        For a graceful shutdown only: both are non-real-time commands that
        ur-rtde waits on, seconds on a dead link. Without it the RTDE watchdog
        ends the script once the writes stop.
        """
        try:
            self._c.speedStop(_SHUTDOWN_DECEL)  # type: ignore[attr-defined]
            self._c.stopScript()  # type: ignore[attr-defined]
        except Exception:  # the link may already be gone  # noqa: BLE001
            pass

    def close(self, stop_script: bool = False) -> None:
        """Disconnect every interface (after :meth:`stop_script` with ``stop_script``); never raises."""
        if stop_script:
            self.stop_script()
        for iface in (self.io, self._r, self._c):
            _disconnect(iface)


def _disconnect(iface: object | None) -> None:
    if iface is None:
        return
    try:
        iface.disconnect()  # type: ignore[attr-defined]
    except Exception:  # the link may already be gone  # noqa: BLE001
        pass
