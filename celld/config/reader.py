"""Reading one TOML table: typed getters that check range and name the key.

:class:`TableReader` is how every config section (and the seam finder's
``[seam]`` table) reads its values: each getter checks the type and range and
raises :class:`~celld.errors.ConfigError` naming the file and the dotted key;
:meth:`TableReader.done` refuses keys no getter asked for, and
:meth:`TableReader.refuse_moved` keys that were renamed or moved.

Key names carry their unit (README, "Configuration"): times end in ``_s`` or
``_ms``; lengths are metres unsuffixed (or ``_m``) or millimetres ``_mm``;
angles radians unsuffixed or degrees ``_deg``; speeds m/s unsuffixed or
``_mm_s``; rates ``_hz``; pixels ``_px``. A getter's ``scale`` converts to SI
once, here.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

from celld.errors import ConfigError, InputError
from celld.se3 import check_transform

_REQUIRED = object()


class TableReader:
    """Reads typed values out of one TOML table and tracks which keys were used.

    Every getter checks the type and range and raises ConfigError with the file
    and the dotted key. :meth:`done` refuses any key that no getter asked for.
    """

    def __init__(self, table: dict[str, Any], source: str, prefix: str = "") -> None:
        if not isinstance(table, dict):
            raise ConfigError(source, prefix, f"expected a table, got {type(table).__name__}")
        self._table = table
        self.source = source
        self.prefix = prefix
        self._used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def error(self, name: str, reason: str) -> ConfigError:
        return ConfigError(self.source, self.key(name), reason)

    def has(self, name: str) -> bool:
        return name in self._table

    def refuse_moved(self, moved: Mapping[str, str]) -> None:
        """Refuse keys that were renamed or moved, naming where each went.

        ``moved`` maps an old key to its new place, e.g. ``{"settle":
        "calibration.settle_s (seconds)"}``; a file that still has an old key is
        refused rather than silently read with the default.
        """
        for old, new in moved.items():
            if old in self._table:
                raise self.error(old, f"this key is now {new}")

    def _get(self, name: str, default: Any) -> Any:
        self._used.add(name)
        if name in self._table:
            return self._table[name]
        if default is _REQUIRED:
            raise self.error(name, "required key is missing")
        return default

    def str(self, name: str, default: Any = None, choices: Sequence[str] | None = None) -> str:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, str):
            raise self.error(name, f"expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise self.error(name, f"expected one of {', '.join(choices)}, got {value!r}")
        return value

    def bool(self, name: str, default: Any = None) -> bool:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, bool):
            raise self.error(name, f"expected true or false, got {value!r}")
        return value

    def int(self, name: str, default: Any = None, lo: float = -math.inf, hi: float = math.inf) -> int:
        value = self._get(name, _REQUIRED if default is None else default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(name, f"expected an integer, got {value!r}")
        if not lo <= value <= hi:
            raise self.error(name, f"expected {lo} <= value <= {hi}, got {value}")
        return value

    def float(
        self,
        name: str,
        default: Any = None,
        lo: float = -math.inf,
        hi: float = math.inf,
        scale: float = 1.0,
        open_lo: bool = False,
    ) -> float:
        """A finite number in [lo, hi] (bounds in the file's units), times ``scale``."""
        value = self._get(name, _REQUIRED if default is None else default)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(name, f"expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(name, f"expected a finite number, got {value}")
        if value < lo or value > hi or (open_lo and value <= lo):
            op = "<" if open_lo else "<="
            raise self.error(name, f"expected {lo} {op} value <= {hi}, got {value}")
        return value * scale

    def vector(self, name: str, length: int, default: Any = None, scale: float = 1.0) -> tuple[float, ...]:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, (list, tuple)) or len(value) != length:
            raise self.error(name, f"expected a list of {length} numbers, got {value!r}")
        out = []
        for v in value:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise self.error(name, f"expected finite numbers, got {v!r}")
            out.append(float(v) * scale)
        return tuple(out)

    def matrix4(self, name: str, default: Any = None) -> tuple[tuple[float, ...], ...]:
        """A (4, 4) rigid transform given as 4 rows of 4 numbers (metres)."""
        value = self._get(name, _REQUIRED if default is None else default)
        try:
            T = check_transform(value, self.key(name))
        except (InputError, ValueError, TypeError) as exc:
            raise self.error(name, f"expected a 4x4 rigid transform: {exc}") from exc
        return tuple(tuple(float(x) for x in row) for row in T)

    def table(self, name: str, required: bool = False) -> "TableReader":
        value = self._get(name, _REQUIRED if required else {})
        return TableReader(value, self.source, self.key(name))

    def done(self) -> None:
        """Refuse keys that no getter asked for (typos, stale options)."""
        unknown = sorted(set(self._table) - self._used)
        if unknown:
            raise ConfigError(self.source, self.key(unknown[0]), f"unknown key (known here: {', '.join(sorted(self._used)) or 'none'})")
