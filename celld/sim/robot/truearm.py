"""The physical arm behind the simulated controller: where its flange truly is (pure, plain floats).

A UR controller believes its kinematic model: it reports, and moves by, the
forward and inverse kinematics of its (factory-calibrated) DH table. The arm
itself is not that model. :class:`ArmTruth` is how the simulated arm differs
from the controller's belief, drawn by :mod:`celld.sim.world`:

- a true DH table and true joint zeros (the controller's nominal table with
  perturbed lengths, twists and joint offsets): a pose-dependent absolute
  error of the flange;
- repeatability: each time the arm comes to rest it rests a little off,
  a joint offset drawn anew at every stop (backlash, friction), which stays
  until the next stop;
- settling: when a motion ends the arm rings down for a moment, a damped
  oscillation in joint space that starts from the previous rest error;
- encoder noise: the joints the controller *reports* (RTDE ``actual_q`` and
  the TCP pose computed from them) carry white noise; the arm does not move
  with it;
- compliance: each joint yields by its compliance times the torque gravity
  (the arm's true links and the tool's true mass) and the hose package's
  pull on the torch put on it (:mod:`celld.robot.dynamics`): a sag that
  depends on the pose;
- thermal growth: the links lengthen with the arm's temperature, which rises
  from cold towards its warm value while the controller runs;
- lost motion: each joint rests half its lost motion behind where it was
  sent, on the side it came from.

:class:`TrueArm` runs in the simulated controller's 500 Hz cycle: given the
joints the controller commands (its belief), it returns the physical joints
and the true flange pose, and the noisy joints the controller reports. Plain
floats and :mod:`random` (no numpy per cycle), seeded, so a world replays.
With :data:`IDEAL` (no error at all) the physical arm is the controller's
model exactly, as it was before the simulator owned a world.
"""

from __future__ import annotations

import json
import math
import random
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from celld.errors import ConfigError
from celld.robot import dynamics
from celld.robot import kinematics as kin
from celld.robot.kinematics import Rows

# Joint speeds below this (rad/s) count as "at rest" for the repeatability and the settling.
_REST_SPEED = 1e-6
# The settling transient is dropped after this many time constants (exp(-10) = 4.5e-5).
_SETTLE_SPAN = 10.0

_SOURCE = "sim robot truth"

# The joints' sag changes slowly with the pose: it is worked out again every this many cycles (50 Hz at 500 Hz).
_SAG_EVERY = 10

# Linear expansion of the links (aluminium), 1/K.
ALUMINIUM = 23e-6


