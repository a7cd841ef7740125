"""What a supervised node (:class:`~.managed_node.ManagedNode`) needs from its supervisor.

The supervisor's per-node decisions (crash, hang, backoff, give-up, recovery steps, the release
gate) run in ``ManagedNode``, driven by three entry points on the main thread: ``on_exit``,
``on_status`` and ``tick``; the heartbeat's in ``watchdog.Watchdog`` and the recovery steps in
``recovery.Recovery``, which it drives. Everything they reach outside themselves goes through
this protocol: the clock, the heartbeat reader, the launcher, the event log, the safe state,
the ring, the status socket's address, and the node's shadow-topic writers (made by the ROS
side, which also serves the release gate's service and calls ``ManagedNode.on_gate_call``). The
real :class:`~.supervisor.Supervisor` provides them;
tests/supervisor/fake_supervisor.py provides fakes, so those decisions are unit-tested without
a ROS process (tests/supervisor/test_managed_node.py, tests/supervisor/test_watchdog.py), as
supervisord tests its process logic.
"""

from __future__ import annotations

import queue
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Protocol

from rosbags.interfaces import Qos

from ..log import LogEntry
from ..protocol import InputSpec
from .config import SupervisorConfig
from .process import Launcher


class EventSink(Protocol):
    """``events.jsonl``, /rory/events and whatever else listens."""

    def write(self, kind: str, node: str, **fields: Any) -> None:
        """Record one event."""
        ...


class SafetyPort(Protocol):
    """The safe state, held from a node's S1 until its S4 (``safety.SafeState``)."""

    def hold(self, node_id: str) -> None:
        """Hold it for this node (published at once if no one held it)."""
        ...

    def release(self, node_id: str) -> None:
        """This node no longer needs it (released when no node does)."""
        ...


class RingSink(Protocol):
    """Where an activated ring delivers: first its backlog, as one batch, then each message."""

    def add_backlog(self, entries: list[LogEntry]) -> None:
        """What the ring held at activation, in receive order."""

    def add(self, entry: LogEntry) -> None:
        """One message taken after the backlog (called from the ring's thread)."""


class Capture(list[LogEntry]):
    """A sink that keeps everything, in order (the supervisor's early capture of a stalled
    node's inputs; tests)."""

    def add_backlog(self, entries: list[LogEntry]) -> None:
        self.extend(entries)

    def add(self, entry: LogEntry) -> None:
        self.append(entry)


class RingTopicPort(Protocol):
    """The ring's reader of one input of a node (``ring.RingTopic``)."""

    @property
    def spec(self) -> InputSpec:
        """The input it reads, with the node's QoS."""
        ...

    def publisher_count(self) -> int:
        """Publishers the reader is matched with."""
        ...


class RingPort(Protocol):
    """The supervisor's own readers of one node's inputs (``ring.Ring``, made of rclpy
    readers; a fake in the unit tests): passive until a crash activates them."""

    @property
    def topics(self) -> Mapping[str, RingTopicPort]:
        """Its reader of each input topic."""
        ...

    @property
    def active_topics(self) -> set[str]:
        """Topics taken as they come."""
        ...

    def ensure(self, specs: Iterable[InputSpec]) -> None:
        """Have a reader for each input."""
        ...

    def publisher_count(self, topic: str) -> int:
        """Publishers the reader of ``topic`` is matched with."""
        ...

    def publisher_counts(self) -> dict[str, int]:
        """Matched publishers per topic."""
        ...

    def offered_qos(self, topic: str) -> list[Qos]:
        """The QoS the topic's publishers offer."""
        ...

    def activate(self, sink: RingSink, before: list[LogEntry] | None = None) -> None:
        """Hand ``sink`` what the readers hold, then each new message."""
        ...

    def deactivate(self, topic: str | None = None) -> None:
        """Make one topic (or all) passive again."""
        ...


class EnvelopePort(Protocol):
    """Where the supervisor sends a node's envelopes (``protocol.SignedPublisher`` on the
    node's shadow topic; a recorder in the unit tests)."""

    def publish(self, raw: bytes) -> None:
        """Send one envelope (packed, unsigned: the port signs it)."""
        ...


class SupervisorPorts(Protocol):
    """The supervisor as a managed node sees it."""

    @property
    def config(self) -> SupervisorConfig:
        """The whole configuration (store, folder, every node)."""
        ...

    @property
    def clock(self) -> Callable[[], float]:
        """Monotonic seconds."""
        ...

    @property
    def launcher(self) -> Launcher:
        """Starts node processes."""
        ...

    @property
    def events_log(self) -> EventSink:
        """Where events go."""
        ...

    @property
    def events(self) -> queue.SimpleQueue[Any]:
        """The main loop's queue (child exits, releases, gate calls)."""
        ...

    @property
    def safety(self) -> SafetyPort:
        """The safe state."""
        ...

    @property
    def channel(self) -> str:
        """The namespace of the topics between supervisor and nodes (``/rory``)."""
        ...

    @property
    def secret(self) -> bytes:
        """This run's key: envelopes and statuses are signed with it."""
        ...

    @property
    def status_address(self) -> str:
        """Where the nodes send their statuses (inbox.py), for their environment."""
        ...

    def read_beat(self, slot: Path) -> int | None:
        """A node's last heartbeat on the clock's scale, in ns; None before its first."""
        ...

    def make_ring(self, node_id: str) -> RingPort:
        """A ring for one node's inputs."""
        ...

    def open_shadow_topic(self, node_id: str, incarnation: int) -> EnvelopePort:
        """A writer on the shadow topic of this incarnation of the node (``protocol.replay_topic``);
        the node's earlier writers wait to be retired."""
        ...

    def retire_shadow_topics(self, node_id: str) -> None:
        """Destroy the node's earlier writers (all but the newest): no replay streams on them
        any more."""
        ...

    def post_status(self, text: str) -> None:
        """Queue a status message (from the inbox's thread)."""
        ...
