"""The status messages a node sends its supervisor.

Statuses go node -> supervisor as datagrams on the supervisor's status socket
(status_socket.py, ``ENV_STATUS``), one JSON object each, not over DDS: nothing of RORY's in the
node's executor or participant in steady state (docs/architecture.md).
"""

from __future__ import annotations

import enum
import hmac
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final, TypeVar

from ..errors import ProtocolError
from ..freshness import Verdict
from .env import Method, Mode
from .inputs import InputSpec
from .signing import tag

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

    def optional_choice(self, name: str, kind: type[_E]) -> _E | None:
        value = self._get(name)
        if value is not None and value not in {k.value for k in kind}:
            raise self._wrong(name, f'one of {", ".join(k.value for k in kind)} or null', value)
        return None if value is None else kind(value)

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
    clock_fallbacks: int  # clock readings replay had no recorded value for (node/event_clock.py)
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


class CheckpointFailure(enum.StrEnum):
    """Why a checkpoint was not taken (``Checkpointer.take``): an ERROR status says so."""

    SKIPPED = 'skipped'  # its snapshot was refused (a variable cannot be read or packed)
    NOT_WRITTEN = 'not_written'  # the snapshot was taken, its file not written (e.g. disk full)


@dataclass(frozen=True, slots=True, kw_only=True)
class ErrorStatus:
    """Something the operator must know (e.g. a variable that cannot be saved)."""

    kind: ClassVar[StatusKind] = StatusKind.ERROR
    message: str
    # The checkpoint this error says was not taken, and why; None: the error is about something
    # else. The supervisor reads :attr:`checkpoint_failed`, never the message.
    checkpoint: CheckpointFailure | None = None

    @property
    def checkpoint_failed(self) -> bool:
        """Whether a checkpoint was not taken (the node's checkpoints are failing until one
        is written)."""
        return self.checkpoint is not None

    def to_json(self) -> dict[str, Any]:
        """The fields as they travel."""
        return {'message': self.message,
                'checkpoint': None if self.checkpoint is None else self.checkpoint.value}

    @classmethod
    def from_fields(cls, fields: _Fields) -> ErrorStatus:
        """Read the fields (:meth:`to_json`'s).

        Raises:
            ProtocolError: A field missing or of the wrong type.
        """
        return cls(message=fields.text('message'),
                   checkpoint=fields.optional_choice('checkpoint', CheckpointFailure))


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
    obj['sig'] = tag(key, _canonical(obj).encode()).hex()
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
        if not hmac.compare_digest(sig, tag(key, _canonical(obj).encode()).hex()):
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
