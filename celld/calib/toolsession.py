"""One tool calibration, capture by capture: the SRM tip and the torch found, then each solved in the TCP frame.

Owns what the tool-calibrate job decides between two captures. It is fed one
capture at a time (the TCP pose the robot reports, its joints and the cloud);
it places the cloud with the current calibration (the scanner where it was at
those joints, Eq. 8 on the arm; its range bias on metal taken off), finds the
tip ball near where the tool's drawing puts it
(:func:`~celld.calib.tooltip.detect_tip`) and the welding wire's cut end near
where the configured torch offset puts it
(:func:`~celld.calib.tooltip.detect_wire_end`), and keeps each point in the
base frame or the reason it found none. :meth:`ToolCalibrationSession.finish`
solves each point in the TCP frame by linear least squares together with a
constant base-frame offset (:func:`~celld.calib.toolcal.solve_tool_tip`,
T1-T2) and gives the result with its verdict: the first of the tip's and the
torch's that is not ``ok`` (the torch's reasons prefixed ``torch:``).
:meth:`ToolCalibrationSession.dataset` is what to store to solve it again
offline.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from celld import se3
from celld.calib.mount import Placement, mount_entry
from celld.calib.rangebias import correct_range_bias
from celld.calib.toolcal import FIT_SCHEMA, MIN_SOLVE_POSES, ToolCalParams, ToolTipFit, solve_tool_tip
from celld.calib.tooltip import TipDetection, TipDetectParams, WireDetectParams, detect_tip, detect_wire_end
from celld.config import ToolConfig
from celld.errors import CalibrationError
from celld.schemadoc import array, boolean, integer, obj, string, vector, with_properties


@dataclass(frozen=True)
class ToolCaptureStep:
    """What one capture gave: the tip and the wire's end found (None: not found, with the reason kept)."""

    id: str
    T_base_tcp: np.ndarray
    T_base_cam: np.ndarray
    tip: TipDetection | None
    torch: TipDetection | None
    message: str

    def progress(self) -> dict[str, Any]:
        """The step's progress data (what was found, and the tip's fit in mm)."""
        data: dict[str, Any] = {"pose": self.id, "detected": self.tip is not None, "torch_detected": self.torch is not None}
        if self.tip is not None:
            data |= {"points": self.tip.n_points, "fit_rms_mm": round(self.tip.rms * 1e3, 4), "offset_mm": round(self.tip.offset * 1e3, 3)}
        return data


class _Points:
    """One point of the tool (the tip or the torch) as the captures found it: poses, points, misses."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.missed: list[dict[str, Any]] = []
        self.detections: list[dict[str, Any]] = []

    def detect(self, pid: str, T_base_tcp: np.ndarray, T_base_cam: np.ndarray, find: Callable[[], TipDetection]) -> TipDetection | None:
        """Run the detector ``find``; keep its point (base frame) or the reason it found none."""
        try:
            det = find()
        except CalibrationError as exc:
            self.missed.append({"id": pid, "reason": str(exc)})
            return None
        p_base = se3.apply(T_base_cam, det.p_cam[None])[0]
        self.detections.append(
            {
                "id": pid,
                "T_base_tcp": T_base_tcp.tolist(),
                f"p_base_{self.name}": p_base.tolist(),
                "points": det.n_points,
                "rms_mm": det.rms * 1e3,
                "offset_mm": det.offset * 1e3,
            }
        )
        return det

    def summary(self, det: TipDetection | None) -> str:
        if det is None:
            return f"no {self.name} ({self.missed[-1]['reason']})"
        return f"{self.name} {det.offset * 1e3:.2f} mm from the configured one"

    @property
    def ids(self) -> list[str]:
        return [d["id"] for d in self.detections]

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The TCP poses (n, 4, 4) and the points found (n, 3), base frame."""
        T = np.array([d["T_base_tcp"] for d in self.detections], dtype=np.float64).reshape(-1, 4, 4)
        P = np.array([d[f"p_base_{self.name}"] for d in self.detections], dtype=np.float64).reshape(-1, 3)
        return T, P

    def solve(self) -> ToolTipFit | None:
        """T1-T2 on the points found; None when fewer than 3 leave it unsolved."""
        fit = solve_tool_tip(*self.arrays(), self.ids, ToolCalParams())
        return fit if np.all(np.isfinite(fit.p_tcp_tip)) else None

    def quality(self, fit: ToolTipFit, n_poses: int, what: str) -> dict[str, Any]:
        """The fit's report, with the captures that showed no ``what``."""
        quality = fit.as_dict()
        quality["missed"] = self.missed
        if self.missed:
            quality["warnings"].append(f"{len(self.missed)} of {n_poses} captures showed no {what}")
        return quality


