"""Accuracy of the flange-based eye-on-base calibration, against its targets.

Benchmarks (each writes a table and PNG plots to bench/out/calib_accuracy/):

1. Replica of the paper's section 3.1: 75 flange poses on a 5 x 5 x 3 grid
   in a 0.3 x 0.3 x 0.2 m box with random tilts (up to 0.3 rad), the camera
   at Eq. 19's T_base_cam, Gaussian noise on the camera-frame centres (Eq. 20)
   with sigma 0.2 ... 10 mm in 0.2 mm steps, 100 realizations each (the pair
   order shuffled in each). Methods: all-points SVD (Eq. 9-12), Algorithm 1
   scored by the honest e_icp (Eq. 13: ICP of a simulated verification cloud,
   point noise sigma, against the flange model placed by the robot pose and
   the estimate), Algorithm 1 followed by Eq. 21, the default robust
   estimator, and the oracle: least squares on the true inliers (here every
   pair, so it coincides with all-points SVD).
   Target: the default estimator's mean error within 1.15x the oracle's at
   every sigma.
2. Outliers (paper section 3.2.2): 54 pairs, 3 false detections 20 to 100 mm
   off, sigma 0.2 mm. Same methods plus OpenCV calibrateHandEye (all five
   methods) and calibrateRobotWorldHandEye (both), fed a simulated marker on
   the flange with equivalent noise (four corners of a 63 mm square, each
   with noise 2 sigma per axis, so the marker centre has sigma). Targets: the
   default estimator below 0.5 mm, all-points SVD above 5 mm.
3. End to end (when the scanner simulation and the detector exist): the
   ray-cast scanner and the flange detector on the UR10e, 20 poses, 20
   seeds. PhoXi M: translation <= 0.15 mm and rotation <= 0.05 deg in 19 of
   20 seeds; Azure Kinect on the 90 mm wrist circle (ur10e-wrist): <= 1.5 mm
   with the cell's default for a time-of-flight camera, the range bias on
   metal estimated with T_base_cam (celld.calib.rangebias); reported beside
   it: the same solve without the bias, the bias estimated (and its spread
   over the seeds, its reported 1-sigma, and what the rays alone and the
   finish steps alone would fix it to), and a bare-metal wrist, where only
   the spread of the rays fixes the bias.

4. The simulated cell's worlds (``configs/sim-cell.toml``, celld/sim/world.py;
   ``--setups4`` picks among them, and the eye-on-arm cell of
   ``configs/sim-cell-eye-on-arm.toml``, its scanner on a boom on link 1,
   solved on its link by Eq. 8 and scored where the arm holds it at the
   verification pose):
   the calibration as the cell runs it (its flange model, detector, poses
   and solve) in seeded worlds whose truth differs from the controller's
   belief, preset ``realistic`` (the arm's true kinematics, repeatability
   and encoder noise, capture timing, the scanner's mount, depth scale,
   distortion and metal bias, the flange as made) and ``ideal`` beside it,
   20 poses, 10 seeds each (``celld sim calibrate``'s solve). T_base_cam
   against the true one, and the targeting error: where the flange truly
   lands when sent, through the estimate and the controller's nominal
   kinematics, to points the scanner saw (celld.sim.score.targeting), mean
   and max over the calibration box and over the table (flange down).
   Target (issue 13, the paper's hardware 0.28 mm): targeting mean <= 0.25
   mm in the calibration box in every seed. T_base_cam's own error is no
   target here: it absorbs what it can of the arm's kinematic error.

Speed (separate figure, "solve_plus_step_ms"): one robust solve over 20 pairs
plus one Algorithm 1 step (four pool solves and four e_icp registrations) on
the verification cloud of the PhoXi M set-up; target <= 20 ms (median).

Translation errors are those of T_base_cam's translation, i.e. of the camera
origin in the base frame (about 0.55 m from the flange poses); rotation
errors are the angle of R_true^T R_est.

``--quick`` runs a thin subset (< 1 min); ``--json`` prints one JSON object
of the figures as the last line. Exit code 1 when a job failed, each named on
stderr and in the JSON's ``failed``: a seed of benchmark 3 or a world of
benchmark 4 whose calibration (or verification capture) failed, or
benchmark 2's OpenCV baselines where OpenCV has no calibrateHandEye (the
5.x wheels; the project pins opencv-contrib-python-headless < 5). A method
that fails on a realization of benchmarks 1 and 2 is a figure (its "failed"
count), not a failed job. 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

# One OpenMP thread per process: the sweeps parallelise over processes, and
# the speed figure is CPU time of one thread.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2
import numpy as np
from _common import Failures, pyplot
from scipy.spatial.transform import Rotation

from celld.calib.algorithm1 import run_algorithm1
from celld.calib.flange import preset
from celld.calib.metrics import IcpParams, IcpVerifier, compensate, model_cloud_with_normals, translation_cost
from celld.calib.rigid import solve_rigid, umeyama
from celld.calib.robust import solve_robust
from celld.errors import CalibrationError
from celld.se3 import apply, invert, transform_from
from celld.se3 import error as se3_error

ROOT = Path(__file__).resolve().parents[1]
OUT = Path(__file__).resolve().parent / "out" / "calib_accuracy"

# Eq. 19: the simulated cell's camera, 1 m above the base looking down.
T_BASE_CAM_TRUE = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
# Calibration workspace: box centre and size (base frame, m), tilt bound (rad).
BOX_CENTRE = np.array([0.6, 0.0, 0.45])
BOX_SIZE = np.array([0.3, 0.3, 0.2])
MAX_TILT = 0.3
# Verification pose: the box centre, flange face up towards the camera.
T_BASE_FLAN_V = transform_from(np.eye(3), BOX_CENTRE)
# Simulated verification cloud: points drawn from the model surface.
N_VERIFICATION_POINTS = 2000
# e_icp set-up of the sweeps (ranking Algorithm 1's candidates): model spacing
# (m), verification points used and the ICP stopping criterion. Cheaper than
# the library defaults (1000 points, 1e-6) so that the sweep fits in an hour;
# the speed figure uses the library defaults.
MODEL_SPACING = 0.002
ICP_POINTS = 500
ICP_RELATIVE_CHANGE = 1e-4
# Marker of the OpenCV baselines: a square of the flange's size on the flange.
MARKER_SIDE = 0.063

METHODS_1 = ("svd_all", "algorithm1", "algorithm1_eq21", "robust", "oracle")
OPENCV_HAND_EYE = {
    "cv_tsai": cv2.CALIB_HAND_EYE_TSAI,
    "cv_park": cv2.CALIB_HAND_EYE_PARK,
    "cv_horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "cv_andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "cv_daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
OPENCV_ROBOT_WORLD = {"cv_rw_shah": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH, "cv_rw_li": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI}


# -- geometry -------------------------------------------------------------------


def grid_positions(nx: int, ny: int, nz: int) -> np.ndarray:
    """Positions (nx ny nz, 3) on a regular grid filling the calibration box, base frame."""
    axes = [np.linspace(-s / 2, s / 2, k) for s, k in zip(BOX_SIZE, (nx, ny, nz))]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return g + BOX_CENTRE


def tilted_poses(rng: np.random.Generator, P_base: np.ndarray) -> np.ndarray:
    """Flange poses (n, 4, 4): face up towards the camera, roll/pitch/yaw uniform in +-MAX_TILT."""
    R = Rotation.from_euler("xyz", rng.uniform(-MAX_TILT, MAX_TILT, (len(P_base), 3))).as_matrix()
    T = np.tile(np.eye(4), (len(P_base), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = P_base
    return T


def errors(T_est: np.ndarray | None) -> tuple[float, float]:
    """Translation error (mm) and rotation error (deg) of an estimate of T_base_cam."""
    if T_est is None or not np.all(np.isfinite(T_est)):
        return math.nan, math.nan
    dt = np.linalg.norm(T_est[:3, 3] - T_BASE_CAM_TRUE[:3, 3]) * 1e3
    dR = Rotation.from_matrix(T_BASE_CAM_TRUE[:3, :3].T @ T_est[:3, :3]).magnitude()
    return float(dt), float(np.degrees(dR))


_MODEL: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def model_points(kind: str) -> np.ndarray:
    """The UR10e flange model cloud: 'icp' (the e_icp target) or 'surface' (to draw measurements from)."""
    return _model(kind)[0]


def _model(kind: str) -> tuple[np.ndarray, np.ndarray]:
    if kind not in _MODEL:
        spacing = MODEL_SPACING if kind == "icp" else 0.0007
        _MODEL[kind] = model_cloud_with_normals(preset("ur10e"), spacing)
    return _MODEL[kind]


def make_verifier(P_v: np.ndarray, sigma: float, strict: bool = False) -> IcpVerifier:
    """e_icp of the sweeps: the verification cloud against the UR10e model placed at the verification pose."""
    P, N = _model("icp")
    params = icp_params(sigma)
    return IcpVerifier(P_v, P, T_BASE_FLAN_V, params.strict() if strict else params, normals_flange=N)


def verification_cloud(rng: np.random.Generator, sigma: float) -> np.ndarray:
    """A simulated verification capture in the camera frame: model surface points, point noise sigma."""
    S = model_points("surface")
    pts = S[rng.choice(len(S), N_VERIFICATION_POINTS, replace=False)]
    P_cam = apply(invert(T_BASE_CAM_TRUE) @ T_BASE_FLAN_V, pts)
    return P_cam + rng.normal(0.0, sigma, P_cam.shape)


def icp_params(sigma: float) -> IcpParams:
    """e_icp registration scaled to the point noise (the scanner's noise figure is configuration)."""
    return IcpParams(max_distances=(max(0.003, 4 * sigma),), max_points=ICP_POINTS, relative_change=ICP_RELATIVE_CHANGE)


def marker_pose_noisy(rng: np.random.Generator, T_cam_marker: np.ndarray, sigma: float) -> np.ndarray:
    """A marker pose measured from its four corners, each with noise 2 sigma per axis."""
    h = MARKER_SIDE / 2
    C = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    C_cam = apply(T_cam_marker, C) + rng.normal(0.0, 2 * sigma, (4, 3))
    R, t, _ = umeyama(C_cam, C)
    return transform_from(R, t)


# -- one realization -------------------------------------------------------------


def _algorithm1(
    ids: list[str], P_base: np.ndarray, P_cam: np.ndarray, P_v: np.ndarray, sigma: float, e_required: float
) -> tuple[np.ndarray | None, np.ndarray | None, float]:
    """Algorithm 1 on the pairs in order; and its optimum compensated by Eq. 21.

    The candidates are ranked with the sweep's ICP set-up; the compensation
    re-registers the optimum with the same set-up run to convergence.
    """
    verifier = make_verifier(P_v, sigma)
    res = run_algorithm1(ids, P_base, P_cam, verifier, translation_cost, e_required=e_required)
    if res.T_base_cam is None:
        return None, None, float(res.n_pairs_used)
    e = make_verifier(P_v, sigma, strict=True)(res.T_base_cam)
    T_comp = compensate(res.T_base_cam, e) if e.ok else None
    return res.T_base_cam, T_comp, float(res.n_pairs_used)


def _robust(P_base: np.ndarray, P_cam: np.ndarray) -> tuple[np.ndarray | None, int]:
    try:
        fit = solve_robust(P_base, P_cam)
    except CalibrationError:
        return None, -1
    return fit.T_base_cam, len(fit.rejected)


def realization_1(args: tuple[int, float, int, float, bool]) -> dict[str, Any]:
    """Benchmark 1, one (sigma, realization): errors of every method (Algorithm 1 when asked)."""
    seed, sigma, rep, e_required, with_alg1 = args
    rng = np.random.default_rng([seed, int(round(sigma * 1e5)), rep])
    P_base = grid_positions(5, 5, 3)
    order = rng.permutation(len(P_base))
    P_base = P_base[order]
    P_cam = apply(invert(T_BASE_CAM_TRUE), P_base) + rng.normal(0.0, sigma, P_base.shape)  # Eq. 20
    P_v = verification_cloud(rng, sigma)
    ids = [str(i) for i in order]
    out: dict[str, Any] = {"sigma_mm": sigma * 1e3, "rep": rep}
    T_svd = solve_rigid(P_base, P_cam).T_dst_src
    out["svd_all"] = errors(T_svd)
    out["oracle"] = errors(T_svd)  # no outliers: the true inliers are every pair
    if with_alg1:
        T_a1, T_a1c, _ = _algorithm1(ids, P_base, P_cam, P_v, sigma, e_required)
        out["algorithm1"] = errors(T_a1)
        out["algorithm1_eq21"] = errors(T_a1c)
    T_rob, n_rej = _robust(P_base, P_cam)
    out["robust"] = errors(T_rob)
    out["robust_rejected"] = n_rej
    return out


def realization_2(args: tuple[int, float, int, float]) -> dict[str, Any]:
    """Benchmark 2, one realization: 54 pairs, 3 false detections 20-100 mm off."""
    seed, sigma, rep, e_required = args
    rng = np.random.default_rng([seed, 2, rep])
    P_base = grid_positions(6, 3, 3)
    T_bf = tilted_poses(rng, P_base)
    order = rng.permutation(len(P_base))
    P_base, T_bf = P_base[order], T_bf[order]
    n = len(P_base)
    bad = rng.choice(n, 3, replace=False)
    d = rng.normal(size=(3, 3))
    offsets = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.020, 0.100, (3, 1))
    P_cam = apply(invert(T_BASE_CAM_TRUE), P_base) + rng.normal(0.0, sigma, P_base.shape)
    P_cam[bad] += offsets
    good = np.setdiff1d(np.arange(n), bad)
    P_v = verification_cloud(rng, sigma)
    ids = [str(i) for i in range(n)]
    out: dict[str, Any] = {"rep": rep}
    out["svd_all"] = errors(solve_rigid(P_base, P_cam).T_dst_src)
    out["oracle"] = errors(solve_rigid(P_base[good], P_cam[good]).T_dst_src)
    T_a1, T_a1c, _ = _algorithm1(ids, P_base, P_cam, P_v, sigma, e_required)
    out["algorithm1"] = errors(T_a1)
    out["algorithm1_eq21"] = errors(T_a1c)
    T_rob, _n_rej = _robust(P_base, P_cam)
    out["robust"] = errors(T_rob)
    # Did the robust estimator reject exactly the false detections?
    if T_rob is not None:
        fit = solve_robust(P_base, P_cam)
        out["robust_rejected_exact"] = sorted(r.index for r in fit.rejected) == sorted(bad.tolist())
    # OpenCV baselines: a marker on the flange (frame = flange frame), equivalent noise.
    T_cm = np.array([marker_pose_noisy(rng, invert(T_BASE_CAM_TRUE) @ T, sigma) for T in T_bf])
    T_cm[bad, :3, 3] += offsets
    T_fb = np.array([invert(T) for T in T_bf])
    out.update(_opencv(T_fb, T_cm, ""))
    # The same solvers on the true inliers only: their accuracy without outliers.
    out.update(_opencv(T_fb[good], T_cm[good], "_inliers"))
    return out


