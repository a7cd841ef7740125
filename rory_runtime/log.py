"""Message log segments: rosbag2 MCAP bags that survive SIGKILL of the writer.

A node records every message it receives. Each *segment* is one rosbag2 bag directory
(``<name>/<name>.mcap`` plus ``metadata.yaml`` once closed) written through
:class:`rosbags.rosbag2.Writer` with a storage plugin that differs from the stock one in two
ways:

- The stock plugin collects messages in a 1 MiB in-memory chunk, so a killed writer loses
  them. Here schema, channel and message records are written top-level and unchunked (MCAP
  allows that) and flushed before ``write`` returns: a message is in the OS, safe from a
  SIGKILL of the process (not from a power cut; nothing is fsynced), once written.
- The stock plugin writes ``sequence=0`` and ``publish_time=log_time``. Here each message
  record keeps its identity in those standard MCAP fields: ``log_time`` is the receive time,
  ``publish_time`` the publisher's source timestamp and ``sequence`` the publisher sequence
  number truncated to u32.

Closing writes the summary, footer and ``metadata.yaml`` as usual, so a closed segment is a
normal rosbag2 bag that :class:`rosbags.rosbag2.Reader` opens. The stock reader, however,
refuses a file without footer, which is what a killed writer leaves. :func:`read_segment`
therefore scans the records from the start itself, and stops silently at a torn final
record: after a kill that is expected, not an error.

Closed segments of messages whose receive times go backwards (a clock step, sim time
restarting) stay readable by :func:`read_segment`, but the stock reader refuses to iterate
unindexed MCAP messages out of ``log_time`` order.

Limitation: records carry no checksum, so a corrupted length field that points past the end
of the file is indistinguishable from a torn tail and ends the scan early.
"""

from __future__ import annotations

import os
import re
import shutil
import struct
from collections.abc import Callable, Iterator, Sequence
from contextlib import suppress
from dataclasses import dataclass
from functools import cache
from io import BytesIO
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO, Final, Literal

import yaml
from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinition,
    MessageDefinitionFormat,
    Qos,
)
from rosbags.rosbag2 import CompressionMode, StoragePlugin, Writer, WriterError
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.rosbag2.storage_mcap import (
    Channel,
    McapWriter,
    Schema,
    write_channel,
    write_schema,
    write_string,
)
from rosbags.typesys import Stores, TypesysError, get_typestore

from rory_runtime.errors import LogError
from rory_runtime.fsutil import make_private_dir
from rory_runtime.protocol import NODE_ID_RE, SEQ_MASK

if TYPE_CHECKING:
    from collections.abc import Mapping
    from types import TracebackType

    from rosbags.rosbag2.writer import StorageWriter
    from rosbags.typesys.store import Typestore

MCAP_MAGIC: Final = b'\x89MCAP0\r\n'

OP_HEADER: Final = 0x01
OP_FOOTER: Final = 0x02
OP_SCHEMA: Final = 0x03
OP_CHANNEL: Final = 0x04
OP_MESSAGE: Final = 0x05
OP_METADATA: Final = 0x0C
OP_DATA_END: Final = 0x0F

_RECORD_HEAD: Final = struct.Struct('<BQ')  # opcode, body length
_MESSAGE_FIELDS: Final = struct.Struct('<HIQQ')  # channel id, sequence, log_time, publish_time
_MESSAGE_HEAD: Final = struct.Struct('<BQHIQQ')  # both of the above, for writing in one go
_U16: Final = struct.Struct('<H')
_U32: Final = struct.Struct('<I')
_SEGMENT_RE: Final = re.compile(r'[0-9]{10}')
_MAX_NUMBER: Final = 10**10 - 1  # directory names hold ten digits


