"""The rule for one chunk of a zenoh key that celld writes: a part of the bus prefix, a cell, user or job name.

A chunk is letters, digits, ``_``, ``.`` and ``-``: no wildcards (``*``,
``**``), no ``$``, ``?`` or ``#``, no ``@`` (zenoh's admin space). The bus
builds its keys under this rule (:mod:`celld.bus.keys`) and the config checks
``bus.prefix`` with it (:class:`celld.config.BusConfig`), so a prefix the
config accepts is one the bus can use.
"""

from __future__ import annotations

import re

from celld.errors import BusError

# One key chunk as celld writes it: no wildcards, no '$', '?', '#', no '@' (admin space).
_CHUNK = re.compile(r"^[A-Za-z0-9_.-]+$")


def is_chunk(name: str) -> bool:
    """Whether ``name`` is one plain key chunk."""
    return _CHUNK.match(name) is not None


def check_prefix(prefix: str) -> str:
    """Return ``prefix`` if every ``/``-separated chunk is a plain key chunk.

    Raises
    ------
    BusError
        Naming the offending chunk.
    """
    chunks = prefix.split("/")
    for chunk in chunks:
        if not is_chunk(chunk) or chunk in (".", ".."):
            raise BusError(f"bus prefix {prefix!r}: expected chunks of letters, digits, '_', '.', '-' separated by '/', got {chunk!r}")
    return prefix


def check_chunk(name: str, what: str) -> str:
    """Return ``name`` if it is one plain key chunk (a cell name, a job id)."""
    if not is_chunk(name):
        raise BusError(f"{what} {name!r}: expected letters, digits, '_', '.' or '-' (one zenoh key chunk)")
    return name