@dataclass(frozen=True)
class ArmTruth:
    """How the physical arm differs from the controller's model (SI units, rad).

    Attributes
    ----------
    dh : kinematics.DH
        The arm's true DH table (the controller keeps its nominal one).
    joint_offsets : 6 floats
        True joint angle minus the encoder's reading at the same pose, rad.
    encoder_noise : float
        1 sigma of the white noise on the reported joints, rad.
    repeatability : float
        1 sigma of each joint's rest error, drawn anew at each stop, rad.
    settle_amplitude : float
        1 sigma of each joint's kick when a motion ends, rad; the transient
        ``e(t) = e0 exp(-t / settle_tau) cos(2 pi settle_hz t)``.
    settle_tau, settle_hz : float
        Decay time (s) and frequency (Hz) of the settling transient.
    seed : int
        Seed of the repeatability, settling and encoder noise.
    compliance : 6 floats
        Each joint's compliance, rad/(N m); 0 is rigid.
    link_mass, link_com : 6 floats, 6 triples
        The true links (kg; m in the DH frame after each joint).
    payload_mass, payload_com : float, 3 floats
        The true tool on the flange (kg; m in the flange frame).
    hose_force : 3 floats
        The hose package's pull on the tool, N in the base frame, acting at
        ``hose_point`` (m, flange frame).
    warm_rise : float
        The arm's temperature rise from cold to warm, K; the links grow by
        ``expansion`` per kelvin.
    warmup_tau : float
        Time constant of the warm-up while the controller runs, s.
    lost_motion : 6 floats
        Each joint's lost motion (full width), rad.
    """

    dh: kin.DH = kin.UR10E
    joint_offsets: tuple[float, ...] = (0.0,) * 6
    encoder_noise: float = 0.0
    repeatability: float = 0.0
    settle_amplitude: float = 0.0
    settle_tau: float = 0.08
    settle_hz: float = 8.0
    seed: int = 0
    compliance: tuple[float, ...] = (0.0,) * 6
    link_mass: tuple[float, ...] = (0.0,) * 6
    link_com: tuple[tuple[float, ...], ...] = ((0.0, 0.0, 0.0),) * 6
    payload_mass: float = 0.0
    payload_com: tuple[float, ...] = (0.0, 0.0, 0.0)
    hose_force: tuple[float, ...] = (0.0, 0.0, 0.0)
    hose_point: tuple[float, ...] = (0.0, 0.0, 0.0)
    warm_rise: float = 0.0
    warmup_tau: float = 1800.0
    expansion: float = ALUMINIUM
    lost_motion: tuple[float, ...] = (0.0,) * 6

    def __post_init__(self) -> None:
        if len(self.dh) > 3 and any(self.dh[3]):
            raise ConfigError(_SOURCE, "dh", "expected a table without joint zeros (the arm's are its joint_offsets)")
        d, a, alpha = (cast("tuple[float, float, float, float, float, float]", tuple(float(v) for v in row)) for row in self.dh[:3])
        dh = kin.DH(d, a, alpha)
        object.__setattr__(self, "dh", dh)
        object.__setattr__(self, "joint_offsets", tuple(float(v) for v in self.joint_offsets))
        if any(len(row) != 6 for row in dh) or len(self.joint_offsets) != 6:
            raise ConfigError(_SOURCE, "dh", "expected a DH table of 6 joints and 6 joint offsets")
        values = [*dh.d, *dh.a, *dh.alpha, *self.joint_offsets]
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(_SOURCE, "dh", f"expected finite numbers, got {values}")
        for name in ("encoder_noise", "repeatability", "settle_amplitude"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 <= v <= 0.01):
                raise ConfigError(_SOURCE, name, f"expected 0 <= value <= 0.01 rad, got {v!r}")
        if not (0.0 < self.settle_tau <= 10.0 and 0.0 <= self.settle_hz <= 1000.0):
            raise ConfigError(
                _SOURCE, "settle_tau", f"expected 0 < tau <= 10 s and 0 <= f <= 1000 Hz, got {self.settle_tau}, {self.settle_hz}"
            )
        vectors = {
            "compliance": (6, 0.0, 1e-3),
            "link_mass": (6, 0.0, 100.0),
            "payload_com": (3, -1.0, 1.0),
            "hose_force": (3, -100.0, 100.0),
            "hose_point": (3, -1.0, 1.0),
            "lost_motion": (6, 0.0, 0.01),
        }
        for name, (size, lo, hi) in vectors.items():
            v = tuple(float(x) for x in getattr(self, name))
            if len(v) != size or not all(math.isfinite(x) and lo <= x <= hi for x in v):
                raise ConfigError(_SOURCE, name, f"expected {size} numbers within [{lo:g}, {hi:g}], got {v}")
            object.__setattr__(self, name, v)
        com = tuple(tuple(float(x) for x in c) for c in self.link_com)
        if len(com) != 6 or any(len(c) != 3 or not all(math.isfinite(x) and abs(x) <= 1.0 for x in c) for c in com):
            raise ConfigError(_SOURCE, "link_com", f"expected 6 centres of mass within 1 m, got {com}")
        object.__setattr__(self, "link_com", com)
        scalars = {"payload_mass": (0.0, 100.0), "warm_rise": (0.0, 50.0), "warmup_tau": (1.0, 1e6), "expansion": (0.0, 1e-4)}
        for name, (lo, hi) in scalars.items():
            x = float(getattr(self, name))
            if not (math.isfinite(x) and lo <= x <= hi):
                raise ConfigError(_SOURCE, name, f"expected {lo:g} <= value <= {hi:g}, got {x!r}")
            object.__setattr__(self, name, x)

    def is_model(self, nominal: kin.DH) -> bool:
        """True when the arm is exactly the controller's ``nominal`` model and nothing is noisy."""
        return (
            (self.dh.d, self.dh.a, self.dh.alpha) == (nominal.d, nominal.a, nominal.alpha)
            and tuple(self.joint_offsets) == tuple(nominal.theta)
            and self.encoder_noise == 0.0
            and self.repeatability == 0.0
            and self.settle_amplitude == 0.0
            and not self.bends
            and self.warm_rise == 0.0
            and not any(self.lost_motion)
        )

    @property
    def bends(self) -> bool:
        """True when the joints yield under load."""
        return any(self.compliance)

    def temperature_rise(self, t: float) -> float:
        """The arm's temperature above cold after running ``t`` s, K."""
        return self.warm_rise * (1.0 - math.exp(-max(t, 0.0) / self.warmup_tau)) if self.warm_rise else 0.0

    def dh_at(self, rise: float) -> kin.DH:
        """The true DH table with the links grown by ``rise`` K."""
        if not rise:
            return self.dh
        k = 1.0 + self.expansion * rise
        d, a, alpha = self.dh.d, self.dh.a, self.dh.alpha
        return kin.DH(tuple(v * k for v in d), tuple(v * k for v in a), alpha)  # type: ignore[arg-type]

    @cached_property
    def _loads(self) -> tuple[dynamics.Links, dynamics.Payload]:
        return (
            dynamics.Links(self.link_mass, self.link_com),  # type: ignore[arg-type]
            dynamics.Payload(self.payload_mass, self.payload_com),  # type: ignore[arg-type]
        )

    def sag(self, q: Sequence[float], dh: kin.DH | None = None) -> list[float]:
        """How far each joint yields at the physical joints ``q`` (rad): compliance times the load's torque."""
        if not self.bends:
            return [0.0] * 6
        frames = np.asarray(kin.forward_all_rows(q, self.dh if dh is None else dh)).reshape(1, 6, 3, 4)
        tau = dynamics.joint_torques(frames, *self._loads, self.hose_force, self.hose_point)[0]
        return [float(c * t) for c, t in zip(self.compliance, tau)]

    def lag(self, direction: Sequence[float]) -> list[float]:
        """Each joint's lost motion (rad) when it came the way of ``direction``'s sign (0: from neither side)."""
        return [-0.5 * b * (1.0 if s > 0 else -1.0 if s < 0 else 0.0) for b, s in zip(self.lost_motion, direction)]

    def physical(self, q: ArrayLike, direction: ArrayLike | None = None, rise: float = 0.0) -> tuple[list[float], kin.DH]:
        """The physical joints (the sag under load included) and the DH table with the controller at ``q``, at rest.

        ``direction``: how each joint came there (its sign; None or 0: the
        lost motion's middle); ``rise``: the arm's temperature above cold, K.
        The repeatability, settling and encoder noise are not in it.
        """
        dh = self.dh_at(rise)
        lag = self.lag(np.asarray(direction, dtype=np.float64).tolist()) if direction is not None else [0.0] * 6
        q_cmd = np.asarray(q, dtype=np.float64).tolist()
        q_joint = [q_cmd[j] + self.joint_offsets[j] + lag[j] for j in range(6)]
        sag = self.sag(q_joint, dh)
        return [v + s for v, s in zip(q_joint, sag)], dh

    def flange(self, q: ArrayLike, direction: ArrayLike | None = None, rise: float = 0.0) -> np.ndarray:
        """Where the flange truly is (4, 4) with the controller at joints ``q``, at rest (:meth:`physical`)."""
        return kin.forward(*self.physical(q, direction, rise))

    def to_json(self) -> str:
        """One line of JSON that :meth:`from_json` reads back exactly (floats as repr)."""
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> ArmTruth:
        try:
            data = json.loads(text)
            data["dh"] = kin.DH(*data["dh"])
            return cls(**data)
        except (ValueError, TypeError, KeyError) as exc:
            raise ConfigError(_SOURCE, "arm_truth", f"expected the JSON of an ArmTruth, got {text[:80]!r}: {exc}") from exc


