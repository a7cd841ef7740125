"""Everything the node-side runtime and the supervisor agree on, in one place.

The two halves of RORY meet only here: environment variables the supervisor sets for a node it
spawns, the status messages a node sends, the name and QoS of the topic the supervisor answers
on, and the binary envelopes it sends there.

Statuses go node -> supervisor as datagrams on the supervisor's status socket
(status_socket.py, ``ENV_STATUS``), one JSON object each, not over DDS: nothing of RORY's in the
node's executor or participant in steady state (docs/architecture.md).

Topics (``<node>`` is the node's id from the supervisor configuration; ``/rory`` is the
*channel*, the supervisor's namespace followed by ``rory``, so that two supervisors on one DDS
network, e.g. one per robot under ``-r __ns:=/robot1``, never share a topic):

``/rory/<node>/replay``  supervisor -> node, ``std_msgs/msg/UInt8MultiArray`` carrying an
    envelope. This is the node's *shadow topic*: recorded messages of every input topic travel
    on it, multiplexed, so that the node receives them in exactly the recorded order (DDS keeps
    no order across topics, one shadow topic per input would not). Reliable, volatile, keep-all.

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
import hashlib
import hmac
import json
import re
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final, TypeVar

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from ..errors import ProtocolError
from ..freshness import Verdict

# ---------------------------------------------------------------------------------------------
# Environment the supervisor sets for a node it runs. Without ENV_NODE the runtime stays inert
# and the instrumented program behaves exactly like the original.
ENV_NODE: Final = 'RORY_NODE'
ENV_STORE: Final = 'RORY_STORE'
ENV_INCARNATION: Final = 'RORY_INCARNATION'
ENV_METHOD: Final = 'RORY_METHOD'
ENV_MODE: Final = 'RORY_MODE'
ENV_INTERVAL: Final = 'RORY_CHECKPOINT_INTERVAL'
# Set ('1') for a recovering process of a node with a release gate: it goes live but keeps its
# outputs muted until an OPEN envelope (docs/architecture.md, "The release gate").
ENV_GATED: Final = 'RORY_RELEASE_GATE'
ENV_QUARANTINE: Final = 'RORY_QUARANTINE'  # JSON [[topic, source_ns, seq], ...] to skip
# A key the supervisor draws for each run and gives its nodes through the environment, never
# over DDS: envelopes and status messages carry an HMAC of it, so another participant on the
# domain cannot feed a recovering node forged messages or steer its recovery.
ENV_SECRET: Final = 'RORY_SECRET'  # hex
# Where the node's two topics live: ``<supervisor namespace>/rory`` (see channel()).
ENV_CHANNEL: Final = 'RORY_CHANNEL'
# The supervisor's status socket (status_socket.py): statuses go to it, not over DDS.
ENV_STATUS: Final = 'RORY_STATUS_SOCKET'
DEFAULT_CHANNEL: Final = '/rory'

# A node's id: its name in the supervisor config, its folder in the store (store.py, log.py)
# and a part of its topics' names (/rory/<node>/replay_1), so a letter, then letters, digits or
# _ (what a ROS name allows, and no path). Always used with fullmatch.
NODE_ID_RE: Final = re.compile(r'[A-Za-z][A-Za-z0-9_]*')

# Publisher sequence numbers are stored in MCAP's u32 ``sequence`` field; identities use the
# same truncation everywhere so that a live message and its logged copy compare equal.
SEQ_MASK: Final = 0xFFFFFFFF

MessageId = tuple[int, int]
"""A message's identity: (publisher source timestamp ns, publisher sequence number & SEQ_MASK)."""


def seq_ranges(numbers: Iterable[int], sep: str = ', ') -> str:
    """Sequence numbers as runs: ``[4, 5, 6, 9]`` is ``4-6, 9``."""
    spans: list[list[int]] = []
    for n in numbers:
        if spans and n == spans[-1][1] + 1:
            spans[-1][1] = n
        else:
            spans.append([n, n])
    return sep.join(str(a) if a == b else f'{a}-{b}' for a, b in spans)


def message_id(info: dict[str, Any]) -> MessageId:
    """Identity of a received message from rclpy's message info."""
    return (int(info['source_timestamp']), int(info['publication_sequence_number']) & SEQ_MASK)


