"""Benchmark: tactile seam tracking (Algorithm 2) on three simulated seams.

Each seam is a wall in a horizontal welding plane: a straight line, an arc of
radius 100 mm and a 90-degree corner with a 20 mm fillet. The planned path
handed to the servo is the true seam moved by a 3 mm lateral offset, turned
by 2 degrees about its middle and given 0.3 mm of noise per point (1 mm
apart), as a scanner plan with calibration and extraction errors would be.
V_const = 10 mm/s, delta_d = 1.5 mm.

Modes:

- ``--mode kinematic`` (the development harness): simulated time. The arm is
  a kinematic integrator of the commanded twist (one cycle of latency); the
  motion core (:class:`celld.motion.core.MotionCore`, with its ruckig
  limiter) steps Algorithm 2 at 500 Hz; every camera frame is rendered by
  :class:`celld.sim.srm.SimSrm` at the true pose of its capture time and read
  back by the real detector, and is delivered ``latency + measured detection
  time`` after its capture.
- ``--mode closed-loop``: the motion process and the simulated UR10e through
  real ur-rtde, the camera process with the simulated camera, in wall-clock
  time (see :func:`run_closed_loop`).

Figures: torch lateral error to the true seam (RMS, max) with the tactile
correction and with the plan alone (an ideal follower of the plan: the
distance of the smoothed plan to the seam); the delta_n tracking error (true
normal deformation minus delta_d while tracking); omega peak; guard cycles;
peaks of the sent twists against the limits; detection time per frame;
deformation error (estimate minus simulator truth); latency from a frame's
capture to the first command computed from it.

Targets: lateral RMS <= 0.2 mm and max <= 0.5 mm on all three seams; limits
never exceeded; detection median <= 3 ms per 640 x 480 frame; deformation
error <= 0.02 mm; frame-to-command latency <= 10 ms.

``--quick`` runs shorter seams and fewer frames; ``--json`` prints one JSON
object last. Full runs write ``bench/out/seam_tracking/`` (table and plots).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from celld.config import MotionLimits, TactileConfig  # noqa: E402
from celld.motion.commands import start_servo  # noqa: E402
from celld.motion.core import Action, CoreParams, CycleInput, Mode, MotionCore  # noqa: E402
from celld.motion.limits import CartesianLimits, sequence_peaks  # noqa: E402
from celld.motion.servo import NAME, Algorithm2Servo, Phase, algorithm2_plan, make_algorithm2, prepare_plan  # noqa: E402
from celld.motion.types import ControlStatus, RobotState  # noqa: E402
from celld.sim.srm import SimSrm, SrmSimParams, Wall, _nearest_on_polyline  # noqa: E402
from celld.tactile.aruco import TagDetector  # noqa: E402
from celld.tactile.deformation import DeformationParams, estimate, tare  # noqa: E402
from celld.tactile.sample import ContactState  # noqa: E402

OUT = ROOT / "bench" / "out" / "seam_tracking"
PERIOD = 0.002
# The welding plane: a horizontal table plane in front of the robot.
T_BASE_PLANE = np.array([[1.0, 0, 0, 0.45], [0, 1.0, 0, -0.10], [0, 0, 1.0, 0.12], [0, 0, 0, 1.0]])
TARGETS = {"lateral_rms_mm": 0.2, "lateral_max_mm": 0.5, "detect_median_ms": 3.0, "deformation_error_mm": 0.02, "latency_ms": 10.0}


# -- seams -------------------------------------------------------------------------


def seam(kind: str, quick: bool, step: float = 0.0002) -> np.ndarray:
    """The true seam wall, (n, 2) plane coordinates from the origin along +x."""
    straight = 0.06 if quick else 0.20
    if kind == "straight":
        s = np.arange(0.0, straight + 1e-12, step)
        return np.column_stack([s, np.zeros_like(s)])
    if kind == "arc":
        # Radius 100 mm turning left (the tip rides the outside of the wall).
        R = 0.1
        a = np.arange(0.0, (0.5 if quick else 1.6) + 1e-12, step / R)
        return np.column_stack([R * np.sin(a), R * (1 - np.cos(a))])
    if kind == "corner":
        # 90 degrees to the right with a 20 mm fillet (the tip rides the inside).
        L, R = (0.03 if quick else 0.08), 0.02
        s1 = np.arange(0.0, L, step)
        a = np.arange(0.0, math.pi / 2, step / R)
        s2 = np.arange(0.0, L + 1e-12, step)
        P1 = np.column_stack([s1, np.zeros_like(s1)])
        P2 = np.column_stack([L + R * np.sin(a), -R * (1 - np.cos(a))])
        P3 = np.column_stack([np.full_like(s2, L + R), -R - s2])
        return np.vstack([P1, P2, P3])
    raise ValueError(kind)


def planned(P_true: np.ndarray, rng: np.random.Generator, away: float) -> np.ndarray:
    """The plan: 3 mm lateral offset (``away`` sign), 2 deg rotation about the middle, 0.3 mm noise, 1 mm apart."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P_true, axis=0), axis=1))])
    si = np.arange(0.0, s[-1] + 1e-12, 0.001)
    P = np.column_stack([np.interp(si, s, P_true[:, 0]), np.interp(si, s, P_true[:, 1])])
    t = np.gradient(P, axis=0)
    t /= np.linalg.norm(t, axis=1)[:, None]
    n = np.column_stack([-t[:, 1], t[:, 0]])
    P = P + away * 0.003 * n
    c = P.mean(axis=0)
    a = math.radians(2.0)
    Rz = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    P = (P - c) @ Rz.T + c
    return P + rng.normal(0.0, 0.0003, P.shape)


