"""The supervisor's own readers of a node's inputs: what covers the gap a crash opens.

A node logs every message it applies, so its log ends where it died. What it had received but
not yet applied, and everything published while it is down, would be lost; the *ring* holds it.
For each input topic of a supervised node the supervisor keeps a reader with the node's QoS and
a keep-last history of :func:`~rory_runtime.protocol.ring_depth` messages. Nodes that read a
topic with the same type, reliability and durability share one reader (:class:`SharedReader`)
whose history is at least as deep as each of theirs; each node is still handed only its own
depth. In a stack most nodes read ``/odom`` and ``/scan``, and every reader costs the
supervisor DDS's receive work per message (docs/performance.md, "The ring: one reader per
topic for the whole stack").

Passive, the ring costs next to nothing: nothing takes from its readers, so DDS keeps the last N
messages and no Python runs per message (measured: a passive reader 0.4% of a core at 60 msg/s
against 2.3% for a spinning one). At a crash the ring is *activated*: everything it holds is
taken at once, then new messages are taken as they come, until the node's live subscription
has taken over that topic again.

The ring takes with :mod:`.rcl_take`, not rclpy's ``take_message``, because it needs each
message's publisher GID: the recovery log keeps, per publisher, only what lies above what the
node logged (docs/architecture.md, "The invariant"). So no rclpy executor spins the ring's
readers; one thread waits on the active ones (:class:`RingContext`).

The ring's nodes share the supervisor's rclpy context, and so its DDS participant (rclpy has one
participant per context). A participant of its own cost an idle supervisor 8 more threads,
2 MB of PSS and 0.27 % of a core (``python -m rory_eval.bench.ring_participant_bench``), and every
other participant on the robot one more peer to announce to and track.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import deque
from collections.abc import Iterable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rosbags.interfaces import Qos

from ..log import LogEntry
from ..msgtypes import get_message_class
from ..protocol import SEQ_MASK, InputSpec, ring_depth
from ..qos import offered_qos
from ..threads import name_this_thread
from .hidden import quiet_node
from .ports import RingSink
from .rcl_take import SerializedTaker, Taken

_logger = logging.getLogger('rory.supervisor')

_WAIT_NS = 1_000_000_000
"""The ring thread is woken by messages and by its guard condition (activation, deactivation,
shutdown); the timeout only re-checks the running flag."""


class RingContext:
    """The rclpy context and the taking thread shared by all rings of one supervisor.

    Args:
        context: the supervisor's context, whose participant the ring's readers join; it stays
            the caller's to shut down. Without one, the ring makes and owns a context of its
            own on ``domain_id`` (tests that run a ring alone).
        domain_id: the domain of an owned context.
    """

    def __init__(self, context: Context | None = None, domain_id: int | None = None) -> None:
        self._owns_context = context is None
        if context is None:
            context = Context()
            rclpy.init(
                context=context,
                domain_id=domain_id,
                signal_handler_options=SignalHandlerOptions.NO,
            )
        self.context = context
        # One hidden node holds every reader, never spun: only its graph queries are used (a
        # node per reader, as the ring had when an executor spun each topic's, was ~16 DDS
        # endpoints each).
        self.node = quiet_node('_rory_ring', context)
        self._active: list[SharedReader] = []
        self._readers: list[SharedReader] = []
        self._lock = threading.Lock()
        self._guard = GuardCondition(None, None, context=context)
        self._running = True
        self._thread = threading.Thread(target=self._spin, name='rory-ring', daemon=True)
        self._thread.start()

    def acquire(self, spec: InputSpec) -> SharedReader:
        """A reader of ``spec``'s topic, type, reliability and durability whose history holds
        at least ``spec``'s ring depth: one that exists, else a new one."""
        depth = ring_depth(spec)
        with self._lock:
            reader = next((r for r in self._readers if r.serves(spec, depth)), None)
            if reader is None:
                reader = SharedReader(self, spec)
                self._readers.append(reader)
            reader.users += 1
            return reader

    def release(self, reader: SharedReader) -> None:
        """One user less; the last one's release removes the reader."""
        with self._lock:
            reader.users -= 1
            if reader.users > 0:
                return
            if reader in self._readers:
                self._readers.remove(reader)
        reader.destroy()

    @property
    def reader_count(self) -> int:
        """DDS readers the ring has, all nodes together."""
        with self._lock:
            return len(self._readers)

    def watch(self, reader: SharedReader) -> None:
        """Take ``reader``'s messages as they come."""
        with self._lock:
            if reader not in self._active:
                self._active.append(reader)
        self._guard.trigger()

    def unwatch(self, reader: SharedReader) -> None:
        """Stop taking ``reader``'s messages (DDS keeps its history again)."""
        with self._lock:
            if reader in self._active:
                self._active.remove(reader)
        self._guard.trigger()

    def _spin(self) -> None:
        name_this_thread('rory-ring')
        while self._running and self.context.ok():
            with self._lock:
                readers = list(self._active)
            try:
                self._wait_and_take(readers)
            except Exception:
                if self._running:
                    _logger.exception('[rory] ring error')

    def _wait_and_take(self, readers: list[SharedReader]) -> None:
        with contextlib.ExitStack() as held:
            handles = []
            for reader in readers:
                try:
                    held.enter_context(reader.sub.handle)
                except InvalidHandle:
                    continue  # destroyed meanwhile
                handles.append(reader)
            held.enter_context(self._guard.handle)
            context_handle: Any = self.context.handle  # rclpy's annotation allows None
            held.enter_context(context_handle)
            wait_set = _rclpy.WaitSet(len(handles), 1, 0, 0, 0, 0, self.context.handle)
            wait_set.clear_entities()
            for reader in handles:
                wait_set.add_subscription(reader.sub.handle)
            wait_set.add_guard_condition(self._guard.handle)
            wait_set.wait(_WAIT_NS)
            if not self._running:
                return
            ready = wait_set.get_ready_entities('subscription')
            for reader in handles:
                if reader.sub.handle.pointer in ready:
                    reader.take_new()

    def shutdown(self) -> None:
        """Stop the thread and the context."""
        self._running = False
        with contextlib.suppress(InvalidHandle):
            self._guard.trigger()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(InvalidHandle):
            self._guard.destroy()
        self.node.destroy_node()
        if self._owns_context and self.context.ok():
            self.context.try_shutdown()


