"""The whole cell config: the sections together, the files and their includes.

A file may ``include = ["robots/ur10e.toml", ...]`` other files (paths relative
to it); later values override earlier ones, table by table. :func:`load`
reads a file and its includes, :func:`parse` validates the merged tables into
a :class:`Config`: every section, then the rules between sections
(:func:`~celld.config.tactile.check_servo`), and the defaults that depend on
another section (``calibration.range_bias`` on the scanner).
"""

from __future__ import annotations

import copy
import stat
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from celld.config.cell_model import read_cell_model
from celld.config.power_source import PowerSourceConfig
from celld.config.reader import TableReader
from celld.config.seam import SeamParams, read_seam
from celld.config.sections import (
    BusConfig,
    CalibrationConfig,
    CellConfig,
    MotionLimits,
    RecordingConfig,
    Robot2Config,
    RobotConfig,
    ScannerConfig,
    WeldConfig,
    range_bias_default,
)
from celld.config.tactile import ServoConfig, TactileConfig, ToolConfig, check_servo
from celld.errors import ConfigError
from celld.robot.cellmodel import CellModel


@dataclass(frozen=True)
class Config:
    """The whole cell configuration; every section validated."""

    source: str = "<defaults>"
    cell: CellConfig = field(default_factory=CellConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    motion: MotionLimits = field(default_factory=MotionLimits)
    scanner: ScannerConfig = field(default_factory=ScannerConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    tactile: TactileConfig = field(default_factory=TactileConfig)
    tool: ToolConfig = field(default_factory=ToolConfig)
    servo: ServoConfig = field(default_factory=ServoConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    weld: WeldConfig = field(default_factory=WeldConfig)
    # The welding power source on the robot's I/O ([power_source]); empty: the arc is robot.arc_output alone.
    power_source: PowerSourceConfig = field(default_factory=PowerSourceConfig)
    # The seam finder: the scanner's preset, with the file's [seam] table over it.
    seam: SeamParams = field(default_factory=SeamParams)
    # What the arm and its tool must not hit: the cell's objects, the tool, the margin.
    cell_model: CellModel = field(default_factory=CellModel.default)
    # The simulated cell's own description of the true cell ([sim]), kept as
    # the raw table: only the simulator reads and checks it (celld.sim.world).
    sim: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    # A second robot in view of the scanner ([robot2]), None for a one-robot cell.
    robot2: Robot2Config | None = None
    # The tables the file gave (a daemon's config must give [robot]: celld.preflight); not a key of the file.
    tables: frozenset[str] = field(default=frozenset(), compare=False, metadata={"derived": True})
    # Every key the config read, by the file's own names and in its units, defaults filled in
    # (:attr:`celld.config.reader.TableReader.resolved`): what `celld config check --json` prints.
    resolved: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False, metadata={"derived": True})

    def T_base_cam_nominal(self) -> np.ndarray:
        return np.array(self.scanner.T_base_cam, dtype=np.float64)


# The sections each read from their own table, in order.
_SECTIONS: dict[str, Callable[[TableReader], Any]] = {
    "cell": CellConfig.read,
    "robot": RobotConfig.read,
    "motion": MotionLimits.read,
    "scanner": ScannerConfig.read,
    "calibration": CalibrationConfig.read,
    "tactile": TactileConfig.read,
    "tool": ToolConfig.read,
    "servo": ServoConfig.read,
    "bus": BusConfig.read,
    "recording": RecordingConfig.read,
    "weld": WeldConfig.read,
    "power_source": PowerSourceConfig.read,
    "sim": lambda r: MappingProxyType(copy.deepcopy(r.raw())),
}


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


# A config file (or an include) larger than this is no config: refused before it is read, bytes.
MAX_FILE_BYTES = 1 << 20


def _resolve(path: Path, source: str, key: str) -> Path:
    """``path`` with every link followed; a missing file or a symlink loop refused (an include named by its path)."""
    what = f"{path}: " if key else ""
    try:
        return path.resolve(strict=True)
    except FileNotFoundError as exc:
        raise ConfigError(source, key, f"{what}file not found") from exc
    except (RuntimeError, OSError) as exc:  # Python 3.11 says RuntimeError for a symlink loop
        raise ConfigError(source, key, f"{what}cannot follow its links (a symlink loop?): {exc}") from exc


def _read_text(path: Path, source: str) -> str:
    """A config file's text: only a regular file of at most :data:`MAX_FILE_BYTES` (a device such as /dev/zero or a
    FIFO would never end)."""
    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(source, "", "not a regular file (a device, a FIFO or a directory is no config)")
        if st.st_size > MAX_FILE_BYTES:
            raise ConfigError(source, "", f"{st.st_size} bytes: a config file is at most {MAX_FILE_BYTES} bytes")
        with path.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
        if len(raw) > MAX_FILE_BYTES:
            raise ConfigError(source, "", f"it grew beyond {MAX_FILE_BYTES} bytes while it was read")
        return raw.decode("utf-8")
    except FileNotFoundError as exc:
        raise ConfigError(source, "", "file not found") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(source, "", f"cannot read: {exc}") from exc


def _read_toml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    source = str(path)
    if path in seen:
        raise ConfigError(source, "include", "include cycle: " + " -> ".join(str(p) for p in (*seen, path)))
    text = _read_text(path, source)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(source, "", f"not valid TOML: {exc}") from exc
    includes = data.pop("include", [])
    if not isinstance(includes, list) or not all(isinstance(i, str) for i in includes):
        raise ConfigError(source, "include", f"expected a list of file paths, got {includes!r}")
    merged: dict[str, Any] = {}
    for inc in includes:
        target = _resolve(path.parent / inc, source, "include")
        merged = _merge(merged, _read_toml(target, (*seen, path)))
    return _merge(merged, data)


def parse(data: dict[str, Any], source: str = "<dict>") -> Config:
    """Validate a TOML-shaped dict into a :class:`Config`."""
    top = TableReader(data, source)
    values: dict[str, Any] = {"source": source, "tables": frozenset(k for k, v in data.items() if isinstance(v, dict))}
    for name, reader in _SECTIONS.items():
        sub = top.table(name)
        values[name] = reader(sub)
        sub.done()
    sub = top.table("seam")
    values["seam"] = read_seam(sub, values["scanner"].model, values["tool"].wall_side)
    sub.done()
    sub = top.table("cell_model")
    values["cell_model"] = read_cell_model(sub)
    sub.done()
    if top.has("robot2"):
        sub = top.table("robot2")
        values["robot2"] = Robot2Config.read(sub)
        sub.done()
    top.done()
    values["resolved"] = top.resolved
    check_servo(values["servo"], values["tactile"], values["tool"], source, values["motion"].max_linear_speed)
    if values["calibration"].range_bias is None:
        values["calibration"] = replace(
            values["calibration"], range_bias=range_bias_default(values["scanner"].kind, values["scanner"].model)
        )
    config = Config(**values)
    check_cell(config)
    return config


def check_cell(config: Config) -> None:
    """The rules between sections; raises ConfigError naming the key.

    - the poses the cell moves to (the verification pose of a calibration,
      the weld's scan pose) lie inside the workspace box;
    - the arc has one switch: ``robot.arc_output`` or ``power_source.arc_start``.

    The servo's rules (its speeds within the motion limits among them) are
    :func:`~celld.config.tactile.check_servo`'s.
    """
    src = config.source
    lo, hi = config.robot.workspace_min, config.robot.workspace_max
    for key, pose in (("calibration.verification_pose", config.calibration.verification_pose), ("weld.scan_pose", config.weld.scan_pose)):
        if not all(lo[i] <= pose[i] <= hi[i] for i in range(3)):
            raise ConfigError(src, key, f"expected a position inside the workspace box {list(lo)} .. {list(hi)} m, got {list(pose[:3])}")
    if config.power_source.enabled and config.robot.arc_output >= 0:
        raise ConfigError(
            src, "robot.arc_output", "a cell with a [power_source] starts its arc with power_source.arc_start: leave arc_output out"
        )
    r2 = config.robot2
    if r2 is not None:
        if r2.robot.host == config.robot.host:
            raise ConfigError(src, "robot2.host", f"expected the second robot's own address, got robot.host's {r2.robot.host!r}")
        if config.scanner.mount != "base":
            raise ConfigError(
                src, "robot2", f"two robots are calibrated through a scanner fixed in the cell, not one on {config.scanner.mount}"
            )


def load(path: str | Path) -> Config:
    """Load and validate a config file (and its includes).

    Raises
    ------
    ConfigError
        The file, the dotted key and the reason of the first problem found.
    """
    path = _resolve(Path(path), str(path), "")
    data = _read_toml(path)
    if not data:
        raise ConfigError(str(path), "", "the config is empty: a cell's config names at least its [cell] and [robot]")
    return parse(data, str(path))
