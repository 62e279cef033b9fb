"""Weld procedures as data: one named, versioned TOML file each, read into a frozen :class:`WeldProcedure` (SI).

A procedure is the file ``<name>.toml`` in a procedures directory (this
repository's ``configs/procedures/``; on a cell, ``procedures/`` beside the
cell's config file, :func:`cell_procedures`). It holds what the power source
is set to (wire feed, voltage), how fast the torch travels, the arc's
sequence (pre-flow, strike, re-strikes, what an arc loss does, crater fill,
burn-back, post-flow) and the windows the weld's measured current and voltage
must stay in. A weld's result names the procedure by :attr:`WeldProcedure.ident`
(``name@version``) and carries :meth:`WeldProcedure.as_dict` and the digest of
the file as read, so every weld is traceable to the set points it ran with.

The file is flat TOML, read with :class:`~celld.config.reader.TableReader`:
every key carries its unit (:data:`KEYS`), converted to SI once here; values
out of range, unknown keys and keys in another unit are refused with a
:class:`~celld.errors.ConfigError` naming the file and the key.
"""

from __future__ import annotations

import hashlib
import re
import stat
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from celld.config.reader import TableReader
from celld.errors import ConfigError
from celld.schemadoc import enum, integer, number, obj, string, vector

# The processes a procedure may name: gas metal arc with an active gas (MAG) or an inert one (MIG), and TIG with a
# wire fed cold.
PROCESSES = ("MAG", "MIG", "TIG")
# What the cell does when the arc goes out mid-seam: strike again at the stop point after backing off along the
# welded path, or stop, retract and report the seam's unwelded length.
ARC_LOSS = ("restrike", "retract")
# Every key of a procedure file with the unit it is written in ("" for none): the file's whole vocabulary.
KEYS = {
    "name": "",
    "version": "",
    "description": "",
    "process": "",
    "wire_feed_m_min": "m/min",
    "voltage_v": "V",
    "travel_speed_mm_s": "mm/s",
    "preflow_s": "s",
    "strike_timeout_s": "s",
    "restrikes": "",
    "restrike_pause_s": "s",
    "arc_loss": "",
    "backoff_mm": "mm",
    "scratch_mm": "mm",
    "crater_s": "s",
    "crater_wire_feed_m_min": "m/min",
    "crater_voltage_v": "V",
    "burnback_s": "s",
    "postflow_s": "s",
    "current_window_a": "A",
    "voltage_window_v": "V",
    "window_grace_s": "s",
}
# How each unit ends its key's name.
_SUFFIX = {"m/min": "_m_min", "V": "_v", "mm/s": "_mm_s", "s": "_s", "mm": "_mm", "A": "_a"}
# Words that spell a unit in a key's name: a key that is a known one's stem plus these is the known key in
# another unit (travel_speed_m_s for travel_speed_mm_s), refused naming the key to use.
_UNIT_WORDS = frozenset(("m", "mm", "cm", "in", "ipm", "s", "ms", "min", "v", "mv", "kv", "a", "ma", "ka", "hz"))
# The file's size limit, bytes: a procedure is a few hundred bytes; anything this large is not one.
MAX_FILE_BYTES = 64 * 1024
# A procedure's name: a plain file stem of letters, digits, '-', '_' and '.', not starting with '.' or '-'.
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")
# The procedures directory of a cell: beside its config file.
CELL_DIRECTORY = "procedures"
# Unit conversions to SI.
_PER_MIN = 1.0 / 60.0
_MM = 1e-3
# The back-off when a procedure names none, as written (mm).
_BACKOFF_MM = 5.0
# A re-strike's scratch along the seam at most (mm): "a few millimetres" at the point it strikes.
_SCRATCH_MM = 2.0
_SCRATCH_MAX_MM = 5.0