class SharedReader:
    """The supervisor's reader of one input topic, for every node that reads it with the same
    type, reliability and durability and no deeper history (:class:`RingTopic` is one node's
    view of it).

    Its history, with what activations took (:attr:`retained`), is the newest ``depth``
    messages of the topic, whichever node's activation took them; the newest ``d`` of them are
    what a node's own passive reader of depth ``d`` would hold.
    """

    def __init__(self, ring_ctx: RingContext, spec: InputSpec) -> None:
        self.spec = spec
        self.depth = ring_depth(spec)
        self._ctx = ring_ctx
        self.users = 0
        msg_type = get_message_class(spec.msgtype)
        self.node = ring_ctx.node
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.depth,
            reliability=(
                ReliabilityPolicy.RELIABLE if spec.reliable else ReliabilityPolicy.BEST_EFFORT
            ),
            durability=(
                DurabilityPolicy.TRANSIENT_LOCAL
                if spec.transient_local
                else DurabilityPolicy.VOLATILE
            ),
        )
        # Never called: no executor spins this node; the ring takes with rcl_take. (rclpy's
        # annotation omits the (msg, info) form; it checks the signature at run time.)
        never_called: Any = _never_called
        self.sub: Subscription = self.node.create_subscription(
            msg_type, spec.topic, never_called, qos, raw=True
        )
        self._taker = SerializedTaker()
        # Entries taken while active. DDS no longer holds them, so the next activation gets
        # them from here; with what DDS holds, the newest ``depth`` are "the last N".
        self.retained: deque[LogEntry] = deque(maxlen=self.depth)
        # The active views' delivery, in activation order.
        self._delivers: dict[RingTopic, Any] = {}
        self._lock = threading.Lock()

    def serves(self, spec: InputSpec, depth: int) -> bool:
        """Whether a node reading ``spec`` with ring depth ``depth`` can share this reader."""
        mine = self.spec
        return (mine.topic, mine.msgtype, mine.reliable, mine.transient_local) == (
            spec.topic, spec.msgtype, spec.reliable, spec.transient_local) and self.depth >= depth

    def _entry(self, taken: Taken) -> LogEntry:
        return LogEntry(
            topic=self.spec.topic,
            msgtype=self.spec.msgtype,
            recv_ns=taken.received_ns,
            source_ns=taken.source_ns,
            seq=taken.seq & SEQ_MASK,
            data=taken.data,
            publisher=taken.publisher,
        )

    def take_new(self) -> None:
        """Take what DDS holds now and deliver it to each active view (the ring's thread)."""
        with self._lock:
            # Everything waiting, not one message per wait (a wait rebuilds the wait set, many
            # times the cost of a take), so the history is emptied as soon as this thread
            # runs. It does not save a burst sent faster than Python takes (a publisher
            # catching up after a stall): what exceeds the history is dropped, oldest first,
            # by DDS itself; R's sequence check reports it.
            entries = self._take_waiting()
            self.retained.extend(entries)
            delivers = list(self._delivers.values())
        for deliver in delivers:
            for entry in entries:
                deliver(entry)

    def _take_waiting(self) -> list[LogEntry]:
        """Everything DDS holds for this reader now, oldest first (caller holds the lock)."""
        taken: list[LogEntry] = []
        with self.sub.handle:
            while (message := self._taker.take(self.sub.handle)) is not None:
                taken.append(self._entry(message))
        return taken

    def publisher_count(self) -> int:
        """Publishers this reader is matched with."""
        return self.sub.get_publisher_count()

    def activate(self, view: RingTopic, deliver: Any) -> list[LogEntry]:
        """The newest ``view.depth`` messages, in receive order; see :meth:`RingTopic.activate`.
        """
        with self._lock:
            first = not self._delivers
            if first:
                # Nobody takes from DDS while no view is active: what it holds is taken here.
                self.retained.extend(self._take_waiting())
            # Else the ring's thread takes what DDS holds and hands it to every active view,
            # this one included. Taken here, it would reach this view alone: with two nodes
            # struck together, the first one's recovery lost the message the second one's
            # activation took (make test under load).
            held = list(self.retained)
            self._delivers[view] = deliver
            if first:
                self._ctx.watch(self)
        held.sort(key=lambda e: e.recv_ns)
        # Never more than the node's own depth: the node's window of applied identities is
        # sized to absorb that many (protocol.window_size), no more.
        return held[-view.depth:]

    def deactivate(self, view: RingTopic) -> None:
        """``view`` takes no more; with no active view left, back to passive."""
        with self._lock:
            if self._delivers.pop(view, None) is not None and not self._delivers:
                self._ctx.unwatch(self)

    def destroy(self) -> None:
        """Remove the DDS reader (its last user has released it)."""
        with self._lock:
            if self._delivers:
                self._delivers.clear()
                self._ctx.unwatch(self)
            self._taker.close()
        self.node.destroy_subscription(self.sub)


