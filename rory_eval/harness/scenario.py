"""The integrator scenario: a deterministic publisher, a stateful node under RORY, SIGKILLs.

Everything is real: ``rory-instrument`` rewrites ``examples/integrator``, ``rory supervise`` runs
it, a publisher process sends 1..N, this process SIGKILLs the node at chosen moments (found by
following the supervisor's ``events.jsonl``) and watches ``/integrator/state`` and ``/e_stop``.
With no message lost or applied twice the node's final history is exactly [1, ..., N].
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Bool, String

from rory_runtime import protocol
from rory_runtime.dds import fast_rediscovery_env

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / 'examples' / 'integrator'


@dataclass(frozen=True)
class Program:
    """A node program to instrument and run: it consumes /numbers, publishes its state as JSON."""

    source: Path  # folder rory-instrument copies
    keyvars: Path
    file: str  # the program, relative to the instrumented folder
    state_topic: str
    node: str = 'node'  # its id in the supervisor config
    settings: tuple[tuple[str, Any], ...] = ()  # more fields of its supervisor config entry
    # How many numbers a state the node published shows applied (at most as many as it has
    # applied; exact once all are in): what Kill(after_applied=...) waits for and what tells
    # a run complete. None: the state's ``count``, as the integrator publishes it.
    progress: Callable[[Any], int] | None = None

    def applied(self, state: Any) -> int:
        """Numbers applied as ``state`` shows them (0 for no state yet)."""
        if not state:
            return 0
        if self.progress is not None:
            return self.progress(state)
        count = state.get('count') if isinstance(state, dict) else None
        return count if isinstance(count, int) else 0


INTEGRATOR = Program(
    EXAMPLE, EXAMPLE / 'keyvars.yaml', 'integrator.py', '/integrator/state', 'integrator'
)


def _numbers_applied(state: Any) -> bool:
    """Whether a state the node published shows numbers applied: a program that reports on a
    timer publishes its empty state (``count`` 0) before the first number, and a strike timed
    from that would land up to a report period early."""
    return not (isinstance(state, dict) and state.get('count') == 0)


def _last_applied(state: Any) -> int | None:
    """The last number in an integrator's history (None: no history)."""
    history = state.get('history') if isinstance(state, dict) else None
    return history[-1] if isinstance(history, list) and history else None


@dataclass(frozen=True)
class Kill:
    """When to strike the node: exactly one of the time fields is set; ``how`` is the fault.

    ``how``: a signal name (SIGKILL, SIGSEGV, SIGABRT) sent to the node, or ``raise`` /
    ``hang``, which leave a flag file that a fault-injectable program (rory_eval/faults/flaky) takes
    before its next message and then raises, or blocks forever.
    """

    after: float | None = None  # seconds after the first number was published
    # Once the node's published state shows this many numbers applied (Program.applied): a
    # strike timed by the node's own progress, mid-run however late the observer heard it.
    after_applied: int | None = None
    after_checkpoint: int | None = None  # right after the node reports its k-th checkpoint
    delay: float = 0.0  # with after_checkpoint: this long after that checkpoint
    during_recovery: float | None = None  # this long after the replacement starts replaying
    after_respawn: float | None = None  # this long after a replacement process was spawned
    # This long after the previous strike (the first: after the first number); a signal waits
    # for a live process (it lands at the next spawn when the node is down).
    after_previous: float | None = None
    how: str = 'SIGKILL'

    @property
    def signal(self) -> bool:
        """Sent to the process (not a flag file the program takes)."""
        return self.how not in ('raise', 'hang')

    def describe(self) -> str:
        """Short label."""
        what = '' if self.how == 'SIGKILL' else f'{self.how} '
        if self.after is not None:
            return f'{what}at {self.after:g} s'
        if self.after_applied is not None:
            return f'{what}after {self.after_applied} numbers applied'
        if self.after_previous is not None:
            return f'{what}{self.after_previous:g} s after the previous strike'
        if self.after_checkpoint is not None and self.delay:
            return f'{what}{self.delay:g} s after checkpoint {self.after_checkpoint}'
        if self.after_checkpoint is not None:
            return f'{what}just after checkpoint {self.after_checkpoint}'
        if self.after_respawn is not None:
            return f'{what}{self.after_respawn:g} s after the respawn'
        return f'{what}{self.during_recovery:g} s into the replay'

    def strike(self, pid: int | None, workdir: Path) -> bool:
        """Deliver the fault; False if its process is gone (a signal needs one)."""
        if not self.signal:
            (workdir / f'fault-{self.how}').touch()
            return True
        if pid is None:
            return False
        try:
            os.kill(pid, signal.Signals[self.how])
        except ProcessLookupError:  # died a moment ago; its exit is not in the events yet
            return False
        return True


