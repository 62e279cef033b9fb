"""Scoring a simulated cell's jobs against its world: where things truly went.

Only the demo, the tests and the benchmarks call this, after the jobs have
ended (the truth recorder gathers the arm's true states while a job runs and
is read afterwards); the daemon never sees the world.

- :func:`targeting_errors`: the calibration as a cell uses it. For a true
  point ``p`` the scanner sees (at ``measure(p_cam)``), the daemon sends the
  flange to ``T_base_cam_est @ p_cam`` through the controller's nominal
  inverse kinematics; the flange lands at the arm's true forward kinematics of
  those joints. The error is the distance from ``p`` (no robot motion needed).
- :func:`open_loop_torch`: where the torch would go if the robot followed the
  weld plan from the scan without the tactile correction: the plan's torch
  line, the nominal tool, nominal IK, the true arm and the true tool.
- :class:`TruthRecorder` and :func:`true_torch_path`: the torch as it truly
  went during a weld (the true flange x the true torch point).
- :func:`arc_figures`: the arc as it truly burned during a weld (the
  simulated power source's truth): how far the torch went with it and how
  far without it between the first strike and the last arc-off, the arc
  time, the strikes and the mean current;
- :func:`lateral`: a path's lateral distance from the part's true seam in the
  welding plane (RMS and max, mm; :func:`celld.seam.figures.lateral_error`).
- :func:`after_fault`: what the true arm and the arc output did after a fault
  (a process killed): the arc off, the arm stopped, how far it went.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld import polyline, se3
from celld.calib.kinematic import ArmModel
from celld.config import ToolConfig
from celld.errors import InputError
from celld.log import read_events
from celld.robot import kinematics as kin
from celld.seam.figures import TORCH_STEP, height_over_root, lateral_error
from celld.sim.robot.truth import TRUTH_DTYPE, TruthReader, flange_of
from celld.sim.world import World
from celld.tactile.tool import ToolGeometry

Array = NDArray[np.float64]


def true_flange(world: World, T_base_flange_cmd: ArrayLike, q_near: ArrayLike, rise: float = 0.0) -> tuple[Array, Array] | None:
    """Where the flange truly is when the controller puts it at ``T_base_flange_cmd`` (its belief).

    Returns ``(T_base_flange_true (4, 4), q (6,))`` with ``q`` the controller's
    joints (nominal IK nearest ``q_near``, which the arm comes from), or None
    when the pose is out of reach. ``rise``: the arm's temperature above cold, K.
    """
    q = kin.inverse(np.asarray(T_base_flange_cmd, dtype=np.float64), q_near, world.nominal_dh)
    if q is None:
        return None
    return world.arm.flange(q, q - np.asarray(q_near, dtype=np.float64), rise), q


def true_camera(world: World, q: ArrayLike) -> Array:
    """Where the world's scanner truly is (4, 4) with the controller's joints ``q``: where it is fixed, or
    where the arm's true kinematics put its link."""
    sc = world.scanner
    if not sc.link:
        return sc.T_base_cam
    q_phys, dh = world.arm.physical(np.asarray(q, dtype=np.float64))
    return sc.T_base_cam_at(np.asarray(q_phys), dh)


def measured_in_camera(world: World, P_base: ArrayLike, metal: bool = True, T_base_cam: ArrayLike | None = None) -> Array:
    """Where the world's scanner measures true base points (n, 3), in its camera frame (no noise).

    ``T_base_cam`` is the scanner's true pose (default: where it is fixed;
    a scanner on the arm needs it, where the arm holds it).
    """
    from celld.sim.scanner import scanner_model

    sc = world.scanner
    T = sc.T_base_cam if T_base_cam is None else np.asarray(T_base_cam, dtype=np.float64)
    P_cam = se3.apply(se3.invert(T), np.asarray(P_base, dtype=np.float64).reshape(-1, 3))
    M = sc.measure(P_cam)
    bias = sc.metal_bias if sc.metal_bias is not None else scanner_model(sc.model).metal_bias
    if metal and bias:
        M = M * (1.0 + bias / np.linalg.norm(P_cam, axis=1))[:, None]
    return M