class RingTopic:
    """One supervised node's reader of one input topic: a view of the :class:`SharedReader`
    of that topic and QoS."""

    def __init__(self, ring_ctx: RingContext, spec: InputSpec) -> None:
        self.spec = spec
        self._ctx = ring_ctx
        self.reader = ring_ctx.acquire(spec)
        self.depth = ring_depth(spec)
        self.node = ring_ctx.node
        self.active = False
        self._destroyed = False

    def publisher_count(self) -> int:
        """Publishers the reader is matched with."""
        return self.reader.publisher_count()

    def activate(self, deliver: Any) -> list[LogEntry]:
        """Take everything held now; new messages go to ``deliver`` from then on.

        Returns:
            The newest :attr:`depth` messages the ring has had (taken earlier while active,
            for this node or another that shares the reader, and what DDS holds), in receive
            order: what a reader that was never taken from would hold. (While another node's
            view is active, what DDS holds reaches ``deliver`` instead, as it reaches that
            node's: so both get it.) Older ones were the
            node's long before its crash; keeping them would hand the recovery messages
            applied outside every window it can check (issue 21's duplicates). The caller
            must deliver them before anything ``deliver`` receives: see :meth:`Ring.activate`.
        """
        held = self.reader.activate(self, deliver)
        self.active = True
        return held

    def deactivate(self) -> None:
        """Back to passive for this node."""
        self.reader.deactivate(self)
        self.active = False

    def destroy(self) -> None:
        """This node reads the topic no more (the reader goes with its last user)."""
        if self._destroyed:
            return
        self._destroyed = True
        self.deactivate()
        self._ctx.release(self.reader)