class Method(enum.StrEnum):
    """Recovery method; the three baselines share the supervisor with RORY."""

    RORY = 'rory'  # checkpoint + replay of the messages after its cut
    RESTART = 'restart'  # respawn with no state (what ROS's respawn does)
    CHECKPOINT = 'checkpoint'  # restore the last checkpoint, no replay
    REPLAY = 'replay'  # no checkpoints; replay every message since start

    @property
    def checkpoints(self) -> bool:
        """Whether the node takes checkpoints."""
        return self in (Method.RORY, Method.CHECKPOINT)

    @property
    def logs(self) -> bool:
        """Whether received messages are logged and replayed."""
        return self in (Method.RORY, Method.REPLAY)


class Mode(enum.StrEnum):
    """How a node process starts."""

    FRESH = 'fresh'  # first start: nothing to restore
    RECOVER = 'recover'  # restart after a crash: restore, replay, then release


class ReplayPace(enum.StrEnum):
    """How recorded messages are fed back."""

    PACED = 'paced'  # at the recorded gaps, as in the paper
    FAST = 'fast'  # as fast as the node takes them


# Records in a node's log segments that are not messages: a tick of one of its timers, a
# clock reading taken inside one of its callbacks, a parameter change, a service request
# (docs/architecture.md, "Timers and the clock"). No DDS topic has these names (':' is not
# allowed in a ROS name); they exist only in segments and on the shadow topic.
TIMER_RECORD: Final = '/rory:timer'
CLOCK_RECORD: Final = '/rory:clock'
EVENT_RECORD_TYPE: Final = 'builtin_interfaces/msg/Time'
# A change of the node's parameters from outside, as a serialized
# rcl_interfaces/msg/ParameterEvent (docs/architecture.md, "Parameters").
PARAMETERS_RECORD: Final = '/rory:parameters'
# A request to one of the node's services, by creation order (docs/architecture.md, "Services").
REQUEST_RECORD: Final = '/rory:request'


def pack_time_record(ns: int) -> bytes:
    """The CDR bytes of an event record: the time it carries as a ``builtin_interfaces/Time``
    (what a bag reader shows; RORY reads the record's timestamps)."""
    sec, nanosec = divmod(max(ns, 0), 1_000_000_000)
    return _CDR_LE + struct.pack('<iI', min(sec, 2**31 - 1), nanosec)


def is_input_topic(topic: str) -> bool:
    """Whether a logged record is a message of an input topic (not a tick or clock reading)."""
    return topic not in (TIMER_RECORD, CLOCK_RECORD, PARAMETERS_RECORD, REQUEST_RECORD)


def channel(namespace: str) -> str:
    """The channel of a supervisor whose node is in ``namespace`` (``/robot1/rory``)."""
    return f'{namespace.rstrip("/")}{DEFAULT_CHANNEL}'


def replay_topic(node_id: str, incarnation: int, channel: str = DEFAULT_CHANNEL) -> str:
    """The shadow topic of one process of a node.

    One per incarnation: the supervisor's writer is keep-all and reliable, so a reader it is
    matched with holds every sample until that reader acknowledges it, and a reader of a
    process that died (it stays matched until its DDS lease runs out) never does. A new
    process's reader is on a topic no dead reader was ever on.
    """
    return f'{channel}/{node_id}/replay_{incarnation}'


# Keep-all: a reliable writer then resends whatever a late-matching reader has not
# acknowledged, and nothing is dropped however far the node falls behind.
REPLAY_QOS: Final = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


# ---------------------------------------------------------------------------------------------
# Status messages, node -> supervisor. One JSON object each: ``kind``, ``node``, ``incarnation``,
# ``sent_ns`` (the node's wall clock when it sent it), the fields of its kind (the classes
# below, one per StatusKind) and ``sig``, an HMAC of the canonical JSON without it. Compact,
# with sorted keys: the text a node signs is the text a supervisor checks.


class StatusKind(enum.StrEnum):
    """Kinds of status a node reports."""

    HELLO = 'hello'  # started; carries inputs, restore result
    SYNCED = 'synced'  # answered a SYNC: the shadow path works both ways
    RELEASED = 'released'  # outputs unmuted (muted still, under a release gate), timers running
    OPENED = 'opened'  # the release gate opened: outputs unmuted
    CHECKPOINT = 'checkpoint'  # a checkpoint was written
    SWITCHED = 'switched'  # a topic is now taken from the live subscription
    INPUTS = 'inputs'  # a subscription made after HELLO (e.g. in on_configure): every input
    ERROR = 'error'  # something the operator must know (e.g. a variable that cannot be saved)