@dataclass(frozen=True)
class WeldProcedure:
    """One weld procedure, SI inside (m, s, m/s, V, A).

    Attributes
    ----------
    name, version : str, int
        The file's stem and its version (>= 1): :attr:`ident` names the procedure in a weld's result.
    process : str
        One of :data:`PROCESSES`.
    wire_feed : float
        Wire feed speed, m/s.
    voltage : float
        Arc voltage set point, V.
    travel_speed : float
        The torch's speed along the seam, m/s.
    current_window, voltage_window : tuple of 2 float
        The (lo, hi) the weld's measured current (A) and voltage (V) must stay in.
    preflow : float
        Shielding gas before the arc, s.
    strike_timeout : float
        The arc must be stable within this after welding start, s.
    restrikes : int
        Further attempts after a failed start or an arc loss (0-5).
    restrike_pause : float
        Wait before each further attempt, s.
    arc_loss : str
        One of :data:`ARC_LOSS`.
    backoff : float
        How far back along the welded path the torch goes before a re-strike mid-seam, m.
    scratch : float
        How far a re-strike's scratch start moves the torch forward along the seam at most while the arc is not
        yet stable, m (0: re-strikes at rest); the torch then comes back to where it struck (0-5 mm).
    crater, crater_wire_feed, crater_voltage : float
        Crater fill at the seam's end: dwell (s), wire feed (m/s), voltage (V).
    burnback : float
        Wire burn-back after arc off, s.
    postflow : float
        Shielding gas after the arc, s.
    window_grace : float
        After each arc start the windows are not applied for this long while the arc settles, s.
    description : str
        Free text: what the procedure is for.
    digest : str
        SHA-256 of the file as read, hex ("" for a procedure not read from a file): tells two files of one
        name and version apart.
    """

    name: str
    version: int
    process: str
    wire_feed: float
    voltage: float
    travel_speed: float
    current_window: tuple[float, float]
    voltage_window: tuple[float, float]
    crater_wire_feed: float
    crater_voltage: float
    preflow: float = 0.3
    strike_timeout: float = 1.0
    restrikes: int = 1
    restrike_pause: float = 0.5
    arc_loss: str = "retract"
    backoff: float = _BACKOFF_MM * _MM
    scratch: float = _SCRATCH_MM * _MM
    crater: float = 0.3
    burnback: float = 0.05
    postflow: float = 1.0
    window_grace: float = 0.3
    description: str = ""
    digest: str = ""

    @property
    def ident(self) -> str:
        """``name@version``: how a weld's result and recording name the procedure."""
        return f"{self.name}@{self.version}"

    def as_dict(self) -> dict[str, Any]:
        """The procedure as a weld's result and recording carry it (:data:`PROCEDURE_SCHEMA`): SI, unit-suffixed keys."""
        return {
            "ident": self.ident,
            "name": self.name,
            "version": self.version,
            "process": self.process,
            "digest": self.digest,
            "wire_feed_m_s": self.wire_feed,
            "voltage_v": self.voltage,
            "travel_speed_m_s": self.travel_speed,
            "preflow_s": self.preflow,
            "strike_timeout_s": self.strike_timeout,
            "restrikes": self.restrikes,
            "restrike_pause_s": self.restrike_pause,
            "arc_loss": self.arc_loss,
            "backoff_m": self.backoff,
            "scratch_m": self.scratch,
            "crater_s": self.crater,
            "crater_wire_feed_m_s": self.crater_wire_feed,
            "crater_voltage_v": self.crater_voltage,
            "burnback_s": self.burnback,
            "postflow_s": self.postflow,
            "current_window_a": list(self.current_window),
            "voltage_window_v": list(self.voltage_window),
            "window_grace_s": self.window_grace,
        }


