"""The supervisor's readers of one node's inputs.

The node names its inputs in its HELLO, and each subscription it makes later in an INPUTS
status; for a method that logs, the supervisor's ring (``RingPort``, made by the ROS side:
``SupervisorPorts.make_ring``) reads every one of them, passive until a crash activates it for
the recovery's R. While a running node's heartbeat is late the ring keeps what it takes
(``recovery.EarlyCapture``, S2 early). :class:`InputReaders` keeps these for ``ManagedNode``,
which tells it what the node said and what the watchdog found.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable

from ..protocol import InputSpec
from .ports import Capture, EventSink, RingPort
from .recovery import EarlyCapture
from .states import LOG_PREFIX
from .watchdog import Beat

_logger = logging.getLogger('rory.supervisor')


class InputReaders:
    """The inputs of one node, and the ring that reads them for a method that logs.

    Args:
        node_id: The node's name.
        logs: Whether its method logs (only then is there a ring).
        make_ring: Makes its ring (once, at its first HELLO).
        events: The event log.
    """

    def __init__(self, node_id: str, logs: bool, make_ring: Callable[[str], RingPort],
                 events: EventSink) -> None:
        self.node_id = node_id
        self.logs = logs
        self._make_ring = make_ring
        self._events = events
        self.specs: list[InputSpec] = []  # as the node last named them
        self._ring: RingPort | None = None
        self.early = EarlyCapture(node_id)  # what the ring took since the beat went late

    @property
    def ring(self) -> RingPort | None:
        """The ring, for a method that logs, once the node has named its inputs."""
        return self._ring if self.logs else None

    def named(self, specs: Iterable[InputSpec]) -> RingPort | None:
        """A HELLO named the node's inputs: the ring (made at the first) reads each."""
        self.specs = list(specs)
        if not self.logs:
            return None
        if self._ring is None:
            self._ring = self._make_ring(self.node_id)
        self._ring.ensure(self.specs)
        return self._ring

    def added(self, specs: Iterable[InputSpec]) -> None:
        """An INPUTS status: the node made a subscription after HELLO; the ring reads that
        topic too."""
        inputs = list(specs)
        added = sorted({i.topic for i in inputs} - {i.topic for i in self.specs})
        self.specs = inputs
        self._events.write('inputs', self.node_id, added=added)
        _logger.info('%s %s: new input(s) %s', LOG_PREFIX, self.node_id, ', '.join(added))
        if self.ring is not None:
            self.ring.ensure(self.specs)

    def on_beat(self, beat: Beat) -> None:
        """The watchdog's view of the heartbeat of a running node that is not recovering:
        keep its inputs while the beat is late (S2 early)."""
        if self.ring is not None:
            self.early.on_beat(self.ring, beat)

    def take_early(self) -> Capture | None:
        """What the ring kept since the beat went late, for the recovery of a crash."""
        return self.early.take()

    def stop_early(self, why: str) -> None:
        """Drop what the ring kept, if anything, and make it passive again."""
        self.early.stop(self.ring, why)
