"""One supervised node's decisions (:class:`ManagedNode`), on the supervisor's ports
(ports.py), driven by the main loop: ``on_exit``, ``on_status``, ``on_gate_call`` and
``tick``. No rclpy here: the ROS side (supervisor.py) makes the readers, writers and services
behind the ports. Its parts: the current process (incarnation.py), the recovery and what it
says (recovery.py), the heartbeat (watchdog.py), the release gate (gate.py), the warm standby
(standby_keeper.py), poison (poison.py)."""

from __future__ import annotations

import logging
import random
import signal
import threading
import time
from pathlib import Path
from typing import Any

from ..freshness import Verdict
from ..inflight import slot_path
from ..log import SegmentStore
from ..protocol import (
    CheckpointStatus,
    ErrorStatus,
    HelloStatus,
    InputSpec,
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
from .gate import SYNC_PERIOD, Gate
from .health import NodeHealth, NodeRecord, age
from .incarnation import Incarnation
from .loop_events import ChildExited, Released
from .poison import PoisonGuard
from .ports import RingPort, SupervisorPorts
from .process import RestartPolicy, describe_exit, node_environment, stop_child
from .recovery import EarlyCapture, GapReports, Recovery, say_recovered
from .standby_keeper import StandbyKeeper
from .states import LOG_PREFIX, NodeState, NodeStateMachine, StateEvent
from .watchdog import Beat, Hung, Unheard, Watchdog, say_hung, say_overdue, say_unheard

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
        self.inputs: list[InputSpec] = []
        self.ring: RingPort | None = None
        self.recovery: Recovery | None = None
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
        self.gaps = GapReports(cfg.name, sup.events_log)  # input gaps, each said once
        self.early = EarlyCapture(cfg.name)  # what the ring took since the beat went late
        # The release gate (its service is served by the ROS side: on_gate_call).
        self.gate = (None if cfg.release_gate is None else
                     Gate(cfg.name, cfg.release_gate, self.gate_service, sup.clock,
                          lambda: self.current.send_open()))
        self.record = NodeRecord()  # crashes, last recovery, why FATAL, freshness

    @property
    def id(self) -> str:
        return self.cfg.name

    @property
    def incarnation(self) -> int:
        """The number of its current (or last) process; 0 before the first."""
        return self.current.number

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

        def reap() -> None:
            code = child.wait()
            self.sup.events.put(
                ChildExited(self.id, incarnation, code, self.sup.clock(), time.time_ns())
            )

        threading.Thread(target=reap, name=f'rory-reap-{self.id}', daemon=True).start()

    def start(self) -> None:
        """First start of the node."""
        self.sm.change_state(NodeState.STARTING)
        self.spawn(Mode.FRESH)

    def has_stored_state(self) -> bool:
        """A checkpoint or a message log of an earlier run is on disk."""
        return bool(self.segments.numbers()) or self.checkpoints.latest_valid() is not None

    def _new_recovery(self, crashed: float, crashed_ns: int, ring: RingPort | None) -> Recovery:
        self.recovery = Recovery(
            node_id=self.id, crashed=crashed, crashed_ns=crashed_ns, safety=self.sup.safety,
            ring=ring, segments=self.segments, checkpoints=self.checkpoints,
            clock=self.sup.clock,
        )
        return self.recovery

    def start_resumed(self, down_since: float | None) -> None:
        """First start after a supervisor that died: a recovery from the store (S1-S4).

        The node died with that supervisor. Its checkpoints and its own message log are on
        disk; what its inputs published while no supervisor ran was recorded by nobody, and
        the event says for how long that was.
        """
        now = self.sup.clock()
        gap = None if down_since is None else max(0.0, time.time() - down_since)
        self.sup.events_log.write('resumed', self.id, unrecorded_s=gap)
        _logger.warning(
            '%s %s: resuming from %s after a supervisor that did not stop cleanly%s',
            LOG_PREFIX, self.id, self.sup.config.store / self.id,
            '' if gap is None else f' (inputs unrecorded for up to {gap:.1f} s)',
        )
        self.sm.change_state(NodeState.RESTORING, 'resume from the store')
        rec = self._new_recovery(now, time.time_ns(), None)
        self.resumed = True
        rec.begin()  # S2 without a ring: it joins at HELLO, once the node has named its inputs
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
            self.early.stop(self.ring, 'exited')
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
        self._crashed(ev, was_recovering)
        assert self.recovery is not None  # made or carried on by _crashed
        self.recovery.note_crash(died_on, quarantined)
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
        if self.gate is not None:
            self.gate.held = None
        if self.recovery is not None:
            self.recovery.give_up()

    def _crashed(self, ev: ChildExited, was_recovering: bool) -> None:
        rec = self.recovery
        if rec is not None and was_recovering:
            # Died before its release: the same recovery goes on (R keeps recording, the safe
            # state stays held), and its time still counts from the first crash.
            rec.again(ev.at)
            return
        if rec is not None:
            # Crashed during the handover of an earlier recovery, whose S4 released the safe
            # state: that one ends here, and this crash is a recovery of its own.
            rec.stop()
            self.gaps.report(rec)  # also those held back for a switch that never came
        ring = self.ring if self.cfg.method.logs else None
        self._new_recovery(ev.at, ev.at_ns, ring).begin(self.early.take())

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
        if isinstance(status, HelloStatus):
            self._on_hello(status, message)
        elif isinstance(status, SyncedStatus):
            if self.current.synced(status.nonce, status.live_publishers):
                self._on_synced()
        elif isinstance(status, ReleasedStatus):
            self._on_released(status)
        elif isinstance(status, OpenedStatus):
            gate = self.gate
            if self.sm.state == NodeState.GATED and gate is not None and gate.held is not None:
                # What the node published while it waited was muted: counted, never sent.
                events.write('gate_opened', self.id, reason=gate.reason, muted=status.muted)
                stats = gate.opened()
                assert stats is not None
                self._finish_release(stats)
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
            events.write('checkpoint', self.id, **_fields(message))
        elif isinstance(status, SwitchedStatus):
            events.write('switched', self.id, topic=status.topic,
                         passed_by_relay=list(status.passed_by_relay),
                         live_only=list(status.live_only))
            if self.recovery is not None and self.recovery.on_switched(status.topic,
                                                                       status.live_only):
                self._end_recovery()
        elif isinstance(status, InputsStatus):
            # The node made a subscription after HELLO: read that topic in the ring too.
            inputs = list(status.inputs)
            added = sorted({i.topic for i in inputs} - {i.topic for i in self.inputs})
            self.inputs = inputs
            events.write('inputs', self.id, added=added)
            _logger.info('%s %s: new input(s) %s', LOG_PREFIX, self.id, ', '.join(added))
            if self.cfg.method.logs and self.ring is not None:
                self.ring.ensure(self.inputs)
        elif isinstance(status, ErrorStatus):
            if status.checkpoint_failed:  # a checkpoint not taken (Checkpointer.take)
                self.current.checkpoint_error = status.message
            _logger.error('%s %s: %s', LOG_PREFIX, self.id, status.message)
            events.write('error', self.id, message=status.message)

    def _on_hello(self, hello: HelloStatus, message: StatusMessage) -> None:
        """The process started (``message``, all of it, goes to the event log)."""
        if self.current.hello is not None:
            return
        self.current.hello = hello
        self.inputs = list(hello.inputs)
        self.sup.events_log.write('hello', self.id, **_fields(message))
        for refused in hello.refused:
            _logger.warning('%s %s: %s', LOG_PREFIX, self.id, refused)
        if self.cfg.method.logs:
            if self.ring is None:
                self.ring = self.sup.make_ring(self.id)
            self.ring.ensure(self.inputs)
            if self.recovery is not None and self.recovery.ring is None:
                if not self.resumed:
                    _logger.warning(
                        '%s %s: crashed before RORY knew its inputs; messages published until '
                        'now are not recorded', LOG_PREFIX, self.id,
                    )
                self.recovery.join_ring(self.ring)
        if hello.restored is not None:
            freshness = self.record.freshness = hello.restored.freshness
            if freshness.refused:
                self._refuse_stale(freshness)
                return
        if self.recovery is not None:
            self.recovery.on_hello(float(hello.restore_ms))
            if self.cfg.method.checkpoints and hello.refused and hello.restored is None:
                # Logs are pruned up to the older kept checkpoint's cut: with both refused,
                # replay cannot rebuild what they held. Say so; never pretend.
                _logger.error(
                    '%s %s: every checkpoint was refused; the state is rebuilt only from the log '
                    'that remains and may be incomplete', LOG_PREFIX, self.id,
                )
        if self.cfg.method.logs:
            if self.sm.state == NodeState.STARTING:
                self.sm.change_state(NodeState.ARMING, 'waiting for RORY readers to match')
            elif self.sm.state == NodeState.RESTORING:
                self.sm.change_state(NodeState.REPLAYING,
                                     f'replay after segment {self.current.restored_cut()}')
            self.current.send_sync(self.sup.clock())

    def _refuse_stale(self, verdict: Verdict) -> None:
        """A stale variable whose rule is ``refuse``: the node does not run on its checkpoint
        (freshness.py); an operator decides (raise max_age, or start it fresh)."""
        age = 'unknown' if verdict.age_s is None else f'{verdict.age_s:.1f} s'
        reason = (f'checkpoint too old for {", ".join(verdict.refused)} '
                  f'(age {age} on the {verdict.clock} clock; on_stale: refuse): not '
                  'started, the safe state is held; start it fresh (rory supervise --fresh) or '
                  'raise max_age in keyvars.yaml')
        _logger.error('%s %s: %s', LOG_PREFIX, self.id, reason)
        self._give_up(reason, freshness=verdict.to_json())

    def _on_synced(self) -> None:
        current = self.current
        if self.sm.state == NodeState.REPLAYING and self.recovery is not None:
            assert current.hello is not None and current.replay_pub is not None
            incarnation = current.number
            self.recovery.s3_replay(
                current.replay_pub, incarnation, current.restored_cut(),
                current.replay_pace(self.cfg.replay),
                lambda sent: self.sup.events.put(Released(self.id, incarnation, sent)),
            )

    def _on_released(self, stats: ReleasedStatus) -> None:
        self.current.running_since = self.sup.clock()
        recovering = self.sm.state in (NodeState.RESTORING, NodeState.REPLAYING)
        if recovering and self.recovery is not None and self.gate is not None:
            # Caught up and live, outputs muted: wait for the release call (or the timeout).
            gate = self.gate
            self.sm.change_state(NodeState.GATED, gate.enter(stats))
            self.sup.events_log.write('gated', self.id, service=gate.service,
                                      timeout=gate.config.timeout,
                                      on_timeout=gate.config.on_timeout)
            if gate.called:
                gate.open('called before the node had caught up')
            return
        self._finish_release(stats)

    def on_gate_call(self) -> tuple[bool, str]:
        """A call on the release gate service (main thread): the answer to give."""
        if self.gate is None:
            return False, f'{self.id}: no release gate'
        return self.gate.on_call(self.sm.state)

    def _finish_release(self, stats: ReleasedStatus) -> None:
        rec = self.recovery
        if rec is not None and self.sm.state in (NodeState.RESTORING, NodeState.REPLAYING,
                                                 NodeState.GATED):
            gate_ms, gate_reason = (None, None) if self.gate is None else self.gate.finish()
            timing = rec.s4_release()
            self.record.last_recovery = (timing['total_ms'], self.sup.clock())
            self.sm.change_state(NodeState.RUNNING, 'released')
            pace = (self.current.replay_pace(self.cfg.replay).value if self.cfg.method.logs
                    else None)
            say_recovered(rec, self.id, self.sup.events_log, self.gaps, method=self.cfg.method,
                          incarnation=self.incarnation, timing=timing, stats=stats, pace=pace,
                          freshness=self.record.freshness, gate_ms=gate_ms,
                          gate_reason=gate_reason)
            if rec.ring is None or not rec.ring.active_topics:
                self._end_recovery()
        elif self.sm.state in (NodeState.STARTING, NodeState.ARMING):
            self.sm.change_state(NodeState.RUNNING, 'released')

    def _end_recovery(self) -> None:
        if self.sm.state == NodeState.GATED:
            # Every topic is live again, but S4 waits for the gate; the release ends it.
            return
        if self.recovery is not None:
            # Leaves the safe state if S4 has not: the node exited (status 0) while recovering.
            self.recovery.finish()
            self.gaps.report(self.recovery)  # after finish: none is held back any more
            self.recovery = None
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
            checkpoint_overdue_s=self.checkpoint_overdue(now),
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

    def checkpoint_overdue(self, now: float) -> float | None:
        """Seconds past the time a running node must have checkpointed by, if it is late
        (``Watchdog.checkpoint_overdue``)."""
        return self.watchdog.checkpoint_overdue(now, self._checkpointing_since(),
                                                self.current.checkpoint_interval())

    def tick(self, now: float) -> None:
        """Time-driven work: hang detection, SYNC resends, arming, backoff expiry, standby."""
        state, current = self.sm.state, self.current
        if state in _LIVE:
            self._watch(now)
        overdue = self.watchdog.overdue_news(now, self._checkpointing_since(),
                                             current.checkpoint_interval())
        if overdue is not None:
            say_overdue(self.id, overdue, self.sup.events_log)
        if state == NodeState.RUNNING and self.recovery is not None:
            # Released, still relaying until every topic is live again: a gap the relay shows
            # (a message lost between R and the live reader) is said now, not only at the end
            # of a handover that may never end (a topic whose publisher stops).
            self.gaps.report(self.recovery)
        if state == NodeState.RUNNING and self.standby.due(now, self.incarnation,
                                                          current.running_since):
            self.standby.prepare(now, self.incarnation)
        if state == NodeState.GATED and self.gate is not None:
            given_up = self.gate.tick(now)
            if given_up is not None:
                self._give_up(given_up)
        if state == NodeState.BACKOFF and self.restart_at is not None and now >= self.restart_at:
            self._restart()
        elif state in (NodeState.ARMING, NodeState.REPLAYING):
            if current.synced_counts is None and now - current.sync_sent >= SYNC_PERIOD:
                current.send_sync(self.sup.clock())
            elif (state == NodeState.ARMING and not current.release_sent
                  and current.armed(self.ring)):
                current.send_release(self.segments.next_number())  # once; RELEASED answers

    def _watch(self, now: float) -> None:
        """Crash detection beyond exit codes: act on what the watchdog finds."""
        child = self.current.child
        if child is None:
            return
        for finding in self.watchdog.check(now, heard=self.current.hello is not None):
            if isinstance(finding, Beat):
                # S2 early: only for a running node that logs, not already recovering.
                ring = self.ring if self.cfg.method.logs else None
                if (ring is not None and self.sm.state == NodeState.RUNNING
                        and self.recovery is None):
                    self.early.on_beat(ring, finding)
            elif isinstance(finding, Hung):
                # Say what it was doing. SIGUSR1 for a heartbeat that stopped: faulthandler in
                # the node prints every thread's stack, where it hung, and SIGKILL follows
                # (KillDue). SIGKILL at once for a process that never beat.
                say_hung(self.id, self.incarnation, child.pid, finding,
                         self.poison.died_on(self.incarnation), self.sup.events_log)
                child.send_signal(finding.signal)
            elif isinstance(finding, Unheard):
                # The process runs but its HELLO never arrived: replace it (a crash, recovered).
                say_unheard(self.id, self.incarnation, child.pid, finding, self.sup.events_log)
                child.send_signal(signal.SIGKILL)
            else:  # KillDue: the hung process has printed its stacks
                child.send_signal(signal.SIGKILL)

    def stop(self) -> None:
        """Stop the node's process: SIGINT, then SIGTERM, then SIGKILL."""
        if self.sm.state in (NodeState.STOPPING, NodeState.STOPPED):
            return
        self.sm.change_state(NodeState.STOPPING, 'supervisor stopping')
        self.standby.drop()
        if self.recovery is not None:
            # The safe state stays as it is: held if the node had not been released.
            self.recovery.stop()
            self.gaps.report(self.recovery)  # after stop: none is held back any more
        if self.current.child is not None:
            stop_child(self.current.child)
        self.current.child = None
        self.sm.change_state(NodeState.STOPPED)


def _fields(message: StatusMessage) -> dict[str, Any]:
    """What a status carries but its kind and node, as it travelled: the fields of the
    ``hello`` and ``checkpoint`` events."""
    return {k: v for k, v in message.to_json().items() if k not in ('kind', 'node')}
