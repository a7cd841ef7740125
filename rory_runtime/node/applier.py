"""Where an event of the node is applied: a message, a tick, a request or a parameter change
(docs/architecture.md, "A message, step by step").

The router (routing.py) decides *when* a message is applied; the :class:`Applier` applies it:
under the runtime's one lock, written ahead to the log (methods that log), the in-flight slot
marked busy, the event's clock readings recorded or replayed (event_clock.py), the user's
callback, then the slot idle, the identity added to its topic's window and the counters
(``stats``, reported to the supervisor) moved. The output gate (gating.py) runs the node's
ticks, requests and parameter changes through :meth:`Applier.live_event` and
:meth:`Applier.replayed_event`.

A live message on a LIVE topic takes the shortest path: the subscription's callback is
:meth:`Applier.live_path`'s function for that topic, which does all of the above in one
function, with everything it reads bound once. What a message costs the node's process is
mostly how many distinct Python functions it runs through (issue 36), so that function calls
nothing of RORY's but the log writer.
"""

from __future__ import annotations

import functools
import threading
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rosbags.interfaces import Qos

from .. import protocol
from ..errors import LogError
from ..inflight import InFlightSlot
from ..log import SegmentWriter
from ..protocol import SEQ_MASK, MessageId
from ..qos import offered_qos
from . import event_clock
from .event_clock import EventClock, Reading

if TYPE_CHECKING:
    from rclpy.node import Node

    from .routing import Input

T = TypeVar('T')

STAT_NAMES = ('applied', 'replayed', 'duplicates', 'muted', 'quarantined', 'passed_by_relay',
              'ticks', 'ticks_replayed', 'clock_fallbacks', 'parameter_changes',
              'parameter_changes_replayed', 'requests', 'requests_replayed')
"""The counters a node reports (``ReleasedStatus``), in its order."""

LiveCallback = Callable[[bytes, dict[str, Any]], None]
"""A raw subscription's callback: the CDR bytes and rclpy's message info."""


class Window:
    """Identities of the last messages applied on one topic."""

    __slots__ = ('_order', '_set')

    def __init__(self, size: int, items: Iterable[MessageId] = ()) -> None:
        self._order: deque[MessageId] = deque(maxlen=size)
        self._set: set[MessageId] = set()
        for item in items:
            self.add(item)

    def __contains__(self, ident: MessageId) -> bool:
        return ident in self._set

    def add(self, ident: MessageId) -> None:
        # (Applier.live_path does the same inline.)
        if len(self._order) == self._order.maxlen:
            self._set.discard(self._order[0])
        self._order.append(ident)
        self._set.add(ident)

    def snapshot(self) -> list[tuple[int, int]]:
        return list(self._order)

    @property
    def newest(self) -> MessageId | None:
        """The identity applied last (None: none yet)."""
        return self._order[-1] if self._order else None


class SegmentSource(Protocol):
    """Where the log is written (``Checkpointer``): the segment being written, if open, and the
    one to write to, opened at the first record after a rotation."""

    writer: SegmentWriter | None

    def segment(self) -> SegmentWriter: ...


