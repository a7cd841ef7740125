"""The runtime core inside one supervised node process (docs/architecture.md, "While the node
runs").

:class:`NodeRuntime` holds the one lock that every user callback, applied message and
checkpoint snapshot runs under. It adopts the node's entities (``adopt_*``: publishers muted
until release, timers and services held until release and their events logged), restores the
newest valid checkpoint at start-up (``restore``), applies each message (``_apply``: written
ahead to the log, then the user's callback, under the lock), hears the supervisor on the
shadow topic and reports to it on its status socket (``_status``, status_socket.py); its
heartbeat and checkpoint schedule run on a side thread (pulse.py), nothing of RORY's in the
node's executor in steady state.

Where each input's messages come from, and when they are applied, is the router's
(routing.py); checkpoints and the log segments they cut are the checkpointer's
(checkpointer.py); how a node class gets its runtime is patching.py's.
"""

from __future__ import annotations

import atexit
import contextlib
import faulthandler
import functools
import inspect
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters, SetParametersAtomically
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from rosbags.interfaces import Qos
from std_msgs.msg import UInt8MultiArray

from . import (
    codec,
    event_clock,
    freshness,
    node_lifecycle,
    node_parameters,
    node_services,
    protocol,
    status_socket,
)
from .checkpointer import Checkpointer, node_clock_reading
from .errors import CheckpointError, CodecError, LogError, ProtocolError, RoryError
from .event_clock import EventClock, Reading
from .inflight import InFlightSlot, slot_path
from .log import SegmentStore, default_typestore
from .node_timers import NodeTimers, now_on
from .protocol import (
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
    CheckpointFailure,
    ErrorStatus,
    HelloStatus,
    InputsStatus,
    MessageId,
    Method,
    Mode,
    OpenedStatus,
    ReleasedStatus,
    RestoredCheckpoint,
    Status,
    SyncedStatus,
)
from .pulse import Pulse
from .qos import offered_qos
from .routing import Input, Router, Window
from .state import CheckpointSpec, write_state
from .store import Checkpoint, CheckpointStore

_logger = logging.getLogger('rory.runtime')