# Captures that showed no point of the tool, and why.
_MISSED = array(obj("A capture without the point.", {"id": string(), "reason": string()}, ("id", "reason")), "Captures without the point.")
# The JSON shape of a point's report (_Points.quality): its fit's, and the captures that showed no point.
POINT_QUALITY_SCHEMA = with_properties(FIT_SCHEMA, {"missed": _MISSED}, ("missed",))
# The torch's (_torch_quality): the same, or without a fit (too few captures showed it) its verdict, why and misses.
_TORCH_QUALITY = {
    **POINT_QUALITY_SCHEMA,
    "description": "The torch's own report in the same keys (tip_std_mm its 1-sigma); without a fit, its verdict and why.",
    "required": ["verdict", "passed", "reasons", "warnings", "missed"],
}
# The JSON shape of the tool's report (ToolCalibrationSession.finish): the tip's, whose verdict is the job's, with the torch's.
QUALITY_SCHEMA = with_properties(
    POINT_QUALITY_SCHEMA,
    {"torch": _TORCH_QUALITY},
    ("torch",),
    desc="The verdict on a tool calibration: the tip's report, whose verdict is the job's (the first of the tip's and the "
    "torch's that is not ok: then the reasons are the torch's, prefixed 'torch:'), and the torch's.",
)
_POINT_TCP = vector("A point in the TCP frame, mm.", 3)
_STD_TCP = vector("Its 1-sigma along TCP x, y, z, mm.", 3, null_items=True)
# The JSON shape of a tool calibration (ToolCalibration.tool, a tool-calibrate job's candidate).
TOOL_SCHEMA = obj(
    "A tool calibration: the SRM tip (and the torch) measured in the TCP frame; it overrides tool.tip_tcp_mm "
    "(and, with torch_measured, the torch offset and the tool's x axis) once current.",
    {
        "job": string("The tool-calibrate job that measured it."),
        "tip_tcp_mm": {**_POINT_TCP, "description": "The tip's centre in the TCP frame, mm."},
        "tip_std_mm": _STD_TCP,
        "nominal_tip_tcp_mm": {**_POINT_TCP, "description": "The config's tool.tip_tcp_mm when it was measured."},
        "delta_mm": {**_POINT_TCP, "description": "Measured minus configured tip, TCP frame, mm."},
        "calibration_job": string("The hand-eye calibration the points were placed with."),
        "poses": integer("Poses with a tip measurement.", lo=0),
        "quality": QUALITY_SCHEMA,
        "torch_measured": boolean("The torch was measured: a weld takes torch_offset and the tool's x axis from the tip and it."),
        "torch_tcp_mm": {
            **_POINT_TCP,
            "description": "The torch point (the wire's end), TCP frame, mm: measured when torch_measured, else torch_offset "
            "along -x of the tool frame.",
        },
        "torch_std_mm": _STD_TCP,
        "nominal_torch_tcp_mm": {**_POINT_TCP, "description": "Where the config put the torch when it was measured."},
        "torch_delta_mm": {**_POINT_TCP, "description": "Measured minus configured torch, TCP frame, mm."},
    },
    (
        "job",
        "tip_tcp_mm",
        "tip_std_mm",
        "nominal_tip_tcp_mm",
        "delta_mm",
        "calibration_job",
        "poses",
        "quality",
        "torch_measured",
        "torch_tcp_mm",
    ),
)