@cache
def default_typestore() -> Typestore:
    """Return the ROS 2 Jazzy typestore, built once per process (it takes ~100 ms)."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True, slots=True)
class LogEntry:
    """One logged message.

    Attributes:
        topic: Topic it was received on.
        msgtype: ROS type name, e.g. ``std_msgs/msg/Int64``.
        recv_ns: Receive time (ns); the MCAP ``log_time``.
        source_ns: Publisher's source timestamp (ns); the MCAP ``publish_time``.
        seq: Publisher sequence number truncated to u32; the MCAP ``sequence``.
        data: CDR bytes exactly as received.
        publisher: The writer's GID, where the reader knew it (the supervisor's ring does;
            a log segment does not keep it).

    """

    topic: str
    msgtype: str
    recv_ns: int
    source_ns: int
    seq: int
    data: bytes
    publisher: bytes | None = None

    @property
    def ident(self) -> tuple[int, int]:
        """Identity of the message: ``(source_ns, seq)``."""
        return (self.source_ns, self.seq)


# --------------------------------------------------------------------------- writing


class _DurableMcapWriter(McapWriter):
    """MCAP storage that writes every record top-level and flushes it at once."""

    def __init__(self, path: Path, compression: CompressionMode) -> None:
        super().__init__(path, compression)
        self.bio.flush()  # magic and header record
        # Messages go to the file descriptor in one writev each (write_message); the buffered
        # file object is brought to the file's end before its own rare writes (_resync).
        self._fd = self.bio.fileno()

    def _resync(self) -> None:
        """Put the buffered file object at the file's end, where write_message's records left
        it: its cached position, which close's summary offsets come from, would be stale."""
        self.bio.seek(0, os.SEEK_END)

    def add_msgtype(self, connection: Connection) -> None:
        """Write the schema record of a connection's message type."""
        fmt = connection.msgdef.format
        encoding = 'ros2msg' if fmt == MessageDefinitionFormat.MSG else 'ros2idl'
        schema = Schema(len(self.schemas) + 1, connection.msgtype, encoding, connection.msgdef.data)
        self.schemas.append(schema)
        self._resync()
        write_schema(self.bio, schema)
        self.bio.flush()

    def add_connection(self, connection: Connection, offered_qos_profiles: str) -> None:
        """Write the channel record of a connection."""
        metadata = BytesIO()
        write_string(metadata, 'offered_qos_profiles')
        write_string(metadata, offered_qos_profiles)
        ext = connection.ext
        encoding = ext.serialization_format if isinstance(ext, ConnectionExtRosbag2) else 'cdr'
        channel = Channel(
            connection.id, connection.msgtype, connection.topic, encoding, metadata.getvalue()
        )
        self.channels.append(channel)
        self.channel_stats[connection.id] = 0
        self._resync()
        write_channel(self.bio, channel, self.schemas)
        self.bio.flush()

    def close(self, version: int, metadata: str) -> None:
        """Write the summary and footer after the messages (rosbags' close, at the file's end)."""
        self._resync()
        super().close(version, metadata)

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        """Write a message without identity (stock interface)."""
        self.write_message(connection.id, timestamp, timestamp, 0, data)

    def write_message(
        self,
        channel_id: int,
        log_time: int,
        publish_time: int,
        sequence: int,
        data: bytes | memoryview,
    ) -> None:
        """Write one message record to the OS: one ``writev`` of its head and the data, no
        copy and no buffered file object (what each cost is measured in docs/performance.md,
        "One writev a record").

        Raises:
            struct.error: A time or the sequence does not fit its field; nothing written.
            OSError: Writing failed; the file may end in a torn record.

        """
        head = _MESSAGE_HEAD.pack(
            OP_MESSAGE,
            _MESSAGE_FIELDS.size + len(data),
            channel_id,
            sequence,
            log_time,
            publish_time,
        )
        written = os.writev(self._fd, (head, data))
        if written != len(head) + len(data):
            _write_rest(self._fd, head + bytes(data), written)
        self.channel_stats[channel_id] += 1
        self.message_start_time = min(log_time, self.message_start_time)
        self.message_end_time = max(log_time, self.message_end_time)


def _write_rest(fd: int, record: bytes, written: int) -> None:
    """Write what a short ``writev`` left of ``record`` (a signal, or a disk filling up: then
    the next write raises)."""
    view = memoryview(record)
    while written < len(record):
        written += os.write(fd, view[written:])


