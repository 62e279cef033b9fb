"""The bus as one AsyncAPI 2.6 document: channels (key expressions), operations, messages; and the bundle's export.

``celld bus schema --out DIR`` writes it as ``DIR/asyncapi.json`` beside the
JSON Schemas (:func:`export_schemas`); each message's payload is a ``$ref`` to
``<name>.schema.json`` in the same directory, so the document and the schemas
the cell enforces are one bundle. It is made from
:data:`celld.bus.keys.KEY_TABLE` and the schemas it is given
(:func:`celld.bus.messages.message_schemas`; the cell's bundle, with each job
kind's result, is :data:`celld.daemon.results.BUNDLE`); nothing in it is
written by hand twice. The schemas that are no message's payload (each job
kind's result alone, ``result-<kind>``) are listed under
``components.schemas``.

How zenoh maps onto AsyncAPI 2.6 (which has no request/reply of its own):

- a *queryable* channel has a ``publish`` operation (the client sends a query
  with the request message as its payload) and a ``subscribe`` operation (the
  reply it gets back, one of the reply messages); ``x-zenoh`` says
  ``queryable``;
- a *publication* channel has a ``subscribe`` operation (the client declares a
  subscriber);
- the liveliness token has neither: ``x-zenoh`` says ``liveliness`` (query it
  with a liveliness get or subscriber).

Channel names use ``{prefix}``, ``{cell}``, ``{user}`` and ``{job}``
parameters; a request channel's leading ``{req}`` is ``{prefix}/{cell}`` on an
open bus and ``{prefix}/{cell}/u/{user}`` on a bus with users.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from celld import __version__, fsutil
from celld.bus.keys import KEY_TABLE, KeySpec
from celld.bus.messages import DIALECT

# The AsyncAPI version the document follows.
ASYNCAPI_VERSION = "2.6.0"
# How the schema files are named in the bundle.
SCHEMA_FILE = "{name}.schema.json"
_SCHEMA_FORMAT = "application/schema+json;version=draft-2020-12"

_PARAMETERS: dict[str, dict[str, Any]] = {
    "prefix": {
        "description": "bus.prefix of the cell config (default celld); may have several chunks (plant/line-2/celld).",
        "schema": {"type": "string"},
    },
    "cell": {"description": "cell.name of the cell config; one key chunk.", "schema": {"type": "string", "pattern": "^[A-Za-z0-9_-]+$"}},
    "user": {
        "description": "The bus user the link authenticated as; only on a bus with users.",
        "schema": {"type": "string", "pattern": "^[A-Za-z0-9_.-]+$"},
    },
    "job": {"description": "A job id, as submit returned it.", "schema": {"type": "string", "pattern": "^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$"}},
    "req": {"description": "{prefix}/{cell} on an open bus; {prefix}/{cell}/u/{user} on a bus with users.", "schema": {"type": "string"}},
}


def channel_name(spec: KeySpec) -> str:
    """The AsyncAPI channel of a key table row: ``<req>/submit`` -> ``{req}/submit``."""
    return spec.key.replace("<", "{").replace(">", "}")


def _message_ref(name: str) -> dict[str, str]:
    return {"$ref": f"#/components/messages/{name}"}


def _message_names(specs: tuple[KeySpec, ...]) -> list[str]:
    names: list[str] = []
    for spec in specs:
        for name in ((spec.request,) if spec.request else ()) + spec.replies:
            if name not in names:
                names.append(name)
    return names


def _messages(specs: tuple[KeySpec, ...], schemas: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in _message_names(specs):
        schema = schemas[name]
        out[name] = {
            "name": name,
            "title": schema.get("title", name),
            "summary": str(schema.get("description", "")).split(". ")[0],
            "contentType": "application/json",
            "schemaFormat": _SCHEMA_FORMAT,
            "payload": {"$ref": SCHEMA_FILE.format(name=name)},
        }
    return out


def _channel(spec: KeySpec) -> dict[str, Any]:
    params = [p for p in _PARAMETERS if "{" + p + "}" in channel_name(spec)]
    channel: dict[str, Any] = {
        "description": f"{spec.what} Who: {spec.roles}.",
        "parameters": {p: {"$ref": f"#/components/parameters/{p}"} for p in params},
        "x-zenoh": spec.kind,
    }
    replies = [_message_ref(r) for r in spec.replies]
    if spec.kind == "queryable":
        channel["publish"] = {
            "operationId": spec.name,
            "summary": f"query {channel_name(spec)} (zenoh get) with this payload",
            "message": _message_ref(spec.request) if spec.request else {"payload": {"type": "null"}},
        }
        channel["subscribe"] = {
            "operationId": f"{spec.name}-reply",
            "summary": 'the reply to the query: {"ok": true, ...} or an error-reply',
            "message": {"oneOf": replies} if len(replies) > 1 else replies[0],
        }
    elif spec.kind == "publication":
        channel["subscribe"] = {"operationId": spec.name, "summary": f"subscribe to {channel_name(spec)}", "message": replies[0]}
    return channel


def asyncapi_document(schemas: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The AsyncAPI 2.6 document of the bus whose messages are ``schemas`` (a JSON-able dict)."""
    messages = _message_names(KEY_TABLE)
    return {
        "asyncapi": ASYNCAPI_VERSION,
        "id": "urn:celld:bus",
        "info": {
            "title": "celld cell bus",
            "version": __version__,
            "description": (
                "The zenoh interface of one celld welding cell: jobs in (queries), replies, results, progress "
                "and state out. Every message is a UTF-8 JSON object whose JSON Schema (draft 2020-12, "
                f'{DIALECT}) is the file the payload $ref names. Replies are {{"ok": true, ...}} or '
                '{"ok": false, "error": {"field": JSON path, "reason": text}}. On a bus with users each '
                "user queries its own keys ({prefix}/{cell}/u/{user}/...); zenoh's access control lets a link "
                "query only its own user's keys, which is how the cell knows who asks."
            ),
        },
        "defaultContentType": "application/json",
        "servers": {
            "cell": {
                "url": "{endpoint}",
                "protocol": "zenoh",
                "description": (
                    "A zenoh endpoint of the cell (bus.listen) or of the router it connects to: "
                    "tcp/host:port, or tls/host:port with [bus.tls]."
                ),
                "variables": {"endpoint": {"default": "tcp/127.0.0.1:7447"}},
            }
        },
        "channels": {channel_name(spec): _channel(spec) for spec in KEY_TABLE},
        "components": {
            "messages": _messages(KEY_TABLE, schemas),
            "schemas": {name: {"$ref": SCHEMA_FILE.format(name=name)} for name in schemas if name not in messages},
            "parameters": _PARAMETERS,
        },
    }


def export_schemas(directory: str | Path, schemas: Mapping[str, Mapping[str, Any]]) -> list[Path]:
    """Write the bundle of ``schemas`` into ``directory`` (created); returns the paths.

    Every schema as ``<name>.schema.json``, and ``asyncapi.json``: the document
    of :func:`asyncapi_document`, listing the key expressions (channels), the
    operations on them and their messages, whose payloads are ``$ref``s to the
    schema files beside it. The cell's bundle is
    :data:`celld.daemon.results.BUNDLE` (``celld bus schema``).
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = [fsutil.write_json(out / SCHEMA_FILE.format(name=name), schema) for name, schema in schemas.items()]
    paths.append(fsutil.write_json(out / "asyncapi.json", asyncapi_document(schemas)))
    return paths