class Applier:
    """Applies the node's events under the runtime's lock, logging them ahead.

    Args:
        lock: The runtime's lock, under which every user callback and checkpoint snapshot runs.
        logs: Whether events are written to the log (and clock readings recorded).
        quarantined: Poison messages the supervisor set aside: never applied again.
        inflight: The in-flight slot: the message being applied, readable after a crash.
        segments: Where the log is written (the checkpointer, which rotates it).
        error: Reports an error (the ERROR status).
    """

    def __init__(self, *, lock: threading.RLock, logs: bool,
                 quarantined: frozenset[tuple[str, MessageId]], inflight: InFlightSlot,
                 segments: SegmentSource, error: Callable[[str], None]) -> None:
        self.lock = lock
        self.logs = logs
        self.quarantined = quarantined
        self.inflight = inflight
        self._segments = segments
        self._error = error
        # Per topic, the identities applied last: applying adds to them, the router skips what
        # they hold, checkpoints copy them, a restore sets them.
        self.windows: dict[str, Window] = {}
        self.stats: dict[str, int] = dict.fromkeys(STAT_NAMES, 0)
        # Clock readings inside events, recorded and replayed (only when events are logged).
        self.clock: EventClock | None = None
        if logs:
            event_clock.install()
            self.clock = EventClock(self._log_reading, self._readings_unrecorded)
        # Events run to their end (messages, ticks, requests, parameter changes, replayed or
        # live): the pulse reads it to know the executor is alive without waking it.
        self.progress = 0
        # A user callback raised: the process is going down with it (no checkpoint at exit).
        self.callback_failed = False
        # The node, for the offered QoS a segment records for each topic (set when it exists).
        self.node: Node | None = None
        self._qos_lookups: dict[str, Callable[[], Sequence[Qos]]] = {}

    # -- messages -------------------------------------------------------------------------------

    def live_path(self, inp: Input) -> LiveCallback:
        """The callback of ``inp``'s subscription once its topic is LIVE (the router sets it):
        the message's identity, skipped if its window holds it or it is quarantined, else
        written ahead to the log, the slot busy, the callback with its clock readings recorded,
        the slot idle, the window and counters moved. Straight-line and everything bound here:
        the same steps as :meth:`apply` with ``log=True``, in one function.

        Made when the topic goes LIVE, after any restore of the windows (start-up restores
        before the release that makes a topic LIVE).
        """
        topic = inp.topic
        type_name = inp.type_name
        callback = inp.callback
        with_info = inp.with_info
        user_raw = inp.user_raw
        msg_type = inp.msg_type
        deserialize = _rclpy.rclpy_deserialize
        window = self.windows[topic]
        order, members, size = window._order, window._set, window._order.maxlen
        stats = self.stats
        quarantined = self.quarantined
        lock = self.lock
        logs = self.logs
        segments = self._segments
        lookup = self._offered_qos_of(topic)
        error = self._error
        clock = self.clock
        current = event_clock.current
        get_ident = threading.get_ident
        slot, name_at, name, head_at, head, idle_at, idle = self.inflight.writes(topic)
        applier = self

        def live(raw: bytes, info: dict[str, Any]) -> None:
            ident = (int(info['source_timestamp']),
                     int(info['publication_sequence_number']) & SEQ_MASK)
            if ident in members:
                # e.g. a transient-local publisher re-sending what the checkpoint already holds
                stats['duplicates'] += 1
                return
            if quarantined and (topic, ident) in quarantined:
                stats['quarantined'] += 1
                return
            # rclpy's deserialize_message less its type-support check, made once at adoption
            # (Router.adopt).
            msg = raw if user_raw else deserialize(raw, msg_type)
            received_ns = int(info['received_timestamp'])
            with lock:
                if logs:
                    writer = segments.writer
                    if writer is None:
                        writer = segments.segment()
                    try:
                        writer.write(topic, type_name, received_ns, ident[0], ident[1], raw,
                                     offered_qos=lookup)
                    except LogError as err:
                        error(f'cannot log a message of {topic}: {err}')
                slot[name_at] = name
                slot[head_at] = head(ident[1], ident[0], received_ns)
                if clock is not None:  # EventClock.begin_live
                    clock.thread = get_ident()
                    clock.replaying = False
                    clock.count = 0
                    current.event = clock
                try:
                    if with_info:
                        callback(msg, info)
                    else:
                        callback(msg)
                except BaseException:
                    applier.callback_failed = True
                    raise
                finally:
                    if clock is not None:  # EventClock.end (a live event has no readings)
                        current.event = None
                slot[idle_at] = idle
                if len(order) == size:  # Window.add
                    members.discard(order[0])
                order.append(ident)
                members.add(ident)
                stats['applied'] += 1
                applier.progress += 1

        return live

    def apply(
        self, inp: Input, raw: bytes, info: dict[str, Any], ident: MessageId, readings:
        Iterable[Reading] = (), *, log: bool
    ) -> None:
        """Run the user's callback on one message under the lock; ``log``: a live message,
        written to the log first; else a replayed one, whose clock ``readings`` it gets."""
        msg = raw if inp.user_raw else _rclpy.rclpy_deserialize(raw, inp.msg_type)
        received_ns = int(info['received_timestamp'])
        clock = self.clock
        with self.lock:
            if log and self.logs:
                self._log_message(inp, raw, received_ns, ident)
            self.inflight.busy(inp.topic, ident, received_ns)
            if clock is not None:
                if log:
                    clock.begin_live()
                else:
                    clock.begin_replay(received_ns, readings)
            try:
                if inp.with_info:
                    inp.callback(msg, info)
                else:
                    inp.callback(msg)
            except BaseException:
                self.callback_failed = True
                raise
            finally:
                if clock is not None:
                    clock.end()
            self.inflight.idle()
            self.windows[inp.topic].add(ident)
            self.stats['applied'] += 1
            self.progress += 1

    def _log_message(self, inp: Input, raw: bytes, received_ns: int, ident: MessageId) -> None:
        writer = self._segments.segment()
        try:
            writer.write(inp.topic, inp.type_name, received_ns, ident[0], ident[1], raw,
                         offered_qos=self._offered_qos_of(inp.topic))
        except LogError as err:
            self._error(f'cannot log a message of {inp.topic}: {err}')

    def _offered_qos_of(self, topic: str) -> Callable[[], Sequence[Qos]] | None:
        """What asks the graph for ``topic``'s offered QoS when a segment first logs it (made
        once per topic, not at every message)."""
        lookup = self._qos_lookups.get(topic)
        if lookup is None and self.node is not None:
            lookup = functools.partial(offered_qos, self.node, topic)
            self._qos_lookups[topic] = lookup
        return lookup

    # -- ticks, requests, parameter changes -----------------------------------------------------

    def live_event(self, record: Callable[[], None], run: Callable[[], T]) -> T:
        """Run a user callback (a tick, a request, a parameter change) as a live event: under
        the lock; where events are logged, its record written first (write-ahead) and its
        clock readings logged; a raise remembered (no checkpoint at exit after it)."""
        with self.lock:
            clock = self.clock
            if clock is not None:
                record()
                clock.begin_live()
            try:
                return run()
            except BaseException:
                self.callback_failed = True
                raise
            finally:
                if clock is not None:
                    clock.end()
                self.progress += 1

    def replayed_event(self, event_ns: int, readings: list[Reading], run: Callable[[], T]) -> T:
        """Run a logged tick, request or parameter change again, under the lock, its clocks
        reading what they read live."""
        clock = self.clock
        assert clock is not None  # these are logged only where clocks are
        with self.lock:
            clock.begin_replay(event_ns, readings)
            try:
                return run()
            finally:
                clock.end()
                self.progress += 1

    def write_record(self, record: str, at_ns: int, value_ns: int, detail: int,
                     data: bytes | None = None,
                     record_type: str = protocol.EVENT_RECORD_TYPE) -> None:
        """Log a tick (``detail``: the timer's index), a clock reading (its clock type), a
        request or a parameter change (``data``)."""
        writer = self._segments.segment()
        try:
            writer.write(record, record_type, at_ns, value_ns, detail,
                         protocol.pack_time_record(value_ns) if data is None else data)
        except LogError as err:
            self._error(f'cannot log {record}: {err}')

    def _log_reading(self, reading: Reading) -> None:
        self.write_record(protocol.CLOCK_RECORD, reading.at_ns, reading.value_ns,
                          reading.clock_type)

    def _readings_unrecorded(self) -> None:
        self._error(f'a callback read its clocks more than {event_clock.MAX_READINGS_PER_EVENT} '
                    'times in one event: the rest are not logged, and a replay of that event '
                    'reads them from the event\'s time')

    def count_clock_fallbacks(self) -> None:
        """Replayed clock readings that had no recorded value, into ``stats`` (at release)."""
        if self.clock is not None:
            self.stats['clock_fallbacks'] = self.clock.fallbacks