def _make_private(folder: Path) -> None:
    # rosbags creates its files with the process umask; a log is the owner's only.
    os.chmod(folder, 0o700)
    for path in folder.iterdir():
        os.chmod(path, 0o600)


_YAML_DUMPER = getattr(yaml, 'CSafeDumper', yaml.SafeDumper)  # libyaml when PyYAML has it


def _dump_yaml(data: object) -> str:
    """Block-style YAML, keys in rosbag2's order."""
    text: str = yaml.dump(data, Dumper=_YAML_DUMPER, default_flow_style=False,
                          sort_keys=False)
    return text


def qos_document(offered_qos_profiles: Sequence[Qos]) -> str:
    """The offered QoS profiles as a rosbag2 version 9 channel record holds them: the text
    rosbags writes (keys sorted, block style), emitted by libyaml."""
    text: str = yaml.dump(dump_qos_v9(list(offered_qos_profiles)), Dumper=_YAML_DUMPER,
                          default_flow_style=False, sort_keys=True)
    return text.strip()


@cache
def _definition(typestore: Typestore, msgtype: str) -> tuple[str, str]:
    """A type's message definition and RIHS01 hash; the same for every segment, so computed
    once per process (it walked the typestore at every checkpoint)."""
    msgdef, _ = typestore.generate_msgdef(msgtype, ros_version=2)
    return msgdef, typestore.hash_rihs01(msgtype)


class _SegmentBag(Writer):
    """rosbag2 writer using the durable MCAP storage and recording message identities."""

    STORAGE_PLUGINS: Mapping[StoragePlugin, type[StorageWriter]] = {
        StoragePlugin.MCAP: _DurableMcapWriter,
    }

    def open(self) -> None:
        """Create the bag directory (mode 0700) and the .mcap file (0600)."""
        super().open()
        _make_private(self.path)

    def add_connection(
        self,
        topic: str,
        msgtype: str,
        *,
        typestore: Typestore | None = None,
        msgdef: str | None = None,
        rihs01: str | None = None,
        serialization_format: str = 'cdr',
        offered_qos_profiles: Sequence[Qos] = (),
    ) -> Connection:
        """Rosbags' ``Writer.add_connection`` for a version 9 bag, the offered QoS dumped by
        libyaml.

        Rosbags builds a ruamel YAML emitter for each connection: 5.7 ms of CPU (0.5 with
        libyaml) in the node's executor (py-spy, amcl under RORY) at each topic's first message
        in every segment, and a node starts a segment at every checkpoint. The channel record
        holds the same text (tests/runtime/test_log.py compares it with rosbags').
        """
        storage = self.storage
        if msgdef is None or rihs01 is None or self.version < 9:
            return super().add_connection(
                topic, msgtype, typestore=typestore, msgdef=msgdef, rihs01=rihs01,
                serialization_format=serialization_format,
                offered_qos_profiles=offered_qos_profiles,
            )
        if storage is None:
            msg = 'Bag was not opened.'
            raise WriterError(msg)
        idl = msgdef.startswith('=' * 80 + '\nIDL: ')
        connection = Connection(
            id=len(self.connections) + 1,
            topic=topic,
            msgtype=msgtype,
            msgdef=MessageDefinition(
                MessageDefinitionFormat.IDL if idl else MessageDefinitionFormat.MSG, msgdef
            ),
            digest=rihs01,
            msgcount=0,
            ext=ConnectionExtRosbag2(
                serialization_format=serialization_format,
                offered_qos_profiles=list(offered_qos_profiles),
            ),
            owner=self,
        )
        if any(c.topic == topic and c.msgtype == msgtype and c.ext == connection.ext
               for c in self.connections):
            msg = f'Connection can only be added once: {connection!r}.'
            raise WriterError(msg)
        if msgtype not in self.added_types:
            storage.add_msgtype(connection)
            self.added_types.add(msgtype)
        storage.add_connection(connection, qos_document(offered_qos_profiles))
        self.connections.append(connection)
        self.counts[connection.id] = 0
        return connection

    def close(self) -> None:
        """Write the MCAP summary and metadata record, then metadata.yaml (0600).

        The documents are those of rosbags' ``Writer.close`` for an uncompressed version 9
        bag, emitted by libyaml: rosbags' pure-Python emitter took ~11 ms of CPU per segment,
        and a node closes a segment at every checkpoint.
        """
        storage = self.storage
        if not isinstance(storage, _DurableMcapWriter):
            msg = 'Bag was not opened.'
            raise WriterError(msg)
        # The storage counted the messages (SegmentWriter writes them to it directly).
        self.counts.update(storage.channel_stats)
        self.min_timestamp = storage.message_start_time
        self.max_timestamp = storage.message_end_time
        duration = max(0, self.max_timestamp - self.min_timestamp)
        start = self.min_timestamp
        count = sum(self.counts.values())
        name = storage.path.name
        info = {
            'version': self.version,
            'storage_identifier': self.storage_plugin.name.lower(),
            'relative_file_paths': [name],
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': count,
            'topics_with_message_count': [
                {
                    'topic_metadata': {
                        'name': c.topic,
                        'type': c.msgtype,
                        'serialization_format': c.ext.serialization_format,
                        'offered_qos_profiles': dump_qos_v9(c.ext.offered_qos_profiles),
                        'type_description_hash': c.digest,
                    },
                    'message_count': self.counts[c.id],
                }
                for c in self.connections
                if isinstance(c.ext, ConnectionExtRosbag2)
            ],
            'compression_format': '',
            'compression_mode': '',
            'files': [{
                'path': name,
                'starting_time': {'nanoseconds_since_epoch': start},
                'duration': {'nanoseconds': duration},
                'message_count': count,
            }],
            'custom_data': self.custom_data or None,
            'ros_distro': 'rosbags',
        }
        storage.close(self.version, _dump_yaml(info).strip())
        self.storage = None
        tmp = self.metapath.with_suffix('.yaml.tmp')
        tmp.write_text(_dump_yaml({'rosbag2_bagfile_information': info}), 'utf8')
        tmp.replace(self.metapath)
        _make_private(self.path)


