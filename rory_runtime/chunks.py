"""A checkpoint's variables cut into chunks, so that a checkpoint writes only what changed.

The encoded variables (``codec.encode_vars`` bytes) reach the store as *parts*, in order:
bytes kept inline in the checkpoint file, or a :class:`Chunk` of at most :data:`CHUNK_BYTES`
named by its SHA-256, which the store keeps once however many checkpoints hold it
(store.py). Their concatenation is the encoded variables, byte for byte.

What changed is found without hashing the whole state: a large array's snapshot is copied
into the buffer of the previous snapshot of the same variable chunk by chunk, comparing first
(:func:`copy_changed`, memcmp speed), and a chunk equal to what the buffer held keeps the
digest it had; only the others are hashed (:meth:`Chunker.split`). Large runs of other bytes
(a long list of numbers) are compared with the previous checkpoint's bytes at the same place.

State of at most :data:`INLINE_MAX` bytes stays whole in the checkpoint file, as before
chunks existed: one file, no chunk to look up.
"""

from __future__ import annotations

import ctypes
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

CHUNK_BYTES: Final = 128 * 1024
"""Chunk size. Smaller chunks follow a local change more closely, but every chunk costs a
comparison, a digest and an entry in the checkpoint file whether it changed or not; how the
size was chosen is in docs/performance.md ("Checkpoints write only what changed")."""

INLINE_MAX: Final = 256 * 1024
"""Encoded variables up to this size are written whole in the checkpoint file, as before
chunks: one self-contained file (what most nodes have: a few kB), no chunk file to keep."""

DIGEST_BYTES: Final = 32

