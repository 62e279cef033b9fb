"""Zenoh sessions for celld: configs built from :class:`~celld.config.BusConfig`.

Two sides:

- the **server** side (the daemon, :func:`open_server`) runs in ``bus.mode``
  (``peer`` by default, ``router`` or ``client`` by config), listens on
  ``bus.listen`` and connects to ``bus.connect``;
- the **client** side (the CLI, scripts, :func:`open_client`) does not listen.
  It connects to the cell's concrete listen endpoints (a wildcard host becomes
  loopback, port 0 is skipped) plus ``bus.connect``; with ``mode = "client"``
  only to ``bus.connect`` (the router). It runs as a peer next to a peer cell,
  so one client can reach several cells directly, and as a zenoh client of a
  router otherwise. :func:`open_client` waits until a link is up, so "nobody
  there" and "credentials refused" are errors, not silent empty replies.

Scouting (multicast and gossip) is off unless ``bus.multicast_scouting``: a
loopback bus reaches exactly its configured endpoints.

Access control, when ``bus.users`` is not empty:

- user/password authentication: the server writes the accepted ``user:password``
  lines into a dictionary file, mode 0600, in a private directory (0700) under
  ``$RUNTIME_DIRECTORY`` (systemd's ``RuntimeDirectory=``), ``$XDG_RUNTIME_DIR``
  or the temporary directory; zenoh reads it when the session opens and the
  file is deleted right after. A link whose credentials do not match is refused.
- zenoh's ACL, default deny, one policy per user (:func:`acl_config`): each
  user may query only its own request keys ``<prefix>/<cell>/u/<user>/<name>``
  for the requests its role allows (:mod:`celld.bus.security`), subscribe to
  progress and state, and see the liveliness tokens. A rule must include the
  query's key expression, so another user's key and wildcards are refused.
  A refused query gets no reply at all (zenoh drops it), which the client
  reports as "no reply". This is how the cell knows who asks: the user of
  the queryable a request reached (:func:`callers`).

TLS (``[bus.tls]``, for ``tls/host:port`` endpoints) is zenoh's own TLS
transport (``transport.link.tls``): the cell listens with its certificate and
key, a client verifies it against the root CA (and that it names the host,
unless ``verify_name_on_connect = false``); with ``mutual = true`` the cell
also demands a client certificate signed by that CA, and a client presents
its ``connect_certificate`` (zenoh sends one only when its own
``enable_mtls`` is on, so the client config sets it too). User/password and
the ACL work on top of TLS unchanged.

:func:`~celld.bus.security.bus_warnings` says what is unsafe about a config
(an open bus on a non-loopback address, traffic without TLS off this
machine); :func:`open_server` logs each as a warning.

The ACL filters what crosses this session's own links. In a router topology
(cells in ``client`` mode) the router sees every client under one link, so put
the per-user rules on the router; :func:`acl_config` gives the rules to paste.
Identity is as good as the ACL where the users' links end.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from celld.bus.keys import QUERYABLES, CellKeys, alive_all
from celld.bus.security import ROLE_REQUESTS, Caller, bus_warnings
from celld.config import BusConfig
from celld.errors import BusError
from celld.log import get_logger

log = get_logger(__name__)

# Environment variables naming a private runtime directory, in order of preference.
_RUNTIME_ENV = ("RUNTIME_DIRECTORY", "XDG_RUNTIME_DIR")
# Poll period while waiting for a link, s.
_LINK_POLL = 0.002
# After the first link, how long a client waits for links to its other endpoints, s.
_OTHER_LINKS_GRACE = 0.25
# "proto/host:port" with an optional "#..." or "?..." tail; host may be [v6].
_ENDPOINT = re.compile(r"^(?P<proto>[a-z0-9]+)/(?P<host>\[[^\]]*\]|[^:/\[\]]+):(?P<port>\d+)(?P<tail>[#?].*)?$")


def callers(bus: BusConfig) -> tuple[Caller, ...]:
    """The verified identities the server answers, one per ``bus.users`` entry (none: an open bus)."""
    return tuple(Caller(u.name, u.role, u.job_details) for u in bus.users)


# -- configs ------------------------------------------------------------------------


def user_request_keys(keys: CellKeys, user: str, role: str) -> list[str]:
    """The request keys ``user`` may query with ``role``: its own, and only those its role allows."""
    allowed = ROLE_REQUESTS.get(role, ())
    out = [keys.query(q, user) for q in QUERYABLES if q in allowed]
    if "result" in allowed:
        out.append(keys.results(user))
    return out


def acl_config(bus: BusConfig, keys: CellKeys) -> dict[str, Any] | None:
    """zenoh ``access_control`` for ``bus.users``; None without users.

    Rules are written from the server's side: *ingress* is what a user sends
    to the cell (queries, subscriptions), *egress* what the cell sends back
    (replies, publications, the queryables and the token it declares). Every
    user has a rule pair of its own request keys (:func:`user_request_keys`),
    so a link authenticated as one user can neither query nor even see the
    queryables of another.
    """
    if not bus.users:
        return None
    base = keys.base
    publications = [f"{base}/progress/**", f"{base}/state/**"]
    every_alive = alive_all(keys.prefix)

    def rule(rule_id: str, messages: list[str], flow: str, key_exprs: list[str]) -> dict[str, Any]:
        return {"id": rule_id, "messages": messages, "flows": [flow], "permission": "allow", "key_exprs": key_exprs}

    rules = [
        rule("publications-in", ["declare_subscriber"], "ingress", publications),
        rule("publications-out", ["put"], "egress", publications),
        rule("alive-in", ["liveliness_query", "declare_liveliness_subscriber"], "ingress", [every_alive]),
        rule("alive-out", ["liveliness_token", "reply"], "egress", [keys.alive]),
    ]
    shared = [r["id"] for r in rules]
    subjects, policies = [], []
    for i, u in enumerate(bus.users):
        own = user_request_keys(keys, u.name, u.role)
        rules.append(rule(f"u{i}-queries-in", ["query"], "ingress", own))
        rules.append(rule(f"u{i}-queries-out", ["declare_queryable", "reply"], "egress", own))
        subjects.append({"id": f"u{i}", "usernames": [u.name]})
        policies.append({"id": f"u{i}-policy", "rules": [*shared, f"u{i}-queries-in", f"u{i}-queries-out"], "subjects": [f"u{i}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def tls_config(bus: BusConfig, side: str) -> dict[str, Any] | None:
    """zenoh ``transport.link.tls`` of the ``server`` or ``client`` side; None without ``[bus.tls]``."""
    tls = bus.tls
    if tls is None:
        return None
    conf: dict[str, Any] = {"verify_name_on_connect": tls.verify_name_on_connect}
    if tls.root_ca_certificate:
        conf["root_ca_certificate"] = tls.root_ca_certificate
    if side == "server" and tls.listen_certificate:
        conf["listen_certificate"] = tls.listen_certificate
        conf["listen_private_key"] = tls.listen_private_key
    if tls.connect_certificate:
        conf["connect_certificate"] = tls.connect_certificate
        conf["connect_private_key"] = tls.connect_private_key
    # The listening side demands a client certificate; a connecting side sends one only with it on.
    conf["enable_mtls"] = tls.mutual or (side == "client" and bool(tls.connect_certificate))
    return conf


def tls_problems(bus: BusConfig) -> list[str]:
    """Private keys of ``[bus.tls]`` that other users may read (a file that cannot be read at all is an error:
    :func:`celld.preflight.preflight`)."""
    out: list[str] = []
    if bus.tls is None:
        return out
    for key, path in bus.tls.paths().items():
        try:
            mode = os.stat(path).st_mode
        except OSError:
            continue
        if key.endswith("private_key") and mode & 0o077:
            out.append(f"bus.tls.{key}: {path} may be read by other users (mode {mode & 0o777:o}); chmod 600 it")
    return out


def config_warnings(bus: BusConfig) -> list[str]:
    """Everything unsafe or unusable in ``bus``: :func:`~celld.bus.security.bus_warnings` and :func:`tls_problems`."""
    return bus_warnings(len(bus.users), bus.listen, bus.connect, bus.mode, bus.tls is not None) + tls_problems(bus)


def _scouting(bus: BusConfig) -> dict[str, Any]:
    on = bus.multicast_scouting
    conf: dict[str, Any] = {"multicast": {"enabled": on}, "gossip": {"enabled": on}}
    if not on:
        # A peer's open() otherwise waits 500 ms for scouting that is off;
        # links to the configured endpoints come up in a few ms.
        conf["delay"] = 0
    return conf


def server_config(bus: BusConfig, keys: CellKeys, dictionary_file: str | None = None) -> dict[str, Any]:
    """The zenoh config (as a dict) of the daemon's session.

    Parameters
    ----------
    dictionary_file : str or None
        Path of the ``user:password`` dictionary; required when ``bus.users``
        is not empty (:func:`open_server` writes it).
    """
    if bus.users and not dictionary_file:
        raise BusError("bus.users is set but no credentials dictionary was given")
    conf: dict[str, Any] = {
        "mode": bus.mode,
        "listen": {"endpoints": [] if bus.mode == "client" else list(bus.listen)},
        "connect": {"endpoints": list(bus.connect)},
        "scouting": _scouting(bus),
    }
    usrpwd: dict[str, Any] = {}
    if dictionary_file:
        usrpwd["dictionary_file"] = dictionary_file
    if bus.user:
        usrpwd.update(user=bus.user, password=bus.password)
    transport: dict[str, Any] = {}
    if usrpwd:
        transport["auth"] = {"usrpwd": usrpwd}
    tls = tls_config(bus, "server")
    if tls is not None:
        transport["link"] = {"tls": tls}
    if transport:
        conf["transport"] = transport
    acl = acl_config(bus, keys)
    if acl is not None:
        conf["access_control"] = acl
    return conf


def _client_host(host: str) -> str:
    return {"0.0.0.0": "127.0.0.1", "[::]": "[::1]", "localhost": "127.0.0.1"}.get(host, host)


def client_endpoints(bus: BusConfig) -> list[str]:
    """Where a client connects: the cell's concrete listen endpoints, then ``bus.connect``."""
    out: list[str] = []
    if bus.mode != "client":
        for endpoint in bus.listen:
            m = _ENDPOINT.match(endpoint)
            if m is None or m["port"] == "0":
                continue  # a port the system picks cannot be found from the config
            out.append(f"{m['proto']}/{_client_host(m['host'])}:{m['port']}")
    out.extend(e for e in bus.connect if e not in out)
    return out


