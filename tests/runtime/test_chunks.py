"""chunks.py: what changed is found by comparing, and only that is hashed."""

from __future__ import annotations

import numpy as np
import pytest

from rory_runtime import chunks
from rory_runtime.chunks import Chunk, Chunker, Tracked, copy_changed

STEP = 1024  # a small chunk size, so that small arrays make several chunks


def _digests(buffer: np.ndarray, step: int = STEP) -> chunks.Digests:
    data = buffer.reshape(-1).view(np.uint8)
    return [chunks.sha256(data[o:o + step].tobytes()) for o in range(0, data.nbytes, step)]


def test_copy_changed_copies_only_what_differs_and_keeps_the_other_digests() -> None:
    src = np.arange(1000, dtype=np.float32)  # 4000 bytes: 4 chunks, the last one short
    dst = src.copy()
    known = _digests(dst)
    src[300] = -1.0  # chunk 1
    src[999] = -2.0  # chunk 3, the short one
    digests = copy_changed(dst, src, known, STEP)
    assert digests == [known[0], None, known[2], None]
    assert dst.tobytes() == src.tobytes()


def test_copy_changed_compares_bytes_not_values() -> None:
    src = np.array([0.0, np.nan] * 256, dtype=np.float64)
    dst = src.copy()
    known = _digests(dst)
    src[0] = -0.0  # equal to 0.0 as a value, not as bytes
    digests = copy_changed(dst, src, known, STEP)
    assert digests[0] is None and digests[1:] == known[1:]
    assert dst.tobytes() == src.tobytes()


@pytest.mark.parametrize('case', ['unknown', 'wrong count', 'not C order'])
def test_without_what_to_compare_everything_is_copied_and_nothing_is_known(case: str) -> None:
    grid = np.arange(64 * 64, dtype=np.float32).reshape(64, 64)
    src = grid.T if case == 'not C order' else grid
    dst = np.empty_like(grid)
    known = {'unknown': None, 'wrong count': [b'x' * 32]}.get(case, _digests(grid.T.copy()))
    digests = copy_changed(dst, src, known, STEP)
    assert digests == [None] * 16
    assert dst.tobytes() == np.ascontiguousarray(src).tobytes()


def _joined(parts: list[chunks.Part]) -> bytes:
    return b''.join(p if isinstance(p, bytes) else bytes(p.data) for p in parts)


def test_small_variables_stay_one_inline_part() -> None:
    array = np.arange(100, dtype=np.uint8)
    tracked = Tracked(array.data.cast('B'), [None], 128)
    parts = Chunker(STEP, inline_max=1000).split([b'head', tracked, b'tail'])
    assert parts == [b'head' + array.tobytes() + b'tail']
    assert tracked.digests == [None]  # not hashed: nothing goes to a chunk


def test_large_variables_are_chunked_and_only_unknown_digests_hashed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    array = np.arange(2500, dtype=np.uint8)  # three chunks: 1024, 1024, 452
    known = _digests(array)
    tracked = Tracked(array.data.cast('B'), [known[0], None, known[2]], STEP)
    hashed: list[int] = []
    real = chunks.sha256
    monkeypatch.setattr(chunks, 'sha256', lambda data: hashed.append(len(data)) or real(data))
    parts = Chunker(STEP, inline_max=1000).split([b'a', b'b', tracked, b'c'])
    assert hashed == [STEP]  # the one chunk whose digest was not known
    assert tracked.digests == known
    assert parts[0] == b'ab' and parts[-1] == b'c'
    assert [p.digest for p in parts[1:-1] if isinstance(p, Chunk)] == known
    assert _joined(parts) == b'ab' + array.tobytes() + b'c'


def test_long_runs_of_bytes_are_compared_with_the_last_checkpoints(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    chunker = Chunker(STEP, inline_max=1000)
    blob = bytes(range(256)) * 12  # 3072 bytes: three chunks
    hashed: list[int] = []
    real = chunks.sha256
    monkeypatch.setattr(chunks, 'sha256', lambda data: hashed.append(len(data)) or real(data))
    first = chunker.split([blob])
    assert len(hashed) == 3
    changed = blob[:2000] + b'\xff' + blob[2001:]
    second = chunker.split([changed])
    assert len(hashed) == 4  # the middle chunk only
    assert _joined(first) == blob and _joined(second) == changed
    assert [isinstance(p, Chunk) for p in second] == [True, True, True]
    assert chunks.split_blob(blob[:10]) == [blob[:10]]  # whole blobs: small ones inline
