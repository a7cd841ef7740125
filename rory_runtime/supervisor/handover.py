"""A node's handover to a new process: from its HELLO to its release.

HELLO -> the restore's verdict (a stale checkpoint under ``on_stale: refuse`` stops here) ->
SYNC, sent again until SYNCED proves the shadow path -> the replay (S3; a fresh start waits
until the ring matches the node's publishers and sends RELEASE) -> RELEASED -> at a release
gate, GATED until it is called or times out, then OPEN until OPENED -> S4 and the ``recovered``
event. :class:`Handover` takes these steps for ``ManagedNode`` (managed_node.py) and tells it
what follows as a :class:`Step`: the state to enter, what to do once it is in it, or why to
give up. It never changes the node's state and calls nothing of ``ManagedNode``: what it
reaches is passed to it (the clock, the event log, the gate, the node's record and gap
reports, the main loop's queue), and the process, its recovery and the ring on each call.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..freshness import Verdict
from ..protocol import HelloStatus, OpenedStatus, ReleasedStatus
from .config import NodeConfig
from .gate import SYNC_PERIOD, Gate
from .health import NodeRecord
from .incarnation import Incarnation
from .loop_events import Released
from .ports import EventSink, RingPort
from .recovery import GapReports, Recovery, say_recovered
from .states import LOG_PREFIX, NodeState

_logger = logging.getLogger('rory.supervisor')

_RECOVERING = (NodeState.RESTORING, NodeState.REPLAYING)


@dataclass(frozen=True)
class Step:
    """What the node does next: enter ``state`` (if any) for ``reason``, then run ``then``
    (what the handover says or sends once the state is entered), then end its recovery if
    ``end_recovery``; or, with ``give_up``, give up for that reason (``fields`` go to the
    ``fatal`` event)."""

    state: NodeState | None = None
    reason: str = ''
    then: Callable[[], None] | None = None
    end_recovery: bool = False
    give_up: str | None = None
    fields: dict[str, Any] = field(default_factory=dict)


def stale_refusal(verdict: Verdict) -> str:
    """Why a node whose checkpoint holds a stale variable under ``on_stale: refuse`` is not
    started (freshness.py): an operator decides."""
    age = 'unknown' if verdict.age_s is None else f'{verdict.age_s:.1f} s'
    return (f'checkpoint too old for {", ".join(verdict.refused)} '
            f'(age {age} on the {verdict.clock} clock; on_stale: refuse): not '
            'started, the safe state is held; start it fresh (rory supervise --fresh) or '
            'raise max_age in keyvars.yaml')


class Handover:
    """The handover of one node's processes, one at a time.

    Args:
        cfg: The node's supervisor.yaml entry (its method, replay pace).
        clock: Monotonic seconds.
        events: The event log.
        gate: Its release gate, if it has one.
        record: What its /diagnostics say (the restore's verdict, the last recovery).
        gaps: Its input gaps, each said once (at S4 among them).
        post: Puts an event on the main loop's queue (the replay's :class:`Released`).
        next_segment: The number of its next log segment (RELEASE after a fresh start).
    """

    def __init__(self, cfg: NodeConfig, clock: Callable[[], float], events: EventSink,
                 gate: Gate | None, record: NodeRecord, gaps: GapReports,
                 post: Callable[[Released], None], next_segment: Callable[[], int]) -> None:
        self.node_id = cfg.name
        self.cfg = cfg
        self.gate = gate
        self._clock = clock
        self._events = events
        self._record = record
        self._gaps = gaps
        self._post = post
        self._next_segment = next_segment

    def hello(self, current: Incarnation, hello: HelloStatus, state: NodeState,
              rec: Recovery | None) -> Step:
        """The process's HELLO (kept in ``current``), after the ring has joined: the restore's
        verdict, then SYNC for a method that logs (in ARMING or REPLAYING)."""
        if hello.restored is not None:
            verdict = self._record.freshness = hello.restored.freshness
            if verdict.refused:
                reason = stale_refusal(verdict)
                _logger.error('%s %s: %s', LOG_PREFIX, self.node_id, reason)
                return Step(give_up=reason, fields={'freshness': verdict.to_json()})
        if rec is not None:
            rec.on_hello(float(hello.restore_ms))
            if self.cfg.method.checkpoints and hello.refused and hello.restored is None:
                # Logs are pruned up to the older kept checkpoint's cut: with both refused,
                # replay cannot rebuild what they held. Say so; never pretend.
                _logger.error(
                    '%s %s: every checkpoint was refused; the state is rebuilt only from the log '
                    'that remains and may be incomplete', LOG_PREFIX, self.node_id,
                )
        if not self.cfg.method.logs:
            return Step()

        def sync() -> None:
            current.send_sync(self._clock())

        if state == NodeState.STARTING:
            return Step(NodeState.ARMING, 'waiting for RORY readers to match', then=sync)
        if state == NodeState.RESTORING:
            return Step(NodeState.REPLAYING, f'replay after segment {current.restored_cut()}',
                        then=sync)
        return Step(then=sync)

    def synced(self, current: Incarnation, state: NodeState, rec: Recovery | None) -> None:
        """The first SYNCED of ``current``: the replay starts (S3) if it recovers."""
        if state == NodeState.REPLAYING and rec is not None:
            assert current.hello is not None and current.replay_pub is not None
            incarnation, post, node_id = current.number, self._post, self.node_id
            rec.s3_replay(
                current.replay_pub, incarnation, current.restored_cut(),
                current.replay_pace(self.cfg.replay),
                lambda sent: post(Released(node_id, incarnation, sent)),
            )

    def released(self, current: Incarnation, stats: ReleasedStatus, state: NodeState,
                 rec: Recovery | None) -> Step:
        """RELEASED: the process runs; a recovering node waits at its gate, if it has one."""
        current.running_since = self._clock()
        gate = self.gate
        if state in _RECOVERING and rec is not None and gate is not None:
            # Caught up and live, outputs muted: wait for the release call (or the timeout).
            return Step(NodeState.GATED, gate.enter(stats), then=lambda: self._gated(gate))
        return self.finish(current, stats, state, rec)

    def _gated(self, gate: Gate) -> None:
        self._events.write('gated', self.node_id, service=gate.service,
                           timeout=gate.config.timeout, on_timeout=gate.config.on_timeout)
        if gate.called:
            gate.open('called before the node had caught up')

    def opened(self, current: Incarnation, status: OpenedStatus, state: NodeState,
               rec: Recovery | None) -> Step:
        """OPENED: the gate opened and the node unmuted; the release the gate held ends."""
        gate = self.gate
        if state != NodeState.GATED or gate is None or gate.held is None:
            return Step()
        # What the node published while it waited was muted: counted, never sent.
        self._events.write('gate_opened', self.node_id, reason=gate.reason, muted=status.muted)
        stats = gate.opened()
        assert stats is not None
        return self.finish(current, stats, state, rec)

    def finish(self, current: Incarnation, stats: ReleasedStatus, state: NodeState,
               rec: Recovery | None) -> Step:
        """The release: S4 for a recovery (RUNNING, then the ``recovered`` event, and the
        recovery ends unless the ring still relays), RUNNING for a first start."""
        if rec is not None and state in (*_RECOVERING, NodeState.GATED):
            gate_ms, gate_reason = (None, None) if self.gate is None else self.gate.finish()
            timing = rec.s4_release()
            self._record.last_recovery = (timing['total_ms'], self._clock())
            cfg = self.cfg
            pace = current.replay_pace(cfg.replay).value if cfg.method.logs else None

            def say() -> None:
                say_recovered(rec, self.node_id, self._events, self._gaps, method=cfg.method,
                              incarnation=current.number, timing=timing, stats=stats,
                              pace=pace, freshness=self._record.freshness, gate_ms=gate_ms,
                              gate_reason=gate_reason)

            return Step(NodeState.RUNNING, 'released', then=say,
                        end_recovery=rec.ring is None or not rec.ring.active_topics)
        if state in (NodeState.STARTING, NodeState.ARMING):
            return Step(NodeState.RUNNING, 'released')
        return Step()

    def on_call(self, state: NodeState) -> tuple[bool, str]:
        """A call on the release gate service: the answer to give."""
        if self.gate is None:
            return False, f'{self.node_id}: no release gate'
        return self.gate.on_call(state)

    def drop(self) -> None:
        """The node is given up: the gate holds no release any more."""
        if self.gate is not None:
            self.gate.held = None

    def tick(self, now: float, current: Incarnation, state: NodeState,
             ring: RingPort | None) -> Step:
        """SYNC again until SYNCED, RELEASE once the ring matches (a fresh start), OPEN again
        until OPENED; a gate's timeout."""
        if state == NodeState.GATED and self.gate is not None:
            given_up = self.gate.tick(now)
            if given_up is not None:
                return Step(give_up=given_up)
        elif state in (NodeState.ARMING, NodeState.REPLAYING):
            if current.synced_counts is None and now - current.sync_sent >= SYNC_PERIOD:
                current.send_sync(self._clock())
            elif state == NodeState.ARMING and not current.release_sent and current.armed(ring):
                current.send_release(self._next_segment())  # once; RELEASED answers
        return Step()
