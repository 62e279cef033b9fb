"""celld: the controller of one robotic welding cell.

A UR10e arm, a 3D scanner above the table and a touch-based welding tool whose
soft finger (SRM) carries a camera watching an ArUco tag. celld calibrates the
scanner to the robot from the robot's own tool flange (Algorithm 1 of the
paper), finds the weld seam in a scan and tracks it by touch (Algorithm 2).

Conventions, used everywhere in the package:

- Units are SI inside: metres, radians, seconds, m/s. Other units appear only
  at a boundary and carry a suffix: ``_mm``, ``_deg``, ``_px``, ``_hz``, ``_ms``.
- ``T_a_b`` is the pose of frame b in frame a, a (4, 4) homogeneous matrix, so
  ``p_a = T_a_b @ p_b``. The paper's ^{Base}_{Cam}H is ``T_base_cam``.
- Points are ``(n, 3)`` arrays named with their frame: ``p_cam``, ``P_base``.
- UR poses are ``[x, y, z, rx, ry, rz]`` (metres, rotation vector); they are
  converted to ``T_base_tcp`` at the robot boundary (:mod:`celld.se3`).
- Time stamps are ``time.monotonic_ns()``; wall clock only in the job journal
  and file names.
- Errors form one tree, in :mod:`celld.errors`.
"""

from __future__ import annotations

__version__ = "0.1.0"
