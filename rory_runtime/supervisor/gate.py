"""A node's release gate (supervisor.yaml ``release_gate``: ``config.ReleaseGate``).

A recovered node that has caught up stays GATED: live, its outputs muted, the safe state held,
until ``/rory/<node>/release`` is called (a ``std_srvs/Trigger`` service the ROS side serves:
it asks the main loop, which calls ``ManagedNode.on_gate_call``) or the gate's timeout acts.
:class:`Gate` keeps what the gate holds and decides; the node changes its state and ends S4.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from ..protocol import ReleasedStatus
from .config import ReleaseGate
from .states import LOG_PREFIX, NodeState

_logger = logging.getLogger('rory.supervisor')

SYNC_PERIOD = 0.05
"""Seconds between SYNC envelopes until the node answers (DDS discovery of a new process), and
between OPEN envelopes until it says OPENED."""

_CALL_AHEAD = frozenset({NodeState.CRASHED, NodeState.BACKOFF, NodeState.RESTORING,
                         NodeState.REPLAYING})
"""States in which a call on the gate opens it as soon as the node reaches it."""


class Gate:
    """The release gate of one node.

    Args:
        node_id: The node's name, for its log lines and answers.
        config: Its ``release_gate`` entry.
        service: The service that opens it.
        clock: Monotonic seconds.
        send_open: Sends OPEN to the node's current process (on its shadow topic).
    """

    def __init__(self, node_id: str, config: ReleaseGate, service: str,
                 clock: Callable[[], float], send_open: Callable[[], None]) -> None:
        self.node_id = node_id
        self.config = config
        self.service = service
        self._clock = clock
        self._send_open = send_open
        # The RELEASED stats held while GATED, since when, when the gate times out, whether
        # it was called before the node reached it, OPEN sent (and when), why it opened.
        self.held: ReleasedStatus | None = None
        self.since: float | None = None
        self.deadline: float | None = None
        self.called = False
        self.open_sent = False
        self.open_sent_at = 0.0
        self.reason = ''

    def enter(self, stats: ReleasedStatus) -> str:
        """Caught up and live, outputs muted: hold ``stats`` until the gate opens. The reason
        of the GATED state."""
        timeout = self.config.timeout
        self.held = stats
        self.since = self._clock()
        self.open_sent = False
        self.deadline = None if timeout is None else self.since + timeout
        limit = ('' if timeout is None
                 else f', {self.config.on_timeout.replace("_", " ")} after {timeout:g} s')
        return (f'caught up; outputs muted and the safe state held until {self.service} is '
                f'called{limit}')

    def open(self, why: str) -> None:
        """Tell the node to unmute; S4 ends when it says OPENED."""
        if self.open_sent:
            return
        self.open_sent = True
        self.reason = why
        _logger.info('%s %s: release gate opened (%s)', LOG_PREFIX, self.node_id, why)
        self.send_open()

    def send_open(self) -> None:
        # Sent again each SYNC_PERIOD until OPENED: under restart and checkpoint no SYNC has
        # proved the shadow path, and an OPEN sent before the node's reader matched is lost.
        self.open_sent_at = self._clock()
        self._send_open()

    def on_call(self, state: NodeState) -> tuple[bool, str]:
        """A call on the service while the node is in ``state``: the answer to give."""
        if state == NodeState.GATED:
            self.open(f'{self.service} called')
            return True, f'{self.node_id}: released'
        if state in _CALL_AHEAD:
            self.called = True
            return (True, f'{self.node_id}: {state.value.lower()}; released as soon as it has '
                    'caught up')
        return False, f'{self.node_id}: {state.value}, no recovery waits for release'

    def opened(self) -> ReleasedStatus | None:
        """The node said OPENED: the stats held (None if none was)."""
        stats, self.held = self.held, None
        return stats

    def finish(self) -> tuple[float | None, str | None]:
        """S4: how long the node was gated (ms) and why the gate opened; the gate is reset."""
        gate_ms = None if self.since is None else round((self._clock() - self.since) * 1000.0, 1)
        reason = self.reason or None
        self.since, self.deadline, self.called = None, None, False
        self.open_sent, self.reason = False, ''
        return gate_ms, reason

    def tick(self, now: float) -> str | None:
        """While GATED: OPEN again until OPENED; at the timeout, open it (``on_timeout:
        release``) or say why the supervisor gives up (``give_up``)."""
        if self.open_sent and now - self.open_sent_at >= SYNC_PERIOD:
            self.send_open()
        if self.deadline is not None and now >= self.deadline and not self.open_sent:
            timeout = self.config.timeout
            if self.config.on_timeout == 'release':
                self.open(f'no call within {timeout:g} s; on_timeout: release')
            else:
                return (f'no call on {self.service} within {timeout:g} s; on_timeout: give_up; '
                        'the safe state is held')
        return None
