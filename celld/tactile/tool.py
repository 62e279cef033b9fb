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

from dataclasses import dataclass

import numpy as np

from celld.config import ToolConfig
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