@dataclass(frozen=True)
class ToolCalibration:
    """A tool calibration's outcome: ``tool`` (the tip and torch in the TCP frame, mm, with the quality report),
    the fits (the torch's None when too few captures showed it) and the residuals to draw."""

    tool: dict[str, Any]  # TOOL_SCHEMA
    tip_fit: ToolTipFit
    torch_fit: ToolTipFit | None
    residuals: tuple[list[str], np.ndarray, np.ndarray, list[bool]]


class ToolCalibrationSession:
    """The tip and the torch of the tool ``tool`` measured with the scanner placed by ``placement``.

    Parameters
    ----------
    tool : ToolConfig
        The tool as configured (its drawn tip, finger axis, torch offset, tip radius and wire).
    placement : Placement
        The current calibration: where the scanner is (on the base, or on a link of the arm).
    range_bias : float
        The current calibration's range bias on metal, m (taken off every cloud).
    """

    def __init__(self, tool: ToolConfig, placement: Placement, range_bias: float = 0.0) -> None:
        self.tool = tool
        self.placement = placement
        self.range_bias = float(range_bias)
        self.p_tcp_nominal = np.asarray(tool.tip_tcp, dtype=np.float64)
        self.z_tcp = np.asarray(tool.tool_z_tcp, dtype=np.float64)
        self.x_tcp = np.asarray(tool.tool_x_tcp, dtype=np.float64)
        self.p_tcp_torch_nominal = self.p_tcp_nominal - tool.torch_offset * self.x_tcp  # Eq. 14, as configured
        self._tip, self._torch = _Points("tip"), _Points("torch")
        self._tip_params, self._wire_params = TipDetectParams(), WireDetectParams()
        self._count = 0

    @property
    def n_captures(self) -> int:
        return self._count

    def capture(self, T_base_tcp: ArrayLike, q: ArrayLike | None, cloud: ArrayLike) -> ToolCaptureStep:
        """One capture at the TCP pose the robot reports, with its joints: the tip and the wire's end found in it
        (the pose through the calibration's arm model, when it has one: :meth:`Placement.modelled`)."""
        pid = f"{self._count:03d}"
        self._count += 1
        T_bt = self.placement.modelled(T_base_tcp, q) if self.placement.arm is not None else np.asarray(T_base_tcp, dtype=np.float64)
        points = correct_range_bias(cloud, self.range_bias) if self.range_bias else np.asarray(cloud)
        T_base_cam = self.placement.T_base_cam(q)  # a scanner on the arm moves with its link (Eq. 8)
        T_cam_tcp = se3.invert(T_base_cam) @ T_bt
        u_cam = T_cam_tcp[:3, :3] @ self.z_tcp  # along the finger and the wire, towards the flange
        tip_pred, torch_pred = se3.apply(T_cam_tcp, np.array([self.p_tcp_nominal, self.p_tcp_torch_nominal]))
        tool = self.tool
        tip = self._tip.detect(pid, T_bt, T_base_cam, lambda: detect_tip(points, tip_pred, u_cam, tool.tip_radius, self._tip_params))
        torch = self._torch.detect(
            pid, T_bt, T_base_cam, lambda: detect_wire_end(points, torch_pred, u_cam, tool.wire_diameter / 2.0, self._wire_params)
        )
        message = f"pose {pid}: {self._tip.summary(tip)}, {self._torch.summary(torch)}"
        return ToolCaptureStep(pid, T_bt, T_base_cam, tip, torch, message)

    def counts(self) -> tuple[int, int]:
        """Captures that showed the tip, and the torch."""
        return len(self._tip.ids), len(self._torch.ids)

    def dataset(self, calibration_job: str) -> dict[str, Any]:
        """Everything to solve the session again offline (``toolcal.json``): base frame, metres."""
        return {
            "frame": "base",
            "units": "m",
            "calibration_job": calibration_job,
            **mount_entry(self.placement.mount, self.placement.T_ref_cam),
            "range_bias_m": self.range_bias,
            "tip_tcp_config": self.p_tcp_nominal.tolist(),
            "tip_radius": self.tool.tip_radius,
            "torch_tcp_config": self.p_tcp_torch_nominal.tolist(),
            "wire_diameter": self.tool.wire_diameter,
            "detections": self._tip.detections,
            "missed": self._tip.missed,
            "torch_detections": self._torch.detections,
            "torch_missed": self._torch.missed,
        }

    def finish(self, job: str, calibration_job: str) -> ToolCalibration:
        """Both points solved, with their reports and the job's verdict.

        Raises
        ------
        CalibrationError
            Fewer than three captures showed the tip (the first miss named).
        """
        tip, torch, n = self._tip, self._torch, self._count
        fit = tip.solve()
        torch_fit = torch.solve()
        if fit is None:
            raise CalibrationError(
                f"only {len(tip.ids)} of {n} captures showed the tip; at least {MIN_SOLVE_POSES} are needed"
                + (f" (first miss: {tip.missed[0]['reason']})" if tip.missed else "")
            )
        quality = tip.quality(fit, n, "tip")
        quality["torch"] = self._torch_quality(torch_fit)
        if quality["torch"]["verdict"] != "ok" and quality["verdict"] == "ok":
            # The job's verdict: the first of the tip's and the torch's that is not ok.
            quality["verdict"], quality["passed"] = quality["torch"]["verdict"], False
            quality["reasons"] = ["torch: " + r for r in quality["torch"]["reasons"]]
        p_tip, p_nominal = fit.p_tcp_tip, self.p_tcp_nominal
        result: dict[str, Any] = {
            "job": job,
            "tip_tcp_mm": (p_tip * 1e3).tolist(),
            "tip_std_mm": quality["tip_std_mm"],
            "nominal_tip_tcp_mm": (p_nominal * 1e3).tolist(),
            "delta_mm": ((p_tip - p_nominal) * 1e3).tolist(),
            "calibration_job": calibration_job,
            "poses": len(tip.ids),
            "quality": quality,
        }
        if torch_fit is not None:
            p_torch = torch_fit.p_tcp_tip
            result |= {
                "torch_measured": True,
                "torch_tcp_mm": (p_torch * 1e3).tolist(),
                "torch_std_mm": quality["torch"]["tip_std_mm"],
                "nominal_torch_tcp_mm": (self.p_tcp_torch_nominal * 1e3).tolist(),
                "torch_delta_mm": ((p_torch - self.p_tcp_torch_nominal) * 1e3).tolist(),
            }
        else:
            # No torch measured: it follows the tip as configured (Eq. 14).
            result |= {"torch_measured": False, "torch_tcp_mm": ((p_tip - self.tool.torch_offset * self.x_tcp) * 1e3).tolist()}
        return ToolCalibration(result, fit, torch_fit, self._residual_points(fit))

    def _torch_quality(self, fit: ToolTipFit | None) -> dict[str, Any]:
        """The torch's report: its fit's, or a ``poor_data`` verdict saying why there is none."""
        torch, n = self._torch, self._count
        if fit is None:
            first = f" (first miss: {torch.missed[0]['reason']})" if torch.missed else ""
            return {
                "verdict": "poor_data",
                "passed": False,
                "reasons": [
                    f"only {len(torch.ids)} of {n} captures showed the welding wire's end; at least {MIN_SOLVE_POSES} are needed{first}"
                ],
                "warnings": [],
                "missed": torch.missed,
            }
        return torch.quality(fit, n, "wire end")

    def _residual_points(self, fit: ToolTipFit) -> tuple[list[str], np.ndarray, np.ndarray, list[bool]]:
        """Ids, the fitted tip through each pose (plus the fit's base offset), the tips found, and which are used."""
        T, P = self._tip.arrays()
        P_robot = np.einsum("nij,j->ni", T[:, :3, :3], fit.p_tcp_tip) + T[:, :3, 3] + fit.offset_base
        out = set(fit.inliers)
        return self._tip.ids, P_robot, P, [i not in out for i in range(len(T))]
