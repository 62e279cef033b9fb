"""3D scanner drivers behind one small protocol.

- :mod:`celld.scanner.base`: :class:`OrganizedCloud` (H, W, 3 metres, camera
  frame, NaN = no return) and the :class:`Scanner` protocol.
- :mod:`celld.scanner.replay`: recorded clouds from a directory (.npy, .ply).
- :mod:`celld.scanner.photoneo`: Photoneo PhoXi through GenICam (harvesters).
- :mod:`celld.scanner.open3d_sensors`: Azure Kinect and RealSense through Open3D.
- :mod:`celld.scanner.depth`: depth image to organized cloud (pure).
- :func:`open_scanner`: the driver a config names.

The simulated cell's scanner is not here: the simulator builds it
(:class:`celld.sim.scanner.SimulatedScanner`) and hands it to the daemon.
Every real driver raises :class:`~celld.errors.DriverUnavailable` naming what
is missing (package, SDK library, producer, device) when it cannot open.
"""

from __future__ import annotations

from celld.scanner.base import CaptureStats, OrganizedCloud, Scanner, check_organized
from celld.scanner.factory import open_scanner

__all__ = ["CaptureStats", "OrganizedCloud", "Scanner", "check_organized", "open_scanner"]
