"""Tests of the message log segments."""

from __future__ import annotations

import os
import shutil
import signal
import stat
import struct
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from rclpy.serialization import serialize_message
from rosbags.interfaces import Qos
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Int64

from rory_runtime.errors import LogError
from rory_runtime.log import (
    LogEntry,
    SegmentStore,
    SegmentWriter,
    default_typestore,
    read_segment,
)

INT64 = 'std_msgs/msg/Int64'
SCAN = 'sensor_msgs/msg/LaserScan'
NODE = 'integrator'


def int64(value: int) -> bytes:
    return bytes(serialize_message(Int64(data=value)))


def scan(n: int = 360, offset: float = 0.0) -> bytes:
    message = LaserScan(ranges=[offset + i for i in range(n)], angle_max=3.14)
    message.header.frame_id = 'laser'
    return bytes(serialize_message(message))


def sample_entries(count: int = 6) -> list[LogEntry]:
    """Messages on two topics, with identities that exercise every field width."""
    entries = []
    for i in range(count):
        if i % 3 == 2:
            entries.append(LogEntry('/scan', SCAN, 10_000 + i, 5_000 + i, i, scan(8, i)))
        else:
            seq = (2**32 + i) & 0xFFFFFFFF if i == 4 else i + 1
            entries.append(LogEntry('/count', INT64, 10_000 + i, 2**63 + i, seq, int64(i)))
    return entries


def write_segment(path: Path, entries: list[LogEntry], *, close: bool = True) -> SegmentWriter:
    writer = SegmentWriter(path)
    for e in entries:
        writer.write(e.topic, e.msgtype, e.recv_ns, e.source_ns, e.seq, e.data)
    if close:
        writer.close()
    return writer


def mcap_file(segment: Path) -> Path:
    return segment / f'{segment.name}.mcap'


