"""One supervised node's decisions (:class:`ManagedNode`), on the supervisor's ports
(ports.py), driven by the main loop: ``on_exit``, ``on_status``, ``on_gate_call`` and
``tick``. No rclpy here: the ROS side (supervisor.py) makes the readers, writers and services
behind the ports. ManagedNode owns the node's state and its life (spawn, crash, restart, give
up, stop); its parts decide the rest: the current process (incarnation.py), the handover from
HELLO to release (handover.py, with the release gate: gate.py), its recoveries (recoveries.py;
each one's steps and what it says: recovery.py), the readers of its inputs (readers.py), the
heartbeat (watchdog.py), the warm standby (standby_keeper.py), poison (poison.py)."""

from __future__ import annotations

import logging
import random
import signal
import time
from pathlib import Path
from typing import Any

from ..inflight import slot_path
from ..log import SegmentStore
from ..protocol import (
    CheckpointStatus,
    ErrorStatus,
    HelloStatus,
    InputsStatus,
    Mode,
    OpenedStatus,
    ReleasedStatus,
    StatusMessage,
    SwitchedStatus,
    SyncedStatus,
)
from ..store import CheckpointStore
from .config import NodeConfig
from .events import status_fields
from .gate import Gate
from .handover import Handover, Step
from .health import NodeHealth, NodeRecord, age
from .incarnation import Incarnation
from .loop_events import ChildExited
from .poison import PoisonGuard
from .ports import SupervisorPorts
from .process import RestartPolicy, describe_exit, node_environment, reap, stop_child
from .readers import InputReaders
from .recoveries import Recoveries
from .recovery import Recovery, say_resumed
from .standby_keeper import StandbyKeeper
from .states import LOG_PREFIX, NodeState, NodeStateMachine, StateEvent
from .watchdog import Beat, Watchdog, enforce, say_overdue

_logger = logging.getLogger('rory.supervisor')

_LIVE = frozenset({
    NodeState.STARTING, NodeState.ARMING, NodeState.RUNNING, NodeState.RESTORING,
    NodeState.REPLAYING, NodeState.GATED,
})
"""States in which a node has a process that must beat."""


