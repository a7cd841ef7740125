"""One supervised node's decisions (:class:`ManagedNode`), on the supervisor's ports
(ports.py), driven by the main loop: ``on_exit``, ``on_status``, ``on_gate_call`` and
``tick``."""

from __future__ import annotations

import logging
import os
import random
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any

from .. import protocol
from ..dds import node_profile_env
from ..freshness import Verdict
from ..freshness import describe as describe_verdict
from ..inflight import InFlight, slot_path
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
    ReplayPace,
    StatusMessage,
    SwitchedStatus,
    SyncedStatus,
)
from ..store import CheckpointStore
from .config import NodeConfig
from .gate import SYNC_PERIOD, Gate
from .health import NodeHealth, age
from .loop_events import ChildExited, Released
from .poison import PoisonGuard, Quarantined
from .ports import EnvelopePort, RingPort, SupervisorPorts
from .process import Child, RestartPolicy, describe_exit
from .recovery import EarlyCapture, GapReports, Recovery
from .standby_keeper import StandbyKeeper
from .states import LOG_PREFIX, NodeState, NodeStateMachine, StateEvent
from .watchdog import Beat, Hung, Unheard, Watchdog

_logger = logging.getLogger('rory.supervisor')


STOP_GRACE = (3.0, 2.0)
"""Seconds to wait after SIGINT, then after SIGTERM, before SIGKILL."""

_LIVE = frozenset({
    NodeState.STARTING, NodeState.ARMING, NodeState.RUNNING, NodeState.RESTORING,
    NodeState.REPLAYING, NodeState.GATED,
})
"""States in which a node has a process that must beat."""


@dataclass
class Incarnation:
    """What the supervisor knows of one process of a node; a new one at each spawn (its
    heartbeat and kill: ``Watchdog``)."""

    number: int
    sync_nonce: int  # a SYNCED answering any SYNC with it proves the shadow path
    hello: HelloStatus | None = None
    sync_sent: float = 0.0
    synced_counts: dict[str, int] | None = None  # its live publishers per input, from SYNCED
    release_sent: bool = False
    checkpoint_error: str | None = None  # its last checkpoint failure, until one succeeds


