"""A minimal MES client of a celld cell, with nothing of celld: zenoh, the exported schemas, the standard library.

It does what an MES connector does for one order step:

1. validates the job against the cell's exported JSON Schemas (``celld bus
   schema --out DIR``; with the ``jsonschema`` package, skipped without it);
2. subscribes to the cell's progress events, then submits the job with a
   ``request_id`` of the order step, and submits again with the same id if
   the reply was lost (the cell returns the job it already made: a retry can
   never make a second weld);
3. waits for the job's end (progress events, and a status query when none
   comes for a second);
4. fetches the result over the bus (``<req>/result/<job>``) and prints one JSON
   line: ``{"job", "state", "reason", "result", "files"}``.

Keys (the README's key table): requests go to ``<prefix>/<cell>/<name>`` on an
open bus and to ``<prefix>/<cell>/u/<user>/<name>`` on a bus with users;
progress comes on ``<prefix>/<cell>/progress/<job>``.

    python examples/mes_client.py --endpoint tcp/127.0.0.1:7447 --cell cell-01 \\
        --schemas /tmp/celld-schemas --request-id order-4711-step-3 \\
        --job '{"kind": "weld", "workpiece": "v-groove", "ref": "order-4711"}' \\
        [--user mes --password-file pw] [--ca ca.pem [--cert mes.pem --key mes.key]]

Exit code: 0 the job succeeded, 1 it ended otherwise, 2 it could not be run
(refused, no reply, bad arguments).
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from pathlib import Path
from typing import Any

import zenoh

TERMINAL = ("succeeded", "failed", "cancelled", "interrupted")
# Seconds without a progress event before the client asks status.
STATUS_POLL = 1.0


class Refused(Exception):
    """The cell answered {"ok": false, "error": {...}}."""


class Schemas:
    """The exported JSON Schemas; validation needs the jsonschema package and is skipped without it."""

    def __init__(self, directory: str | None) -> None:
        self.by_name: dict[str, Any] = {}
        if directory:
            for path in Path(directory).glob("*.schema.json"):
                self.by_name[path.name.removesuffix(".schema.json")] = json.loads(path.read_text())
        try:
            import jsonschema

            self._validator = jsonschema.Draft202012Validator
        except ImportError:
            self._validator = None
            print("note: jsonschema not installed, messages are not validated here", file=sys.stderr)

    def check(self, name: str, value: Any) -> None:
        if self._validator is None or name not in self.by_name:
            return
        errors = sorted(self._validator(self.by_name[name]).iter_errors(value), key=lambda e: list(e.path))
        if errors:
            e = errors[0]
            raise ValueError(f"{name}: $.{'.'.join(map(str, e.path))}: {e.message}")


class Cell:
    """One cell over zenoh."""

    def __init__(self, args: argparse.Namespace) -> None:
        conf: dict[str, Any] = {
            "mode": args.mode,
            "connect": {"endpoints": [args.endpoint]},
            "listen": {"endpoints": []},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}, "delay": 0},
        }
        transport: dict[str, Any] = {}
        if args.user:
            password = Path(args.password_file).read_text().splitlines()[0] if args.password_file else args.password
            transport["auth"] = {"usrpwd": {"user": args.user, "password": password}}
        if args.ca:
            tls: dict[str, Any] = {"root_ca_certificate": args.ca}
            if args.cert:  # mutual TLS: present a certificate (zenoh sends one only with enable_mtls)
                tls.update(connect_certificate=args.cert, connect_private_key=args.key, enable_mtls=True)
            transport["link"] = {"tls": tls}
        if transport:
            conf["transport"] = transport
        self.session = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
        deadline = time.monotonic() + args.timeout
        while not (self.session.info.peers_zid() or self.session.info.routers_zid()):
            if time.monotonic() > deadline:
                raise ConnectionError(f"no link to {args.endpoint} (cell down, wrong credentials or certificates?)")
            time.sleep(0.01)
        self.base = f"{args.prefix}/{args.cell}"
        self.req = f"{self.base}/u/{args.user}" if args.user else self.base
        self.timeout = args.timeout

    def request(self, key: str, message: dict[str, Any] | None = None, attempts: int = 20) -> dict[str, Any]:
        """One query; the reply as a dict. A fresh session may not know the cell's queryables yet: retried briefly."""
        payload = json.dumps(message).encode() if message else None
        for _ in range(attempts):
            for reply in self.session.get(key, payload=payload, timeout=self.timeout):
                if reply.ok is None:
                    continue
                value = json.loads(reply.ok.payload.to_bytes())
                if not value.get("ok"):
                    error = value.get("error", {})
                    raise Refused(f"{error.get('field') or '-'}: {error.get('reason')}")
                return value
            time.sleep(0.05)
        raise TimeoutError(f"no reply on {key} (cell down, or this user may not send it)")

    def close(self) -> None:
        self.session.close()