def client_config(bus: BusConfig, user: str | None = None, password: str | None = None) -> dict[str, Any]:
    """The zenoh config (as a dict) of a client of the cell (CLI, scripts, benchmarks).

    ``user`` and ``password`` default to ``bus.user`` and ``bus.password``.
    """
    endpoints = client_endpoints(bus)
    if not endpoints and not bus.multicast_scouting:
        raise BusError(
            "no endpoint to connect to: bus.listen has no fixed port and bus.connect is empty "
            '(give the cell a fixed port, e.g. listen = ["tcp/127.0.0.1:7447"])'
        )
    mode = "peer" if bus.mode == "peer" else "client"
    timeout_ms = int(bus.connect_timeout * 1e3)
    conf: dict[str, Any] = {
        "mode": mode,
        "listen": {"endpoints": []},
        "connect": {
            "endpoints": endpoints,
            "timeout_ms": {"router": -1, "peer": -1, "client": timeout_ms},
            "exit_on_failure": {"router": False, "peer": False, "client": True},
            # A cell that is starting (or restarting) answers within a tenth of a second of listening, not at
            # zenoh's next attempt of 1-4 s later.
            "retry": {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2},
        },
        "scouting": _scouting(bus),
    }
    user = bus.user if user is None else user
    password = bus.password if password is None else password
    transport: dict[str, Any] = {}
    if user:
        transport["auth"] = {"usrpwd": {"user": user, "password": password or ""}}
    tls = tls_config(bus, "client")
    if tls is not None:
        transport["link"] = {"tls": tls}
    if transport:
        conf["transport"] = transport
    return conf


