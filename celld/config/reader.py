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

import builtins
import math
from collections.abc import Mapping, Sequence
from typing import Any

from celld.errors import ConfigError, InputError
from celld.se3 import check_transform

_REQUIRED = object()


class TableReader:
    """Reads typed values out of one TOML table and tracks which keys were used.

    Every getter checks the type and range and raises ConfigError with the file
    and the dotted key. :meth:`done` refuses any key that no getter asked for.
    """

    def __init__(self, table: dict[builtins.str, Any], source: builtins.str, prefix: builtins.str = "") -> None:
        if not isinstance(table, dict):
            raise ConfigError(source, prefix, f"expected a table, got {type(table).__name__}")
        self._table = table
        self.source = source
        self.prefix = prefix
        self._used: set[str] = set()
        # Every key a getter asked for, under the file's own name and in the file's units: the value the file gave,
        # else the default it fell back to; a table's as its own such mapping (what `celld config check --json` prints).
        self.resolved: dict[str, Any] = {}

    def key(self, name: builtins.str) -> builtins.str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def error(self, name: builtins.str, reason: builtins.str) -> ConfigError:
        return ConfigError(self.source, self.key(name), reason)

    def has(self, name: builtins.str) -> builtins.bool:
        return name in self._table

    def refuse_moved(self, moved: Mapping[builtins.str, builtins.str]) -> None:
        """Refuse keys that were renamed or moved, naming where each went.

        ``moved`` maps an old key to its new place, e.g. ``{"settle":
        "calibration.settle_s (seconds)"}``; a file that still has an old key is
        refused rather than silently read with the default.
        """
        for old, new in moved.items():
            if old in self._table:
                raise self.error(old, f"this key is now {new}")

    def _get(self, name: builtins.str, default: Any) -> Any:
        self._used.add(name)
        if name in self._table:
            value = self._table[name]
        elif default is _REQUIRED:
            raise self.error(name, "required key is missing")
        else:
            value = default
        self.resolved[name] = value
        return value

    def str(self, name: builtins.str, default: Any = None, choices: Sequence[builtins.str] | None = None) -> builtins.str:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, str):
            raise self.error(name, f"expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise self.error(name, f"expected one of {', '.join(choices)}, got {value!r}")
        return value

    def bool(self, name: builtins.str, default: Any = None) -> builtins.bool:
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, bool):
            raise self.error(name, f"expected true or false, got {value!r}")
        return value

    def int(self, name: builtins.str, default: Any = None, lo: builtins.float = -math.inf, hi: builtins.float = math.inf) -> builtins.int:
        value = self._get(name, _REQUIRED if default is None else default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(name, f"expected an integer, got {value!r}")
        if not lo <= value <= hi:
            raise self.error(name, f"expected {lo} <= value <= {hi}, got {value}")
        return value

    def float(
        self,
        name: builtins.str,
        default: Any = None,
        lo: builtins.float = -math.inf,
        hi: builtins.float = math.inf,
        scale: builtins.float = 1.0,
        open_lo: builtins.bool = False,
    ) -> builtins.float:
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

    def vector(
        self,
        name: builtins.str,
        length: builtins.int,
        default: Any = None,
        scale: builtins.float = 1.0,
        bound: builtins.float = math.inf,
        what: builtins.str = "",
    ) -> tuple[builtins.float, ...]:
        """A list of ``length`` finite numbers (times ``scale``), each within +-``bound`` as written (``what`` says why)."""
        value = self._get(name, _REQUIRED if default is None else default)
        if not isinstance(value, (list, tuple)) or len(value) != length:
            raise self.error(name, f"expected a list of {length} numbers, got {value!r}")
        out = []
        for v in value:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise self.error(name, f"expected finite numbers, got {v!r}")
            if abs(float(v)) > bound:
                raise self.error(name, f"expected every value within +-{bound:g}{what}, got {v!r}")
            out.append(float(v) * scale)
        return tuple(out)

    def matrix4(self, name: builtins.str, default: Any = None) -> tuple[tuple[builtins.float, ...], ...]:
        """A (4, 4) rigid transform given as 4 rows of 4 numbers (metres)."""
        value = self._get(name, _REQUIRED if default is None else default)
        try:
            T = check_transform(value, self.key(name))
        except (InputError, ValueError, TypeError) as exc:
            raise self.error(name, f"expected a 4x4 rigid transform: {exc}") from exc
        return tuple(tuple(float(x) for x in row) for row in T)

    def tables(self, name: builtins.str) -> list[TableReader]:
        """An array of tables ``[[name]]`` (empty when absent), a reader each."""
        raw = self._get(name, [])
        if not isinstance(raw, list):
            raise self.error(name, f"expected an array of tables [[{self.key(name)}]], got {type(raw).__name__}")
        readers = [TableReader(t, self.source, self.key(f"{name}[{i}]")) for i, t in enumerate(raw)]
        self.resolved[name] = [r.resolved for r in readers]
        return readers

    def names(self, name: builtins.str) -> tuple[builtins.str, ...]:
        """A list of non-empty strings (empty when absent)."""
        value = self._get(name, [])
        if not isinstance(value, list) or not all(isinstance(v, builtins.str) and v for v in value):
            raise self.error(name, f"expected a list of names, got {value!r}")
        return tuple(value)

    def table(self, name: builtins.str, required: builtins.bool = False) -> TableReader:
        value = self._get(name, _REQUIRED if required else {})
        reader = TableReader(value, self.source, self.key(name))
        self.resolved[name] = reader.resolved
        return reader

    def raw(self) -> dict[builtins.str, Any]:
        """The whole table as it is, every key counted as read: for a table that another layer validates."""
        self._used.update(self._table)
        self.resolved.update(self._table)
        return self._table

    def done(self) -> None:
        """Refuse keys that no getter asked for (typos, stale options)."""
        unknown = sorted(set(self._table) - self._used)
        if unknown:
            raise ConfigError(self.source, self.key(unknown[0]), f"unknown key (known here: {', '.join(sorted(self._used)) or 'none'})")
