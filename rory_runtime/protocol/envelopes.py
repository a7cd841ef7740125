"""The envelopes the supervisor sends a node on its shadow topic (topics.py).

Envelope layout (little endian), inside the ``data`` field of the UInt8MultiArray::

    magic 'RY' | version u8 | kind u8 | incarnation u32 | body

    SYNC     nonce u64                      path check: the node answers with a SYNCED status
    MSG      flags u8 | recv_ns i64 | source_ns i64 | seq u32 | topic_len u16 | topic | cdr
    RELEASE  next_segment u64 | delivered u64
    OPEN     (no body)                      the release gate opened: unmute the outputs
    ALIVE    (no body)                      the relay is alive with nothing to relay

A MSG with ``FLAG_RELAY`` was recorded after RELEASE: the node logs it when it applies it,
because it is not in any sealed log segment. After RELEASE the relay sends an ALIVE whenever
it has sent nothing for :data:`RELAY_KEEPALIVE_S`, so that a node can tell a relay with
nothing to relay (its ring received nothing, e.g. during a link outage) from a supervisor that
died (``routing.RELAY_SILENCE_NS``).
"""

from __future__ import annotations

import enum
import hmac
import struct
from dataclasses import dataclass
from typing import Any, Final

from ..errors import ProtocolError
from .inputs import SEQ_MASK, MessageId
from .signing import TAG_BYTES, tag

# Envelopes, supervisor -> node. Built and parsed by hand: the CDR of a UInt8MultiArray with
# an empty layout is a fixed 16-byte prefix, so neither side pays for message conversion.

_CDR_PREFIX = struct.Struct('<4sIII')  # encapsulation, dim count, data_offset, data length
CDR_LE: Final = b'\x00\x01\x00\x00'  # CDR encapsulation, little endian (records.py's too)
_HEAD = struct.Struct('<2sBBI')
_MAGIC = b'RY'
# The version of what a node and its supervisor say to each other, statuses included: a node
# and a supervisor of different versions refuse each other's envelopes from the first SYNC on,
# not at the first status one of them reads otherwise. Each version has two numbers, plain and
# signed. 1 and 2: the first; 3 and 4: since an ERROR status says whether and why a checkpoint
# was not taken (statuses.CheckpointFailure).
_VERSION = 3
_SIGNED = 4  # version 3 followed by an HMAC tag of the payload
_SYNC = struct.Struct('<Q')
_MSG = struct.Struct('<BqqIH')
_RELEASE = struct.Struct('<QQ')

FLAG_RELAY: Final = 0x01

RELAY_KEEPALIVE_S: Final = 0.5
"""After RELEASE, the relay sends an ALIVE envelope when it has sent nothing for this long.
A quarter of the node's ``routing.RELAY_SILENCE_NS`` (2 s): three may be lost or late before
the node takes the relay for dead."""


class EnvelopeKind(enum.IntEnum):
    """Kinds of envelope on a shadow topic."""

    SYNC = 1
    MSG = 2
    RELEASE = 3
    OPEN = 4
    ALIVE = 5


@dataclass(frozen=True, slots=True)
class Sync:
    """Path check the node answers with a SYNCED status."""

    incarnation: int
    nonce: int


@dataclass(frozen=True, slots=True)
class Msg:
    """One recorded message of an input topic."""

    incarnation: int
    flags: int
    recv_ns: int
    source_ns: int
    seq: int
    topic: str
    data: bytes

    @property
    def ident(self) -> MessageId:
        """The message's identity."""
        return (self.source_ns, self.seq)


@dataclass(frozen=True, slots=True)
class Release:
    """Everything recorded so far was sent: unmute, and log from ``next_segment`` on."""

    incarnation: int
    next_segment: int
    delivered: int


@dataclass(frozen=True, slots=True)
class Open:
    """The node's release gate opened: unmute its outputs."""

    incarnation: int


@dataclass(frozen=True, slots=True)
class Alive:
    """The relay is alive and has nothing to relay (sent after RELEASE, when idle)."""

    incarnation: int


Envelope = Sync | Msg | Release | Open | Alive


def _wrap(payload: bytes) -> bytes:
    return _CDR_PREFIX.pack(CDR_LE, 0, 0, len(payload)) + payload


def pack_sync(incarnation: int, nonce: int) -> bytes:
    """Serialized UInt8MultiArray carrying a SYNC."""
    head = _HEAD.pack(_MAGIC, _VERSION, EnvelopeKind.SYNC, incarnation)
    return _wrap(head + _SYNC.pack(nonce))


def pack_msg(
    incarnation: int,
    *,
    topic: str,
    recv_ns: int,
    source_ns: int,
    seq: int,
    data: bytes,
    flags: int = 0,
) -> bytes:
    """Serialized UInt8MultiArray carrying one recorded message."""
    name = topic.encode()
    head = _HEAD.pack(_MAGIC, _VERSION, EnvelopeKind.MSG, incarnation)
    body = _MSG.pack(flags, recv_ns, source_ns, seq & SEQ_MASK, len(name))
    return _wrap(b''.join((head, body, name, data)))


