"""``rory supervise``: runs instrumented nodes and recovers them when they crash.

Threads: the main thread owns all decisions (it handles one event at a time from a queue and is
the only one that spawns processes); an rclpy executor thread delivers status messages from the
nodes; one reaper thread per process waits for it to end; the ring thread takes messages for
recovering nodes; one streamer thread per recovery feeds a shadow topic.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import secrets
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any, Literal

import rclpy
import rclpy.utilities
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import UInt8MultiArray
from std_srvs.srv import Trigger

from .. import protocol
from ..dds import fast_rediscovery_env
from ..errors import ProtocolError, RoryError
from ..fsutil import make_private_dir
from ..inflight import read_beat
from ..log import default_typestore
from ..threads import name_this_thread
from .config import SupervisorConfig, check_store, store_error
from .diagnostics import Reporter
from .events import EventLog, RosoutHandler
from .inbox import StatusInbox
from .loop_events import ChildExited, Event, GateCall, Released, StatusReceived, Stop, ask_gate
from .managed_node import ManagedNode
from .output import OutputPrefixer
from .parameters import NODE_NAME as SUPERVISOR_NODE
from .parameters import apply_parameters, own_ros_args
from .ports import EnvelopePort
from .process import Launcher
from .ring import Ring, RingContext
from .run_marker import PreviousRun, RunMarker, make_room_for_previous
from .safety import SafeState
from .standby import ForkLauncher
from .states import LOG_PREFIX, NodeState
from .zygote import Zygote, forkable

_logger = logging.getLogger('rory.supervisor')

StartMode = Literal['auto', 'fresh', 'resume']
"""auto: resume the nodes of a run that did not stop cleanly, else fresh."""

FAST_TICK = 0.02
"""Seconds between ticks while a node starts, arms or recovers (SYNC resends, arming)."""

IDLE_TICK = 0.25
"""Seconds between ticks while every node runs: heartbeat checks only (hang_timeout is in
seconds). Events (an exit, a status) wake the loop at once whatever the tick."""

SPIN_TIMEOUT = 1.0
"""rclpy executors wake on work and on their context's shutdown; the timeout only bounds how
long a spinner takes to notice anything else. Short timeouts cost CPU: each spin_once builds a
wait set (~0.3 ms)."""

_QUIET = frozenset({NodeState.RUNNING, NodeState.EXITED, NodeState.FATAL})


class Supervisor:
    """Runs the configured nodes until stopped by a signal or until they have all ended."""

    def __init__(self, config: SupervisorConfig, launcher: Launcher | None = None,
                 start: StartMode = 'auto', ros_args: Sequence[str] = ()) -> None:
        self.config = config
        # ROS arguments of `rory supervise ... --ros-args ...`: for the supervisor's own node
        # (e.g. use_sim_time, a namespace) and, appended to their commands, for every node.
        self.ros_args = tuple(ros_args)
        self.secret = secrets.token_bytes(32)  # this run's key (protocol.ENV_SECRET)
        self.start_mode = start
        # Made in run(), before rclpy.init: the zygote must be forked from a process that
        # has no participant and no thread of its own yet.
        self.launcher: Launcher = launcher or ForkLauncher(None)
        self._own_launcher = launcher is None
        # A SimpleQueue: put is safe from the signal handler (a queue.Queue's lock could be
        # held by the interrupted get), and get(timeout) waits in C, not in a Python Condition
        # (the main loop wakes several times a second at rest: docs/performance.md).
        self.events: queue.SimpleQueue[Event] = queue.SimpleQueue()
        self.nodes: dict[str, ManagedNode] = {}
        self._ring_ctx: RingContext | None = None
        # Per node, the writers of its shadow topics: the current incarnation's last.
        self._shadow_writers: dict[str, list[Any]] = {}
        self._inbox: StatusInbox | None = None
        self._stopping = False
        self.channel = protocol.DEFAULT_CHANNEL  # set from its node's namespace in run()
        self.clock: Callable[[], float] = time.monotonic

    def read_beat(self, slot: Path) -> int | None:
        """A node's last heartbeat (inflight.py), ``time.monotonic_ns()``; None before one."""
        return read_beat(slot)

    @property
    def status_address(self) -> str:
        """Where the nodes send their statuses (inbox.py), as the environment spells it."""
        assert self._inbox is not None, 'the inbox is made in run()'
        return self._inbox.address

    # called from other threads
    def post_status(self, text: str) -> None:
        """Queue a status message for the main thread (from the inbox's thread)."""
        try:
            message = protocol.decode_status(text, self.secret)
        except ProtocolError as err:
            _logger.warning('%s ignoring malformed status: %s', LOG_PREFIX, err)
            return
        if message.node not in self.nodes:
            # Signed with this run's key but for no node of this config: not ours to act on.
            _logger.warning('%s ignoring a status of an unknown node %r', LOG_PREFIX,
                            message.node)
            return
        self.events.put(StatusReceived(message.node, message))

    def make_ring(self, node_id: str) -> Ring:
        """A ring for one node (the shared ring executor is created on first use; its readers
        join the supervisor's own context and participant)."""
        if self._ring_ctx is None:
            self._ring_ctx = RingContext(self.ros_node.context)
        return Ring(self._ring_ctx, node_id)

    def open_shadow_topic(self, node_id: str, incarnation: int) -> EnvelopePort:
        """A writer on the shadow topic of this incarnation of the node (the supervisor's own
        node publishes it); the node's earlier writers wait to be retired."""
        writer = self.ros_node.create_publisher(
            UInt8MultiArray, protocol.replay_topic(node_id, incarnation, self.channel),
            protocol.REPLAY_QOS)
        self._shadow_writers.setdefault(node_id, []).append(writer)
        return protocol.SignedPublisher(writer, self.secret)

    def retire_shadow_topics(self, node_id: str) -> None:
        """Destroy the node's earlier writers: no replay streams on them any more."""
        writers = self._shadow_writers.get(node_id, [])
        for writer in writers[:-1]:
            self.ros_node.destroy_publisher(writer)
        del writers[:-1]

    def _serve_gate(self, node: ManagedNode) -> None:
        """The node's release gate service (``std_srvs/Trigger``); the main loop answers."""

        def call(_request: Any, response: Any) -> Any:
            # On the ROS spinner thread: the main loop owns the node's state and answers.
            response.success, response.message = ask_gate(self.events, node.id)
            return response

        self.ros_node.create_service(Trigger, node.gate_service, call)

    def _claim_store(self) -> tuple[RunMarker, bool, float | None]:
        """Lock the store; whether to resume, and since when the nodes were unsupervised.

        Raises:
            ConfigError: The store cannot be made or written (before any node starts).
        """
        check_store(self.config)
        try:
            marker = RunMarker(self.config.store)
            previous = marker.acquire()
        except OSError as err:
            raise store_error(self.config, err.strerror or str(err)) from None
        unclean = previous is not None and not previous.clean
        resume = self.start_mode == 'resume' or (self.start_mode == 'auto' and unclean)
        down_since = None
        if resume and previous is not None:
            # The node logged up to its death; its newest log file's mtime bounds that.
            down_since = self._last_write(previous)
        return marker, resume, down_since

    def _last_write(self, previous: PreviousRun) -> float | None:
        newest = 0.0
        for node in self.config.nodes:
            folder = self.config.store / node.name
            if folder.exists():
                for path in folder.rglob('*'):
                    with contextlib.suppress(OSError):
                        newest = max(newest, path.stat().st_mtime)
        return newest or (previous.started or None)

    def _prepare_store(self) -> None:
        # A fresh run must not mix with an earlier run's checkpoints and logs: set them aside.
        # The newest earlier run is under .previous/, older ones under .previous.1/, ...:
        # keep_runs of them in all.
        store = self.config.store
        make_private_dir(store)
        previous = store / '.previous'
        events = store / 'events.jsonl'
        if events.exists() or any((store / n.name).exists() for n in self.config.nodes):
            kept = make_room_for_previous(store, self.config.keep_runs)
            if kept:
                _logger.info('%s earlier runs kept in %s (newest) to %s (keep_runs: %d)',
                             LOG_PREFIX, previous, kept[-1], self.config.keep_runs)
        if events.exists():
            make_private_dir(previous)
            events.replace(previous / 'events.jsonl')
        for node in self.config.nodes:
            current = store / node.name
            if current.exists():
                target = previous / node.name
                if target.exists():
                    shutil.rmtree(target)
                make_private_dir(previous)
                current.rename(target)
                _logger.info('%s %s: earlier run set aside in %s', LOG_PREFIX, node.name, target)

    def _install_signals(self) -> Callable[[], None]:
        def handler(signum: int, _frame: FrameType | None) -> None:
            self.events.put(Stop(signal.Signals(signum).name))

        old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}

        def restore() -> None:
            for s, h in old.items():
                signal.signal(s, h)

        return restore

    def _apply_dds_settings(self) -> None:
        # Before any participant exists in this process; children inherit os.environ. An
        # operator's own Fast DDS profile wins. The supervisor gets the nodes' profile, lease
        # and all: its participant carries the ring, which must see the network as the node's
        # own reader does. With a longer lease here (tried: 3 s) a link outage between 1 and
        # 3 s dropped the node's reader at the publisher but not the ring's, the two were
        # matched again at different times, and the node's reader could hold a message the
        # ring never got (tests/integration/test_multihost.py).
        if self.config.dds == 'fast_rediscovery' and not (
            os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
            or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE')
        ):
            os.environ.update(fast_rediscovery_env())

    def _start_zygote(self) -> None:
        """The fork server every node starts from (supervisor/zygote.py): its imports, frozen,
        shared by every node process and the standbys."""
        programs = [p for p in (forkable(n.command) for n in self.config.nodes) if p]
        if not programs:
            return
        try:
            zygote = Zygote.start(programs, preload=('rory_runtime.node.attach',))
        except (OSError, RoryError) as err:
            _logger.warning('%s no fork server (%s); every node starts with exec, cold',
                            LOG_PREFIX, err)
            return
        self.launcher = ForkLauncher(zygote, pool_size=self.config.standby_pool_size,
                                         spares=self.config.spare_forks)

    def run(self) -> int:
        """Supervise until stopped. Returns the process exit code."""
        self._apply_dds_settings()
        if self._own_launcher:
            self._start_zygote()
            if self.config.prefixes_output and isinstance(self.launcher, ForkLauncher):
                # After the zygote's fork: the prefixer is a thread.
                self.launcher.output = OutputPrefixer(sys.stdout.buffer, sys.stderr.buffer)
        try:
            # Its log goes to /rosout through rclpy (RosoutHandler); the console already has it.
            rclpy.init(args=['rory', '--ros-args', '--disable-stdout-logs',
                             *own_ros_args(self.ros_args)],
                       signal_handler_options=SignalHandlerOptions.NO)
        except BaseException:
            self.launcher.close()
            raise
        self.ros_node = Node(SUPERVISOR_NODE)
        # Its nodes' topics live under its own namespace: a supervisor per robot, same config.
        self.channel = protocol.channel(self.ros_node.get_namespace())
        try:
            # Before the store is claimed: a parameter may name another store.
            self.config = apply_parameters(self.ros_node, self.config)
            marker, resume, down_since = self._claim_store()
        except BaseException:
            self.launcher.close()
            self.ros_node.destroy_node()
            rclpy.utilities.try_shutdown()
            raise
        restore_signals = self._install_signals()
        if not resume:
            self._prepare_store()
        self.events_log = EventLog(self.config.store / 'events.jsonl')
        rosout = RosoutHandler(self.ros_node.get_logger())
        logging.getLogger('rory').addHandler(rosout)
        self.reporter = Reporter(self.ros_node)
        self.events_log.listeners.append(self.reporter.event)
        if any(n.method.logs for n in self.config.nodes):
            # The recovery log needs the typestore at a crash; load it now, not then (~0.1 s).
            threading.Thread(target=default_typestore, daemon=True).start()
        executor = SingleThreadedExecutor()
        spinner = threading.Thread(target=self._spin, args=(executor,), name='rory-ros')
        code = 1
        self._inbox = StatusInbox(self.post_status)
        try:
            self.safety = SafeState(
                self.ros_node, self.config,
                lambda node, what, topic: self.events_log.write('safe_state', node, what=what,
                                                                topic=topic))
            for cfg in self.config.nodes:
                node = self.nodes[cfg.name] = ManagedNode(self, cfg)
                # Its release gate's service; its statuses come on the status socket (inbox.py).
                if node.handover.gate is not None:
                    self._serve_gate(node)
            executor.add_node(self.ros_node)
            spinner.start()
            for node in self.nodes.values():
                if resume and node.has_stored_state():
                    node.start_resumed(down_since)
                else:
                    node.start()
            code = self._loop()
        finally:
            for node in self.nodes.values():
                node.stop()
            self.launcher.close()
            # Every node was stopped by us: the next run starts fresh.
            marker.mark_clean()
            marker.release()
            if self._ring_ctx is not None:
                self._ring_ctx.shutdown()
            self._inbox.close()
            # Shut the context down first so the spinner leaves spin_once, then join it: an
            # executor thread still inside rcl at interpreter exit aborts the process.
            rclpy.utilities.try_shutdown()
            if spinner.is_alive():
                spinner.join(timeout=2.0)
            executor.shutdown(timeout_sec=1.0)
            logging.getLogger('rory').removeHandler(rosout)
            self.ros_node.destroy_node()
            self.events_log.close()
            restore_signals()
        return code

    def _spin(self, executor: SingleThreadedExecutor) -> None:
        name_this_thread('rory-ros')
        while rclpy.utilities.ok():
            try:
                executor.spin_once(timeout_sec=SPIN_TIMEOUT)
            except Exception:
                if rclpy.utilities.ok():
                    _logger.exception('%s executor error', LOG_PREFIX)

    def _loop(self) -> int:
        while True:
            quiet = all(n.sm.state in _QUIET for n in self.nodes.values())
            try:
                event = self.events.get(timeout=IDLE_TICK if quiet else FAST_TICK)
            except queue.Empty:
                event = None
            if isinstance(event, Stop):
                _logger.info('%s stopping (%s)', LOG_PREFIX, event.reason)
                return 0
            if isinstance(event, ChildExited):
                self.nodes[event.node].on_exit(event)
            elif isinstance(event, StatusReceived):
                self.nodes[event.node].on_status(event.message)
            elif isinstance(event, Released):
                pass  # the node's RELEASED status ends the recovery; this only marks the send
            elif isinstance(event, GateCall):
                event.reply.put(self.nodes[event.node].on_gate_call())
            now = self.clock()
            for node in self.nodes.values():
                node.tick(now)
            if self.reporter.due(now):
                self.reporter.diagnostics(n.health(now) for n in self.nodes.values())
            states = {n.sm.state for n in self.nodes.values()}
            if states <= {NodeState.EXITED, NodeState.FATAL}:
                failed = NodeState.FATAL in states
                _logger.info('%s all nodes have ended%s', LOG_PREFIX, ' (FATAL)' if failed else '')
                return 1 if failed else 0