# The JSON shape of WeldProcedure.as_dict: every key always there.
_PROCEDURE_PROPERTIES = {
    "ident": string("name@version."),
    "name": string("The procedure file's stem."),
    "version": integer("The procedure's version.", lo=1),
    "process": enum(PROCESSES, "The welding process."),
    "digest": string("SHA-256 of the procedure file as read, hex; empty when it was not read from a file."),
    "wire_feed_m_s": number("Wire feed speed.", lo=0.0),
    "voltage_v": number("Arc voltage set point.", lo=0.0),
    "travel_speed_m_s": number("Travel speed along the seam.", lo=0.0),
    "preflow_s": number("Gas before the arc.", lo=0.0),
    "strike_timeout_s": number("The arc must be stable within this after welding start.", lo=0.0),
    "restrikes": integer("Further attempts after a failed start or an arc loss.", lo=0),
    "restrike_pause_s": number("Wait before each further attempt.", lo=0.0),
    "arc_loss": enum(ARC_LOSS, "What an arc loss mid-seam does."),
    "backoff_m": number("How far back along the welded path the torch goes before a re-strike.", lo=0.0),
    "scratch_m": number("How far a re-strike's scratch start goes along the seam at most (0: at rest).", lo=0.0),
    "crater_s": number("Crater fill dwell at the seam's end.", lo=0.0),
    "crater_wire_feed_m_s": number("Wire feed speed during the crater fill.", lo=0.0),
    "crater_voltage_v": number("Voltage during the crater fill.", lo=0.0),
    "burnback_s": number("Wire burn-back after arc off.", lo=0.0),
    "postflow_s": number("Gas after the arc.", lo=0.0),
    "current_window_a": vector("The (lo, hi) the measured current must stay in.", 2, lo=0.0),
    "voltage_window_v": vector("The (lo, hi) the measured voltage must stay in.", 2, lo=0.0),
    "window_grace_s": number("After each arc start the windows are not applied for this long.", lo=0.0),
}
PROCEDURE_SCHEMA = obj(
    "The weld procedure a weld was made with: its name and version, the file's digest, its set points and sequence "
    "(SI) and the windows its current and voltage were held to.",
    _PROCEDURE_PROPERTIES,
    _PROCEDURE_PROPERTIES,
)


def cell_procedures(config_file: Path) -> Path:
    """The procedures directory of the cell whose config file is ``config_file``: ``procedures/`` beside it."""
    return config_file.parent / CELL_DIRECTORY


def list_procedures(directory: Path) -> list[str]:
    """The names of the procedures in ``directory``, sorted (none when it does not exist)."""
    if not directory.is_dir():
        return []
    return sorted(p.stem for p in directory.glob("*.toml") if _NAME.match(p.stem) and p.is_file())