def to_base(P2: np.ndarray, z: float | np.ndarray = 0.0) -> np.ndarray:
    P3 = np.column_stack([P2, np.broadcast_to(z, (len(P2),))])
    return P3 @ T_BASE_PLANE[:3, :3].T + T_BASE_PLANE[:3, 3]


def start_pose(plan_base: np.ndarray, cfg: TactileConfig, clearance: float = 0.004, lead: int = 5) -> np.ndarray:
    """TCP pose at the start: over the plan ``lead`` points (mm) in, backed off from the wall, facing along the plan."""
    t = plan_base[lead + 5] - plan_base[lead]
    t[2] = 0.0
    t /= np.linalg.norm(t)
    z_up = T_BASE_PLANE[:3, 2]
    n = np.cross(z_up, t)
    side = 1.0 if cfg.wall_side == "left" else -1.0
    p = plan_base[lead] - side * clearance * n
    # Default tool: TCP x = t_d, TCP z down the finger.
    R = np.column_stack([t, np.cross(-z_up, t), -z_up])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


# -- kinematic harness --------------------------------------------------------------


class Arm:
    """A kinematic arm: integrates the commanded TCP twist with one cycle of latency."""

    def __init__(self, T: np.ndarray) -> None:
        self.T = T.copy()
        self.v = np.zeros(6)
        self._next = np.zeros(6)
        self.hist_t: list[int] = []
        self.hist_T: list[np.ndarray] = []
        self.hist_v: list[np.ndarray] = []

    def apply(self, action: Action, twist: np.ndarray) -> None:
        from scipy.spatial.transform import Rotation

        self.v = self._next
        self._next = twist.copy() if action == Action.SPEED else np.zeros(6)
        self.T[:3, 3] += self.v[:3] * PERIOD
        self.T[:3, :3] = Rotation.from_rotvec(self.v[3:] * PERIOD).as_matrix() @ self.T[:3, :3]

    def record(self, t_ns: int) -> None:
        self.hist_t.append(t_ns)
        self.hist_T.append(self.T.copy())
        self.hist_v.append(self.v.copy())

    def at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Pose and twist at ``t_ns`` (linear interpolation of the position, nearest rotation)."""
        i = int(np.searchsorted(self.hist_t, t_ns))
        i = min(max(i, 1), len(self.hist_t) - 1)
        t0, t1 = self.hist_t[i - 1], self.hist_t[i]
        w = 0.0 if t1 == t0 else min(max((t_ns - t0) / (t1 - t0), 0.0), 1.0)
        T = (self.hist_T[i - 1] if w < 0.5 else self.hist_T[i]).copy()
        T[:3, 3] = (1 - w) * self.hist_T[i - 1][:3, 3] + w * self.hist_T[i][:3, 3]
        return T, self.hist_v[i]


class SrmFrameTruth(NamedTuple):
    delta_true: np.ndarray
    in_contact: bool


def direct_sample(delta_true: np.ndarray, rng: np.random.Generator, cfg: TactileConfig, stamp: int, seq: int, prev: ContactState):
    """A sample straight from the simulator's truth plus 3 um of noise (development only, no rendering)."""
    from celld.tactile.deformation import contact_state
    from celld.tactile.sample import TactileSample

    d = delta_true + rng.normal(0.0, 3e-6, 3)
    return TactileSample(stamp, seq, d, contact_state(d, prev, cfg.contact_threshold, cfg.overload), 1.0, True, 2_000_000)