def _opencv(T_fb: np.ndarray, T_cm: np.ndarray, suffix: str) -> dict[str, tuple[float, float]]:
    """OpenCV's eye-to-hand solvers fed flange poses and marker poses."""
    out: dict[str, tuple[float, float]] = {}
    if missing_opencv():  # bench2 names it as a failed job
        return {name + suffix: (math.nan, math.nan) for name in (*OPENCV_HAND_EYE, *OPENCV_ROBOT_WORLD)}
    for name, method in OPENCV_HAND_EYE.items():
        try:
            # Eye-to-hand: pass base->gripper (T_flange_base); the result is T_base_cam.
            R, t = cv2.calibrateHandEye(
                list(T_fb[:, :3, :3]), list(T_fb[:, :3, 3]), list(T_cm[:, :3, :3]), list(T_cm[:, :3, 3]), method=method
            )
            out[name + suffix] = errors(transform_from(R, t.ravel()))
        except cv2.error:
            out[name + suffix] = (math.nan, math.nan)
    T_mc = np.array([invert(T) for T in T_cm])
    for name, method in OPENCV_ROBOT_WORLD.items():
        try:
            # Eye-on-base through the robot-world solver: its "camera" is the
            # marker on the gripper, its "world" the fixed camera; base2world
            # is then T_cam_base.
            R_bw, t_bw, _, _ = cv2.calibrateRobotWorldHandEye(
                list(T_mc[:, :3, :3]), list(T_mc[:, :3, 3]), list(T_fb[:, :3, :3]), list(T_fb[:, :3, 3]), method=method
            )
            out[name + suffix] = errors(invert(transform_from(R_bw, t_bw.ravel())))
        except cv2.error:
            out[name + suffix] = (math.nan, math.nan)
    return out