class TrueArm:
    """The physical arm's state in the simulated controller's cycle.

    Call :meth:`update` once per cycle with the controller's joints; read
    :attr:`q` (physical joints, the sag under load included), :attr:`T_flange` (true flange pose, 12
    row-major floats) and :attr:`q_reported` (the encoder reading the
    controller reports).
    """

    def __init__(self, truth: ArmTruth) -> None:
        self.truth = truth
        self._rng = random.Random(truth.seed)
        self._rest = [0.0] * 6  # the current rest error (repeatability)
        self._kick = [0.0] * 6  # amplitude of the settling transient
        self._t_stop = -math.inf
        self._moving = False
        self._came = [0.0] * 6  # the sign of each joint's last motion (lost motion)
        self._lag = [0.0] * 6  # the lost motion that follows from it
        self._sag = [0.0] * 6
        self._cycle = 0
        self._lags = any(truth.lost_motion)
        self._dh = truth.dh
        self.temperature_rise = 0.0
        self.q: list[float] = [0.0] * 6
        self.q_reported: list[float] = [0.0] * 6
        self.T_flange: Rows = kin.forward_rows(self.q, truth.dh)

    def update(self, q: Sequence[float], qd: Sequence[float], t: float) -> None:
        """The arm at controller time ``t`` (s) with commanded joints ``q`` and speeds ``qd``."""
        tr = self.truth
        gauss = self._rng.gauss
        moving = any(abs(v) > _REST_SPEED for v in qd)
        if self._moving and not moving:
            # A stop: the arm comes to rest at a new rest error, ringing down from the old one.
            rest = [gauss(0.0, tr.repeatability) if tr.repeatability else 0.0 for _ in range(6)]
            kick = [gauss(0.0, tr.settle_amplitude) if tr.settle_amplitude else 0.0 for _ in range(6)]
            self._kick = [self._rest[j] - rest[j] + kick[j] for j in range(6)]
            self._rest = rest
            self._t_stop = t
        self._moving = moving
        dt = t - self._t_stop
        f = 0.0
        if 0.0 <= dt < _SETTLE_SPAN * tr.settle_tau:
            f = math.exp(-dt / tr.settle_tau) * math.cos(2.0 * math.pi * tr.settle_hz * dt)
        if moving and self._lags:
            came = [(1.0 if v > 0 else -1.0) if abs(v) > _REST_SPEED else c for v, c in zip(qd, self._came)]
            if came != self._came:
                self._came, self._lag = came, tr.lag(came)
        lag = self._lag
        off, rest, kick = tr.joint_offsets, self._rest, self._kick
        q_joint = [q[j] + off[j] + lag[j] + rest[j] + kick[j] * f for j in range(6)]
        if self._cycle % _SAG_EVERY == 0:
            self.temperature_rise = tr.temperature_rise(t)
            self._dh = tr.dh_at(self.temperature_rise)
            self._sag = tr.sag(q_joint, self._dh)
        self._cycle += 1
        self.q = [v + s for v, s in zip(q_joint, self._sag)]
        self.T_flange = kin.forward_rows(self.q, self._dh)
        if tr.encoder_noise:
            self.q_reported = [v + gauss(0.0, tr.encoder_noise) for v in q]
        else:
            self.q_reported = list(q)
