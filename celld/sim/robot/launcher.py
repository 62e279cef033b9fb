"""Start the simulated controller as its own process and talk to it: :func:`launch`.

ur-rtde's constructors hold the GIL, so the simulator must never run in the
process that constructs ur-rtde objects; :func:`launch` starts
``python -m celld.sim.robot`` and returns once every port is bound. The
:class:`SimRobotHandle` it returns injects faults and teleports the arm
through the simulator's control endpoint, and reads the true state from
shared memory (:mod:`celld.sim.robot.truth`).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld.errors import InputError, RobotError
from celld.log import settings
from celld.sim.robot.options import CONTROL_PORT, SimOptions
from celld.sim.robot.truth import TruthReader, TruthSample

# How long a control request may take, s.
_REQUEST_TIMEOUT = 5.0
# How long the simulator may take to exit after "shutdown", s.
_STOP_TIMEOUT = 5.0


def control_request(host: str, op: str, **args: Any) -> dict[str, Any]:
    """Send one request to the control endpoint of the simulator on ``host``; return its reply.

    Raises InputError when the simulator refuses the request, RobotError when
    it cannot be reached.
    """
    payload = (json.dumps({"op": op, **args}) + "\n").encode()
    try:
        with socket.create_connection((host, CONTROL_PORT), timeout=_REQUEST_TIMEOUT) as sock:
            sock.sendall(payload)
            buf = b""
            while not buf.endswith(b"\n"):
                chunk = sock.recv(65536)
                if not chunk:
                    break
                buf += chunk
    except OSError as exc:
        raise RobotError(f"simulated robot on {host}: control endpoint unreachable ({exc})") from exc
    if not buf:
        raise RobotError(f"simulated robot on {host}: control endpoint closed without a reply")
    reply = json.loads(buf)
    if not reply.pop("ok", False):
        raise InputError(f"simulated robot on {host}: {reply.get('error', 'request refused')}")
    return dict(reply)


class SimRobotHandle:
    """A running simulated controller: its address, faults, teleport and true state.

    Use as a context manager, or call :meth:`stop`.
    """

    def __init__(self, options: SimOptions, process: subprocess.Popen[bytes]) -> None:
        self.options = options
        self.host = options.host
        self.process = process
        self._truth: TruthReader | None = None

    # --- control endpoint -------------------------------------------------------------

    def request(self, op: str, **args: Any) -> dict[str, Any]:
        """Send one request to the control endpoint; see :func:`control_request`."""
        return control_request(self.host, op, **args)

    def inject(self, fault: str, **kw: float) -> None:
        """Play a fault (see :mod:`celld.sim.robot.faults`), e.g. ``inject("stall", ms=200)``."""
        self.request("inject", fault=fault, **kw)

    def clear_faults(self) -> None:
        """Undo latency, stall, refused uploads, links held down and a pressed e-stop."""
        self.request("clear")

    def set_q(self, q: ArrayLike) -> None:
        """Teleport the arm to joints ``q`` (6,), rad, at rest (test set-up)."""
        values = np.asarray(q, dtype=np.float64).reshape(-1).tolist()
        self.request("set_q", q=values)

    def set_digital_inputs(self, bits: int) -> None:
        """Set ``actual_digital_input_bits`` (standard 0-7, configurable 8-15, tool 16-17); the inputs a power
        source drives (:mod:`celld.sim.robot.source`) are its own again from the next cycle."""
        self.request("set_digital_in", bits=int(bits))

    def status(self) -> dict[str, Any]:
        """Modes, program, joints, pose, connected links and cycle statistics."""
        return self.request("status")

    # --- true state -------------------------------------------------------------------

    def _reader(self) -> TruthReader:
        if self._truth is None:
            if not self.options.truth:
                raise RobotError(f"simulated robot on {self.host} runs without truth publishing")
            self._truth = TruthReader(self.host)
        return self._truth

    def truth(self) -> tuple[int, NDArray[np.float64], NDArray[np.float64]]:
        """``(stamp_ns, T_base_tcp (4, 4), q (6,))`` of the latest cycle (time.monotonic_ns())."""
        s = self._reader().latest()
        return s.stamp_ns, s.T_base_tcp, s.q

    def truth_history(self) -> NDArray[np.void]:
        """The true states of the last ~2 s, oldest first (:data:`~celld.sim.robot.truth.TRUTH_DTYPE`)."""
        return self._reader().history()

    def truth_at(self, stamp_ns: int) -> TruthSample:
        """The true state at ``stamp_ns`` (within the last ~2 s), interpolated."""
        return self._reader().at(stamp_ns)

    # --- life cycle -------------------------------------------------------------------

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self) -> int:
        """Stop the simulator; return its exit code."""
        if self._truth is not None:
            self._truth.close()
            self._truth = None
        if self.process.poll() is None:
            try:
                self.request("shutdown")
            except (RobotError, InputError):
                self.process.terminate()
            try:
                self.process.wait(_STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(_STOP_TIMEOUT)
        return int(self.process.returncode)

    def __enter__(self) -> SimRobotHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def launch(host: str, timeout: float = 15.0, extra_args: Sequence[str] = (), **options: Any) -> SimRobotHandle:
    """Start the simulated UR10e on ``host`` (127.x.y.z) and wait until it listens.

    ``options`` are fields of :class:`~celld.sim.robot.options.SimOptions`
    (``workspace_min``, ``tcp_speed_limit``, ``unlock_delay``, ``q0``, ...).
    The simulator exits by itself when this process dies.
    """
    opts = SimOptions(host=host, parent_pid=os.getpid()).with_(**options)
    cmd = [sys.executable, "-m", "celld.sim.robot", *opts.to_argv(), *settings().argv(), *extra_args]
    process = subprocess.Popen(cmd, stdin=subprocess.DEVNULL)
    handle = SimRobotHandle(opts, process)
    deadline = time.monotonic() + timeout
    while True:
        if process.poll() is not None:
            raise RobotError(f"simulated robot on {host} exited with code {process.returncode} before listening")
        try:
            handle.request("ping")
            return handle
        except RobotError:
            if time.monotonic() > deadline:
                handle.stop()
                raise RobotError(f"simulated robot on {host} did not listen within {timeout:g} s") from None
            time.sleep(0.05)
