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
  with it.

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
from typing import cast

from celld.errors import ConfigError
from celld.robot import kinematics as kin
from celld.robot.kinematics import Rows

# Joint speeds below this (rad/s) count as "at rest" for the repeatability and the settling.
_REST_SPEED = 1e-6
# The settling transient is dropped after this many time constants (exp(-10) = 4.5e-5).
_SETTLE_SPAN = 10.0

_SOURCE = "sim robot truth"


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
    """

    dh: kin.DH = kin.UR10E
    joint_offsets: tuple[float, ...] = (0.0,) * 6
    encoder_noise: float = 0.0
    repeatability: float = 0.0
    settle_amplitude: float = 0.0
    settle_tau: float = 0.08
    settle_hz: float = 8.0
    seed: int = 0

    def __post_init__(self) -> None:
        d, a, alpha = (cast("tuple[float, float, float, float, float, float]", tuple(float(v) for v in row)) for row in self.dh)
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

    def is_model(self, nominal: kin.DH) -> bool:
        """True when the arm is exactly the controller's ``nominal`` model and nothing is noisy."""
        return (
            tuple(self.dh) == tuple(nominal)
            and not any(self.joint_offsets)
            and self.encoder_noise == 0.0
            and self.repeatability == 0.0
            and self.settle_amplitude == 0.0
        )

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
    :attr:`q` (physical joints), :attr:`T_flange` (true flange pose, 12
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
        off, rest, kick = tr.joint_offsets, self._rest, self._kick
        self.q = [q[j] + off[j] + rest[j] + kick[j] * f for j in range(6)]
        self.T_flange = kin.forward_rows(self.q, tr.dh)
        if tr.encoder_noise:
            self.q_reported = [v + gauss(0.0, tr.encoder_noise) for v in q]
        else:
            self.q_reported = list(q)
