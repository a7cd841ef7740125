"""Checkpoints of large state (store.py, format version 2; chunk_file.py): only the chunks no
checkpoint on disk holds yet are written, each chunk is checked at load, and the room of the
chunks no kept checkpoint names is reused."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import msgpack
import numpy as np
import pytest

from rory_runtime import chunk_file, chunks
from rory_runtime.codec import ArrayPool, decode_vars, encode_vars, pack_pieces, snapshot_vars
from rory_runtime.errors import CheckpointError
from rory_runtime.store import CHUNKED_VERSION, MAGIC, Checkpoint, CheckpointStore, deserialize

NODE = 'mapper'
CHUNK = chunks.CHUNK_BYTES
ROWS_PER_CHUNK = CHUNK // (256 * 4)  # of GRID's rows


def new_grid() -> np.ndarray:
    return np.arange(1024 * 256, dtype=np.float32).reshape(1024, 256)  # 1 MiB: 8 chunks


class Node:
    """Checkpoints a node's variables as the checkpointer does: snapshot, pieces, parts."""

    def __init__(self, store: CheckpointStore, values: dict[str, object]) -> None:
        self.store = store
        self.values = values
        self.pool = ArrayPool(CHUNK)
        self.chunker = chunks.Chunker()
        self.seq = store.next_seq()

    def checkpoint(self) -> Path:
        snapshot = snapshot_vars(self.values, self.pool)
        try:
            parts = self.chunker.split(pack_pieces(snapshot))
            path = self.store.write(make_ckpt(self.seq), parts=parts)
        finally:
            self.pool.refill(snapshot)
        self.seq += 1
        return path


def make_ckpt(seq: int, vars_blob: bytes = b'') -> Checkpoint:
    return Checkpoint(node=NODE, seq=seq, incarnation=1, created_ns=seq, manifest='m',
                      method='rory', cut=seq, windows={'/scan': [(seq, 1)]}, vars_blob=vars_blob)


@pytest.fixture
def store(tmp_path: Path) -> CheckpointStore:
    return CheckpointStore(tmp_path / 'store', NODE)