TAG_BYTES: Final = 16
"""Length of an HMAC-SHA256 tag as carried (truncated, as RFC 2104 allows)."""


def _tag(key: bytes, data: bytes) -> bytes:
    return hmac.new(key, data, hashlib.sha256).digest()[:TAG_BYTES]


def _canonical(obj: dict[str, Any]) -> str:
    return json.dumps(obj, separators=(',', ':'), sort_keys=True)


_E = TypeVar('_E', bound=enum.StrEnum)


def _json_type(value: Any) -> str:
    if value is None:
        return 'null'
    if isinstance(value, bool):
        return 'a boolean'
    if isinstance(value, int):
        return 'an integer'
    if isinstance(value, float):
        return 'a number'
    if isinstance(value, str):
        return 'a string'
    if isinstance(value, list):
        return 'an array'
    return 'an object' if isinstance(value, dict) else type(value).__name__


def _is_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)  # True is no count


class _Fields:
    """Typed reads of a status's JSON object: a field missing or of the wrong type is a
    ProtocolError that names it. Fields no kind defines are not read."""

    def __init__(self, where: str, obj: Mapping[str, Any], prefix: str = '') -> None:
        self.where = where  # 'hello status'
        self._obj = obj
        self._prefix = prefix  # 'restored.' for a nested object

    def _get(self, name: str) -> Any:
        if name not in self._obj:
            raise ProtocolError(f'{self.where} lacks {self._prefix}{name}')
        return self._obj[name]

    def _wrong(self, name: str, expected: str, value: Any) -> ProtocolError:
        return ProtocolError(f'{self.where}: {self._prefix}{name} must be {expected}, '
                             f'not {_json_type(value)}')

    def integer(self, name: str) -> int:
        value = self._get(name)
        if not _is_integer(value):
            raise self._wrong(name, 'an integer', value)
        return int(value)

    def optional_integer(self, name: str) -> int | None:
        value = self._get(name)
        if value is not None and not _is_integer(value):
            raise self._wrong(name, 'an integer or null', value)
        return None if value is None else int(value)

    def number(self, name: str) -> float:
        """An integer or a number, as sent: ``2`` stays ``2`` (the JSON is not rewritten)."""
        value = self._get(name)
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise self._wrong(name, 'a number', value)
        return value

    def text(self, name: str) -> str:
        value = self._get(name)
        if not isinstance(value, str):
            raise self._wrong(name, 'a string', value)
        return value

    def optional_text(self, name: str) -> str | None:
        value = self._get(name)
        if value is not None and not isinstance(value, str):
            raise self._wrong(name, 'a string or null', value)
        return value

    def choice(self, name: str, kind: type[_E]) -> _E:
        value = self._get(name)
        if value not in {k.value for k in kind}:
            raise self._wrong(name, f'one of {", ".join(k.value for k in kind)}', value)
        return kind(value)

    def texts(self, name: str) -> tuple[str, ...]:
        value = self._get(name)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self._wrong(name, 'an array of strings', value)
        return tuple(value)

    def integers(self, name: str) -> tuple[int, ...]:
        value = self._get(name)
        if not isinstance(value, list) or not all(_is_integer(v) for v in value):
            raise self._wrong(name, 'an array of integers', value)
        return tuple(value)

    def counts(self, name: str) -> dict[str, int]:
        value = self._get(name)
        if not isinstance(value, dict) or not all(_is_integer(v) for v in value.values()):
            raise self._wrong(name, 'an object of integers', value)
        return dict(value)

    def optional_number(self, name: str) -> float | None:
        value = self._get(name)
        if value is None:
            return None
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise self._wrong(name, 'a number or null', value)
        return value

    def numbers(self, name: str) -> dict[str, float]:
        value = self._get(name)
        if not isinstance(value, dict) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value.values()):
            raise self._wrong(name, 'an object of numbers', value)
        return dict(value)

    def verdict(self, name: str) -> Verdict:
        """What the freshness rules did (freshness.Verdict, as :meth:`Verdict.to_json` sends it)."""
        fields = self.nested(name)
        if fields is None:
            raise self._wrong(name, 'an object', None)
        return Verdict(age_s=fields.optional_number('age_s'), clock=fields.text('clock'),
                       restored=list(fields.texts('restored')), reset=list(fields.texts('reset')),
                       kept_stale=list(fields.texts('kept_stale')),
                       refused=list(fields.texts('refused')), max_age=fields.numbers('max_age'))

    def mapping(self, name: str) -> dict[str, Any]:
        value = self._get(name)
        if not isinstance(value, dict):
            raise self._wrong(name, 'an object', value)
        return value

    def inputs(self, name: str) -> tuple[InputSpec, ...]:
        value = self._get(name)
        if not isinstance(value, list):
            raise self._wrong(name, 'an array of input descriptions', value)
        try:
            return tuple(InputSpec.from_json(item) for item in value)
        except ProtocolError as err:
            raise ProtocolError(f'{self.where}: {self._prefix}{name}: {err}') from None

    def nested(self, name: str) -> _Fields | None:
        """An object field, or None for null."""
        value = self._get(name)
        if value is None:
            return None
        if not isinstance(value, dict):
            raise self._wrong(name, 'an object or null', value)
        return _Fields(self.where, value, f'{self._prefix}{name}.')