def targeting_errors(
    world: World,
    T_base_cam_est: ArrayLike,
    P_base: ArrayLike,
    R_base_flange: ArrayLike,
    q_near: ArrayLike,
    T_base_cam_true: ArrayLike | None = None,
    arm: ArmModel | None = None,
    rise: float = 0.0,
) -> Array:
    """Distances (n,) between true points and where the flange lands when sent to them through the calibration, m.

    ``R_base_flange`` (3, 3) is the flange's orientation for every target;
    points out of reach give NaN. ``T_base_cam_true`` is where the scanner
    truly is when it sees them (default: where it is fixed). ``arm``: the
    arm's calibrated model, through which each target is pre-corrected
    (None: the controller is sent the target as it is); ``rise``: the arm's
    temperature above cold, K.
    """
    P = np.asarray(P_base, dtype=np.float64).reshape(-1, 3)
    targets = se3.apply(np.asarray(T_base_cam_est, dtype=np.float64), measured_in_camera(world, P, T_base_cam=T_base_cam_true))
    out = np.full(len(P), np.nan)
    q = np.asarray(q_near, dtype=np.float64)
    for i, (p, t) in enumerate(zip(P, targets)):
        T_cmd = se3.transform_from(R_base_flange, t)
        if arm is not None:
            pre = arm.precorrect(T_cmd, q)
            if pre is None:
                continue
            T_cmd = pre[0]
        got = true_flange(world, T_cmd, q, rise)
        if got is not None:
            out[i] = float(np.linalg.norm(got[0][:3, 3] - p))
            q = got[1]
    return out


def handover_errors(
    world: World,
    T_base1_base2_est: ArrayLike,
    P_base2: ArrayLike,
    R_base2_flange: ArrayLike,
    q1_near: ArrayLike,
    q2_near: ArrayLike,
) -> Array:
    """Distances (n,) between the two flanges when robot 1 is sent to meet robot 2's, m.

    Robot 2's controller puts its flange at each point of ``P_base2`` (its own
    base frame, orientation ``R_base2_flange``); robot 1's controller is sent
    to the same pose placed in base 1 by ``T_base1_base2_est``, its flange
    turned to face robot 2's (a hand-over). Both arms are the world's (their
    kinematic errors count, as on a real cell), and robot 2 stands at its true
    place. Points out of either robot's reach give NaN.
    """
    r2 = world.robot2
    if r2 is None:
        raise InputError("handover_errors: the world has no second robot")
    T_est = se3.check_transform(T_base1_base2_est, "T_base1_base2_est")
    R2 = np.asarray(R_base2_flange, dtype=np.float64)
    flip = np.diag([1.0, -1.0, -1.0])  # face to face: robot 1's flange turned half a turn about its x
    q1, q2 = np.asarray(q1_near, dtype=np.float64), np.asarray(q2_near, dtype=np.float64)
    P = np.asarray(P_base2, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(P), np.nan)
    for i, p in enumerate(P):
        T2_cmd = se3.transform_from(R2, p)
        q2_cmd = kin.inverse(T2_cmd, q2, r2.nominal_dh)
        if q2_cmd is None:
            continue
        p2_true = (r2.T_base1_base2 @ r2.arm.flange(q2_cmd, q2_cmd - q2))[:3, 3]
        T1_cmd = T_est @ T2_cmd
        got = true_flange(world, se3.transform_from(T1_cmd[:3, :3] @ flip, T1_cmd[:3, 3]), q1)
        if got is None:
            continue
        out[i] = float(np.linalg.norm(got[0][:3, 3] - p2_true))
        q1, q2 = got[1], q2_cmd
    return out


def box_grid(centre: ArrayLike, size: ArrayLike, n: Sequence[int] = (5, 5, 3)) -> Array:
    """Points (prod(n), 3) on a regular grid filling a box of ``size`` (m) about ``centre``."""
    c, s = np.asarray(centre, dtype=np.float64), np.asarray(size, dtype=np.float64)
    axes = [np.linspace(c[k] - s[k] / 2.0, c[k] + s[k] / 2.0, n[k]) for k in range(3)]
    return np.array(list(itertools.product(*axes)))


