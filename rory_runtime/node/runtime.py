"""The runtime core inside one supervised node process (docs/architecture.md, "While the node
runs").

:class:`NodeRuntime` wires the parts and runs the node's start-up and release: it restores the
newest valid checkpoint at start-up (``restore``), hears the supervisor on the shadow topic and
releases the node (S4). The parts, each in its module:

* routing.py, the :class:`Router`: each input topic's phase, and when its messages are applied;
* applier.py, the :class:`Applier`: applies each event under the one lock, written ahead to
  the log, with its clock records, windows and counters; a live message goes from the
  subscription straight to it;
* gating.py, the :class:`OutputGate`: publishers muted, timers and services held until release;
* checkpointer.py, the :class:`Checkpointer`: checkpoints and the log segments they cut;
* reporting.py, the :class:`Reporter`: statuses and errors to the supervisor's socket;
* pulse.py: the heartbeat and checkpoint schedule on a side thread, nothing of RORY's in the
  node's executor in steady state.

How a node class gets its runtime is patching.py's.
"""

from __future__ import annotations

import atexit
import contextlib
import faulthandler
import functools
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from std_msgs.msg import UInt8MultiArray

from .. import codec, freshness, protocol, status_socket
from ..errors import CheckpointError, CodecError, ProtocolError, RoryError
from ..inflight import InFlightSlot, slot_path
from ..log import SegmentStore, default_typestore
from ..protocol import (
    DEFAULT_CHANNEL,
    ENV_CHANNEL,
    ENV_GATED,
    ENV_INCARNATION,
    ENV_INTERVAL,
    ENV_METHOD,
    ENV_MODE,
    ENV_NODE,
    ENV_QUARANTINE,
    ENV_SECRET,
    ENV_STATUS,
    ENV_STORE,
    HelloStatus,
    InputsStatus,
    MessageId,
    Method,
    Mode,
    OpenedStatus,
    ReleasedStatus,
    RestoredCheckpoint,
    SyncedStatus,
)
from ..store import Checkpoint, CheckpointStore
from . import lifecycle as node_lifecycle
from . import parameters as node_parameters
from .applier import Applier, Window
from .checkpointer import Checkpointer, node_clock_reading
from .gating import OutputGate
from .pulse import Pulse
from .reporting import Reporter
from .routing import Router
from .state import CheckpointSpec, write_state
from .timers import now_on

_logger = logging.getLogger('rory.runtime')


DEFAULT_INTERVAL = 2.0
SIM_CLOCK_WAIT = 5.0  # seconds a recovery under use_sim_time waits for /clock to judge ages


# RORY's own shadow subscription takes no QoS event handlers: rclpy gives each entity default
# ones (incompatible QoS and type warnings), every one a waitable that each executor wait of the
# node's own callbacks must add and poll. Both ends are RORY's, with QoS from protocol.py, so
# the warnings could only ever be about RORY itself.
def _without_events_sub() -> SubscriptionEventCallbacks:
    return SubscriptionEventCallbacks(use_default_callbacks=False)


