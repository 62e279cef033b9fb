"""The simulated scanner of a world, as its scanner process builds it.

:func:`open_world_scanner` runs in the child of
:class:`~celld.scanner.process.ScannerProcess` (``celld.sim.cell`` hands it
over): this module imports only what the simulated scanner needs, so the child
starts without the daemon's modules.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from celld.scanner.base import Scanner
from celld.sim.robot.truth import TruthReader
from celld.sim.scanner import SceneObject, SimulatedScanner, robot_scene_source, scanner_model
from celld.sim.scene import robot_scene
from celld.sim.workpiece import SimWorkpiece, workpiece_scene
from celld.sim.world import World


def open_world_scanner(world: World, part: SimWorkpiece | None, host: str, host2: str | None = None) -> Scanner:
    """The simulated scanner of ``world``: it sees the robot on ``host`` (and a second one on ``host2``) where their
    simulators truly put them, and ``part`` as placed."""
    objects: list[SceneObject] = [] if part is None else workpiece_scene(part.workpiece, part.T_base_obj)
    truth = TruthReader(host)  # the simulated robot on the controller's address
    sc = world.scanner
    model = scanner_model(sc.model)
    if sc.metal_bias is not None:
        model = replace(model, metal_bias=sc.metal_bias)
    # One table: the part's scene brings the steel welding table (the robot
    # scene's would lie in the same plane, a matte twin a time-of-flight
    # camera reads 8 mm apart from it).
    arm = world.arm
    robot2 = world.robot2
    # The second robot (its simulator on the controller's address for it), if the cell has one.
    truth2 = TruthReader(host2) if robot2 is not None and host2 is not None else None
    closers = [truth.close] if truth2 is None else [truth.close, truth2.close]

    def extra() -> list[SceneObject]:
        if robot2 is None or truth2 is None:
            return objects
        # Its flange and wrist where its true base and joints put them.
        T_base1_flange2 = robot2.T_base1_base2 @ truth2.latest().T_base_flange
        return [*objects, *robot_scene(T_base1_flange2, robot2.flange, table=False)]

    def close() -> None:
        for c in closers:
            c()

    def T_base_cam() -> np.ndarray:
        # A scanner on the arm is where the arm's true joints put its link now.
        return sc.T_base_cam_at(truth.latest().q, arm.dh)

    return SimulatedScanner(
        model,
        T_base_cam if sc.link else sc.T_base_cam,
        robot_scene_source(
            lambda: truth.latest().T_base_flange,
            world.flange,
            table=not objects,
            extra=extra,
            tool=world.tool.config,  # the tool as built, never the controller's [tool]
            p_flange_torch=world.tool.p_flange_torch,
        ),
        seed=sc.noise_seed,
        resolution_scale=sc.resolution_scale,
        roi_px=sc.roi_px,
        on_close=close,
        measure=None if sc.ideal else sc.measure,
        capture_delay=sc.capture_delay,
    )