def targeting(
    world: World, T_base_cam_est: ArrayLike, config: Any, T_base_cam_true: ArrayLike | None = None, arm: ArmModel | None = None
) -> dict[str, Any]:
    """The calibration's targeting error (mm) over two workspaces of a cell config.

    ``calibration``: the box the calibration poses span about the verification
    pose, the flange as at the verification pose (facing the scanner); ``table``:
    a 300 x 300 x 150 mm box over the part's place, 150-300 mm above the
    table, the flange facing down, as when the tool works on the table.
    Joints near the robot's home. ``T_base_cam_true``: where the scanner truly
    is when it sees the points (default: where it is fixed; a scanner on the
    arm, where the arm holds it, with ``T_base_cam_est`` its estimate there); ``arm``: the arm's calibrated
    model, through which every target is pre-corrected (:func:`targeting_errors`).
    """
    cal = config.calibration
    T_v = se3.from_ur_pose(cal.verification_pose)
    home = np.asarray(config.robot.home_q, dtype=np.float64)
    e_cal = targeting_errors(world, T_base_cam_est, box_grid(T_v[:3, 3], cal.pose_box), T_v[:3, :3], home, T_base_cam_true, arm)
    R_down = se3.from_xyz_rpy([0.0, 0.0, 0.0], [math.pi, 0.0, math.pi / 2])[:3, :3]
    e_tab = targeting_errors(world, T_base_cam_est, box_grid([0.6, 0.0, 0.225], [0.3, 0.3, 0.15]), R_down, home, T_base_cam_true, arm)

    def stats(e: Array) -> dict[str, Any]:
        ok = e[np.isfinite(e)]
        return {"mean_mm": float(ok.mean()) * 1e3, "max_mm": float(ok.max()) * 1e3, "points": int(len(ok))}

    return {"calibration": stats(e_cal), "table": stats(e_tab)}


def _plan_frames(seam: Array, wall: Array) -> tuple[Array, Array, Array]:
    """Travel, finger-wall side and up directions (n, 3) of a plan's torch line and wall line."""
    t = np.gradient(seam, axis=0)
    t /= np.linalg.norm(t, axis=1)[:, None]
    n = wall - seam
    n -= np.sum(n * t, axis=1)[:, None] * t
    n /= np.linalg.norm(n, axis=1)[:, None]
    z = np.cross(t, n)
    z *= np.where(z[:, 2] < 0.0, -1.0, 1.0)[:, None]
    return t, n, z


def measured_tool(typed: ToolConfig, tool: dict[str, Any]) -> ToolConfig:
    """The tool as a tool calibration's result (``tool``: its ``tip_tcp_mm`` and ``torch_tcp_mm``) gives it the
    controller, on the ``typed`` one."""
    from dataclasses import replace

    from celld.tactile.tool import with_measured_torch

    tip = np.asarray(tool["tip_tcp_mm"], dtype=np.float64) * 1e-3
    return with_measured_torch(replace(typed, tip_tcp=tuple(tip.tolist())), np.asarray(tool["torch_tcp_mm"]) * 1e-3).tool


def open_loop_torch(world: World, planned: ArrayLike, planned_wall: ArrayLike, q_near: ArrayLike, tool: ToolConfig | None = None) -> Array:
    """The true torch positions (n, 3) if the robot followed the plan alone.

    ``planned`` (n, 3) is the weld's torch line (the seam at the tip height, as
    the scan and the calibration placed it) and ``planned_wall`` (n, 3) the
    wall line beside it (the weld job's ``paths.json``). The controller puts
    its tool's torch on each point, the tool's x along the travel and its z
    out of the joint: ``tool`` (the tool as the controller knows it, e.g. with
    its tool calibration's tip and torch), or the tool as typed (the world's
    drawing); the arm and the tool are the world's.
    """
    S = np.asarray(planned, dtype=np.float64)
    t, _, z = _plan_frames(S, np.asarray(planned_wall, dtype=np.float64))
    nominal = ToolGeometry.from_config(world.tool.nominal if tool is None else tool)
    T_tool_flange = se3.invert(nominal.T_tcp_tool)  # the simulated cell's TCP is the flange
    q = np.asarray(q_near, dtype=np.float64)
    out = np.full_like(S, np.nan)
    p_torch = np.append(world.tool.p_flange_torch, 1.0)
    for i in range(len(S)):
        x = t[i] - float(t[i] @ z[i]) * z[i]
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(z[i], x), z[i]])
        T_base_tool = se3.transform_from(R, S[i] + nominal.torch_offset * x)
        got = true_flange(world, T_base_tool @ T_tool_flange, q)
        if got is not None:
            out[i] = (got[0] @ p_torch)[:3]
            q = got[1]
    return out[np.all(np.isfinite(out), axis=1)]


# The truth of a touch check is read from the arm's states with the believed tip this close to the checked point, m
# (the touches reach the joint's walls, 2-3 mm either side of it).
TOUCH_CHECK_NEAR = 4e-3


