"""The supervisor's own readers of a node's inputs: what covers the gap a crash opens.

A node logs every message it applies, so its log ends where it died. What it had received but
not yet applied, and everything published while it is down, would be lost; the *ring* holds it.
For each input topic of a supervised node the supervisor keeps a reader with the node's QoS and
a keep-last history of :func:`~rory_runtime.protocol.ring_depth` messages.

Passive, the ring costs next to nothing: its readers belong to rclpy nodes that no executor
spins, so DDS keeps the last N messages and no Python runs per message (measured: a passive
reader 0.4% of a core at 60 msg/s against 2.3% for a spinning one). At a crash the ring is
*activated*: everything it holds is taken at once, then new messages are taken as they come,
until the node's live subscription has taken over that topic again.

The ring's nodes share the supervisor's rclpy context, and so its DDS participant (rclpy has one
participant per context). A participant of its own cost an idle supervisor 8 more threads,
2 MB of PSS and 0.27 % of a core (0.70 against 0.43 %: ``python -m
rory_eval.ring_participant_bench``), and every other participant on the robot one more peer to
announce to and track. Only the ring's own executor, on its own thread, ever spins them.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rosbags.interfaces import Qos

from ..log import LogEntry
from ..msgtypes import get_message_class
from ..protocol import InputSpec, message_id, ring_depth
from ..qos import offered_qos
from ..threads import name_this_thread

_logger = logging.getLogger('rory.supervisor')

Sink = Callable[[LogEntry], None]


class RingContext:
    """The rclpy context, executor and thread shared by all rings of one supervisor.

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
        self.executor = SingleThreadedExecutor(context=self.context)
        self._running = True
        self._thread = threading.Thread(target=self._spin, name='rory-ring', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        name_this_thread('rory-ring')
        while self._running and self.context.ok():
            try:
                # Woken by work and by shutdown(); the timeout only re-checks the flag.
                self.executor.spin_once(timeout_sec=1.0)
            except Exception:
                if self._running:
                    _logger.exception('[rory] ring executor error')

    def shutdown(self) -> None:
        """Stop the thread and the context."""
        self._running = False
        self.executor.wake()
        self._thread.join(timeout=2.0)
        self.executor.shutdown(timeout_sec=1.0)
        if self._owns_context and self.context.ok():
            self.context.try_shutdown()


class RingTopic:
    """The supervisor's reader of one input topic of one node."""

    def __init__(self, ring_ctx: RingContext, node_id: str, index: int, spec: InputSpec) -> None:
        self.spec = spec
        self.depth = ring_depth(spec)
        self._ctx = ring_ctx
        self._msg_type = get_message_class(spec.msgtype)
        # One rclpy node per topic, so that activating a topic means adding just its node to the
        # executor; the other topics stay passive.
        self.node = Node(f'_rory_ring_{node_id}_{index}', context=ring_ctx.context)
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
        # rclpy's annotation omits the (msg, info) form; it checks the signature at run time.
        on_message: Any = self._on_message
        self.sub: Subscription = self.node.create_subscription(
            self._msg_type, spec.topic, on_message, qos, raw=True
        )
        # Entries taken while active; with what DDS still holds, they are "the last N".
        self.retained: deque[LogEntry] = deque(maxlen=self.depth)
        self._sink: Sink | None = None
        self._lock = threading.Lock()
        self.active = False

    def _entry(self, raw: bytes, info: dict[str, Any]) -> LogEntry:
        source_ns, seq = message_id(info)
        return LogEntry(
            topic=self.spec.topic,
            msgtype=self.spec.msgtype,
            recv_ns=int(info['received_timestamp']),
            source_ns=source_ns,
            seq=seq,
            data=bytes(raw),
        )

    def _on_message(self, raw: bytes, info: dict[str, Any]) -> None:
        entries = [self._entry(raw, info)]
        with self._lock:
            # Take everything already waiting, not one message per executor round (a round
            # rebuilds the wait set, many times the cost of a take), so the reader's history
            # is emptied as soon as this thread runs. It does not save a burst sent faster
            # than Python takes (a publisher catching up after a stall): what exceeds the
            # history is dropped, oldest first, by DDS itself; R's sequence check reports it.
            entries.extend(self._take_waiting())
            self.retained.extend(entries)
            sink = self._sink
        if sink is not None:
            for entry in entries:
                sink(entry)

    def _take_waiting(self) -> list[LogEntry]:
        """Everything DDS holds for this reader now, oldest first (caller holds the lock)."""
        taken: list[LogEntry] = []
        with self.sub.handle:
            while True:
                message = self.sub.handle.take_message(self._msg_type, True)
                if message is None:
                    return taken
                raw, info = message
                taken.append(self._entry(raw, info))

    def publisher_count(self) -> int:
        """Publishers this reader is matched with."""
        return self.sub.get_publisher_count()

    def activate(self, sink: Sink) -> list[LogEntry]:
        """Take everything held now; new messages go to ``sink`` from then on.

        Returns:
            What the ring held (retained entries and DDS's history), in receive order. The
            caller must deliver it before anything ``sink`` receives: see :meth:`Ring.activate`.
        """
        with self._lock:
            held = list(self.retained)
            taken = self._take_waiting()
            self.retained.extend(taken)
            held.extend(taken)
            self._sink = sink
        if not self.active:
            self.active = True
            self._ctx.executor.add_node(self.node)
        held.sort(key=lambda e: e.recv_ns)
        return held

    def deactivate(self) -> None:
        """Back to passive: DDS keeps the history again."""
        with self._lock:
            self._sink = None
        if self.active:
            self.active = False
            self._ctx.executor.remove_node(self.node)

    def destroy(self) -> None:
        """Remove the reader."""
        self.deactivate()
        self.node.destroy_node()


class Ring:
    """All ring readers of one supervised node."""

    def __init__(self, ring_ctx: RingContext, node_id: str) -> None:
        self._ctx = ring_ctx
        self.node_id = node_id
        self.topics: dict[str, RingTopic] = {}
        self._order = threading.Lock()
        self._sink: Sink | None = None

    def ensure(self, specs: Iterable[InputSpec]) -> None:
        """Have a reader for each input (a changed type or QoS replaces the reader)."""
        for spec in specs:
            current = self.topics.get(spec.topic)
            if current is not None and current.spec == spec:
                continue
            if current is not None:
                current.destroy()
            self.topics[spec.topic] = RingTopic(self._ctx, self.node_id, len(self.topics), spec)

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

    def activate(self, sink: Sink, before: list[LogEntry] | None = None) -> None:
        """Activate every topic: ``sink`` gets what they held, in receive order, then each new
        message as it comes.

        ``before``: entries an earlier activation delivered into this list (an early capture);
        they go to ``sink`` first, read under the lock that the delivery thread takes too, so
        none is missed between the two sinks. Repeats of them in what the ring holds reach
        ``sink`` again (the recovery log drops known identities).

        The ring's executor thread may take a new message before the backlog is delivered;
        ``_deliver`` waits on the same lock, so nothing overtakes the backlog (under load it
        did: a message applied before the one published just ahead of it).
        """
        with self._order:
            self._sink = sink
            held: list[LogEntry] = list(before or ())
            for topic in self.topics.values():
                held.extend(topic.activate(self._deliver))
            held.sort(key=lambda e: e.recv_ns)
            for entry in held:
                sink(entry)

    def _deliver(self, entry: LogEntry) -> None:
        with self._order:
            if self._sink is not None:
                self._sink(entry)

    def deactivate(self, topic: str | None = None) -> None:
        """Make one topic (or all) passive again."""
        targets = self.topics.values() if topic is None else [self.topics[topic]]
        for t in targets:
            t.deactivate()

    @property
    def active_topics(self) -> set[str]:
        """Topics currently taken as they come."""
        return {name for name, t in self.topics.items() if t.active}