class ManagedNode:
    """One supervised node: its process, its state, its ring and its recovery."""

    def __init__(self, sup: SupervisorPorts, cfg: NodeConfig) -> None:
        self.sup = sup
        self.cfg = cfg
        self.sm = NodeStateMachine(cfg.name, _logger, clock=sup.clock,
                                   listeners=[self._on_state])
        self.policy = RestartPolicy(cfg.backoff)
        # What belongs to the current process (its pid, HELLO, shadow topic); a new one at
        # each spawn.
        self.current = Incarnation(0, 0)
        self.inputs = InputReaders(cfg.name, cfg.method.logs, sup.make_ring, sup.events_log)
        self.restart_at: float | None = None
        self.checkpoints = CheckpointStore(sup.config.store, cfg.name)
        self.segments = SegmentStore(sup.config.store, cfg.name)
        self.poison = PoisonGuard(sup.config.store, cfg.name, self.segments)
        self.watchdog = Watchdog(slot_path(sup.config.store, cfg.name), sup.clock,
                                 sup.read_beat, cfg.hang_timeout, cfg.start_timeout,
                                 cfg.hello_timeout)
        self.resumed = False  # first started from the store of a run that did not stop
        self.standby = StandbyKeeper(sup, cfg,
                                     lambda: self._env(Mode.RECOVER, self.incarnation + 1))
        # Its recovery now, if any, and its input gaps.
        self.recoveries = Recoveries(cfg.name, sup.safety, self.segments, self.checkpoints,
                                     sup.clock, sup.events_log)
        self.record = NodeRecord()  # crashes, last recovery, why FATAL, freshness
        # HELLO to release, with the release gate (its service is served by the ROS side:
        # on_gate_call).
        gate = (None if cfg.release_gate is None else
                Gate(cfg.name, cfg.release_gate, self.gate_service, sup.clock,
                     lambda: self.current.send_open()))
        self.handover = Handover(cfg, sup.clock, sup.events_log, gate, self.record,
                                 self.recoveries.gaps,
                                 sup.events.put, self.segments.next_number)

    @property
    def id(self) -> str:
        return self.cfg.name

    @property
    def incarnation(self) -> int:
        """The number of its current (or last) process; 0 before the first."""
        return self.current.number

    @property
    def recovery(self) -> Recovery | None:
        """Its recovery now, if any (``Recoveries.current``)."""
        return self.recoveries.current

    @property
    def slot(self) -> Path:
        """Its in-flight slot (heartbeat, the message being applied: inflight.py)."""
        return self.watchdog.slot

    @property
    def gate_service(self) -> str:
        """The release gate's ``std_srvs/Trigger`` service: ``/rory/<node>/release``."""
        return f'{self.sup.channel}/{self.id}/release'

    # -- process life -------------------------------------------------------------------------

    def _on_state(self, event: StateEvent) -> None:
        self.sup.events_log.write(
            'state', self.id, old=event.old.value, new=event.new.value, reason=event.reason,
            incarnation=self.incarnation,
        )

    def _env(self, mode: Mode, incarnation: int) -> dict[str, str]:
        sup = self.sup
        return node_environment(self.cfg, mode, incarnation, store=sup.config.store,
                                quarantine=self.poison.env_value(), secret=sup.secret,
                                channel=sup.channel, status_address=sup.status_address)

    def spawn(self, mode: Mode) -> None:
        """Start a new process of this node (main thread only)."""
        incarnation = self.incarnation + 1
        # One nonce per process: a SYNCED that answers any of its SYNCs proves the path.
        self.current = current = Incarnation(incarnation, random.getrandbits(63))
        self.watchdog.watch()
        # A writer on the new incarnation's shadow topic; the last one waits to be retired.
        current.replay_pub = self.sup.open_shadow_topic(self.id, incarnation)
        env = self._env(mode, incarnation)
        child = self.sup.launcher.spawn(self.cfg.command, env, self.sup.config.folder,
                                        label=self.id)
        current.child = child
        warm = self.standby.spawned(child)
        _logger.info(
            '%s %s: spawned pid %d (incarnation %d, %s, %s)', LOG_PREFIX, self.id, child.pid,
            incarnation, mode.value, 'from its standby' if warm else 'cold',
        )
        self.sup.events_log.write('spawn', self.id, pid=child.pid, incarnation=incarnation,
                                  mode=mode.value, warm=warm)
        reap(child, self.id, lambda code: self.sup.events.put(
            ChildExited(self.id, incarnation, code, self.sup.clock(), time.time_ns())))

    def start(self) -> None:
        """First start of the node."""
        self.sm.change_state(NodeState.STARTING)
        self.spawn(Mode.FRESH)

    def has_stored_state(self) -> bool:
        """A checkpoint or a message log of an earlier run is on disk."""
        return bool(self.segments.numbers()) or self.checkpoints.latest_valid() is not None

    def start_resumed(self, down_since: float | None) -> None:
        """First start after a supervisor that died: a recovery from the store (S1-S4).

        The node died with that supervisor. Its checkpoints and its own message log are on
        disk; what its inputs published while no supervisor ran was recorded by nobody, and
        the event says for how long that was.
        """
        now = self.sup.clock()
        say_resumed(self.id, self.sup.config.store / self.id, down_since, self.sup.events_log)
        self.sm.change_state(NodeState.RESTORING, 'resume from the store')
        self.resumed = True
        # S2 without a ring: it joins at HELLO, once the node has named its inputs.
        rec = self.recoveries.start(now, time.time_ns(), None)
        rec.s3_restart(lambda: self.spawn(Mode.RECOVER))

    def on_exit(self, ev: ChildExited) -> None:
        """The process ended."""
        if ev.incarnation != self.incarnation or self.sm.state in (
            NodeState.STOPPING, NodeState.STOPPED, NodeState.FATAL,
        ):
            return  # (FATAL: a process the supervisor ended when it gave up)
        current = self.current
        current.child = None
        how = describe_exit(ev.code)
        if self.watchdog.kill_reason is not None:
            how = f'{self.watchdog.kill_reason}, {how}'
        self.sup.events_log.write('exit', self.id, code=ev.code, incarnation=ev.incarnation)
        if ev.code == 0 and not self.cfg.restart_on_clean_exit:
            self.sm.change_state(NodeState.EXITED, how)
            self.standby.drop()
            self._end_recovery()
            self.inputs.stop_early('exited')
            return
        self.record.crashes += 1
        ran_for = 0.0 if current.running_since is None else ev.at - current.running_since
        current.running_since = None
        was_recovering = self.sm.recovering
        # Did it die applying a message - the same one as last time (poison)?
        rlog = self.recovery.rlog if self.recovery is not None else None
        died_on, quarantined = self.poison.judge(
            ev.incarnation, list(rlog.entries) if rlog is not None else [], self.sup.events_log)
        self.sm.change_state(NodeState.CRASHED, how)
        rec = self.recoveries.crashed(ev.at, ev.at_ns, was_recovering, self.inputs.ring,
                                      self.inputs.take_early)
        rec.note_crash(died_on, quarantined)
        delay = self.policy.on_crash(ran_for)
        if delay is None:
            self._give_up(f'{self.policy.consecutive - 1} restarts in a row failed; giving up',
                          crashes=self.policy.consecutive)
            return
        if delay > 0:
            self.restart_at = self.sup.clock() + delay
            self.sm.change_state(NodeState.BACKOFF, f'restart in {delay:.1f} s')
        else:
            self._restart()

    def _give_up(self, reason: str, **fields: Any) -> None:
        """FATAL: the node is not started again. Giving up leaves the robot in the safe state:
        nothing will drive it back out."""
        self.record.fatal_reason = reason
        self.sm.change_state(NodeState.FATAL, reason)
        self.sup.events_log.write('fatal', self.id, reason=reason, **fields)
        child, self.current.child = self.current.child, None
        if child is not None:  # refused or gated: the process the supervisor will not run
            child.send_signal(signal.SIGKILL)
        self.standby.drop()
        self.handover.drop()
        self.recoveries.give_up()

    def _restart(self) -> None:
        self.restart_at = None
        self.sm.change_state(NodeState.RESTORING, 'restart, restore')
        assert self.recovery is not None
        self.recovery.s3_restart(lambda: self.spawn(Mode.RECOVER))

    # -- what the process says ----------------------------------------------------------------

    def on_status(self, message: StatusMessage) -> None:
        """A status message from this node's runtime."""
        if message.incarnation != self.incarnation:
            return
        status, events = message.status, self.sup.events_log
        current, state, handover = self.current, self.sm.state, self.handover
        if isinstance(status, HelloStatus):
            if current.hello is None:
                self._on_hello(status, message)
        elif isinstance(status, SyncedStatus):
            if current.synced(status.nonce, status.live_publishers):
                handover.synced(current, state, self.recovery)
        elif isinstance(status, ReleasedStatus):
            self._take(handover.released(current, status, state, self.recovery))
        elif isinstance(status, OpenedStatus):
            self._take(handover.opened(current, status, state, self.recovery))
        elif isinstance(status, CheckpointStatus):
            # DEBUG: one every checkpoint_interval per node is routine (events.jsonl,
            # /rory/events and the diagnostics' checkpoint age carry it); at INFO it went to the
            # console and /rosout, an rclpy log call of ~0.3 ms each, several a second at rest.
            _logger.debug(
                '%s %s: checkpoint %s (cut %s, %s B, stall %.2f ms)', LOG_PREFIX, self.id,
                status.seq, status.cut, status.size, float(status.stall_ms),
            )
            self.watchdog.checkpoint_taken(self.sup.clock())
            self.current.checkpoint_error = None
            events.write('checkpoint', self.id, **status_fields(message))
        elif isinstance(status, SwitchedStatus):
            events.write('switched', self.id, topic=status.topic,
                         passed_by_relay=list(status.passed_by_relay),
                         live_only=list(status.live_only))
            if self.recovery is not None and self.recovery.on_switched(status.topic,
                                                                       status.live_only):
                self._end_recovery()
        elif isinstance(status, InputsStatus):
            self.inputs.added(status.inputs)
        elif isinstance(status, ErrorStatus):
            if status.checkpoint_failed:  # a checkpoint not taken (Checkpointer.take)
                self.current.checkpoint_error = status.message
            _logger.error('%s %s: %s', LOG_PREFIX, self.id, status.message)
            events.write('error', self.id, message=status.message)

    def _on_hello(self, hello: HelloStatus, message: StatusMessage) -> None:
        """The process started (``message``, all of it, goes to the event log): the ring
        reads its inputs (and joins a recovery that had none), then the handover goes on."""
        self.current.hello = hello
        self.sup.events_log.write('hello', self.id, **status_fields(message))
        for refused in hello.refused:
            _logger.warning('%s %s: %s', LOG_PREFIX, self.id, refused)
        ring = self.inputs.named(hello.inputs)
        if ring is not None and self.recovery is not None and self.recovery.ring is None:
            if not self.resumed:
                _logger.warning('%s %s: crashed before RORY knew its inputs; messages published '
                                'until now are not recorded', LOG_PREFIX, self.id)
            self.recovery.join_ring(ring)
        self._take(self.handover.hello(self.current, hello, self.sm.state, self.recovery))

    def _take(self, step: Step) -> None:
        """The handover's next step: give up, or enter its state, do what follows, end the
        recovery."""
        if step.give_up is not None:
            self._give_up(step.give_up, **step.fields)
            return
        if step.state is not None:
            self.sm.change_state(step.state, step.reason)
        if step.then is not None:
            step.then()
        if step.end_recovery:
            self._end_recovery()

    def on_gate_call(self) -> tuple[bool, str]:
        """A call on the release gate service (main thread): the answer to give."""
        return self.handover.on_call(self.sm.state)

    def _end_recovery(self) -> None:
        if self.sm.state == NodeState.GATED:
            # Every topic is live again, but S4 waits for the gate; the release ends it.
            return
        # Leaves the safe state if S4 has not: the node exited (status 0) while recovering.
        self.recoveries.end()
        self.sup.retire_shadow_topics(self.id)

    # -- time ---------------------------------------------------------------------------------

    def health(self, now: float) -> NodeHealth:
        """This node as /diagnostics shows it."""
        record, child = self.record, self.current.child
        last = record.last_recovery
        return NodeHealth(
            node=self.id, state=self.sm.state, method=self.cfg.method.value,
            pid=child.pid if child is not None else None,
            incarnation=self.incarnation, crashes=record.crashes,
            last_recovery_ms=last[0] if last else None,
            last_recovery_age_s=age(last[1], now) if last else None,
            last_checkpoint_age_s=age(self.watchdog.last_checkpoint_at, now),
            standby=self.standby.status(),
            checkpoint_overdue_s=self.watchdog.checkpoint_overdue(
                now, self._checkpointing_since(), self.current.checkpoint_interval()),
            checkpoint_error=self.current.checkpoint_error,
            fatal_reason=record.fatal_reason,
            freshness=record.freshness if self.cfg.method.checkpoints else None,
            gate_service=self.gate_service if self.cfg.release_gate is not None else None,
        )

    def _checkpointing_since(self) -> float | None:
        """When it was released, if it runs released (RUNNING) and checkpoints; else None."""
        if self.sm.state != NodeState.RUNNING or not self.cfg.method.checkpoints:
            return None
        return self.current.running_since

    def tick(self, now: float) -> None:
        """Time-driven work: hang detection, SYNC resends, arming, backoff expiry, standby."""
        state, current = self.sm.state, self.current
        if state in _LIVE:
            self._watch(now)
        overdue = self.watchdog.overdue_news(now, self._checkpointing_since(),
                                             current.checkpoint_interval())
        if overdue is not None:
            say_overdue(self.id, overdue, self.sup.events_log)
        if state == NodeState.RUNNING:
            # Released, still relaying until every topic is live again: a gap the relay shows
            # (a message lost between R and the live reader) is said now, not only at the end
            # of a handover that may never end (a topic whose publisher stops).
            self.recoveries.report_gaps()
        if state == NodeState.RUNNING and self.standby.due(now, self.incarnation,
                                                          current.running_since):
            self.standby.prepare(now, self.incarnation)
        if state == NodeState.BACKOFF and self.restart_at is not None and now >= self.restart_at:
            self._restart()
        else:  # SYNC, RELEASE and OPEN resent; the gate's timeout
            self._take(self.handover.tick(now, current, state, self.inputs.ring))

    def _watch(self, now: float) -> None:
        """Crash detection beyond exit codes: act on what the watchdog finds."""
        child = self.current.child
        if child is None:
            return
        for finding in self.watchdog.check(now, heard=self.current.hello is not None):
            if not isinstance(finding, Beat):  # hung, unheard: say it, signal the process
                enforce(finding, self.id, self.incarnation, child,
                        lambda: self.poison.died_on(self.incarnation), self.sup.events_log)
            elif self.sm.state == NodeState.RUNNING and self.recovery is None:
                self.inputs.on_beat(finding)  # S2 early: running, not already recovering

    def stop(self) -> None:
        """Stop the node's process: SIGINT, then SIGTERM, then SIGKILL."""
        if self.sm.state in (NodeState.STOPPING, NodeState.STOPPED):
            return
        self.sm.change_state(NodeState.STOPPING, 'supervisor stopping')
        self.standby.drop()
        self.recoveries.stop()  # the safe state as it is: held if the node was not released
        if self.current.child is not None:
            stop_child(self.current.child)
        self.current.child = None
        self.sm.change_state(NodeState.STOPPED)

