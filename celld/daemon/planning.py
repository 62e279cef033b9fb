"""Every move checked before the robot moves: reach, IK branch, singularities and collisions with the cell.

:class:`MotionPlanner` holds the collision checker of the cell
(:mod:`celld.robot.collision`) for the arm of ``robot.model``, the cell model
of ``[cell_model]`` and the TCP offset, twice: with the tool on the flange
(moves and welds) and without it (a calibration reads the bare flange, so
the tool is off). The daemon asks it

- before each Cartesian move (:meth:`check_move`) and joint move
  (:meth:`check_joint_move`);
- for a weld's whole path before the first move of the weld
  (:meth:`check_path`);
- for a calibration plan (:meth:`plan_calibration`): generated poses that
  would hit the cell or cannot be reached are replaced by others from the
  same box, and reported; poses a job gives are checked, and a refused one
  refuses the job before the robot moves.

A refusal raises :class:`~celld.errors.PathRefused` with the checker's
message: the pose, the reason, which link or tool part and which object, and
where along the path. The checks are pure and take tens of milliseconds per
move (bench/collision_check.py); the daemon runs them in a worker thread.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from celld import se3
from celld.config import Config
from celld.errors import PathRefused
from celld.robot import kinematics as kin
from celld.robot.cellmodel import Box
from celld.robot.collision import Checker, PathCheck, Refusal

Array = NDArray[np.float64]

# Rounds of replacement poses a calibration plan draws before it gives up.
_REPLACEMENT_ROUNDS = 6


@dataclass(frozen=True)
class CalibrationPlan:
    """The poses a calibration will visit, in order, with the joints at each, and what was refused on the way."""

    poses: tuple[Array, ...]  # (4, 4) flange poses, base frame
    q: tuple[tuple[float, ...], ...]  # the joints at each pose
    refused: tuple[Refusal, ...]  # candidates that were checked and left out, with why


class MotionPlanner:
    """The cell's collision and reach checks (module docstring)."""

    def __init__(self, config: Config) -> None:
        self.arm = kin.model(config.robot.model)
        T_flange_tcp = se3.from_ur_pose(config.robot.tcp_offset)
        self.with_tool = Checker(self.arm, config.cell_model, T_flange_tcp)
        self.bare = Checker(self.arm, config.cell_model.without_tool(), T_flange_tcp)

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

    def check_joint_move(self, q_start: Array, q_goal: Array, tool: bool = True) -> PathCheck:
        """A joint move, linear in joint space; raises PathRefused naming why."""
        return self._raise(self._checker(tool).check_joint_path(q_start, q_goal))

    def check_path(self, q_start: Array, T_base_tcp_path: Array, tool: bool = True) -> PathCheck:
        """Straight TCP moves through the poses (n, 4, 4) in order (a weld); raises PathRefused naming why."""
        return self._raise(self._checker(tool).check_waypoints(q_start, T_base_tcp_path))

    def plan_calibration(
        self,
        q_start: Array,
        candidates: Array,
        n: int,
        replacements: Callable[[int, int], Array] | None = None,
    ) -> CalibrationPlan:
        """The first ``n`` of ``candidates`` (k, 4, 4) the arm can visit in order without the tool, from ``q_start``.

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
        checker = self.bare
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


def record_plan(rec: Any, checker: Checker, joints: Sequence[Sequence[float]], name: str = "pose") -> None:
    """Draw a plan in a job recording: the cell's box objects and the arm with its tool at each joint vector.

    ``rec`` is a :class:`~celld.recording.job.JobRecording` (or None: nothing
    to do). Objects other than boxes are not drawn yet (the checks use them all).
    """
    if rec is None:
        return
    for obj in checker.cell.objects:
        if isinstance(obj.shape, Box):
            rec.log_boxes(obj.name, obj.T_base_obj[None], np.asarray(obj.shape.size)[None])
    for i, q in enumerate(joints):
        _, ends, radii = checker.segments(np.asarray(q, dtype=np.float64))
        rec.log_capsules(f"{name}_{i + 1:02d}", ends, radii)
