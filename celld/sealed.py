"""Stored state that says when it is damaged: JSON files sealed with their format, their maker and a checksum.

What the cell keeps between jobs (the current calibration, the tool's, their
candidates, the finger's reference rest; later the arm's corrections) is
written with :func:`write_sealed` and read with :func:`read_sealed`. A sealed
file is the JSON object it stores plus three keys:

- ``format``: ``celld.<kind>/<version>``; a file of another kind or of a
  newer version is refused;
- ``job``: the job that made it (``""`` when no job did);
- ``sha256``: the SHA-256 of the object without this key, serialised
  canonically (sorted keys, no spaces, ASCII; Python's float repr makes the
  round trip exact).

A file that cannot be read, is cut short, is not an object, has no seal or
fails its checksum raises :class:`~celld.errors.DamagedStateError`, whose
message is what status and every refusal say ("the stored calibration is
damaged: <why>"). An absent file is not damage: :func:`read_sealed` returns
None. A file larger than :data:`MAX_BYTES` is refused before it is read.
What a read found is kept while the file stays the same (its inode, size
and times): status, asked many times a second, reads each file once.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from celld import fsutil
from celld.errors import DamagedStateError

FORMAT_KEY = "format"
CHECKSUM_KEY = "sha256"
JOB_KEY = "job"
# The version every kind is written in now; a reader takes this one and older.
VERSION = 1
# No stored state is anywhere near this; larger is refused unread, bytes.
MAX_BYTES = 16 * 2**20
# Files whose last reading is kept (read_sealed); more are forgotten all at once.
_CACHED_FILES = 64
# What read_sealed found, by (path, kind, what): the file's identity then, and the document or why it is damaged.
_read: dict[tuple[str, str, str], tuple[tuple[int, ...], dict[str, Any] | None, str]] = {}


def format_of(kind: str, version: int = VERSION) -> str:
    return f"celld.{kind}/{version}"


def checksum(document: Mapping[str, Any]) -> str:
    """The SHA-256 (hex) of ``document`` without its checksum key, serialised canonically."""
    body = {k: v for k, v in document.items() if k != CHECKSUM_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def seal(body: Mapping[str, Any], kind: str, job: str = "") -> dict[str, Any]:
    """``body`` with its seal: the format of ``kind``, the job that made it (``job``, or the body's own) and the checksum."""
    document = {k: v for k, v in body.items() if k not in (FORMAT_KEY, CHECKSUM_KEY)}
    document[FORMAT_KEY] = format_of(kind)
    document[JOB_KEY] = str(job or body.get(JOB_KEY, ""))
    document[CHECKSUM_KEY] = checksum(document)
    return document


def write_sealed(path: str | os.PathLike[str], body: Mapping[str, Any], kind: str, job: str = "") -> dict[str, Any]:
    """Seal ``body`` and write it atomically to ``path``; returns the sealed document."""
    document = seal(body, kind, job)
    fsutil.write_json(path, document)
    return document


def read_sealed(path: str | os.PathLike[str], kind: str, what: str) -> dict[str, Any] | None:
    """The document sealed in ``path`` (seal keys included), None when there is no file.

    Raises
    ------
    DamagedStateError
        ``path`` is there but cannot be trusted; ``what`` names the state in the message.
    """
    p = Path(path)
    key = (str(p), kind, what)
    try:
        with open(p, "rb") as f:
            st = os.fstat(f.fileno())
            identity = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
            known = _read.get(key)
            if known is not None and known[0] == identity:
                if known[1] is None:
                    raise DamagedStateError(what, str(p), known[2])
                return dict(known[1])
            if st.st_size > MAX_BYTES:
                raise DamagedStateError(what, str(p), f"{st.st_size} bytes, more than the {MAX_BYTES} any stored state has")
            raw = f.read(MAX_BYTES + 1)
    except FileNotFoundError:
        return None
    except DamagedStateError:
        raise
    except OSError as exc:
        raise DamagedStateError(what, str(p), f"cannot be read: {exc.strerror or exc}") from exc
    if len(_read) >= _CACHED_FILES:
        _read.clear()
    try:
        document = verify(raw, kind, what, str(p))
    except DamagedStateError as exc:
        _read[key] = (identity, None, exc.why)
        raise
    _read[key] = (identity, document, "")
    return dict(document)


def verify(raw: bytes, kind: str, what: str, path: str) -> dict[str, Any]:
    """The sealed document in ``raw`` (a file's bytes), checked: JSON object, format of ``kind``, checksum."""
    try:
        document = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        cut = " (cut short)" if raw and not raw.rstrip().endswith(b"}") else ""
        raise DamagedStateError(what, path, f"not JSON{cut}: {exc}") from exc
    if not isinstance(document, dict):
        raise DamagedStateError(what, path, f"not a JSON object but {type(document).__name__}")
    fmt = document.get(FORMAT_KEY)
    if fmt is None or CHECKSUM_KEY not in document:
        raise DamagedStateError(what, path, "it carries no format and checksum: written by hand or by a celld older than sealed files")
    expected = format_of(kind)
    name, _, version = str(fmt).rpartition("/")
    if name != expected.rpartition("/")[0]:
        raise DamagedStateError(what, path, f"format {fmt!r} is not a {what} ({expected})")
    if not version.isdigit() or int(version) > VERSION:
        raise DamagedStateError(what, path, f"format {fmt!r} is newer than this celld reads ({expected})")
    try:
        expected_sum = checksum(document)
    except ValueError as exc:  # NaN or infinity: never written by write_sealed
        raise DamagedStateError(what, path, f"holds a value JSON does not: {exc}") from exc
    if document[CHECKSUM_KEY] != expected_sum:
        raise DamagedStateError(what, path, "its checksum does not match its content: edited or corrupted since it was written")
    return document