def records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of the top-level records, parsed independently of the module."""
    found = []
    pos = 8
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from('<BQ', data, pos)
        found.append((opcode, pos, pos + 9 + length))
        if opcode in {0x0F, 0x02}:
            break
        pos += 9 + length
    return found


def read_all(path: Path) -> list[LogEntry]:
    return list(read_segment(path))


# --------------------------------------------------------------------------- writing


def test_write_and_read_back(tmp_path: Path) -> None:
    entries = sample_entries(9)
    writer = write_segment(tmp_path / 'seg', entries)
    assert writer.count == 9
    assert read_all(tmp_path / 'seg') == entries
    assert read_all(mcap_file(tmp_path / 'seg')) == entries  # the .mcap file itself works too


def test_identity_is_in_the_standard_mcap_fields(tmp_path: Path) -> None:
    write_segment(tmp_path / 'seg', [LogEntry('/count', INT64, 111, 222, 333, int64(7))])
    data = mcap_file(tmp_path / 'seg').read_bytes()
    messages = [(start, end) for opcode, start, end in records(data) if opcode == 0x05]
    assert len(messages) == 1
    start, end = messages[0]
    _channel, sequence, log_time, publish_time = struct.unpack_from('<HIQQ', data, start + 9)
    assert (sequence, log_time, publish_time) == (333, 111, 222)
    assert data[start + 9 + 22 : end] == int64(7)


def test_seq_is_truncated_to_u32(tmp_path: Path) -> None:
    writer = SegmentWriter(tmp_path / 'seg')
    writer.write('/count', INT64, 1, 2, 2**32 + 5, int64(1))
    writer.write('/count', INT64, 1, 2, 2**64 - 1, int64(1))
    writer.close()
    assert [e.seq for e in read_all(tmp_path / 'seg')] == [5, 0xFFFFFFFF]
    assert read_all(tmp_path / 'seg')[0].ident == (2, 5)


def test_written_messages_are_readable_before_close(tmp_path: Path) -> None:
    entries = sample_entries(5)
    writer = write_segment(tmp_path / 'seg', entries[:3], close=False)
    assert read_all(tmp_path / 'seg') == entries[:3]
    for e in entries[3:]:
        writer.write(e.topic, e.msgtype, e.recv_ns, e.source_ns, e.seq, e.data)
    assert read_all(tmp_path / 'seg') == entries
    assert not (tmp_path / 'seg' / 'metadata.yaml').exists()
    writer.close()
    assert (tmp_path / 'seg' / 'metadata.yaml').exists()
    assert read_all(tmp_path / 'seg') == entries


def test_stock_reader_opens_a_closed_segment(tmp_path: Path) -> None:
    segment = tmp_path / 'seg'
    writer = SegmentWriter(segment)
    for i in range(10):
        writer.write('/count', INT64, 1_000 + 2 * i, 7, i, int64(i * 11))
        writer.write('/scan', SCAN, 1_001 + 2 * i, 8, i, scan(360, float(i)))
    writer.close()

    typestore = default_typestore()
    with Reader(segment) as reader:
        assert reader.message_count == 20
        assert {c.topic: c.msgtype for c in reader.connections} == {
            '/count': INT64,
            '/scan': SCAN,
        }
        got = [
            (conn.topic, stamp, typestore.deserialize_cdr(raw, conn.msgtype))
            for conn, stamp, raw in reader.messages()
        ]
    assert [stamp for _, stamp, _ in got] == list(range(1_000, 1_020))
    assert [m.data for t, _, m in got if t == '/count'] == [i * 11 for i in range(10)]
    scans = [m for t, _, m in got if t == '/scan']
    assert scans[3].header.frame_id == 'laser'
    assert list(scans[3].ranges[:3]) == [3.0, 4.0, 5.0]
    assert len(scans[3].ranges) == 360


def test_receive_times_going_backwards(tmp_path: Path) -> None:
    entries = [LogEntry('/count', INT64, recv, 1, 1, int64(recv)) for recv in (30, 10, 20)]
    write_segment(tmp_path / 'seg', entries)
    assert read_all(tmp_path / 'seg') == entries


def test_empty_segment(tmp_path: Path) -> None:
    SegmentWriter(tmp_path / 'seg').close()
    assert read_all(tmp_path / 'seg') == []
    with Reader(tmp_path / 'seg') as reader:
        assert reader.message_count == 0


def test_unknown_message_type(tmp_path: Path) -> None:
    writer = SegmentWriter(tmp_path / 'seg')
    with pytest.raises(LogError) as info:
        writer.write('/odd', 'my_msgs/msg/Thing', 1, 2, 3, b'\x00\x01\x00\x00')
    assert str(info.value).endswith(
        "topic '/odd': message type 'my_msgs/msg/Thing' is not in the typestore"
    )
    # The segment is still usable for known types.
    writer.write('/count', INT64, 1, 2, 3, int64(4))
    writer.close()
    assert [e.topic for e in read_all(tmp_path / 'seg')] == ['/count']


def test_times_must_fit_u64(tmp_path: Path) -> None:
    writer = SegmentWriter(tmp_path / 'seg')
    for recv, source in ((-1, 0), (0, 2**64)):
        with pytest.raises(LogError, match="topic '/count': times must be u64"):
            writer.write('/count', INT64, recv, source, 0, int64(1))
    writer.write('/count', INT64, 1, 2, 3, int64(4))
    writer.close()
    assert len(read_all(tmp_path / 'seg')) == 1


def test_write_after_close_and_double_close(tmp_path: Path) -> None:
    writer = SegmentWriter(tmp_path / 'seg')
    writer.close()
    writer.close()
    with pytest.raises(LogError, match='segment is closed'):
        writer.write('/count', INT64, 1, 2, 3, int64(4))


def test_context_manager_closes(tmp_path: Path) -> None:
    with SegmentWriter(tmp_path / 'seg') as writer:
        writer.write('/count', INT64, 1, 2, 3, int64(4))
    assert (tmp_path / 'seg' / 'metadata.yaml').exists()


def test_existing_segment_is_not_overwritten(tmp_path: Path) -> None:
    (tmp_path / 'seg').mkdir()
    with pytest.raises(LogError, match='cannot create segment'):
        SegmentWriter(tmp_path / 'seg')


def test_a_short_writev_is_completed_so_no_record_is_torn(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_writev = os.writev

    def short(fd: int, buffers: list[bytes]) -> int:
        head = bytes(buffers[0])
        return os.write(fd, head[:5])  # as a signal can cut a write to a regular file

    writer = write_segment(tmp_path / 'seg', sample_entries(1), close=False)
    monkeypatch.setattr(os, 'writev', short)
    for entry in sample_entries(3)[1:]:
        writer.write(entry.topic, entry.msgtype, entry.recv_ns, entry.source_ns, entry.seq,
                     entry.data)
    monkeypatch.setattr(os, 'writev', real_writev)
    writer.close()
    assert read_all(tmp_path / 'seg') == sample_entries(3)
    with Reader(tmp_path / 'seg') as reader:  # the summary's offsets found the records
        assert reader.message_count == 3
        assert sum(1 for _ in reader.messages()) == 3


def test_failed_write_makes_the_segment_refuse_more(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    writer = write_segment(tmp_path / 'seg', sample_entries(2), close=False)

    def full_disk(fd: int, buffers: object) -> int:
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(os, 'writev', full_disk)  # a message record is one writev
    with pytest.raises(LogError, match=r"topic '/count': cannot write: .*No space left"):
        writer.write('/count', INT64, 1, 2, 3, int64(4))
    with pytest.raises(LogError, match='unusable after an earlier failure'):
        writer.write('/count', INT64, 1, 2, 3, int64(4))
    writer.close()
    assert not (tmp_path / 'seg' / 'metadata.yaml').exists()
    assert read_all(tmp_path / 'seg') == sample_entries(2)


def test_default_typestore_is_cached() -> None:
    assert default_typestore() is default_typestore()


def test_write_throughput(tmp_path: Path) -> None:
    data = scan(360)
    default_typestore()
    writer = SegmentWriter(tmp_path / 'seg')
    count = 20_000
    start = time.perf_counter()
    for i in range(count):
        writer.write('/scan', SCAN, i, i, i, data)
    elapsed = time.perf_counter() - start
    writer.close()
    size = mcap_file(tmp_path / 'seg').stat().st_size
    print(
        f'LaserScan(360) ({len(data)} B): {count / elapsed:,.0f} writes/s,'
        f' {size / elapsed / 2**20:.0f} MiB/s'
    )
    assert writer.count == count


# --------------------------------------------------------------------------- killed writers

CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Int64
    from rory_runtime.log import SegmentWriter

    writer = SegmentWriter(Path(sys.argv[1]))
    limit = int(sys.argv[2])
    i = 0
    while limit < 0 or i < limit:
        writer.write('/count', 'std_msgs/msg/Int64', 1000 + i, 500 + i, i,
                     serialize_message(Int64(data=i)))
        i += 1
        if i == 1 and limit < 0:
            print('writing', flush=True)
    print('written', flush=True)
    time.sleep(120)
    """
)