def _zenoh_config(conf: dict[str, Any]) -> zenoh.Config:
    try:
        return zenoh.Config.from_json5(json.dumps(conf))
    except zenoh.ZError as exc:
        raise BusError(f"zenoh refused the bus config: {exc}") from exc


# -- sessions -----------------------------------------------------------------------


def _private_dir() -> Path:
    for name in _RUNTIME_ENV:
        base = os.environ.get(name, "")
        if base and os.path.isdir(base):
            break
    else:
        base = tempfile.gettempdir()
    # mkdtemp creates the directory with mode 0700.
    return Path(tempfile.mkdtemp(prefix="celld-bus-", dir=base))


def _write_dictionary(directory: Path, bus: BusConfig) -> Path:
    path = directory / "usrpwd"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        for u in bus.users:
            f.write(f"{u.name}:{u.password}\n")
    return path


@dataclass
class ServerSession:
    """The daemon's open zenoh session and the keys of its cell."""

    session: zenoh.Session
    keys: CellKeys
    config: dict[str, Any] = field(repr=False)

    def close(self) -> None:
        if not self.session.is_closed():
            self.session.close()

    def __enter__(self) -> ServerSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_server(bus: BusConfig, keys: CellKeys) -> ServerSession:
    """Open the daemon's session: listen, connect, authenticate and apply the ACL.

    Raises
    ------
    BusError
        zenoh refused the config or could not listen (address in use, ...).
    """
    for warning in config_warnings(bus):
        log.warning("bus_config_unsafe", warning=warning)
    private = _private_dir() if bus.users else None
    try:
        dictionary = str(_write_dictionary(private, bus)) if private else None
        conf = server_config(bus, keys, dictionary)
        try:
            session = zenoh.open(_zenoh_config(conf))
        except zenoh.ZError as exc:
            raise BusError(f"cannot open the zenoh session ({bus.mode}, listen {list(bus.listen)}): {exc}") from exc
    finally:
        # zenoh read the dictionary when the session opened: keep no password on disk.
        if private is not None:
            shutil.rmtree(private, ignore_errors=True)
    log.info(
        "bus_session_open",
        mode=bus.mode,
        listen=list(bus.listen),
        connect=list(bus.connect),
        users=len(bus.users),
        tls=bus.tls is not None and bool(bus.tls.listen_certificate),
        mutual_tls=bool(bus.tls and bus.tls.mutual),
    )
    return ServerSession(session=session, keys=keys, config=conf)


