"""A time-of-flight calibration end to end: the ray-cast Azure Kinect, the 90 mm wrist circle, the range bias.

The simulated Azure Kinect reads bare metal 8 mm long (the truth, read here
only to score). The session solve estimates that bias with T_base_cam from
the captures alone; the seam of a steel part scanned by the same camera is
placed by the calibration and its bias. Slow: twenty ray-cast captures.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from celld import polyline, se3
from celld.calib.detect_params import PARAMS_BY_SCANNER
from celld.calib.flange import preset
from celld.calib.rangebias import correct_range_bias
from celld.calib.session import CalibrationSession
from celld.calib.solve import CalibrationResult, SolveParams
from celld.config.seam import SeamParams
from celld.seam.pipeline import find_seam
from celld.seam.workpiece import example
from celld.sim import workpiece as simscene
from celld.sim.scanner import SCANNER_MODELS, SimScanner
from celld.sim.scene import robot_scene

# The simulator's truth (Eq. 19); the estimators never see it.
T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
TRUE_BIAS = SCANNER_MODELS["azure-kinect"].metal_bias
CENTRE = np.array([0.6, 0.0, 0.3])  # the calibration box, 0.7 m below the camera


def poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Flange poses in a 0.3 x 0.3 x 0.2 m box, face up, tilted up to 0.3 rad."""
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("xyz", rng.uniform(-0.3, 0.3, (n, 3))).as_matrix()
    T[:, :3, 3] = CENTRE + rng.uniform(-0.5, 0.5, (n, 3)) * [0.3, 0.3, 0.2]
    return T


@pytest.fixture(scope="module")
def calibration() -> CalibrationResult:
    flange = preset("ur10e-wrist")
    detect = PARAMS_BY_SCANNER["azure-kinect"]
    scanner = SimScanner("azure-kinect", T_BASE_CAM, seed=2)
    params = SolveParams(range_bias="estimate")
    session = CalibrationSession(flange, params, detect, planned=20, online=False)
    for T in poses(np.random.default_rng(2), 20):
        session.capture(T, scanner.capture(robot_scene(T, flange)).points)
    T_v = se3.transform_from(np.eye(3), CENTRE)
    session.verify(T_v, scanner.capture(robot_scene(T_v, flange)).points)
    return session.finish()


def test_the_wrist_circle_calibration_meets_its_target_and_estimates_the_bias(calibration: CalibrationResult) -> None:
    dt, dr = se3.error(calibration.T_base_cam, T_BASE_CAM)
    # The calibration target of a time-of-flight camera: 1.5 mm at the camera's origin.
    assert dt <= 1.5e-3, dt
    assert math.degrees(dr) < 0.2
    rb = calibration.range_bias
    assert rb is not None and rb.source == "steps" and len(rb.step_ids) >= 15
    assert rb.bias == pytest.approx(TRUE_BIAS, abs=0.3e-3)
    assert 0.0 < rb.bias_std < 0.1e-3
    q = calibration.quality
    assert q.verdict == "ok", q.reasons
    assert q.range_bias_std == pytest.approx(rb.bias_std) and q.as_dict()["range_bias_mm"] == pytest.approx(rb.bias * 1e3)


def test_the_seam_of_a_steel_part_needs_the_bias_the_calibration_estimated(calibration: CalibrationResult) -> None:
    wp = example("v-groove")
    T_true = simscene.random_pose(wp, np.random.default_rng(4), math.radians(10.0), 0.03)
    cloud = SimScanner("azure-kinect", T_BASE_CAM, seed=4).capture(simscene.workpiece_scene(wp, T_true)).points
    truth = se3.apply(T_true, polyline.resample(wp.seam, 2e-4)[0])
    params = SeamParams.for_scanner("azure-kinect")
    nominal = simscene.nominal_pose(wp)

    def rms(points: np.ndarray) -> float:
        path = find_seam(points, wp, calibration.T_base_cam_stored, params, T_base_obj_nominal=nominal)
        return float(np.sqrt(np.mean(polyline.distance(path.points_base, truth) ** 2)))

    # As the daemon places it: the scan moved back along its rays by the calibration's bias.
    assert rms(correct_range_bias(cloud, calibration.bias)) <= 1.5e-3
    # Without the bias the steel reads 8 mm deep: the seam lands that far off.
    assert rms(cloud) > 5e-3
