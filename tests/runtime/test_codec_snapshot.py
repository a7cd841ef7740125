"""snapshot_vars + pack_snapshot (or pack_pieces): encode_vars split in two, the same bytes, a
true snapshot."""

from __future__ import annotations

import collections
import dataclasses
import threading
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import Point

from rory_runtime import chunks
from rory_runtime.codec import (
    ArrayPool,
    decode_vars,
    encode_vars,
    pack_pieces,
    pack_snapshot,
    snapshot_vars,
)
from rory_runtime.errors import CodecError


@dataclasses.dataclass
class _Cell:
    xy: tuple[float, float]
    samples: np.ndarray[Any, np.dtype[Any]]


GRID = np.arange(12, dtype=np.float32).reshape(3, 4)

CORPUS: list[dict[str, object]] = [
    {'grid': GRID},
    {'grid': GRID.T, 'strided': GRID[:, ::2], 'empty': np.zeros((0, 3)), 'scalar': np.array(5)},
    {'big_endian': np.arange(4, dtype='>i4'), 'mask': np.array([True, False]),
     'complex': np.array([1 + 2j])},
    {'levels': [GRID, GRID * 2], 'by_name': {'a': GRID, 'b': [1, (2, GRID)]}},
    {'in_tuple': (GRID, 'x'), 'in_deque': collections.deque([GRID], maxlen=3),
     'in_dataclass': _Cell((1.0, 2.0), GRID), 'in_set': {1, 2}},
    {'pose': Point(x=1.0), 'big': 2**80, 'text': 'grid', 'nothing': None},
]


@pytest.mark.parametrize('values', CORPUS)
def test_the_two_halves_give_encode_vars_bytes(values: dict[str, object]) -> None:
    assert pack_snapshot(snapshot_vars(values)) == encode_vars(values)


def test_a_snapshot_does_not_change_when_the_node_does() -> None:
    grid = np.zeros((4, 4), dtype=np.float32)
    path = [(0, 0)]
    counts = {'scans': 1}
    values: dict[str, object] = {'grid': grid, 'path': path, 'counts': counts}
    before = encode_vars(values)
    snapshot = snapshot_vars(values)
    # The node goes on between the snapshot and the packing (the I/O thread packs later).
    grid[1, 1] = 7.0
    path.append((1, 1))
    counts['scans'] = 2
    blob = pack_snapshot(snapshot)
    assert blob == before
    restored = decode_vars(blob)
    assert np.array_equal(restored['grid'], np.zeros((4, 4), dtype=np.float32))
    assert restored['path'] == [(0, 0)] and restored['counts'] == {'scans': 1}


def test_what_cannot_be_checkpointed_is_refused_at_the_snapshot() -> None:
    with pytest.raises(CodecError, match=r"variable 'lock'.*lock"):
        snapshot_vars({'lock': threading.Lock()})


def test_plain_encoding_after_a_snapshot_is_not_deferred() -> None:
    snapshot_vars({'grid': GRID})
    assert decode_vars(encode_vars({'grid': GRID}))['grid'].tolist() == GRID.tolist()


# -- ArrayPool: the buffers of the last packed snapshot, for the next -------------------------

BIG = np.arange(64 * 1024, dtype=np.float32).reshape(256, 256)  # 256 kB: pooled
SMALL = np.arange(16, dtype=np.int64)  # below ArrayPool.MIN_BYTES: never pooled


def test_a_pooled_snapshot_gives_encode_vars_bytes_and_reuses_the_last_buffers() -> None:
    pool = ArrayPool()
    grid = BIG.copy()
    values: dict[str, object] = {'grid': grid, 'small': SMALL, 'nested': [BIG]}
    first = snapshot_vars(values, pool)
    assert pack_snapshot(first) == encode_vars(values)
    pool.refill(first)
    assert len(pool) == 2  # the two large arrays, not the small one
    grid += 1.0
    second = snapshot_vars(values, pool)
    assert len(pool) == 0  # both buffers went to the new snapshot
    expected = encode_vars(values)
    grid += 1.0  # the node goes on; the snapshot must not see it
    assert pack_snapshot(second) == expected


def test_a_buffer_is_never_in_two_unpacked_snapshots() -> None:
    pool = ArrayPool()
    grid = BIG.copy()
    values: dict[str, object] = {'grid': grid}
    a = snapshot_vars(values, pool)
    grid += 1.0
    b = snapshot_vars(values, pool)  # taken before a was packed: a new buffer
    b_bytes = encode_vars(values)
    a_bytes = pack_snapshot(a)
    pool.refill(a)
    grid += 1.0
    c = snapshot_vars(values, pool)  # takes a's buffer; b still holds its own
    c_bytes = encode_vars(values)
    grid += 1.0
    assert pack_snapshot(b) == b_bytes
    assert pack_snapshot(c) == c_bytes
    assert a_bytes != b_bytes != c_bytes