def _never_called(_raw: bytes, _info: Any) -> None:
    raise AssertionError('the ring takes with rcl_take; no executor spins its nodes')


class Ring:
    """All ring readers of one supervised node."""

    def __init__(self, ring_ctx: RingContext, node_id: str) -> None:
        self._ctx = ring_ctx
        self.node_id = node_id
        self.topics: dict[str, RingTopic] = {}
        self._order = threading.Lock()
        self._sink: RingSink | None = None

    def ensure(self, specs: Iterable[InputSpec]) -> None:
        """Have a reader for each input (a changed type or QoS replaces the reader)."""
        for spec in specs:
            current = self.topics.get(spec.topic)
            if current is not None and current.spec == spec:
                continue
            if current is not None:
                current.destroy()
            self.topics[spec.topic] = RingTopic(self._ctx, spec)

    def publisher_count(self, topic: str) -> int:
        """Publishers the reader of ``topic`` is matched with (0 without a reader)."""
        reader = self.topics.get(topic)
        return 0 if reader is None else reader.publisher_count()

    def publisher_counts(self) -> dict[str, int]:
        """Matched publishers per topic."""
        return {topic: t.publisher_count() for topic, t in self.topics.items()}

    def offered_qos(self, topic: str) -> list[Qos]:
        """The QoS the topic's publishers offer, as this ring's reader sees them."""
        reader = self.topics.get(topic)
        return [] if reader is None else offered_qos(reader.node, topic)

    def activate(self, sink: RingSink, before: list[LogEntry] | None = None) -> None:
        """Activate every topic: ``sink`` gets what they held, in receive order, as one backlog,
        then each new message as it comes.

        ``before``: entries an earlier activation delivered (an early capture); they lead the
        backlog, read under the lock that the delivery thread takes too, so none is missed
        between the two sinks. Repeats of them in what the ring holds reach ``sink`` again
        (the recovery log drops known identities).

        The ring's thread may take a new message before the backlog is delivered; ``_deliver``
        waits on the same lock, so nothing overtakes the backlog (under load it did: a message
        applied before the one published just ahead of it).
        """
        with self._order:
            self._sink = sink
            held: list[LogEntry] = list(before or ())
            for topic in self.topics.values():
                held.extend(topic.activate(self._deliver))
            held.sort(key=lambda e: e.recv_ns)
            sink.add_backlog(held)

    def _deliver(self, entry: LogEntry) -> None:
        with self._order:
            if self._sink is not None:
                self._sink.add(entry)

    def deactivate(self, topic: str | None = None) -> None:
        """Make one topic (or all) passive again."""
        targets = self.topics.values() if topic is None else [self.topics[topic]]
        for t in targets:
            t.deactivate()

    @property
    def active_topics(self) -> set[str]:
        """Topics currently taken as they come."""
        return {name for name, t in self.topics.items() if t.active}