T = TypeVar('T')

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
        self.method = env.method
        self._logs = env.method.logs  # (read at every message: an attribute, not the property)
        self.init_depth = 0
        self.node: Node | None = None
        self.lock = threading.RLock()
        self.released = False
        # Outputs go out: at release, or under a release gate when the supervisor says OPEN.
        self.outputs_open = False
        # Per topic, the identities applied last: _apply adds to them, the router skips what
        # they hold, checkpoints copy them, a restore sets them.
        self.windows: dict[str, Window] = {}
        # The shadow topic's reader (made at start-up), until retire_shadow destroys it.
        self.shadow_subscription: Subscription | None = None
        # The node's timers by creation order (a logged tick names its timer by index), held
        # until release, then put back on their grids (node_timers.py).
        self.timers = NodeTimers(lambda: self.released, self._error)
        # The user's services by creation order: a logged request names its service by index.
        self.services: list[tuple[Service, Callable[[Any, Any], Any]]] = []
        # Clock readings inside events, recorded and replayed (only when messages are logged).
        self.clock: EventClock | None = None
        if self.method.logs:
            event_clock.install()
            self.clock = EventClock(self._log_reading, self._readings_unrecorded)
        # The node's own set_parameters_atomically, behind the wrapper that logs changes
        # from outside (set in on_constructed).
        self._set_parameters_atomically: Callable[[list[Parameter]], SetParametersResult] | None
        self._set_parameters_atomically = None
        self.publishers: list[Publisher] = []
        self._qos_lookups: dict[str, Callable[[], Sequence[Qos]]] = {}
        self.stats = {'applied': 0, 'replayed': 0, 'duplicates': 0, 'muted': 0, 'quarantined': 0,
                      'passed_by_relay': 0, 'ticks': 0, 'ticks_replayed': 0,
                      'clock_fallbacks': 0, 'parameter_changes': 0,
                      'parameter_changes_replayed': 0, 'requests': 0, 'requests_replayed': 0}
        # Each input topic's phase, and where its messages are applied from (routing.py).
        self.router = Router(
            recovering=env.mode == Mode.RECOVER and self.method.logs,
            quarantined=env.quarantined, lock=self.lock, windows=self.windows,
            stats=self.stats, apply=self._apply, replay_event=self._replay_event,
            error=self._error, status=self._status,
        )
        # What the node is applying right now, readable after a crash (poison detection).
        self.inflight = InFlightSlot(slot_path(env.store, env.node_id), env.incarnation)
        self.checkpoints = CheckpointStore(env.store, env.node_id)
        self.segments = SegmentStore(env.store, env.node_id)
        self.reported_errors: set[str] = set()
        self._group: MutuallyExclusiveCallbackGroup | None = None
        # Statuses go to the supervisor's socket, not over DDS (status_socket.py).
        self._status_sender = (None if env.status_socket is None
                               else status_socket.StatusSender(env.status_socket))
        self._startup_timer: Timer | None = None
        self._hello_sent = False
        # A user callback raised (the process is going down with it), or the exit-time
        # checkpoint is done: see close().
        self._callback_failed = False
        self._final_taken = False
        self._started = False
        # Callbacks run to their end (messages, ticks, requests, parameter changes, replayed or
        # live): the pulse reads it to know the executor is alive without waking it.
        self.progress = 0
        self.pulse = Pulse(lambda: None, lambda: None, lambda: 0, lambda: 0)  # on_constructed
        # The segment being written and the checkpoints that cut the log (checkpointer.py).
        self.checkpointer = Checkpointer(
            spec, self.method, env.node_id, env.incarnation, self.lock, self.checkpoints,
            self.segments, error=self._error, status=self._status, timers=self.timers.snapshot,
            failed=self._error,
        )
        atexit.register(self.close)

    @property
    def interval(self) -> float:
        """Seconds between checkpoints: the supervisor's setting, else keyvars.yaml's, else 2."""
        return self.env.interval or self.spec.checkpoint_interval or DEFAULT_INTERVAL

    # -- adoption of the user's entities ----------------------------------------------------

    def adopt_subscription(self, sub: Subscription) -> None:
        """Take over a user subscription: raw delivery through the router."""
        if self.router.adopt(sub, released=self.released) is None:
            return  # adopted already
        if self._hello_sent:
            # Made after start-up (a lifecycle node's on_configure): the ring must read it too.
            self._status(InputsStatus(
                inputs=tuple(i.spec for i in self.router.inputs.values())))

    def adopt_publisher(self, pub: Publisher) -> None:
        """Mute a user publisher while the node is isolated."""
        if pub in self.publishers:
            return
        self.publishers.append(pub)
        publish = pub.publish

        def gated_publish(msg: Any) -> None:
            if self.outputs_open:
                publish(msg)
            else:
                self.stats['muted'] += 1

        pub.publish = gated_publish  # type: ignore[method-assign]

    def adopt_timer(self, timer: Timer) -> None:
        """Hold a user timer until release, and run its callback under the runtime lock."""
        if getattr(timer, '_rory', False) or self.timers.known(timer):
            return
        callback = timer.callback
        if inspect.iscoroutinefunction(callback):
            raise RoryError('async timer callbacks are not supported yet')
        index = self.timers.adopt(timer, callback).index

        def locked_tick() -> Any:
            if not self.released:
                return None

            def record() -> None:
                self._write_record(protocol.TIMER_RECORD, time.time_ns(),
                                   int(event_clock.original_now(timer.clock).nanoseconds), index)
                self.stats['ticks'] += 1

            return self._live_event(record, callback)

        timer.callback = locked_tick
        timer._rory = True  # type: ignore[attr-defined]

    def adopt_service(self, srv: Service) -> None:
        """Hold a user service until release; log each request before its handler runs."""
        if any(srv is known for known, _ in self.services):
            return
        callback = srv.callback
        if inspect.iscoroutinefunction(callback):
            raise RoryError(f'async service callbacks are not supported yet ({srv.srv_name})')
        index = len(self.services)
        self.services.append((srv, callback))
        if not self.released:  # (one made after release serves at once)
            srv.callback_group = node_services.HeldUntilRelease(srv.callback_group,
                                                                lambda: self.released)

        def logged_request(request: Any, response: Any) -> Any:
            def record() -> None:
                self._write_record(protocol.REQUEST_RECORD, time.time_ns(), 0, index,
                                   node_services.pack_request(request),
                                   node_services.RECORD_TYPE)
                self.stats['requests'] += 1

            return self._live_event(record, lambda: callback(request, response))

        srv.callback = logged_request

    # -- start-up -------------------------------------------------------------------------------

    def on_constructed(self, node: Node) -> None:
        """The node object is complete: create RORY's own entities and schedule start-up."""
        if self._started:
            return
        self._started = True
        self.node = node
        self.watch_parameters(node)
        change_state = node_lifecycle.change_state_service(node)
        if change_state is not None:
            # Transitions from outside are requests like any service's: held, logged, replayed.
            self.adopt_service(change_state)
        self._group = MutuallyExclusiveCallbackGroup()
        if self.method.logs:
            # Loading the typestore costs ~0.1 s; do it before the first message needs it.
            threading.Thread(target=default_typestore, daemon=True).start()
        # The heartbeat and the checkpoint schedule: a side thread that posts to the node's
        # executor only when it must (pulse.py), no timer in its wait set. The supervisor kills
        # a node whose beat stops for its hang_timeout, after SIGUSR1 has made this process
        # print where every thread is (faulthandler), so the operator sees where it hung.
        with contextlib.suppress(ValueError, RuntimeError, OSError):
            faulthandler.register(signal.SIGUSR1, all_threads=True)
        self.inflight.beat()
        self.pulse = Pulse(lambda: node.executor, self.inflight.beat, lambda: self.progress,
                           functools.partial(now_on, node.get_clock()))
        self.pulse.start()
        # The first callback the executor runs is this one, so restoring here happens before
        # any user callback (user timers are held and user messages buffered until release).
        self._startup_timer = Node.create_timer(
            node, 0.0, self._startup, callback_group=self._group
        )

    def watch_parameters(self, node: Node) -> None:
        """Route parameter changes from outside through :meth:`_parameters_from_outside`.

        rclpy's parameter services call ``set_parameters_atomically`` on the node; an instance
        attribute of that name is what they find. Its two setting services are held until
        release like the node's own (``HeldUntilRelease``): a change requested while the node
        recovers waits, then is applied and logged in order.
        """
        for srv in node.services:
            if srv.srv_type in (SetParameters, SetParametersAtomically):
                srv.callback_group = node_services.HeldUntilRelease(srv.callback_group,
                                                                    lambda: self.released)
        original = node.set_parameters_atomically
        self._set_parameters_atomically = original

        def set_parameters_atomically(parameter_list: list[Parameter]) -> SetParametersResult:
            return self._parameters_from_outside(original, parameter_list)

        node.set_parameters_atomically = set_parameters_atomically  # type: ignore[method-assign]

    def _parameters_from_outside(
        self, original: Callable[[list[Parameter]], SetParametersResult],
        parameter_list: list[Parameter],
    ) -> SetParametersResult:
        """A parameter change: an input when it comes from outside an event."""
        if event_clock.in_event():
            return original(parameter_list)  # a callback's own change: replayed with it
        if not self.released:
            # Called directly (the services wait until release): not in order with the
            # replay, so refused rather than applied out of order.
            return SetParametersResult(
                successful=False, reason='[rory] the node is recovering (or not yet released); '
                'set it again once it is back')

        def record() -> None:
            self._write_record(protocol.PARAMETERS_RECORD, time.time_ns(), 0, 0,
                               node_parameters.pack(parameter_list), node_parameters.RECORD_TYPE)
            self.stats['parameter_changes'] += 1

        return self._live_event(record, lambda: original(parameter_list))

    def _live_event(self, record: Callable[[], None], run: Callable[[], T]) -> T:
        """Run a user callback (a tick, a request, a parameter change) as a live event: under
        the lock; where messages are logged, its record written first (write-ahead) and its
        clock readings logged; a raise remembered (no checkpoint at exit after it)."""
        with self.lock:
            clock = self.clock
            if clock is not None:
                record()
                clock.begin_live()
            try:
                return run()
            except BaseException:
                self._callback_failed = True
                raise
            finally:
                if clock is not None:
                    clock.end()
                self.progress += 1

    def _replayed_event(self, event_ns: int, readings: list[Reading],
                        run: Callable[[], T]) -> T:
        """Run a logged tick, request or parameter change again, under the lock, its clocks
        reading what they read live."""
        clock = self.clock
        assert clock is not None  # these are logged only where clocks are
        with self.lock:
            clock.begin_replay(event_ns, readings)
            try:
                return run()
            finally:
                clock.end()
                self.progress += 1

    def _replay_request(self, index: int, data: bytes, event_ns: int,
                        readings: list[Reading]) -> None:
        """A logged request to the user's service number ``index``, handled again; the response
        goes nowhere."""
        if index >= len(self.services):
            self._error(f'the log has a request to service {index}, but the node made '
                        f'{len(self.services)} service(s): request skipped')
            return
        srv, callback = self.services[index]
        srv_type: Any = srv.srv_type  # rclpy's annotation lacks Request and Response
        try:
            request = node_services.unpack_request(data, srv_type.Request)
        except ValueError as err:
            self._error(f'a logged request to {srv.srv_name} is unreadable: {err}')
            return
        self._replayed_event(event_ns, readings,
                             lambda: callback(request, srv_type.Response()))
        self.stats['requests_replayed'] += 1

    def _replay_parameters(self, data: bytes, event_ns: int, readings: list[Reading]) -> None:
        """A logged parameter change, applied again with the node's parameter callbacks."""
        original = self._set_parameters_atomically
        assert original is not None
        try:
            result = self._replayed_event(
                event_ns, readings, lambda: original(node_parameters.unpack(data)))
        except (ParameterException, ValueError) as err:
            self._error(f'a logged parameter change failed again in replay: {err}')
            return
        self.stats['parameter_changes_replayed'] += 1
        if not result.successful:
            self._error(f'a logged parameter change was refused in replay: {result.reason}')

    def _startup(self) -> None:
        assert self.node is not None
        if self._startup_timer is not None:
            self._startup_timer.cancel()
            self.node.destroy_timer(self._startup_timer)
            self._startup_timer = None
        self.timers.mark_start()
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
                callback_group=self._group,
                event_callbacks=_without_events_sub(),
            )
        self._status(HelloStatus(
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
            self._release(self.segments.next_number())

    def restore(self, refused: list[str]) -> RestoredCheckpoint | None:
        """S3 restore: load the newest checkpoint that passes every check into the node."""
        assert self.node is not None

        def on_refused(err: CheckpointError) -> None:
            refused.append(str(err))
            self._error(f'checkpoint refused: {err}')
            self.checkpoints.quarantine(err.path)

        while True:
            ckpt = self.checkpoints.latest_valid(
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
                with self.lock:
                    # Parameters first: their callbacks may set attributes; the key variables
                    # then get the values they had when the checkpoint was taken.
                    restored_parameters = self._restore_parameters(ckpt.parameters)
                    # Then the lifecycle state, through the node's transition callbacks: what
                    # they make exists again before the key variables are written.
                    lifecycle_error = node_lifecycle.restore(self.node, ckpt.lifecycle)
                    if lifecycle_error is not None:
                        self._error(lifecycle_error)
                    write_state(self.spec, self.node, codec.decode_vars(ckpt.vars_blob),
                                skip=frozenset(verdict.reset))
                    # Last: the timers as they were, those made after start-up made again
                    # and bound to the attributes that held them.
                    self._restore_timers(ckpt.timers)
            except CodecError as err:
                # Checksum was fine but the payload is not ours: set it aside, try the older one.
                on_refused(CheckpointError(self.checkpoints.path(ckpt.seq), str(err)))
                continue
            with self.lock:
                for topic, idents in ckpt.windows.items():
                    inp = self.router.inputs.get(topic)
                    size = protocol.window_size(inp.spec) if inp else len(idents) + 64
                    self.windows[topic] = Window(size, ((s, q) for s, q in idents))
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
            self.timers.restore(data, self.node)
        except ValueError as err:  # a damaged checkpoint
            self._error(f'checkpoint timers unreadable, none restored: {err}')

    def _restore_parameters(self, data: bytes) -> list[str]:
        """Set the checkpoint's parameter values that differ from this process's."""
        if not data or self.node is None:
            return []
        try:
            restored, refused = node_parameters.restore(self.node, data)
        except ValueError as err:  # a damaged checkpoint
            self._error(f'checkpoint parameters unreadable, none restored: {err}')
            return []
        for line in refused:
            self._error(line)
        return restored

    # -- the shadow topic ---------------------------------------------------------------------

    def _on_envelope(self, raw: bytes, _info: dict[str, Any]) -> None:
        try:
            envelope = protocol.unpack(raw, self.env.secret)
        except ProtocolError as err:
            shadow = protocol.replay_topic(self.env.node_id, self.env.incarnation,
                                           self.env.channel)
            self._error(f'malformed envelope on {shadow}: {err}')
            return
        if envelope.incarnation != self.env.incarnation:
            return  # meant for an earlier process of this node
        if isinstance(envelope, protocol.Sync):
            counts = {topic: inp.sub.get_publisher_count()
                      for topic, inp in self.router.inputs.items()}
            self._status(SyncedStatus(nonce=envelope.nonce, live_publishers=counts))
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
        if self.released:  # (again if OPEN came twice: the supervisor resends until it hears)
            self.outputs_open = True
            self._status(OpenedStatus(muted=self.stats['muted']))

    def _replay_event(self, msg: protocol.Msg, readings: list[Reading]) -> None:
        """A logged tick, request or parameter change from the shadow topic, run again with the
        clock ``readings`` it took live."""
        if msg.topic == protocol.TIMER_RECORD:
            self._replay_tick(msg.seq, msg.recv_ns, msg.source_ns, readings)
        elif msg.topic == protocol.PARAMETERS_RECORD:
            self._replay_parameters(msg.data, msg.recv_ns, readings)
        else:
            self._replay_request(msg.seq, msg.data, msg.recv_ns, readings)

    def _replay_tick(self, index: int, event_ns: int, tick_ns: int,
                     readings: list[Reading]) -> None:
        """One logged tick of the user's timer number ``index`` (at ``tick_ns`` on its clock),
        replayed."""
        callback = self.timers.callback(index)
        if callback is None:
            self._error(f'the log has a tick of timer {index}, but the node has no timer '
                        f'{index} ({self.timers.count()} made): tick skipped')
            return
        self.timers.ticked(index, tick_ns)
        self._replayed_event(event_ns, readings, callback)
        self.stats['ticks_replayed'] += 1

    # -- applying a message, and the write-ahead log ------------------------------------------

    def _apply(
        self, inp: Input, raw: bytes, info: dict[str, Any], ident: MessageId, readings:
        Iterable[Reading] = (), *, log: bool
    ) -> None:
        """Run the user's callback on one message under the lock; ``log``: a live message,
        written to the log first; else a replayed one, whose clock ``readings`` it gets."""
        # rclpy's deserialize_message less its type-support check, made once at adoption
        # (Router.adopt): a Python call fewer on every message.
        msg = raw if inp.user_raw else _rclpy.rclpy_deserialize(raw, inp.msg_type)
        received_ns = int(info['received_timestamp'])
        clock = self.clock
        with self.lock:
            if log and self._logs:
                self._log(inp, raw, info, ident)
            self.inflight.busy(inp.topic, ident, received_ns)
            if clock is not None:
                if log:
                    clock.begin_live()
                else:
                    clock.begin_replay(received_ns, readings)
            try:
                if inp.with_info:
                    inp.callback(msg, info)
                else:
                    inp.callback(msg)
            except BaseException:
                self._callback_failed = True
                raise
            finally:
                if clock is not None:
                    clock.end()
            self.inflight.idle()
            self.windows[inp.topic].add(ident)
            self.stats['applied'] += 1
            self.progress += 1

    def _log(self, inp: Input, raw: bytes, info: dict[str, Any], ident: MessageId) -> None:
        writer = self.checkpointer.segment()
        try:
            writer.write(
                inp.topic, inp.type_name, int(info['received_timestamp']), ident[0], ident[1], raw,
                offered_qos=self._offered_qos_of(inp.topic),
            )
        except LogError as err:
            self._error(f'cannot log a message of {inp.topic}: {err}')

    def _offered_qos_of(self, topic: str) -> Callable[[], Sequence[Qos]] | None:
        """What asks the graph for ``topic``'s offered QoS when a segment first logs it (made
        once per topic, not at every message)."""
        lookup = self._qos_lookups.get(topic)
        if lookup is None and self.node is not None:
            lookup = functools.partial(offered_qos, self.node, topic)
            self._qos_lookups[topic] = lookup
        return lookup

    def _write_record(self, record: str, at_ns: int, value_ns: int, detail: int,
                      data: bytes | None = None,
                      record_type: str = protocol.EVENT_RECORD_TYPE) -> None:
        """Log a tick (``detail``: the timer's index), a clock reading (its clock type) or a
        parameter change (``data``)."""
        writer = self.checkpointer.segment()
        try:
            writer.write(record, record_type, at_ns, value_ns, detail,
                         protocol.pack_time_record(value_ns) if data is None else data)
        except LogError as err:
            self._error(f'cannot log {record}: {err}')

    def _log_reading(self, reading: Reading) -> None:
        self._write_record(protocol.CLOCK_RECORD, reading.at_ns, reading.value_ns,
                           reading.clock_type)

    def _readings_unrecorded(self) -> None:
        self._error(f'a callback read its clocks more than {event_clock.MAX_READINGS_PER_EVENT} '
                    'times in one event: the rest are not logged, and a replay of that event '
                    'reads them from the event\'s time')

    # -- release (S4) ---------------------------------------------------------------------------

    def _release(self, next_segment: int) -> None:
        """S4 on the node's side: outputs, timers and checkpoints on; buffered input applied."""
        assert self.node is not None
        if self.released:
            return
        overdue: list[Callable[[], Any]] = []
        with self.lock:
            self.open_gates(next_segment)
            self._unhold_services()
            # Each timer back on its grid; a tick that fell due while the node was down runs
            # once, on the executor, after the release (as an overdue timer in a stalled one).
            self.timers.release(overdue.append)
            if self.method.checkpoints or self.method.logs:
                tick = self.checkpoint_tick if self.method.checkpoints else self._rotate_tick
                self.pulse.schedule_checkpoints(self.interval, tick)
        if self.method.checkpoints:
            # On the I/O thread: the first snapshot's copies land in memory already written.
            self.checkpointer.io.submit(
                functools.partial(self.checkpointer.prime_array_pool, self.node))
        if self.clock is not None:
            self.stats['clock_fallbacks'] = self.clock.fallbacks
        self._status(ReleasedStatus(**self.stats))
        executor = self.node.executor
        for tick in overdue:
            if executor is not None:
                executor.create_task(tick)
            else:
                tick()

    def _unhold_services(self) -> None:
        """Give each held service its own callback group back: released, the hold would
        only add a Python call for each of them to every wait of the executor."""
        assert self.node is not None
        for srv in self.node.services:
            if isinstance(srv.callback_group, node_services.HeldUntilRelease):
                srv.callback_group = srv.callback_group.inner

    def open_gates(self, next_segment: int) -> None:
        """Unmute, log from ``next_segment`` on, and apply what live readers hold for the topics
        not taken from the shadow topic (all of them after a fresh start): the part of the
        release (:meth:`_release`) that needs no rclpy node."""
        self.released = True
        self.outputs_open = not self.env.gated
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
        if (self.shadow_subscription is None or not self.released or self.router.shadow_needed()
                or self.node is None or not self.outputs_open):
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
        for line in self.timers.unbuildable(self.node):
            self._error(line)
        persist = self.checkpointer.take(self.node, self.windows)
        if persist is not None:
            self.checkpointer.io.submit(persist)

    # -- reporting ----------------------------------------------------------------------------

    def _status(self, status: Status) -> None:
        if self._status_sender is None:
            return
        self._status_sender.send(protocol.encode_status(
            status, self.env.node_id, self.env.incarnation, key=self.env.secret,
            sent_ns=time.time_ns()))

    def _error(self, message: str, checkpoint: CheckpointFailure | None = None) -> None:
        """Log ``message`` and send it as an ERROR status, once; ``checkpoint``: it says a
        checkpoint was not taken, and why (the supervisor reads that, not the message)."""
        if message in self.reported_errors:
            return
        self.reported_errors.add(message)
        if self.node is not None and self.node.context.ok():
            self.node.get_logger().error(f'[rory] {message}')
        else:
            # With its context shut down (rclpy's SIGINT handler does it before the exit-time
            # checkpoint), the node's logger adds a failure to publish on /rosout.
            _logger.error('[rory] %s', message)
        self._status(ErrorStatus(message=message, checkpoint=checkpoint))

    def close(self) -> None:
        """Finish background I/O and seal the open segment, so a clean exit leaves complete
        bags; after a clean stop (SIGINT, SIGTERM), take a last checkpoint first."""
        self.pulse.stop()
        self.checkpointer.io.drain()
        if (self.released and self.method.checkpoints and self.node is not None
                and not self._callback_failed and not self._final_taken):
            # The node stopped between two callbacks (none raised): its state now is what a
            # next run with --resume, `rory inspect` or `rory bundle` should find. After an
            # exception a callback may have been cut halfway: no checkpoint of that.
            self._final_taken = True
            try:
                persist = self.checkpointer.take(self.node, self.windows)
                if persist is not None:
                    persist()
            except Exception as err:  # at exit nothing may propagate; the older one stays
                _logger.error('[rory] no checkpoint at exit: %s: %s', type(err).__name__, err)
        self.checkpointer.close_segment()
        if self._status_sender is not None:
            self._status_sender.close()  # (the exit checkpoint's status with the rest)