@dataclass(frozen=True, slots=True)
class RestoredCheckpoint:
    """The checkpoint a recovering process restored (HELLO's ``restored``,
    ``NodeRuntime.restore``)."""

    seq: int
    cut: int | None  # the last log segment whose messages it holds; None: the node logs none
    created_ns: int
    parameters: tuple[str, ...]  # the parameters set from it
    lifecycle: str | None  # the lifecycle state it returned to; None: not a lifecycle node
    freshness: Verdict  # what the freshness rules did

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'seq': self.seq, 'cut': self.cut, 'created_ns': self.created_ns,
                'parameters': list(self.parameters), 'lifecycle': self.lifecycle,
                'freshness': self.freshness.to_json()}

    @classmethod
    def from_fields(cls, fields: _Fields) -> RestoredCheckpoint:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(seq=fields.integer('seq'), cut=fields.optional_integer('cut'),
                   created_ns=fields.integer('created_ns'),
                   parameters=fields.texts('parameters'),
                   lifecycle=fields.optional_text('lifecycle'),
                   freshness=fields.verdict('freshness'))


@dataclass(frozen=True, slots=True, kw_only=True)
class HelloStatus:
    """The process started: what it is, what it subscribes to, what it restored."""

    kind: ClassVar[StatusKind] = StatusKind.HELLO
    mode: Mode
    method: Method
    pid: int
    manifest: str  # the instrumented code's version (patching.checkpointed)
    inputs: tuple[InputSpec, ...]
    restored: RestoredCheckpoint | None  # None: a fresh start, or no checkpoint passed
    refused: tuple[str, ...]  # why each checkpoint it did not restore was refused
    restore_ms: float
    process_start_ns: int | None  # wall clock; None where /proc cannot say
    interval: float  # seconds between its checkpoints
    replay: str | None  # the pace keyvars.yaml asks for ('paced', 'fast'), if it does
    dds_profile: str | None  # the Fast DDS profile file its participant was made with
    dds_transports: str | None  # FASTDDS_BUILTIN_TRANSPORTS, if set

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {
            'mode': self.mode.value, 'method': self.method.value, 'pid': self.pid,
            'manifest': self.manifest, 'inputs': [i.to_json() for i in self.inputs],
            'restored': None if self.restored is None else self.restored.to_json(),
            'refused': list(self.refused), 'restore_ms': self.restore_ms,
            'process_start_ns': self.process_start_ns, 'interval': self.interval,
            'replay': self.replay, 'dds_profile': self.dds_profile,
            'dds_transports': self.dds_transports,
        }

    @classmethod
    def from_fields(cls, fields: _Fields) -> HelloStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        restored = fields.nested('restored')
        return cls(
            mode=fields.choice('mode', Mode), method=fields.choice('method', Method),
            pid=fields.integer('pid'), manifest=fields.text('manifest'),
            inputs=fields.inputs('inputs'),
            restored=None if restored is None else RestoredCheckpoint.from_fields(restored),
            refused=fields.texts('refused'), restore_ms=fields.number('restore_ms'),
            process_start_ns=fields.optional_integer('process_start_ns'),
            interval=fields.number('interval'), replay=fields.optional_text('replay'),
            dds_profile=fields.optional_text('dds_profile'),
            dds_transports=fields.optional_text('dds_transports'),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class SyncedStatus:
    """The answer to a SYNC: the shadow path works both ways."""

    kind: ClassVar[StatusKind] = StatusKind.SYNCED
    nonce: int  # the SYNC's
    live_publishers: dict[str, int]  # per input topic, the publishers its reader matched

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'nonce': self.nonce, 'live_publishers': self.live_publishers}

    @classmethod
    def from_fields(cls, fields: _Fields) -> SyncedStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(nonce=fields.integer('nonce'),
                   live_publishers=fields.counts('live_publishers'))