def touch_check_truth(
    part: Any, check: dict[str, Any], records: np.ndarray, tip_believed: ArrayLike, tip_true: ArrayLike, arc_output: int
) -> dict[str, float] | None:
    """What a weld's touch check (its ``height_probe.touch_check``, :func:`celld.weld.plan.touch_check`) should have
    read, from the simulated arm's states during the weld (``records``, :data:`TRUTH_DTYPE`).

    Where the controller believed the finger's tip was (its model's TCP, ``tip_believed`` the tip in the TCP frame as
    the weld knew the tool) and where it truly was (the true TCP, ``tip_true`` the tool as built), over the states
    with the believed tip within :data:`TOUCH_CHECK_NEAR` of the check's point before the arc was first on
    (:func:`arc_on`): their
    mean difference carries the check's point, as the controller was sent it, to where the arm truly puts it (the
    arm's error there as it came: its temperature, rest error and lost motion included). ``across_mm``: the part's
    true root line's foot minus that point, across; ``height_mm``: the planned height minus its true height over
    the true root. None when no state was near the point.
    """
    p, a = np.asarray(check["at_base"], dtype=np.float64), np.asarray(check["across"], dtype=np.float64)
    on = arc_on(records, arc_output)
    recs = records[: int(np.argmax(on))] if on.any() else records
    tb = np.append(np.asarray(tip_believed, dtype=np.float64), 1.0)
    tt = np.append(np.asarray(tip_true, dtype=np.float64), 1.0)
    believed = (recs["T_base_tcp_model"] @ tb)[:, :3]
    near = np.linalg.norm(believed - p, axis=1) <= TOUCH_CHECK_NEAR
    if not near.any():
        return None
    true = (recs["T_base_tcp"][near] @ tt)[:, :3]
    x = p + np.mean(true - believed[near], axis=0)  # the checked point where the arm truly puts it
    R, o = part.T_base_plane[:3, :3], part.T_base_plane[:3, 3]
    S = (np.asarray(part.seam_base, dtype=np.float64) - o) @ R
    q = (x - o) @ R
    proj = polyline.project(q[None, :2], S[:, :2])
    arc = polyline.arc_length(S[:, :2])
    foot = np.array([np.interp(proj.arc[0], arc, S[:, k]) for k in range(3)])  # plane coordinates
    across = float((R @ (foot - q)) @ a)
    height = float(check["tip_height_mm"]) * 1e-3 - float(q[2] - foot[2])
    return {"across_mm": across * 1e3, "height_mm": height * 1e3, "error_mm": math.hypot(across, height) * 1e3, "states": int(near.sum())}


class TruthRecorder:
    """Gathers the simulated arm's true states while a job runs (the shared history holds only ~2 s).

    Use as a context manager around the job; :meth:`records` afterwards.
    """

    def __init__(self, host: str, period: float = 0.2) -> None:
        self._reader = TruthReader(host)
        self._period = period
        self._chunks: list[np.ndarray] = []
        self._last = -1
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="truth-recorder", daemon=True)

    def _poll(self) -> None:
        recs = self._reader.history()
        new = recs[recs["stamp_ns"] > self._last]
        if len(new):
            self._chunks.append(new.copy())
            self._last = int(new["stamp_ns"][-1])

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            self._poll()

    def __enter__(self) -> TruthRecorder:
        self._poll()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._poll()
        self._reader.close()

    def records(self) -> np.ndarray:
        """Every true state gathered, oldest first (:data:`celld.sim.robot.truth.TRUTH_DTYPE`)."""
        return np.concatenate(self._chunks) if self._chunks else np.zeros(0, TRUTH_DTYPE)


def arc_on(records: np.ndarray, arc_output: int) -> np.ndarray:
    """Which truth ``records`` had the arc on: digital output ``arc_output`` on, or with ``arc_output`` -1 an arc
    truly burning (a cell with a power source); every record without either."""
    if arc_output >= 0:
        return np.asarray((records["digital_out"].astype(np.int64) >> arc_output) & 1 == 1)
    if records["arc_on"].any():
        return records["arc_on"].astype(bool)
    return np.ones(len(records), bool)


def true_torch_path(world: World, records: np.ndarray, arc_output: int) -> Array:
    """The torch's true path (m, 3) while the arc was on (:func:`arc_on`), thinned as the weld's own."""
    recs = records[arc_on(records, arc_output)]
    if len(recs) == 0:
        return np.zeros((0, 3))
    F = flange_of(recs["T_base_tcp"], recs["T_flange_tcp"])
    P = np.einsum("nij,j->ni", F[:, :3, :3], world.tool.p_flange_torch) + F[:, :3, 3]
    return polyline.thin(P, TORCH_STEP)