def link_count(session: zenoh.Session) -> int:
    """How many peers and routers the session is linked to."""
    info = session.info
    return len(info.peers_zid()) + len(info.routers_zid())


def has_link(session: zenoh.Session) -> bool:
    """Whether the session has at least one peer or router link."""
    return link_count(session) > 0


def open_client(
    bus: BusConfig,
    user: str | None = None,
    password: str | None = None,
    timeout: float | None = None,
) -> zenoh.Session:
    """Open a client session and wait until it has a link to a cell or a router.

    Parameters
    ----------
    user, password : str, optional
        Credentials to present; default ``bus.user`` and ``bus.password``.
    timeout : float, optional
        How long to wait for a link, s; default ``bus.connect_timeout``.

    With several endpoints (cells of a fleet) it returns once all are linked,
    or a quarter of a second after the first link, so a cell that is down
    does not delay every command by the whole timeout.

    Raises
    ------
    BusError
        No link within the timeout: nothing listens there, or the credentials
        were refused (zenoh does not say which).
    """
    conf = client_config(bus, user, password)
    endpoints = conf["connect"]["endpoints"]
    timeout = bus.connect_timeout if timeout is None else timeout
    try:
        session = zenoh.open(_zenoh_config(conf))
    except zenoh.ZError as exc:
        raise BusError(f"cannot reach {endpoints}: {exc} (is celld running there, are the credentials right?)") from exc
    deadline = time.monotonic() + timeout
    while not has_link(session):
        if time.monotonic() > deadline:
            session.close()
            raise BusError(
                f"no link to {endpoints or 'a scouted cell'} within {timeout:g} s "
                "(is celld running there, are the user and password right?)"
            )
        time.sleep(_LINK_POLL)
    grace = min(deadline, time.monotonic() + _OTHER_LINKS_GRACE)
    while link_count(session) < len(endpoints) and time.monotonic() < grace:
        time.sleep(_LINK_POLL)
    return session
