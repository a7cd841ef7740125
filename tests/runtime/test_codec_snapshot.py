"""snapshot_vars + pack_snapshot: encode_vars split in two, the same bytes, a true snapshot."""

from __future__ import annotations

import collections
import dataclasses
import threading
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import Point

from rory_runtime.codec import decode_vars, encode_vars, pack_snapshot, snapshot_vars
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
