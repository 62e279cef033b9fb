"""A simulated UR10e controller that unmodified ur-rtde connects to.

The simulator runs as its own process (ur-rtde's constructors hold the GIL, so
a simulator in the same process would deadlock them) and binds one loopback
address, so every test can take its own and the fixed UR ports never collide::

    with launch("127.0.0.12", tcp_speed_limit=1.0) as sim:
        rtde_c = RTDEControlInterface("127.0.0.12")
        ...
        sim.inject("protective_stop")
        stamp_ns, T_base_tcp, q = sim.truth()

Modules: :mod:`~.rtde_protocol` (RTDE codecs), :mod:`~.controller` (modes,
registers, IO, the cycle), :mod:`~.model` (the arm and its motions),
:mod:`~.script` (ur-rtde's control script), :mod:`~.dashboard`,
:mod:`~.faults`, :mod:`~.truth` (true state in shared memory),
:mod:`~.source` (a welding power source on the I/O),
:mod:`~.links` and :mod:`~.server` (sockets and the 500 Hz loop),
:mod:`~.launcher` (this package's entry point for other processes).
"""

from __future__ import annotations

from celld.sim.robot.launcher import SimRobotHandle, launch
from celld.sim.robot.options import SimOptions
from celld.sim.robot.truth import TruthReader, TruthSample

__all__ = ["SimOptions", "SimRobotHandle", "TruthReader", "TruthSample", "launch"]
