"""Cell configuration: TOML files loaded once into frozen, validated values.

A config is data. It is read and checked at start-up, before any device is
opened; a bad file is refused with a :class:`~celld.errors.ConfigError` that
names the file, the dotted key and the reason. Unknown keys are refused too,
so a typo never silently falls back to a default, and so are keys that were
renamed or moved (the message names the new key).

- :mod:`celld.config.reader`: :class:`TableReader` and the unit-suffix rule;
- :mod:`celld.config.sections`: cell, robot, motion, scanner, calibration,
  bus, recording, weld; the ``[sim]`` table is
  kept raw in :attr:`Config.sim` (only a table is required): the simulator
  reads and checks it (:mod:`celld.sim.world`), production code never does;
- :mod:`celld.config.tactile`: the SRM sensor, the tool and the servo, with
  the servo's bounds stated once;
- :mod:`celld.config.seam`: the seam finder's parameters, its presets per
  scanner and the ``[seam]`` table;
- :mod:`celld.config.cell`: :class:`Config`, :func:`load` and :func:`parse`.
"""

from __future__ import annotations

from celld.config.cell import Config, load, parse
from celld.config.reader import TableReader
from celld.config.sections import (
    BUS_ROLES,
    RANGE_BIAS_MODES,
    SCANNER_KINDS,
    SCANNER_MODELS,
    SCANNER_MOUNTS,
    BusConfig,
    BusTls,
    BusUser,
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
from celld.config.tactile import SERVO_BOUNDS, Bound, ServoConfig, TactileConfig, ToolConfig, check_servo, with_overrides

__all__ = [
    "BUS_ROLES",
    "RANGE_BIAS_MODES",
    "SCANNER_KINDS",
    "SCANNER_MODELS",
    "SCANNER_MOUNTS",
    "SERVO_BOUNDS",
    "Bound",
    "BusConfig",
    "BusTls",
    "BusUser",
    "CalibrationConfig",
    "CellConfig",
    "Config",
    "MotionLimits",
    "RecordingConfig",
    "Robot2Config",
    "RobotConfig",
    "ScannerConfig",
    "ServoConfig",
    "TableReader",
    "TactileConfig",
    "ToolConfig",
    "WeldConfig",
    "check_servo",
    "load",
    "parse",
    "range_bias_default",
    "with_overrides",
]