def arc_figures(world: World, records: np.ndarray) -> dict[str, float]:
    """The true arc of the records of a weld (:data:`~celld.sim.robot.truth.TRUTH_DTYPE`, oldest first).

    ``arc_on_m``: the torch's true travel with an arc burning; ``no_arc_m``:
    its travel without one between the first strike and the last arc-off (a
    lost arc, a failed re-strike: a stretch of seam left unwelded); ``arc_s``:
    the arc time; ``strikes``: how often an arc came on; ``mean_current_a``:
    the mean true current while it burned (nan without an arc).
    """
    on = records["arc_on"].astype(bool)
    lit = np.flatnonzero(on)
    if len(lit) == 0:
        return {"arc_on_m": 0.0, "no_arc_m": 0.0, "arc_s": 0.0, "strikes": 0.0, "mean_current_a": math.nan}
    F = flange_of(records["T_base_tcp"], records["T_flange_tcp"])
    P = np.einsum("nij,j->ni", F[:, :3, :3], world.tool.p_flange_torch) + F[:, :3, 3]
    step = np.linalg.norm(np.diff(P, axis=0), axis=1)
    dt = np.diff(records["stamp_ns"].astype(np.int64)) * 1e-9
    burning = on[:-1]  # a step is travelled with the arc as it was at its start
    span = np.zeros(len(step), bool)
    span[lit[0] : lit[-1] + 1] = True
    return {
        "arc_on_m": float(step[burning].sum()),
        "no_arc_m": float(step[span & ~burning].sum()),
        "arc_s": float(dt[burning].sum()),
        "strikes": float(np.count_nonzero(on[1:] & ~on[:-1]) + int(on[0])),
        "mean_current_a": float(records["weld_current"][on].mean()),
    }


def lateral(part: Any, P_base: ArrayLike) -> dict[str, float]:
    """Lateral distance (RMS, max mm) of a path from the part's true seam in its welding plane."""
    return lateral_error(np.asarray(P_base, dtype=np.float64), part.seam_base, part.T_base_plane)


def height(part: Any, P_base: ArrayLike, target: float) -> dict[str, float]:
    """Height (mm) of a path over the part's true root line, and its error from ``target`` (m): the largest
    distance from it (``error_max_mm``) and the mean's (``error_mean_mm``, signed)."""
    h = height_over_root(np.asarray(P_base, dtype=np.float64), part.seam_base, part.T_base_plane)
    if not h["points"]:
        return {**h, "error_mean_mm": float("nan"), "error_max_mm": float("nan")}
    t = target * 1e3
    return {**h, "error_mean_mm": h["mean_mm"] - t, "error_max_mm": max(abs(h["min_mm"] - t), abs(h["max_mm"] - t))}


# A TCP slower than this counts as at rest, m/s.
REST_SPEED = 1e-4
# ... and it must stay so this long, s, for the arm to count as stopped.
REST_HOLD = 0.05


class AfterFault(NamedTuple):
    """The true arm and arc after a fault, from the simulator's truth history (times from the fault, s)."""

    speed_at_fault: float  # TCP speed just before the fault, m/s (nan: the history starts after it)
    stopped_s: float  # the first time from which the TCP stays at rest REST_HOLD s (inf: not in the history)
    travel: float  # TCP distance from the fault (or the history's start) to where it stopped, m
    arc_off_s: float  # the arc output off for good (0: it was off already; inf: still on at the history's end)


def after_fault(history: np.ndarray, t_fault_ns: int, arc_output: int) -> AfterFault:
    """Read a truth history (the simulated robot's ``truth_history()``, :data:`TRUTH_DTYPE`) after ``t_fault_ns``.

    "Stopped" is the first lasting rest: a job may move the arm again on
    purpose later (a weld retracts after a failed track), which is no part of
    the stop.
    """
    t = (history["stamp_ns"].astype(np.int64) - t_fault_ns) * 1e-9
    p = history["T_base_tcp"][:, :3, 3]
    v = np.r_[0.0, np.linalg.norm(np.diff(p, axis=0), axis=1) / np.maximum(np.diff(t), 1e-9)]
    i0 = int(np.argmax(t >= 0.0))
    still = v <= REST_SPEED
    stopped, i_stop = math.inf, len(t) - 1
    for i in range(i0, len(t)):
        j = int(np.searchsorted(t, t[i] + REST_HOLD))
        if j < len(t) and still[i:j].all():
            stopped, i_stop = max(float(t[i]), 0.0), i
            break
    arc = (history["digital_out"].astype(np.int64) >> arc_output) & 1
    on = np.flatnonzero((t >= 0.0) & (arc == 1))
    arc_off = 0.0 if not len(on) else (float(t[on[-1] + 1]) if on[-1] + 1 < len(t) else math.inf)
    speed = float(np.median(v[max(i0 - 5, 1) : i0 + 1])) if i0 > 0 else math.nan
    return AfterFault(speed, stopped, float(np.linalg.norm(p[i_stop] - p[i0])), arc_off)


