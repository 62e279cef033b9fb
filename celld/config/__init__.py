"""Cell configuration: TOML files loaded once into frozen, validated values.

A config is data. It is read and checked at start-up, before any device is
opened; a bad file is refused with a :class:`~celld.errors.ConfigError` that
names the file, the dotted key and the reason. Unknown keys are refused too,
so a typo never silently falls back to a default, and so are keys that were
renamed or moved (the message names the new key).

- :mod:`celld.config.reader`: :class:`TableReader` and the unit-suffix rule;
- :mod:`celld.config.sections`: cell, robot, motion, scanner, calibration,
  bus, recording, weld, sim, and the seam finder's table;
- :mod:`celld.config.tactile`: the SRM sensor, the tool and the servo, with
  the servo's bounds stated once;
- :mod:`celld.config.cell`: :class:`Config`, :func:`load` and :func:`parse`.
"""

from __future__ import annotations

from celld.config.cell import Config, load, parse
from celld.config.reader import TableReader
from celld.config.sections import (
    BUS_ROLES,
    SCANNER_KINDS,
    SCANNER_MODELS,
    BusConfig,
    BusTls,
    BusUser,
    CalibrationConfig,
    CellConfig,
    MotionLimits,
    RecordingConfig,
    RobotConfig,
    ScannerConfig,
    SimConfig,
    WeldConfig,
)
from celld.config.tactile import SERVO_BOUNDS, Bound, ServoConfig, TactileConfig, ToolConfig, check_servo, with_overrides

__all__ = [
    "BUS_ROLES", "SCANNER_KINDS", "SCANNER_MODELS", "SERVO_BOUNDS", "Bound", "BusConfig", "BusTls", "BusUser", "CalibrationConfig",
    "CellConfig", "Config", "MotionLimits", "RecordingConfig", "RobotConfig", "ScannerConfig", "ServoConfig", "SimConfig",
    "TableReader", "TactileConfig", "ToolConfig", "WeldConfig", "check_servo", "load", "parse", "with_overrides",
]
