"""True state of the simulated arm in shared memory, for the other simulated devices.

The simulated scanner and SRM camera need the TCP pose at their own capture
times, without going through RTDE; a benchmark scores a weld against whether
an arc truly burned and at what current (the simulated power source,
:mod:`celld.sim.robot.source`). What is published is the physical arm
(:mod:`celld.sim.robot.truearm`): its joints and its true TCP, which differ
from what the controller reports over RTDE by the world's kinematic error,
repeatability, settling and encoder noise (identical when the world has none). Every 2 ms cycle the simulator writes one
:data:`TRUTH_DTYPE` record, stamped with the ``time.monotonic_ns()`` instant
the state belongs to (CLOCK_MONOTONIC is shared by all processes), to

- a :class:`~celld.shm.SeqlockSlot` holding the latest record, and
- a :class:`~celld.shm.Ring` holding the last :data:`HISTORY_CAPACITY` records
  (about 2 s), so a capture at time t can be interpolated.

Segment names derive from the simulator's host address (:func:`segment_names`),
so simulators on different loopback addresses never share them. Readers use
:class:`TruthReader`; nothing here needs the simulator's process.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from celld.errors import InputError, RobotError
from celld.shm import Ring, SeqlockSlot

# One record per controller cycle.
TRUTH_DTYPE = np.dtype(
    [
        ("stamp_ns", "<i8"),  # time.monotonic_ns() of this state
        ("q", "<f8", (6,)),  # physical joints, rad
        ("qd", "<f8", (6,)),  # joint speeds, rad/s
        ("T_base_tcp", "<f8", (4, 4)),  # true TCP pose in the base frame (true flange x the TCP offset)
        ("T_flange_tcp", "<f8", (4, 4)),  # TCP offset in force at that cycle
        ("T_base_tcp_model", "<f8", (4, 4)),  # the controller's belief: its model's TCP at the joints it commands
        ("digital_out", "<u8"),  # actual_digital_output_bits (bit 0-7 standard outputs)
        ("robot_mode", "<i4"),
        ("safety_mode", "<i4"),
        ("runtime_state", "<i4"),
        ("arc_on", "u1"),  # 1: a welding arc truly burns this cycle (the simulated power source's)
        ("weld_current", "<f4"),  # the arc's true current, A (0 without an arc or a source)
        ("wire_stuck", "u1"),  # 1: the simulated source's wire is stuck in the pool this cycle
    ]
)
# Records in the history ring: 1024 cycles = 2.048 s at 500 Hz.
HISTORY_CAPACITY = 1024
# How long :meth:`TruthReader.latest` reads again after torn reads, s (the simulator writes every 2 ms).
_LATEST_TIMEOUT = 0.5


class TruthSample(NamedTuple):
    """The true state of the arm at ``stamp_ns`` (time.monotonic_ns())."""

    stamp_ns: int
    T_base_tcp: NDArray[np.float64]  # (4, 4)
    q: NDArray[np.float64]  # (6,) rad
    qd: NDArray[np.float64]  # (6,) rad/s
    digital_out: int
    T_flange_tcp: NDArray[np.float64] = np.eye(4)  # (4, 4) the controller's TCP offset at that cycle
    arc_on: bool = False  # a welding arc truly burns
    weld_current: float = 0.0  # its true current, A

    @property
    def T_base_flange(self) -> NDArray[np.float64]:
        """The true flange pose (4, 4)."""
        return flange_of(self.T_base_tcp, self.T_flange_tcp)


def flange_of(T_base_tcp: NDArray[np.float64], T_flange_tcp: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_base_flange`` of TCP poses and TCP offsets, (4, 4) or (n, 4, 4) each."""
    R, t = T_flange_tcp[..., :3, :3], T_flange_tcp[..., :3, 3]
    inv = np.zeros(np.broadcast_shapes(T_flange_tcp.shape, (4, 4)))
    Rt = np.swapaxes(R, -1, -2)
    inv[..., :3, :3] = Rt
    inv[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    inv[..., 3, 3] = 1.0
    return T_base_tcp @ inv


def segment_names(host: str) -> tuple[str, str]:
    """Names of the latest-sample slot and the history ring of the simulator on ``host``."""
    tag = host.replace(".", "_")
    return f"celld_simrobot_{tag}", f"celld_simrobot_{tag}_hist"


class TruthPublisher:
    """Writer side, in the simulator: one record per cycle, no allocation per write."""

    def __init__(self, host: str) -> None:
        slot_name, ring_name = segment_names(host)
        self._slot = SeqlockSlot.create(slot_name, TRUTH_DTYPE)
        self._ring = Ring.create(ring_name, TRUTH_DTYPE, HISTORY_CAPACITY)
        self._rec = np.zeros(1, TRUTH_DTYPE)
        self._rec["T_base_tcp"][0] = np.eye(4)
        self._rec["T_flange_tcp"][0] = np.eye(4)
        self._rec["T_base_tcp_model"][0] = np.eye(4)
        r = self._rec[0]
        # Views into the one record, filled in place each cycle.
        self._q = r["q"]
        self._qd = r["qd"]
        self._T = r["T_base_tcp"][:3].reshape(12)
        self._T_ft = r["T_flange_tcp"][:3].reshape(12)
        self._T_model = r["T_base_tcp_model"][:3].reshape(12)

    def publish(
        self,
        stamp_ns: int,
        q: Sequence[float],
        qd: Sequence[float],
        T_base_tcp_rows: Sequence[float],
        T_base_tcp_model_rows: Sequence[float],
        T_flange_tcp_rows: Sequence[float],
        digital_out: int,
        modes: tuple[int, int, int],
        arc_on: bool = False,
        weld_current: float = 0.0,
        wire_stuck: bool = False,
    ) -> None:
        """One cycle's record: the physical joints, the true TCP and the controller's (its model's TCP at the joints
        it commands), the TCP offset, the outputs and modes, the arc as it truly burns."""
        r = self._rec
        r["stamp_ns"] = stamp_ns
        self._q[:] = q
        self._qd[:] = qd
        self._T[:] = T_base_tcp_rows
        self._T_ft[:] = T_flange_tcp_rows
        self._T_model[:] = T_base_tcp_model_rows
        r["digital_out"] = digital_out
        r["robot_mode"], r["safety_mode"], r["runtime_state"] = modes
        r["arc_on"] = arc_on
        r["weld_current"] = weld_current
        r["wire_stuck"] = wire_stuck
        self._slot.write(r[0])
        self._ring.append(r[0])

    def close(self) -> None:
        for seg in (self._slot, self._ring):
            seg.close()
            seg.unlink()


class TruthReader:
    """Reader side: the latest true state, and the state at any instant of the last ~2 s."""

    def __init__(self, host: str, timeout: float = 5.0) -> None:
        slot_name, ring_name = segment_names(host)
        deadline = time.monotonic() + timeout
        while True:
            try:
                self._slot = SeqlockSlot.attach(slot_name, TRUTH_DTYPE)
                self._ring = Ring.attach(ring_name, TRUTH_DTYPE, HISTORY_CAPACITY)
                break
            except FileNotFoundError as exc:
                if time.monotonic() > deadline:
                    raise RobotError(f"no simulated robot truth for {host}: segment {slot_name} absent") from exc
                time.sleep(0.05)

    def latest(self) -> TruthSample:
        """The most recent state; raises RobotError when the simulator has not written one yet.

        A torn read (the simulator wrote while it was copied, every try) is read
        again rather than answered with the slot's last whole copy, which may be
        arbitrarily old on a starved machine: a check of where the arm is now must
        not see where it was minutes ago.
        """
        deadline = time.monotonic() + _LATEST_TIMEOUT
        while True:
            rec, torn = self._slot.read()
            if rec is None:
                raise RobotError("the simulated robot has not published a state yet")
            if not torn:
                return _sample(rec)
            if time.monotonic() > deadline:
                raise RobotError(f"the simulated robot's state was torn on every read for {_LATEST_TIMEOUT:g} s")
            time.sleep(0.0005)

    def history(self) -> NDArray[np.void]:
        """The records of the last ~2 s, oldest first (``TRUTH_DTYPE``)."""
        return self._ring.latest(HISTORY_CAPACITY)

    def at(self, stamp_ns: int) -> TruthSample:
        """The state at ``stamp_ns``, interpolated between the two cycles around it.

        Position and joints are linear, orientation is a slerp. Raises InputError
        when ``stamp_ns`` lies outside the history (older than ~2 s or in the future
        beyond one cycle).
        """
        recs = self.history()
        if len(recs) == 0:
            raise RobotError("the simulated robot has not published a state yet")
        stamps = recs["stamp_ns"]
        if stamp_ns < stamps[0] or stamp_ns > stamps[-1] + 2_000_000:
            raise InputError(f"truth at {stamp_ns} ns: outside the history [{int(stamps[0])}, {int(stamps[-1])}] ns")
        i = int(np.searchsorted(stamps, stamp_ns, side="right"))
        if i >= len(recs):
            return _sample(recs[-1])
        a, b = recs[i - 1], recs[i]
        w = (stamp_ns - int(a["stamp_ns"])) / max(1, int(b["stamp_ns"]) - int(a["stamp_ns"]))
        from scipy.spatial.transform import Rotation, Slerp  # not at import: the simulator never needs it

        T = np.eye(4)
        T[:3, 3] = (1 - w) * a["T_base_tcp"][:3, 3] + w * b["T_base_tcp"][:3, 3]
        rots = Rotation.from_matrix(np.stack([a["T_base_tcp"][:3, :3], b["T_base_tcp"][:3, :3]]))
        T[:3, :3] = Slerp([0.0, 1.0], rots)([w]).as_matrix()[0]
        q = (1 - w) * a["q"] + w * b["q"]
        qd = (1 - w) * a["qd"] + w * b["qd"]
        return TruthSample(
            int(stamp_ns), T, q, qd, int(a["digital_out"]), np.array(a["T_flange_tcp"]), bool(a["arc_on"]), float(a["weld_current"])
        )

    def close(self) -> None:
        self._slot.close()
        self._ring.close()


def _sample(rec: np.void) -> TruthSample:
    return TruthSample(
        int(rec["stamp_ns"]),
        np.array(rec["T_base_tcp"]),
        np.array(rec["q"]),
        np.array(rec["qd"]),
        int(rec["digital_out"]),
        np.array(rec["T_flange_tcp"]),
        bool(rec["arc_on"]),
        float(rec["weld_current"]),
    )