class SegmentWriter:
    """Writes one log segment; every message is in the OS before :meth:`write` returns.

    Args:
        path: Bag directory to create; must not exist.
        typestore: Where message definitions come from; defaults to ROS 2 Jazzy's.

    Raises:
        LogError: The segment cannot be created.

    Attributes:
        path: The bag directory.
        count: Messages written.

    """

    def __init__(self, path: Path, typestore: Typestore | None = None) -> None:
        self.path = Path(path)
        self.count = 0
        self._typestore = typestore
        self._connections: dict[tuple[str, str], Connection] = {}
        self._failure: str | None = None
        self._closed = False
        try:
            self._bag = _SegmentBag(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
            self._bag.open()
        except (WriterError, OSError) as err:
            raise LogError(self.path, f'cannot create segment: {err}') from None
        # A message goes straight to the storage, which counts it for the bag's close.
        assert isinstance(self._bag.storage, _DurableMcapWriter)
        self._write_message = self._bag.storage.write_message

    def write(
        self,
        topic: str,
        msgtype: str,
        recv_ns: int,
        source_ns: int,
        seq: int,
        data: bytes,
        offered_qos: Callable[[], Sequence[Qos]] | None = None,
    ) -> None:
        """Append one message.

        Args:
            topic: Topic it was received on.
            msgtype: ROS type name, e.g. ``std_msgs/msg/Int64``.
            recv_ns: Receive time (ns).
            source_ns: Publisher's source timestamp (ns).
            seq: Publisher sequence number; stored truncated to u32.
            data: CDR bytes as received.
            offered_qos: The topic's publishers' QoS, asked for only when the segment first
                logs this topic (stored as rosbag2's ``offered_qos_profiles``).

        Raises:
            LogError: Unknown message type, a time outside u64, the segment is closed, or
                writing failed (after which the segment takes no more messages).

        """
        if self._closed or self._failure is not None:
            raise LogError(self.path, self._refusal(topic))
        connection = self._connections.get((topic, msgtype))
        if connection is None:
            connection = self._add_connection(topic, msgtype, offered_qos)
        try:
            self._write_message(connection.id, recv_ns, source_ns, seq & SEQ_MASK, data)
        except struct.error:
            msg = f'topic {topic!r}: times must be u64, got recv {recv_ns}, source {source_ns}'
            raise LogError(self.path, msg) from None
        except OSError as err:
            raise self._fail(topic, err) from None
        self.count += 1

    def close(self) -> None:
        """Write the MCAP summary, footer and metadata.yaml; a no-op when already closed.

        After a failed write only the file is closed: it stays readable by
        :func:`read_segment` up to the failure, like the segment of a killed writer.

        Raises:
            LogError: Writing the summary or metadata failed.

        """
        if self._closed:
            return
        self._closed = True
        if self._failure is not None:
            with suppress(OSError):
                self._bag.abort()
            return
        try:
            self._bag.close()
        except OSError as err:
            with suppress(OSError):
                self._bag.abort()
            raise LogError(self.path, f'cannot close segment: {err}') from None

    def __enter__(self) -> SegmentWriter:
        """Return self; the segment is already open."""
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc_val: BaseException | None,
        exc_tb: TracebackType | None,
    ) -> Literal[False]:
        """Close the segment; what was written stays valid even if the block raised."""
        self.close()
        return False

    def _add_connection(self, topic: str, msgtype: str,
                        offered_qos: Callable[[], Sequence[Qos]] | None) -> Connection:
        typestore = self._typestore if self._typestore is not None else default_typestore()
        qos = tuple(offered_qos()) if offered_qos is not None else ()
        try:
            msgdef, rihs01 = _definition(typestore, msgtype)
            connection = self._bag.add_connection(topic, msgtype, msgdef=msgdef, rihs01=rihs01,
                                                  offered_qos_profiles=qos)
        except (TypesysError, KeyError):
            msg = f'topic {topic!r}: message type {msgtype!r} is not in the typestore'
            raise LogError(self.path, msg) from None
        except OSError as err:
            raise self._fail(topic, err) from None
        self._connections[topic, msgtype] = connection
        return connection

    def _fail(self, topic: str, err: OSError) -> LogError:
        # A failed write may have left part of a record behind; appending after it would
        # turn a torn tail into corruption in the middle, so the segment takes no more.
        self._failure = f'{err}'
        return LogError(self.path, f'topic {topic!r}: cannot write: {err}')

    def _refusal(self, topic: str) -> str:
        if self._failure is not None:
            return f'topic {topic!r}: segment unusable after an earlier failure: {self._failure}'
        return f'topic {topic!r}: segment is closed'


