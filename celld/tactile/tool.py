"""Geometry of the touch-based welding tool: tool frame, SRM tip, torch, camera.

The tool (paper Fig. 7) carries a soft finger (SRM) whose tip rides against one
wall of the seam, a camera up the finger that watches an ArUco tag at the
tip, and the welding torch. Seen from above, in the welding plane (paper
Fig. 8)::

        torch P_t              tip P_r (undeformed)        travel ->
            o-------------- |d| ------------o  ---> x = t_d
                                            |
                                            v  n_d = y  (left of travel)
                                  ~~~~~~~~~~~~~~~~~ seam wall (wall_side = left)

Frames and points (all rigid with the TCP):

- **tool frame** ``{tool}``: origin at the centre of the SRM tip when the
  finger is undeformed, the paper's P_r. ``x`` is t_d, from the torch towards
  the tip; ``z`` runs along the finger towards the flange, which is the normal
  of the welding plane pointing away from the work; ``y = z x x`` is n_d, the
  paper's ``[-sin a, cos a]``. ``T_tcp_tool`` comes from the config
  (``tool_x_tcp``, ``tool_z_tcp``, ``tip_tcp_mm``). With the default config the
  robot's TCP is set at the undeformed tip with its z axis down the finger.
- **torch**: ``P_t = P_r - |d| t_d`` (Eq. 14, line 9), ``|d|`` =
  ``torch_offset``; it trails the tip.
- **camera**: ``T_tool_cam`` from the config; it looks down the finger at the
  tag, which sits at the tip with its face towards the camera.
- **deformation** ``delta`` (Eq. 15): ``P_r = P_s + delta``, the undeformed tip
  position minus the deformed one, in the tool frame:
  ``[tangential, normal, out of plane]``. Pressing a wall on the +y side gives
  a positive normal delta; ``wall_side`` says which side the wall is on, and
  the servo's desired deformation is ``delta_d`` signed by it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from celld.config import SERVO_BOUNDS, ToolConfig
from celld.errors import InputError
from celld.se3 import check_transform, transform_from

Array = np.ndarray


@dataclass(frozen=True)
class ToolGeometry:
    """The rigid geometry of the welding tool, in SI units.

    Attributes
    ----------
    T_tcp_tool : (4, 4)
        Pose of the tool frame (origin at the undeformed tip) in the TCP frame.
    T_tool_cam : (4, 4)
        Pose of the finger camera in the tool frame.
    torch_offset : float
        ``|d|`` of Eq. 14, metres.
    tip_radius : float
        Radius of the SRM tip, metres; the wall is this far from the tip centre.
    side : float
        +1 when the wall is on the +y (n_d) side of the tool, -1 otherwise.
    """

    T_tcp_tool: Array
    T_tool_cam: Array
    torch_offset: float
    tip_radius: float
    side: float

    @classmethod
    def from_config(cls, cfg: ToolConfig) -> ToolGeometry:
        x = np.asarray(cfg.tool_x_tcp, dtype=np.float64)
        z = np.asarray(cfg.tool_z_tcp, dtype=np.float64)
        R_tcp_tool = np.column_stack([x, np.cross(z, x), z])
        return cls(
            T_tcp_tool=transform_from(R_tcp_tool, cfg.tip_tcp),
            T_tool_cam=check_transform(cfg.T_tool_cam, "tool.T_tool_cam"),
            torch_offset=cfg.torch_offset,
            tip_radius=cfg.tip_radius,
            side=1.0 if cfg.wall_side == "left" else -1.0,
        )

    @property
    def R_tool_cam(self) -> Array:
        return self.T_tool_cam[:3, :3]

    def T_base_tool(self, T_base_tcp: Array) -> Array:
        """Pose of the tool frame in the base frame, (4, 4)."""
        return np.asarray(T_base_tcp, dtype=np.float64) @ self.T_tcp_tool

    def torch_tool(self) -> Array:
        """The torch point in the tool frame, (3,): ``-|d| x`` (Eq. 14)."""
        return np.array([-self.torch_offset, 0.0, 0.0])


# A measured torch a weld refuses: its direction from the tip this far (rad) from
# the configured tool x, or this far (m) off the tip's height along the finger.
MAX_TORCH_YAW = math.radians(10.0)
MAX_TORCH_HEIGHT = 0.005


@dataclass(frozen=True)
class MeasuredTorch:
    """The tool re-framed on a measured torch (:func:`with_measured_torch`).

    Attributes
    ----------
    tool : ToolConfig
        The tool with ``tool_x_tcp`` from the torch towards the tip (across the
        configured finger axis ``tool_z_tcp``) and ``torch_offset`` the torch's
        distance from the tip across that axis: the torch then sits exactly at
        ``P_r - |d| t_d`` (Eq. 14).
    sensor_yaw : float
        Angle about the tool's z from the new x to the configured one, rad: the
        finger camera's deformation (reported in the configured tool frame)
        turns by it into the new frame.
    height : float
        The torch's offset from the tip along the finger axis (towards the flange), m.
    """

    tool: ToolConfig
    sensor_yaw: float
    height: float


def with_measured_torch(cfg: ToolConfig, p_tcp_torch: np.ndarray) -> MeasuredTorch:
    """``cfg`` with its torch where a tool calibration measured it (TCP frame, m).

    The finger axis stays the configured one; the tool's x is the direction from
    the torch to the tip across it, and ``torch_offset`` the distance across it.

    Raises
    ------
    InputError
        The measured torch is not a finite point, lies on the finger's axis, is
        turned more than :data:`MAX_TORCH_YAW` from where the config puts it or
        stands more than :data:`MAX_TORCH_HEIGHT` off the tip's height.
    """
    torch = np.asarray(p_tcp_torch, dtype=np.float64)
    if torch.shape != (3,) or not np.all(np.isfinite(torch)):
        raise InputError(f"measured torch: expected a finite (3,) point in the TCP frame, got {torch.tolist()}")
    x_cfg = np.asarray(cfg.tool_x_tcp, dtype=np.float64)
    z = np.asarray(cfg.tool_z_tcp, dtype=np.float64)
    v = np.asarray(cfg.tip_tcp, dtype=np.float64) - torch
    height = float(-(v @ z))
    v_plane = v - (v @ z) * z
    offset = float(np.linalg.norm(v_plane))
    bound = SERVO_BOUNDS["torch_offset"]
    if not bound.holds(offset):
        raise InputError(f"measured torch: {offset * 1e3:.2f} mm from the tip across the finger; torch_offset_mm must be {bound.text(1e3)}")
    x = v_plane / offset
    yaw = math.atan2(float(z @ np.cross(x, x_cfg)), float(x @ x_cfg))
    if abs(yaw) > MAX_TORCH_YAW:
        raise InputError(
            f"measured torch: {math.degrees(yaw):.1f} deg about the finger from where the config puts it "
            f"(at most {math.degrees(MAX_TORCH_YAW):.0f}); check tool.tool_x_tcp and the torch"
        )
    if abs(height) > MAX_TORCH_HEIGHT:
        raise InputError(
            f"measured torch: its end stands {height * 1e3:.2f} mm off the tip's height along the finger "
            f"(at most {MAX_TORCH_HEIGHT * 1e3:.0f} mm); trim the wire"
        )
    tool = replace(cfg, tool_x_tcp=(float(x[0]), float(x[1]), float(x[2])), torch_offset=offset)
    return MeasuredTorch(tool, yaw, height)


def yaw_in_plane(delta: np.ndarray, yaw: float) -> np.ndarray:
    """The in-plane components ``delta[:2]`` turned by ``yaw`` about z (a frame turned by ``-yaw``), (2,)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * delta[0] - s * delta[1], s * delta[0] + c * delta[1]])
