"""A cell with a device missing still starts and serves: its SRM camera missing, it calibrates and moves, refuses
welds and says why; its robot off at boot, it is ready for systemd at once, says what it waits for, refuses what
needs the robot until the robot is there, then runs it; another program on its robot (a pendant's, another
celld's), it leaves the robot alone unless told to take it over."""

from __future__ import annotations

from pathlib import Path

import pytest

from celld.errors import JobError
from celld.sim.cell import run_cell

pytestmark = pytest.mark.cell


def test_without_its_camera_the_daemon_runs_reports_it_and_refuses_welds(tmp_path: Path, cell_config) -> None:
    cfg = cell_config(
        "sim-cell.toml",
        "no-camera",
        {"sim": {"scanner": {"resolution_scale": 0.25}}, "tactile": {"kind": "opencv", "device": "/dev/celld-no-such-camera"}},
        recording=False,  # nothing here reads a recording
    )
    with run_cell(cfg, tmp_path / "daemon.log", timeout=90) as cell:
        client = cell.client
        _, health = client.submit_and_wait({"kind": "health", "check": "tactile"}, timeout=60)
        assert health["state"] == "failed" and "tactile process is not running" in health["reason"], health
        # Refused at once with the reason, not queued to fail.
        with pytest.raises(JobError, match="refused: finger camera not running: waiting"):
            client.submit({"kind": "weld"})
        _, robot = client.submit_and_wait({"kind": "health", "check": "robot"}, timeout=60)
        assert robot["state"] == "succeeded", robot["reason"]
        assert cell.daemon.poll() is None


def test_a_cell_that_boots_before_its_robot_is_ready_says_what_it_waits_for_and_refuses_moves_until_then(
    tmp_path: Path, cell_config, monkeypatch: pytest.MonkeyPatch
) -> None:
    from celld import config as config_mod
    from celld.sim.cell import launch, robot_options, start_daemon, stop_daemon, world_of
    from celld.sim.world import WorldOptions
    from tests.daemon.test_robot_faults_e2e import NotifyReceiver, _wait

    receiver = NotifyReceiver(tmp_path / "notify.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify.sock"))
    path = cell_config("sim-cell.toml", "robot-off", {"sim": {"scanner": {"resolution_scale": 0.25}}}, recording=False)
    cfg = config_mod.load(path)
    move = {"kind": "move", "target": {"space": "joint", "q": list(cfg.robot.home_q)}}
    try:
        with open(tmp_path / "daemon.log", "ab") as log:
            daemon = start_daemon(path, log, timeout=60, links=False)  # no robot at its address yet
            try:
                client = daemon.client
                # READY with the bus served, not held back by the robot: no restart loop under systemd.
                _wait(lambda: any(m == "READY=1" for _, m in receiver.messages), 30, "READY=1")
                status = _wait(lambda: (s := client.status())["robot_link"] != "up" and "waiting" in s["message"] and s, 10, "status")
                assert status["state"] == "fault" and status["message"].startswith("robot link down: waiting (no link to the robot")
                assert any(m.startswith("STATUS=cell robot-off: robot link down: waiting") for _, m in receiver.messages)
                with pytest.raises(JobError, match="refused: robot link down: waiting .*check the robot is on"):
                    client.submit(move)
                assert client.list() == []  # refused at once: nothing queued to fail later
                # A health job needs no device: it runs, and finds the scanner not open (the simulated one is
                # drawn from the robot's truth, so it waits for the robot too, tried again in the background).
                _, health = client.submit_and_wait({"kind": "health", "check": "scanner"}, timeout=30)
                assert health["state"] == "failed" and "the scanner is not open: no simulated robot" in health["reason"]

                w = world_of(cfg, WorldOptions())
                with launch(cfg.robot.host, realtime=True, q0=tuple(cfg.robot.home_q), **robot_options(w)):
                    _wait(lambda: client.status()["robot_link"] == "up", 40, "the link once the robot is on")
                    _wait(lambda: client.status()["state"] == "idle", 10, "the cell idle")
                    _, moved = client.submit_and_wait(move, timeout=60)
                    assert moved["state"] == "succeeded", moved["reason"]
                    assert daemon.process.poll() is None
                    # systemd's STATUS, said every second, no longer waits for the robot (the scanner and camera
                    # may still be on their back-off).
                    said = lambda: [m for _, m in receiver.messages if m.startswith("STATUS=cell robot-off: ")][-1]  # noqa: E731
                    _wait(lambda: "robot link down" not in said(), 5, "systemd's status without the robot's wait")
            finally:
                daemon.client.close()
                stop_daemon(daemon.process)
    finally:
        receiver.close()