def pack_release(incarnation: int, next_segment: int, delivered: int) -> bytes:
    """Serialized UInt8MultiArray carrying a RELEASE."""
    head = _HEAD.pack(_MAGIC, _VERSION, EnvelopeKind.RELEASE, incarnation)
    return _wrap(head + _RELEASE.pack(next_segment, delivered))


def pack_open(incarnation: int) -> bytes:
    """Serialized UInt8MultiArray carrying an OPEN."""
    return _wrap(_HEAD.pack(_MAGIC, _VERSION, EnvelopeKind.OPEN, incarnation))


def pack_alive(incarnation: int) -> bytes:
    """Serialized UInt8MultiArray carrying an ALIVE."""
    return _wrap(_HEAD.pack(_MAGIC, _VERSION, EnvelopeKind.ALIVE, incarnation))


def sign(raw: bytes, key: bytes) -> bytes:
    """A packed envelope, signed: version 2, the payload followed by its HMAC tag.

    Raises:
        ProtocolError: ``raw`` is not an unsigned envelope.
    """
    if len(raw) < _CDR_PREFIX.size + _HEAD.size:
        raise ProtocolError(f'envelope too short ({len(raw)} bytes)')
    _, _, _, length = _CDR_PREFIX.unpack_from(raw)
    payload = bytearray(raw[_CDR_PREFIX.size : _CDR_PREFIX.size + length])
    if payload[2] != _VERSION:
        raise ProtocolError(f'envelope version {payload[2]} cannot be signed')
    payload[2] = _SIGNED
    return _wrap(bytes(payload) + tag(key, bytes(payload)))


class SignedPublisher:
    """Publishes envelopes signed with the run's key (the shadow topic's only writer)."""

    def __init__(self, publisher: Any, key: bytes) -> None:
        self._publisher = publisher
        self._key = key

    def publish(self, raw: bytes) -> None:
        """Sign and publish one packed envelope."""
        self._publisher.publish(sign(raw, self._key))


def unpack(raw: bytes, key: bytes | None = None) -> Envelope:
    """Parse a serialized UInt8MultiArray envelope; with ``key``, only one signed with it.

    Raises:
        ProtocolError: Anything that is not a well-formed envelope of this version, or (with
            ``key``) one not signed with it.
    """
    view = memoryview(raw)
    if len(view) < _CDR_PREFIX.size + _HEAD.size:
        raise ProtocolError(f'envelope too short ({len(view)} bytes)')
    encap, ndim, _, length = _CDR_PREFIX.unpack_from(view)
    # DDS pads a serialized payload to a multiple of 4 bytes; the padding is not ours.
    padding = len(view) - _CDR_PREFIX.size - length
    if encap[:2] != CDR_LE[:2] or ndim != 0 or not 0 <= padding <= 3:
        raise ProtocolError('envelope is not a plain UInt8MultiArray')
    view = view[: _CDR_PREFIX.size + length]
    if length < _HEAD.size:
        raise ProtocolError(f'envelope payload too short ({length} bytes)')
    off = _CDR_PREFIX.size
    magic, version, kind, incarnation = _HEAD.unpack_from(view, off)
    if magic != _MAGIC or version not in (_VERSION, _SIGNED):
        raise ProtocolError(f'bad envelope magic/version {magic!r}/{version}')
    if key is not None:
        if version != _SIGNED or length < _HEAD.size + TAG_BYTES:
            raise ProtocolError('envelope is not signed')
        end = _CDR_PREFIX.size + length - TAG_BYTES
        if not hmac.compare_digest(bytes(view[end:]), tag(key, bytes(view[_CDR_PREFIX.size:end]))):
            raise ProtocolError('envelope signature does not match this run\'s key')
        view = view[:end]
    elif version == _SIGNED:
        view = view[: len(view) - TAG_BYTES]
    off += _HEAD.size
    try:
        if kind == EnvelopeKind.SYNC:
            (nonce,) = _SYNC.unpack_from(view, off)
            return Sync(incarnation, nonce)
        if kind == EnvelopeKind.MSG:
            flags, recv_ns, source_ns, seq, name_len = _MSG.unpack_from(view, off)
            off += _MSG.size
            if off + name_len > len(view):
                raise ProtocolError('envelope topic runs past its end')
            topic = bytes(view[off : off + name_len]).decode()
            return Msg(
                incarnation, flags, recv_ns, source_ns, seq, topic, bytes(view[off + name_len :])
            )
        if kind == EnvelopeKind.RELEASE:
            next_segment, delivered = _RELEASE.unpack_from(view, off)
            return Release(incarnation, next_segment, delivered)
        if kind == EnvelopeKind.OPEN:
            return Open(incarnation)
        if kind == EnvelopeKind.ALIVE:
            return Alive(incarnation)
    except (struct.error, UnicodeDecodeError) as err:
        raise ProtocolError(f'malformed envelope of kind {kind}: {err}') from None
    raise ProtocolError(f'unknown envelope kind {kind}')