@dataclass(frozen=True)
class RuntimeEnv:
    """How the supervisor configured this process."""

    node_id: str
    store: Path
    incarnation: int
    method: Method
    mode: Mode
    interval: float | None  # None: the supervisor config left it to the node's keyvars
    quarantined: frozenset[tuple[str, MessageId]] = frozenset()
    secret: bytes | None = None  # the run's key: envelopes and statuses are signed with it
    channel: str = DEFAULT_CHANNEL  # the namespace of its two topics with the supervisor
    gated: bool = False  # a release gate: outputs stay muted after release until OPEN
    status_socket: str | None = None  # the supervisor's (status_socket.py); None: statuses dropped

    @classmethod
    def from_environ(cls, environ: dict[str, str] | None = None) -> RuntimeEnv | None:
        """Read the supervisor's settings, or None when the process is not supervised.

        Raises:
            RoryError: RORY_NODE is set but the other settings are missing or invalid.
        """
        env = dict(os.environ if environ is None else environ)
        node_id = env.get(ENV_NODE)
        if not node_id:
            return None
        try:
            return cls(
                node_id=node_id,
                store=Path(env[ENV_STORE]),
                incarnation=int(env[ENV_INCARNATION]),
                method=Method(env[ENV_METHOD]),
                mode=Mode(env[ENV_MODE]),
                interval=float(env[ENV_INTERVAL]) if env.get(ENV_INTERVAL) else None,
                quarantined=frozenset(
                    (str(topic), (int(source_ns), int(seq)))
                    for topic, source_ns, seq in json.loads(env.get(ENV_QUARANTINE) or '[]')
                ),
                secret=bytes.fromhex(env[ENV_SECRET]) if env.get(ENV_SECRET) else None,
                channel=env.get(ENV_CHANNEL) or DEFAULT_CHANNEL,
                gated=env.get(ENV_GATED) == '1',
                status_socket=(status_socket.from_env(env[ENV_STATUS])
                               if env.get(ENV_STATUS) else None),
            )
        except (KeyError, ValueError, TypeError) as err:
            raise RoryError(f'{ENV_NODE} is set but the environment is bad: {err}') from None




def _process_start_ns() -> int | None:
    """Wall-clock start of this process (for the restart part of recovery time)."""
    try:
        ticks = int(Path('/proc/self/stat').read_text().rsplit(')', 1)[1].split()[19])
        boot = next(
            int(line.split()[1])
            for line in Path('/proc/stat').read_text().splitlines()
            if line.startswith('btime')
        )
    except (OSError, ValueError, IndexError, StopIteration):
        return None
    return (boot * 1_000_000_000) + ticks * 1_000_000_000 // os.sysconf('SC_CLK_TCK')


