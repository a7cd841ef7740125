"""Tests of the durable checkpoint store."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import signal
import stat
import struct
import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import msgpack
import pytest

from rory_runtime.codec import decode_vars, encode_vars
from rory_runtime.errors import CheckpointError
from rory_runtime.store import (
    FORMAT_VERSION,
    MAGIC,
    Checkpoint,
    CheckpointStore,
    deserialize,
    serialize,
)

NODE = 'integrator'


def make_ckpt(seq: int, **changes: object) -> Checkpoint:
    ckpt = Checkpoint(
        node=NODE,
        seq=seq,
        incarnation=2,
        created_ns=1_700_000_000_000_000_000 + seq,
        manifest='sha256:abc',
        method='rory',
        cut=seq + 10,
        windows={'/a': [(100, 1), (200, 2)], '/b': []},
        vars_blob=encode_vars({'total': 1.5 * seq, 'history': [(1, 2)]}),
    )
    return replace(ckpt, **changes)  # type: ignore[arg-type]


@pytest.fixture
def store(tmp_path: Path) -> CheckpointStore:
    return CheckpointStore(tmp_path / 'state', NODE)


def refusal(store: CheckpointStore, path: Path, **kwargs: str) -> CheckpointError:
    with pytest.raises(CheckpointError) as info:
        store.load(path, **kwargs)
    assert info.value.path == path
    return info.value


def frame(header: object, vars_blob: bytes = b'', version: int = FORMAT_VERSION) -> bytes:
    """A checkpoint file with a valid checksum around a hand-made header."""
    packed = header if isinstance(header, bytes) else msgpack.packb(header, use_bin_type=True)
    body = MAGIC + struct.pack('<HI', version, len(packed)) + packed + vars_blob
    return body + hashlib.sha256(body).digest()


def header_of(ckpt: Checkpoint) -> dict[str, object]:
    return {
        'node': ckpt.node,
        'seq': ckpt.seq,
        'incarnation': ckpt.incarnation,
        'created_ns': ckpt.created_ns,
        'manifest': ckpt.manifest,
        'method': ckpt.method,
        'cut': ckpt.cut,
        'windows': {k: [list(i) for i in v] for k, v in ckpt.windows.items()},
        'vars_len': len(ckpt.vars_blob),
    }


# --------------------------------------------------------------------------- basics


def test_roundtrip(store: CheckpointStore) -> None:
    ckpt = make_ckpt(1)
    path = store.write(ckpt)
    assert path == store.dir / '0000000001.ckpt'
    assert path.parent == store.root / NODE / 'checkpoints'
    loaded = store.load(path, expect_manifest='sha256:abc', expect_node=NODE)
    assert loaded == ckpt
    assert loaded.windows['/a'] == [(100, 1), (200, 2)]
    assert isinstance(loaded.windows['/a'][0], tuple)
    assert decode_vars(loaded.vars_blob) == {'total': 1.5, 'history': [(1, 2)]}


def test_roundtrip_with_parameters_and_without(store: CheckpointStore) -> None:
    with_parameters = dataclasses.replace(make_ckpt(1), parameters=b'\x00\x01cdr')
    assert store.load(store.write(with_parameters)).parameters == b'\x00\x01cdr'
    # A checkpoint from before parameters were kept has none: restored as empty.
    path = store.dir / '0000000002.ckpt'
    path.write_bytes(frame(header_of(make_ckpt(2)), make_ckpt(2).vars_blob))
    assert store.load(path).parameters == b''


def test_roundtrip_with_the_clock_and_freshness_rules(store: CheckpointStore) -> None:
    ckpt = dataclasses.replace(make_ckpt(1), clock_ns=123_000_000_000, sim_time=True,
                               freshness=(('pose', 5.0, 'reset'), ('global:goal', 30.0, 'keep')))
    assert deserialize(serialize(ckpt)) == ckpt
    # From before they were kept: no clock (0), no rules.
    plain = deserialize(serialize(make_ckpt(2)))
    assert (plain.clock_ns, plain.sim_time, plain.freshness) == (0, False, ())


def test_roundtrip_without_log(store: CheckpointStore) -> None:
    ckpt = make_ckpt(1, cut=None, windows={}, vars_blob=b'')
    assert store.load(store.write(ckpt)) == ckpt


def test_file_layout_is_as_documented() -> None:
    ckpt = make_ckpt(3)
    data = serialize(ckpt)
    assert data[:8] == b'RORYCKPT'
    version, header_len = struct.unpack_from('<HI', data, 8)
    assert version == 1
    header = msgpack.unpackb(data[14 : 14 + header_len])
    assert header == header_of(ckpt)
    assert data[14 + header_len : -32] == ckpt.vars_blob
    assert data[-32:] == hashlib.sha256(data[:-32]).digest()
    assert deserialize(data) == ckpt


def test_modes(store: CheckpointStore) -> None:
    old = os.umask(0o022)
    try:
        path = store.write(make_ckpt(1))
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(store.dir.stat().st_mode) == 0o700
    assert stat.S_IMODE(store.dir.parent.stat().st_mode) == 0o700
    assert stat.S_IMODE(store.root.stat().st_mode) == 0o700


def test_paths_newest_first_and_next_seq(store: CheckpointStore) -> None:
    assert store.paths() == []
    assert store.next_seq() == 1
    store.write(make_ckpt(1))
    store.write(make_ckpt(2))
    assert store.paths() == [store.dir / '0000000002.ckpt', store.dir / '0000000001.ckpt']
    assert store.next_seq() == 3
    (store.dir / 'notes.txt').write_text('not a checkpoint')
    (store.dir / '12.ckpt').write_bytes(b'')
    assert len(store.paths()) == 2


def test_keeps_only_the_newest_two(store: CheckpointStore) -> None:
    for seq in range(1, 6):
        store.write(make_ckpt(seq))
    assert [p.name for p in store.paths()] == ['0000000005.ckpt', '0000000004.ckpt']
    assert store.next_seq() == 6


def test_keep_is_configurable(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path, NODE, keep=3)
    for seq in range(1, 6):
        store.write(make_ckpt(seq))
    assert len(store.paths()) == 3
    with pytest.raises(ValueError, match='keep'):
        CheckpointStore(tmp_path, NODE, keep=0)


# A node id is what the supervisor config allows (protocol.NODE_ID_RE): no path, and a part
# of a ROS topic name, so no '-' or '.' and no digit first.
@pytest.mark.parametrize('node', ['', '.', '..', 'a/b', '/abs', 'a\x00b', 'sp ace', 'my-node',
                                  'a.b', '0abc', '_x'])
def test_bad_node_id(tmp_path: Path, node: str) -> None:
    with pytest.raises(ValueError, match='is not a node id'):
        CheckpointStore(tmp_path, node)


# --------------------------------------------------------------------------- write refusals


def test_write_refuses_a_seq_not_above_the_newest(store: CheckpointStore) -> None:
    store.write(make_ckpt(2))
    for seq in (1, 2):
        with pytest.raises(CheckpointError, match='not above the newest'):
            store.write(make_ckpt(seq))
    assert store.load(store.paths()[0]) == make_ckpt(2)


def test_write_refuses_another_node(store: CheckpointStore) -> None:
    with pytest.raises(CheckpointError, match="checkpoint of node 'other'"):
        store.write(make_ckpt(1, node='other'))


@pytest.mark.parametrize(
    ('changes', 'field'),
    [
        ({'seq': 0}, 'seq'),
        ({'seq': 10**10}, 'seq'),
        ({'incarnation': -1}, 'incarnation'),
        ({'created_ns': 2**64}, 'created_ns'),
        ({'cut': True}, 'cut'),
        ({'manifest': None}, 'manifest'),
        ({'windows': {'/a': [(1, 2, 3)]}}, 'windows'),
        ({'windows': {1: []}}, 'windows'),
        ({'windows': {'/a': [(-1, 0)]}}, 'windows'),
        ({'vars_blob': bytearray(b'x')}, 'vars_blob'),
    ],
)
def test_write_refuses_invalid_fields(
    store: CheckpointStore, changes: dict[str, object], field: str
) -> None:
    with pytest.raises(CheckpointError, match=f'invalid field.*{field}'):
        store.write(replace(make_ckpt(1), **changes))  # type: ignore[arg-type]
    assert store.paths() == []


# --------------------------------------------------------------------------- atomicity


def test_crash_before_rename_leaves_no_final_file(
    store: CheckpointStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    store.write(make_ckpt(1))

    def crash(src: object, dst: object) -> None:
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(os, 'replace', crash)
    with pytest.raises(CheckpointError, match=r'cannot write.*No space left'):
        store.write(make_ckpt(2))
    monkeypatch.undo()
    assert [p.name for p in store.paths()] == ['0000000001.ckpt']
    assert sorted(os.listdir(store.dir)) == ['0000000001.ckpt']  # temp file removed


def test_sigkill_mid_write_leaves_a_temp_file_that_is_ignored_then_cleaned(
    store: CheckpointStore,
) -> None:
    store.write(make_ckpt(1))
    # The child dies by SIGKILL after writing and fsyncing the temp file, right before the
    # rename, which is the worst moment for a writer to die.
    script = textwrap.dedent(
        f"""
        import os, signal
        from pathlib import Path
        from rory_runtime.store import Checkpoint, CheckpointStore
        ckpt = Checkpoint({NODE!r}, 2, 2, 0, 'm', 'rory', None, {{}}, b'vars')
        os.replace = lambda src, dst: os.kill(os.getpid(), signal.SIGKILL)
        CheckpointStore(Path({str(store.root)!r}), {NODE!r}).write(ckpt)
        """
    )
    child = subprocess.run(
        [sys.executable, '-c', script],
        capture_output=True,
        check=False,
    )
    assert child.returncode == -signal.SIGKILL, child.stderr.decode()
    leftovers = [name for name in os.listdir(store.dir) if name.endswith('.tmp')]
    assert len(leftovers) == 1
    assert leftovers[0].startswith('.0000000002.ckpt.')
    assert [p.name for p in store.paths()] == ['0000000001.ckpt']
    assert store.latest_valid() == make_ckpt(1)
    assert store.next_seq() == 2

    store.write(make_ckpt(2))
    assert sorted(os.listdir(store.dir)) == ['0000000001.ckpt', '0000000002.ckpt']


def test_temp_file_of_a_live_writer_is_kept(store: CheckpointStore) -> None:
    store.write(make_ckpt(1))
    live = store.dir / f'.0000000009.ckpt.{os.getppid()}.abc.tmp'
    dead = store.dir / '.0000000008.ckpt.999999999.abc.tmp'
    odd = store.dir / '.odd.tmp'
    for path in (live, dead, odd):
        path.write_bytes(b'partial')
    store.write(make_ckpt(2))
    assert live.exists()
    assert not dead.exists()
    assert not odd.exists()


def test_truncated_final_file_is_skipped(store: CheckpointStore) -> None:
    store.write(make_ckpt(1))
    newest = store.write(make_ckpt(2))
    newest.write_bytes(newest.read_bytes()[:40])
    refused: list[CheckpointError] = []
    assert store.latest_valid(on_refused=refused.append) == make_ckpt(1)
    assert [err.path for err in refused] == [newest]
    assert 'truncated' in refused[0].reason


# --------------------------------------------------------------------------- refusals on load


def test_every_corrupt_byte_is_refused(store: CheckpointStore, tmp_path: Path) -> None:
    data = serialize(make_ckpt(1))
    path = tmp_path / 'x.ckpt'
    for index in range(len(data)):
        damaged = bytearray(data)
        damaged[index] ^= 0x01
        path.write_bytes(damaged)
        err = refusal(store, path)
        expected = 'bad magic' if index < len(MAGIC) else 'checksum mismatch'
        assert expected in err.reason, (index, err.reason)


def test_every_truncation_is_refused(store: CheckpointStore, tmp_path: Path) -> None:
    data = serialize(make_ckpt(1, windows={}, vars_blob=encode_vars({'x': 1})))
    path = tmp_path / 'x.ckpt'
    for length in range(len(data)):
        path.write_bytes(data[:length])
        err = refusal(store, path)
        assert 'truncated' in err.reason, (length, err.reason)
    path.write_bytes(data)
    assert store.load(path).seq == 1


def test_appended_bytes_are_refused(store: CheckpointStore, tmp_path: Path) -> None:
    path = tmp_path / 'x.ckpt'
    path.write_bytes(serialize(make_ckpt(1)) + b'\x00')
    assert 'checksum' in refusal(store, path).reason


def test_missing_and_unreadable_files(store: CheckpointStore, tmp_path: Path) -> None:
    assert 'cannot read' in refusal(store, tmp_path / 'nope.ckpt').reason
    assert 'cannot read' in refusal(store, tmp_path).reason  # a directory


def test_not_a_checkpoint(store: CheckpointStore, tmp_path: Path) -> None:
    path = tmp_path / 'x.ckpt'
    path.write_bytes(b'PK\x03\x04' + b'\x00' * 100)
    assert 'bad magic' in refusal(store, path).reason


def test_unsupported_version(store: CheckpointStore, tmp_path: Path) -> None:
    path = tmp_path / 'x.ckpt'
    path.write_bytes(frame(header_of(make_ckpt(1, vars_blob=b'')), version=3))
    assert refusal(store, path).reason == ('unsupported format version 3, this reader supports 1'
                                           ' and 2')


def test_manifest_mismatch(store: CheckpointStore) -> None:
    path = store.write(make_ckpt(1))
    err = refusal(store, path, expect_manifest='sha256:new')
    assert err.reason == (
        'written by a different version of the instrumented code:'
        ' manifest sha256:abc, expected sha256:new'
    )


def test_node_mismatch(store: CheckpointStore, tmp_path: Path) -> None:
    path = tmp_path / 'x.ckpt'
    path.write_bytes(serialize(make_ckpt(1, node='other')))
    assert "node 'other', expected 'integrator'" in refusal(store, path, expect_node=NODE).reason


GOOD = header_of(make_ckpt(1, vars_blob=b''))


@pytest.mark.parametrize(
    ('header', 'reason'),
    [
        ({k: v for k, v in GOOD.items() if k != 'seq'}, "field 'seq' is missing"),
        ({k: v for k, v in GOOD.items() if k != 'windows'}, "field 'windows' is missing"),
        ({k: v for k, v in GOOD.items() if k != 'vars_len'}, 'vars_len None'),
        ({**GOOD, 'seq': True}, "field 'seq' should be an int >= 1, got True"),
        ({**GOOD, 'seq': 0}, "field 'seq' should be an int >= 1"),
        ({**GOOD, 'seq': '1'}, "field 'seq'"),
        ({**GOOD, 'incarnation': -1}, "field 'incarnation'"),
        ({**GOOD, 'created_ns': 1.5}, "field 'created_ns'"),
        ({**GOOD, 'node': 5}, "field 'node' should be a str, got 5"),
        ({**GOOD, 'manifest': None}, "field 'manifest' should be a str"),
        ({**GOOD, 'method': 3}, "field 'method'"),
        ({**GOOD, 'cut': 'x'}, "field 'cut'"),
        ({**GOOD, 'cut': False}, "field 'cut'"),
        ({**GOOD, 'windows': []}, "field 'windows'"),
        ({**GOOD, 'windows': {'/a': [[1]]}}, "field 'windows'['/a'] should be a pair"),
        ({**GOOD, 'windows': {'/a': [[1, -2]]}}, "field 'windows'['/a'] should be a pair"),
        ({**GOOD, 'windows': {'/a': [[1, True]]}}, "field 'windows'['/a'] should be a pair"),
        ({**GOOD, 'windows': {'/a': {}}}, "field 'windows'"),
        ({**GOOD, 'vars_len': 5}, 'vars_len 5, file holds 0'),
        ([1, 2, 3], 'a list, not a map'),
        (msgpack.packb({1: 2}), 'malformed header'),  # non-str key
        (msgpack.packb(GOOD) + b'\x00', 'malformed header'),  # trailing byte
        (msgpack.packb(GOOD)[:-1], 'malformed header'),  # header cut short
        (b'\xc1', 'malformed header'),
        (msgpack.packb({**GOOD, 'x': msgpack.ExtType(1, b'')}), 'malformed header'),
        ({**GOOD, 'parameters': 'text'}, "field 'parameters' should be bytes"),
        ({**GOOD, 'parameters': [b'x']}, "field 'parameters' should be bytes"),
    ],
)
def test_malformed_header(
    store: CheckpointStore, tmp_path: Path, header: object, reason: str
) -> None:
    path = tmp_path / 'x.ckpt'
    path.write_bytes(frame(header))
    err = refusal(store, path)
    assert err.reason.startswith('malformed'), err.reason
    assert reason in err.reason


def test_header_length_beyond_the_file(store: CheckpointStore, tmp_path: Path) -> None:
    data = bytearray(frame(GOOD))
    struct.pack_into('<I', data, 10, 10_000)
    body = bytes(data[:-32])
    path = tmp_path / 'x.ckpt'
    path.write_bytes(body + hashlib.sha256(body).digest())
    assert 'header length 10000 exceeds the file' in refusal(store, path).reason


# --------------------------------------------------------------------------- fallback


def test_newest_corrupt_falls_back_to_older(store: CheckpointStore) -> None:
    store.write(make_ckpt(1))
    newest = store.write(make_ckpt(2))
    data = bytearray(newest.read_bytes())
    data[len(data) // 2] ^= 0xFF
    newest.write_bytes(data)
    refused: list[CheckpointError] = []
    assert store.latest_valid(on_refused=refused.append) == make_ckpt(1)
    assert len(refused) == 1
    assert refused[0].path == newest
    assert 'checksum mismatch' in refused[0].reason


def test_latest_valid_without_callback_and_when_none_is_valid(store: CheckpointStore) -> None:
    assert store.latest_valid() is None
    for seq in (1, 2):
        store.write(make_ckpt(seq))
    for path in store.paths():
        path.write_bytes(b'garbage')
    assert store.latest_valid() is None
    refused: list[CheckpointError] = []
    assert store.latest_valid(on_refused=refused.append) is None
    assert [err.path for err in refused] == store.paths()


def test_latest_valid_checks_the_manifest(store: CheckpointStore) -> None:
    store.write(make_ckpt(1, manifest='v1'))
    store.write(make_ckpt(2, manifest='v2'))
    refused: list[CheckpointError] = []
    assert store.latest_valid(expect_manifest='v1', on_refused=refused.append) == make_ckpt(
        1, manifest='v1'
    )
    assert 'manifest v2, expected v1' in refused[0].reason
    assert store.latest_valid(expect_manifest='v3') is None
    assert store.latest_valid() == make_ckpt(2, manifest='v2')


def test_latest_valid_refuses_another_nodes_file(store: CheckpointStore) -> None:
    store.write(make_ckpt(1))
    foreign = store.path(2)
    foreign.write_bytes(serialize(make_ckpt(2, node='other')))
    refused: list[CheckpointError] = []
    assert store.latest_valid(on_refused=refused.append) == make_ckpt(1)
    assert "node 'other'" in refused[0].reason
