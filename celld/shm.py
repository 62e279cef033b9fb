"""Shared memory between celld's processes: latest-sample slots, rings, mailboxes.

Data between processes goes through shared memory, not pipes or the bus:

- :class:`SeqlockSlot` holds the latest sample of a fixed numpy dtype behind a
  seqlock. One writer, any number of readers. A reader that catches the writer
  mid-write (a torn read) keeps its last good sample and counts the tear.
- :class:`Ring` holds the last ``capacity`` records of a fixed dtype, one per
  append, each stamped with its sequence number. One writer; a reader asks for
  everything since the sequence number it last saw and learns how many records
  it lost to overwriting.
- :class:`Mailbox` is a single-producer single-consumer queue of byte
  messages (commands), ``slots`` deep, each at most ``slot_size`` bytes.
- :class:`SharedArray` is one array of a fixed shape and dtype that a worker
  process fills and its owner reads (a scanner's cloud), handed over without
  pickling; the pipe beside it says when.

Layout rules: every counter is an aligned uint64 on its own 64-byte line, so
a store is one machine write (atomic on x86-64 and aarch64) and writers and
readers do not share lines. A writer publishes data before the counter that
makes it visible. No call allocates on the writer's hot path
(:meth:`SeqlockSlot.write`, :meth:`Ring.append`) or on :meth:`SeqlockSlot.read_into`.

The creator owns a segment and unlinks it; an attaching process does not
register the segment with its resource tracker, because in Python 3.11 the
tracker of an attaching process may otherwise unlink a segment it never
created (bpo-39959).
"""

from __future__ import annotations

import threading
from multiprocessing import resource_tracker, shared_memory
from typing import Any

import numpy as np

from celld.errors import InputError

# Bytes between counters and data: one cache line.
_LINE = 64


def _register_all_but_shm(name: Any, rtype: str) -> None:
    if rtype != "shared_memory":
        _register(name, rtype)


_register = resource_tracker.register
# Serialises the (rare) attaches that briefly swap the tracker's register function.
_ATTACH_LOCK = threading.Lock()


def _open(name: str, size: int, create: bool) -> shared_memory.SharedMemory:
    if create:
        try:
            return shared_memory.SharedMemory(name=name, create=True, size=size)
        except FileExistsError:
            # A segment left behind by a crashed owner: replace it.
            stale = shared_memory.SharedMemory(name=name, create=False)
            stale.close()
            stale.unlink()
            return shared_memory.SharedMemory(name=name, create=True, size=size)
    # Attach without registering with the resource tracker (what 3.13's
    # track=False does). Registering and then unregistering is not enough:
    # a child started with spawn or fork shares its parent's tracker, which
    # keeps a set of names, so the child's unregister would also erase the
    # creator's registration (and the tracker prints a KeyError when the
    # creator unlinks).
    with _ATTACH_LOCK:
        resource_tracker.register = _register_all_but_shm
        try:
            shm = shared_memory.SharedMemory(name=name, create=False)
        finally:
            resource_tracker.register = _register
    if shm.size < size:
        shm.close()
        raise InputError(f"shared memory {name!r}: expected at least {size} bytes, found {shm.size}")
    return shm


def unlink_segment(name: str) -> bool:
    """Remove the named segment a dead process left behind; True if there was one.

    For a daemon cleaning up after its killed predecessor: nothing attaches
    to the segment and no resource tracker is told.
    """
    import _posixshmem  # the module multiprocessing.shared_memory itself uses

    try:
        _posixshmem.shm_unlink("/" + name)
    except FileNotFoundError:
        return False
    return True


class _Segment:
    """A named segment with uint64 counters on their own lines and a data area."""

    def __init__(self, name: str, n_counters: int, data_bytes: int, create: bool) -> None:
        self.name = name
        self.owner = create
        self._data_offset = n_counters * _LINE
        self._shm = _open(name, self._data_offset + data_bytes, create)
        buf = self._shm.buf
        self._counters: list[np.ndarray] = [np.ndarray((1,), np.uint64, buf, i * _LINE) for i in range(n_counters)]
        if create:
            for c in self._counters:
                c[0] = 0

    def data(self, dtype: Any, count: int) -> np.ndarray:
        return np.ndarray((count,), dtype, self._shm.buf, self._data_offset)

    def raw(self, nbytes: int) -> memoryview:
        buf = self._shm.buf
        if buf is None:
            raise InputError(f"shared memory {self.name!r}: used after close")
        return buf[self._data_offset : self._data_offset + nbytes]

    def close(self) -> None:
        self._counters = []
        try:
            self._shm.close()
        except BufferError:  # a view is still alive somewhere; the mapping goes with the process
            pass

    def unlink(self) -> None:
        if self.owner:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass


