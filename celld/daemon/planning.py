"""Every move checked before the robot moves: reach, IK branch, singularities and collisions with the cell.

:class:`MotionPlanner` holds the collision checker of the cell
(:mod:`celld.robot.collision`) for the arm of ``robot.model``, the cell model
of ``[cell_model]`` and the TCP offset, twice: with the tool on the flange
(moves and welds) and without it (a calibration reads the bare flange, so
the tool is off). The daemon asks it

- before each Cartesian move (:meth:`plan_move`: the straight line against
  the cell, and the speed scale that keeps every joint within
  ``max_joint_speed``, :func:`cartesian_move_scale`) and joint move
  (:meth:`plan_joint_move`: the line in joint space against the cell and the
  workspace box, and the speed scale that keeps the TCP within the
  Cartesian limits, :func:`joint_move_scale`);
- for a weld's whole path before the first move of the weld
  (:meth:`check_path`);
- for a calibration plan (:meth:`plan_calibration`): generated poses that
  would hit the cell or cannot be reached are replaced by others from the
  same box, and reported; poses a job gives are checked, and a refused one
  refuses the job before the robot moves.

In a cell with a second robot, a job that moves one robot while the other
waits checks the moving one against the waiting arm: :func:`arm_obstacles`
turns an arm at its joints into capsule objects of the other's base frame,
and :meth:`MotionPlanner.with_objects` adds them to the checks.

A refusal raises :class:`~celld.errors.PathRefused` with the checker's
message: the pose, the reason, which link or tool part and which object, and
where along the path. The checks are pure and take tens of milliseconds per
move (bench/collision_check.py); the daemon runs them in a worker thread.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from celld import schemadoc, se3
from celld.config import Config, MotionLimits
from celld.errors import PathRefused
from celld.log import get_logger
from celld.robot import kinematics as kin
from celld.robot.cellmodel import Box, CellObject, Rod
from celld.robot.collision import Checker, PathCheck, Refusal

if TYPE_CHECKING:
    from celld.recording.job import JobRecording

log = get_logger(__name__)

Array = NDArray[np.float64]

# A joint move shorter than this (rad, every joint) is no move: below the motion loop's arrival tolerance (5e-5 rad).
STILL = 1e-5
# Rounds of replacement poses a calibration plan draws before it gives up.
_REPLACEMENT_ROUNDS = 6


@dataclass(frozen=True)
class JointMovePlan:
    """A checked joint move: the TCP at the goal and the speed scale the move runs at."""

    T_base_tcp_goal: Array  # (4, 4)
    speed_scale: float  # the caller's, lowered so the TCP keeps the Cartesian limits
    tcp_speed: float  # the TCP's largest speed the move can reach at that scale, m/s (an upper bound)
    check: PathCheck


def joint_move_scale(
    Q: Array,
    s: Array,
    dh: kin.DH,
    T_flange_tcp: Array,
    limits: MotionLimits,
) -> tuple[float, float, float]:
    """The largest speed scale (<= 1) of a joint move that keeps the TCP within the Cartesian limits.

    The move runs on the line ``Q(s)`` (samples ``Q`` (n, 6) at ``s`` (n,) in
    [0, 1]) with every joint bounded by the joint limits; the synchronised
    planner lets the path parameter reach at most ``s' = v_j / max|dq|`` and
    ``s'' = a_j / max|dq|``, all scaled by the speed scale ``k``; on the unit
    path ``s'^2`` also stays below ``k s''`` (half the path to speed up, half
    to stop). The TCP's speed is then at most ``k s' max|dp/ds|`` and its
    acceleration at most ``k s'' max|dp/ds| + min(k^2 s'^2, k s'')
    max|d2p/ds2|`` <= ``k (...)`` for ``k <= 1``
    (the same for the rotation), which gives ``k``. The derivatives come from
    finite differences of the forward kinematics over the samples; the jerk
    is not bounded this way.

    Returns
    -------
    (scale, tcp_speed, tcp_angular_speed) : the scale, and the TCP's linear
    (m/s) and angular (rad/s) speed bounds at that scale.
    """
    span = float(np.abs(Q[-1] - Q[0]).max())
    if span <= STILL or len(s) < 2:
        # Already there (a joint move to where the arm stands): finite differences
        # of so short a line are rounding noise, which would scale the move to nothing.
        return 1.0, 0.0, 0.0
    T = np.array([kin.forward(q, dh, T_flange_tcp) for q in Q])
    ds = np.diff(s)
    dp = np.diff(T[:, :3, 3], axis=0)
    lin1 = np.linalg.norm(dp, axis=1) / ds
    # Rotation angle between neighbouring samples.
    R_rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    cos = np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang1 = np.arccos(cos) / ds
    lin2 = ang2 = np.zeros(1)
    if len(s) > 2:
        mid = 0.5 * (ds[1:] + ds[:-1])
        lin2 = np.abs(np.diff(lin1)) / mid
        ang2 = np.abs(np.diff(ang1)) / mid
    sd = limits.max_joint_speed / span
    sdd = limits.max_joint_accel / span
    # On the unit path s' cannot outgrow sqrt(s''): a short move is over before
    # it reaches the joint speed, so its centripetal term stays bounded.
    sd2 = min(sd * sd, sdd)
    L1, W1, L2, W2 = float(lin1.max()), float(ang1.max()), float(lin2.max()), float(ang2.max())
    k = min(
        1.0,
        limits.max_linear_speed / max(sd * L1, 1e-12),
        limits.max_angular_speed / max(sd * W1, 1e-12),
        limits.max_linear_accel / max(sdd * L1 + sd2 * L2, 1e-12),
        limits.max_angular_accel / max(sdd * W1 + sd2 * W2, 1e-12),
    )
    return k, k * sd * L1, k * sd * W1


def cartesian_move_scale(Q: Array, s: Array, T_start: Array, T_goal: Array, limits: MotionLimits) -> tuple[float, float]:
    """The largest speed scale (<= 1) of a straight TCP move that keeps every joint within ``max_joint_speed``.

    The move is straight in position and in rotation vector from ``T_start``
    to ``T_goal`` (4, 4), phase-synchronised (:mod:`celld.motion.controllers`):
    its path parameter runs at most at ``s' = min(v / |dp|, w / |dphi|)`` with
    the linear and angular speed limits, all scaled by ``k``. The joints on the
    line, ``Q(s)`` (samples ``Q`` (n, 6) at ``s`` (n,) in [0, 1], the collision
    check's), then turn at ``|dq/ds| k s'``; near a wrist singularity or over a
    large turn of the tool that exceeds what the robot's safety allows (its
    protective stop: measured, a UR10e's wrist 1 at 3.2 rad/s on a move at
    2 rad/s about the TCP), however well the TCP keeps its own limits. The
    joints' accelerations follow the TCP's and are not bounded here.

    Returns
    -------
    (scale, joint_speed) : the scale, and the fastest joint's speed bound at that scale (rad/s).
    """
    dp, dphi = se3.error(T_goal, T_start)
    if len(s) < 2 or (dp <= 1e-9 and dphi <= 1e-9):
        return 1.0, 0.0
    sd = min(limits.max_linear_speed / max(dp, 1e-12), limits.max_angular_speed / max(dphi, 1e-12))
    ds = np.diff(s)
    keep = ds > 0
    if not np.any(keep):
        return 1.0, 0.0
    rate = float((np.abs(np.diff(Q, axis=0))[keep] / ds[keep, None]).max()) * sd
    k = min(1.0, limits.max_joint_speed / max(rate, 1e-12))
    return k, k * rate


@dataclass(frozen=True)
class CartesianMovePlan:
    """A checked straight TCP move: the speed scale it runs at, and the check."""

    speed_scale: float  # the caller's, lowered so every joint keeps max_joint_speed
    joint_speed: float  # the fastest joint's speed bound at that scale, rad/s
    check: PathCheck


@dataclass(frozen=True)
class CalibrationPlan:
    """The poses a calibration will visit, in order, with the joints at each, and what was refused on the way."""

    poses: tuple[Array, ...]  # (4, 4) flange poses, base frame
    q: tuple[tuple[float, ...], ...]  # the joints at each pose
    refused: tuple[Refusal, ...]  # candidates that were checked and left out, with why

    def refused_entries(self) -> list[dict[str, Any]]:
        """What was refused on the way, as a dry run's plan lists it (:data:`REFUSED_SCHEMA`)."""
        return [{"pose": list(r.target), "reason": r.reason, "message": r.message} for r in self.refused]


# The JSON shape of CalibrationPlan.refused_entries.
REFUSED_SCHEMA = schemadoc.array(
    schemadoc.obj(
        "A candidate pose that was checked and left out.",
        {
            "pose": schemadoc.vector("The candidate TCP pose [x, y, z, rx, ry, rz], m and rad, base frame.", 6),
            "reason": schemadoc.string("Why, in a word."),
            "message": schemadoc.string("Why, in full: what it would hit, or why it is out of reach."),
        },
        ("pose", "reason", "message"),
    ),
    "Candidate poses checked and left out (each replaced by another), with why.",
)


class MotionPlanner:
    """The cell's collision and reach checks (module docstring)."""

    def __init__(self, config: Config, table: kin.DH | None = None) -> None:
        # The arm of robot.model, computed with its controller's own table where it is known.
        self.arm = kin.model(config.robot.model)
        if table is not None:
            self.arm = dataclasses.replace(self.arm, dh=table)
        self.limits = config.motion
        self.workspace = (np.asarray(config.robot.workspace_min), np.asarray(config.robot.workspace_max))
        T_flange_tcp = se3.from_ur_pose(config.robot.tcp_offset)
        self.T_flange_tcp = T_flange_tcp
        self.cell = config.cell_model  # the config's cell: what with_objects adds to
        self.with_tool = Checker(self.arm, config.cell_model, T_flange_tcp)
        self.bare = Checker(self.arm, config.cell_model.without_tool(), T_flange_tcp)

    def with_objects(self, objects: Sequence[CellObject]) -> MotionPlanner:
        """The same checks with ``objects`` added to the config's cell (another robot's arm where it waits);
        objects an earlier call added are not kept."""
        new = copy.copy(self)
        cell = self.cell
        for obj in objects:
            cell = cell.with_object(obj)
        new.with_tool = Checker(self.arm, cell, self.T_flange_tcp, self.with_tool.params)
        new.bare = Checker(self.arm, cell.without_tool(), self.T_flange_tcp, self.bare.params)
        return new

    def _checker(self, tool: bool) -> Checker:
        return self.with_tool if tool else self.bare

    @staticmethod
    def _raise(check: PathCheck) -> PathCheck:
        if check.refusal is not None:
            raise PathRefused(check.refusal.message)
        return check

    def check_move(self, q_start: Array, T_base_tcp_goal: Array, tool: bool = True) -> PathCheck:
        """A straight TCP move from the joints ``q_start``; raises PathRefused naming why."""
        return self._raise(self._checker(tool).check_cartesian_path(q_start, T_base_tcp_goal))

    def plan_move(self, q_start: Array, T_base_tcp_goal: Array, speed_scale: float = 1.0, tool: bool = True) -> CartesianMovePlan:
        """Check a straight TCP move and choose its speed scale (:func:`cartesian_move_scale`); raises
        PathRefused naming why."""
        check = self.check_move(q_start, T_base_tcp_goal, tool)
        T_flange_tcp = self.T_flange_tcp if tool else np.eye(4)
        T_start = kin.forward(np.asarray(q_start, dtype=np.float64), self.arm.dh, T_flange_tcp)
        k, w = cartesian_move_scale(check.q, check.s, T_start, np.asarray(T_base_tcp_goal, dtype=np.float64), self.limits)
        return CartesianMovePlan(speed_scale * k, w * speed_scale, check)

    def check_joint_move(self, q_start: Array, q_goal: Array, tool: bool = True) -> PathCheck:
        """A joint move, linear in joint space; raises PathRefused naming why."""
        return self._raise(self._checker(tool).check_joint_path(q_start, q_goal))

    def plan_joint_move(self, q_start: Array, q_goal: Array, speed_scale: float = 1.0, tool: bool = True) -> JointMovePlan:
        """Check a joint move and choose its speed scale (module docstring); raises PathRefused naming why.

        Besides the cell, every sample of the line keeps the TCP inside the
        workspace box of ``[robot]`` (the motion loop's stop on a breach would
        come too late for a move that plainly leaves it).
        """
        check = self.check_joint_move(q_start, q_goal, tool)
        T_flange_tcp = self.T_flange_tcp if tool else np.eye(4)
        lo, hi = self.workspace
        # The collision samples are as dense as the arm's spheres need; the
        # box and the speed bound take at least 64.
        q0, q1 = np.asarray(q_start, dtype=np.float64), np.asarray(q_goal, dtype=np.float64)
        s_all: Array = np.linspace(0.0, 1.0, max(64, len(check.s)), dtype=np.float64)
        Q = q0 + s_all[:, None] * (q1 - q0)
        for q, si in zip(Q, s_all, strict=True):
            p = kin.forward(q, self.arm.dh, T_flange_tcp)[:3, 3]
            if np.any(p < lo) or np.any(p > hi):
                goal = "[" + ", ".join(f"{v:.3f}" for v in q1) + "]"
                raise PathRefused(
                    f"joint move to {goal}: the TCP leaves the workspace box {lo.tolist()} .. {hi.tolist()} m "
                    f"at {si:.0%} of the move, at {np.round(p, 3).tolist()} m"
                )
        k, v, _ = joint_move_scale(Q, s_all, self.arm.dh, T_flange_tcp, self.limits)
        scale = speed_scale * k
        T_goal = kin.forward(q_goal, self.arm.dh, T_flange_tcp)
        return JointMovePlan(T_goal, scale, v * speed_scale, check)

    def check_path(self, q_start: Array, T_base_tcp_path: Array, tool: bool = True) -> PathCheck:
        """Straight TCP moves through the poses (n, 4, 4) in order (a weld); raises PathRefused naming why."""
        return self._raise(self._checker(tool).check_waypoints(q_start, T_base_tcp_path))

    def plan_calibration(
        self,
        q_start: Array,
        candidates: Array,
        n: int,
        replacements: Callable[[int, int], Array] | None = None,
        tool: bool = False,
    ) -> CalibrationPlan:
        """The first ``n`` of ``candidates`` (k, 4, 4) the arm can visit in order without the tool (with it:
        ``tool``, a tool calibration), from ``q_start``.

        Refused candidates are skipped and kept with their reason; when fewer
        than ``n`` pass and ``replacements(count, round)`` is given, it draws
        more candidates (about twice the shortfall each round). Given poses
        (no ``replacements``) must all pass: a refused one raises PathRefused,
        before the robot moves.

        Raises
        ------
        PathRefused
            A given pose is refused, or not enough poses pass after the
            replacement rounds (the message lists the first refusals).
        """
        checker = self._checker(tool)
        poses: list[Array] = []
        joints: list[tuple[float, ...]] = []
        refused: list[Refusal] = []
        q = np.asarray(q_start, dtype=np.float64)
        batch = np.asarray(candidates, dtype=np.float64)
        for rnd in range(_REPLACEMENT_ROUNDS + 1):
            plan = checker.check_plan(q, batch)
            for pc in plan.poses:
                if len(poses) == n:
                    break
                if pc.refusal is not None or pc.q is None:
                    if pc.refusal is not None:
                        refused.append(pc.refusal)
                    if replacements is None:
                        raise PathRefused(f"calibration pose {pc.index + 1} of {len(batch)}: {pc.refusal}")
                    continue
                poses.append(batch[pc.index])
                joints.append(pc.q)
                q = np.asarray(pc.q)
            if len(poses) == n or replacements is None:
                break
            if rnd == _REPLACEMENT_ROUNDS:
                break
            batch = np.asarray(replacements(2 * (n - len(poses)), rnd), dtype=np.float64)
        if len(poses) < n:
            first = "; ".join(r.message for r in refused[:3])
            raise PathRefused(f"only {len(poses)} of {n} calibration poses can be reached without touching the cell: {first}")
        return CalibrationPlan(tuple(poses), tuple(joints), tuple(refused))


def report_plan(ctx: Any, plan: CalibrationPlan, what: str) -> None:
    """Log each refused pose of a generated plan and publish the plan's progress event (``ctx`` a JobContext)."""
    for r in plan.refused:
        log.warning("pose_replaced", job=ctx.job_id, plan=what, reason=r.message)
    ctx.progress(
        "plan",
        0.0,
        f"{len(plan.poses)} poses planned, {len(plan.refused)} replaced (they would hit the cell or are out of reach)",
        replaced=[r.message for r in plan.refused],
    )


def record_plan(rec: JobRecording | None, checker: Checker, joints: Sequence[Sequence[float]], name: str = "pose") -> None:
    """Draw a plan in a job recording: the cell's box objects and the arm with its tool at each joint vector.

    ``rec`` is a :class:`~celld.recording.job.JobRecording` (or None: nothing
    to do). Objects other than boxes are not drawn yet (the checks use them all).
    """
    if rec is None:
        return
    record_cell(rec, checker)
    for i, q in enumerate(joints):
        _, ends, radii = checker.segments(np.asarray(q, dtype=np.float64))
        rec.log_capsules(f"{name}_{i + 1:02d}", ends, radii)


def record_cell(rec: JobRecording | None, checker: Checker) -> None:
    """Draw the cell model's box objects, and another robot's waiting arm, in a job recording (``rec`` None: nothing to do)."""
    if rec is None:
        return
    for obj in checker.cell.objects:
        if isinstance(obj.shape, Box):
            rec.log_boxes(obj.name, obj.T_base_obj[None], np.asarray(obj.shape.size)[None])
        elif isinstance(obj.shape, Rod):  # another robot's arm where it waits
            half = se3.apply(obj.T_base_obj, np.array([[0.0, 0.0, -0.5], [0.0, 0.0, 0.5]]) * obj.shape.length)
            rec.log_capsules(obj.name, half[None], [obj.shape.radius])


def record_arm(rec: JobRecording | None, checker: Checker, q: Sequence[float] | np.ndarray, stamp_ns: int | None = None) -> None:
    """Draw the arm (and the checker's tool) at joints ``q`` as ``/world/robot/arm`` at a time: the arm as it moved."""
    if rec is None:
        return
    _, ends, radii = checker.segments(np.asarray(q, dtype=np.float64))
    rec.log_capsules("arm", ends, radii, stamp_ns=stamp_ns)


# What another robot's arm keeps from this one's on top of the cell's margin, m: its base is placed by
# its drawing, which may be off by millimetres (a robot-robot calibration measures how far).
ARM_CLEARANCE = 0.02


def arm_obstacles(checker: Checker, q: Sequence[float] | Array, T_here_there: Array, prefix: str) -> tuple[CellObject, ...]:
    """Another robot's arm at its joints ``q`` as capsule objects of this robot's base frame.

    ``checker`` is the other robot's (its arm's capsules, without its tool),
    ``T_here_there`` its base in this robot's base frame; every capsule is
    swollen by :data:`ARM_CLEARANCE` and named ``<prefix>-<link>``.
    """
    names, ends, radii = checker.segments(q)
    T = se3.check_transform(T_here_there, "T_here_there")
    objects = []
    for name, (p0, p1), r in zip(names, ends, radii, strict=True):
        a, b = se3.apply(T, np.array([p0, p1]))
        axis = b - a
        length = float(np.linalg.norm(axis))
        frame = se3.frame_from_z((a + b) / 2, axis if length > 1e-9 else [0.0, 0.0, 1.0])
        objects.append(CellObject(f"{prefix}-{name}", Rod(float(r) + ARM_CLEARANCE, length), frame))
    return tuple(objects)
