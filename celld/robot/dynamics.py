"""What gravity and outside forces do to a UR arm's joints: static torques about each joint axis (pure).

An arm's joints are not rigid: under the torque gravity (its own links and
the payload) and outside forces (a hose package pulling on the tool) put on
them, each joint yields a little, ``dq_j = c_j tau_j`` with ``c_j`` its
compliance (rad/N m). :func:`joint_torques` gives those torques for a batch of
poses from the frames :func:`celld.robot.kinematics.forward_all_rows` returns;
the simulated arm bends by them (:mod:`celld.sim.robot.truearm`) and the arm's
kinematic calibration models them (:mod:`celld.calib.kinematic`), each with its
own masses: the world draws the true ones, the calibration takes the
published links and the configured payload.

Link masses and centres of mass: Universal Robots, "DH parameters for
calculations of kinematics and dynamics" (each link's centre of mass in the
DH frame after its joint). Models the page gives no dynamics for have none
here (:func:`links` returns None).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld.robot import kinematics as kin

Array = NDArray[np.float64]

GRAVITY = 9.81  # m/s^2, along -z of the base (a base on the floor)


class Links(NamedTuple):
    """The six moving links of an arm: mass (kg) and centre of mass in the DH frame after each joint (m)."""

    mass: tuple[float, float, float, float, float, float]
    com: tuple[tuple[float, float, float], ...]


class Payload(NamedTuple):
    """What the flange carries: mass (kg) and centre of mass in the flange frame (m)."""

    mass: float = 0.0
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)


LINKS: dict[str, Links] = {
    "ur3e": Links(
        (1.98, 3.4445, 1.437, 0.871, 0.805, 0.261),
        ((0.0, -0.02, 0.0), (0.13, 0.0, 0.1157), (0.05, 0.0, 0.0238), (0.0, 0.0, 0.01), (0.0, 0.0, 0.01), (0.0, 0.0, -0.02)),
    ),
    "ur5e": Links(
        (3.761, 8.058, 2.846, 1.37, 1.3, 0.365),
        (
            (0.0, -0.02561, 0.00193),
            (0.2125, 0.0, 0.11336),
            (0.15, 0.0, 0.0265),
            (0.0, -0.0018, 0.01634),
            (0.0, 0.0018, 0.01634),
            (0.0, 0.0, -0.001159),
        ),
    ),
    "ur10e": Links(
        (7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
        ((0.021, 0.0, 0.027), (0.38, 0.0, 0.158), (0.24, 0.0, 0.068), (0.0, 0.007, 0.018), (0.0, 0.007, 0.018), (0.0, 0.0, -0.026)),
    ),
}


def links(model: str) -> Links | None:
    """The published links of a UR model, or None when UR publishes none for it."""
    return LINKS.get(model)


def joint_torques(
    frames: ArrayLike,
    arm: Links | None,
    payload: Payload = Payload(),
    force: ArrayLike | None = None,
    force_point: ArrayLike | None = None,
    gravity: float = GRAVITY,
) -> Array:
    """Static torque (n, 6) that gravity and an outside force put on each joint, about its axis (N m).

    ``frames`` (n, 6, 3, 4) are ``T_base_1..T_base_6``; ``arm`` the links (None:
    massless links, the payload alone); ``force`` (3,) a force in the base
    frame (N) acting at ``force_point`` (3,), a point in the flange frame (m).
    A positive torque turns its joint the positive way: a compliant joint
    yields by ``compliance * torque``.
    """
    F = np.asarray(frames, dtype=np.float64)
    F, z, o = kin.joint_axes(F[None] if F.ndim == 3 else F)
    R, t = F[..., :3], F[..., 3]  # (n, 6, 3, 3), (n, 6, 3)
    # Every mass as a point in the base frame, and the last joint it sits beyond: link k (frame k)
    # beyond joint k, the payload (the flange frame) beyond all six.
    com = np.zeros((6, 3)) if arm is None else np.asarray(arm.com, dtype=np.float64)
    mass = np.zeros(6) if arm is None else np.asarray(arm.mass, dtype=np.float64)
    P = np.einsum("nkij,kj->nki", R, com) + t  # (n, 6, 3)
    P = np.concatenate([P, (np.einsum("nij,j->ni", R[:, 5], np.asarray(payload.com, dtype=np.float64)) + t[:, 5])[:, None]], axis=1)
    w = np.append(mass, payload.mass)
    owner = np.append(np.arange(6), 5)
    beyond = (owner[:, None] >= np.arange(6)[None, :]) * w[:, None]  # (7, 6): mass m's weight on joint j
    # tau_j = z_j . sum_m (p_m - o_j) x (w_m g): the first moment of the masses beyond joint j about o_j.
    moment = np.einsum("mj,nmi->nji", beyond, P) - beyond.sum(axis=0)[None, :, None] * o
    tau = np.einsum("nji,nji->nj", z, np.cross(moment, [0.0, 0.0, -gravity]))
    if force is not None:
        # A force at a point loads the joints by the transpose of that point's Jacobian.
        p_local = np.zeros(3) if force_point is None else np.asarray(force_point, dtype=np.float64).reshape(3)
        J = kin.jacobian_from_frames(F, np.einsum("nij,j->ni", R[:, 5], p_local) + t[:, 5])
        tau += np.einsum("nij,i->nj", J[:, :3, :], np.asarray(force, dtype=np.float64).reshape(3))
    return tau