# A read that meets the writer mid-write tries again this many times in all
# before it falls back to the last good sample (a new reader has none yet).
_READ_TRIES = 3


class SeqlockSlot:
    """The latest sample of a numpy structured ``dtype``, behind a seqlock.

    Use :meth:`create` in the owning process and :meth:`attach` elsewhere.
    """

    def __init__(self, name: str, dtype: Any, create: bool) -> None:
        self.dtype = np.dtype(dtype)
        self._seg = _Segment(name, 1, self.dtype.itemsize, create)
        self._seq = self._seg._counters[0]
        self._value = self._seg.data(self.dtype, 1)
        self._last = np.zeros(1, self.dtype)
        self._have_last = False
        self.torn_count = 0

    @classmethod
    def create(cls, name: str, dtype: Any) -> SeqlockSlot:
        return cls(name, dtype, create=True)

    @classmethod
    def attach(cls, name: str, dtype: Any) -> SeqlockSlot:
        return cls(name, dtype, create=False)

    @property
    def seq(self) -> int:
        """Number of completed writes so far (twice the seqlock counter)."""
        return int(self._seq[0]) // 2

    def write(self, record: Any) -> None:
        """Publish ``record`` (a structured scalar or 1-element array of ``dtype``)."""
        self._seq[0] += 1  # odd: a write is under way
        self._value[0] = record
        self._seq[0] += 1  # even: the write is complete

    def read_into(self, out: np.ndarray) -> bool:
        """Copy the latest complete sample into ``out`` (shape (1,), ``dtype``).

        Returns False when no sample was ever written. On a torn read ``out``
        receives the last good sample and :attr:`torn_count` grows.
        """
        for _ in range(_READ_TRIES):
            s1 = int(self._seq[0])
            if s1 == 0:
                return False
            if s1 % 2 == 0:
                out[0] = self._value[0]
                if int(self._seq[0]) == s1:
                    self._last[0] = out[0]
                    self._have_last = True
                    return True
        self.torn_count += 1
        if not self._have_last:
            return False  # only torn reads so far: a sample exists, but none whole yet
        out[0] = self._last[0]
        return True

    def read(self) -> tuple[np.void | None, bool]:
        """Return ``(sample, torn)``: a copy of the latest good sample, or None if none yet."""
        before = self.torn_count
        out = np.zeros(1, self.dtype)
        ok = self.read_into(out)
        return (out[0] if ok else None), self.torn_count != before

    def close(self) -> None:
        self._value = self._last = None  # type: ignore[assignment]
        self._seq = None  # type: ignore[assignment]
        self._seg.close()

    def unlink(self) -> None:
        self._seg.unlink()


class Ring:
    """The last ``capacity`` records of a structured ``dtype``; one writer.

    Each record slot carries the sequence number it holds (1-based), so a
    reader detects records the writer overwrote while it was copying.
    """

    def __init__(self, name: str, dtype: Any, capacity: int, create: bool) -> None:
        if capacity < 2:
            raise InputError(f"ring {name!r}: expected capacity >= 2, got {capacity}")
        self.dtype = np.dtype(dtype)
        self._slot_dtype = np.dtype([("seq", np.uint64), ("rec", self.dtype)])
        self.capacity = capacity
        self._seg = _Segment(name, 1, self._slot_dtype.itemsize * capacity, create)
        self._head = self._seg._counters[0]
        self._slots = self._seg.data(self._slot_dtype, capacity)
        self._seqs = self._slots["seq"]
        self._recs = self._slots["rec"]

    @classmethod
    def create(cls, name: str, dtype: Any, capacity: int) -> Ring:
        return cls(name, dtype, capacity, create=True)

    @classmethod
    def attach(cls, name: str, dtype: Any, capacity: int) -> Ring:
        return cls(name, dtype, capacity, create=False)

    @property
    def head(self) -> int:
        """Number of records appended so far."""
        return int(self._head[0])

    def append(self, record: Any) -> None:
        n = int(self._head[0])
        i = n % self.capacity
        self._seqs[i] = 0  # invalid while it is being written
        self._recs[i] = record
        self._seqs[i] = n + 1
        self._head[0] = n + 1

    def read_since(self, seq: int) -> tuple[np.ndarray, int, int]:
        """Return ``(records, next_seq, lost)`` for every record after ``seq``.

        ``seq`` is the ``next_seq`` of the previous call (0 at the start).
        ``lost`` counts records that were overwritten before they could be read.
        """
        head = int(self._head[0])
        start = max(seq, head - self.capacity)
        lost = start - seq
        if head <= start:
            return np.zeros(0, self.dtype), head if head > seq else seq, lost
        idx = np.arange(start, head) % self.capacity
        slots = self._slots[idx].copy()
        # Keep only the records still holding the sequence numbers we expected,
        # before and after the copy: the writer zeroes a slot's number before
        # it overwrites the record, so a record it touched during the copy fails.
        expected = np.arange(start + 1, head + 1, dtype=np.uint64)
        ok = (slots["seq"] == expected) & (self._seqs[idx] == expected)
        first_ok = int(np.argmax(ok)) if ok.any() else len(ok)
        lost += first_ok
        good = slots["rec"][first_ok:][ok[first_ok:]]
        lost += int(np.count_nonzero(~ok[first_ok:]))
        return good, head, lost

    def latest(self, n: int) -> np.ndarray:
        """Return up to the ``n`` most recent records (oldest first)."""
        head = self.head
        records, _, _ = self.read_since(max(0, head - min(n, self.capacity)))
        return records

    def close(self) -> None:
        self._slots = self._seqs = self._recs = None  # type: ignore[assignment]
        self._head = None  # type: ignore[assignment]
        self._seg.close()

    def unlink(self) -> None:
        self._seg.unlink()


