"""The daemon's arm computes with the table its controller computes with, read from the primary interface."""

from __future__ import annotations

import asyncio
import dataclasses
import socket
import threading
from pathlib import Path

import numpy as np
import pytest

from celld.calib.kinematic import ArmModel
from celld.calib.mount import Placement, ScannerMount
from celld.config import load
from celld.daemon import arm as arm_mod
from celld.daemon.arm import Arm
from celld.daemon.store import for_controller
from celld.errors import CalibrationError, DeviceError
from celld.robot import kinematics as kin
from celld.robot import primary
from celld.sim.robot import primary as sp

ROOT = Path(__file__).resolve().parents[2]
CONFIG = load(ROOT / "configs" / "sim-cell.toml")


def _table(seed: int) -> kin.DH:
    rng = np.random.default_rng(seed)
    return kin.DH(*(tuple((np.asarray(row) + rng.normal(0.0, 1e-3, 6)).tolist()) for row in kin.UR10E))  # type: ignore[arg-type]


def _primary_interface(host: str, table: kin.DH) -> socket.socket:
    """A primary interface on ``host``:30001 that sends robot state with ``table`` to every client."""
    srv = socket.create_server((host, primary.PRIMARY_PORT))

    def serve() -> None:
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            with conn:
                conn.sendall(sp.version_message((5, 11, 6, 1)) + sp.robot_state_message(table))

    threading.Thread(target=serve, daemon=True).start()
    return srv


def _arm(host: str) -> Arm:
    return Arm(dataclasses.replace(CONFIG, robot=dataclasses.replace(CONFIG.robot, host=host)))


def test_until_the_controllers_table_is_read_the_arm_plans_on_the_published_one_and_says_so(loopback_host: str) -> None:
    arm = _arm(loopback_host)
    assert arm.dh == kin.UR10E
    with pytest.raises(DeviceError, match="robot 1: the controller's kinematics .* unknown: not read yet"):
        arm.require_kinematics()


def test_the_arm_reads_its_controllers_table_and_plans_with_it(loopback_host: str) -> None:
    table = _table(4)
    with _primary_interface(loopback_host, table):
        arm = _arm(loopback_host)
        asyncio.run(asyncio.wait_for(arm._read_kinematics(), 10.0))
    assert arm.require_kinematics().dh == table and arm.dh == table and arm.planner.arm.dh == table
    # Its joint targets are the controller's: the table puts the flange where asked, the published one does not.
    T = kin.forward(np.asarray(CONFIG.robot.home_q), table)
    q = kin.inverse(T, np.asarray(CONFIG.robot.home_q), arm.dh)
    assert q is not None and np.allclose(kin.forward(q, table), T, atol=1e-9)


def test_a_table_of_another_model_is_not_taken_and_the_reason_kept(loopback_host: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(arm_mod, "KINEMATICS_RETRY", 0.05)
    with _primary_interface(loopback_host, kin.model("ur5e").dh):
        arm = _arm(loopback_host)

        async def scenario() -> None:
            task = asyncio.create_task(arm._read_kinematics())
            await asyncio.sleep(1.0)
            assert not task.done()  # it keeps trying
            task.cancel()

        asyncio.run(scenario())
    assert arm.kinematics is None and arm.dh == kin.UR10E
    with pytest.raises(DeviceError, match=r"robot\.model: .* mm from a ur10e's"):
        arm.require_kinematics()


def test_a_job_through_an_arm_calibration_made_on_another_table_is_refused() -> None:
    table = _table(5)
    controller = primary.ControllerKinematics(table, (0,) * 6, 2)
    on = Placement(ScannerMount(), np.eye(4), ArmModel.identity(table))
    assert for_controller(on, lambda: controller) is on
    with pytest.raises(CalibrationError, match="now computes with .*: calibrate again"):
        for_controller(Placement(ScannerMount(), np.eye(4), ArmModel.identity(kin.UR10E)), lambda: controller)
    # A hand-eye calibration alone holds on any table, and does not wait for it.
    hand_eye = Placement(ScannerMount(), np.eye(4))
    assert for_controller(hand_eye, lambda: (_ for _ in ()).throw(AssertionError("not asked"))) is hand_eye