# --------------------------------------------------------------------------- reading


def read_segment(path: Path) -> Iterator[LogEntry]:
    """Read the messages of a segment, closed or left behind by a killed writer.

    Args:
        path: The bag directory (or its .mcap file).

    Returns:
        An iterator over the complete messages in file order. It stops silently at a torn
        final record.

    Raises:
        LogError: No .mcap file (raised at once), or, while iterating, the file is not MCAP
            or holds a complete but malformed record (the message names its offset).

    """
    return _scan(_mcap_path(Path(path)))


def _mcap_path(path: Path) -> Path:
    if path.is_file():
        return path
    mcap = path / f'{path.name}.mcap'
    if not mcap.is_file():
        raise LogError(path, f'no {mcap.name} in segment')
    return mcap


def _scan(mcap: Path) -> Iterator[LogEntry]:
    try:
        stream = mcap.open('rb')
    except OSError as err:
        raise LogError(mcap, f'cannot open: {err.strerror or err}') from None
    with stream:
        yield from _Scanner(mcap, stream).entries()


class _Scanner:
    """Reads top-level MCAP records of one file in order."""

    def __init__(self, path: Path, stream: BinaryIO) -> None:
        self.path = path
        self.stream = stream
        # Size at open: a length field beyond it is a torn record, and never triggers a
        # huge allocation.
        self.size = os.fstat(stream.fileno()).st_size
        self.schemas: dict[int, str] = {}
        self.channels: dict[int, tuple[str, str]] = {}

    def entries(self) -> Iterator[LogEntry]:
        magic = self.stream.read(len(MCAP_MAGIC))
        if magic != MCAP_MAGIC:
            if MCAP_MAGIC.startswith(magic):
                return  # killed before the magic was complete
            raise LogError(self.path, 'not an MCAP file (bad magic)')
        offset = len(MCAP_MAGIC)
        first = True
        while (record := self._next_record(offset)) is not None:
            opcode, body = record
            if first:
                self._header(opcode, body, offset)
                first = False
            elif opcode == OP_MESSAGE:
                yield self._message(body, offset)
            elif opcode == OP_SCHEMA:
                self._schema(body, offset)
            elif opcode == OP_CHANNEL:
                self._channel(body, offset)
            elif opcode in {OP_DATA_END, OP_FOOTER}:
                return
            elif opcode != OP_METADATA:
                # Segments are written unchunked; anything else means the bytes are damaged.
                msg = f'unexpected record opcode 0x{opcode:02x} at offset {offset}'
                raise LogError(self.path, msg)
            offset += _RECORD_HEAD.size + len(body)

    def _next_record(self, offset: int) -> tuple[int, bytes] | None:
        """Return the next complete record, or None at the end or at a torn record."""
        head = self.stream.read(_RECORD_HEAD.size)
        if len(head) < _RECORD_HEAD.size:
            return None
        opcode, length = _RECORD_HEAD.unpack(head)
        if length > self.size - offset - _RECORD_HEAD.size:
            return None
        body = self.stream.read(length)
        if len(body) < length:
            return None
        return opcode, body

    def _header(self, opcode: int, body: bytes, offset: int) -> None:
        if opcode != OP_HEADER:
            msg = f'expected the MCAP header record at offset {offset}, got opcode 0x{opcode:02x}'
            raise LogError(self.path, msg)
        fields = _Fields(body, self.path, 'header', offset)
        profile = fields.string()
        if profile != 'ros2':
            raise LogError(self.path, f'MCAP profile {profile!r}, expected ros2')

    def _schema(self, body: bytes, offset: int) -> None:
        fields = _Fields(body, self.path, 'schema', offset)
        schema_id = fields.u16()
        name = fields.string()
        fields.string()  # encoding
        fields.string()  # definition
        if schema_id == 0:
            raise fields.error('schema id 0')
        self.schemas[schema_id] = name

    def _channel(self, body: bytes, offset: int) -> None:
        fields = _Fields(body, self.path, 'channel', offset)
        channel_id = fields.u16()
        schema_id = fields.u16()
        topic = fields.string()
        fields.string()  # message encoding
        fields.blob()  # metadata
        msgtype = self.schemas.get(schema_id)
        if msgtype is None:
            raise fields.error(f'unknown schema id {schema_id}')
        self.channels[channel_id] = (topic, msgtype)

    def _message(self, body: bytes, offset: int) -> LogEntry:
        if len(body) < _MESSAGE_FIELDS.size:
            msg = f'malformed message record at offset {offset}: {len(body)} bytes'
            raise LogError(self.path, msg)
        channel_id, sequence, log_time, publish_time = _MESSAGE_FIELDS.unpack_from(body)
        channel = self.channels.get(channel_id)
        if channel is None:
            msg = f'message record at offset {offset} refers to unknown channel {channel_id}'
            raise LogError(self.path, msg)
        topic, msgtype = channel
        data = body[_MESSAGE_FIELDS.size :]
        return LogEntry(topic, msgtype, log_time, publish_time, sequence, data)


