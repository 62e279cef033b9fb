"""The bus subcommands of ``celld``, against a cell served on loopback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import structlog

from celld.bus import requests, wire
from celld.cli import main
from celld.config import BusUser


@pytest.fixture(autouse=True)
def _unconfigured_logging():
    # main() binds structlog to the captured stderr of this test; let the next test start clean.
    yield
    structlog.reset_defaults()


def write_config(tmp_path: Path, cell) -> str:
    path = tmp_path / "cell.toml"
    listen = ", ".join(f'"{e}"' for e in cell.bus.listen)
    path.write_text(f'[cell]\nname = "{cell.keys.cell}"\n\n[bus]\nlisten = [{listen}]\nconnect_timeout_s = 2.0\nquery_timeout_s = 3.0\n')
    return str(path)


@pytest.fixture
def served(serve_cell, capsys: pytest.CaptureFixture[str]):
    """A cell, with what its start-up logged cleared from the captured output."""

    def make(**options):
        cell = serve_cell(**options)
        capsys.readouterr()
        return cell

    return make


def test_submit_wait_status_jobs_cancel(served, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cell = served()
    cfg = write_config(tmp_path, cell)
    assert main(["submit", "health", "--config", cfg, "--wait", "--ref", "night-shift"]) == 0
    out, err = capsys.readouterr()
    job = out.split()[0]
    assert out.strip().startswith(f"{job} health succeeded -> ") and out.strip().endswith(f"results/{job}.json")
    assert "running wait 0%" in err and "succeeded end 100%" in err

    assert main(["submit", "move", "--config", cfg, "--joints", "0", "-1.57", "1.57", "-1.57", "-1.57", "0", "--json"]) == 0
    reply = json.loads(capsys.readouterr().out)
    assert reply["ok"] and reply["state"] in ("running", "queued")

    assert main(["jobs", "--config", cfg, "--json"]) == 0
    jobs = json.loads(capsys.readouterr().out)
    assert [j["kind"] for j in jobs] == ["move", "health"] and jobs[1]["ref"] == "night-shift"

    assert main(["status", "--config", cfg, "--job", job]) == 0
    assert capsys.readouterr().out.strip().startswith(f"{job} health succeeded -> ")

    assert main(["status", "--all", "--config", cfg, "--json"]) == 0
    assert [s["cell"] for s in json.loads(capsys.readouterr().out)] == [cell.keys.cell]

    assert main(["cancel", job, "--config", cfg]) == 2
    assert "has already ended (succeeded)" in capsys.readouterr().err


def test_result_and_request_id_from_the_command_line(served, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cell = served()
    cfg = write_config(tmp_path, cell)
    assert main(["submit", "health", "--config", cfg, "--wait", "--request-id", "cli-1"]) == 0
    job = capsys.readouterr().out.split()[0]
    assert main(["submit", "health", "--config", cfg, "--request-id", "cli-1"]) == 0
    assert capsys.readouterr().out.startswith(f"{job} succeeded (replayed")
    assert main(["result", job, "--config", cfg, "--json"]) == 0
    reply = json.loads(capsys.readouterr().out)
    assert reply["state"] == "succeeded" and reply["result"]["waited_s"] == pytest.approx(0.05)
    assert main(["result", job, "--config", cfg, "--out", str(tmp_path / "r.json")]) == 0
    assert json.loads((tmp_path / "r.json").read_text()) == reply["result"]


def test_bad_parameters_are_refused_before_sending(served, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cell = served()
    cfg = write_config(tmp_path, cell)
    assert main(["submit", "calibrate", "--config", cfg, "--n-poses", "3"]) == 2
    assert capsys.readouterr().err.strip() == "celld: error: $.n_poses: expected a value >= 4, got 3"
    job_file = tmp_path / "job.json"
    job_file.write_text('{"kind": "weld", "delta_d_mm": 1.5, "speed": 3}')
    assert main(["submit", "file", str(job_file), "--config", cfg]) == 2
    assert "$.speed: unknown field" in capsys.readouterr().err
    assert cell.server.stats.requests == 0 and cell.journal.jobs() == []


def test_accept_with_force(served, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # The dummy cell's calibration carries no quality verdict: accepted as before; --force is sent and taken.
    cell = served()
    cfg = write_config(tmp_path, cell)
    assert main(["submit", "calibrate", "--config", cfg, "--wait"]) == 0
    job = capsys.readouterr().out.split()[0]
    assert main(["accept", job, "--force", "--config", cfg, "--json"]) == 0
    reply = json.loads(capsys.readouterr().out)
    assert reply["ok"] and reply["calibration"]["job"] == job and "forced" not in reply["calibration"]


def test_viewer_credentials_cannot_submit(served, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cell = served(users=(BusUser("vic", "view-secret", "viewer"),))
    cfg = write_config(tmp_path, cell)
    password = tmp_path / "password"
    password.write_text("view-secret\n")
    common = ["--config", cfg, "--user", "vic", "--password-file", str(password)]
    assert main(["status", *common]) == 0
    assert capsys.readouterr().out.startswith(f"{cell.keys.cell}: idle")
    assert main(["submit", "health", *common]) == 2
    assert "no reply" in capsys.readouterr().err
    assert cell.journal.jobs() == []


def test_submit_tool_calibrate_builds_its_message() -> None:
    import argparse

    from celld.bus.cli import _job_message, add_parser

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(
        [
            "submit",
            "tool-calibrate",
            "--n-poses",
            "9",
            "--max-tilt-deg",
            "15",
            "--tip-position",
            "0.6",
            "0",
            "0.45",
            "--seed",
            "4",
            "--dry-run",
            "--ref",
            "tool-7",
        ]
    )
    message = _job_message(args)
    assert message == {
        "kind": "tool-calibrate",
        "n_poses": 9,
        "max_tilt_deg": 15.0,
        "tip_position": [0.6, 0.0, 0.45],
        "seed": 4,
        "dry_run": True,
        "ref": "tool-7",
    }
    assert requests.parse_submit(wire.encode(message)) == requests.ToolCalibrateJob(
        n_poses=9, max_tilt=pytest.approx(0.2617993877991494), tip_position=(0.6, 0.0, 0.45), seed=4, dry_run=True, ref="tool-7"
    )


def test_submit_move_of_the_second_robot_builds_its_message(capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from celld.bus.cli import _job_message, add_parser

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(["submit", "move", "--pose", "0.65", "0", "0.45", "0", "0", "0", "--robot", "2"])
    message = _job_message(args)
    assert message == {"kind": "move", "target": {"space": "cartesian", "pose": [0.65, 0.0, 0.45, 0.0, 0.0, 0.0]}, "robot": 2}
    assert requests.parse_submit(wire.encode(message)) == requests.MoveJob("cartesian", (0.65, 0.0, 0.45, 0.0, 0.0, 0.0), robot=2)
    with pytest.raises(SystemExit):
        parser.parse_args(["submit", "move", "--joints", "0", "0", "0", "0", "0", "0", "--robot", "3"])
    assert "invalid choice: 3" in capsys.readouterr().err


def test_the_config_comes_from_celld_config_when_no_option_names_one(monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    from celld.bus.cli import add_parser
    from celld.cliparse import SYSTEM_CONFIG
    from celld.daemon.cli import add_parser as add_daemon_parser

    def parsed(*argv: str) -> argparse.Namespace:
        parser = argparse.ArgumentParser()
        sub = parser.add_subparsers(dest="cmd")
        add_parser(sub)
        add_daemon_parser(sub)
        return parser.parse_args(list(argv))

    monkeypatch.delenv("CELLD_CONFIG", raising=False)
    assert parsed("status").config == SYSTEM_CONFIG and parsed("run").config == SYSTEM_CONFIG
    monkeypatch.setenv("CELLD_CONFIG", "configs/sim-cell.toml")
    assert parsed("status").config == "configs/sim-cell.toml" and parsed("run").config == "configs/sim-cell.toml"
    assert parsed("journal", "check").config == "configs/sim-cell.toml"
    assert parsed("status", "--config", "other.toml").config == "other.toml"  # the option wins
    monkeypatch.setenv("CELLD_CONFIG", "  ")  # set but empty: as if unset
    assert parsed("status").config == SYSTEM_CONFIG
