"""The simulated cells of the end-to-end tests: their config files, and calibrations solved offline in their worlds.

:func:`write_cell_config` writes a test's cell config: the cell file it
includes, this test's own name, state directory, loopback address(es) and
bus endpoint, whether its jobs are recorded, and the tables the test sets
(deep-merged, the test's values winning). The ``cell_config`` fixture of
``tests/daemon/conftest.py`` is it on the test's ``tmp_path`` and address.

:func:`solve_offline` calibrates a cell's scanner in its simulated world
without robot or daemon (:func:`celld.sim.calib_demo.calibrate_in_world`: the
flange seen by the world's scanner where the world's arm truly puts it,
detected and solved as the calibrate job does; the truth is never read), and
:func:`stored_calibration` gives it the form the daemon keeps an accepted
calibration in (``<state_dir>/calibration.json``, as
``celld/daemon/calibrate.py`` writes it). Tests whose subject is what comes
after a calibration (a tool calibration, a weld) start from one of these; the
calibrate job itself is tested end to end in ``test_daemon_e2e.py`` and the
other e2e tests of a calibration.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from celld import config as config_mod
from celld import sealed
from celld.calib.dataset import SessionWriter
from celld.calib.mount import ScannerMount, in_frame
from celld.calib.solve import SolveParams
from celld.daemon.calibrate import calibration_entry
from celld.journal import new_job_id, utc_now
from celld.sim.calib_demo import OfflineCalibration, calibrate_in_world
from celld.sim.world import World

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
# The test cells move at speeds a UR10e runs in production (its joints reach 2.1-3.1 rad/s, its TCP 1 m/s),
# not at the cautious defaults of configs/robots/ur10e.toml (0.25 m/s, 1 rad/s): most of what a cell test
# costs is the arm moving between poses in real time. The simulated arm follows the commands kinematically,
# so what the tests check (every limit held as configured, the calibration, the weld) is the same; the
# realtime tests of tests/motion/test_process.py hold the limits at the defaults.
FAST_MOTION = {
    "max_linear_speed": 0.75,
    "max_linear_accel": 2.5,
    "max_linear_jerk": 25.0,
    "max_angular_speed": 2.0,
    "max_angular_accel": 8.0,
    "max_angular_jerk": 80.0,
    "max_joint_speed": 2.0,
    "max_joint_accel": 4.0,
    "max_joint_jerk": 40.0,
}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(int(value))
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"a cell config holds finite numbers only, got {value!r}")
        return repr(float(value))
    if isinstance(value, (str, Path)):
        return json.dumps(str(value))  # a JSON string of printable text is a TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {type(value).__name__} {value!r}")


def toml_text(doc: Mapping[str, Any]) -> str:
    """``doc`` as TOML: its top-level keys, then one ``[table]`` per mapping (nested as ``[a.b]``)."""
    lines: list[str] = []

    def table(name: str, body: Mapping[str, Any]) -> None:
        values = {k: v for k, v in body.items() if not isinstance(v, Mapping)}
        tables = {k: v for k, v in body.items() if isinstance(v, Mapping)}
        if name and (values or not tables):
            lines.append(f"[{name}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in values.items())
        for k, v in tables.items():
            table(f"{name}.{k}" if name else k, v)

    table("", doc)
    return "\n".join(lines) + "\n"


def merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` on top, tables merged key by key."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merged(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def write_cell_config(
    path: Path,
    include: str | Sequence[str],
    name: str,
    host: str,
    tables: Mapping[str, Any] | None = None,
    *,
    host2: str | None = None,
    recording: bool = True,
) -> Path:
    """Write a test's cell config at ``path`` and return it.

    ``include`` names the config file(s) under ``configs/`` it builds on.
    The cell is called ``name``, keeps its state beside ``path``
    (``state/``), runs its robot on ``host`` (a second robot on ``host2``)
    at :data:`FAST_MOTION`'s limits and its bus on ``tcp/<host>:7447``; with ``recording`` false its jobs
    write no rerun recording (for tests that never read one). ``tables``
    comes on top: ``{"sim": {"preset": "ideal", "scanner": {"resolution_scale": 0.5}}}``.
    """
    files = [include] if isinstance(include, str) else list(include)
    doc: dict[str, Any] = {
        "include": [str(CONFIGS / f) for f in files],
        "cell": {"name": name, "state_dir": str(path.parent / "state")},
        "robot": {"host": host},
        "bus": {"listen": [f"tcp/{host}:7447"]},
        "motion": dict(FAST_MOTION),
    }
    if host2 is not None:
        doc["robot2"] = {"host": host2}
    if not recording:
        doc["recording"] = {"enabled": False}
    path.write_text(toml_text(merged(doc, tables or {})))
    return path


def solve_offline(cfg: config_mod.Config, world: World, n_poses: int, seed: int, dataset: Path) -> OfflineCalibration:
    """The calibration of ``cfg``'s scanner in ``world`` from ``n_poses`` generated poses (every one: no early
    stop), its session saved in ``dataset`` as a calibrate job saves its own."""
    mount = ScannerMount.of(cfg.scanner.mount, cfg.robot.model)
    writer = SessionWriter(dataset, flange=cfg.calibration.flange, scanner=cfg.scanner.model, mount=mount)
    return calibrate_in_world(cfg, world, n_poses, seed, writer)


def stored_calibration(cfg: config_mod.Config, done: OfflineCalibration, dataset: Path, job: str | None = None) -> dict[str, Any]:
    """``done`` (its session saved in ``dataset``) as the daemon stores an accepted calibration
    (``calibration.json``): what the calibrate job offers (:func:`celld.daemon.calibrate.calibration_entry`),
    made by job ``job`` (a fresh job id by default; no journal holds it), and when it was accepted."""
    result = done.result
    mount = ScannerMount.of(cfg.scanner.mount, cfg.robot.model)
    report = in_frame(result.as_dict(), mount)
    entry = calibration_entry(
        job or new_job_id(), mount, result, report, SolveParams.from_config(cfg.calibration), dataset, result.algorithm1
    )
    # As an accept (with force, if its quality gate failed) makes it current.
    return {**entry, "accepted": utc_now(), **({} if result.quality.verdict == "ok" else {"forced": True})}


def install_calibration(state_dir: str | Path, calibration: Mapping[str, Any]) -> Path:
    """Make ``calibration`` the cell's current one, as an accept does (the daemon reads it at each job)."""
    path = Path(state_dir) / "calibration.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    sealed.write_sealed(path, calibration, "calibration")
    return path