def missing_opencv() -> list[str]:
    """The OpenCV hand-eye solvers this OpenCV lacks (5.x has neither in Python)."""
    return [f for f in ("calibrateHandEye", "calibrateRobotWorldHandEye") if not hasattr(cv2, f)]


# -- runs -------------------------------------------------------------------------


def _map(fn: Any, jobs: list[Any], workers: int) -> list[Any]:
    if workers <= 1:
        return [fn(j) for j in jobs]
    with ProcessPoolExecutor(max_workers=workers) as ex:
        return list(ex.map(fn, jobs, chunksize=max(1, len(jobs) // (8 * workers))))


def _stats(rows: list[dict[str, Any]], method: str) -> dict[str, float]:
    a = np.array([r[method] for r in rows], dtype=float)
    ok = np.all(np.isfinite(a), axis=1)
    a = a[ok]
    if len(a) == 0:
        return {"t_mean_mm": math.nan, "t_std_mm": math.nan, "r_mean_deg": math.nan, "r_std_deg": math.nan, "failed": int((~ok).sum())}
    return {
        "t_mean_mm": float(a[:, 0].mean()),
        "t_std_mm": float(a[:, 0].std()),
        "r_mean_deg": float(a[:, 1].mean()),
        "r_std_deg": float(a[:, 1].std()),
        "t_max_mm": float(a[:, 0].max()),
        "failed": int((~ok).sum()),
    }


def bench1(args: argparse.Namespace) -> dict[str, Any]:
    if args.quick:
        sigmas, reps = [0.0002, 0.001, 0.005], 2
    else:
        sigmas, reps = [round(0.0002 * k, 6) for k in range(1, 51)], args.reps
    if args.quick or args.alg1_sigmas_mm == "all":
        alg1_sigmas = set(sigmas)
    else:
        alg1_sigmas = {round(float(x) * 1e-3, 6) for x in args.alg1_sigmas_mm.split(",")}
    jobs = [(args.seed, s, r, args.e_required_mm * 1e-3, s in alg1_sigmas) for s in sigmas for r in range(reps)]
    t0 = time.perf_counter()
    rows = _map(realization_1, jobs, args.workers)
    elapsed = time.perf_counter() - t0
    table = []
    for s in sigmas:
        rs = [r for r in rows if abs(r["sigma_mm"] - s * 1e3) < 1e-9]
        entry: dict[str, Any] = {"sigma_mm": s * 1e3}
        for m in METHODS_1:
            entry[m] = _stats([r for r in rs if m in r], m) if any(m in r for r in rs) else None
        entry["robust_rejected_mean"] = float(np.mean([r["robust_rejected"] for r in rs]))
        o, d = entry["oracle"], entry["robust"]
        entry["ratio_t"] = d["t_mean_mm"] / o["t_mean_mm"]
        entry["ratio_r"] = d["r_mean_deg"] / o["r_mean_deg"]
        table.append(entry)
    worst_t = max(e["ratio_t"] for e in table)
    worst_r = max(e["ratio_r"] for e in table)
    result = {
        "sigmas_mm": [e["sigma_mm"] for e in table],
        "algorithm1_sigmas_mm": sorted(x * 1e3 for x in alg1_sigmas),
        "reps": reps,
        "table": table,
        "robust_over_oracle_max_t": worst_t,
        "robust_over_oracle_max_r": worst_r,
        "target_1_15_met": bool(worst_t <= 1.15 and worst_r <= 1.15),
        "seconds": elapsed,
    }
    _write_bench1(result, args)
    return result


def bench2(args: argparse.Namespace, failures: Failures) -> dict[str, Any]:
    if missing := missing_opencv():
        failures.add(
            "bench2 OpenCV baselines",
            f"OpenCV {cv2.__version__} has no {' or '.join(missing)} in Python: install opencv-contrib-python-headless<5 "
            "(pyproject.toml pins it)",
        )
    reps = 3 if args.quick else args.reps
    jobs = [(args.seed, 0.0002, r, args.e_required_mm * 1e-3) for r in range(reps)]
    t0 = time.perf_counter()
    rows = _map(realization_2, jobs, args.workers)
    cv_names = list(OPENCV_HAND_EYE) + list(OPENCV_ROBOT_WORLD)
    methods = list(METHODS_1) + cv_names + [m + "_inliers" for m in cv_names]
    stats = {m: _stats(rows, m) for m in methods}
    exact = [r.get("robust_rejected_exact", False) for r in rows]
    result = {
        "reps": reps,
        "sigma_mm": 0.2,
        "stats": stats,
        "robust_rejected_exactly_the_outliers": float(np.mean(exact)),
        "robust_t_max_mm": stats["robust"]["t_max_mm"],
        "target_robust_below_0_5mm": bool(stats["robust"]["t_max_mm"] < 0.5),
        "target_svd_above_5mm": bool(stats["svd_all"]["t_mean_mm"] > 5.0),
        "svd_fraction_above_5mm": float(np.mean([r["svd_all"][0] > 5.0 for r in rows])),
        "seconds": time.perf_counter() - t0,
    }
    _write_bench2(result, rows, methods, args)
    return result


def speed(args: argparse.Namespace) -> dict[str, Any]:
    """One robust solve (20 pairs) plus one Algorithm 1 step, PhoXi M-like noise."""
    from celld.calib.algorithm1 import Algorithm1

    rng = np.random.default_rng(args.seed)
    sigma = 0.0001
    P_base = BOX_CENTRE + rng.uniform(-0.5, 0.5, (20, 3)) * BOX_SIZE
    P_cam = apply(invert(T_BASE_CAM_TRUE), P_base) + rng.normal(0.0, sigma, P_base.shape)
    P_v = verification_cloud(rng, sigma)
    P, N = _model("icp")
    verifier = IcpVerifier(P_v, P, T_BASE_FLAN_V, IcpParams(), normals_flange=N)  # the library defaults
    wall, cpu = [], []
    n = 10 if args.quick else 60
    for k in range(n):
        alg = Algorithm1(verifier, translation_cost, e_required=0.0, k_max=100)
        alg.start([str(i) for i in range(4)], P_base[:4], P_cam[:4])
        t0, c0 = time.perf_counter(), time.process_time()
        solve_robust(P_base, P_cam)
        alg.add("new", P_base[4 + k % 16], P_cam[4 + k % 16])
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    t_icp = []
    for _ in range(n):
        c0 = time.process_time()
        verifier(T_BASE_CAM_TRUE)
        t_icp.append((time.process_time() - c0) * 1e3)
    return {
        # CPU time of this process: the machine is shared, wall time is noisier.
        "solve_plus_step_ms_median": float(np.median(cpu)),
        "solve_plus_step_ms_p90": float(np.percentile(cpu, 90)),
        "solve_plus_step_wall_ms_median": float(np.median(wall)),
        "e_icp_cpu_ms_median": float(np.median(t_icp)),
        "icp_points": verifier.n_verification_points,
        "model_points": int(len(model_points("icp"))),
        "target_20ms_met": bool(np.median(cpu) <= 20.0),
    }


# Benchmark 3 set-ups: scanner, flange preset, wrist finish (None: the
# preset's, painted), box centre (base frame, m) inside the scanner's range
# (the camera is 1 m above the base), translation target (mm) and rotation
# target (deg). The estimator is the cell's default for the scanner (the
# range bias estimated for the Azure Kinect, calibration.range_bias).
E2E_SETUPS: dict[str, tuple[str, str, str | None, np.ndarray, float, float]] = {
    "phoxi-m": ("phoxi-m", "ur10e", None, np.array([0.6, 0.0, 0.35]), 0.15, 0.05),
    "azure-kinect": ("azure-kinect", "ur10e-wrist", None, np.array([0.6, 0.0, 0.3]), 1.5, math.inf),
    # A bare-metal wrist: no painted shoulder, the bias fixed by the spread of the rays alone.
    "azure-kinect-metal-wrist": ("azure-kinect", "ur10e-wrist", "metal", np.array([0.6, 0.0, 0.3]), 1.5, math.inf),
}
E2E_METHODS = ("robust", "robust_no_bias", "robust_eq21", "svd_all", "algorithm1")


def realization_3(job: tuple[int, str, int, float]) -> dict[str, Any]:
    """Benchmark 3, one seed: ray-cast captures, the detector, the session solve."""
    from dataclasses import replace

    from celld.calib.detect_params import PARAMS_BY_SCANNER
    from celld.calib.session import CalibrationSession
    from celld.calib.solve import SolveParams, solve_pairs
    from celld.config import range_bias_default
    from celld.sim.scanner import SimScanner
    from celld.sim.scene import robot_scene

    seed, setup, n_poses, scale = job
    scanner_name, flange_name, wrist, centre, _, _ = E2E_SETUPS[setup]
    flange = preset(flange_name) if wrist is None else replace(preset(flange_name), wrist_finish=wrist)
    dparams = PARAMS_BY_SCANNER[scanner_name]
    scanner = SimScanner(scanner_name, T_BASE_CAM_TRUE, seed=seed, resolution_scale=scale)
    rng = np.random.default_rng([seed, 3])
    P_base = centre + rng.uniform(-0.5, 0.5, (n_poses, 3)) * BOX_SIZE
    T_bf = tilted_poses(rng, P_base)
    T_v = transform_from(np.eye(3), centre)
    t0 = time.perf_counter()
    mode = range_bias_default("sim", scanner_name)
    # The cell's defaults (no compensation: the verdict is the one a calibrate job gets); Eq. 21 apart.
    params = SolveParams(method="robust", e_required=0.0, range_bias=mode)
    session = CalibrationSession(flange, params, dparams, planned=n_poses, online=False)
    for T in T_bf:
        session.capture(T, scanner.capture(robot_scene(T, flange)).points)
    found = session.detections()
    out: dict[str, Any] = {"seed": seed, "setup": setup, "detected": session.n_pairs, "poses": n_poses, "range_bias_mode": mode}
    try:
        session.verify(T_v, scanner.capture(robot_scene(T_v, flange)).points)
    except CalibrationError as exc:
        out["verification_error"] = str(exc)
    try:
        res = session.finish()
        plain = solve_pairs(found.ids, found.P_base, found.P_cam, replace(params, range_bias="none"), session.verifier, found.rejected)
    except CalibrationError as exc:
        out["error"] = str(exc)
        for m in E2E_METHODS:
            out[m] = (math.nan, math.nan)
        return out
    out["robust"] = errors(res.T_base_cam)
    out["robust_no_bias"] = errors(plain.T_base_cam)
    out["robust_eq21"] = errors(compensate(res.T_base_cam, res.e_icp) if res.e_icp is not None and res.e_icp.ok else None)
    out["svd_all"] = errors(solve_rigid(found.P_base, found.P_cam).T_dst_src)
    out["algorithm1"] = errors(None if res.algorithm1 is None else res.algorithm1.T_base_cam)
    out["rejected"] = len(res.rejected)
    out["verdict"] = res.quality.verdict
    out["predicted_t_mm"] = res.uncertainty.translation_error * 1e3
    out["predicted_r_deg"] = math.degrees(res.uncertainty.rotation_error)
    if res.range_bias is not None:
        rb = res.range_bias
        out["range_bias_mm"] = rb.bias * 1e3
        out["range_bias_std_mm"] = rb.bias_std * 1e3
        out["range_bias_source"] = rb.source
        out["range_bias_sigma_pairs_mm"] = rb.sigma_from_pairs * 1e3
        out["range_bias_sigma_steps_mm"] = rb.sigma_from_steps * 1e3
    out["seconds"] = time.perf_counter() - t0
    return out


def bench3(args: argparse.Namespace, failures: Failures) -> dict[str, Any]:
    if args.quick:
        plan = {"phoxi-m": (1, 8, 0.4), "azure-kinect": (2, 8, 1.0), "azure-kinect-metal-wrist": (2, 8, 1.0)}
    else:
        plan = {name: (args.seeds3, 20, 1.0) for name in E2E_SETUPS}
    result: dict[str, Any] = {}
    t0 = time.perf_counter()
    for setup, (n_seeds, n_poses, scale) in plan.items():
        rows = _map(realization_3, [(seed, setup, n_poses, scale) for seed in range(n_seeds)], args.workers)
        for x in rows:
            for key in ("verification_error", "error"):
                if key in x:
                    what = "the verification capture" if key == "verification_error" else "the calibration"
                    failures.add(f"bench3 {setup} seed {x['seed']}", f"{what} failed: {x[key]}")
        t_target, r_target = E2E_SETUPS[setup][4], E2E_SETUPS[setup][5]
        t = np.array([r["robust"][0] for r in rows])
        r = np.array([r["robust"][1] for r in rows])
        ok = (t <= t_target) & (r <= r_target)
        need = n_seeds - 1 if n_seeds > 1 else n_seeds
        bias = np.array([x.get("range_bias_mm", math.nan) for x in rows])
        result[setup] = {
            "seeds": n_seeds,
            "poses": n_poses,
            "resolution_scale": scale,
            "range_bias_mode": rows[0].get("range_bias_mode"),
            "stats": {m: _stats(rows, m) for m in E2E_METHODS},
            "robust_t_mm": t.tolist(),
            "robust_r_deg": r.tolist(),
            "robust_no_bias_t_mm": [x["robust_no_bias"][0] for x in rows],
            "robust_no_bias_r_deg": [x["robust_no_bias"][1] for x in rows],
            "seeds_within_target": int(ok.sum()),
            "target_met": bool(ok.sum() >= need),
            "verdicts": {v: sum(x.get("verdict") == v for x in rows) for v in sorted({str(x.get("verdict")) for x in rows})},
            "detected_mean": float(np.mean([x["detected"] for x in rows])),
            "rejected_mean": float(np.mean([x.get("rejected", 0) for x in rows])),
            "predicted_t_mm_mean": float(np.nanmean([x.get("predicted_t_mm", math.nan) for x in rows])),
            "predicted_r_deg_mean": float(np.nanmean([x.get("predicted_r_deg", math.nan) for x in rows])),
            "range_bias_mm": bias.tolist(),
            "range_bias_mm_mean": float(np.nanmean(bias)) if np.isfinite(bias).any() else None,
            "range_bias_mm_spread": float(np.nanstd(bias)) if np.isfinite(bias).any() else None,
            "range_bias_std_mm_mean": _nanmean([x.get("range_bias_std_mm", math.nan) for x in rows]),
            "range_bias_sigma_pairs_mm_mean": _nanmean([x.get("range_bias_sigma_pairs_mm", math.nan) for x in rows]),
            "range_bias_sigma_steps_mm_mean": _nanmean([x.get("range_bias_sigma_steps_mm", math.nan) for x in rows]),
            "errors": [x["error"] for x in rows if "error" in x],
        }
    result["seconds"] = time.perf_counter() - t0
    _write_bench3(result, args)
    return result


# Benchmark 4's set-ups: the cell config (configs/) and the world's preset.
WORLD_SETUPS = {
    "realistic": ("sim-cell.toml", "realistic"),
    "ideal": ("sim-cell.toml", "ideal"),
    # The scanner on a boom on link 1 (eye-on-arm, Eq. 8), in the realistic world.
    "eye-on-arm realistic": ("sim-cell-eye-on-arm.toml", "realistic"),
}
WORLD_TARGETING_MEAN = 0.25e-3  # m, targeting mean in the calibration box


def realization_4(job: tuple[str, int, int]) -> dict[str, Any]:
    """Benchmark 4, one world: the cell's calibration in it, scored against its truth.

    A scanner on the arm is scored where the arm holds it at the verification
    pose: its estimate there (the link's nominal pose at the reported joints
    times the estimated ``T_link1_cam``) against the truth there.
    """
    from celld.calib.mount import ScannerMount
    from celld.config import load
    from celld.sim.calib_demo import calibrate_in_world
    from celld.sim.score import targeting, true_camera
    from celld.sim.world import WorldOptions, world_of

    setup, seed, n_poses = job
    config_name, preset_name = WORLD_SETUPS[setup]
    cfg = load(ROOT / "configs" / config_name)
    world = world_of(cfg, WorldOptions(preset=preset_name, seed=seed))
    out: dict[str, Any] = {"setup": setup, "preset": preset_name, "seed": seed, "poses": n_poses}
    try:
        done = calibrate_in_world(cfg, world, n_poses, seed)
    except CalibrationError as exc:
        out["error"] = str(exc)
        return out
    res = done.result
    dt, dr = se3_error(res.T_base_cam, done.T_mount_cam_true)
    mount = ScannerMount.of(cfg.scanner.mount, cfg.robot.model, world.nominal_dh)
    q_v = done.q_verification
    aim = targeting(world, mount.T_base_cam(res.T_base_cam, q_v), cfg, true_camera(world, q_v))
    out.update(
        t_mm=dt * 1e3,
        r_deg=math.degrees(dr),
        pairs=len(res.pair_ids),
        verdict=res.quality.verdict,
        target_mean_mm=aim["calibration"]["mean_mm"],
        target_max_mm=aim["calibration"]["max_mm"],
        table_mean_mm=aim["table"]["mean_mm"],
        table_max_mm=aim["table"]["max_mm"],
        seconds=done.seconds,
    )
    return out


def bench4(args: argparse.Namespace, failures: Failures) -> dict[str, Any]:
    n_seeds, n_poses = (2, 10) if args.quick else (args.seeds4, 20)
    result: dict[str, Any] = {"setups": list(args.setups4)}
    t0 = time.perf_counter()
    for name in args.setups4:
        rows = _map(realization_4, [(name, seed, n_poses) for seed in range(1, n_seeds + 1)], args.workers)
        for r in rows:
            if "error" in r:
                failures.add(f"bench4 {name} seed {r['seed']}", f"the calibration failed: {r['error']}")
        means = np.array([r.get("target_mean_mm", math.nan) for r in rows])
        result[name] = {
            "seeds": n_seeds,
            "poses": n_poses,
            "rows": rows,
            "target_mean_mm_max": float(np.nanmax(means)) if np.isfinite(means).any() else None,
            "target_met": bool(np.all(means <= WORLD_TARGETING_MEAN * 1e3)),
        }
    result["seconds"] = time.perf_counter() - t0
    _write_bench4(result, args)
    return result


def _write_bench4(result: dict[str, Any], args: argparse.Namespace) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    tag = "_quick" if args.quick else ""
    lines = [
        "| set-up | seed | T_base_cam (T_link1_cam) vs truth mm / deg | targeting mean / max mm (cal. box) | over the table mean / max mm | pairs | verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in result["setups"]:
        for r in result[name]["rows"]:
            if "error" in r:
                lines.append(f"| {name} | {r['seed']} | - | - | - | - | failed: {r['error']} |")
                continue
            lines.append(
                f"| {name} | {r['seed']} | {r['t_mm']:.3f} / {r['r_deg']:.4f} | {r['target_mean_mm']:.3f} / {r['target_max_mm']:.3f} | "
                f"{r['table_mean_mm']:.3f} / {r['table_max_mm']:.3f} | {r['pairs']} | {r['verdict']} |"
            )
    (OUT / f"bench4_table{tag}.md").write_text("\n".join(lines) + "\n")


def _nanmean(values: list[float]) -> float | None:
    a = np.array(values, dtype=float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else None


def _write_bench3(result: dict[str, Any], args: argparse.Namespace) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    tag = "_quick" if args.quick else ""
    lines = ["| set-up | method | t mean (mm) | t max (mm) | r mean (deg) | seeds within target |", "|---|---|---|---|---|---|"]
    setups = [k for k in result if k in E2E_SETUPS]
    for setup in setups:
        res = result[setup]
        for m, st in res["stats"].items():
            within = f"{res['seeds_within_target']}/{res['seeds']}" if m == "robust" else ""
            lines.append(
                f"| {setup} | {m} | {st['t_mean_mm']:.3f} | {st.get('t_max_mm', math.nan):.3f} | {st['r_mean_deg']:.4f} | {within} |"
            )
    lines += [
        "",
        "| set-up | range bias mean (mm) | spread over seeds (mm) | reported 1-sigma (mm) | from pairs alone | from steps alone |",
        "|---|---|---|---|---|---|",
    ]
    for setup in setups:
        res = result[setup]
        if res["range_bias_mm_mean"] is None:
            continue

        def f(x: float | None) -> str:
            return "-" if x is None or not math.isfinite(x) else f"{x:.3f}"

        lines.append(
            f"| {setup} | {f(res['range_bias_mm_mean'])} | {f(res['range_bias_mm_spread'])} | {f(res['range_bias_std_mm_mean'])} | "
            f"{f(res['range_bias_sigma_pairs_mm_mean'])} | {f(res['range_bias_sigma_steps_mm_mean'])} |"
        )
    (OUT / f"bench3_table{tag}.md").write_text("\n".join(lines) + "\n")
    plt = pyplot("calib_accuracy")
    if plt is None:
        return
    fig, axes = plt.subplots(1, len(setups), figsize=(6 * len(setups), 4.2), squeeze=False)
    for ax, setup in zip(axes[0], setups):
        res = result[setup]
        ax.plot(res["robust_t_mm"], res["robust_r_deg"], "o", label=f"default estimator (range bias: {res['range_bias_mode']})")
        if res["range_bias_mode"] == "estimate":
            ax.plot(res["robust_no_bias_t_mm"], res["robust_no_bias_r_deg"], "x", color="0.5", label="without the range bias")
            ax.set_xscale("log")
        ax.axvline(E2E_SETUPS[setup][4], color="k", ls=":", label="translation target")
        if math.isfinite(E2E_SETUPS[setup][5]):
            ax.axhline(E2E_SETUPS[setup][5], color="k", ls="--", label="rotation target")
        ax.set_xlabel("translation error (mm)")
        ax.set_ylabel("rotation error (deg)")
        ax.set_title(f"{setup}: {res['seeds']} seeds x {res['poses']} poses")
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(OUT / f"bench3_errors{tag}.png", dpi=120)
    plt.close(fig)


def _write_bench1(result: dict[str, Any], args: argparse.Namespace) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    tag = "_quick" if args.quick else ""
    lines = [
        "sigma_mm,"
        + ",".join(f"{m}_t_mean_mm,{m}_t_std_mm,{m}_r_mean_deg,{m}_r_std_deg" for m in METHODS_1)
        + ",robust_rejected_mean,ratio_t,ratio_r"
    ]
    for e in result["table"]:
        vals = [f"{e['sigma_mm']:.1f}"]
        for m in METHODS_1:
            s = e[m]
            if s is None:
                vals += [""] * 4
                continue
            vals += [f"{s['t_mean_mm']:.4f}", f"{s['t_std_mm']:.4f}", f"{s['r_mean_deg']:.5f}", f"{s['r_std_deg']:.5f}"]
        vals += [f"{e['robust_rejected_mean']:.3f}", f"{e['ratio_t']:.4f}", f"{e['ratio_r']:.4f}"]
        lines.append(",".join(vals))
    (OUT / f"bench1_table{tag}.csv").write_text("\n".join(lines) + "\n")
    plt = pyplot("calib_accuracy")
    if plt is None:
        return
    x = np.array(result["sigmas_mm"])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, key, unit in ((axes[0], "t", "mm"), (axes[1], "r", "deg")):
        # The oracle (= all-points SVD here) last and dashed, on top of the default estimator it matches.
        for m, style in zip(("algorithm1", "algorithm1_eq21", "robust", "svd_all"), ("C1o-", "C2s-", "C0-", "k--")):
            rows = [(e["sigma_mm"], e[m]) for e in result["table"] if e[m] is not None]
            xs = np.array([r[0] for r in rows])
            mean = np.array([r[1][f"{key}_mean_{unit}"] for r in rows])
            std = np.array([r[1][f"{key}_std_{unit}"] for r in rows])
            label = "all-points SVD = oracle" if m == "svd_all" else m
            ax.plot(xs, mean, style, label=label, ms=4)
            ax.fill_between(xs, mean - std, mean + std, color=style[:2] if style[0] == "C" else "0.7", alpha=0.15)
        ax.set_yscale("log")
        ax.set_xlabel("sigma of the centre noise (mm)")
        ax.set_ylabel(f"{'translation' if key == 't' else 'rotation'} error of T_base_cam ({unit})")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(f"Benchmark 1: 75 poses, {result['reps']} realizations per sigma (mean +- std)")
    fig.tight_layout()
    fig.savefig(OUT / f"bench1_errors{tag}.png", dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(x, [e["ratio_t"] for e in result["table"]], "C0-", label="translation")
    ax.plot(x, [e["ratio_r"] for e in result["table"]], "C3-", label="rotation")
    ax.axhline(1.15, color="k", ls=":", label="target 1.15")
    ax.set_xlabel("sigma (mm)")
    ax.set_ylabel("default estimator / oracle (mean error)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(OUT / f"bench1_ratio{tag}.png", dpi=120)
    plt.close(fig)


def _write_bench2(result: dict[str, Any], rows: list[dict[str, Any]], methods: list[str], args: argparse.Namespace) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    tag = "_quick" if args.quick else ""
    lines = ["| method | t mean (mm) | t std (mm) | t max (mm) | r mean (deg) | r std (deg) | failed |", "|---|---|---|---|---|---|---|"]
    for m in methods:
        s = result["stats"][m]
        lines.append(
            f"| {m} | {s['t_mean_mm']:.3f} | {s['t_std_mm']:.3f} | {s.get('t_max_mm', math.nan):.3f} | "
            f"{s['r_mean_deg']:.4f} | {s['r_std_deg']:.4f} | {s['failed']} |"
        )
    (OUT / f"bench2_table{tag}.md").write_text("\n".join(lines) + "\n")
    plt = pyplot("calib_accuracy")
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(10, 4.5))
    data = [[r[m][0] for r in rows if np.isfinite(r[m][0])] for m in methods]
    ax.boxplot(data, showfliers=True)
    ax.set_xticks(range(1, len(methods) + 1), methods, rotation=40, ha="right")
    ax.set_yscale("log")
    ax.axhline(0.5, color="C2", ls=":", label="target: default < 0.5 mm")
    ax.axhline(5.0, color="C3", ls=":", label="all-points SVD > 5 mm")
    ax.set_ylabel("translation error of T_base_cam (mm)")
    ax.set_title(f"Benchmark 2: 54 pairs, 3 false detections, sigma 0.2 mm, {result['reps']} realizations")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / f"bench2_errors{tag}.png", dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="thin subset, under a minute")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object, last line")
    p.add_argument("--bench", default="1,2,speed", help="comma-separated: 1, 2, 3, 4, speed")
    p.add_argument("--reps", type=int, default=100, help="realizations per sigma (full run)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds3", type=int, default=20, help="seeds of benchmark 3 (full run)")
    p.add_argument("--seeds4", type=int, default=10, help="worlds per set-up of benchmark 4 (full run)")
    p.add_argument(
        "--setups4",
        default=",".join(WORLD_SETUPS),
        help=f"comma-separated set-ups of benchmark 4 ({', '.join(WORLD_SETUPS)})",
    )
    p.add_argument(
        "--alg1-sigmas-mm",
        default="0.2,0.4,1,2,4,6,8,10",
        help="sigmas (mm) at which benchmark 1 runs Algorithm 1 (its ICP is the cost), or 'all'",
    )
    p.add_argument("--e-required-mm", type=float, default=0.0, help="Algorithm 1 target (0: use every pair)")
    args = p.parse_args(argv)
    args.setups4 = [s.strip() for s in args.setups4.split(",") if s.strip()]
    unknown = [s for s in args.setups4 if s not in WORLD_SETUPS]
    if unknown:
        p.error(f"--setups4: unknown set-up {unknown[0]!r}; known: {', '.join(WORLD_SETUPS)}")
    which = {s.strip() for s in args.bench.split(",")}
    figures: dict[str, Any] = {"quick": args.quick}
    failures = Failures("calib_accuracy")
    if "speed" in which:
        figures["speed"] = speed(args)
        print(f"speed: {json.dumps(figures['speed'])}")
    if "1" in which:
        r1 = bench1(args)
        figures["bench1"] = {k: v for k, v in r1.items() if k != "table"}
        for e in r1["table"]:
            a1 = e["algorithm1"]
            a1c = e["algorithm1_eq21"]
            alg = f"alg1 {a1['t_mean_mm']:.3f} alg1+eq21 {a1c['t_mean_mm']:.3f} " if a1 is not None else ""
            print(
                f"bench1 sigma {e['sigma_mm']:5.1f} mm: t mean (mm) svd/oracle {e['svd_all']['t_mean_mm']:.3f} {alg}"
                f"robust {e['robust']['t_mean_mm']:.3f} (ratio {e['ratio_t']:.3f}); r mean (deg) svd {e['svd_all']['r_mean_deg']:.4f} "
                f"robust {e['robust']['r_mean_deg']:.4f} (ratio {e['ratio_r']:.3f})" + (f" alg1 {a1['r_mean_deg']:.4f}" if a1 else "")
            )
        figures["bench1"]["summary"] = [
            {"sigma_mm": e["sigma_mm"], **{m: [e[m]["t_mean_mm"], e[m]["r_mean_deg"]] for m in METHODS_1 if e[m] is not None}}
            for e in r1["table"]
        ]
    if "2" in which:
        r2 = bench2(args, failures)
        figures["bench2"] = r2
        for m, s in r2["stats"].items():
            print(f"bench2 {m:16s} t {s['t_mean_mm']:8.3f} +- {s['t_std_mm']:7.3f} mm  r {s['r_mean_deg']:7.4f} deg  failed {s['failed']}")
    if "3" in which:
        figures["bench3"] = bench3(args, failures)
        for setup in E2E_SETUPS:
            res = figures["bench3"][setup]
            st = res["stats"]["robust"]
            nb = res["stats"]["robust_no_bias"]
            line = (
                f"bench3 {setup}: robust t mean {st['t_mean_mm']:.3f} mm (max {st.get('t_max_mm', math.nan):.3f}), "
                f"r mean {st['r_mean_deg']:.4f} deg, within target in {res['seeds_within_target']}/{res['seeds']} seeds"
            )
            if res["range_bias_mode"] == "estimate":
                line += (
                    f"; without the range bias {nb['t_mean_mm']:.3f} mm; range bias {res['range_bias_mm_mean']:.3f} mm "
                    f"(spread {res['range_bias_mm_spread']:.3f}, reported 1-sigma {res['range_bias_std_mm_mean']:.3f}); verdicts {res['verdicts']}"
                )
            print(line)
    if "4" in which:
        figures["bench4"] = bench4(args, failures)
        for preset_name in args.setups4:
            res = figures["bench4"][preset_name]
            ok = [r for r in res["rows"] if "error" not in r]
            means = [r["target_mean_mm"] for r in ok]
            print(
                f"bench4 {preset_name}: {len(ok)} of {res['seeds']} worlds calibrated; targeting mean in the calibration box "
                + (f"{min(means):.3f}-{max(means):.3f} mm" if means else "-")
                + f" (target <= {WORLD_TARGETING_MEAN * 1e3:.2f} mm in every seed: {'met' if res['target_met'] else 'missed'}); "
                + "over the table "
                + (f"{min(r['table_mean_mm'] for r in ok):.3f}-{max(r['table_mean_mm'] for r in ok):.3f} mm" if ok else "-")
            )
    figures["failed"] = failures.jobs
    OUT.mkdir(parents=True, exist_ok=True)
    name = "figures_" + "_".join(sorted(which)) + ("_quick" if args.quick else "")
    (OUT / f"{name}.json").write_text(json.dumps(figures, indent=1, default=float))
    if args.json:
        print(json.dumps(figures, default=float))
    return failures.exit_code()


if __name__ == "__main__":
    sys.exit(main())