def start_child(segment: Path, limit: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, '-c', CHILD, str(segment), str(limit)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def kill(child: subprocess.Popen[str]) -> None:
    os.kill(child.pid, signal.SIGKILL)
    assert child.wait(timeout=30) == -signal.SIGKILL


@pytest.mark.parametrize('k', [0, 1, 7, 500])
def test_sigkill_after_k_writes_keeps_exactly_k(tmp_path: Path, k: int) -> None:
    segment = tmp_path / 'seg'
    child = start_child(segment, k)
    assert child.stdout is not None
    line = child.stdout.readline()
    assert line == 'written\n', child.stderr.read() if child.stderr else ''
    kill(child)
    assert not (segment / 'metadata.yaml').exists()
    entries = read_all(segment)
    assert [(e.recv_ns, e.source_ns, e.seq, e.data) for e in entries] == [
        (1000 + i, 500 + i, i, int64(i)) for i in range(k)
    ]
    assert all((e.topic, e.msgtype) == ('/count', INT64) for e in entries)


def test_sigkill_while_writing_leaves_a_readable_prefix(tmp_path: Path) -> None:
    segment = tmp_path / 'seg'
    child = start_child(segment, -1)
    assert child.stdout is not None
    assert child.stdout.readline() == 'writing\n'
    time.sleep(0.3)
    kill(child)
    entries = read_all(segment)
    assert len(entries) >= 1
    assert [e.seq for e in entries] == list(range(len(entries)))
    assert entries[-1].data == int64(len(entries) - 1)


# --------------------------------------------------------------------------- torn and corrupt


@pytest.mark.parametrize('closed', [True, False], ids=['closed', 'killed'])
def test_truncation_at_every_offset_yields_a_prefix(tmp_path: Path, closed: bool) -> None:
    entries = sample_entries(6)
    writer = write_segment(tmp_path / 'seg', entries, close=closed)
    data = mcap_file(tmp_path / 'seg').read_bytes()
    if not closed:
        writer.close()  # after the copy: the bytes are those a killed writer leaves
    message_ends = [end for opcode, _, end in records(data) if opcode == 0x05]
    assert len(message_ends) == len(entries)
    copy = tmp_path / 'copy.mcap'
    copy.write_bytes(data)
    for length in range(len(data), -1, -1):
        os.truncate(copy, length)
        expected = sum(end <= length for end in message_ends)
        assert read_all(copy) == entries[:expected], length


def test_partial_magic_is_an_empty_segment(tmp_path: Path) -> None:
    path = tmp_path / 'x.mcap'
    for data in (b'', b'\x89MC'):
        path.write_bytes(data)
        assert read_all(path) == []


def corrupt(tmp_path: Path, patch: object) -> tuple[list[LogEntry], bytes]:
    """Write a segment, apply patch(data, records) to the .mcap bytes, return the result."""
    entries = sample_entries(6)
    write_segment(tmp_path / 'seg', entries)
    path = mcap_file(tmp_path / 'seg')
    data = bytearray(path.read_bytes())
    patch(data, records(bytes(data)))  # type: ignore[operator]
    path.write_bytes(data)
    return entries, bytes(data)


def read_until_error(path: Path) -> tuple[list[LogEntry], LogError]:
    got: list[LogEntry] = []
    with pytest.raises(LogError) as info:
        for entry in read_segment(path):
            got.append(entry)
    return got, info.value


def nth(recs: list[tuple[int, int, int]], opcode: int, n: int) -> int:
    return [start for op, start, _ in recs if op == opcode][n]


def test_message_with_unknown_channel(tmp_path: Path) -> None:
    offset = 0

    def patch(data: bytearray, recs: list[tuple[int, int, int]]) -> None:
        nonlocal offset
        offset = nth(recs, 0x05, 2)
        struct.pack_into('<H', data, offset + 9, 99)

    entries, _ = corrupt(tmp_path, patch)
    got, err = read_until_error(tmp_path / 'seg')
    assert got == entries[:2]
    assert err.reason == f'message record at offset {offset} refers to unknown channel 99'
    assert err.path == mcap_file(tmp_path / 'seg')


def test_unexpected_opcode_in_the_middle(tmp_path: Path) -> None:
    offset = 0

    def patch(data: bytearray, recs: list[tuple[int, int, int]]) -> None:
        nonlocal offset
        offset = nth(recs, 0x05, 3)
        data[offset] = 0x06  # a chunk, which segments never hold

    entries, _ = corrupt(tmp_path, patch)
    got, err = read_until_error(tmp_path / 'seg')
    assert got == entries[:3]
    assert err.reason == f'unexpected record opcode 0x06 at offset {offset}'


def test_message_record_too_short(tmp_path: Path) -> None:
    def patch(data: bytearray, recs: list[tuple[int, int, int]]) -> None:
        struct.pack_into('<Q', data, nth(recs, 0x05, 1) + 1, 10)

    corrupt(tmp_path, patch)
    got, err = read_until_error(tmp_path / 'seg')
    assert len(got) == 1
    assert 'malformed message record' in err.reason


def test_channel_record_with_overlong_string(tmp_path: Path) -> None:
    def patch(data: bytearray, recs: list[tuple[int, int, int]]) -> None:
        start = nth(recs, 0x04, 0)
        struct.pack_into('<I', data, start + 9 + 4, 10_000)  # topic length

    corrupt(tmp_path, patch)
    got, err = read_until_error(tmp_path / 'seg')
    assert got == []
    assert 'malformed channel record at offset' in err.reason
    assert 'runs past the end of the record' in err.reason


def test_channel_with_unknown_schema(tmp_path: Path) -> None:
    def patch(data: bytearray, recs: list[tuple[int, int, int]]) -> None:
        struct.pack_into('<H', data, nth(recs, 0x04, 0) + 9 + 2, 42)

    corrupt(tmp_path, patch)
    _, err = read_until_error(tmp_path / 'seg')
    assert 'unknown schema id 42' in err.reason


def test_schema_with_bad_utf8(tmp_path: Path) -> None:
    def patch(data: bytearray, recs: list[tuple[int, int, int]]) -> None:
        data[nth(recs, 0x03, 0) + 9 + 2 + 4] = 0xFF  # first byte of the type name

    corrupt(tmp_path, patch)
    _, err = read_until_error(tmp_path / 'seg')
    assert 'malformed schema record' in err.reason
    assert 'not UTF-8' in err.reason


def test_missing_header_record(tmp_path: Path) -> None:
    def patch(data: bytearray, recs: list[tuple[int, int, int]]) -> None:
        data[8] = 0x03

    corrupt(tmp_path, patch)
    _, err = read_until_error(tmp_path / 'seg')
    assert err.reason == 'expected the MCAP header record at offset 8, got opcode 0x03'


def test_bad_magic(tmp_path: Path) -> None:
    path = tmp_path / 'x.mcap'
    path.write_bytes(b'SQLite format 3\x00' + b'\x00' * 100)
    _, err = read_until_error(path)
    assert err.reason == 'not an MCAP file (bad magic)'


def test_missing_mcap_file_is_reported_at_once(tmp_path: Path) -> None:
    (tmp_path / 'seg').mkdir()
    with pytest.raises(LogError, match=r'no seg\.mcap in segment'):
        read_segment(tmp_path / 'seg')
    with pytest.raises(LogError, match=r'no nope\.mcap'):
        read_segment(tmp_path / 'nope')


# --------------------------------------------------------------------------- segment store


def fill(store: SegmentStore, n: int, entries: list[LogEntry], *, close: bool = True) -> None:
    writer = store.open(n)
    for e in entries:
        writer.write(e.topic, e.msgtype, e.recv_ns, e.source_ns, e.seq, e.data)
    if close:
        writer.close()


def entry(topic: str, source: int, seq: int) -> LogEntry:
    return LogEntry(topic, INT64, source + 1, source, seq, int64(seq))


def test_segment_store(tmp_path: Path) -> None:
    store = SegmentStore(tmp_path / 'state', NODE)
    assert store.dir == tmp_path / 'state' / NODE / 'log'
    assert store.numbers() == []
    assert store.next_number() == 1
    assert list(store.read_after(None)) == []

    first = [entry('/a', 10, 1), entry('/b', 11, 1)]
    second = [entry('/a', 20, 2)]
    third = [entry('/a', 30, 3), entry('/b', 31, 2)]
    fill(store, 1, first)
    fill(store, 2, second)
    fill(store, 3, third, close=False)  # the writer of the newest one was killed
    assert store.numbers() == [1, 2, 3]
    assert store.next_number() == 4
    assert store.path(3) == store.dir / '0000000003'

    assert list(store.read_after(None)) == first + second + third
    assert list(store.read_after(1)) == second + third
    assert list(store.read_after(3)) == []
    assert store.identities_after(1) == {'/a': {(20, 2), (30, 3)}, '/b': {(31, 2)}}
    assert store.identities_after(3) == {}

    store.drop_through(2)
    assert store.numbers() == [3]
    assert list(store.read_after(None)) == third
    store.drop_through(10)
    assert store.numbers() == []
    assert store.next_number() == 1


def test_segment_store_modes(tmp_path: Path) -> None:
    store = SegmentStore(tmp_path / 'state', NODE)
    old = os.umask(0o022)
    try:
        store.open(1).close()
    finally:
        os.umask(old)
    for path in (tmp_path / 'state', tmp_path / 'state' / NODE, store.dir, store.path(1)):
        assert stat.S_IMODE(path.stat().st_mode) == 0o700, path


def test_segment_store_ignores_other_names_and_empty_segments(tmp_path: Path) -> None:
    store = SegmentStore(tmp_path, NODE)
    fill(store, 2, [entry('/a', 1, 1)])
    (store.dir / 'notes').mkdir()
    (store.dir / '12').mkdir()
    (store.dir / '0000000009').write_text('a file, not a segment')
    store.path(5).mkdir()  # writer killed between mkdir and creating the .mcap file
    assert store.numbers() == [2, 5]
    assert store.next_number() == 6
    assert list(store.read_after(None)) == [entry('/a', 1, 1)]
    store.drop_through(100)
    assert sorted(os.listdir(store.dir)) == ['0000000009', '12', 'notes']


def test_segment_store_refuses_to_reopen(tmp_path: Path) -> None:
    store = SegmentStore(tmp_path, NODE)
    store.open(1).close()
    with pytest.raises(LogError, match='cannot create segment'):
        store.open(1)
    for n in (0, 10**10):
        with pytest.raises(LogError, match=r'outside 1\.\.9999999999'):
            store.open(n)


def test_segment_store_read_after_reports_corruption(tmp_path: Path) -> None:
    store = SegmentStore(tmp_path, NODE)
    fill(store, 1, [entry('/a', 1, 1)])
    shutil.rmtree(store.path(1))
    store.path(1).mkdir()
    (store.path(1) / 'metadata.yaml').write_text('{}')
    with pytest.raises(LogError, match=r'no 0000000001\.mcap'):
        list(store.read_after(None))


# A node id is what the supervisor config allows (protocol.NODE_ID_RE): no path, and a part
# of a ROS topic name, so no '-' or '.' and no digit first.
@pytest.mark.parametrize('node', ['', '..', 'a/b', 'my-node', 'a.b', '0abc', '_x'])
def test_segment_store_bad_node_id(tmp_path: Path, node: str) -> None:
    with pytest.raises(ValueError, match='is not a node id'):
        SegmentStore(tmp_path, node)


def test_read_after_stops_before_a_bound_and_skips_a_segment_killed_before_its_file(
    tmp_path: Path,
) -> None:
    # The recovery replays the segments after a checkpoint's cut up to its recovery log R;
    # a node killed right after rotating leaves a segment directory with no file in it.
    store = SegmentStore(tmp_path, 'n')
    first, third, fourth = sample_entries(2), sample_entries(3), sample_entries(1)
    for number, entries in ((1, first), (3, third), (4, fourth)):
        writer = store.open(number)
        for e in entries:
            writer.write(e.topic, e.msgtype, e.recv_ns, e.source_ns, e.seq, e.data)
        writer.close()
    store.path(2).mkdir(mode=0o700)  # killed before the MCAP file existed
    assert list(store.read_after(None, before=4)) == [*first, *third]
    assert list(store.read_after(1, before=4)) == third


def test_metadata_is_what_rosbags_writes(tmp_path: Path) -> None:
    # The segment's metadata.yaml and MCAP metadata record come from our own close (libyaml,
    # ~10x cheaper); they must say what rosbags' Writer.close says for the same bag.
    import yaml
    from rclpy.qos import QoSProfile
    from rosbags.rosbag2 import StoragePlugin, Writer

    from rory_runtime.qos import to_rosbag

    offered = to_rosbag(QoSProfile(depth=10))
    messages = [('/n', INT64, 100 + k, int64(k)) for k in range(3)]
    messages += [('/scan', SCAN, 150, scan())]
    ours = SegmentWriter(tmp_path / 'ours' / 'seg')
    for topic, msgtype, t, data in messages:
        ours.write(topic, msgtype, t, t - 1, 7, data, offered_qos=lambda: [offered])
    ours.close()
    theirs = Writer(tmp_path / 'theirs' / 'seg', version=9, storage_plugin=StoragePlugin.MCAP)
    theirs.open()
    connections = {}
    for topic, msgtype, t, data in messages:
        if topic not in connections:
            connections[topic] = theirs.add_connection(topic, msgtype,
                                                       typestore=default_typestore(),
                                                       offered_qos_profiles=[offered])
        theirs.write(connections[topic], t, data)
    theirs.close()
    assert (yaml.safe_load((tmp_path / 'ours' / 'seg' / 'metadata.yaml').read_text())
            == yaml.safe_load((tmp_path / 'theirs' / 'seg' / 'metadata.yaml').read_text()))
    with Reader(tmp_path / 'ours' / 'seg') as reader:
        assert reader.message_count == 4
        assert {c.topic: c.ext.offered_qos_profiles for c in reader.connections} == {
            '/n': [offered], '/scan': [offered]}


def test_channel_qos_document_is_the_text_rosbags_writes() -> None:
    # A segment's channel records carry the offered QoS as YAML. Rosbags emits it with ruamel
    # (~6 ms a connection, in the node's executor); ours comes from libyaml and must be the
    # same text, whatever the profile.
    from io import StringIO

    from rclpy.duration import Duration
    from rclpy.qos import (
        QoSDurabilityPolicy,
        QoSLivelinessPolicy,
        QoSProfile,
        QoSReliabilityPolicy,
        qos_profile_sensor_data,
    )
    from rosbags.rosbag2.metadata import dump_qos_v9
    from ruamel.yaml import YAML

    from rory_runtime.log import qos_document
    from rory_runtime.qos import to_rosbag

    def theirs(profiles: list[Qos]) -> str:  # rosbags' Writer.add_connection, version 9
        stream = StringIO()
        emitter = YAML(typ='safe')
        emitter.default_flow_style = False
        emitter.dump(dump_qos_v9(profiles), stream)
        return stream.getvalue().strip()

    latched = QoSProfile(
        depth=1, durability=QoSDurabilityPolicy.TRANSIENT_LOCAL,
        reliability=QoSReliabilityPolicy.RELIABLE, deadline=Duration(seconds=1, nanoseconds=5),
        liveliness=QoSLivelinessPolicy.MANUAL_BY_TOPIC,
        lifespan=Duration(seconds=2**31 - 1, nanoseconds=999_999_999),
    )
    for profiles in ([], [QoSProfile(depth=10)], [qos_profile_sensor_data],
                     [latched, QoSProfile(depth=5)]):
        offered = [to_rosbag(p) for p in profiles]
        assert qos_document(offered) == theirs(offered)
