"""The supervisor's process model: one explicit state per supervised node.

Every change goes through :meth:`NodeStateMachine.change_state`, which refuses an edge that is
not in :data:`TRANSITIONS`, logs the change with the stable prefix ``[rory] <node>:`` and hands
an event to whoever listens (the log, tests, later /rory/events).

Normal life::

    STOPPED -> STARTING -> ARMING -> RUNNING

``ARMING`` (methods that log) waits until the supervisor's own readers of the node's inputs are
matched, so that a crash from then on loses nothing. A crash::

    RUNNING -> CRASHED (S1 safe state, S2 isolation) -> RESTORING (S3: restart + restore)
            -> REPLAYING (S3: replay) -> RUNNING (S4 release)

with ``BACKOFF`` between CRASHED and RESTORING in a crash loop and ``FATAL`` when it gives up.
A node with a release gate waits after its release, live but with its outputs muted and the
safe state held, for a call on ``/rory/<node>/release`` (or its timeout)::

    REPLAYING (or RESTORING) -> GATED -> RUNNING (S4)    or    GATED -> FATAL

A checkpoint whose stale variable's rule is ``refuse`` (freshness.py) gives up at once:
``RESTORING -> FATAL``.
A clean exit (status 0) is the node finishing: ``EXITED``, not a crash. After a supervisor
that did not stop cleanly (killed, power cut), the next one resumes the node from the store::

    STOPPED -> RESTORING (S1, S2, S3 from the checkpoints and logs on disk) -> ...
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

LOG_PREFIX: Final = '[rory]'


class NodeState(enum.StrEnum):
    """Where a supervised node is in its life."""

    STOPPED = 'STOPPED'
    STARTING = 'STARTING'
    ARMING = 'ARMING'
    RUNNING = 'RUNNING'
    CRASHED = 'CRASHED'
    BACKOFF = 'BACKOFF'
    RESTORING = 'RESTORING'
    REPLAYING = 'REPLAYING'
    GATED = 'GATED'
    EXITED = 'EXITED'
    FATAL = 'FATAL'
    STOPPING = 'STOPPING'


S = NodeState
TRANSITIONS: Final[dict[NodeState, frozenset[NodeState]]] = {
    S.STOPPED: frozenset({S.STARTING, S.RESTORING}),
    S.STARTING: frozenset({S.ARMING, S.RUNNING, S.CRASHED, S.EXITED, S.STOPPING}),
    S.ARMING: frozenset({S.RUNNING, S.CRASHED, S.EXITED, S.STOPPING}),
    S.RUNNING: frozenset({S.CRASHED, S.EXITED, S.STOPPING}),
    S.CRASHED: frozenset({S.BACKOFF, S.RESTORING, S.FATAL, S.STOPPING}),
    S.BACKOFF: frozenset({S.RESTORING, S.STOPPING}),
    S.RESTORING: frozenset({S.REPLAYING, S.RUNNING, S.GATED, S.CRASHED, S.EXITED, S.FATAL,
                            S.STOPPING}),
    S.REPLAYING: frozenset({S.RUNNING, S.GATED, S.CRASHED, S.EXITED, S.STOPPING}),
    S.GATED: frozenset({S.RUNNING, S.CRASHED, S.EXITED, S.FATAL, S.STOPPING}),
    S.EXITED: frozenset({S.STOPPING}),
    S.FATAL: frozenset({S.STOPPING}),
    S.STOPPING: frozenset({S.STOPPED}),
}

RECOVERING: Final = frozenset({S.CRASHED, S.BACKOFF, S.RESTORING, S.REPLAYING, S.GATED})
"""States between a crash and the release that ends its recovery."""


class IllegalTransition(RuntimeError):
    """A change of state the process model does not allow: a bug in the supervisor."""


@dataclass(frozen=True)
class StateEvent:
    """One change of state, as emitted to listeners."""

    node: str
    old: NodeState
    new: NodeState
    reason: str
    monotonic: float


class NodeStateMachine:
    """The state of one supervised node.

    Args:
        node: The node's id.
        logger: Where changes are logged.
        clock: Monotonic clock (injected so tests can drive it).
        listeners: Called with every StateEvent.
    """

    def __init__(
        self,
        node: str,
        logger: logging.Logger,
        clock: Callable[[], float] = time.monotonic,
        listeners: list[Callable[[StateEvent], None]] | None = None,
    ) -> None:
        self.node = node
        self.state = NodeState.STOPPED
        self.since = clock()
        self._logger = logger
        self._clock = clock
        self.listeners: list[Callable[[StateEvent], None]] = list(listeners or [])

    def change_state(self, new: NodeState, reason: str = '') -> StateEvent:
        """Move to ``new`` if the model allows it; log and emit the change.

        Raises:
            IllegalTransition: The edge is not in TRANSITIONS.
        """
        old = self.state
        if new not in TRANSITIONS[old]:
            raise IllegalTransition(f'{self.node}: {old} -> {new} is not allowed ({reason})')
        self.state = new
        self.since = self._clock()
        event = StateEvent(self.node, old, new, reason, self.since)
        suffix = f' ({reason})' if reason else ''
        self._logger.info('%s %s: %s -> %s%s', LOG_PREFIX, self.node, old, new, suffix)
        for listener in self.listeners:
            listener(event)
        return event

    @property
    def recovering(self) -> bool:
        """Whether a crash is being recovered."""
        return self.state in RECOVERING