class Mailbox:
    """A single-producer single-consumer queue of byte messages.

    The producer :meth:`post`s, the consumer :meth:`take`s; a message is at
    most ``slot_size`` bytes and at most ``slots`` wait at once (a full
    mailbox refuses, it never overwrites an unread command).
    """

    def __init__(self, name: str, slots: int, slot_size: int, create: bool) -> None:
        if slots < 1 or slot_size < 1:
            raise InputError(f"mailbox {name!r}: expected slots >= 1 and slot_size >= 1")
        self.slots = slots
        self.slot_size = slot_size
        # Each slot: uint64 length then the bytes, rounded to a line.
        self._stride = ((8 + slot_size + _LINE - 1) // _LINE) * _LINE
        self._seg = _Segment(name, 2, self._stride * slots, create)
        self._head, self._tail = self._seg._counters
        self._buf = self._seg.raw(self._stride * slots)
        self._lengths: list[np.ndarray] = [np.ndarray((1,), np.uint64, self._buf, i * self._stride) for i in range(slots)]

    @classmethod
    def create(cls, name: str, slots: int = 8, slot_size: int = 256 * 1024) -> Mailbox:
        return cls(name, slots, slot_size, create=True)

    @classmethod
    def attach(cls, name: str, slots: int = 8, slot_size: int = 256 * 1024) -> Mailbox:
        return cls(name, slots, slot_size, create=False)

    @property
    def posted(self) -> int:
        """Number of messages posted so far."""
        return int(self._head[0])

    @property
    def taken(self) -> int:
        """Number of messages the consumer has taken so far."""
        return int(self._tail[0])

    def pending(self) -> int:
        return self.posted - self.taken

    def post(self, payload: bytes) -> int:
        """Queue ``payload``; return its sequence number (1-based).

        Raises InputError when the payload is too large or the mailbox is full.
        """
        if len(payload) > self.slot_size:
            raise InputError(f"mailbox message of {len(payload)} bytes exceeds the slot size {self.slot_size}")
        head = int(self._head[0])
        if head - int(self._tail[0]) >= self.slots:
            raise InputError(f"mailbox full: {self.slots} messages wait unread")
        i = head % self.slots
        off = i * self._stride + 8
        self._buf[off : off + len(payload)] = payload
        self._lengths[i][0] = len(payload)
        self._head[0] = head + 1
        return head + 1

    def take(self) -> bytes | None:
        """Return the oldest unread message, or None when there is none."""
        tail = int(self._tail[0])
        if tail >= int(self._head[0]):
            return None
        i = tail % self.slots
        n = int(self._lengths[i][0])
        off = i * self._stride + 8
        payload = bytes(self._buf[off : off + n])
        self._tail[0] = tail + 1
        return payload

    def close(self) -> None:
        self._lengths = []
        self._buf.release()
        self._head = self._tail = None  # type: ignore[assignment]
        self._seg.close()

    def unlink(self) -> None:
        self._seg.unlink()


class SharedArray:
    """One array of a fixed shape and dtype in a named segment (no counters: a pipe says when it is filled)."""

    def __init__(self, name: str, shape: tuple[int, ...], dtype: Any, create: bool) -> None:
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        self._seg = _Segment(name, 0, int(np.prod(self.shape)) * self.dtype.itemsize, create)
        self.name = name
        self.array = self._seg.data(self.dtype, int(np.prod(self.shape))).reshape(self.shape)

    @classmethod
    def create(cls, name: str, shape: tuple[int, ...], dtype: Any) -> SharedArray:
        return cls(name, shape, dtype, True)

    @classmethod
    def attach(cls, name: str, shape: tuple[int, ...], dtype: Any) -> SharedArray:
        return cls(name, shape, dtype, False)

    def close(self) -> None:
        self.array = np.empty((0,), self.dtype)
        self._seg.close()

    def unlink(self) -> None:
        self._seg.unlink()
