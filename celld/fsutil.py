"""Atomic file writes: a reader sees the old file or the whole new one, never a part.

Every result celld writes (calibrations, datasets, seam paths, exported
schemas) goes through here. The recipe, in the order that makes it survive a
crash or a power cut at any point:

1. write a temporary file in the *same* directory (a rename is only atomic
   within one file system), named ``.<name>.<random>.celld-tmp``;
2. flush and ``fsync`` it, so its data is on disk before its name is;
3. ``os.replace`` it onto the final name (atomic on POSIX);
4. ``fsync`` the directory, so the rename itself is on disk.

A process killed between 1 and 3 leaves only a temporary file, which
:func:`remove_stale_temporaries` deletes (the daemon calls it at start-up).
Errors are the ``OSError`` of the failing call, naming the final file; the
temporary file is removed on the way out. :func:`storage_error` turns one into a
:class:`~celld.errors.StorageError` naming the store and the file, and
:func:`free_bytes` says how much room a directory's file system has left.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from celld.errors import StorageError

# Suffix of temporary files; nothing else in a state directory ends with it.
TEMP_SUFFIX = ".celld-tmp"
# Default permissions of result files (before the umask).
DEFAULT_MODE = 0o644
# errno values that mean "this store cannot take writes", not "this call was wrong".
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS, errno.EFBIG})


def _temp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{secrets.token_hex(4)}{TEMP_SUFFIX}")


def fsync_dir(directory: str | os.PathLike[str]) -> None:
    """``fsync`` a directory so that renames and creations in it are durable."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: int = DEFAULT_MODE) -> Iterator[BinaryIO]:
    """Open a temporary binary file that becomes ``path`` when the block exits cleanly.

    If the block raises, the temporary file is removed and ``path`` is left as
    it was. The parent directory must exist.

    Examples
    --------
    >>> with atomic_open(tmp / "cloud.npy") as f:   # doctest: +SKIP
    ...     np.save(f, P_cam)
    """
    path = Path(path)
    tmp = _temp_path(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, mode)
    except OSError as exc:
        raise _about(exc, path) from exc
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.errno is not None:
            raise _about(exc, path) from exc
        raise
    fsync_dir(path.parent)


def _about(exc: OSError, path: Path) -> OSError:
    """``exc`` naming the file the caller asked for, not the temporary one (same errno, same subclass)."""
    return OSError(exc.errno, exc.strerror, str(path))


def write_bytes(path: str | os.PathLike[str], data: bytes, mode: int = DEFAULT_MODE) -> Path:
    """Atomically replace ``path`` with ``data``; returns the path."""
    with atomic_open(path, mode) as f:
        f.write(data)
    return Path(path)


def write_text(path: str | os.PathLike[str], text: str, mode: int = DEFAULT_MODE) -> Path:
    """Atomically replace ``path`` with ``text`` encoded as UTF-8."""
    return write_bytes(path, text.encode("utf-8"), mode)


def write_json(path: str | os.PathLike[str], value: Any, mode: int = DEFAULT_MODE, indent: int | None = 2) -> Path:
    """Atomically write ``value`` as JSON (NaN and infinities are refused: they are not JSON).

    Raises
    ------
    ValueError
        ``value`` holds NaN or an infinity.
    TypeError
        ``value`` holds something JSON cannot represent.
    """
    text = json.dumps(value, indent=indent, allow_nan=False, ensure_ascii=False)
    return write_text(path, text + "\n", mode)


def write_npy(path: str | os.PathLike[str], array: np.ndarray, mode: int = DEFAULT_MODE) -> Path:
    """Atomically write one array in ``.npy`` format (no pickled objects)."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return write_bytes(path, buf.getvalue(), mode)


def write_npz(path: str | os.PathLike[str], mode: int = DEFAULT_MODE, **arrays: np.ndarray) -> Path:
    """Atomically write named arrays in ``.npz`` format (compressed)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **{k: np.asarray(v) for k, v in arrays.items()})  # type: ignore[arg-type]  # numpy's stub reads **kwds as allow_pickle
    return write_bytes(path, buf.getvalue(), mode)


def remove_stale_temporaries(directory: str | os.PathLike[str], recursive: bool = True) -> list[Path]:
    """Delete temporary files left by a process that died mid-write; returns them.

    Only files named by :func:`atomic_open` (hidden, ending in
    :data:`TEMP_SUFFIX`) are touched. Call it when no writer is running.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    pattern = f".*{TEMP_SUFFIX}"
    found = directory.rglob(pattern) if recursive else directory.glob(pattern)
    removed = []
    for p in sorted(found):
        with contextlib.suppress(FileNotFoundError):
            p.unlink()
            removed.append(p)
    return removed


def free_bytes(directory: str | os.PathLike[str]) -> int:
    """Bytes an unprivileged writer may still use on the file system of ``directory``.

    Raises
    ------
    OSError
        ``directory`` does not exist or cannot be examined.
    """
    st = os.statvfs(directory)
    return int(st.f_bavail) * int(st.f_frsize)


def is_storage_error(exc: BaseException, under: str | os.PathLike[str] | None = None) -> bool:
    """Whether ``exc`` is a store refusing writes: disk full, quota, I/O error, read-only,
    or any ``OSError`` about a file under ``under`` (a socket's ``ConnectionError`` is not)."""
    if isinstance(exc, StorageError):
        return True
    if not isinstance(exc, OSError) or isinstance(exc, ConnectionError):
        return False
    if exc.errno in STORAGE_ERRNOS:
        return True
    filename = exc.filename
    return under is not None and isinstance(filename, (str, os.PathLike)) and Path(filename).is_relative_to(under)


def storage_error(what: str, exc: BaseException, path: str | os.PathLike[str] | None = None) -> StorageError:
    """``exc`` (an ``OSError``, or a StorageError passed through) as a StorageError of store ``what``."""
    if isinstance(exc, StorageError):
        return exc
    filename = path if path is not None else getattr(exc, "filename", None)
    code = getattr(exc, "errno", None)
    reason = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
    if code is not None:
        reason = f"{reason} (errno {code})"
    return StorageError(what, str(filename) if filename is not None else "", reason, code)