@dataclass(frozen=True, slots=True, kw_only=True)
class ReleasedStatus:
    """Released: outputs unmuted (still muted under a release gate), timers running. Carries
    the runtime's counters (``NodeRuntime.stats``), each since the process started."""

    kind: ClassVar[StatusKind] = StatusKind.RELEASED
    applied: int  # messages the user callbacks ran on, live or replayed
    replayed: int  # of them, from the shadow topic
    duplicates: int  # skipped: already applied (in a window of applied identities)
    muted: int  # publishes dropped while the outputs were muted
    quarantined: int  # skipped: the supervisor quarantined them (a poison message)
    passed_by_relay: int  # reached only the live reader after later ones came by relay
    ticks: int  # timer callbacks run live
    ticks_replayed: int
    clock_fallbacks: int  # clock readings replay had no recorded value for (event_clock.py)
    parameter_changes: int  # from outside, logged
    parameter_changes_replayed: int
    requests: int  # service requests, logged
    requests_replayed: int

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {
            'applied': self.applied, 'replayed': self.replayed, 'duplicates': self.duplicates,
            'muted': self.muted, 'quarantined': self.quarantined,
            'passed_by_relay': self.passed_by_relay, 'ticks': self.ticks,
            'ticks_replayed': self.ticks_replayed, 'clock_fallbacks': self.clock_fallbacks,
            'parameter_changes': self.parameter_changes,
            'parameter_changes_replayed': self.parameter_changes_replayed,
            'requests': self.requests, 'requests_replayed': self.requests_replayed,
        }

    @classmethod
    def from_fields(cls, fields: _Fields) -> ReleasedStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(
            applied=fields.integer('applied'), replayed=fields.integer('replayed'),
            duplicates=fields.integer('duplicates'), muted=fields.integer('muted'),
            quarantined=fields.integer('quarantined'),
            passed_by_relay=fields.integer('passed_by_relay'), ticks=fields.integer('ticks'),
            ticks_replayed=fields.integer('ticks_replayed'),
            clock_fallbacks=fields.integer('clock_fallbacks'),
            parameter_changes=fields.integer('parameter_changes'),
            parameter_changes_replayed=fields.integer('parameter_changes_replayed'),
            requests=fields.integer('requests'),
            requests_replayed=fields.integer('requests_replayed'),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class OpenedStatus:
    """The release gate opened: outputs unmuted."""

    kind: ClassVar[StatusKind] = StatusKind.OPENED
    muted: int  # publishes dropped while they were muted

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'muted': self.muted}

    @classmethod
    def from_fields(cls, fields: _Fields) -> OpenedStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(muted=fields.integer('muted'))


@dataclass(frozen=True, slots=True, kw_only=True)
class CheckpointStatus:
    """A checkpoint was written (``Checkpointer.take``)."""

    kind: ClassVar[StatusKind] = StatusKind.CHECKPOINT
    seq: int
    cut: int | None  # the last log segment whose messages it holds; None: the node logs none
    size: int  # bytes of its packed variables ('bytes' on the wire)
    stall_ms: float  # the node paused for the snapshot
    total_ms: float  # snapshot to durable file

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'seq': self.seq, 'cut': self.cut, 'bytes': self.size,
                'stall_ms': self.stall_ms, 'total_ms': self.total_ms}

    @classmethod
    def from_fields(cls, fields: _Fields) -> CheckpointStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(seq=fields.integer('seq'), cut=fields.optional_integer('cut'),
                   size=fields.integer('bytes'), stall_ms=fields.number('stall_ms'),
                   total_ms=fields.number('total_ms'))