def orphaned_after(log_text: str, t_fault_ns: int, host: str = "") -> tuple[float, str]:
    """When (s after ``t_fault_ns``) and why a motion process took its daemon for gone, from its exit event in
    the daemon's JSON log (``motion_loop_ended``: ``orphaned_ns``, monotonic, and ``reason``, its first clause);
    ``host`` picks a robot's. (nan, "no exit line") without one."""
    for end in read_events(log_text, "motion_loop_ended"):
        if host and end.get("host") != host:
            continue
        at = end.get("orphaned_ns")
        if isinstance(at, int) and at:
            return (at - t_fault_ns) * 1e-9, str(end.get("reason", "?")).split(":")[0]
    return math.nan, "no exit line"


# The arc counts as off the seam when the torch is further than this from the true seam line, m.
OFF_SEAM = 0.005
# A stuck wire counts as dragged when the torch moved further than this while it was stuck, m.
STUCK_MOVE = 1e-4


def arc_truth(world: World, part: Any, records: np.ndarray, arc_start_bit: int) -> dict[str, Any]:
    """The weld's true arc along the true seam, from the simulator's truth records of it (oldest first).

    ``arc_start_bit``: the bit of ``digital_out`` the cell's arc start is wired to (-1: a register, whose
    starts the truth does not see: no per-start figures). Returns the seam's true length and the union of
    its stretches the torch passed over with an arc burning (``welded_m``, each stretch once), per start
    attempt the torch's travel along the seam from its welding start to a stable arc (or to the attempt's
    end when none came), the arc-on samples more than :data:`OFF_SEAM` across the seam (in its welding
    plane), and how many times
    the torch moved more than :data:`STUCK_MOVE` while its wire was stuck.
    """
    from celld.weld.arc_report import welded_intervals

    F = flange_of(records["T_base_tcp"], records["T_flange_tcp"])
    P = np.einsum("nij,j->ni", F[:, :3, :3], world.tool.p_flange_torch) + F[:, :3, 3]
    seam = np.asarray(part.seam_base, dtype=np.float64)
    length = float(polyline.arc_length(seam)[-1])
    proj = polyline.project(P, seam)
    s = np.clip(proj.arc, 0.0, length)
    on = records["arc_on"].astype(bool)
    # Across the seam in its welding plane (the torch's height over the root is not "off the seam").
    across = np.cross(np.asarray(part.T_base_plane)[:3, 2], proj.tangent)
    off_seam = np.abs(np.einsum("ij,ij->i", P - proj.point, across))
    welded = welded_intervals(s, on)
    starts: list[float] = []
    if arc_start_bit >= 0:
        start = (records["digital_out"].astype(np.int64) >> arc_start_bit & 1).astype(bool)
        rises = np.flatnonzero(start[1:] & ~start[:-1]) + 1
        for i in rises:
            after = np.flatnonzero(~start[i:])
            end = i + (int(after[0]) if len(after) else len(start) - i)
            lit = np.flatnonzero(on[i:end])
            j = i + int(lit[0]) if len(lit) else end - 1
            starts.append(float(np.abs(np.diff(s[i : j + 1])).sum()))
    stuck = records["wire_stuck"].astype(bool)
    dragged = 0
    for k in np.flatnonzero(stuck & ~np.concatenate([[False], stuck[:-1]])):
        run = np.flatnonzero(~stuck[k:])
        stop = k + (int(run[0]) if len(run) else len(stuck) - k)
        if float(np.linalg.norm(P[k:stop] - P[k], axis=1).max()) > STUCK_MOVE:
            dragged += 1
    return {
        "seam_length_m": length,
        "welded_m": float(sum(b - a for a, b in welded)),
        "start_travel_m": starts,
        "arc_on_off_seam_samples": int(np.count_nonzero(on & (off_seam > OFF_SEAM))),
        "stuck_windows": int(np.count_nonzero(stuck & ~np.concatenate([[False], stuck[:-1]]))),
        "stuck_wire_moves": dragged,
    }