@pytest.fixture
def written(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The length of every chunk written to a chunk file."""
    lengths: list[int] = []
    real = chunk_file._pwrite_all

    def count(fd: int, data: bytes | memoryview, offset: int) -> None:
        lengths.append(len(data))
        real(fd, data, offset)

    monkeypatch.setattr(chunk_file, '_pwrite_all', count)
    return lengths


def chunks_file(store: CheckpointStore) -> Path:
    return store.dir / chunk_file.NAME


def refs_of(path: Path) -> list[list[object]]:
    data = path.read_bytes()
    (header_len,) = struct.unpack_from('<I', data, 10)
    header = msgpack.unpackb(data[14:14 + header_len])
    return [entry for entry in header['parts'] if isinstance(entry, list)]


# --------------------------------------------------------------------------- round trip


def test_a_restore_is_exact_bit_for_bit(store: CheckpointStore) -> None:
    grid = new_grid()
    grid[0, :4] = [np.nan, -0.0, np.inf, -np.inf]
    grid.view(np.uint32)[1, 0] = 0x7FC00001  # a NaN with a payload
    values: dict[str, object] = {
        'levels': [grid, grid[::2, ::2].copy()],
        'be': np.arange(40_000, dtype='>f8').reshape(200, 200),
        'mask': np.ones(70_000, dtype=bool),
        'fortran': np.asfortranarray(np.arange(90_000, dtype=np.int16).reshape(300, 300)),
        'pose': (1.0, 2.0, 3.0),
        'count': 7,
    }
    path = Node(store, values).checkpoint()
    assert path.read_bytes()[8:10] == struct.pack('<H', CHUNKED_VERSION)
    loaded = store.load(path, expect_node=NODE, expect_manifest='m')
    assert loaded == make_ckpt(1, encode_vars(values))
    restored = decode_vars(loaded.vars_blob)
    for name in ('be', 'mask', 'fortran'):
        assert restored[name].dtype == values[name].dtype  # type: ignore[attr-defined]
        assert restored[name].tobytes() == np.ascontiguousarray(values[name]).tobytes()
    assert [level.tobytes() for level in restored['levels']] == [grid.tobytes(),
                                                                  grid[::2, ::2].tobytes()]
    assert restored['pose'] == (1.0, 2.0, 3.0) and restored['count'] == 7


def test_the_file_names_its_chunks_by_offset_length_and_sha256(store: CheckpointStore) -> None:
    path = Node(store, {'grid': new_grid()}).checkpoint()
    data = path.read_bytes()
    assert data[:8] == MAGIC and data[-32:] == hashlib.sha256(data[:-32]).digest()
    held = chunks_file(store).read_bytes()
    refs = refs_of(path)
    assert len(refs) == 8
    for offset, length, digest in refs:
        assert isinstance(offset, int) and isinstance(length, int)
        assert length == CHUNK and hashlib.sha256(held[offset:offset + length]).digest() == digest
    with pytest.raises(CheckpointError, match='no chunk file was given'):
        deserialize(data, path)


def test_small_state_stays_one_file_of_format_1(store: CheckpointStore) -> None:
    path = Node(store, {'grid': np.zeros((16, 16), np.float32), 'n': 1}).checkpoint()
    assert path.read_bytes()[8:10] == struct.pack('<H', 1)
    assert os.listdir(store.dir) == [path.name]


# --------------------------------------------------------------------------- only what changed


def test_only_the_changed_chunks_are_written(store: CheckpointStore, written: list[int]) -> None:
    grid = new_grid()
    node = Node(store, {'grid': grid, 'n': 0})
    node.checkpoint()
    assert written == [CHUNK] * 8
    written.clear()
    grid[3 * ROWS_PER_CHUNK, 5] += 1.0  # chunk 3
    grid[7 * ROWS_PER_CHUNK + 1, 0] += 1.0  # chunk 7
    second = node.checkpoint()
    assert written == [CHUNK, CHUNK]
    assert sorted(os.listdir(store.dir)) == ['0000000001.ckpt', '0000000002.ckpt',
                                             chunk_file.NAME]
    assert os.path.getsize(chunks_file(store)) == 10 * CHUNK
    assert decode_vars(store.load(second).vars_blob)['grid'].tobytes() == grid.tobytes()


def test_a_checkpoint_without_changes_writes_no_chunk(store: CheckpointStore,
                                                       written: list[int]) -> None:
    values: dict[str, object] = {'grid': new_grid()}
    node = Node(store, values)
    first = refs_of(node.checkpoint())
    written.clear()
    second = refs_of(node.checkpoint())
    # Another process (nothing in memory, every chunk hashed): what is on disk is enough.
    third = refs_of(Node(CheckpointStore(store.root, NODE), values).checkpoint())
    assert written == []
    assert first == second == third


def test_equal_chunks_are_stored_once(store: CheckpointStore, written: list[int]) -> None:
    Node(store, {'zeros': np.zeros((1024, 256), np.float32)}).checkpoint()
    assert written == [CHUNK]  # eight equal chunks


# --------------------------------------------------------------------------- refusals


def _two_checkpoints(store: CheckpointStore) -> tuple[Path, Path, np.ndarray]:
    grid = new_grid()
    node = Node(store, {'grid': grid})
    older = node.checkpoint()
    grid[2 * ROWS_PER_CHUNK, 0] = -1.0  # chunk 2: a chunk of its own in the newer checkpoint
    return older, node.checkpoint(), grid


def test_a_corrupt_chunk_refuses_that_checkpoint_and_the_older_one_is_restored(
    store: CheckpointStore,
) -> None:
    older, newer, _ = _two_checkpoints(store)
    offset = refs_of(newer)[2][0]
    assert offset != refs_of(older)[2][0]
    assert isinstance(offset, int)
    with open(chunks_file(store), 'r+b') as f:
        f.seek(offset + 100)
        f.write(b'\xff')
    refused: list[CheckpointError] = []
    restored = store.latest_valid(on_refused=refused.append)
    assert restored is not None and restored.seq == 1
    assert [err.path for err in refused] == [newer]
    assert refused[0].reason.startswith('corrupt chunk: checksum mismatch')
    assert store.quarantine(newer).name == '0000000002.ckpt.refused'
    assert store.paths() == [older]


def test_a_chunk_both_checkpoints_hold_refuses_both(store: CheckpointStore) -> None:
    older, newer, _ = _two_checkpoints(store)
    shared = refs_of(newer)[0][0]
    assert shared == refs_of(older)[0][0]  # stored once
    assert isinstance(shared, int)
    with open(chunks_file(store), 'r+b') as f:
        f.seek(shared)
        f.write(b'\xff')
    refused: list[CheckpointError] = []
    assert store.latest_valid(on_refused=refused.append) is None
    assert [err.path for err in refused] == [newer, older]


def test_a_missing_chunk_refuses_that_checkpoint(store: CheckpointStore) -> None:
    older, newer, _ = _two_checkpoints(store)
    cut = max(ref[0] for ref in refs_of(newer))  # type: ignore[type-var]
    assert isinstance(cut, int)
    os.truncate(chunks_file(store), cut)  # the newer checkpoint's own chunk sits last
    refused: list[CheckpointError] = []
    restored = store.latest_valid(on_refused=refused.append)
    assert restored is not None and restored.seq == 1
    assert [err.path for err in refused] == [newer]
    assert refused[0].reason.startswith('missing chunk: 131072 bytes at')
    chunks_file(store).unlink()
    with pytest.raises(CheckpointError, match='missing chunks: cannot open the chunk file') as info:
        store.load(older)
    assert info.value.path == older


@pytest.mark.parametrize(('parts', 'reason'), [
    ('x', "field 'parts' should be a list"),
    ([[0, 5]], "field 'parts' should be a list of inline lengths"),
    ([[0, 5, b'short']], "field 'parts' should be a list of inline lengths"),
    ([[-1, 5, bytes(32)]], "field 'parts' should be a list of inline lengths"),
    ([3], 'parts name 3 inline bytes, the file holds 0'),
    ([[0, 5, bytes(32)], True], "field 'parts'"),
])
def test_a_malformed_parts_table_is_refused(store: CheckpointStore, tmp_path: Path,
                                            parts: object, reason: str) -> None:
    header = {'node': NODE, 'seq': 1, 'incarnation': 1, 'created_ns': 1, 'manifest': 'm',
              'method': 'rory', 'cut': None, 'windows': {}, 'vars_len': 5, 'parts': parts}
    packed = msgpack.packb(header, use_bin_type=True)
    body = MAGIC + struct.pack('<HI', CHUNKED_VERSION, len(packed)) + packed
    path = tmp_path / 'x.ckpt'
    path.write_bytes(body + hashlib.sha256(body).digest())
    with pytest.raises(CheckpointError, match='malformed') as info:
        store.load(path)
    assert reason in info.value.reason


# --------------------------------------------------------------------------- garbage


def test_the_room_of_dropped_chunks_is_reused(store: CheckpointStore) -> None:
    grid = new_grid()
    node = Node(store, {'grid': grid})
    for k in range(12):
        grid[(k % 8) * ROWS_PER_CHUNK, 0] += 1.0
        node.checkpoint()
        # 8 chunks of the newest, the one the older holds apart, the one in flight
        assert os.path.getsize(chunks_file(store)) <= 10 * CHUNK
    newest, older = store.paths()
    assert decode_vars(store.load(newest).vars_blob)['grid'].tobytes() == grid.tobytes()
    assert store.load(older).seq == 11


def test_nothing_a_kept_checkpoint_names_is_ever_written_over(store: CheckpointStore) -> None:
    grid = new_grid()
    node = Node(store, {'grid': grid})
    for _ in range(6):
        grid += 1.0  # every chunk, every time
        node.checkpoint()
        for path in store.paths():  # both kept checkpoints load, whole
            store.load(path)
    assert os.path.getsize(chunks_file(store)) <= 3 * 8 * CHUNK


def test_the_chunk_file_goes_when_no_checkpoint_names_a_chunk(store: CheckpointStore) -> None:
    values: dict[str, object] = {'grid': new_grid()}
    node = Node(store, values)
    node.checkpoint()
    values['grid'] = np.zeros(4)  # the state shrinks: checkpoints hold it whole
    node.checkpoint()
    assert chunks_file(store).exists()  # the older checkpoint still names chunks
    node.checkpoint()
    assert sorted(os.listdir(store.dir)) == ['0000000002.ckpt', '0000000003.ckpt']


def test_a_copy_kept_under_quarantine_keeps_its_chunks(store: CheckpointStore) -> None:
    grid = new_grid()
    node = Node(store, {'grid': grid})
    kept = store.root / NODE / 'quarantine' / '_scan-0-7.before' / 'checkpoints'
    kept.mkdir(parents=True)
    copy = kept / node.checkpoint().name  # what supervisor/poison.py copies: the file only
    shutil.copy2(store.path(1), copy)
    before = grid.tobytes()
    for _ in range(4):
        grid += 1.0
        node.checkpoint()
    restored = decode_vars(store.load(copy).vars_blob)
    assert restored['grid'].tobytes() == before
    shutil.rmtree(kept.parent)
    node.checkpoint()  # now free: the file holds two checkpoints' chunks and one in flight
    assert os.path.getsize(chunks_file(store)) <= 3 * 8 * CHUNK


def test_not_knowing_every_checkpoint_writes_past_everything(
    store: CheckpointStore, monkeypatch: pytest.MonkeyPatch,
) -> None:
    grid = new_grid()
    Node(store, {'grid': grid}).checkpoint()
    size = os.path.getsize(chunks_file(store))
    real = Path.read_bytes

    def unreadable(path: Path) -> bytes:
        if path.name == '0000000001.ckpt':
            raise PermissionError(13, 'Permission denied')
        return real(path)

    fresh = CheckpointStore(store.root, NODE)  # nothing cached
    monkeypatch.setattr(Path, 'read_bytes', unreadable)
    grid += 1.0
    Node(fresh, {'grid': grid}).checkpoint()
    monkeypatch.undo()
    offsets = [ref[0] for ref in refs_of(fresh.path(2))]
    assert all(isinstance(o, int) and o >= size for o in offsets)
    assert store.load(store.path(1)).seq == 1 and store.load(store.path(2)).seq == 2


# --------------------------------------------------------------------------- crash safety


def test_sigkill_between_the_chunks_and_the_rename_leaves_the_older_checkpoint(
    store: CheckpointStore,
) -> None:
    grid = new_grid()
    Node(store, {'grid': grid}).checkpoint()
    first = store.load(store.path(1))
    # The child writes its changed chunks into the chunk file, fsyncs them and its
    # checkpoint's temporary file, and dies by SIGKILL right before the rename.
    script = textwrap.dedent(f"""
        import os, signal
        from pathlib import Path
        import numpy as np
        from rory_runtime import chunks
        from rory_runtime.codec import ArrayPool, pack_pieces, snapshot_vars
        from rory_runtime.store import Checkpoint, CheckpointStore
        grid = np.arange(1024 * 256, dtype=np.float32).reshape(1024, 256) + 1.0
        parts = chunks.Chunker().split(pack_pieces(snapshot_vars({{'grid': grid}}, ArrayPool())))
        os.replace = lambda src, dst: os.kill(os.getpid(), signal.SIGKILL)
        CheckpointStore(Path({str(store.root)!r}), {NODE!r}).write(
            Checkpoint({NODE!r}, 2, 1, 2, 'm', 'rory', 2, {{}}, b''), parts=parts)
    """)
    child = subprocess.run([sys.executable, '-c', script], capture_output=True, check=False)
    assert child.returncode == -signal.SIGKILL, child.stderr.decode()
    assert os.path.getsize(chunks_file(store)) == 16 * CHUNK  # its chunks are there
    assert store.paths() == [store.path(1)]
    assert store.latest_valid() == first
    grid += 2.0
    Node(store, {'grid': grid}).checkpoint()  # the room the child wrote is free again
    assert not [name for name in os.listdir(store.dir) if name.endswith('.tmp')]
    assert os.path.getsize(chunks_file(store)) == 16 * CHUNK
    assert store.load(store.path(1)) == first
    assert decode_vars(store.load(store.path(2)).vars_blob)['grid'].tobytes() == grid.tobytes()