@dataclass(frozen=True, slots=True, kw_only=True)
class SwitchedStatus:
    """A topic is taken from its live reader from now on (``Router.switch``)."""

    kind: ClassVar[StatusKind] = StatusKind.SWITCHED
    topic: str
    # Publication sequence numbers of the messages left out: they reached only the live
    # reader, after the relay had delivered later ones of the same publisher.
    passed_by_relay: tuple[int, ...]
    # Publication sequence numbers of the messages applied from the live reader that the relay
    # never delivered, in their publisher's order before a relayed one (``Router._live_only``):
    # the supervisor's ring never got them, and its input gap leaves them out.
    live_only: tuple[int, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'topic': self.topic, 'passed_by_relay': list(self.passed_by_relay),
                'live_only': list(self.live_only)}

    @classmethod
    def from_fields(cls, fields: _Fields) -> SwitchedStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(topic=fields.text('topic'), passed_by_relay=fields.integers('passed_by_relay'),
                   live_only=fields.integers('live_only'))


@dataclass(frozen=True, slots=True, kw_only=True)
class InputsStatus:
    """The node subscribed after HELLO (e.g. in ``on_configure``): every input it has now."""

    kind: ClassVar[StatusKind] = StatusKind.INPUTS
    inputs: tuple[InputSpec, ...]

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'inputs': [i.to_json() for i in self.inputs]}

    @classmethod
    def from_fields(cls, fields: _Fields) -> InputsStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(inputs=fields.inputs('inputs'))


@dataclass(frozen=True, slots=True, kw_only=True)
class ErrorStatus:
    """Something the operator must know (e.g. a variable that cannot be saved)."""

    kind: ClassVar[StatusKind] = StatusKind.ERROR
    message: str

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'message': self.message}

    @classmethod
    def from_fields(cls, fields: _Fields) -> ErrorStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(message=fields.text('message'))


Status = (HelloStatus | SyncedStatus | ReleasedStatus | OpenedStatus | CheckpointStatus
          | SwitchedStatus | InputsStatus | ErrorStatus)

_STATUS_CLASSES: Final[dict[StatusKind, type[Status]]] = {
    StatusKind.HELLO: HelloStatus,
    StatusKind.SYNCED: SyncedStatus,
    StatusKind.RELEASED: ReleasedStatus,
    StatusKind.OPENED: OpenedStatus,
    StatusKind.CHECKPOINT: CheckpointStatus,
    StatusKind.SWITCHED: SwitchedStatus,
    StatusKind.INPUTS: InputsStatus,
    StatusKind.ERROR: ErrorStatus,
}


@dataclass(frozen=True, slots=True)
class StatusMessage:
    """One status as it travels: which process of which node sent it, when, and what it says."""

    node: str
    incarnation: int
    sent_ns: int | None  # the node's wall clock when it sent it (None: not given)
    status: Status

    def to_json(self) -> dict[str, Any]:
        """The JSON object, without its signature."""
        head: dict[str, Any] = {'kind': self.status.kind.value, 'node': self.node,
                                'incarnation': self.incarnation}
        if self.sent_ns is not None:
            head['sent_ns'] = self.sent_ns
        return {**head, **self.status.to_json()}


def encode_status(status: Status, node_id: str, incarnation: int, *, key: bytes | None = None,
                  sent_ns: int | None = None) -> str:
    """JSON text of a status message, signed with ``key`` (field ``sig``) when given."""
    obj = StatusMessage(node_id, incarnation, sent_ns, status).to_json()
    if key is None:
        return _canonical(obj)
    obj['sig'] = _tag(key, _canonical(obj).encode()).hex()
    return _canonical(obj)


def decode_status(text: str, key: bytes | None = None) -> StatusMessage:
    """Parse a status message; with ``key``, only one signed with it. Fields its kind does not
    define are left out (the signature covers them all).

    Raises:
        ProtocolError: Not a JSON object with kind, node and incarnation and the fields of its
            kind, each of its type (the message names the field), or (with ``key``) unsigned
            or signed with another key.
    """
    try:
        obj = json.loads(text)
    except ValueError as err:
        raise ProtocolError(f'status is not JSON: {err}') from None
    if not isinstance(obj, dict):
        raise ProtocolError('status is not a JSON object')
    sig = obj.pop('sig', None)
    if key is not None:
        if not isinstance(sig, str):
            raise ProtocolError('status is not signed')
        if not hmac.compare_digest(sig, _tag(key, _canonical(obj).encode()).hex()):
            raise ProtocolError('status signature does not match this run\'s key')
    kind = obj.get('kind')
    if kind not in {k.value for k in StatusKind}:
        raise ProtocolError(f'status has unknown kind {kind!r}')
    head = _Fields('status', obj)
    node, incarnation = head.text('node'), head.integer('incarnation')
    sent_ns = head.integer('sent_ns') if 'sent_ns' in obj else None
    fields = _Fields(f'{kind} status', obj)
    return StatusMessage(node, incarnation, sent_ns,
                         _STATUS_CLASSES[StatusKind(kind)].from_fields(fields))


