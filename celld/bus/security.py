"""Who is asking, and what each role may do; warnings about a bus that is open to the network.

Identity. zenoh hands a queryable no verified name of the requester (a
query's ``source_info`` and ``attachment`` are whatever the sender put
there). What zenoh does verify is the user/password of each link, and its
access control (ACL) decides per user which key expressions that link may
query. So on a bus with users every user has its own request keys::

    <prefix>/<cell>/u/<user>/<request>        submit, status, cancel, ...
    <prefix>/<cell>/u/<user>/result/<job>

and the ACL lets a link authenticated as ``<user>`` query only keys under
``<prefix>/<cell>/u/<user>/`` (a rule must *include* the query's key
expression, so a wildcard such as ``u/*/cancel`` is refused too). The cell
declares one queryable per user and request; the user a request came from is
the user of the queryable it reached (:class:`Caller`), never a claim in the
payload. The server also refuses a query whose key is not exactly its own
(a wildcard that some router without the ACL let through).

On an open bus (no ``bus.users``) there are no users: every request is
:data:`OPEN`, with every right, and keys have no ``u/<user>`` part.

Roles (``bus.users[].role``):

==========  ===================================================================
role        may
==========  ===================================================================
viewer      status, list, calibration; progress and state; its records show
            no parameters, references, owner or result (``redacted``) and
            results are refused, unless the user has ``job_details = true``
operator    also submit, accept and robot (recovery) commands; cancel its own jobs; sees its own jobs in
            full (others' redacted unless ``job_details``)
supervisor  as operator, and cancel any job, and see every job in full
==========  ===================================================================
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Iterable
from dataclasses import dataclass

ROLES = ("viewer", "operator", "supervisor")
# Requests each role may send (the ACL and the server both enforce this).
READ_REQUESTS = ("status", "list", "calibration", "result")
WRITE_REQUESTS = ("submit", "cancel", "accept", "robot")
ROLE_REQUESTS: dict[str, tuple[str, ...]] = {
    "viewer": READ_REQUESTS,
    "operator": READ_REQUESTS + WRITE_REQUESTS,
    "supervisor": READ_REQUESTS + WRITE_REQUESTS,
}
# "proto/host:port" with an optional "#..." or "?..." tail; host may be [v6].
ENDPOINT = re.compile(r"^(?P<proto>[a-z0-9]+)/(?P<host>\[[^\]]*\]|[^:/\[\]]+):(?P<port>\d+)(?P<tail>[#?].*)?$")


@dataclass(frozen=True)
class Caller:
    """The user a request came from, as the bus verified it, and what it may do.

    ``user`` is "" on an open bus (:data:`OPEN`).
    """

    user: str
    role: str
    job_details: bool = False

    def may(self, request: str) -> bool:
        """Whether this caller may send ``request`` at all."""
        return request in ROLE_REQUESTS.get(self.role, ())

    def owns(self, owner: str) -> bool:
        return bool(self.user) and owner == self.user

    def may_see(self, owner: str) -> bool:
        """Whether this caller sees a job of ``owner`` in full (parameters, reference, result)."""
        return not self.user or self.role == "supervisor" or self.job_details or self.owns(owner)

    def may_cancel(self, owner: str) -> bool:
        return not self.user or self.role == "supervisor" or (self.role == "operator" and self.owns(owner))

    def __str__(self) -> str:
        return f"{self.user} ({self.role})" if self.user else "the open bus"


# Every request on an open bus: no verified user, every right.
OPEN = Caller("", "supervisor", True)


def endpoint_host(endpoint: str) -> str | None:
    """The host of a zenoh endpoint ``proto/host:port``, without brackets; None if it does not parse."""
    m = ENDPOINT.match(endpoint)
    if m is None:
        return None
    return m["host"].strip("[]")


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine only (127.0.0.0/8, ::1, localhost); a wildcard is not."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name may resolve anywhere


def bus_warnings(
    users: int,
    listen: Iterable[str],
    connect: Iterable[str],
    mode: str = "peer",
    tls: bool = False,
) -> list[str]:
    """What is unsafe about a bus config: the daemon logs these at start, ``celld config check`` prints them.

    Parameters
    ----------
    users : int
        How many ``bus.users`` (0: an open bus).
    listen, connect : endpoints
    mode : str
        The daemon's zenoh mode (a ``client`` does not listen).
    tls : bool
        Whether ``[bus.tls]`` is configured.
    """
    endpoints = ([] if mode == "client" else list(listen)) + list(connect)
    exposed = [e for e in endpoints if not is_loopback(endpoint_host(e) or "?")]
    out: list[str] = []
    if not exposed:
        return out
    if users == 0:
        out.append(
            f"the bus is open (no bus.users) on a non-loopback address ({', '.join(exposed)}): anyone who can "
            "reach it may submit, cancel and read every job; add [[bus.users]] (and [bus.tls])"
        )
    plain = [e for e in exposed if not e.startswith(("tls/", "quic/"))]
    if plain:
        out.append(
            f"bus traffic on {', '.join(plain)} is not encrypted: job parameters and results can be read on the "
            "network; listen on tls/ endpoints with [bus.tls]"
        )
    elif not tls:
        out.append("tls/ endpoints without [bus.tls]: zenoh has no certificate to use")
    return out
