"""Which message a node was applying when it died, and whether it is alive: the in-flight slot.

The node's runtime writes the topic and identity of a message into a small memory-mapped file
before calling the user's callback, and marks it idle after. A write to a shared mapping is a
memory store, no system call, and it survives the process being killed (the page belongs to
the file). After a crash the supervisor reads the slot: the message the node died applying is a
suspect; dying on the same message twice makes it a poison message (see supervisor/poison.py).

The same page carries the node's heartbeat: the runtime's side thread (node/pulse.py) writes
``CLOCK_MONOTONIC`` (system-wide, so the supervisor can compare) a few times a second while the
node's executor shows it runs. A node whose executor is stuck - in a callback that never
returns, a deadlock, a busy loop - stops beating, and the supervisor treats it as crashed.
Reading it is a file read: no DDS, so a loaded network cannot fake a hang.

Layout (little endian, 256 bytes)::

    magic 'RYIF' | version u8 | busy u8 | topic_len u16 | incarnation u32 | seq u32
    source_ns i64 | recv_ns i64 | topic (utf-8, up to 216 bytes) ... | beat_ns i64 (at 248)
"""

from __future__ import annotations

import functools
import mmap
import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from .fsutil import make_private_dir
from .protocol import MessageId

SLOT_SIZE = 256
_HEAD = struct.Struct('<4sBBHIIqq')
_MAGIC = b'RYIF'
_VERSION = 2
_BEAT = struct.Struct('<q')
_BEAT_AT = SLOT_SIZE - _BEAT.size
_TOPIC_MAX = _BEAT_AT - _HEAD.size


@dataclass(frozen=True)
class InFlight:
    """The message a node was applying."""

    incarnation: int
    topic: str
    ident: MessageId
    recv_ns: int


def slot_path(store: Path, node_id: str) -> Path:
    """Where a node's slot lives."""
    return store / node_id / 'inflight'


_IDLE = _HEAD.pack(_MAGIC, _VERSION, 0, 0, 0, 0, 0, 0)[:8]  # the slot's first 8 bytes, idle
_IDLE_AT = slice(0, len(_IDLE))
_HEAD_AT = slice(0, _HEAD.size)


class SlotWrites(NamedTuple):
    """What :meth:`InFlightSlot.busy` and :meth:`InFlightSlot.idle` write for one topic's
    messages, for a caller that writes it itself: the applier's hot path (node/applier.py), where
    two method calls fewer per message are worth it. The layout stays this module's.

    Busy: ``map[name_at] = name; map[head_at] = head(seq, source_ns, recv_ns)``; idle:
    ``map[idle_at] = idle``.
    """

    map: mmap.mmap
    name_at: slice
    name: bytes
    head_at: slice
    head: Callable[[int, int, int], bytes]  # the header, busy, of (seq, source_ns, recv_ns)
    idle_at: slice
    idle: bytes


class InFlightSlot:
    """The node's side: mark a message busy before its callback, idle after."""

    def __init__(self, path: Path, incarnation: int) -> None:
        make_private_dir(path.parent)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            os.ftruncate(fd, SLOT_SIZE)
            self._map = mmap.mmap(fd, SLOT_SIZE)
        finally:
            os.close(fd)
        self._incarnation = incarnation
        self._topic_cache: dict[str, bytes] = {}
        self._map[_BEAT_AT:SLOT_SIZE] = _BEAT.pack(0)  # no beat yet from this process
        self.idle()

    def busy(self, topic: str, ident: MessageId, recv_ns: int) -> None:
        """A callback is about to run on this message."""
        name = self._topic_cache.get(topic)
        if name is None:
            name = topic.encode()[:_TOPIC_MAX]
            self._topic_cache[topic] = name
        self._map[_HEAD.size : _HEAD.size + len(name)] = name
        self._map[: _HEAD.size] = _HEAD.pack(
            _MAGIC, _VERSION, 1, len(name), self._incarnation, ident[1], ident[0], recv_ns
        )

    def writes(self, topic: str) -> SlotWrites:
        """What :meth:`busy` and :meth:`idle` write for ``topic``'s messages (made once)."""
        name = topic.encode()[:_TOPIC_MAX]
        head = functools.partial(_HEAD.pack, _MAGIC, _VERSION, 1, len(name), self._incarnation)
        return SlotWrites(self._map, slice(_HEAD.size, _HEAD.size + len(name)), name, _HEAD_AT,
                          head, _IDLE_AT, _IDLE)

    def idle(self) -> None:
        """No callback is running on a message."""
        self._map[:8] = _IDLE

    def beat(self) -> None:
        """The executor is alive (node/pulse.py decides when)."""
        _BEAT.pack_into(self._map, _BEAT_AT, time.monotonic_ns())

    def close(self) -> None:
        """Unmap."""
        self._map.close()


def read_beat(path: Path) -> int | None:
    """The node's last heartbeat (``time.monotonic_ns()``), or None before its first."""
    try:  # (os-level: the supervisor reads every node's beat several times a second)
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        data = os.pread(fd, _BEAT.size, _BEAT_AT)
    except OSError:
        return None
    finally:
        os.close(fd)
    if len(data) != _BEAT.size:
        return None
    beat: int = _BEAT.unpack(data)[0]
    return beat or None


def read_slot(path: Path) -> InFlight | None:
    """The message a dead node was applying, or None (idle, absent or unreadable)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if len(data) < SLOT_SIZE:
        return None
    magic, version, busy, topic_len, incarnation, seq, source_ns, recv_ns = _HEAD.unpack_from(data)
    if magic != _MAGIC or version != _VERSION or busy != 1 or topic_len > _TOPIC_MAX:
        return None
    try:
        topic = data[_HEAD.size : _HEAD.size + topic_len].decode()
    except UnicodeDecodeError:
        return None
    return InFlight(incarnation, topic, (source_ns, seq), recv_ns)
