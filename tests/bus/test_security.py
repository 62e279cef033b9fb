"""Security of the bus over real zenoh on loopback.

- TLS and mutual TLS through zenoh's own TLS transport, with certificates
  from a test CA (openssl); a client without the CA, or without a certificate
  the cell trusts, never gets a link.
- Identity: each user queries its own keys and zenoh's ACL lets a link query
  only its own user's keys, so the cell knows who asks. An operator cancels
  only its own jobs, a supervisor any; a viewer sees status but not other
  users' parameters, references or results, unless ``job_details``.
- Warnings for an open bus off loopback; passwords never printed.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from celld.bus import messages, wire
from celld.bus.client import CellClient
from celld.bus.security import bus_warnings
from celld.cli import main
from celld.config import BusTls, BusUser
from celld.errors import BusError, JobError
from tests.bus.tlscerts import CertAuthority

USERS = (
    BusUser("olga", "op-secret", "operator"),
    BusUser("oscar", "op2-secret", "operator"),
    BusUser("sam", "sup-secret", "supervisor"),
    BusUser("vic", "view-secret", "viewer"),
    BusUser("val", "view2-secret", "viewer", job_details=True),
)
PASSWORDS = {u.name: u.password for u in USERS}
WELD = {"kind": "weld", "ref": "order-4711", "arc": False}


def as_user(cell, name: str, **kw) -> CellClient:
    return CellClient(cell.client_bus(name, PASSWORDS[name]), cell.keys.cell, **kw)


# -- TLS -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ca(tmp_path_factory) -> CertAuthority:
    return CertAuthority.make(tmp_path_factory.mktemp("ca"))


@pytest.fixture(scope="module")
def other_ca(tmp_path_factory) -> CertAuthority:
    return CertAuthority.make(tmp_path_factory.mktemp("other-ca"), "mallory-ca")


def served_tls(serve_cell, ca: CertAuthority, loopback_host: str, mutual: bool, users=()):
    leaf = ca.issue("cell-a", loopback_host)
    tls = BusTls(root_ca_certificate=str(ca.cert), listen_certificate=str(leaf.cert), listen_private_key=str(leaf.key), mutual=mutual)
    cell = serve_cell(tls=tls, users=users)
    assert cell.bus.listen[0].startswith("tls/")
    return cell


def tls_client(cell, tls: BusTls, user: str = "", password: str = "", timeout: float = 2.0) -> CellClient:
    bus = replace(cell.client_bus(user, password), tls=tls, connect_timeout=timeout)
    return CellClient(bus, cell.keys.cell)


def test_tls_carries_the_bus_and_a_client_without_the_ca_is_refused(serve_cell, ca, loopback_host) -> None:
    cell = served_tls(serve_cell, ca, loopback_host, mutual=False)
    with tls_client(cell, BusTls(root_ca_certificate=str(ca.cert))) as client:
        reply = client.submit({"kind": "health"})
        assert client.watch_progress().wait(reply["job"], timeout=5.0)["state"] == "succeeded"
    with pytest.raises(BusError, match="no link"):
        tls_client(cell, BusTls(), timeout=0.7)  # no CA: the cell's certificate is not trusted
    plain = replace(cell.client_bus(), listen=(cell.bus.listen[0].replace("tls/", "tcp/"),), tls=None, connect_timeout=0.7)
    with pytest.raises(BusError, match="no link"):
        CellClient(plain, cell.keys.cell)  # plain TCP to a TLS port


def test_mutual_tls_admits_only_clients_with_a_certificate_of_the_ca(serve_cell, ca, other_ca, loopback_host) -> None:
    cell = served_tls(serve_cell, ca, loopback_host, mutual=True)
    mine, theirs = ca.issue("mes-client"), other_ca.issue("mes-client")
    good = BusTls(root_ca_certificate=str(ca.cert), connect_certificate=str(mine.cert), connect_private_key=str(mine.key))
    with tls_client(cell, good) as client:
        assert client.status()["state"] == "idle"
    for bad in (
        BusTls(root_ca_certificate=str(ca.cert)),  # no certificate to show
        BusTls(root_ca_certificate=str(ca.cert), connect_certificate=str(theirs.cert), connect_private_key=str(theirs.key)),
    ):
        with pytest.raises(BusError, match="no link"):
            tls_client(cell, bad, timeout=0.7)


def test_users_and_roles_work_over_mutual_tls(serve_cell, ca, loopback_host) -> None:
    cell = served_tls(serve_cell, ca, loopback_host, mutual=True, users=USERS)
    leaf = ca.issue("olga-pc")
    tls = BusTls(root_ca_certificate=str(ca.cert), connect_certificate=str(leaf.cert), connect_private_key=str(leaf.key))
    with tls_client(cell, tls, "olga", "op-secret") as client:
        job = client.submit({"kind": "health"})["job"]
        assert client.status(job)["owner"] == "olga"
    with pytest.raises(BusError, match="no link"):
        tls_client(cell, tls, "olga", "wrong", timeout=0.7)


# -- identity and roles -----------------------------------------------------------------------


@pytest.fixture
def cell(serve_cell):
    return serve_cell(users=USERS, job_duration=5.0)


def test_an_operator_cancels_only_its_own_jobs_and_a_supervisor_any(cell) -> None:
    with as_user(cell, "olga") as olga, as_user(cell, "oscar") as oscar, as_user(cell, "sam") as sam:
        job = olga.submit(WELD)["job"]
        with pytest.raises(JobError) as refused:
            oscar.cancel(job, "mine now")
        assert refused.value.field == "$.job" and "only its own jobs" in refused.value.reason
        assert olga.status(job)["state"] in ("queued", "running")
        second = olga.submit({"kind": "health"})["job"]
        assert olga.cancel(second, "not needed")["state"] == "cancelled"
        assert sam.cancel(job, "fixture blocked")["state"] == "cancelled"
        record = olga.status(job)
        assert record["reason"] == "fixture blocked (by sam)" and record["owner"] == "olga"
        assert olga.status(second)["reason"] == "not needed (by olga)"


def test_a_viewer_sees_status_but_not_parameters_references_or_results(cell) -> None:
    with as_user(cell, "olga") as olga, as_user(cell, "vic") as vic, as_user(cell, "val") as val:
        job = olga.submit({"kind": "health", "ref": "order-4711"})["job"]
        assert olga.watch_progress().wait(job, timeout=10.0)["state"] == "succeeded"
        status = vic.status()
        messages.check_message("status-reply", status)
        assert status["cell"] == cell.keys.cell
        for record in (vic.status(job), vic.list()[0]):
            messages.check_message("job-reply", {"ok": True, "record": record})
            assert record["redacted"] is True and record["state"] == "succeeded"
            assert not {"params", "ref", "owner", "request_id", "result"} & set(record)
        with pytest.raises(JobError, match="may not read the results"):
            vic.result(job)
        # job_details lets a viewer see them; the owner always does.
        assert val.status(job)["ref"] == "order-4711" and val.result(job)["state"] == "succeeded"
        assert olga.status(job)["params"] == {"kind": "health", "check": "all", "ref": "order-4711"}


def test_an_operator_sees_other_operators_jobs_redacted(cell) -> None:
    with as_user(cell, "olga") as olga, as_user(cell, "oscar") as oscar, as_user(cell, "sam") as sam:
        job = olga.submit({"kind": "health", "ref": "olga-7"})["job"]
        assert oscar.status(job)["redacted"] is True
        assert sam.status(job)["ref"] == "olga-7"


def test_a_user_cannot_reach_another_users_keys_or_use_wildcards(cell) -> None:
    with as_user(cell, "olga") as olga, as_user(cell, "vic") as vic:
        job = olga.submit(WELD)["job"]
        # vic authenticated fine, but zenoh's ACL drops every query outside u/vic/.
        for key in (cell.keys.query("cancel", "olga"), f"{cell.keys.base}/u/*/cancel", cell.keys.query("cancel"), f"{cell.keys.base}/**"):
            with pytest.raises(BusError, match="no reply"):
                vic.request_raw("cancel", wire.encode({"job": job}), key=key)
        for key in (cell.keys.query("submit", "vic"), cell.keys.query("accept", "vic")):  # not in a viewer's role
            with pytest.raises(BusError, match="no reply"):
                vic.request_raw("submit", b'{"kind": "health"}', key=key)
        assert olga.status(job)["state"] in ("queued", "running")
        assert len(cell.journal.jobs()) == 1


def test_request_ids_are_kept_per_user(cell) -> None:
    with as_user(cell, "olga") as olga, as_user(cell, "oscar") as oscar:
        a = olga.submit({"kind": "health", "request_id": "step-1"})
        b = oscar.submit({"kind": "health", "request_id": "step-1"})
        assert a["job"] != b["job"] and not a.get("replayed") and not b.get("replayed")
        assert olga.submit({"kind": "health", "request_id": "step-1"})["job"] == a["job"]


# -- warnings and secrets -----------------------------------------------------------------------


def test_an_open_bus_off_loopback_is_warned_about() -> None:
    assert bus_warnings(0, ["tcp/127.0.0.1:7447"], []) == []
    assert bus_warnings(0, ["tcp/localhost:7447", "tcp/[::1]:7447"], []) == []
    for endpoint in ("tcp/0.0.0.0:7447", "tcp/192.0.2.10:7447", "tcp/cell-01.plant:7447", "tcp/[::]:7447"):
        warnings = bus_warnings(0, [endpoint], [])
        assert any("open" in w and endpoint in w for w in warnings), (endpoint, warnings)
    assert any("open" in w for w in bus_warnings(0, [], ["tcp/192.0.2.1:7447"], mode="client"))
    with_users = bus_warnings(2, ["tcp/192.0.2.10:7447"], [])
    assert with_users and not any("open" in w for w in with_users) and "not encrypted" in with_users[0]
    assert bus_warnings(2, ["tls/192.0.2.10:7447"], [], tls=True) == []


def _config(tmp_path: Path, bus: str) -> Path:
    path = tmp_path / "cell.toml"
    path.write_text(f'[cell]\nname = "cell-a"\nstate_dir = "{tmp_path / "state"}"\n\n[robot]\nhost = "127.0.0.9"\n\n[bus]\n{bus}')
    return path


def test_config_check_warns_about_an_open_bus_and_never_prints_passwords(tmp_path: Path, capsys) -> None:
    open_bus = _config(tmp_path, 'listen = ["tcp/0.0.0.0:7447"]\n')
    assert main(["config", "check", str(open_bus)]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "open" in err and "0.0.0.0" in err

    secured = _config(
        tmp_path,
        'listen = ["tcp/127.0.0.1:7447"]\nuser = "olga"\npassword = "hunter2-olga"\n'
        '[[bus.users]]\nname = "olga"\npassword = "hunter2-olga"\nrole = "operator"\n'
        '[[bus.users]]\nname = "sam"\npassword = "s3cret-sam"\nrole = "supervisor"\n',
    )
    assert main(["config", "check", "--json", str(secured)]) == 0
    out, err = capsys.readouterr()
    assert "hunter2" not in out + err and "s3cret" not in out + err
    resolved = json.loads(out)
    assert resolved["bus"]["password"] == "***" and [u["password"] for u in resolved["bus"]["users"]] == ["***", "***"]
    assert [u["role"] for u in resolved["bus"]["users"]] == ["operator", "supervisor"]
    assert err == "", "loopback with users: nothing to warn about"


def test_passwords_stay_out_of_reprs() -> None:
    from celld.config import BusConfig

    text = repr(BusConfig(users=USERS, user="olga", password="op-secret"))
    assert "secret" not in text and "olga" in text


def test_a_bus_with_users_refuses_user_names_that_are_not_key_chunks(tmp_path: Path) -> None:
    from celld import config
    from celld.errors import ConfigError

    bad = _config(tmp_path, '[[bus.users]]\nname = "a/b"\npassword = "x"\nrole = "operator"\n')
    with pytest.raises(ConfigError, match="key chunk"):
        config.load(bad)


def test_tls_listen_endpoints_need_a_certificate(tmp_path: Path) -> None:
    from celld import config
    from celld.errors import ConfigError

    with pytest.raises(ConfigError, match="listen_certificate"):
        config.load(_config(tmp_path, 'listen = ["tls/127.0.0.1:7447"]\n'))
    with pytest.raises(ConfigError, match="mutual TLS"):
        config.load(_config(tmp_path, 'listen = ["tcp/127.0.0.1:7447"]\n[bus.tls]\nmutual = true\n'))
