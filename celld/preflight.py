"""What a config names, checked against this machine and this code before the cell starts.

:func:`celld.config.load` checks a config on its own (types, ranges, the
rules between sections) and is pure. :func:`preflight` checks what only the
installed code and the machine can say: the flange preset and the tag
dictionary exist, the state directory can be written, the TLS files of
``[bus.tls]`` can be read; and that a daemon's config names its robot (a
config without ``[robot]`` would drive 127.0.0.1; a client's needs none).
``celld config check`` prints its findings; the daemon refuses to start
with any.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

from celld.config import Config
from celld.errors import ConfigError, InputError


class Finding(NamedTuple):
    key: str  # dotted config key
    reason: str


def _writable_dir(path: Path) -> str:
    """Why ``path`` cannot be (made and) written, or ""."""
    p = path.resolve()
    probe = p
    while not probe.exists():
        if probe.parent == probe:
            return f"{p}: no existing parent directory"
        probe = probe.parent
    if not probe.is_dir():
        return f"{probe} is not a directory"
    if not os.access(probe, os.W_OK | os.X_OK):
        what = "it" if probe == p else f"its parent {probe}, where it would be created,"
        return f"{p}: {what} is not writable by this user (uid {os.getuid()})"
    return ""


def preflight(config: Config, daemon: bool = True) -> list[Finding]:
    """Every problem found (empty when the cell may start); ``daemon`` False checks a client's config (the CLI's,
    an MES's), which names no robot."""
    out: list[Finding] = []
    if daemon and "robot" not in config.tables:
        out.append(Finding("robot", "the config has no [robot] table: a daemon needs its robot's host (a client's config needs none)"))
    tls = config.bus.tls
    for key, path in ({} if tls is None else tls.paths()).items():
        try:
            with open(path, "rb"):
                pass
        except OSError as exc:
            out.append(Finding(f"bus.tls.{key}", f"cannot read {path}: {exc.strerror or exc}"))
    from celld.calib.flange import preset

    try:
        preset(config.calibration.flange)
    except InputError as exc:
        out.append(Finding("calibration.flange", str(exc)))
    if config.tactile.kind != "none":
        from celld.tactile.aruco import TagDetector

        try:
            TagDetector.from_config(config.tactile)
        except (ConfigError, InputError) as exc:
            out.append(Finding("tactile.tag_dictionary", getattr(exc, "reason", str(exc))))
    why = _writable_dir(Path(config.cell.state_dir))
    if why:
        out.append(Finding("cell.state_dir", why))
    return out


def require(config: Config) -> None:
    """Raise ConfigError with every finding of :func:`preflight`."""
    found = preflight(config)
    if found:
        key = found[0].key if len(found) == 1 else ", ".join(f.key for f in found)
        raise ConfigError(config.source, key, "; ".join(f"{f.key}: {f.reason}" for f in found))