class NodeRuntime:
    """RORY's state inside one supervised node."""

    @classmethod
    def of(cls, node: Node, env: RuntimeEnv) -> NodeRuntime:
        """The runtime of a node, created on first use (before Node.__init__ has run)."""
        runtime: NodeRuntime | None = node.__dict__.get('_rory_runtime')
        if runtime is None:
            runtime = cls(type(node).__rory_spec__, env)  # type: ignore[attr-defined]
            node.__dict__['_rory_runtime'] = runtime
        return runtime

    def __init__(self, spec: CheckpointSpec, env: RuntimeEnv) -> None:
        self.spec = spec
        self.env = env
        self.init_depth = 0
        self.node: Node | None = None
        # Statuses and errors, for every part (reporting.py).
        self.reporter = Reporter(env.node_id, env.incarnation, env.secret, env.status_socket)
        error = self.reporter.error
        # One lock: every user callback, applied message and checkpoint snapshot runs under it.
        lock = threading.RLock()
        # The segment being written and the checkpoints that cut the log (checkpointer.py).
        self.checkpointer = Checkpointer(
            spec, env.method, env.node_id, env.incarnation, lock,
            CheckpointStore(env.store, env.node_id), SegmentStore(env.store, env.node_id),
            error=error, status=self.reporter.status, failed=error,
        )
        # Applies each event under the lock, logged ahead; windows and counters (applier.py).
        # The in-flight slot: what the node is applying right now, readable after a crash.
        self.applier = Applier(
            lock=lock, logs=env.method.logs, quarantined=env.quarantined,
            inflight=InFlightSlot(slot_path(env.store, env.node_id), env.incarnation),
            segments=self.checkpointer, error=error,
        )
        # Publishers muted, timers and services held until release (gating.py).
        self.gate = OutputGate(self.applier, gated=env.gated, error=error)
        # A checkpoint keeps the timers too; they are the gate's, made after the checkpointer
        # (the applier writes to the checkpointer's segments, the gate runs events through it).
        self.checkpointer.timers = self.gate.timers.snapshot
        # Each input topic's phase, and where its messages are applied from (routing.py).
        self.router = Router(
            recovering=env.mode == Mode.RECOVER and env.method.logs, applier=self.applier,
            replay_event=self.gate.replay_event, error=error, status=self.reporter.status,
        )
        # The shadow topic's reader (made at start-up), until retire_shadow destroys it.
        self.shadow_subscription: Subscription | None = None
        # RORY's start-up timer, until its first (and only) callback destroys it.
        self._startup_timer: Timer | None = None
        self._hello_sent = False
        self._final_taken = False  # the exit-time checkpoint is done: see close()
        self.pulse = Pulse(lambda: None, lambda: None, lambda: 0, lambda: 0)  # on_constructed
        atexit.register(self.close)

    @property
    def method(self) -> Method:
        """What the node keeps (the supervisor's setting)."""
        return self.env.method

    @property
    def interval(self) -> float:
        """Seconds between checkpoints: the supervisor's setting, else keyvars.yaml's, else 2."""
        return self.env.interval or self.spec.checkpoint_interval or DEFAULT_INTERVAL

    @property
    def released(self) -> bool:
        """S4 done: timers, services and the log's numbering are the node's own again."""
        return self.gate.released

    # -- adoption of the user's entities ----------------------------------------------------

    def adopt_subscription(self, sub: Subscription) -> None:
        """Take over a user subscription: raw delivery through the router."""
        if self.router.adopt(sub, released=self.gate.released) is None:
            return  # adopted already
        if self._hello_sent:
            # Made after start-up (a lifecycle node's on_configure): the ring must read it too.
            self.reporter.status(InputsStatus(
                inputs=tuple(i.spec for i in self.router.inputs.values())))

    def adopt_publisher(self, pub: Publisher) -> None:
        """Mute a user publisher while the node is isolated."""
        self.gate.adopt_publisher(pub)

    def adopt_timer(self, timer: Timer) -> None:
        """Hold a user timer until release, and run its callback under the runtime lock."""
        self.gate.adopt_timer(timer)

    def adopt_service(self, srv: Service) -> None:
        """Hold a user service until release; log each request before its handler runs."""
        self.gate.adopt_service(srv)

    # -- start-up -------------------------------------------------------------------------------

    def on_constructed(self, node: Node) -> None:
        """The node object is complete: create RORY's own entities and schedule start-up."""
        if self.node is not None:
            return
        self.node = node
        self.applier.node = node
        self.reporter.node = node
        self.gate.watch_parameters(node)
        change_state = node_lifecycle.change_state_service(node)
        if change_state is not None:
            # Transitions from outside are requests like any service's: held, logged, replayed.
            self.adopt_service(change_state)
        if self.method.logs:
            # Loading the typestore costs ~0.1 s; do it before the first message needs it.
            threading.Thread(target=default_typestore, daemon=True).start()
        # The heartbeat and the checkpoint schedule: a side thread that posts to the node's
        # executor only when it must (pulse.py), no timer in its wait set. The supervisor kills
        # a node whose beat stops for its hang_timeout, after SIGUSR1 has made this process
        # print where every thread is (faulthandler), so the operator sees where it hung.
        with contextlib.suppress(ValueError, RuntimeError, OSError):
            faulthandler.register(signal.SIGUSR1, all_threads=True)
        inflight, applier = self.applier.inflight, self.applier
        inflight.beat()
        self.pulse = Pulse(lambda: node.executor, inflight.beat, lambda: applier.progress,
                           functools.partial(now_on, node.get_clock()))
        self.pulse.start()
        # The first callback the executor runs is this one, so restoring here happens before
        # any user callback (user timers are held and user messages buffered until release).
        # RORY's transient entities (this timer, then the shadow topic's reader) share one
        # mutually exclusive callback group.
        self._startup_timer = Node.create_timer(
            node, 0.0, self._startup, callback_group=MutuallyExclusiveCallbackGroup()
        )

    def _startup(self) -> None:
        assert self.node is not None and self._startup_timer is not None
        group = self._startup_timer.callback_group
        self._startup_timer.cancel()
        self.node.destroy_timer(self._startup_timer)
        self._startup_timer = None
        self.gate.timers.mark_start()
        began = time.perf_counter()
        restored: RestoredCheckpoint | None = None
        refused: list[str] = []
        if self.env.mode == Mode.RECOVER and self.method.checkpoints:
            restored = self.restore(refused)
        restore_ms = (time.perf_counter() - began) * 1000.0
        self.checkpointer.number_from_store()
        if self.method.logs or self.env.gated:
            on_envelope: Any = self._on_envelope  # rclpy's annotation omits (msg, info)
            self.shadow_subscription = Node.create_subscription(
                self.node,
                UInt8MultiArray,
                protocol.replay_topic(self.env.node_id, self.env.incarnation, self.env.channel),
                on_envelope,
                protocol.REPLAY_QOS,
                raw=True,
                callback_group=group,
                event_callbacks=_without_events_sub(),
            )
        self.reporter.status(HelloStatus(
            mode=self.env.mode,
            method=self.method,
            pid=os.getpid(),
            manifest=self.spec.manifest,
            inputs=tuple(inp.spec for inp in self.router.inputs.values()),
            restored=restored,
            refused=tuple(refused),
            restore_ms=restore_ms,
            process_start_ns=_process_start_ns(),
            interval=self.interval,
            replay=self.spec.replay,
            # What its participant was made with (a fork's /proc/PID/environ shows the
            # supervisor's environment at its start, not this process's).
            dds_profile=(os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
                         or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE')),
            dds_transports=os.environ.get('FASTDDS_BUILTIN_TRANSPORTS'),
        ))
        self._hello_sent = True
        if restored is not None and restored.freshness.refused:
            # A stale variable whose rule is refuse: the node must not run on what it has;
            # the supervisor ends this process and holds the safe state.
            return
        if not self.method.logs:
            # restart and checkpoint have nothing to replay: release right away.
            self._release(self.checkpointer.segments.next_number())

    def restore(self, refused: list[str]) -> RestoredCheckpoint | None:
        """S3 restore: load the newest checkpoint that passes every check into the node."""
        assert self.node is not None
        checkpoints = self.checkpointer.checkpoints
        lock = self.applier.lock

        def on_refused(err: CheckpointError) -> None:
            refused.append(str(err))
            self.reporter.error(f'checkpoint refused: {err}')
            checkpoints.quarantine(err.path)

        while True:
            ckpt = checkpoints.latest_valid(
                expect_manifest=self.spec.manifest, on_refused=on_refused
            )
            if ckpt is None:
                return None
            verdict = self._judge(ckpt)
            if verdict.refused:
                return RestoredCheckpoint(seq=ckpt.seq, cut=ckpt.cut, created_ns=ckpt.created_ns,
                                          parameters=(), lifecycle=None,
                                          freshness=verdict)
            try:
                with lock:
                    # Parameters first: their callbacks may set attributes; the key variables
                    # then get the values they had when the checkpoint was taken.
                    restored_parameters = self._restore_parameters(ckpt.parameters)
                    # Then the lifecycle state, through the node's transition callbacks: what
                    # they make exists again before the key variables are written.
                    lifecycle_error = node_lifecycle.restore(self.node, ckpt.lifecycle)
                    if lifecycle_error is not None:
                        self.reporter.error(lifecycle_error)
                    write_state(self.spec, self.node, codec.decode_vars(ckpt.vars_blob),
                                skip=frozenset(verdict.reset))
                    # Last: the timers as they were, those made after start-up made again
                    # and bound to the attributes that held them.
                    self._restore_timers(ckpt.timers)
            except CodecError as err:
                # Checksum was fine but the payload is not ours: set it aside, try the older one.
                on_refused(CheckpointError(checkpoints.path(ckpt.seq), str(err)))
                continue
            with lock:
                # (Before the release that makes a topic LIVE: Applier.live_path binds these.)
                for topic, idents in ckpt.windows.items():
                    inp = self.router.inputs.get(topic)
                    size = protocol.window_size(inp.spec) if inp else len(idents) + 64
                    self.applier.windows[topic] = Window(size, ((s, q) for s, q in idents))
                self.checkpointer.resume_after(ckpt.cut)
            return RestoredCheckpoint(seq=ckpt.seq, cut=ckpt.cut, created_ns=ckpt.created_ns,
                                      parameters=tuple(restored_parameters),
                                      lifecycle=node_lifecycle.state_of(self.node) or None,
                                      freshness=verdict)

    def _judge(self, ckpt: Checkpoint) -> freshness.Verdict:
        """Which of the checkpoint's variables are fresh enough to restore (freshness.py)."""
        now = self._clock_reading()
        if now.sim and now.ns <= 0 and self.spec.freshness:
            # Simulation time that has not ticked in this process yet: wait for /clock.
            now = freshness.ClockReading(self._first_sim_clock_ns(SIM_CLOCK_WAIT), True)
        taken = freshness.ClockReading(ckpt.clock_ns, ckpt.sim_time) if ckpt.clock_ns else None
        if taken is None and not now.sim:  # a checkpoint from before the clock was kept
            taken = freshness.ClockReading(ckpt.created_ns, False)
        return freshness.judge(self.spec.keys(), self.spec.freshness, taken, now)

    def _clock_reading(self) -> freshness.ClockReading:
        """The node's own ROS clock, read live (never a replayed reading)."""
        assert self.node is not None
        return node_clock_reading(self.node)

    def _first_sim_clock_ns(self, timeout: float) -> int:
        """The time of the next /clock message, 0 if none comes within ``timeout``."""
        assert self.node is not None
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock as ClockMsg

        # RORY's own reader (not adopted as an input), as rclpy's TimeSource subscribes.
        sub = Node.create_subscription(
            self.node, ClockMsg, '/clock', lambda _msg: None,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT),
            event_callbacks=_without_events_sub())
        try:
            wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, self.node.context.handle)
            wait_set.clear_entities()
            wait_set.add_subscription(sub.handle)
            wait_set.wait(int(timeout * 1e9))
            if sub.handle.pointer in wait_set.get_ready_entities('subscription'):
                taken = sub.handle.take_message(ClockMsg, False)
                if taken is not None:
                    stamp = taken[0].clock
                    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
            return 0
        finally:
            self.node.destroy_subscription(sub)

    def _restore_timers(self, data: bytes) -> None:
        if not data or self.node is None:
            return
        try:
            self.gate.timers.restore(data, self.node)
        except ValueError as err:  # a damaged checkpoint
            self.reporter.error(f'checkpoint timers unreadable, none restored: {err}')

    def _restore_parameters(self, data: bytes) -> list[str]:
        """Set the checkpoint's parameter values that differ from this process's."""
        if not data or self.node is None:
            return []
        try:
            restored, refused = node_parameters.restore(self.node, data)
        except ValueError as err:  # a damaged checkpoint
            self.reporter.error(f'checkpoint parameters unreadable, none restored: {err}')
            return []
        for line in refused:
            self.reporter.error(line)
        return restored

    # -- the shadow topic ---------------------------------------------------------------------

    def _on_envelope(self, raw: bytes, _info: dict[str, Any]) -> None:
        try:
            envelope = protocol.unpack(raw, self.env.secret)
        except ProtocolError as err:
            shadow = protocol.replay_topic(self.env.node_id, self.env.incarnation,
                                           self.env.channel)
            self.reporter.error(f'malformed envelope on {shadow}: {err}')
            return
        if envelope.incarnation != self.env.incarnation:
            return  # meant for an earlier process of this node
        if isinstance(envelope, protocol.Sync):
            counts = {topic: inp.sub.get_publisher_count()
                      for topic, inp in self.router.inputs.items()}
            self.reporter.status(SyncedStatus(nonce=envelope.nonce, live_publishers=counts))
        elif isinstance(envelope, protocol.Msg):
            self.router.from_shadow(envelope)
        elif isinstance(envelope, protocol.Alive):
            self.router.relay_alive()
        elif isinstance(envelope, protocol.Open):
            self._open_outputs()
        else:
            self._release(envelope.next_segment)

    def _open_outputs(self) -> None:
        """The release gate opened: what the node publishes from now on goes out."""
        if self.gate.open_outputs():
            self.reporter.status(OpenedStatus(muted=self.applier.stats['muted']))

    # -- release (S4) ---------------------------------------------------------------------------

    def _release(self, next_segment: int) -> None:
        """S4 on the node's side: outputs, timers and checkpoints on; buffered input applied."""
        assert self.node is not None
        if self.gate.released:
            return
        overdue: list[Callable[[], Any]] = []
        with self.applier.lock:
            self.open_gates(next_segment)
            # Each timer back on its grid; a tick that fell due while the node was down runs
            # once, on the executor, after the release (as an overdue timer in a stalled one).
            self.gate.release_held(self.node, overdue.append)
            if self.method.checkpoints or self.method.logs:
                tick = self.checkpoint_tick if self.method.checkpoints else self._rotate_tick
                self.pulse.schedule_checkpoints(self.interval, tick)
        if self.method.checkpoints:
            # On the I/O thread: the first snapshot's copies land in memory already written.
            self.checkpointer.io.submit(
                functools.partial(self.checkpointer.prime_array_pool, self.node))
        self.applier.count_clock_fallbacks()
        self.reporter.status(ReleasedStatus(**self.applier.stats))
        executor = self.node.executor
        for tick in overdue:
            if executor is not None:
                executor.create_task(tick)
            else:
                tick()

    def open_gates(self, next_segment: int) -> None:
        """Unmute, log from ``next_segment`` on, and apply what live readers hold for the topics
        not taken from the shadow topic (all of them after a fresh start): the part of the
        release (:meth:`_release`) that needs no rclpy node."""
        self.gate.open()
        self.checkpointer.log_from(next_segment)
        self.router.release()

    # -- checkpoints --------------------------------------------------------------------------

    def retire_shadow(self) -> None:
        """Destroy the shadow subscription once nothing can come on it any more: released, every
        topic handed over to its live reader, no relayed message waiting for a subscription.

        Until a crash it would only lengthen every executor wait of the node (a subscription
        and its place in the wait set); the supervisor sends a process nothing after that but
        a release gate's OPEN, and a recovered process makes its own. Called from the periodic
        tick, never from the subscription's own callback.
        """
        if (self.shadow_subscription is None or not self.gate.released
                or self.router.shadow_needed() or self.node is None
                or not self.gate.outputs_open):
            return  # (outputs still muted: the release gate's OPEN comes on it)
        Node.destroy_subscription(self.node, self.shadow_subscription)
        self.shadow_subscription = None

    def _rotate_tick(self) -> None:
        # replay method: no checkpoints, but keep segments bounded in size.
        self.retire_shadow()
        self.checkpointer.rotate_and_close()

    def checkpoint_tick(self) -> None:
        """The checkpoint timer (methods that checkpoint): snapshot the node under the lock,
        write it on the I/O thread."""
        self.retire_shadow()
        assert self.node is not None
        for line in self.gate.timers.unbuildable(self.node):
            self.reporter.error(line)
        persist = self.checkpointer.take(self.node, self.applier.windows)
        if persist is not None:
            self.checkpointer.io.submit(persist)

    def close(self) -> None:
        """Finish background I/O and seal the open segment, so a clean exit leaves complete
        bags; after a clean stop (SIGINT, SIGTERM), take a last checkpoint first."""
        self.pulse.stop()
        self.checkpointer.io.drain()
        if (self.gate.released and self.method.checkpoints and self.node is not None
                and not self.applier.callback_failed and not self._final_taken):
            # The node stopped between two callbacks (none raised): its state now is what a
            # next run with --resume, `rory inspect` or `rory bundle` should find. After an
            # exception a callback may have been cut halfway: no checkpoint of that.
            self._final_taken = True
            try:
                persist = self.checkpointer.take(self.node, self.applier.windows)
                if persist is not None:
                    persist()
            except Exception as err:  # at exit nothing may propagate; the older one stays
                _logger.error('[rory] no checkpoint at exit: %s: %s', type(err).__name__, err)
        self.checkpointer.close_segment()
        self.reporter.close()  # (the exit checkpoint's status with the rest)
