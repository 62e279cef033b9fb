"""The zenoh key expressions of one cell, all under ``<prefix>/<cell>/``.

=====================================  ===========  =====================================
key                                    kind         what
=====================================  ===========  =====================================
``<prefix>/<cell>/submit``             queryable    a job; replies with its id or an error
``<prefix>/<cell>/status``             queryable    the cell's state, or one job's record
``<prefix>/<cell>/cancel``             queryable    cancel a job
``<prefix>/<cell>/list``               queryable    jobs from the journal
``<prefix>/<cell>/accept``             queryable    make a calibration result current
``<prefix>/<cell>/calibration``        queryable    the current calibration
``<prefix>/<cell>/robot``              queryable    an operator's recovery command (unlock, power on, ...)
``<prefix>/<cell>/progress/<job>``     publication  progress events of one job
``<prefix>/<cell>/state/robot``        publication  robot state, decimated
``<prefix>/<cell>/state/tactile``      publication  SRM deformation, decimated
``<prefix>/<cell>/alive``              liveliness   present while the daemon runs
=====================================  ===========  =====================================

Several cells share one zenoh network under one prefix; ``<prefix>/*/alive``
finds them all. The prefix may have several chunks (``plant/line-2/celld``);
the cell name is one chunk.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from celld.errors import BusError

# One key chunk as celld writes it: no wildcards, no '$', '?', '#', no '@' (admin space).
_CHUNK = re.compile(r"^[A-Za-z0-9_.-]+$")
# The queryables, in the order a server declares them.
QUERYABLES = ("submit", "status", "cancel", "list", "accept", "calibration", "robot")
# Queryables that change the cell: an operator may query them, a viewer may not.
OPERATOR_QUERYABLES = ("submit", "cancel", "accept", "robot")
# Queryables that only read.
VIEWER_QUERYABLES = ("status", "list", "calibration")


def check_prefix(prefix: str) -> str:
    """Return ``prefix`` if every ``/``-separated chunk is a plain key chunk.

    Raises
    ------
    BusError
        Naming the offending chunk.
    """
    chunks = prefix.split("/")
    for chunk in chunks:
        if not _CHUNK.match(chunk) or chunk in (".", ".."):
            raise BusError(f"bus prefix {prefix!r}: expected chunks of letters, digits, '_', '.', '-' separated by '/', got {chunk!r}")
    return prefix


def check_chunk(name: str, what: str) -> str:
    """Return ``name`` if it is one plain key chunk (a cell name, a job id)."""
    if not _CHUNK.match(name):
        raise BusError(f"{what} {name!r}: expected letters, digits, '_', '.' or '-' (one zenoh key chunk)")
    return name


@dataclass(frozen=True)
class CellKeys:
    """Every key of one cell. Build with :meth:`of` to have both parts checked."""

    prefix: str
    cell: str

    @classmethod
    def of(cls, prefix: str, cell: str) -> CellKeys:
        return cls(check_prefix(prefix), check_chunk(cell, "cell name"))

    @property
    def base(self) -> str:
        return f"{self.prefix}/{self.cell}"

    def query(self, name: str) -> str:
        """The key of queryable ``name`` (one of :data:`QUERYABLES`)."""
        if name not in QUERYABLES:
            raise BusError(f"unknown queryable {name!r}: expected one of {', '.join(QUERYABLES)}")
        return f"{self.base}/{name}"

    def progress(self, job: str) -> str:
        return f"{self.base}/progress/{check_chunk(job, 'job id')}"

    @property
    def progress_all(self) -> str:
        return f"{self.base}/progress/*"

    @property
    def state_robot(self) -> str:
        return f"{self.base}/state/robot"

    @property
    def state_tactile(self) -> str:
        return f"{self.base}/state/tactile"

    @property
    def alive(self) -> str:
        return f"{self.base}/alive"


def alive_all(prefix: str) -> str:
    """The key expression matching the liveliness token of every cell under ``prefix``."""
    return f"{check_prefix(prefix)}/*/alive"


def cell_of_alive_key(prefix: str, key: str) -> str | None:
    """The cell name in a liveliness key ``<prefix>/<cell>/alive``, or None if it is not one."""
    head = prefix + "/"
    if not key.startswith(head) or not key.endswith("/alive"):
        return None
    cell = key[len(head) : -len("/alive")]
    return cell if _CHUNK.match(cell) else None