@dataclass
class ScenarioResult:
    """What one run produced."""

    method: str
    expected: int
    state: Any  # the node's last published state
    recoveries: list[dict[str, Any]]
    kills: list[tuple[str, float]]
    e_stop: list[tuple[float, bool]]
    events: list[dict[str, Any]] = field(repr=False)
    log: str = field(repr=False, default='')
    # Readers of the node's shadow topic in the graph when the run ended (the node retires its
    # own after the handover; -1: not looked at).
    shadow_readers_at_end: int = -1

    @property
    def history(self) -> list[int]:
        """The integrator's list of the numbers it applied."""
        return list(self.state.get('history', [])) if isinstance(self.state, dict) else []

    @property
    def correct(self) -> bool:
        """The final state equals the no-crash state."""
        return self.history == list(range(1, self.expected + 1))

    @property
    def lost(self) -> int:
        """Numbers never applied."""
        return self.expected - len(set(self.history) & set(range(1, self.expected + 1)))

    @property
    def duplicated(self) -> int:
        """Numbers applied more than once."""
        return len(self.history) - len(set(self.history))

    @property
    def recovery_ms(self) -> list[float]:
        """Crash detected -> released, per recovery."""
        return [float(r['total_ms']) for r in self.recoveries]


def scenario_env(domain_id: int, reach: str = 'LOCALHOST') -> dict[str, str]:
    """Environment for every process of one isolated run.

    Args:
        domain_id: Its ROS domain.
        reach: ``ROS_AUTOMATIC_DISCOVERY_RANGE`` (SUBNET across network namespaces).
    """
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = reach
    # UDPv4 only; under LOCALHOST that takes range SUBNET and a profile bound to 127.0.0.1.
    env.update(fast_rediscovery_env(env))
    env['PYTHONUNBUFFERED'] = '1'
    return env


@contextlib.contextmanager
def joining(domain_id: int) -> Iterator[None]:
    """While this process creates its own participant in a run's domain: the run's discovery
    settings (``FAST*``, ``ROS_*`` of :func:`scenario_env`) in ``os.environ``, where rmw and
    Fast DDS read them; the environment as it was afterwards.

    Restoring matters in a long-lived process (a pytest worker, a campaign): the next run's
    children are spawned from ``os.environ`` and must not inherit this one's domain.
    """
    joined = {k: v for k, v in scenario_env(domain_id).items() if k.startswith(('FAST', 'ROS_'))}
    before = {k: os.environ.get(k) for k in joined}
    os.environ.update(joined)
    try:
        yield
    finally:
        for key, value in before.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


_environ_lock = threading.Lock()
_instrumented: dict[str, Path] = {}  # fingerprint of source and keyvars -> rory-instrument's output
_instrument_lock = threading.Lock()


def _fingerprint(program: Program) -> str:
    """What rory-instrument's output depends on: the source folder's files and the keyvars."""
    digest = hashlib.sha256()
    files = sorted(p for p in program.source.rglob('*')
                   if p.is_file() and '__pycache__' not in p.parts)
    for path in [*files, program.keyvars]:
        digest.update(str(path).encode() + b'\0' + path.read_bytes() + b'\0')
    return digest.hexdigest()


def instrument(program: Program, out: Path) -> None:
    """``rory-instrument`` the program's source folder into ``out``.

    The instrumenter runs once per source and keyvars in this process (0.6 s for the
    integrator, 1.8 s for the test corpus); later runs get a copy of its output, which is the
    same bytes (it holds no path of where it was written).
    """
    key = _fingerprint(program)
    with _instrument_lock:
        done = _instrumented.get(key)
        if done is None or not done.exists():
            cache = Path(tempfile.mkdtemp(prefix='rory-instrumented-'))
            atexit.register(shutil.rmtree, cache, True)
            done = cache / 'out'
            subprocess.run(
                [
                    sys.executable, '-m', 'rory_instrument', str(program.source),
                    '--vars', str(program.keyvars), '-o', str(done),
                ],
                check=True,
                capture_output=True,
            )
            _instrumented[key] = done
    shutil.copytree(done, out)