# PyDLL, not CDLL: the call keeps the GIL. It is taken under the node's lock, a few
# microseconds per chunk; releasing the GIL there would let another thread in between chunks
# and keep the node paused until it gives it back.
_libc: Final = ctypes.PyDLL(None)
_memcmp: Final = _libc.memcmp
_memcmp.argtypes = (ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_memcmp.restype = ctypes.c_int
_memcpy: Final = _libc.memcpy
_memcpy.argtypes = (ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_memcpy.restype = ctypes.c_void_p

Digests = list[bytes | None]
"""Per chunk of a buffer, the SHA-256 of its bytes, or None when not known."""


@dataclass(frozen=True, slots=True)
class Chunk:
    """A run of the encoded variables that the store keeps apart, by its SHA-256.

    ``data`` may be a view into a snapshot's buffer: valid until the store has written it.
    """

    digest: bytes
    data: bytes | memoryview


Part = bytes | Chunk
"""Inline bytes, or a chunk."""


@dataclass(slots=True)
class Tracked:
    """The bytes of one large array of a snapshot, C order, and what is known of its chunks.

    Attributes:
        data: The bytes (a flat byte view of the snapshot's buffer).
        digests: Per chunk of ``chunk_bytes``, its digest, or None; :meth:`Chunker.split`
            fills in the missing ones, so that the next snapshot into the same buffer can
            keep those of the chunks it finds unchanged.
        chunk_bytes: The size the digests were taken at.
    """

    data: memoryview
    digests: Digests
    chunk_bytes: int


Piece = bytes | Tracked
"""What ``codec.pack_pieces`` gives: the encoded variables as bytes and large arrays."""


def size_of(parts: Sequence[Part]) -> int:
    """How many bytes of encoded variables ``parts`` make."""
    return sum(len(part) if isinstance(part, bytes) else len(part.data) for part in parts)


def chunk_count(size: int, chunk_bytes: int) -> int:
    """How many chunks ``size`` bytes make."""
    return -(-size // chunk_bytes)


def copy_changed(
    dst: np.ndarray[Any, np.dtype[Any]],
    src: np.ndarray[Any, np.dtype[Any]],
    known: Digests | None,
    chunk_bytes: int,
) -> Digests:
    """Copy ``src`` into ``dst`` (same dtype and shape, ``dst`` C order), chunk by chunk,
    skipping the chunks whose bytes are already there.

    Args:
        dst: The buffer, holding the bytes ``known`` describes.
        src: The array to copy.
        known: The digests of ``dst``'s chunks as it is now, or None.
        chunk_bytes: The chunk size.

    Returns:
        The digests of ``dst``'s chunks after the copy: a known digest where the chunk was
        already equal, None where it was copied.
    """
    count = chunk_count(dst.nbytes, chunk_bytes)
    if known is None or len(known) != count or not src.flags.c_contiguous:
        # Nothing to compare against (a new or primed buffer), or the bytes of src are not
        # in C order: one plain copy.
        np.copyto(dst, src, casting='no')
        return [None] * count
    size = dst.nbytes
    to_address: int = dst.ctypes.data
    from_address: int = src.ctypes.data
    digests: Digests = []
    for index, digest in enumerate(known):
        offset = index * chunk_bytes
        length = min(chunk_bytes, size - offset)
        if digest is not None and not _memcmp(to_address + offset, from_address + offset, length):
            digests.append(digest)
            continue
        _memcpy(to_address + offset, from_address + offset, length)
        digests.append(None)
    return digests


def split_blob(blob: bytes) -> list[Part]:
    """The parts of encoded variables given whole (every chunk hashed)."""
    return Chunker().split([blob])


class Chunker:
    """Cuts a checkpoint's pieces into parts; one per checkpointer, used on one thread.

    It remembers the chunks of the previous checkpoint's large runs of bytes, to find those
    that did not change without hashing them.
    """

    def __init__(self, chunk_bytes: int = CHUNK_BYTES, inline_max: int = INLINE_MAX) -> None:
        self.chunk_bytes = chunk_bytes
        self.inline_max = inline_max
        self._previous: dict[tuple[int, int], tuple[bytes, bytes]] = {}

    def split(self, pieces: Sequence[Piece]) -> list[Part]:
        """The parts of the encoded variables ``pieces`` make, in order.

        Fills in the missing digests of the tracked arrays' chunks.
        """
        total = sum(len(p) if isinstance(p, bytes) else p.data.nbytes for p in pieces)
        if total <= self.inline_max:
            return [b''.join(p if isinstance(p, bytes) else p.data for p in pieces)]
        parts: list[Part] = []
        inline: list[bytes] = []
        previous, self._previous = self._previous, {}
        for index, piece in enumerate(pieces):
            if isinstance(piece, bytes) and len(piece) < self.chunk_bytes:
                inline.append(piece)
                continue
            if inline:
                parts.append(b''.join(inline))
                inline = []
            if isinstance(piece, bytes):
                parts.extend(self._bytes_chunks(index, piece, previous))
            else:
                parts.extend(_tracked_chunks(piece))
        if inline:
            parts.append(b''.join(inline))
        return parts

    def _bytes_chunks(
        self, index: int, piece: bytes, previous: dict[tuple[int, int], tuple[bytes, bytes]]
    ) -> list[Part]:
        chunks: list[Part] = []
        for offset in range(0, len(piece), self.chunk_bytes):
            data = piece[offset:offset + self.chunk_bytes]
            before = previous.get((index, offset))
            # bytes == bytes is a memcmp; hashing would cost several times more.
            digest = before[1] if before is not None and before[0] == data else sha256(data)
            self._previous[(index, offset)] = (data, digest)
            chunks.append(Chunk(digest, data))
        return chunks


def _tracked_chunks(piece: Tracked) -> list[Part]:
    size, step = piece.data.nbytes, piece.chunk_bytes
    if len(piece.digests) != chunk_count(size, step):
        piece.digests = [None] * chunk_count(size, step)
    chunks: list[Part] = []
    for index, offset in enumerate(range(0, size, step)):
        data = piece.data[offset:offset + step]
        digest = piece.digests[index]
        if digest is None:
            digest = piece.digests[index] = sha256(data)
        chunks.append(Chunk(digest, data))
    return chunks


def sha256(data: bytes | memoryview) -> bytes:
    """The SHA-256 digest of ``data``."""
    return hashlib.sha256(data).digest()