class _Fields:
    """Bounds-checked little-endian reader over one record body."""

    def __init__(self, body: bytes, path: Path, kind: str, offset: int) -> None:
        self.body = body
        self.pos = 0
        self.path = path
        self.kind = kind
        self.offset = offset

    def error(self, reason: str) -> LogError:
        msg = f'malformed {self.kind} record at offset {self.offset}: {reason}'
        return LogError(self.path, msg)

    def u16(self) -> int:
        (value,) = _U16.unpack(self._take(_U16.size))
        return int(value)

    def blob(self) -> bytes:
        (length,) = _U32.unpack(self._take(_U32.size))
        return self._take(int(length))

    def string(self) -> str:
        try:
            return self.blob().decode()
        except UnicodeDecodeError:
            raise self.error('string is not UTF-8') from None

    def _take(self, count: int) -> bytes:
        end = self.pos + count
        if end > len(self.body):
            raise self.error('field runs past the end of the record')
        chunk = self.body[self.pos : end]
        self.pos = end
        return chunk


# --------------------------------------------------------------------------- bookkeeping


class SegmentStore:
    """The numbered log segments of one node: ``<root>/<node>/log/<n:010d>/``.

    Args:
        root: Directory holding one subdirectory per node.
        node: Node id; used as a directory name, so letters, digits, ``_ . -`` only.

    Raises:
        ValueError: Bad node id.

    Attributes:
        dir: The node's log directory.

    """

    def __init__(self, root: Path, node: str) -> None:
        if not NODE_ID_RE.fullmatch(node):
            msg = f'{node!r} is not a node id (a letter, then letters, digits or _)'
            raise ValueError(msg)
        self.node = node
        self.dir = Path(root) / node / 'log'

    def numbers(self) -> list[int]:
        """Return the existing segment numbers, ascending."""
        try:
            entries = list(os.scandir(self.dir))
        except FileNotFoundError:
            return []
        except OSError as err:
            raise LogError(self.dir, f'cannot list: {err.strerror or err}') from None
        return sorted(
            int(entry.name)
            for entry in entries
            if _SEGMENT_RE.fullmatch(entry.name) and entry.is_dir()
        )

    def path(self, n: int) -> Path:
        """Return the bag directory of segment n."""
        return self.dir / f'{n:010d}'

    def next_number(self) -> int:
        """Return one above the highest existing segment number (1 if none)."""
        return max(self.numbers(), default=0) + 1

    def open(self, n: int, typestore: Typestore | None = None) -> SegmentWriter:
        """Create segment n, making the log directory and its parents with mode 0700.

        Raises:
            LogError: The segment exists already, cannot be created, or n is outside
                1..9999999999.

        """
        if not 1 <= n <= _MAX_NUMBER:
            raise LogError(self.path(n), f'segment number {n} outside 1..{_MAX_NUMBER}')
        try:
            make_private_dir(self.dir)
        except OSError as err:
            raise LogError(self.dir, f'cannot create: {err.strerror or err}') from None
        return SegmentWriter(self.path(n), typestore)

    def read_after(self, cut: int | None, before: int | None = None) -> Iterator[LogEntry]:
        """Yield the entries of segments numbered above cut (all if None) and below ``before``.

        Segments come in number order, entries in file order. A segment directory that is
        still empty (its writer was killed right after creating it) holds no messages.
        """
        for n in self.numbers():
            if (cut is not None and n <= cut) or (before is not None and n >= before):
                continue
            path = self.path(n)
            if not any(path.iterdir()):
                continue
            yield from read_segment(path)

    def identities_after(self, cut: int | None) -> dict[str, set[tuple[int, int]]]:
        """Return per topic the identities ``(source_ns, seq)`` logged after cut."""
        identities: dict[str, set[tuple[int, int]]] = {}
        for entry in self.read_after(cut):
            identities.setdefault(entry.topic, set()).add(entry.ident)
        return identities

    def drop_through(self, n: int) -> None:
        """Delete the segments numbered n and below.

        Raises:
            LogError: A segment cannot be deleted.

        """
        for number in self.numbers():
            if number > n:
                break
            path = self.path(number)
            try:
                shutil.rmtree(path)
            except FileNotFoundError:
                pass
            except OSError as err:
                raise LogError(path, f'cannot delete segment: {err}') from None


