"""The simulated scanner behind the :class:`~celld.scanner.base.Scanner` protocol.

:class:`celld.sim.scanner.SimScanner` ray casts a list of scene objects. A
cell's scanner captures whatever is in front of it, so this adapter asks a
scene source for the objects at capture time: in the simulated cell that is
the robot scene built from the simulated robot's true flange pose
(:func:`robot_scene_source`), plus any workpiece.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from celld import se3
from celld.errors import DeviceError, InputError
from celld.scanner.base import CaptureStats, OrganizedCloud

# A scene source: called at each capture, returns the objects in view.
SceneSource = Callable[[], Sequence[Any]]


def robot_scene_source(
    T_base_flange: Callable[[], ArrayLike],
    flange: Any,
    table: bool = True,
    clutter_seed: int | None = None,
    extra: Callable[[], Sequence[Any]] | None = None,
) -> SceneSource:
    """A scene source of the calibration scene at the robot's current pose.

    Parameters
    ----------
    T_base_flange : callable
        Returns the (4, 4) flange pose in the base frame now (in the simulated
        cell: the simulated controller's truth).
    flange : celld.calib.flange.FlangeModel
        The flange on the wrist.
    table, clutter_seed
        As :func:`celld.sim.scene.robot_scene`.
    extra : callable, optional
        Returns more objects (a workpiece) to add to each capture.
    """
    from celld.sim.scene import robot_scene

    def scene() -> list[Any]:
        T = se3.check_transform(T_base_flange(), "T_base_flange")
        objects = list(robot_scene(T, flange, table=table, clutter_seed=clutter_seed))
        if extra is not None:
            objects.extend(extra())
        return objects

    return scene


class SimulatedScanner:
    """A :class:`celld.sim.scanner.SimScanner` fixed at ``T_base_cam`` that captures a scene source.

    Parameters
    ----------
    model : str
        Scanner model of :data:`celld.sim.scanner.SCANNER_MODELS` (``"phoxi-m"``, ...).
    T_base_cam : array_like
        (4, 4) true pose of the camera in the base frame (the simulator's truth).
    scene : callable
        Returns the scene objects in view at capture time.
    seed : int
        Noise seed; captures are a deterministic sequence per seed and scene.
    resolution_scale : float
        Image scale in [0.01, 1].
    """

    def __init__(
        self,
        model: str,
        T_base_cam: ArrayLike,
        scene: SceneSource,
        seed: int = 0,
        resolution_scale: float = 1.0,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        from celld.sim.scanner import SimScanner

        if not callable(scene):
            raise InputError(f"simulated scanner: expected a callable scene source, got {type(scene).__name__}")
        self.model_name = model
        self._scene = scene
        self._sim = SimScanner(model, np.asarray(T_base_cam, dtype=np.float64), seed=seed, resolution_scale=resolution_scale, clock=clock)
        self._seed = seed
        self._lock = threading.Lock()
        self._stats = CaptureStats()
        self._open = True

    def capture(self) -> OrganizedCloud:
        """Ray cast the scene as it is now."""
        with self._lock:
            if not self._open:
                raise DeviceError("simulated scanner: capture after close")
            started = time.monotonic_ns()
            try:
                cloud = self._sim.capture(self._scene())
            except InputError as exc:
                self._stats.failure(exc)
                raise
            self._stats.success(cloud.stamp_ns, started)
            return cloud

    def info(self) -> dict[str, Any]:
        m = self._sim.model
        return {
            "kind": "sim",
            "model": self.model_name,
            "device": "simulated",
            "width_px": m.width_px,
            "height_px": m.height_px,
            "intrinsics_px": (m.fx, m.fy, m.cx, m.cy),
            "range": (m.min_range, m.max_range),
            "seed": self._seed,
        }

    def health(self) -> dict[str, Any]:
        return self._stats.as_dict(self._open)

    def close(self) -> None:
        self._open = False