def run(args: argparse.Namespace) -> int:
    schemas = Schemas(args.schemas)
    job = json.loads(args.job)
    job["request_id"] = args.request_id
    schemas.check("submit", job)
    cell = Cell(args)
    events: queue.Queue[dict[str, Any]] = queue.Queue()
    subscriber = cell.session.declare_subscriber(
        f"{cell.base}/progress/*", lambda sample: events.put(json.loads(sample.payload.to_bytes()))
    )
    try:
        for attempt in range(3):  # the same request_id each time: a lost reply never makes a second job
            try:
                reply = cell.request(f"{cell.req}/submit", job)
                break
            except TimeoutError:
                if attempt == 2:
                    raise
        schemas.check("submit-reply", reply)
        job_id = reply["job"]
        print(f"job {job_id} {reply['state']}" + (" (replayed)" if reply.get("replayed") else ""), file=sys.stderr)
        state = reply["state"]
        while state not in TERMINAL:
            try:
                event = events.get(timeout=STATUS_POLL)
            except queue.Empty:
                event = None
            if event is not None and event.get("job") == job_id:
                schemas.check("progress", event)
                print(f"  {event['state']} {event['stage']} {event.get('fraction')} {event.get('message', '')}", file=sys.stderr)
                if event["state"] not in TERMINAL:
                    continue
            state = cell.request(f"{cell.req}/status", {"job": job_id})["record"]["state"]
        result = cell.request(f"{cell.req}/result/{job_id}")
        schemas.check("result-reply", result)
        print(json.dumps({k: result.get(k) for k in ("job", "state", "reason", "result", "files")}))
        return 0 if result["state"] == "succeeded" else 1
    finally:
        subscriber.undeclare()
        cell.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--endpoint", required=True, help="the cell's zenoh endpoint: tcp/host:port or tls/host:port")
    p.add_argument("--mode", default="peer", choices=("peer", "client"), help="client: through a zenoh router")
    p.add_argument("--prefix", default="celld", help="bus.prefix of the cell")
    p.add_argument("--cell", required=True, help="cell.name of the cell")
    p.add_argument("--user", default="", help="bus user (a bus with users)")
    p.add_argument("--password", default="")
    p.add_argument("--password-file")
    p.add_argument("--ca", help="root CA certificate (PEM) for tls/ endpoints")
    p.add_argument("--cert", help="this client's certificate (mutual TLS)")
    p.add_argument("--key", help="this client's private key (mutual TLS)")
    p.add_argument("--schemas", help="the directory celld bus schema --out wrote")
    p.add_argument("--job", required=True, help="the submit message, JSON")
    p.add_argument("--request-id", required=True, help="your id of this order step (idempotent submit)")
    p.add_argument("--timeout", type=float, default=5.0, help="reply and connect timeout, s")
    args = p.parse_args(argv)
    try:
        return run(args)
    except (Refused, TimeoutError, ConnectionError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
