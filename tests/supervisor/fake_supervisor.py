"""Fakes of the supervisor's ports (rory_runtime/supervisor/ports.py): a managed node's
decisions driven by hand, with no ROS process, no DDS and no real child process.

``Harness`` holds one ``ManagedNode`` over a fake clock, launcher, event log, safe state, ring
and shadow-topic writers; a test starts it, feeds it statuses and exits as a node process would, and
reads back what the supervisor did (states, events, signals, envelopes, the safe state, what
the ring was given). The recovery log and the replay streamer are the real ones, on a store in
the test's tmp_path: a ``rory`` node's replay runs as it does under the supervisor.
"""

from __future__ import annotations

import dataclasses
import queue
import signal
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml

from rory_runtime import protocol
from rory_runtime.log import LogEntry
from rory_runtime.protocol import (
    HelloStatus,
    InputSpec,
    Method,
    Mode,
    ReleasedStatus,
    Status,
    SyncedStatus,
)
from rory_runtime.supervisor.config import SupervisorConfig, load_config
from rory_runtime.supervisor.loop_events import ChildExited, GateCall, Released, ask_gate
from rory_runtime.supervisor.managed_node import ManagedNode
from rory_runtime.supervisor.ports import RingPort
from rory_runtime.supervisor.states import NodeState