def test_a_daemon_does_not_take_the_robot_from_another_program_or_celld_unless_told_to(tmp_path: Path, cell_config) -> None:
    from dashboard_client import DashboardClient

    from celld import config as config_mod
    from celld.sim.cell import launch, robot_options, start_daemon, stop_daemon, world_of
    from celld.sim.world import WorldOptions
    from tests.daemon.cells import write_cell_config
    from tests.daemon.test_robot_faults_e2e import _wait

    path = cell_config("sim-cell.toml", "held", {"sim": {"scanner": {"resolution_scale": 0.25}}}, recording=False)
    cfg = config_mod.load(path)
    move = {"kind": "move", "target": {"space": "joint", "q": list(cfg.robot.home_q)}}
    w = world_of(cfg, WorldOptions())
    with launch(cfg.robot.host, realtime=True, q0=tuple(cfg.robot.home_q), **robot_options(w)), open(tmp_path / "daemon.log", "ab") as log:
        dashboard = DashboardClient(cfg.robot.host)
        dashboard.connect()
        try:
            # Another controller's program runs on the robot (loaded and played from its dashboard).
            dashboard.loadURP("fixture.urp")
            dashboard.play()
            assert dashboard.programState().startswith("PLAYING fixture.urp")
            daemon = start_daemon(path, log, timeout=60, links=False)
            try:
                client = daemon.client
                status = _wait(lambda: "held by another program" in (s := client.status())["message"] and s, 20, "status")
                assert status["robot_link"] != "up" and "PLAYING fixture.urp runs on it" in status["message"]
                assert "--take-over" in status["message"]
                with pytest.raises(JobError, match="refused: robot held by another program: waiting"):
                    client.submit(move)
                assert dashboard.programState().startswith("PLAYING fixture.urp")  # left alone
                # Once it stops, the robot is celld's.
                dashboard.stop()
                _wait(lambda: client.status()["robot_link"] == "up", 30, "the link once the other program stopped")
                _, moved = client.submit_and_wait(move, timeout=60)
                assert moved["state"] == "succeeded", moved["reason"]
                # A second celld (its own state directory and bus) on the same robot finds this one's program
                # running and leaves it: the first one goes on moving the robot.
                second = tmp_path / "second"
                second.mkdir()
                tables = {"sim": {"scanner": {"resolution_scale": 0.25}}, "bus": {"listen": [f"tcp/{cfg.robot.host}:7448"]}}
                other = start_daemon(
                    write_cell_config(second / "cell.toml", "sim-cell.toml", "held2", cfg.robot.host, tables, recording=False),
                    log,
                    timeout=60,
                    links=False,
                )
                try:
                    said = _wait(lambda: "held by another program" in (s := other.client.status())["message"] and s, 20, "status")
                    assert "PLAYING rtde_control runs on it" in said["message"]
                    with pytest.raises(JobError, match="refused: robot held by another program"):
                        other.client.submit(move)
                    _, moved = client.submit_and_wait(move, timeout=60)
                    assert moved["state"] == "succeeded", moved["reason"]
                finally:
                    other.client.close()
                    stop_daemon(other.process)
            finally:
                daemon.client.close()
                stop_daemon(daemon.process)
            # Told to, it takes the robot at once.
            dashboard.loadURP("fixture.urp")
            dashboard.play()
            daemon = start_daemon(path, log, timeout=60, take_over=True)  # returns once the link is up
            try:
                assert not dashboard.programState().startswith("PLAYING fixture.urp")
                _, moved = daemon.client.submit_and_wait(move, timeout=60)
                assert moved["state"] == "succeeded", moved["reason"]
            finally:
                daemon.client.close()
                stop_daemon(daemon.process)
        finally:
            dashboard.disconnect()


def test_a_daemon_does_not_take_robot_2_from_another_program_either(tmp_path: Path, cell_config) -> None:
    """Robot 2 of a two-robot cell is checked like robot 1: another program on it keeps it, and while it runs
    nothing moves (robot 1 moves only beside robot 2 where it stands); once it stops, celld takes robot 2."""
    from dashboard_client import DashboardClient

    from celld import config as config_mod
    from celld.sim.cell import launch, robot2_options, robot_options, start_daemon, stop_daemon, world_of
    from celld.sim.world import WorldOptions
    from tests.daemon.test_robot_faults_e2e import _wait

    path = cell_config(
        "sim-cell-two-robots.toml", "held-robot2", {"sim": {"scanner": {"resolution_scale": 0.25}}}, robot2=True, recording=False
    )
    cfg = config_mod.load(path)
    assert cfg.robot2 is not None
    r2 = cfg.robot2.robot
    move = {"kind": "move", "target": {"space": "joint", "q": list(cfg.robot.home_q)}}
    w = world_of(cfg, WorldOptions())
    with (
        launch(cfg.robot.host, realtime=True, q0=tuple(cfg.robot.home_q), **robot_options(w)),
        launch(r2.host, realtime=True, q0=tuple(r2.home_q), **robot2_options(w)),
        open(tmp_path / "daemon.log", "ab") as log,
    ):
        dashboard = DashboardClient(r2.host)
        dashboard.connect()
        try:
            dashboard.loadURP("fixture.urp")
            dashboard.play()
            daemon = start_daemon(path, log, timeout=60, links=False)
            try:
                client = daemon.client
                status = _wait(lambda: "robot 2 held by another program" in (s := client.status())["message"] and s, 30, "status")
                assert "PLAYING fixture.urp runs on it" in status["message"] and "--take-over" in status["message"]
                assert status["robot"]["robot2_held"].startswith("PLAYING fixture.urp"), status["robot"]
                assert status["robot"]["robot2_link"] != "up"
                with pytest.raises(JobError, match="refused: robot 2 held by another program: waiting"):
                    client.submit(move)
                assert dashboard.programState().startswith("PLAYING fixture.urp")  # left alone
                dashboard.stop()
                _wait(lambda: client.status()["robot"]["robot2_link"] == "up", 30, "robot 2's link once the other program stopped")
                assert client.status()["robot"]["robot2_held"] is None
                _, moved = client.submit_and_wait(move, timeout=60)
                assert moved["state"] == "succeeded", moved["reason"]
            finally:
                daemon.client.close()
                stop_daemon(daemon.process)
        finally:
            dashboard.disconnect()