def test_buffers_go_by_dtype_and_shape_and_a_refill_lets_the_old_ones_go() -> None:
    pool = ArrayPool()
    pool.refill(snapshot_vars({'grid': BIG}, pool))
    reshaped = {'grid': BIG.reshape(128, 512)}
    snapshot = snapshot_vars(reshaped, pool)
    assert len(pool) == 1  # another shape: not taken
    assert pack_snapshot(snapshot) == encode_vars(reshaped)
    pool.refill(snapshot)
    assert len(pool) == 1  # the 256x256 buffer is let go, the 128x512 one kept
    snapshot_vars({'grid': BIG.astype(np.float64)}, pool)
    assert len(pool) == 1  # another dtype: not taken


def test_prime_writes_buffers_for_large_top_level_arrays_only_into_an_empty_pool() -> None:
    pool = ArrayPool()
    pool.prime({'grid': BIG, 'small': SMALL, 'nested': [BIG], 'text': 'x',
                'objects': np.array([object()] * 20000, dtype=object)})
    assert len(pool) == 1
    values: dict[str, object] = {'grid': BIG}
    snapshot = snapshot_vars(values, pool)
    assert len(pool) == 0
    assert pack_snapshot(snapshot) == encode_vars(values)
    pool.refill(snapshot)
    pool.prime({'a': BIG, 'b': BIG})  # not empty: left as it is
    assert len(pool) == 1


# -- pack_pieces: the same bytes, large arrays by reference, their unchanged chunks known ----


def _joined(pieces: list[chunks.Piece]) -> bytes:
    return b''.join(p if isinstance(p, bytes) else p.data for p in pieces)


BIG_CORPUS: list[dict[str, object]] = [
    *CORPUS,
    {'grid': BIG, 'small': SMALL, 'levels': [BIG, BIG.T, 3], 'by_name': {'a': {'b': BIG}}},
    {'in_tuple': (BIG,), 'in_dataclass': _Cell((0.0, 1.0), BIG), 'big_endian': BIG.astype('>f8'),
     'odd': np.arange(100_003, dtype=np.uint8), 'empty': np.zeros((0, 70_000), np.uint8)},
]


@pytest.mark.parametrize('values', BIG_CORPUS)
@pytest.mark.parametrize('chunk_bytes', [0, 4096])
def test_pieces_joined_are_the_encode_vars_bytes(values: dict[str, object],
                                                 chunk_bytes: int) -> None:
    pool = ArrayPool(chunk_bytes)
    for _ in range(2):  # the second time into the first one's buffers
        snapshot = snapshot_vars(values, pool)
        pieces = pack_pieces(snapshot)
        assert _joined(pieces) == encode_vars(values)
        pool.refill(snapshot)


def test_large_arrays_in_lists_and_dicts_are_pieces_by_reference() -> None:
    values: dict[str, object] = {'levels': [BIG, BIG * 2], 'named': {'a': BIG}, 'grid': BIG,
                                 'in_tuple': (BIG,), 'small': SMALL}
    snapshot = snapshot_vars(values, ArrayPool(4096))
    tracked = [p for p in pack_pieces(snapshot) if isinstance(p, chunks.Tracked)]
    assert len(tracked) == 4  # a tuple packs its items at the snapshot: inline
    assert all(p.data.nbytes == BIG.nbytes and p.chunk_bytes == 4096 for p in tracked)
    assert all(p.digests == [None] * (BIG.nbytes // 4096) for p in tracked)


def test_the_next_snapshot_keeps_the_digests_of_unchanged_chunks() -> None:
    pool = ArrayPool(4096)
    a, b = BIG.copy(), BIG.copy()  # same dtype and shape: each keeps its own buffer
    values: dict[str, object] = {'a': a, 'levels': [b]}
    first = snapshot_vars(values, pool)
    pieces = pack_pieces(first)
    chunks.Chunker(4096, inline_max=0).split(pieces)  # hashes every chunk
    pool.refill(first)
    a[10, 10] += 1.0  # chunk 2 of a (rows of 1 kB, 4 rows a chunk)
    second = snapshot_vars(values, pool)
    tracked = [p for p in pack_pieces(second) if isinstance(p, chunks.Tracked)]
    assert [i for i, d in enumerate(tracked[0].digests) if d is None] == [2]
    assert None not in tracked[1].digests
    assert _joined(pack_pieces(second)) == encode_vars(values)