class RunResult(NamedTuple):
    figures: dict[str, Any]
    series: dict[str, np.ndarray]


def lateral(P_true: np.ndarray, q: np.ndarray) -> tuple[float, float, bool]:
    """Signed distance of ``q`` to the seam (left positive), its arc position (m), and whether it is beside it."""
    X, t, s_idx, inside = _nearest_on_polyline(P_true, q)
    n = np.array([-t[1], t[0]])
    i = min(int(s_idx), len(P_true) - 2)
    seg = float(np.linalg.norm(P_true[i + 1] - P_true[i]))
    arc = _arc(P_true)[i] + (s_idx - i) * seg
    return float((q - X) @ n), arc, inside


_ARC: dict[int, np.ndarray] = {}


def _arc(P: np.ndarray) -> np.ndarray:
    key = id(P)
    if key not in _ARC:
        _ARC[key] = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    return _ARC[key]


def run_kinematic(kind: str, cfg: TactileConfig, motion: MotionLimits, quick: bool, seed: int, direct: bool = False) -> RunResult:
    """One seam in simulated time; ``direct`` skips rendering (truth plus 3 um noise; development only)."""
    rng = np.random.default_rng(seed)
    P_true = seam(kind, quick)
    side = 1.0 if cfg.wall_side == "left" else -1.0
    # The plan misses the wall by 3 mm on the free side (the worst case for the approach).
    P_plan2 = planned(P_true, rng, away=-side)
    P_plan = to_base(P_plan2, rng.normal(0.0, 0.0003, len(P_plan2)))
    plan = algorithm2_plan(P_plan, cfg, motion, T_base_plane=T_BASE_PLANE)
    limits = CartesianLimits.from_config(motion)
    core = MotionCore(
        CoreParams(limits, PERIOD, (-1.5, -1.5, -0.5), (1.5, 1.5, 1.5), state_stale=0.05, tactile_stale=motion.tactile_stale),
        {NAME: make_algorithm2},
    )
    srm = SimSrm(cfg, Wall(P_true, free=-side), T_BASE_PLANE, SrmSimParams(seed=seed, fps=cfg.fps))
    detector = TagDetector.from_config(cfg)
    dparams = DeformationParams.from_config(cfg)
    arm = Arm(start_pose(P_plan, cfg))
    # Tare with the finger free at the start pose.
    cv2.setNumThreads(1)
    rest = tare(
        np.array([detector.detect(srm.frame(0, arm.T, np.zeros(3), 0.0).image).p_cam for _ in range(10)]),
        cfg.tare_max_spread, 10,
    )
    frame_ns = int(round(1e9 / cfg.fps))
    next_frame = 0
    pending: list[tuple[int, Any]] = []
    latest = None
    contact = ContactState.NONE
    seq = 0
    log: dict[str, list] = {k: [] for k in ("t", "e_torch", "s_torch", "beside", "omega", "phase", "twist", "guarded",
                                                "delta_n_true", "latency")}
    frames: dict[str, list] = {"stamp": [], "err": [], "detect_ms": [], "valid": [], "contact": []}
    servo: Algorithm2Servo | None = None
    t_ns = 0
    max_s = 600.0
    status = ControlStatus.OK
    torch_tool = np.array([-cfg.torch_offset, 0.0, 0.0, 1.0])
    from celld.tactile.tool import ToolGeometry

    tool = ToolGeometry.from_config(cfg)
    last_true_dn = math.nan
    for k in range(int(max_s / PERIOD)):
        arm.record(t_ns)
        # Camera frames captured up to now: rendered at their capture pose.
        while next_frame <= t_ns:
            T_c, v_c = arm.at(next_frame)
            r = (T_c @ tool.T_tcp_tool)[:3, 3] - T_c[:3, 3]
            v_tip = v_c[:3] + np.cross(v_c[3:], r)
            seq += 1
            if direct:
                c, shift = srm.contact(T_c, v_tip)
                f = SrmFrameTruth(-shift, c.in_contact)
                d_ns = 2_000_000
                sample = direct_sample(f.delta_true, rng, cfg, next_frame, seq, contact)
            else:
                f = srm.frame(next_frame, T_c, v_tip, next_frame * 1e-9)
                t0 = time.perf_counter_ns()
                det = detector.detect(f.image)
                d_ns = time.perf_counter_ns() - t0
                sample = estimate(det, rest, dparams, next_frame, seq, contact, d_ns)
            if sample.valid:
                contact = sample.contact
                frames["err"].append(sample.delta_tool - f.delta_true)
            frames["stamp"].append(next_frame)
            frames["detect_ms"].append(d_ns * 1e-6)
            frames["valid"].append(sample.valid)
            frames["contact"].append(f.in_contact)
            last_true_dn = float(f.delta_true[1]) if f.in_contact else 0.0
            pending.append((next_frame + int(srm.params.latency * 1e9) + d_ns, sample))
            next_frame += frame_ns
        while pending and pending[0][0] <= t_ns:
            latest = pending.pop(0)[1]
        state = RobotState(t_ns, np.zeros(6), np.zeros(6), arm.T.copy(), arm.v.copy())
        age = (t_ns - latest.stamp_ns) * 1e-9 if latest is not None else math.inf
        # The servo starts once the camera delivers (as in the cell, where it runs before).
        starting = servo is None and latest is not None
        cmd = start_servo(plan) if starting else None
        out = core.step(CycleInput(state, 0.0, 1, latest, age, np.zeros(6), math.inf, cmd, 1 if starting else 0))
        if starting:
            servo = core.controller.law  # type: ignore[attr-defined]
        if servo is None:
            arm.apply(out.action, out.twist)
            t_ns += int(PERIOD * 1e9)
            continue
        arm.apply(out.action, out.twist)
        d = servo.last
        T_tool = arm.T @ tool.T_tcp_tool
        p_torch = ((T_tool @ torch_tool)[:3] - T_BASE_PLANE[:3, 3]) @ T_BASE_PLANE[:3, :2]
        e, s_t, beside = lateral(P_true, p_torch)
        log["t"].append(t_ns * 1e-9)
        log["e_torch"].append(e)
        log["s_torch"].append(s_t)
        log["beside"].append(beside)
        log["omega"].append(d.omega)
        log["phase"].append(int(d.phase))
        log["twist"].append(out.twist.copy() if out.action == Action.SPEED else np.zeros(6))
        log["guarded"].append(d.guarded)
        log["delta_n_true"].append(last_true_dn)
        log["latency"].append(d.latency)
        status = out.status
        if core.mode == Mode.IDLE:
            break
        t_ns += int(PERIOD * 1e9)
    series = {k: np.array(v) for k, v in log.items()}
    figures = summarise(kind, cfg, motion, servo, series, frames, P_true, P_plan2, status)
    series["refined"] = servo.refined_plane
    series["P_true"] = P_true
    series["P_plan"] = P_plan2
    return RunResult(figures, series)