class ManagedNode:
    """One supervised node: its process, its state, its ring and its recovery."""

    def __init__(self, sup: SupervisorPorts, cfg: NodeConfig) -> None:
        self.sup = sup
        self.cfg = cfg
        self.id = cfg.name
        self._now = sup.clock  # monotonic seconds (a unit test's fake clock)
        self.sm = NodeStateMachine(cfg.name, _logger, clock=sup.clock,
                                   listeners=[self._on_state])
        self.policy = RestartPolicy(cfg.backoff)
        self.child: Child | None = None
        self.incarnation = 0
        # What belongs to the current process; a new one at each spawn.
        self.current = Incarnation(0, 0)
        self.inputs: list[InputSpec] = []
        self.ring: RingPort | None = None
        self.recovery: Recovery | None = None
        self.running_since: float | None = None
        self.restart_at: float | None = None
        self.checkpoints = CheckpointStore(sup.config.store, cfg.name)
        self.segments = SegmentStore(sup.config.store, cfg.name)
        self.poison = PoisonGuard(sup.config.store, cfg.name, self.segments)
        self.slot = slot_path(sup.config.store, cfg.name)
        self.watchdog = Watchdog(self.slot, sup.clock, sup.read_beat, cfg.hang_timeout,
                                 cfg.start_timeout, cfg.hello_timeout)
        self.resumed = False  # first started from the store of a run that did not stop
        self.standby = StandbyKeeper(sup, cfg,
                                     lambda: self._env(Mode.RECOVER, self.incarnation + 1))
        self.crashes_total = 0
        self.gaps = GapReports(self.id, sup.events_log)  # input gaps, each said once
        self.early = EarlyCapture(self.id)  # what the ring took since the beat went late
        self.last_recovery: tuple[float, float] | None = None  # (total ms, monotonic when)
        # The shadow topic of the current process (protocol.replay_topic: one per incarnation),
        # made at each spawn by the ROS side; earlier ones are destroyed once no replay
        # streams on them (retire_shadow_topics).
        self.replay_pub: EnvelopePort | None = None
        # The release gate (its service is served by the ROS side: on_gate_call).
        self.gate = (None if cfg.release_gate is None else
                     Gate(self.id, cfg.release_gate, f'{sup.channel}/{self.id}/release',
                          sup.clock, self._publish_open))
        self.fatal_reason: str | None = None
        # What the last recovery did with each key variable (freshness.py's verdict).
        self.last_freshness: Verdict | None = None

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
        env = dict(os.environ)
        env.update(self.cfg.env)
        env.update(
            {
                protocol.ENV_NODE: self.id,
                protocol.ENV_STORE: str(self.sup.config.store),
                protocol.ENV_INCARNATION: str(incarnation),
                protocol.ENV_METHOD: self.cfg.method.value,
                protocol.ENV_MODE: mode.value,
                protocol.ENV_QUARANTINE: self.poison.env_value(),
                protocol.ENV_SECRET: self.sup.secret.hex(),
                protocol.ENV_CHANNEL: self.sup.channel,
                protocol.ENV_STATUS: self.sup.status_address,
                'PYTHONUNBUFFERED': '1',
            }
        )
        env.update(node_profile_env(env))  # a cold node's discovery: rory_runtime/dds
        if self.cfg.checkpoint_interval is not None:
            env[protocol.ENV_INTERVAL] = repr(self.cfg.checkpoint_interval)
        else:
            env.pop(protocol.ENV_INTERVAL, None)
        if mode == Mode.RECOVER and self.cfg.release_gate is not None:
            env[protocol.ENV_GATED] = '1'
        else:
            env.pop(protocol.ENV_GATED, None)
        return env

    def spawn(self, mode: Mode) -> None:
        """Start a new process of this node (main thread only)."""
        self.incarnation += 1
        # One nonce per process: a SYNCED that answers any of its SYNCs proves the path.
        self.current = Incarnation(self.incarnation, random.getrandbits(63))
        self.watchdog.watch()
        # A writer on the new incarnation's shadow topic; the last one waits to be retired.
        self.replay_pub = self.sup.open_shadow_topic(self.id, self.incarnation)
        env = self._env(mode, self.incarnation)
        child = self.sup.launcher.spawn(self.cfg.command, env, self.sup.config.folder,
                                        label=self.id)
        self.child = child
        incarnation = self.incarnation
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
                ChildExited(self.id, incarnation, code, self._now(), time.time_ns())
            )

        threading.Thread(target=reap, name=f'rory-reap-{self.id}', daemon=True).start()

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
        now = self._now()
        gap = None if down_since is None else max(0.0, time.time() - down_since)
        self.sup.events_log.write('resumed', self.id, unrecorded_s=gap)
        _logger.warning(
            '%s %s: resuming from %s after a supervisor that did not stop cleanly%s',
            LOG_PREFIX, self.id, self.sup.config.store / self.id,
            '' if gap is None else f' (inputs unrecorded for up to {gap:.1f} s)',
        )
        self.sm.change_state(NodeState.RESTORING, 'resume from the store')
        rec = Recovery(
            node_id=self.id, crashed=now, crashed_ns=time.time_ns(), safety=self.sup.safety,
            ring=None, segments=self.segments, checkpoints=self.checkpoints, clock=self._now,
        )
        self.recovery = rec
        self.resumed = True
        rec.begin()  # S2 without a ring: it joins at HELLO, once the node has named its inputs
        rec.s3_restart(lambda: self.spawn(Mode.RECOVER))

    def on_exit(self, ev: ChildExited) -> None:
        """The process ended."""
        if ev.incarnation != self.incarnation or self.sm.state in (
            NodeState.STOPPING, NodeState.STOPPED, NodeState.FATAL,
        ):
            return  # (FATAL: a process the supervisor ended when it gave up)
        self.child = None
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
        self.crashes_total += 1
        ran_for = 0.0 if self.running_since is None else ev.at - self.running_since
        self.running_since = None
        was_recovering = self.sm.recovering
        died_on, quarantined = self._judge_crash(ev)
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
            self.restart_at = self._now() + delay
            self.sm.change_state(NodeState.BACKOFF, f'restart in {delay:.1f} s')
        else:
            self._restart()

    def _give_up(self, reason: str, **fields: Any) -> None:
        """FATAL: the node is not started again. Giving up leaves the robot in the safe state:
        nothing will drive it back out."""
        self.fatal_reason = reason
        self.sm.change_state(NodeState.FATAL, reason)
        self.sup.events_log.write('fatal', self.id, reason=reason, **fields)
        child, self.child = self.child, None
        if child is not None:  # refused or gated: the process the supervisor will not run
            child.send_signal(signal.SIGKILL)
        self.standby.drop()
        if self.gate is not None:
            self.gate.held = None
        if self.recovery is not None:
            self.recovery.give_up()

    def _judge_crash(self, ev: ChildExited) -> tuple[InFlight | None, Quarantined | None]:
        """Did it die applying a message - the same one as last time (poison)? That message,
        and its quarantine if it was."""
        rlog = self.recovery.rlog if self.recovery is not None else None
        recent = list(rlog.entries) if rlog is not None else []
        suspect = self.poison.died_on(ev.incarnation)
        quarantined = self.poison.on_crash(ev.incarnation, recent)
        if quarantined is not None:
            self.sup.events_log.write(
                'quarantined', self.id, topic=quarantined.topic, source_ns=quarantined.ident[0],
                seq=quarantined.ident[1], path=str(quarantined.path),
            )
        elif suspect is not None:
            self.sup.events_log.write(
                'died_on', self.id, topic=suspect.topic, source_ns=suspect.ident[0],
                seq=suspect.ident[1], incarnation=ev.incarnation,
            )
        return suspect, quarantined

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
        rec = Recovery(
            node_id=self.id, crashed=ev.at, crashed_ns=ev.at_ns, safety=self.sup.safety,
            ring=ring, segments=self.segments, checkpoints=self.checkpoints, clock=self._now,
        )
        self.recovery = rec
        rec.begin(self.early.take())

    def _restart(self) -> None:
        self.restart_at = None
        self.sm.change_state(NodeState.RESTORING, 'restart, restore')
        assert self.recovery is not None
        self.recovery.s3_restart(lambda: self.spawn(Mode.RECOVER))

    def on_status(self, message: StatusMessage) -> None:
        """A status message from this node's runtime."""
        if message.incarnation != self.incarnation:
            return
        status = message.status
        if isinstance(status, HelloStatus):
            self._on_hello(status, message)
        elif isinstance(status, SyncedStatus):
            current = self.current
            if status.nonce == current.sync_nonce and current.synced_counts is None:
                current.synced_counts = dict(status.live_publishers)
                self._on_synced()
        elif isinstance(status, ReleasedStatus):
            self._on_released(status)
        elif isinstance(status, OpenedStatus):
            gate = self.gate
            if self.sm.state == NodeState.GATED and gate is not None and gate.held is not None:
                # What the node published while it waited was muted: counted, never sent.
                self.sup.events_log.write('gate_opened', self.id, reason=gate.reason,
                                          muted=status.muted)
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
            self.watchdog.checkpoint_taken(self._now())
            self.current.checkpoint_error = None
            self.sup.events_log.write('checkpoint', self.id, **_fields(message))
        elif isinstance(status, SwitchedStatus):
            self.sup.events_log.write('switched', self.id, topic=status.topic,
                                      passed_by_relay=list(status.passed_by_relay),
                                      live_only=list(status.live_only))
            if self.recovery is not None and self.recovery.on_switched(status.topic,
                                                                       status.live_only):
                self._end_recovery()
        elif isinstance(status, InputsStatus):
            self._on_inputs(status)
        elif isinstance(status, ErrorStatus):
            if status.checkpoint_failed:  # a checkpoint not taken (Checkpointer.take)
                self.current.checkpoint_error = status.message
            _logger.error('%s %s: %s', LOG_PREFIX, self.id, status.message)
            self.sup.events_log.write('error', self.id, message=status.message)

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
            freshness = hello.restored.freshness
            self.last_freshness = freshness
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
                                     f'replay after segment {_restored_cut(hello)}')
            self._send_sync()

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

    def _on_inputs(self, status: InputsStatus) -> None:
        """The node made a subscription after HELLO: read that topic in the ring too."""
        inputs = list(status.inputs)
        added = sorted({i.topic for i in inputs} - {i.topic for i in self.inputs})
        self.inputs = inputs
        self.sup.events_log.write('inputs', self.id, added=added)
        _logger.info('%s %s: new input(s) %s', LOG_PREFIX, self.id, ', '.join(added))
        if self.cfg.method.logs and self.ring is not None:
            self.ring.ensure(self.inputs)

    def _send_sync(self) -> None:
        self.current.sync_sent = self._now()
        assert self.replay_pub is not None  # made by spawn()
        self.replay_pub.publish(protocol.pack_sync(self.incarnation, self.current.sync_nonce))

    def _on_synced(self) -> None:
        if self.sm.state == NodeState.REPLAYING and self.recovery is not None:
            assert self.current.hello is not None and self.replay_pub is not None
            cut = _restored_cut(self.current.hello)
            incarnation = self.incarnation
            self.recovery.s3_replay(
                self.replay_pub, incarnation, cut, self._replay_pace(),
                lambda sent: self.sup.events.put(Released(self.id, incarnation, sent)),
            )

    def _replay_pace(self) -> ReplayPace:
        """The supervisor config's pace, else the node's own (keyvars.yaml), else fast.

        Fast is the default since callbacks get the clock readings, ticks, parameter changes
        and requests they had live (docs/architecture.md, "Timers and the clock"); paced is
        for nodes that read time RORY cannot replay (docs/keyvars.md).
        """
        if self.cfg.replay is not None:
            return self.cfg.replay
        wanted = None if self.current.hello is None else self.current.hello.replay
        return ReplayPace(wanted) if wanted in {p.value for p in ReplayPace} else ReplayPace.FAST

    def _armed(self) -> bool:
        """The ring matches every publisher the node's own readers have (fresh start)."""
        if self.current.synced_counts is None or self.ring is None:
            return False
        counts = self.ring.publisher_counts()
        return all(counts.get(t, 0) >= n for t, n in self.current.synced_counts.items())

    def _on_released(self, stats: ReleasedStatus) -> None:
        self.running_since = self._now()
        recovering = self.sm.state in (NodeState.RESTORING, NodeState.REPLAYING)
        if recovering and self.recovery is not None and self.gate is not None:
            self._enter_gate(self.gate, stats)
            return
        self._finish_release(stats)

    def _enter_gate(self, gate: Gate, stats: ReleasedStatus) -> None:
        """Caught up and live, outputs muted: wait for the release call (or the timeout)."""
        self.sm.change_state(NodeState.GATED, gate.enter(stats))
        self.sup.events_log.write('gated', self.id, service=gate.service,
                                  timeout=gate.config.timeout, on_timeout=gate.config.on_timeout)
        if gate.called:
            gate.open('called before the node had caught up')

    def _publish_open(self) -> None:
        assert self.replay_pub is not None  # made by spawn()
        self.replay_pub.publish(protocol.pack_open(self.incarnation))

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
            self.last_recovery = (timing['total_ms'], self._now())
            self.sm.change_state(NodeState.RUNNING, 'released')
            gated = '' if gate_ms is None else f'; gated {gate_ms / 1000:.1f} s, {gate_reason}'
            _logger.info(
                '%s %s: recovered in %.1f ms (%s; crashes %d; replayed %s, duplicates skipped '
                '%s%s)', LOG_PREFIX, self.id, timing['total_ms'],
                ' '.join(f'{k[:-3]}={v:.1f}' for k, v in timing.items() if k != 'total_ms'),
                rec.crashes, stats.replayed, stats.duplicates, gated,
            )
            verdict = self.last_freshness
            if verdict is not None and self.cfg.method.checkpoints:
                level = (logging.WARNING if verdict.reset or verdict.kept_stale
                         else logging.INFO)
                _logger.log(level, '%s %s: %s', LOG_PREFIX, self.id,
                            describe_verdict(verdict))
            pace = self._replay_pace().value if self.cfg.method.logs else None
            gaps = self.gaps.report(rec)
            never = rec.never_delivered()
            for topic, dropped in never.items():
                _logger.warning(
                    '%s %s: input %s: %d message(s) (publication seq %s) reached RORY\'s reader '
                    'but never the node, below what the node had of the same publisher: not '
                    'replayed, to keep that publisher\'s order (a node that had not crashed '
                    'never had them either)', LOG_PREFIX, self.id, topic, dropped['count'],
                    dropped['seqs'])
            self.sup.events_log.write(
                'recovered', self.id, method=self.cfg.method.value, crashes=rec.crashes,
                incarnation=self.incarnation, replay=pace, **timing, **_recovery_counts(stats),
                input_gaps=[g.to_json() for g in gaps], r_log=rec.r_summary(),
                never_delivered=never, **rec.poison_summary(),
                freshness=None if self.last_freshness is None else self.last_freshness.to_json(),
                gate_ms=gate_ms,
                gate=gate_reason,
            )
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

    def health(self, now: float) -> NodeHealth:
        """This node as /diagnostics shows it."""
        last = self.last_recovery
        return NodeHealth(
            node=self.id, state=self.sm.state, method=self.cfg.method.value,
            pid=self.child.pid if self.child is not None else None,
            incarnation=self.incarnation, crashes=self.crashes_total,
            last_recovery_ms=last[0] if last else None,
            last_recovery_age_s=age(last[1], now) if last else None,
            last_checkpoint_age_s=age(self.watchdog.last_checkpoint_at, now),
            standby=self.standby.status(),
            checkpoint_overdue_s=self.checkpoint_overdue(now),
            checkpoint_error=self.current.checkpoint_error,
            fatal_reason=self.fatal_reason,
            freshness=self.last_freshness if self.cfg.method.checkpoints else None,
            gate_service=self.gate_service if self.cfg.release_gate is not None else None,
        )

    def _checkpointing_since(self) -> float | None:
        """When it was released, if it runs released (RUNNING) and checkpoints; else None."""
        if self.sm.state != NodeState.RUNNING or not self.cfg.method.checkpoints:
            return None
        return self.running_since

    def _checkpoint_interval(self) -> float:
        interval = None if self.current.hello is None else self.current.hello.interval
        return float(interval or 2.0)

    def checkpoint_overdue(self, now: float) -> float | None:
        """Seconds past the time a running node must have checkpointed by, if it is late
        (``Watchdog.checkpoint_overdue``)."""
        return self.watchdog.checkpoint_overdue(now, self._checkpointing_since(),
                                                self._checkpoint_interval())

    def tick(self, now: float) -> None:
        """Time-driven work: hang detection, SYNC resends, arming, backoff expiry, standby."""
        state = self.sm.state
        if state in _LIVE:
            self._watch(now)
        overdue = self.watchdog.overdue_news(now, self._checkpointing_since(),
                                             self._checkpoint_interval())
        if overdue is not None:
            age_s = overdue.since_s
            _logger.warning(
                '%s %s: no checkpoint for %s: the interval follows the node\'s ROS time (under '
                'use_sim_time, is /clock advancing?), or its checkpoints fail (see its errors); '
                'a crash now loses more', LOG_PREFIX, self.id,
                'the whole run' if age_s is None else f'{age_s:.1f} s')
            self.sup.events_log.write('checkpoints_overdue', self.id,
                                      since_s=None if age_s is None else round(age_s, 1))
        if state == NodeState.RUNNING and self.recovery is not None:
            # Released, still relaying until every topic is live again: a gap the relay shows
            # (a message lost between R and the live reader) is said now, not only at the end
            # of a handover that may never end (a topic whose publisher stops).
            self.gaps.report(self.recovery)
        if state == NodeState.RUNNING and self.standby.due(now, self.incarnation,
                                                          self.running_since):
            self.standby.prepare(now, self.incarnation)
        if state == NodeState.GATED and self.gate is not None:
            given_up = self.gate.tick(now)
            if given_up is not None:
                self._give_up(given_up)
        if state == NodeState.BACKOFF and self.restart_at is not None and now >= self.restart_at:
            self._restart()
        elif state in (NodeState.ARMING, NodeState.REPLAYING):
            if self.current.synced_counts is None and now - self.current.sync_sent >= SYNC_PERIOD:
                self._send_sync()
            elif state == NodeState.ARMING and not self.current.release_sent and self._armed():
                self.current.release_sent = True  # once; the node answers RELEASED
                assert self.replay_pub is not None  # made by spawn()
                self.replay_pub.publish(
                    protocol.pack_release(self.incarnation, self.segments.next_number(), 0)
                )

    def _watch(self, now: float) -> None:
        """Crash detection beyond exit codes: act on what the watchdog finds."""
        child = self.child
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
                self._on_hung(child, finding)
            elif isinstance(finding, Unheard):
                self._on_unheard(child, finding)
            else:  # KillDue: the hung process has printed its stacks
                child.send_signal(signal.SIGKILL)

    def _on_hung(self, child: Child, hung: Hung) -> None:
        """No first beat, or no beat for hang_timeout: say what it was doing, signal it."""
        busy = self.poison.died_on(self.incarnation)
        on = f' while applying {busy.topic} {busy.ident}' if busy is not None else ''
        _logger.error(
            '%s %s: hung: no %s for %.1f s (limit %.1f s)%s; killing pid %d', LOG_PREFIX,
            self.id, hung.waiting_for, hung.stalled_s, hung.limit_s, on, child.pid,
        )
        self.sup.events_log.write(
            'hang', self.id, incarnation=self.incarnation,
            stalled_s=round(hung.stalled_s, 3),
            waiting_for=hung.waiting_for, topic=busy.topic if busy else None,
            source_ns=busy.ident[0] if busy else None, seq=busy.ident[1] if busy else None,
        )
        # SIGUSR1 for a heartbeat that stopped: faulthandler in the node prints every
        # thread's stack, where it hung, and SIGKILL follows (KillDue). SIGKILL at once for a
        # process that never beat: it has no stack worth printing.
        child.send_signal(hung.signal)

    def _on_unheard(self, child: Child, unheard: Unheard) -> None:
        """The process runs but its HELLO never arrived: replace it (a crash, recovered)."""
        _logger.error(
            '%s %s: pid %d has run %.1f s without its HELLO reaching the supervisor (its '
            'status publisher was never discovered); replacing it', LOG_PREFIX, self.id,
            child.pid, unheard.beating_s,
        )
        self.sup.events_log.write('unheard', self.id, incarnation=self.incarnation,
                                  beating_s=round(unheard.beating_s, 3))
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
        child = self.child
        if child is not None:
            for sig, grace in zip(
                (signal.SIGINT, signal.SIGTERM, signal.SIGKILL), (*STOP_GRACE, 5.0), strict=True
            ):
                child.send_signal(sig)
                try:
                    child.wait(timeout=grace)
                    break
                except Exception:
                    continue
        self.child = None
        self.sm.change_state(NodeState.STOPPED)


def _fields(message: StatusMessage) -> dict[str, Any]:
    """What a status carries but its kind and node, as it travelled: the fields of the
    ``hello`` and ``checkpoint`` events."""
    return {k: v for k, v in message.to_json().items() if k not in ('kind', 'node')}


def _restored_cut(hello: HelloStatus) -> int | None:
    """The last log segment the restored checkpoint holds: replay starts after it."""
    return None if hello.restored is None else hello.restored.cut


def _recovery_counts(stats: ReleasedStatus) -> dict[str, int]:
    """The node's counters the ``recovered`` event carries."""
    return {'applied': stats.applied, 'replayed': stats.replayed,
            'duplicates': stats.duplicates, 'muted': stats.muted,
            'ticks_replayed': stats.ticks_replayed, 'clock_fallbacks': stats.clock_fallbacks,
            'parameter_changes_replayed': stats.parameter_changes_replayed,
            'requests_replayed': stats.requests_replayed}
