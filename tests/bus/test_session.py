"""Keys and zenoh configs built from BusConfig (no network)."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from celld import config
from celld.bus import session
from celld.bus.keys import CellKeys, alive_all, cell_of_alive_key
from celld.config import BusConfig, BusUser
from celld.errors import BusError, ConfigError
from celld.keychunk import check_prefix

KEYS = CellKeys.of("plant/line-2/celld", "cell-01")
USERS = (BusUser("olga", "pw1", "operator"), BusUser("vic", "pw2", "viewer"), BusUser("oscar", "pw3", "operator"))


def test_keys_sit_under_prefix_and_cell() -> None:
    assert KEYS.query("submit") == "plant/line-2/celld/cell-01/submit"
    assert KEYS.progress("20250101-120000-abcdef") == "plant/line-2/celld/cell-01/progress/20250101-120000-abcdef"
    assert KEYS.state_robot == "plant/line-2/celld/cell-01/state/robot"
    assert KEYS.alive == "plant/line-2/celld/cell-01/alive"
    assert alive_all("plant/line-2/celld") == "plant/line-2/celld/*/alive"
    assert cell_of_alive_key("plant/line-2/celld", KEYS.alive) == "cell-01"
    assert cell_of_alive_key("plant/line-2/celld", "plant/line-2/celld/a/b/alive") is None


@pytest.mark.parametrize("prefix", ["", "a//b", "a/*", "a/**", "$x", "a?b", "a#b", "@admin", "a b", "/a"])
def test_bad_prefixes_are_refused(prefix: str) -> None:
    with pytest.raises(BusError):
        check_prefix(prefix)


def test_config_refuses_bad_bus_values() -> None:
    def bus(**values: object) -> None:
        config.parse({"bus": values})

    with pytest.raises(ConfigError, match="bus.prefix"):
        bus(prefix="a/*")
    with pytest.raises(ConfigError, match=r"bus.users\[0\].name"):
        bus(users=[{"name": "a:b", "password": "x", "role": "viewer"}])
    with pytest.raises(ConfigError, match=r"bus.users\[1\].name"):
        bus(users=[{"name": "a", "password": "x", "role": "viewer"}, {"name": "a", "password": "y", "role": "operator"}])
    with pytest.raises(ConfigError, match=r"bus.users\[0\].role"):
        bus(users=[{"name": "a", "password": "x", "role": "admin"}])
    with pytest.raises(ConfigError, match="bus.password"):
        bus(user="olga")
    with pytest.raises(ConfigError, match="bus.listen"):
        bus(listen=["127.0.0.1:7447"])


def test_loopback_peer_config_has_scouting_off_and_no_auth() -> None:
    conf = session.server_config(BusConfig(listen=("tcp/127.0.0.5:7447",)), KEYS)
    assert conf["mode"] == "peer" and conf["listen"]["endpoints"] == ["tcp/127.0.0.5:7447"]
    assert conf["scouting"]["multicast"]["enabled"] is False and conf["scouting"]["gossip"]["enabled"] is False
    assert "transport" not in conf and "access_control" not in conf


def test_acl_gives_each_user_its_own_request_keys_and_its_roles_requests() -> None:
    acl = session.acl_config(BusConfig(users=USERS), KEYS)
    assert acl is not None and acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s["usernames"] for s in acl["subjects"]}
    policies = {subjects[p["subjects"][0]][0]: set(p["rules"]) for p in acl["policies"]}
    assert sorted(policies) == ["olga", "oscar", "vic"], "one subject, one policy per user"

    def allowed(user: str, message: str, flow: str, key: str) -> bool:
        return any(message in rules[r]["messages"] and flow in rules[r]["flows"] and key in rules[r]["key_exprs"] for r in policies[user])

    for q in ("submit", "cancel", "accept"):
        assert allowed("olga", "query", "ingress", KEYS.query(q, "olga"))
        assert not allowed("olga", "query", "ingress", KEYS.query(q, "oscar")), "another user's key"
        assert not allowed("olga", "query", "ingress", KEYS.query(q)), "the open bus's key"
        assert not allowed("vic", "query", "ingress", KEYS.query(q, "vic"))
        assert not allowed("vic", "declare_queryable", "egress", KEYS.query(q, "vic"))
    for q in ("status", "list", "calibration"):
        assert allowed("vic", "query", "ingress", KEYS.query(q, "vic")) and allowed("vic", "reply", "egress", KEYS.query(q, "vic"))
        assert not allowed("vic", "query", "ingress", KEYS.query(q, "olga"))
    assert allowed("vic", "query", "ingress", KEYS.results("vic"))
    assert allowed("vic", "put", "egress", f"{KEYS.base}/progress/**")
    assert allowed("vic", "liveliness_token", "egress", KEYS.alive)
    assert session.acl_config(BusConfig(), KEYS) is None


def test_server_writes_the_dictionary_privately_and_removes_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, loopback_host: str) -> None:
    monkeypatch.setenv("RUNTIME_DIRECTORY", str(tmp_path))
    seen: dict[str, object] = {}
    real_open = session.zenoh.open

    def spy(conf):  # look at the dictionary while zenoh would read it
        path = Path(json.loads(str(conf.get_json("transport/auth/usrpwd/dictionary_file"))))
        seen["mode"] = stat.S_IMODE(path.stat().st_mode)
        seen["dir_mode"] = stat.S_IMODE(path.parent.stat().st_mode)
        seen["text"] = path.read_text()
        seen["path"] = path
        return real_open(conf)

    monkeypatch.setattr(session.zenoh, "open", spy)
    bus = BusConfig(listen=(f"tcp/{loopback_host}:0",), users=USERS)
    with session.open_server(bus, KEYS) as s:
        assert not s.session.is_closed()
    assert seen["mode"] == 0o600 and seen["dir_mode"] == 0o700
    assert seen["text"] == "olga:pw1\nvic:pw2\noscar:pw3\n"
    assert seen["path"].parent.parent == tmp_path and not seen["path"].parent.exists()


def test_client_endpoints_follow_the_cell() -> None:
    peer = BusConfig(listen=("tcp/0.0.0.0:7447", "tcp/[::]:7448", "tcp/127.0.0.1:0"), connect=("tcp/10.0.0.12:7447",))
    assert session.client_endpoints(peer) == ["tcp/127.0.0.1:7447", "tcp/[::1]:7448", "tcp/10.0.0.12:7447"]
    client = BusConfig(mode="client", listen=("tcp/127.0.0.1:7447",), connect=("tcp/10.0.0.1:7447",))
    assert session.client_endpoints(client) == ["tcp/10.0.0.1:7447"]
    conf = session.client_config(client, "vic", "pw2")
    assert conf["mode"] == "client" and conf["listen"]["endpoints"] == []
    assert conf["transport"]["auth"]["usrpwd"] == {"user": "vic", "password": "pw2"}
    with pytest.raises(BusError, match="no endpoint"):
        session.client_config(BusConfig(listen=("tcp/127.0.0.1:0",)))


def test_bad_endpoint_is_a_bus_error(loopback_host: str) -> None:
    with pytest.raises(BusError):
        session.open_server(BusConfig(listen=("nosuchproto/127.0.0.1:1",)), KEYS)