class FakeClock:
    """Monotonic seconds that move only when told."""

    def __init__(self, start: float = 1000.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> float:
        self.now += seconds
        return self.now


class FakeChild:
    """A node process: ends when the test says, or on SIGINT, SIGTERM or SIGKILL (a node
    stops on SIGINT); records every signal."""

    def __init__(self, pid: int, argv: list[str], env: dict[str, str]) -> None:
        self.pid = pid
        self.argv = argv
        self.env = env
        self.signals: list[int] = []
        self.warm = False
        self.why_cold = 'fake'
        self._code: int | None = None
        self._done = threading.Event()

    def finish(self, code: int) -> None:
        if self._code is None:
            self._code = code
        self._done.set()

    def wait(self, timeout: float | None = None) -> int:
        if not self._done.wait(timeout):
            raise TimeoutError(f'pid {self.pid} still runs')
        assert self._code is not None
        return self._code

    def poll(self) -> int | None:
        return self._code

    def send_signal(self, sig: int) -> None:
        self.signals.append(sig)
        if sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            self.finish(-sig)


class FakeLauncher:
    """Starts FakeChild processes; a standby only when ``standby`` is set."""

    def __init__(self) -> None:
        self.children: list[FakeChild] = []
        self.standby = False
        self.prepared: list[list[str]] = []

    def spawn(self, argv: Any, env: Any, cwd: Path, label: str = '') -> FakeChild:
        child = FakeChild(100 + len(self.children), list(argv), dict(env))
        self.children.append(child)
        return child

    def prepare(self, argv: Any, env: Any, cwd: Path) -> list[int] | None:
        self.prepared.append(list(argv))
        return [999] if self.standby else None

    def discard(self, argv: Any, cwd: Path) -> None:
        pass

    def close(self) -> None:
        pass


class FakeEvents:
    """events.jsonl, kept in memory."""

    def __init__(self, clock: FakeClock) -> None:
        self.records: list[dict[str, Any]] = []
        self._clock = clock

    def write(self, kind: str, node: str, **fields: Any) -> None:
        self.records.append({'t': self._clock(), 'kind': kind, 'node': node, **fields})

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [r for r in self.records if r['kind'] == kind]


class FakeSafety:
    """Who holds the safe state, and every call of hold and release in order (the real one
    ignores a repeat; the log keeps it, so a test sees a recovery release twice)."""

    def __init__(self) -> None:
        self.holders: set[str] = set()
        self.log: list[tuple[str, str]] = []

    def hold(self, node_id: str) -> None:
        self.holders.add(node_id)
        self.log.append(('hold', node_id))

    def release(self, node_id: str) -> None:
        self.holders.discard(node_id)
        self.log.append(('release', node_id))

    @property
    def held(self) -> bool:
        return bool(self.holders)


class FakePublisher:
    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.sent: list[Any] = []

    def publish(self, msg: Any) -> None:
        self.sent.append(msg)


@dataclasses.dataclass
class FakeRingTopic:
    """One reader of the ring, as the supervisor reads it (``ring.RingTopic``)."""

    spec: InputSpec

    def publisher_count(self) -> int:
        return 1


class FakeRing:
    """A ring whose readers always match and never take a message: it records which sink it
    was activated for (with the entries an early capture handed over), and which topics are
    active, as the real one does."""

    def __init__(self) -> None:
        self.topics: dict[str, FakeRingTopic] = {}
        self.active_topics: set[str] = set()
        self.sinks: list[Any] = []  # every activation's sink, in order
        self.handed_over: list[list[LogEntry]] = []  # and what led its backlog

    @property
    def activations(self) -> int:
        return len(self.sinks)

    def ensure(self, specs: Iterable[InputSpec]) -> None:
        self.topics.update({spec.topic: FakeRingTopic(spec) for spec in specs})

    def publisher_counts(self) -> dict[str, int]:
        return dict.fromkeys(self.topics, 1)

    def offered_qos(self, topic: str) -> list[Any]:
        return []

    def publisher_count(self, topic: str) -> int:
        return 1

    def activate(self, sink: Any, before: list[LogEntry] | None = None) -> None:
        self.sinks.append(sink)
        self.handed_over.append(list(before or ()))
        self.active_topics = set(self.topics)
        sink.add_backlog(list(before or ()))

    def deactivate(self, topic: str | None = None) -> None:
        if topic is None:
            self.active_topics.clear()
        else:
            self.active_topics.discard(topic)


class FakeSupervisor:
    """Every port a ManagedNode uses (SupervisorPorts), faked."""

    def __init__(self, config: SupervisorConfig) -> None:
        self.config = config
        self.clock = FakeClock()
        self.launcher = FakeLauncher()
        self.events_log = FakeEvents(self.clock)
        self.events: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.safety = FakeSafety()
        self.writers: list[FakePublisher] = []  # every shadow topic's writer, in order
        self.retired: list[FakePublisher] = []
        self.channel = protocol.DEFAULT_CHANNEL
        self.secret = b'k' * 32
        self.status_address = '@rory-status-fake'
        self.beats: dict[Path, int] = {}
        self.rings: list[FakeRing] = []

    def read_beat(self, slot: Path) -> int | None:
        return self.beats.get(slot)

    def make_ring(self, node_id: str) -> RingPort:
        ring = FakeRing()
        self.rings.append(ring)
        return ring

    def open_shadow_topic(self, node_id: str, incarnation: int) -> protocol.SignedPublisher:
        writer = FakePublisher(protocol.replay_topic(node_id, incarnation, self.channel))
        self.writers.append(writer)
        return protocol.SignedPublisher(writer, self.secret)

    def retire_shadow_topics(self, node_id: str) -> None:
        self.retired.extend(w for w in self.writers[:-1] if w not in self.retired)

    def post_status(self, text: str) -> None:
        pass


INPUT = InputSpec(topic='/in', msgtype='std_msgs/msg/String', reliable=True,
                  transient_local=False, depth=10)
"""The one input of a node in these tests (its ring reader, its handover)."""

HELLO = HelloStatus(mode=Mode.FRESH, method=Method.RESTART, pid=1, manifest='sha256:0',
                    inputs=(), restored=None, refused=(), restore_ms=1.0, process_start_ns=None,
                    interval=2.0, replay=None, dds_profile=None, dds_transports=None)
"""A HELLO with nothing restored; ``Harness.hello`` fills in the node's method and inputs."""

RELEASED_STATS = {'applied': 0, 'replayed': 0, 'duplicates': 0, 'muted': 0, 'quarantined': 0,
                  'passed_by_relay': 0, 'ticks': 0, 'ticks_replayed': 0, 'clock_fallbacks': 0,
                  'parameter_changes': 0, 'parameter_changes_replayed': 0, 'requests': 0,
                  'requests_replayed': 0}


class Harness:
    """One managed node over fakes. ``node`` is the supervisor.yaml entry's fields."""

    def __init__(self, tmp_path: Path, **node: Any) -> None:
        entry = {'name': 'n', 'command': ['true'], 'method': 'restart', 'warm_standby': False,
                 **node}
        path = tmp_path / 'supervise.yaml'
        path.write_text(yaml.safe_dump({'nodes': [entry], 'store': 'store'}))
        self.sup = FakeSupervisor(load_config(path))
        self.node = ManagedNode(self.sup, self.sup.config.nodes[0])

    @property
    def clock(self) -> FakeClock:
        return self.sup.clock

    @property
    def child(self) -> FakeChild:
        return self.sup.launcher.children[-1]

    def states(self) -> list[str]:
        return [r['new'] for r in self.sup.events_log.of('state')]

    def state(self) -> NodeState:
        """The node's state now (a call: each read is fresh to the type checker too)."""
        return self.node.sm.state

    def status(self, status: Status) -> None:
        """A status of the node's current process, as the supervisor gets it: signed with the
        run's key, encoded and decoded."""
        text = protocol.encode_status(status, self.node.id, self.node.incarnation,
                                      key=self.sup.secret)
        self.node.on_status(protocol.decode_status(text, self.sup.secret))

    def hello(self, **fields: Any) -> None:
        inputs = (INPUT,) if self.node.cfg.method.logs else ()
        mode = Mode.RECOVER if self.node.incarnation > 1 else Mode.FRESH
        self.status(dataclasses.replace(HELLO, mode=mode, method=self.node.cfg.method,
                                        inputs=inputs, **fields))

    def synced(self) -> None:
        """SYNCED, answering the supervisor's SYNC (its nonce)."""
        self.status(SyncedStatus(nonce=self.node.current.sync_nonce,
                                 live_publishers={INPUT.topic: 1}))

    def replayed(self) -> None:
        """Wait for the replay streamer to have sent RELEASE (it posts Released)."""
        event = self.sup.events.get(timeout=5.0)
        assert isinstance(event, Released), event

    def released(self, **stats: Any) -> None:
        self.status(ReleasedStatus(**{**RELEASED_STATS, **stats}))

    def up(self) -> None:
        """The process came up: HELLO and RELEASED (restart and checkpoint release at once);
        for a method that logs, SYNCED and the replay first when it recovers."""
        self.hello()
        if self.node.sm.state == NodeState.REPLAYING:
            self.synced()
            self.replayed()
        elif self.node.sm.state == NodeState.ARMING:
            self.synced()
            self.tick()  # the ring matches at once: RELEASE
        self.released()

    def beat(self, at: float | None = None) -> None:
        """The node's heartbeat, now (or at ``at`` seconds) on the fake clock."""
        self.sup.beats[self.node.slot] = int((self.clock() if at is None else at) * 1e9)

    def exit(self, code: int) -> None:
        """The current process ends with ``code``; the supervisor hears it."""
        self.child.finish(code)
        self.reap()

    def reap(self) -> None:
        """Deliver the exit the reaper thread posted (a Released before it is passed over, as
        the main loop does)."""
        event = self.sup.events.get(timeout=5.0)
        while isinstance(event, Released):
            event = self.sup.events.get(timeout=5.0)
        assert isinstance(event, ChildExited), event
        self.node.on_exit(event)

    def tick(self, seconds: float = 0.0) -> None:
        self.node.tick(self.clock.advance(seconds))

    def call_release(self) -> tuple[bool, str]:
        """A call on the release gate service, answered as the main loop would."""
        answer: dict[str, tuple[bool, str]] = {}

        def call() -> None:  # the service's thread (supervisor.py serves it)
            answer['reply'] = ask_gate(self.sup.events, self.node.id)

        caller = threading.Thread(target=call)
        caller.start()
        event = self.sup.events.get(timeout=5.0)
        assert isinstance(event, GateCall)
        event.reply.put(self.node.on_gate_call())
        caller.join(timeout=5.0)
        return answer['reply']

    def envelopes(self) -> list[Any]:
        """What the supervisor sent on the current process's shadow topic, unpacked."""
        writer = self.sup.writers[-1]
        return [protocol.unpack(raw, self.sup.secret) for raw in writer.sent]