def prepare(
    workdir: Path,
    method: str,
    *,
    interval: float | None,
    pace: str | None,
    program: Program = INTEGRATOR,
    warm_standby: bool | None = None,
) -> Path:
    """Instrument the program into ``workdir`` and write a supervisor config; its path.

    ``interval`` and ``pace`` left None leave them to the program's keyvars.yaml.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    out = workdir / 'out'
    if not out.exists():
        instrument(program, out)
    node: dict[str, Any] = {
        'name': program.node,
        'command': ['python', f'out/{program.file}'],
        'method': method,
    }
    node.update(program.settings)
    if interval is not None:
        node['checkpoint_interval'] = interval
    if pace is not None:
        node['replay'] = pace
    if warm_standby is not None:
        node['warm_standby'] = warm_standby
    config = {
        'nodes': [node],
        'safe_state': [
            {
                'topic': '/e_stop',
                'type': 'std_msgs/msg/Bool',
                'hold': {'data': True},
                'release': {'data': False},
            }
        ],
        'store': f'store-{method}',
    }
    path = workdir / f'supervise-{method}.yaml'
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


class _Listener:
    """A node of its own, in its own rclpy context, spun by a thread of this process: what a
    run's observers and readers stand on."""

    def __init__(self, domain_id: int, node_name: str) -> None:
        self.context = Context()
        rclpy.init(
            context=self.context, domain_id=domain_id,
            signal_handler_options=SignalHandlerOptions.NO,
        )
        self.node = Node(node_name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)

    def _start(self) -> None:
        """Spin, once the subscriptions are made."""
        self.executor.add_node(self.node)
        self._thread.start()

    def _spin(self) -> None:
        while not self._closing.is_set() and self.context.ok():
            with contextlib.suppress(Exception):
                self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        # Executor and node before the context: an executor collected after its context is
        # gone prints "Exception ignored in Executor.__del__" at exit.
        self._closing.set()
        self._thread.join(timeout=2.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()


class _Observer(_Listener):
    """Subscribes to the node's state and the safe-state topic in its own rclpy context."""

    def __init__(self, domain_id: int, state_topic: str = INTEGRATOR.state_topic) -> None:
        super().__init__(domain_id, 'scenario_observer')
        latched = QoSProfile(
            depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
            reliability=ReliabilityPolicy.RELIABLE,
        )
        self.state: Any = {}
        self.state_changed = time.monotonic()
        self.state_heard = 0.0  # the last state message, changed or not
        self.e_stop: list[tuple[float, bool]] = []
        # Volatile: matches latched and plain state publishers alike (a transient-local reader
        # does not match a volatile writer); this observer starts before the node anyway.
        self.node.create_subscription(String, state_topic, self._on_state, QoSProfile(depth=10))
        self.node.create_subscription(Bool, '/e_stop', self._on_e_stop, latched)
        self._start()

    def _on_state(self, msg: String) -> None:
        state = json.loads(msg.data)
        self.state_heard = time.monotonic()
        if state != self.state:
            self.state = state
            self.state_changed = time.monotonic()

    def _on_e_stop(self, msg: Bool) -> None:
        self.e_stop.append((time.monotonic(), bool(msg.data)))


def integrators_config(workdir: Path, names: list[str], *, standbys: int | None = None) -> Path:
    """The integrator once per name under one supervisor (method rory, checkpoints every 2 s,
    fast replay), each with its own node name and state topic (``/NAME/state``), all reading
    /numbers; ``standbys``: the pool's size (None: the default). The config's path."""
    path = prepare(workdir, 'rory', interval=2.0, pace='fast')
    doc: dict[str, Any] = yaml.safe_load(path.read_text())
    (node,) = doc['nodes']
    doc['nodes'] = [
        {**node, 'name': name,
         'command': [*node['command'], '--ros-args', '-r', f'__node:={name}',
                     '-r', f'/integrator/state:=/{name}/state']}
        for name in names
    ]
    if standbys is not None:
        doc['standbys'] = standbys
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class StateReader(_Listener):
    """One participant reading the state topics of :func:`integrators_config`'s nodes
    (``/NAME/state``); when each was last heard, and what."""

    def __init__(self, domain_id: int, names: list[str],
                 node_name: str = 'struck_together_reader') -> None:
        super().__init__(domain_id, node_name)
        self.state: dict[str, Any] = {name: {} for name in names}
        self.heard: dict[str, list[float]] = {name: [] for name in names}
        for name in names:
            self.node.create_subscription(String, f'/{name}/state',
                                          functools.partial(self._on_state, name),
                                          QoSProfile(depth=10))
        self._start()

    def _on_state(self, name: str, msg: String) -> None:
        self.state[name] = json.loads(msg.data)
        self.heard[name].append(time.monotonic())

    def first_heard_after(self, name: str, moment: float) -> float | None:
        return next((t for t in self.heard[name] if t > moment), None)


class LineFollower:
    """Follows a file another process appends to: the whole lines added since the last poll
    (a line still being written waits for its newline)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._offset = 0

    def poll(self) -> list[bytes]:
        """The whole lines appended since the last poll, without their newlines."""
        if not self.path.exists():
            return []
        with self.path.open('rb') as f:
            f.seek(self._offset)
            data = f.read()
        end = data.rfind(b'\n') + 1
        self._offset += end
        return data[:end].splitlines()


class EventsFile:
    """Follows a JSON-lines file another process appends to (the supervisor's events.jsonl,
    an observer's output); whole lines only."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.events: list[dict[str, Any]] = []
        self.changed = time.monotonic()  # when the last record came
        self._lines = LineFollower(path)

    def poll(self) -> list[dict[str, Any]]:
        """The records appended since the last poll (also kept in :attr:`events`)."""
        new = [json.loads(line) for line in self._lines.poll() if line.strip()]
        if new:
            self.events.extend(new)
            self.changed = time.monotonic()
        return new


@contextlib.contextmanager
def child_process(
    args: list[str], env: dict[str, str], cwd: Path, log: Path
) -> Iterator[subprocess.Popen[bytes]]:
    with log.open('wb') as out:
        proc = subprocess.Popen(args, env=env, cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            yield proc
        finally:
            stop_process(proc)


def stop_process(proc: subprocess.Popen[Any]) -> None:
    """Stop a process of a run that leads its own session, as Ctrl-C would: SIGINT, then,
    after 15 s, SIGKILL to its whole process group; reaped either way."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def run(
    method: str,
    kills: tuple[Kill, ...],
    workdir: Path,
    *,
    domain_id: int,
    count: int = 300,
    rate: float = 50.0,
    interval: float | None = 2.0,
    pace: str | None = 'paced',
    timeout: float = 90.0,
    program: Program = INTEGRATOR,
    warm_standby: bool | None = None,
    other_readers: int = 0,
) -> ScenarioResult:
    """Run the scenario once; always reaps every process it started.

    ``other_readers``: readers of the numbers besides the node and RORY's ring (a helper the
    caller started) that the publisher waits for before its first number.
    """
    workdir = workdir.resolve()
    config = prepare(workdir, method, interval=interval, pace=pace, program=program,
                     warm_standby=warm_standby)
    store = workdir / f'store-{method}'
    if store.exists():
        shutil.rmtree(store)
    # This process joins the run too (the observer): same discovery settings as the others.
    # Runs in threads of one process (independent runs side by side) take turns at
    # os.environ.
    with _environ_lock:
        env = scenario_env(domain_id)
        with joining(domain_id):
            observer = _Observer(domain_id, program.state_topic)
    events = EventsFile(store / 'events.jsonl')
    tracker = EventTracker()
    kills_done: list[tuple[str, float]] = []
    pending = list(kills)
    deadline = time.monotonic() + timeout
    sup_log = workdir / f'supervisor-{method}.log'
    try:
        with child_process(
            [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
            env, workdir, sup_log,
        ) as sup:
            while tracker.state != 'RUNNING':
                tracker.feed(events.poll())
                if sup.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f'node did not start:\n{sup_log.read_text()}')
                time.sleep(0.01)
            # The node, plus RORY's own reader for the methods that record.
            min_subs = str((2 if method in ('rory', 'replay') else 1) + other_readers)
            publisher = [sys.executable, str(EXAMPLE / 'count_publisher.py'), str(count), str(rate)]
            with child_process(
                [*publisher, min_subs], env, workdir, workdir / f'publisher-{method}.log'
            ) as pub:
                started: float | None = None
                previous: float | None = None  # the last strike
                before = observer.state
                while True:
                    now = time.monotonic()
                    if now > deadline:
                        raise RuntimeError(f'scenario timed out:\n{sup_log.read_text()[-4000:]}')
                    tracker.feed(events.poll())
                    if (started is None and observer.state != before
                            and _numbers_applied(observer.state)):
                        started = now  # the first number has been applied
                    applied = program.applied(observer.state)
                    if pending and started is not None:
                        kill = pending[0]
                        if tracker.due(kill, started, now, previous, applied) and kill.strike(
                                tracker.pid, workdir):
                            kills_done.append((kill.describe(), now))
                            previous = now
                            pending.pop(0)
                            tracker.replaying_since = None
                            tracker.respawned_at = None
                    published = pub.poll() is not None
                    # Settled: no news from the node for a while since it last became RUNNING
                    # (a recovered node publishes its state on its 1 Hz timer). Until this
                    # observer has heard the current process at all, wait longer: a cold
                    # restart can take seconds to be discovered (rory_eval/bench/discovery.py), and
                    # judging the state an earlier process published would report its losses,
                    # not the node's (a campaign run judged 102 numbers lost that the node had).
                    # Once heard, it must still be heard: the programs publish their state
                    # on a 1 Hz timer, and a node that went silent is hung (its recovery, a
                    # hang_timeout away, is still to come), not finished.
                    heard = observer.state_heard >= tracker.running_since
                    quiet = now - max(observer.state_changed, tracker.running_since)
                    alive = now - observer.state_heard < 2.0
                    settled = quiet > 2.5 and alive if heard else quiet > 8.0
                    # Complete: every number applied, or (a node that lost some: restart,
                    # checkpoint) the last one sent applied, after which nothing more comes.
                    complete = applied == count or _last_applied(observer.state) == count
                    if published and not pending and tracker.state == 'RUNNING' and (
                        complete or settled
                    ):
                        break
                    time.sleep(0.005)
                # While the node still runs.
                shadow_readers = observer.node.count_subscribers(
                    protocol.replay_topic(program.node, tracker.incarnation))
    finally:
        observer.close()
        events.poll()
    return ScenarioResult(
        method=method,
        expected=count,
        state=observer.state,
        recoveries=[e for e in events.events if e['kind'] == 'recovered'],
        kills=kills_done,
        e_stop=observer.e_stop,
        events=events.events,
        log=sup_log.read_text(),
        shadow_readers_at_end=shadow_readers,
    )


class EventTracker:
    """What the supervisor's events say so far: the node's pid and state, checkpoints, replay
    start, the replacements' spawns (monotonic times of when this tracker was fed them)."""

    def __init__(self) -> None:
        self.pid: int | None = None
        self.incarnation = 0
        self.state = ''
        self.checkpoints = 0
        self.checkpoint_at: list[float] = []  # monotonic, when each was heard
        self.replaying_since: float | None = None
        self.respawned_at: float | None = None  # the latest recovery's spawn
        self.first_respawned_at: float | None = None
        self.running_since = 0.0

    def feed(self, new: list[dict[str, Any]]) -> None:
        """Take in newly read events."""
        for ev in new:
            if ev['kind'] == 'exit' and ev.get('incarnation') == self.incarnation:
                self.pid = None  # nothing to signal until the next spawn
            elif ev['kind'] == 'spawn':
                self.pid = int(ev['pid'])
                self.incarnation = int(ev['incarnation'])
                if ev.get('mode') == 'recover':
                    self.respawned_at = time.monotonic()
                    if self.first_respawned_at is None:
                        self.first_respawned_at = self.respawned_at
            elif ev['kind'] == 'checkpoint':
                self.checkpoints += 1
                self.checkpoint_at.append(time.monotonic())
            elif ev['kind'] == 'state':
                self.state = ev['new']
                self.replaying_since = time.monotonic() if ev['new'] == 'REPLAYING' else None
                if ev['new'] == 'RUNNING':
                    self.running_since = time.monotonic()

    def due(self, kill: Kill, started: float, now: float, previous: float | None = None,
            applied: int = 0) -> bool:
        """Whether ``kill`` should strike now (``previous``: when the last strike was;
        ``applied``: numbers the node's last published state shows applied)."""
        if kill.signal and self.pid is None:
            return False
        if kill.after is not None:
            return now - started >= kill.after
        if kill.after_applied is not None:
            return applied >= kill.after_applied
        if kill.after_previous is not None:
            return now - (started if previous is None else previous) >= kill.after_previous
        if kill.after_checkpoint is not None:
            return (self.checkpoints >= kill.after_checkpoint and now
                    - self.checkpoint_at[kill.after_checkpoint - 1] >= kill.delay)
        if kill.after_respawn is not None:
            since = self.respawned_at
            return since is not None and now - since >= kill.after_respawn
        assert kill.during_recovery is not None
        since = self.replaying_since
        return since is not None and now - since >= kill.during_recovery