def load_procedure(directory: Path, name: str) -> WeldProcedure:
    """The procedure ``name`` from ``directory/<name>.toml``, checked.

    Raises
    ------
    ConfigError
        ``name`` is not a plain file stem (a path, ``..``, other characters); there is no such procedure (the
        message lists those there are); the file is not a regular file, is over :data:`MAX_FILE_BYTES`, is not
        UTF-8 TOML; or a value is refused (the file and the key named).
    """
    _check_name(directory, name)
    path = directory / f"{name}.toml"
    raw = _read_bytes(directory, name, path)
    source = str(path)
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(source, "", f"not UTF-8 text: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(source, "", f"not valid TOML: {exc}") from exc
    return parse(data, source, name, hashlib.sha256(raw).hexdigest())


def parse(data: dict[str, Any], source: str, stem: str, digest: str = "") -> WeldProcedure:
    """A procedure from its TOML table (``source`` names it in errors; ``stem`` is the name it must have).

    Raises
    ------
    ConfigError
        A key in another unit (naming the key to use), a value of the wrong type or out of range, a window whose
        lo is not below its hi, a name other than ``stem``, or an unknown key.
    """
    r = TableReader(data, source)
    _refuse_other_units(r, data)
    name = r.str("name")
    if name != stem:
        raise r.error("name", f"expected the file's name {stem!r}, got {name!r}")
    wire_feed = r.float("wire_feed_m_min", lo=0.5, hi=25.0, scale=_PER_MIN)
    voltage = r.float("voltage_v", lo=5.0, hi=50.0)
    procedure = WeldProcedure(
        name=name,
        version=r.int("version", lo=1, hi=1_000_000),
        process=r.str("process", choices=PROCESSES),
        wire_feed=wire_feed,
        voltage=voltage,
        travel_speed=r.float("travel_speed_mm_s", lo=1.0, hi=30.0, scale=_MM),
        current_window=_window(r, "current_window_a", 10.0, 600.0),
        voltage_window=_window(r, "voltage_window_v", 5.0, 60.0),
        preflow=r.float("preflow_s", WeldProcedure.preflow, lo=0.0, hi=5.0),
        strike_timeout=r.float("strike_timeout_s", WeldProcedure.strike_timeout, lo=0.05, hi=5.0),
        restrikes=r.int("restrikes", WeldProcedure.restrikes, lo=0, hi=5),
        restrike_pause=r.float("restrike_pause_s", WeldProcedure.restrike_pause, lo=0.0, hi=2.0),
        arc_loss=r.str("arc_loss", WeldProcedure.arc_loss, choices=ARC_LOSS),
        backoff=r.float("backoff_mm", _BACKOFF_MM, lo=0.0, hi=10.0, scale=_MM),
        scratch=r.float("scratch_mm", _SCRATCH_MM, lo=0.0, hi=_SCRATCH_MAX_MM, scale=_MM),
        crater=r.float("crater_s", WeldProcedure.crater, lo=0.0, hi=5.0),
        # The crater fill runs at the main set points unless it names its own: the same number scaled the same way.
        crater_wire_feed=r.float("crater_wire_feed_m_min", data["wire_feed_m_min"], lo=0.5, hi=25.0, scale=_PER_MIN),
        crater_voltage=r.float("crater_voltage_v", data["voltage_v"], lo=5.0, hi=50.0),
        burnback=r.float("burnback_s", WeldProcedure.burnback, lo=0.0, hi=1.0),
        postflow=r.float("postflow_s", WeldProcedure.postflow, lo=0.0, hi=10.0),
        window_grace=r.float("window_grace_s", WeldProcedure.window_grace, lo=0.0, hi=2.0),
        description=r.str("description", ""),
        digest=digest,
    )
    r.done()
    return procedure


def _check_name(directory: Path, name: str) -> None:
    """Refuse a procedure name that is not a plain file stem: it must not reach outside ``directory``."""
    if not isinstance(name, str):
        raise ConfigError(str(directory), "", f"expected a procedure name (a string), got {name!r}")
    if name.endswith(".toml"):
        raise ConfigError(str(directory), "", f"procedure name {name!r}: give the name without .toml")
    if not _NAME.match(name) or ".." in name:
        raise ConfigError(
            str(directory),
            "",
            f"procedure name {name!r}: expected a plain file stem of at most 64 letters, digits, '-', '_' and '.' "
            "(no path separators, no '..', not starting with '.' or '-')",
        )


def _read_bytes(directory: Path, name: str, path: Path) -> bytes:
    """The procedure file's bytes: a regular file of at most :data:`MAX_FILE_BYTES`, its size checked before it is read."""
    source = str(path)
    try:
        st = path.stat()
    except FileNotFoundError as exc:
        if not directory.is_dir():
            raise ConfigError(str(directory), "", f"no procedure {name!r}: the procedures directory does not exist") from exc
        names = list_procedures(directory)
        there = f"the procedures here: {', '.join(names)}" if names else "there are no procedures here"
        raise ConfigError(str(directory), "", f"no procedure {name!r} (no file {name}.toml); {there}") from exc
    except OSError as exc:
        raise ConfigError(source, "", f"cannot read: {exc}") from exc
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(source, "", "not a regular file (a device, a FIFO or a directory is no procedure)")
    if st.st_size > MAX_FILE_BYTES:
        raise ConfigError(source, "", f"{st.st_size} bytes: a procedure file is at most {MAX_FILE_BYTES} bytes")
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(source, "", f"cannot read: {exc}") from exc
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(source, "", f"it grew beyond {MAX_FILE_BYTES} bytes while it was read")
    return raw


def _refuse_other_units(r: TableReader, data: dict[str, Any]) -> None:
    """Refuse a key that is a known key in another unit (``travel_speed_m_s``), naming the key and unit to use.

    Checked before any value is read, so a file that writes a quantity in the wrong unit hears that, not that
    the right key is missing.
    """
    stems = {key.removesuffix(_SUFFIX[unit]): key for key, unit in KEYS.items() if unit}
    for key in data:
        if key in KEYS:
            continue
        matches = [s for s in stems if key == s or (key.startswith(s + "_") and set(key[len(s) + 1 :].split("_")) <= _UNIT_WORDS)]
        if matches:
            known = stems[max(matches, key=len)]
            raise r.error(key, f"expected {known} (in {KEYS[known]}): every key carries its unit")


def _window(r: TableReader, key: str, lo: float, hi: float) -> tuple[float, float]:
    """A [lo, hi] window, both ends within ``[lo, hi]`` and lo below hi."""
    window = r.vector(key, 2)
    if not all(lo <= v <= hi for v in window):
        raise r.error(key, f"expected both ends within {lo:g}-{hi:g} {KEYS[key]}, got {list(window)}")
    if not window[0] < window[1]:
        raise r.error(key, f"expected [lo, hi] with lo below hi, got {list(window)}")
    return window[0], window[1]