def summarise(kind, cfg, motion, servo, S, frames, P_true, P_plan2, status) -> dict[str, Any]:
    ref = servo.refined_plane
    # The weld starts where the tip first touched: from there the torch runs on the refined path.
    s0 = lateral(P_true, ref[0])[1] if len(ref) else math.inf
    weld = S["beside"] & (S["s_torch"] >= s0) & (S["phase"] != int(Phase.TOUCH))
    e = S["e_torch"][weld]
    lead = S["beside"] & (S["s_torch"] < s0) & (S["phase"] != int(Phase.TOUCH))
    # Plan alone: the smoothed plan's distance to the seam where beside it.
    smooth = prepare_plan(np.column_stack([P_plan2, np.zeros(len(P_plan2))]), np.eye(4), cfg.plan_smoothing).P
    e_plan = np.array([lateral(P_true, q)[0] for q in smooth[::4]])
    side = 1.0 if cfg.wall_side == "left" else -1.0
    track = S["phase"] == int(Phase.TRACK)
    dn = S["delta_n_true"][track] - side * cfg.delta_d
    dn = dn[np.isfinite(dn)]
    err = np.array(frames["err"]) if frames["err"] else np.zeros((0, 3))
    in_contact = np.array(frames["contact"])[np.array(frames["valid"])] if frames["err"] else np.zeros(0, bool)
    peaks = sequence_peaks(np.array(S["twist"]), PERIOD, np.zeros((2, 6)))
    ratios = peaks.ratios(CartesianLimits.from_config(motion))
    lat = S["latency"][np.isfinite(S["latency"])]
    covered = (S["s_torch"][weld].max() - s0) if np.any(weld) else 0.0
    length = float(np.sum(np.linalg.norm(np.diff(P_true, axis=0), axis=1)))
    return {
        "seam": kind,
        "status": ControlStatus(status).name,
        "reason": servo.reason,
        "seam_length_mm": round(length * 1e3, 1),
        "welded_mm": round(covered * 1e3, 1),
        "lateral_rms_mm": round(float(np.sqrt(np.mean(e**2))) * 1e3, 4) if len(e) else None,
        "lateral_max_mm": round(float(np.abs(e).max()) * 1e3, 4) if len(e) else None,
        "lead_in_max_mm": round(float(np.abs(S["e_torch"][lead]).max()) * 1e3, 4) if np.any(lead) else None,
        "plan_only_rms_mm": round(float(np.sqrt(np.mean(e_plan**2))) * 1e3, 3),
        "plan_only_max_mm": round(float(np.abs(e_plan).max()) * 1e3, 3),
        "delta_n_rms_mm": round(float(np.sqrt(np.mean(dn**2))) * 1e3, 4) if len(dn) else None,
        "delta_n_max_mm": round(float(np.abs(dn).max()) * 1e3, 4) if len(dn) else None,
        "omega_peak_rad_s": round(float(np.nanmax(np.abs(S["omega"]))), 4),
        "guard_cycles": int(np.sum(S["guarded"])),
        "cycles": int(len(S["t"])),
        "limit_ratio_max": round(float(max(ratios)), 4),
        "limit_ratios": {k: round(float(v), 4) for k, v in ratios._asdict().items()},
        "frames": len(frames["stamp"]),
        "invalid_frames": int(np.sum(~np.array(frames["valid"]))),
        "detect_median_ms": round(float(np.median(frames["detect_ms"])), 3),
        "detect_p99_ms": round(float(np.percentile(frames["detect_ms"], 99)), 3),
        "deformation_rms_mm": round(float(np.sqrt(np.mean(err[in_contact, :2] ** 2))) * 1e3, 4) if np.any(in_contact) else None,
        "deformation_max_mm": round(float(np.abs(err[in_contact, :2]).max()) * 1e3, 4) if np.any(in_contact) else None,
        "deformation_out_of_plane_rms_mm": round(float(np.sqrt(np.mean(err[:, 2] ** 2))) * 1e3, 4) if len(err) else None,
        "latency_median_ms": round(float(np.median(lat)) * 1e3, 3) if len(lat) else None,
        "latency_max_ms": round(float(lat.max()) * 1e3, 3) if len(lat) else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--mode", choices=("kinematic", "closed-loop"), default="kinematic")
    ap.add_argument("--seams", default="straight,arc,corner")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--direct", action="store_true", help="development: deformation from the simulator's truth, no images")
    args = ap.parse_args(argv)
    cfg = TactileConfig()
    motion = MotionLimits()
    results = []
    for kind in args.seams.split(","):
        t0 = time.perf_counter()
        if args.mode == "kinematic":
            r = run_kinematic(kind, cfg, motion, args.quick, args.seed, args.direct)
        else:
            from bench.seam_tracking_closed_loop import run_closed_loop  # pragma: no cover

            r = run_closed_loop(kind, cfg, motion, args.quick, args.seed)
        r.figures["wall_s"] = round(time.perf_counter() - t0, 1)
        results.append(r)
        if not args.json:
            print(json.dumps(r.figures))
    figures = {"mode": args.mode + ("-direct" if args.direct else ""), "quick": args.quick, "seams": [r.figures for r in results], "targets": TARGETS}
    if not args.quick:
        write_outputs(results, figures)
    print(json.dumps(figures))
    return 0


def write_outputs(results: list[RunResult], figures: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "results.json").write_text(json.dumps(figures, indent=2))
    for r in results:
        S, f = r.series, r.figures
        fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
        ax[0].plot(S["P_true"][:, 0] * 1e3, S["P_true"][:, 1] * 1e3, "k-", lw=2, label="true seam")
        ax[0].plot(S["P_plan"][:, 0] * 1e3, S["P_plan"][:, 1] * 1e3, ".", ms=2, label="plan")
        ax[0].plot(S["refined"][:, 0] * 1e3, S["refined"][:, 1] * 1e3, "-", label="refined (SRM tip)")
        ax[0].set_aspect("equal")
        ax[0].legend()
        ax[0].set_xlabel("x mm")
        ax[1].plot(S["t"], S["e_torch"] * 1e3, label="torch lateral error")
        ax[1].plot(S["t"], S["omega"], label="omega rad/s")
        ax[1].set_ylim(-1.0, 1.0)
        ax[1].legend()
        ax[1].set_xlabel("t s")
        fig.suptitle(f"{f['seam']}: RMS {f['lateral_rms_mm']} mm, max {f['lateral_max_mm']} mm")
        fig.savefig(OUT / f"{f['seam']}.png", dpi=100)
        plt.close(fig)
    lines = ["| seam | lateral RMS mm | max mm | plan only RMS/max mm | delta_n RMS mm | omega peak | guard | limit ratio | detect ms | deform RMS/max mm | latency ms |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        f = r.figures
        lines.append(
            f"| {f['seam']} | {f['lateral_rms_mm']} | {f['lateral_max_mm']} | {f['plan_only_rms_mm']}/{f['plan_only_max_mm']} | "
            f"{f['delta_n_rms_mm']} | {f['omega_peak_rad_s']} | {f['guard_cycles']} | {f['limit_ratio_max']} | "
            f"{f['detect_median_ms']} | {f['deformation_rms_mm']}/{f['deformation_max_mm']} | {f['latency_median_ms']} |"
        )
    (OUT / "results.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