# ---------------------------------------------------------------------------------------------
# Envelopes, supervisor -> node. Built and parsed by hand: the CDR of a UInt8MultiArray with
# an empty layout is a fixed 16-byte prefix, so neither side pays for message conversion.

_CDR_PREFIX = struct.Struct('<4sIII')  # encapsulation, dim count, data_offset, data length
_CDR_LE = b'\x00\x01\x00\x00'
_HEAD = struct.Struct('<2sBBI')
_MAGIC = b'RY'
_VERSION = 1
_SIGNED = 2  # version 1 followed by an HMAC tag of the payload
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
    return _CDR_PREFIX.pack(_CDR_LE, 0, 0, len(payload)) + payload


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
    return _wrap(bytes(payload) + _tag(key, bytes(payload)))


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
    if encap[:2] != _CDR_LE[:2] or ndim != 0 or not 0 <= padding <= 3:
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
        if not hmac.compare_digest(bytes(view[end:]), _tag(key, bytes(view[_CDR_PREFIX.size:end]))):
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


# ---------------------------------------------------------------------------------------------
# Describing a node's inputs, so the supervisor can hold matching readers (the ring).


@dataclass(frozen=True)
class InputSpec:
    """One subscription of a supervised node, as the supervisor needs to mirror it."""

    topic: str
    msgtype: str  # 'pkg/msg/Name'
    reliable: bool
    transient_local: bool
    depth: int  # 0 for keep-all

    def to_json(self) -> dict[str, Any]:
        """Plain dict for a status message."""
        return {
            'topic': self.topic,
            'type': self.msgtype,
            'reliable': self.reliable,
            'transient_local': self.transient_local,
            'depth': self.depth,
        }

    @classmethod
    def from_json(cls, obj: Any) -> InputSpec:
        """Parse the dict form.

        Raises:
            ProtocolError: Missing or ill-typed fields.
        """
        expected = {
            'topic': str, 'type': str, 'reliable': bool, 'transient_local': bool, 'depth': int,
        }
        if not isinstance(obj, dict):
            raise ProtocolError(f'bad input description {obj!r}: not an object')
        for key, kind in expected.items():
            value = obj.get(key)
            # bool is an int in Python; a depth of True is not a depth
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise ProtocolError(f'bad input description {obj!r}: {key} must be {kind.__name__}')
        if obj['depth'] < 0:
            raise ProtocolError(f'bad input description {obj!r}: depth must be >= 0')
        return cls(
            topic=obj['topic'],
            msgtype=obj['type'],
            reliable=obj['reliable'],
            transient_local=obj['transient_local'],
            depth=obj['depth'],
        )

    @classmethod
    def from_qos(cls, topic: str, msgtype: str, qos: QoSProfile) -> InputSpec:
        """Describe a subscription from its QoS profile."""
        keep_all = qos.history == HistoryPolicy.KEEP_ALL
        return cls(
            topic=topic,
            msgtype=msgtype,
            reliable=qos.reliability != ReliabilityPolicy.BEST_EFFORT,
            transient_local=qos.durability == DurabilityPolicy.TRANSIENT_LOCAL,
            depth=0 if keep_all else int(qos.depth),
        )


def ring_depth(spec: InputSpec) -> int:
    """How many recent messages of an input the supervisor's passive reader holds.

    A crashed node can have left at most its own queue depth of received-but-unapplied
    messages; the margin covers what arrives between the crash and the supervisor noticing.
    """
    return (spec.depth if spec.depth else 256) + 16


def window_size(spec: InputSpec) -> int:
    """How many applied message identities the node remembers per input.

    Must exceed :func:`ring_depth`: everything the ring hands back after a crash is then
    either in the node's window (absorbed, skipped) or new.
    """
    return ring_depth(spec) + 64
