"""The chunk file of a node's checkpoints: each chunk (chunks.py) kept once, wherever the
checkpoint files that hold it say.

``<store>/<node>/checkpoints/chunks.dat`` has no header: a chunk is ``length`` bytes at
``offset``, and a checkpoint file names each of its chunks by ``(offset, length, SHA-256)``
(store.py), checked at every load. A chunk that a checkpoint on disk names is never written
over; a new one goes into a free slot of :data:`SLOT_BYTES` (one no checkpoint names), and
the file is made durable before the checkpoint that names it is renamed into place. So a
writer killed at any moment leaves every checkpoint on disk whole. The free space is slots
no checkpoint names any more: reused by the next write, and cut off the end of the file
(:func:`collect`).

A chunk shared by checkpoints is stored once: when it is corrupt on disk, every checkpoint
holding it is refused.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from . import chunks
from .errors import CheckpointError
from .fsutil import fsync_dir

NAME: Final = 'chunks.dat'
SLOT_BYTES: Final = chunks.CHUNK_BYTES
"""Where this writer places chunks: at multiples of it, a chunk of at most one slot each. A
reader only follows offsets."""


@dataclass(frozen=True, slots=True)
class Ref:
    """Where a chunk is in the chunk file, and its SHA-256."""

    offset: int
    length: int
    digest: bytes


def place(directory: Path, parts: Sequence[chunks.Part], live: Iterable[Ref] | None) -> list[Ref]:
    """Write the chunks among ``parts`` that the file does not hold yet, durably.

    Args:
        directory: The checkpoints folder.
        parts: A checkpoint's parts; its chunks are placed, in order.
        live: Every chunk a checkpoint on disk names: reused when a chunk is one of them,
            never written over. None when not all are known: new chunks then go past the
            end of the file and of every chunk named.

    Returns:
        Where each chunk of ``parts`` is, in order.

    Raises:
        OSError: The file cannot be written.
    """
    fd = os.open(directory / NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    try:
        size = os.fstat(fd).st_size
        created = size == 0  # (or left empty by a writer that died): its name made durable
        known = [] if live is None else list(live)
        # A chunk is reused only where the file still holds it.
        held = {ref.digest: ref for ref in known if ref.offset + ref.length <= size}
        slots = _Slots(known, size, reuse=live is not None)
        refs: list[Ref] = []
        written = False
        for part in parts:
            if not isinstance(part, chunks.Chunk):
                continue
            ref = held.get(part.digest)
            if ref is None or ref.length != len(part.data):
                ref = Ref(slots.take(len(part.data)), len(part.data), part.digest)
                _pwrite_all(fd, part.data, ref.offset)
                held[part.digest] = ref  # the same chunk twice in one checkpoint: once
                written = True
            refs.append(ref)
        if written:
            os.fdatasync(fd)
    finally:
        os.close(fd)
    if created:
        fsync_dir(directory)  # the file's name durable before a checkpoint names it
    return refs


def read(path: Path, refs: Sequence[Ref], checkpoint: Path) -> list[bytes]:
    """The chunks at ``refs`` of the chunk file ``path``, each checked against its digest.

    Raises:
        CheckpointError: Naming ``checkpoint``: the file or a chunk is missing, unreadable
            or corrupt.
    """
    if not refs:
        return []
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError as err:
        msg = f'missing chunks: cannot open the chunk file {path}: {err.strerror or err}'
        raise CheckpointError(checkpoint, msg) from None
    try:
        found: list[bytes] = []
        for ref in refs:
            try:
                data = os.pread(fd, ref.length, ref.offset)
            except OSError as err:
                msg = f'cannot read the chunk at {ref.offset} of {path}: {err.strerror or err}'
                raise CheckpointError(checkpoint, msg) from None
            if len(data) != ref.length:
                msg = (f'missing chunk: {ref.length} bytes at {ref.offset} of {path}, which '
                       f'ends at {ref.offset + len(data)}')
                raise CheckpointError(checkpoint, msg)
            if chunks.sha256(data) != ref.digest:
                msg = (f'corrupt chunk: checksum mismatch of the {ref.length} bytes at '
                       f'{ref.offset} of {path}')
                raise CheckpointError(checkpoint, msg)
            found.append(data)
        return found
    finally:
        os.close(fd)


def collect(directory: Path, live: Iterable[Ref]) -> None:
    """Cut what no checkpoint names off the end of the file, once it is a quarter of what
    they name; drop the file when no checkpoint names any chunk. ``live``: every chunk a
    checkpoint on disk names.

    Raises:
        OSError: The file cannot be changed.
    """
    path = directory / NAME
    end = max((ref.offset + ref.length for ref in live), default=0)
    if end == 0:
        path.unlink(missing_ok=True)
        return
    keep = -(-end // SLOT_BYTES) * SLOT_BYTES
    # A small free end is left to the next writes: growing the file again would cost each
    # of them a journal commit in its fdatasync (the size changes), where filling a free slot
    # inside costs none.
    if path.stat().st_size > keep + max(keep // 4, SLOT_BYTES):
        os.truncate(path, keep)


class _Slots:
    """The free slots of the file, lowest first."""

    def __init__(self, live: list[Ref], size: int, *, reuse: bool) -> None:
        self._used: set[int] = set()
        end = size
        for ref in live:
            first, ref_end = ref.offset // SLOT_BYTES, ref.offset + ref.length
            if ref_end <= (first + 1) * SLOT_BYTES:
                self._used.add(first)  # the common case: a chunk in one slot
            else:
                self._used.update(range(first, -(-ref_end // SLOT_BYTES)))
            if ref_end > end:
                end = ref_end
        # Every slot below it is taken. Not knowing every live chunk, nothing in the file may
        # be written over: new chunks go past the end of everything.
        self._next = 0 if reuse else -(-end // SLOT_BYTES)

    def take(self, length: int) -> int:
        """The offset of free room for ``length`` bytes, now taken."""
        count = max(1, -(-length // SLOT_BYTES))
        start = self._next
        while any(slot in self._used for slot in range(start, start + count)):
            start += 1
        self._used.update(range(start, start + count))
        if count == 1:
            self._next = start + 1
        return start * SLOT_BYTES


def _pwrite_all(fd: int, data: bytes | memoryview, offset: int) -> None:
    view = memoryview(data).cast('B')
    while view:
        written = os.pwrite(fd, view, offset)
        view, offset = view[written:], offset + written
