"""The layout of a job recording: entity paths, timelines and the default blueprint.

Every writer and reader of a recording takes its entity paths from here, so the
daemon, the viewer layout and the tests agree on one tree::

    /world                      3D scene, the robot base frame (z up, metres)
      /world/clouds/<name>      clouds in the base frame
      /world/camera             the scanner: pose T_base_cam
        /world/camera/clouds/<name>   clouds in the camera frame
      /world/circles/<name>     detected circles (ring), normal as a child arrow
      /world/tcp                the robot TCP: pose T_base_tcp over time
        /world/tcp/flange       the flange model at each calibration pose
      /world/paths/<name>       planned, refined and torch paths
      /world/workpiece          the part model where the scan placed it
      /world/cell/<object>      the cell model's objects (table, scanner, fixtures)
      /world/robot/<name>       the arm and its tool as capsules (at planned poses; "arm" as it moved)
      /world/robot2             a second robot's base, T_base1_base2 as a robot-robot calibration solved it
      /world/calib/residuals    per-pair residuals, robot centre to scanner centre (x20)
    /srm/camera                 the SRM finger camera image
      /srm/camera/tag           the detected ArUco tag outline, pixels
    /servo/delta                the SRM deformation in the tool frame (m): tangential, normal, out of plane
    /servo/delta_n              Algorithm 2's normal deformation delta_n and its target delta_d (m)
    /servo/v_r, /servo/omega    Algorithm 2's commanded twist (SI)
    /servo/phase                Algorithm 2's phase (touch, track, search, finish, ...)
    /weld/contact               the finger's contact state (0 none, 1 contact, 2 overload)
    /weld/arc                   the arc output the loop asked for (0 off, 1 on)
    /weld/arc_phase             the power source's sequence (celld.motion.arc.ArcPhase: 4 weld)
    /arc/current, /arc/voltage  welding current (A) and voltage (V) as the power source reports them
    /robot/v_tcp                measured TCP twist, base frame (m/s, rad/s)
    /robot/q                    joint positions (rad)
    /motion/loop/<signal>_ms    RT loop timing, milliseconds (late, period, work)
    /motion/status              the loop's ControlStatus per cycle
    /calib/e_icp                ICP error metric of Eq. 13 per iteration, metres
    /calib/residuals_mm         per-pair residuals of the solved calibration, mm
    /events                     job events as text

Time: ``time`` is a duration timeline in seconds since the recording was
opened, from ``time.monotonic_ns()`` stamps (the same clock in every
process). ``iteration`` is a sequence timeline of Algorithm 1.
"""

from __future__ import annotations

from typing import Any

import rerun.blueprint as rrb

# Timelines.
TIME = "time"
ITERATION = "iteration"

# Entity paths.
WORLD = "/world"
CLOUDS_BASE = "/world/clouds"
CAMERA = "/world/camera"
CLOUDS_CAM = "/world/camera/clouds"
CIRCLES = "/world/circles"
TCP = "/world/tcp"
PATHS = "/world/paths"
CELL = "/world/cell"  # the cell model's objects
WORKPIECE = "/world/workpiece"  # the part model, placed where the scan found it
FLANGE = "/world/tcp/flange"  # the flange model, carried by the TCP at each pose
RESIDUALS = "/world/calib/residuals"  # robot centre -> scanner centre, per pair
CALIB_RESIDUALS = "/calib/residuals_mm"  # the same, a bar per pair, mm
ROBOT = "/world/robot"  # the arm and its tool at planned poses
ROBOT2 = "/world/robot2"  # a second robot's base (robot-robot calibration)
SRM_CAMERA = "/srm/camera"
SRM_TAG = "/srm/camera/tag"
SERVO = "/servo"
SERVO_DELTA = "/servo/delta"
SERVO_V_R = "/servo/v_r"
SERVO_OMEGA = "/servo/omega"
SERVO_DELTA_N = "/servo/delta_n"
SERVO_PHASE = "/servo/phase"
WELD = "/weld"
WELD_CONTACT = "/weld/contact"
WELD_ARC = "/weld/arc"
WELD_ARC_PHASE = "/weld/arc_phase"  # the power source's sequence (celld.motion.arc.ArcPhase)
WELD_CURRENT = "/arc/current"  # A, as the power source reports it (its own tab: not on /weld's 0-2 scale)
WELD_VOLTAGE = "/arc/voltage"  # V
ROBOT_V_TCP = "/robot/v_tcp"
ROBOT_Q = "/robot/q"
MOTION_LOOP = "/motion/loop"
MOTION_STATUS = "/motion/status"
CALIB_E_ICP = "/calib/e_icp"
EVENTS = "/events"

# The paths a welding job draws, and their colours (RGB).
PATH_COLORS: dict[str, tuple[int, int, int]] = {
    "planned": (80, 160, 255),
    "plan": (170, 170, 170),  # the TCP's planned path (a weld's checked waypoints)
    "refined": (255, 170, 0),
    "torch": (230, 40, 40),
}

# The recording kinds the daemon opens; the blueprint puts the kind's views first.
KINDS = ("calibration", "weld", "scan", "other")


def default_blueprint(kind: str = "other") -> rrb.Blueprint:
    """The viewer layout stored in every recording.

    A 3D view of ``/world`` beside the SRM camera, above a tab group of time
    series: the servo signals, the contact and arc state, loop timing and the
    calibration error. A calibration job opens on the ``e_icp`` tab, any
    other job on ``delta_n``.
    """
    tabs = [
        (SERVO_DELTA_N, "delta_n, delta_d (m)"),
        (WELD, "contact, arc"),
        (WELD_CURRENT, "current (A)"),
        (WELD_VOLTAGE, "voltage (V)"),
        (SERVO_DELTA, "delta (m)"),
        (SERVO_V_R, "V_r (m/s)"),
        (SERVO_OMEGA, "omega (rad/s)"),
        (MOTION_LOOP, "loop timing (ms)"),
        (CALIB_E_ICP, "e_icp (m)"),
    ]
    series: list[Any] = [rrb.TimeSeriesView(origin=origin, name=name) for origin, name in tabs]
    series.append(rrb.BarChartView(origin=CALIB_RESIDUALS, name="residuals (mm)"))
    active = [origin for origin, _ in tabs].index(CALIB_E_ICP if kind == "calibration" else SERVO_DELTA_N)
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=WORLD, name="cell"),
                rrb.Spatial2DView(origin=SRM_CAMERA, name="SRM camera"),
                column_shares=[3, 2],
            ),
            rrb.Tabs(*series, active_tab=active),
            row_shares=[3, 2],
        ),
        collapse_panels=True,
    )
