"""``celld sim calibrate``: flange-based calibration of the simulated scanner, offline.

The robot shows its flange to a ray-cast scanner (the simulated cell of
``configs/sim-cell.toml``, in the world of its ``[sim]`` table: the scanner
as mounted and measuring, the flange as made, the arm's true kinematics, so
the flange truly stands where the arm puts it, not where it is commanded) at
generated calibration poses. Each capture goes
through the flange detector; the centre pairs are solved by the robust
estimator, Algorithm 1 runs against the verification cloud with the honest
e_icp metric (Eq. 13), and the session is saved so that
``celld calib solve DIR`` can solve it again offline. Only at the end is the
estimate compared with the simulator's truth, which the solver never sees.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from celld import config as config_mod
from celld import se3
from celld.calib.dataset import SessionWriter
from celld.calib.detect_params import PARAMS_BY_SCANNER, DetectParams
from celld.calib.flange import preset
from celld.calib.kinematic import WIDE, ArmFit, ArmPairs
from celld.calib.kinematic import wide_poses as kinematic_wide_poses
from celld.calib.mount import ScannerMount, in_frame
from celld.calib.poses import calibration_poses
from celld.calib.session import CalibrationSession
from celld.calib.solve import CalibrationResult, SolveParams
from celld.robot import dynamics
from celld.sim.scanner import SimScanner, scanner_model
from celld.sim.scene import robot_scene
from celld.sim.world import World, add_world_arguments, options_from_args, world_of

# The simulated cell the demo runs on, relative to the repository.
DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "sim-cell.toml"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``celld sim calibrate`` (:mod:`celld.sim.cli` adds the subcommand)."""
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="a cell config whose scanner is simulated")
    p.add_argument("--poses", type=int, default=None, help="calibration poses (default: the config's n_poses)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="where to save the session (default: <state_dir>/demo/<time>)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_world_arguments(p)
    p.set_defaults(func=run)


@dataclass(frozen=True)
class OfflineCalibration:
    """What :func:`calibrate_in_world` returns: the solve (in the frame the scanner is fixed in), the scanner's
    true pose there (``T_base_cam``, or ``T_linkN_cam`` on the arm), the controller's joints at the
    verification pose and the time it took (s)."""

    result: CalibrationResult
    T_mount_cam_true: np.ndarray
    q_verification: np.ndarray
    seconds: float


class WorldView:
    """The world's scanner looking at the flange where the world's arm truly puts it (the truth renders, the
    caller only gets clouds and the controller's joints)."""

    def __init__(self, cfg: config_mod.Config, world: World, seed: int) -> None:
        from celld.sim.score import true_camera

        sc = world.scanner
        unit = scanner_model(sc.model) if sc.metal_bias is None else replace(scanner_model(sc.model), metal_bias=sc.metal_bias)
        self.world = world
        self.q = np.asarray(cfg.robot.home_q, dtype=np.float64)  # where the arm comes from
        self.scanner = SimScanner(
            unit,
            true_camera(world, self.q),
            seed=seed,
            resolution_scale=sc.resolution_scale,
            roi_px=sc.roi_px,
            measure=None if sc.ideal else sc.measure,
        )

    def seen(self, T_cmd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The scene with the flange where the arm truly puts it when told ``T_cmd`` (coming from the last
        pose), and the controller's joints."""
        from celld.sim.score import true_camera, true_flange

        got = true_flange(self.world, T_cmd, self.q)
        T_true, q = (T_cmd, self.q) if got is None else got  # out of the nominal reach: drawn where commanded
        self.q = q
        self.scanner.move_to(true_camera(self.world, q))
        return self.scanner.capture(robot_scene(T_true, self.world.flange)).points, q


def calibrate_in_world(
    cfg: config_mod.Config, world: World, n: int, seed: int, writer: SessionWriter | None = None, say: Callable[[str], None] | None = None
) -> OfflineCalibration:
    """Calibrate the scanner of ``world`` from the flange at ``n`` generated poses, as the cell ``cfg`` believes it.

    The controller's side (its flange model, detector parameters, solve
    parameters, poses) comes from ``cfg``; the scene (the scanner as mounted
    and measuring, the flange as made, where the arm truly puts it) from
    ``world``, which the solve never reads. A scanner on the arm (the
    config's ``scanner.mount``, the world's own) moves with the arm's true
    joints and is calibrated on its link (Eq. 8).
    """
    cal = cfg.calibration
    flange = preset(cal.flange)  # the controller's flange model
    view = WorldView(cfg, world, seed)
    # The table the controller computes with: what its primary interface serves, and celld reads.
    mount = ScannerMount.of(cfg.scanner.mount, cfg.robot.model, world.nominal_dh)
    seen = view.seen

    dparams: DetectParams = PARAMS_BY_SCANNER[cfg.scanner.model]  # the controller's scanner: its detector parameters
    T_v = se3.from_ur_pose(cal.verification_pose)
    poses = calibration_poses(T_v, cal.pose_box, n, cal.max_tilt, seed=seed)
    t0 = time.perf_counter()
    # Every pose, as the offline benchmark of a session: no early stop.
    session = CalibrationSession(flange, SolveParams.from_config(cal), dparams, planned=n, mount=mount, writer=writer, online=False)
    P_v, q_v = seen(T_v)
    session.verify(T_v, P_v, q_v)
    for T in poses:
        got = session.capture(T, *seen(T)).pair
        det = got.detection
        if say is None:
            continue
        if got.rejected is not None or det is None:
            say(f"  pair {got.id}: no flange ({got.rejected.reason if got.rejected else 'no detection'})")
            continue
        say(
            f"  pair {got.id}: centre found, radius {det.radius * 1e3:.2f} mm, {det.inliers} rim points, "
            f"residual {det.residual * 1e6:.0f} um"
        )
    return OfflineCalibration(session.finish(), world.scanner.T_mount_cam, q_v, time.perf_counter() - t0)


@dataclass(frozen=True)
class OfflineArmCalibration:
    """What :func:`calibrate_arm_in_world` returns: the hand-eye calibration it starts from, the arm's fit, and
    how many wide poses were shown and found."""

    hand_eye: OfflineCalibration
    fit: ArmFit
    wide_poses: int
    seconds: float
    # What the fit was given: the controller's joints, the flange centres and face normals seen (camera frame).
    q: np.ndarray
    p_cam: np.ndarray
    n_cam: np.ndarray

    @property
    def wide_found(self) -> int:
        return len(self.q)


def wide_poses(cfg: config_mod.Config, n: int, seed: int) -> np.ndarray:
    """The arm calibration's flange poses (n, 4, 4) of the cell ``cfg``: :func:`celld.calib.kinematic.wide_poses`
    around its verification pose."""
    return kinematic_wide_poses(se3.from_ur_pose(cfg.calibration.verification_pose), n, seed)


def calibrate_arm_in_world(
    cfg: config_mod.Config, world: World, n: int, seed: int, n_wide: int | None = None, say: Callable[[str], None] | None = None
) -> OfflineArmCalibration:
    """The hand-eye calibration of :func:`calibrate_in_world` (``n`` poses), then the arm's kinematic
    calibration from ``n_wide`` wide poses (:func:`celld.calib.kinematic.fit_arm`), as the cell ``cfg``
    believes its arm (the controller's DH table, UR's published links, the configured payload)."""
    t0 = time.perf_counter()
    hand_eye = calibrate_in_world(cfg, world, n, seed)
    pairs = ArmPairs(preset(cfg.calibration.flange), PARAMS_BY_SCANNER[cfg.scanner.model], hand_eye.result.T_base_cam)
    view = WorldView(cfg, world, seed + 1)
    poses = wide_poses(cfg, n_wide or WIDE.n_poses, seed)
    for i, T in enumerate(poses):
        cloud, q = view.seen(T)
        if not pairs.add(f"wide pose {i}", cloud, T[:3, 3], q) and say is not None:
            say(f"  {pairs.skipped[-1]}")
    # On the controller's own table, as its primary interface serves it to celld.
    fit = pairs.fit(
        cfg.robot.model, dynamics.Payload(cfg.tool.mass, cfg.tool.com_flange), world.nominal_dh, cfg.calibration.arm_error_prior
    )
    return OfflineArmCalibration(
        hand_eye, fit, len(poses), time.perf_counter() - t0, np.asarray(pairs.q), np.asarray(pairs.p_cam), np.asarray(pairs.n_cam)
    )


def run(args: argparse.Namespace) -> int:
    cfg = config_mod.load(args.config)
    n = args.poses if args.poses is not None else cfg.calibration.n_poses
    # The simulator's truth: it renders the scene, the estimator never reads it.
    world = world_of(cfg, options_from_args(args))
    out = Path(args.out) if args.out else Path(cfg.cell.state_dir) / "sim-calibrate" / time.strftime("%Y%m%d-%H%M%S")
    mount = ScannerMount.of(cfg.scanner.mount, cfg.robot.model, world.nominal_dh)
    writer = SessionWriter(out, flange=cfg.calibration.flange, scanner=cfg.scanner.model, mount=mount)
    say = _printer(args.json)
    name = f"T_{mount.frame}_cam"
    say(f"celld sim calibrate: {world.scanner.model} at {name} (simulated), flange {cfg.calibration.flange}, {n} poses; {world.describe()}")
    done = calibrate_in_world(cfg, world, n, args.seed, writer, say)
    result, T_true, seconds = done.result, done.T_mount_cam_true, done.seconds

    dt, dr = se3.error(result.T_base_cam, T_true)
    report = in_frame(result.as_dict(), mount)
    report.update(
        dataset=str(out),
        seconds=seconds,
        error_vs_truth={"translation_mm": dt * 1e3, "rotation_deg": math.degrees(dr)},
    )
    if args.json:
        print(json.dumps(report))
        return 0
    np.set_printoptions(precision=5, suppress=True)
    say(f"\n{name} ({result.method}, {len(result.pair_ids)} of {n} pairs, {seconds:.1f} s):\n{result.T_base_cam}")
    for r in result.rejected:
        say(f"  rejected {r.id}: {r.reason}")
    if result.e_icp is not None:
        say(f"e_icp (Eq. 13): {np.linalg.norm(result.e_icp.translation) * 1e3:.3f} mm")
    if result.algorithm1 is not None:
        a1 = result.algorithm1
        say(f"Algorithm 1: cost {a1.cost * 1e3:.3f} mm after {a1.n_pairs_used} pairs (target reached: {a1.reached})")
    unc = result.uncertainty
    say(f"predicted 1-sigma error: {unc.translation_error * 1e3:.3f} mm, {math.degrees(unc.rotation_error):.4f} deg")
    if result.range_bias is not None:
        rb = result.range_bias
        say(f"range bias on metal: {rb.bias * 1e3:.3f} +- {rb.bias_std * 1e3:.3f} mm (1 sigma, from {rb.source})")
    say(f"error against the simulator's truth: {dt * 1e3:.3f} mm, {math.degrees(dr):.4f} deg")
    q = result.quality
    say(f"quality gate: {q.verdict}" + "".join(f"\n  fails: {r}" for r in q.reasons) + "".join(f"\n  warning: {w}" for w in q.warnings))
    say(f"session saved to {out}; solve it again with: celld calib solve {out} --json")
    return 0


def _printer(quiet: bool) -> Callable[[str], None]:
    def say(text: str) -> None:
        if not quiet:
            print(text, flush=True)

    return say
