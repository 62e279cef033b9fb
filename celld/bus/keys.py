"""The zenoh key expressions of one cell, all under ``<prefix>/<cell>/``.

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
=======
Requests go to ``<req>/<name>``, where ``<req>`` is ``<prefix>/<cell>`` on an
open bus and ``<prefix>/<cell>/u/<user>`` on a bus with users (each user
queries its own keys; zenoh's ACL lets a link query only its own user's keys,
which is how the cell knows who asks: :mod:`celld.bus.security`).
:data:`KEY_TABLE` is the table below as data: the README's key table and the
exported AsyncAPI document (:mod:`celld.bus.asyncapi`) are made from it.

=========================================  ===========  =====================================
key                                        kind         what
=========================================  ===========  =====================================
``<req>/submit``                           queryable    a job; replies with its id or an error
``<req>/status``                           queryable    the cell's state, or one job's record
``<req>/cancel``                           queryable    cancel a job
``<req>/list``                             queryable    jobs from the journal
``<req>/accept``                           queryable    make a calibration result current
``<req>/calibration``                      queryable    the current calibration
``<req>/result/<job>``                     queryable    a finished job's result
``<req>/robot``                            queryable    an operator's recovery command (unlock, power on, ...)
``<prefix>/<cell>/progress/<job>``         publication  progress events of one job
``<prefix>/<cell>/state/robot``            publication  robot state, decimated
``<prefix>/<cell>/state/tactile``          publication  SRM deformation, decimated
``<prefix>/<cell>/alive``                  liveliness   present while the daemon runs
=========================================  ===========  =====================================

Several cells share one zenoh network under one prefix; ``<prefix>/*/alive``
finds them all. The prefix may have several chunks (``plant/line-2/celld``);
the cell name, a user name and a job id are one chunk each. What a chunk may
hold is :mod:`celld.keychunk`'s rule, which the config checks ``bus.prefix``
with too.
"""

from __future__ import annotations

from dataclasses import dataclass

from celld.errors import BusError
from celld.keychunk import check_chunk, check_prefix, is_chunk

# The queryables with a fixed key, in the order a server declares them; ``result``
# has one key per job (``<req>/result/<job>``).
QUERYABLES = ("submit", "status", "cancel", "list", "accept", "calibration", "robot")
# Queryables that change the cell: an operator may query them, a viewer may not.
OPERATOR_QUERYABLES = ("submit", "cancel", "accept", "robot")
# Queryables that only read.
VIEWER_QUERYABLES = ("status", "list", "calibration")
# The chunk that separates a cell's keys from its users' request keys.
USERS_CHUNK = "u"


@dataclass(frozen=True)
class KeySpec:
    """One row of the key table: a key expression template and what travels on it.

    ``key`` uses ``<prefix>``, ``<cell>``, ``<user>``, ``<job>``; ``<req>`` stands
    for ``<prefix>/<cell>`` (open bus) or ``<prefix>/<cell>/u/<user>`` (bus with
    users). ``request`` and ``replies`` name schemas of :mod:`celld.bus.messages`.
    """

    name: str
    key: str
    kind: str  # queryable | publication | liveliness
    request: str | None
    replies: tuple[str, ...]
    roles: str
    what: str


KEY_TABLE: tuple[KeySpec, ...] = (
    KeySpec(
        "submit",
        "<req>/submit",
        "queryable",
        "submit",
        ("submit-reply", "error-reply"),
        "operator, supervisor",
        "Submit a job. With a request_id the submit is idempotent: the same id and body give the original job back.",
    ),
    KeySpec(
        "status",
        "<req>/status",
        "queryable",
        "status",
        ("status-reply", "job-reply", "error-reply"),
        "every role",
        "The cell's state (with storage: free space, the last storage error), or one job's record with {\"job\": ID}.",
    ),
    KeySpec(
        "cancel",
        "<req>/cancel",
        "queryable",
        "cancel",
        ("cancel-reply", "error-reply"),
        "operator (own jobs), supervisor",
        "Cancel a queued or running job; the robot stops first; the reason is kept in the record.",
    ),
    KeySpec("list", "<req>/list", "queryable", "list", ("list-reply", "error-reply"), "every role", "Jobs from the journal, newest first."),
    KeySpec(
        "accept",
        "<req>/accept",
        "queryable",
        "accept",
        ("accept-reply", "error-reply"),
        "operator, supervisor",
        "Make a succeeded calibrate job's result the current calibration.",
    ),
    KeySpec(
        "calibration",
        "<req>/calibration",
        "queryable",
        "calibration",
        ("calibration-reply", "error-reply"),
        "every role",
        "The current calibration, or null.",
    ),
    KeySpec(
        "result",
        "<req>/result/<job>",
        "queryable",
        "result",
        ("result-reply", "error-reply"),
        "owner, supervisor, users with job_details",
        "A finished job's result (JSON, up to 1 MiB inline), and the files it left on the cell PC.",
    ),
    KeySpec(
        "robot",
        "<req>/robot",
        "queryable",
        "robot",
        ("robot-reply", "error-reply"),
        "operator, supervisor",
        "An operator's recovery command through the dashboard (unlock, power-on, brake-release, ...); refused while a job runs.",
    ),
    KeySpec(
        "progress",
        "<prefix>/<cell>/progress/<job>",
        "publication",
        None,
        ("progress",),
        "every role (subscribe)",
        "Progress events of one job, numbered by seq; the last one has a terminal state.",
    ),
    KeySpec(
        "state-robot",
        "<prefix>/<cell>/state/robot",
        "publication",
        None,
        ("state-robot",),
        "every role (subscribe)",
        "Robot state, decimated to bus.state_rate_hz.",
    ),
    KeySpec(
        "state-tactile",
        "<prefix>/<cell>/state/tactile",
        "publication",
        None,
        ("state-tactile",),
        "every role (subscribe)",
        "SRM deformation, decimated to bus.state_rate_hz.",
    ),
    KeySpec(
        "alive",
        "<prefix>/<cell>/alive",
        "liveliness",
        None,
        (),
        "every role",
        "A liveliness token, present while the daemon runs; <prefix>/*/alive finds every cell.",
    ),
)


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

    def requests(self, user: str = "") -> str:
        """Where ``user``'s requests go: ``<base>`` on an open bus (no user), else ``<base>/u/<user>``."""
        return f"{self.base}/{USERS_CHUNK}/{check_chunk(user, 'user name')}" if user else self.base

    def query(self, name: str, user: str = "") -> str:
        """The key of queryable ``name`` (one of :data:`QUERYABLES`) for ``user`` ("" on an open bus)."""
        if name not in QUERYABLES:
            raise BusError(f"unknown queryable {name!r}: expected one of {', '.join(QUERYABLES)}")
        return f"{self.requests(user)}/{name}"

    def result(self, job: str, user: str = "") -> str:
        """The key of one job's result for ``user``."""
        return f"{self.requests(user)}/result/{check_chunk(job, 'job id')}"

    def results(self, user: str = "") -> str:
        """The key expression of every job's result for ``user`` (what the server declares)."""
        return f"{self.requests(user)}/result/*"

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
    return cell if is_chunk(cell) else None
