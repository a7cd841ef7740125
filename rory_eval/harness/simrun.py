"""One run in the simulator: the sim, some target nodes, and a recorder, all real processes.

This is what target tests and quality measurements stand on::

    run = SimRun('office_small', tmp_path, domain_id=ros_domain, duration=40.0)
    run.add_node('grid_slam', [sys.executable, 'targets/grid_slam/grid_slam_node.py',
                               '--ros-args', '-p', 'use_sim_time:=true'])
    run.record('/map', OccupancyGrid, keep_last=True)
    run.record('/grid_slam/pose', PoseStamped)
    result = run.run()
    result.last('/map'); result.messages['/grid_slam/pose']; result.ground_truth

The recorder lives in this process, in its own rclpy context, spun on a thread; it subscribes
before any node starts. The simulator starts last with ``--wait-for`` so its clock stays at 0
until the targets have subscribed (``wait_for``); it then runs ``duration`` sim seconds, writes
``summary.json`` and ``path.csv`` and exits. Every process is started in its own session and
reaped on the way out, also when the run fails. Each node's CPU seconds and peak RSS over the
simulated part of the run are read from ``/proc`` just before it is stopped, for the node's
whole process tree (a supervisor and the node it runs count together).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from rory_eval.harness.process_usage import TreeSampler, TreeUsage, peak_rss_mb, tree_cpu_ticks
from rory_eval.harness.process_usage import tree_pids as process_tree
from rory_eval.harness.scenario import _environ_lock, joining, scenario_env

REPO = Path(__file__).resolve().parents[2]
_CLK_TCK = os.sysconf('SC_CLK_TCK')
_SAMPLE_PERIOD = 1.0  # s between readings of each node's process tree (per role, for overhead)
_RECORDERS = itertools.count(1)

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     reliability=ReliabilityPolicy.RELIABLE)
"""Reliable, transient local, depth 1: what /goal_pose, /e_stop and maps are sent with."""


def exit_on_sigterm() -> None:
    """Make SIGTERM end this process as Ctrl-C does, through its ``finally`` blocks.

    The processes a run spawns are in sessions of their own (a Ctrl-C at the terminal must not
    strike the node under test behind RORY's back), so they outlive a harness that dies of a
    plain SIGTERM: ``pkill -f target_faults`` left a supervisor, a node and the simulator
    running on the campaign's domain. Raising SystemExit instead lets ``SimRun.run`` reap them.
    Call it from a program's ``main`` (signal handlers belong to the main thread).
    """
    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, stop)


def store_events(store: Path) -> list[dict[str, Any]]:
    """The records of a supervisor's ``<store>/events.jsonl`` so far (none before it exists).

    A line still being written (or cut by a stop) is skipped.
    """
    path = store / 'events.jsonl'
    if not path.exists():
        return []
    records = []
    for line in path.read_text(errors='replace').splitlines():
        with contextlib.suppress(json.JSONDecodeError):
            records.append(json.loads(line))
    return records


def wait_for_clock(sim_log: Path, world: str, stop: threading.Event, timeout: float) -> bool:
    """Wait until the simulator's clock runs (its log says so); False if stopped or timed out."""
    deadline = time.monotonic() + timeout
    while not (sim_log.exists()
               and f'{world}: running (seed' in sim_log.read_text(errors='replace')):
        if stop.wait(0.05) or time.monotonic() > deadline:
            return False
    return True


class SimRunError(RuntimeError):
    """A process of the run failed; the message names it and ends with its log's tail."""


@dataclass
class NodeUsage:
    """What one node process used while the simulation ran."""

    cpu_seconds: float  # user + system, its threads and its child processes included
    wall_seconds: float
    peak_rss_mb: float  # sum of the VmHWM of the processes alive at the end (an upper bound)
    tree: TreeUsage | None = None  # the same, per process role, with the steady half and PSS

    @property
    def cpu_percent(self) -> float:
        """CPU seconds per wall second, in percent of one core."""
        return 100.0 * self.cpu_seconds / max(self.wall_seconds, 1e-9)


@dataclass
class SimRunResult:
    """What a run left: recorded messages, the simulator's summary and ground truth."""

    out: Path
    messages: dict[str, list[Any]]
    received_at: dict[str, list[float]]  # monotonic receive times, parallel to messages
    summary: dict[str, Any]
    ground_truth: list[tuple[float, float, float, float]]  # (t, x, y, yaw) in map, 10 Hz
    usage: dict[str, NodeUsage]
    exit_codes: dict[str, int | None]  # None: still running at the end (then stopped)

    def last(self, topic: str) -> Any:
        """The last message recorded on topic; raises naming the topic if there is none."""
        if not self.messages.get(topic):
            msg = f'{topic}: nothing was recorded (see {self.out}/*.log)'
            raise SimRunError(msg)
        return self.messages[topic][-1]

    def log(self, name: str) -> str:
        """A node's (or 'sim') combined stdout and stderr."""
        return (self.out / f'{name}.log').read_text(errors='replace')


@dataclass
class _Node:
    name: str
    argv: list[str]
    cwd: Path
    env: dict[str, str]
    proc: subprocess.Popen[bytes] | None = None
    start_ticks: int = 0
    start_wall: float = 0.0
    sampler: TreeSampler | None = None
    usage: NodeUsage | None = None


@dataclass
class _Recording:
    topic: str
    msg_type: Any
    qos: QoSProfile | int
    keep_last: bool
    messages: list[Any] = field(default_factory=list)
    times: list[float] = field(default_factory=list)


class SimRun:
    """Configure with ``add_node``/``record``/``publish_latched``, then ``run()`` once.

    Args:
        world: office_small, workshop or real_room.
        out: folder for logs, summary.json and path.csv (created).
        domain_id: this run's ROS_DOMAIN_ID; no other run may use it at the same time.
        duration: sim seconds.
        driver: 'internal' (the route, deterministic for a seed), 'route' (the route driver as
            a ROS node) or 'none' (a target drives).
        seed: the simulator's noise seed.
        depth: whether the depth camera runs.
        wait_for: the clock stays at 0 until each topic has that many subscribers (the
            recorder's own subscriptions count).
        sim_args: more ``rory sim run`` arguments.
    """

    def __init__(self, world: str, out: Path, *, domain_id: int, duration: float = 30.0,
                 driver: str = 'internal', seed: int = 0, depth: bool = True,
                 wait_for: dict[str, int] | None = None,
                 sim_args: Sequence[str] = ()) -> None:
        self.world = world
        self.out = out.resolve()
        self.domain_id = domain_id
        self.duration = duration
        self.driver = driver
        self.seed = seed
        self.depth = depth
        self.wait_for = {'/scan': 1} if wait_for is None else dict(wait_for)
        self.sim_args = list(sim_args)
        self.env = scenario_env(domain_id)
        self.env['PYTHONPATH'] = os.pathsep.join(
            p for p in (str(REPO), os.environ.get('PYTHONPATH', '')) if p)
        self._nodes: list[_Node] = []
        self._recordings: dict[str, _Recording] = {}
        self._latched: list[tuple[str, Any]] = []
        self._once: list[tuple[str, Any, int]] = []
        self._done = False

    def add_node(self, name: str, argv: Sequence[str], *, cwd: Path | None = None,
                 env: dict[str, str | None] | None = None) -> None:
        """A process to start before the simulator; its output goes to OUT/NAME.log.

        ``env`` changes the run's environment for this process; a name given None is removed.
        """
        node_env = dict(self.env)
        for key, value in (env or {}).items():
            if value is None:
                node_env.pop(key, None)
            else:
                node_env[key] = value
        self._nodes.append(_Node(name, list(argv), cwd or REPO, node_env))

    def record(self, topic: str, msg_type: Any, *, qos: QoSProfile | int = 100,
               keep_last: bool = False) -> None:
        """Keep every message on topic (or only the last one: maps, clouds)."""
        self._recordings[topic] = _Recording(topic, msg_type, qos, keep_last)

    def publish_latched(self, topic: str, message: Any) -> None:
        """Publish message reliable + transient local from the start (a goal, an initial pose)."""
        self._latched.append((topic, message))

    def publish_once(self, topic: str, message: Any, *, subscribers: int = 1) -> None:
        """Publish message once, reliable and volatile, as a person clicking a goal in RViz.

        It goes out when the clock has started and ``subscribers`` readers have matched; a
        reader that (re)starts later never sees it.
        """
        self._once.append((topic, message, subscribers))

    def recorded(self, topic: str) -> list[tuple[float, Any]]:
        """What was recorded on topic so far, as (monotonic receive time, message); callable
        while the run runs (from a ``stop_when``)."""
        rec = self._recordings[topic]
        return list(zip(list(rec.times), list(rec.messages), strict=False))

    def run(self, *, timeout: float | None = None,
            stop_when: Callable[[], bool] | None = None) -> SimRunResult:
        """Start everything, wait for the simulator to finish its duration, stop and reap all.

        ``stop_when``: asked every 0.2 s while the clock runs; once it says True the simulator
        is stopped early (SIGINT: it finishes its tick and writes its summary and path as at
        the end of its duration).
        """
        if self._done:
            msg = 'a SimRun runs once'
            raise SimRunError(msg)
        self._done = True
        self.out.mkdir(parents=True, exist_ok=True)
        deadline = time.monotonic() + (timeout or self.duration * 3 + 90.0)
        recorder = _Recorder(self.domain_id, self._recordings.values(), self._latched,
                             self._once)
        sim: subprocess.Popen[bytes] | None = None
        exit_codes: dict[str, int | None] = {}
        try:
            for node in self._nodes:
                node.proc = _spawn(node.argv, node.env, node.cwd, self.out / f'{node.name}.log')
            sim = _spawn(self._sim_argv(), self.env, REPO, self.out / 'sim.log')
            self._wait_for_clock(sim, deadline)
            for node in self._nodes:
                assert node.proc is not None
                node.start_ticks = tree_cpu_ticks(node.proc.pid)
                node.start_wall = time.monotonic()
                node.sampler = TreeSampler(node.proc.pid)
                node.sampler.start()
            recorder.publish_once(deadline, self._check_nodes)
            next_sample = time.monotonic() + _SAMPLE_PERIOD
            stopping = False
            while sim.poll() is None:
                self._check_nodes()
                if stop_when is not None and not stopping and stop_when():
                    stopping = True
                    with contextlib.suppress(ProcessLookupError):
                        sim.send_signal(signal.SIGINT)
                if time.monotonic() >= next_sample:
                    next_sample += _SAMPLE_PERIOD
                    for node in self._nodes:
                        if node.sampler is not None:
                            node.sampler.sample()
                if time.monotonic() > deadline:
                    msg = f'the simulator did not finish in time\n{self._tail("sim")}'
                    raise SimRunError(msg)
                time.sleep(0.2)
            if sim.returncode not in (0, 1):
                msg = f'the simulator exited with {sim.returncode}\n{self._tail("sim")}'
                raise SimRunError(msg)
            for node in self._nodes:
                assert node.proc is not None
                if node.proc.poll() is None:
                    node.usage = NodeUsage(
                        (tree_cpu_ticks(node.proc.pid) - node.start_ticks) / _CLK_TCK,
                        time.monotonic() - node.start_wall,
                        sum(peak_rss_mb(pid) for pid in process_tree(node.proc.pid)),
                        node.sampler.finish() if node.sampler is not None else None,
                    )
                exit_codes[node.name] = node.proc.poll()
            # Let the last outputs arrive before the recorder stops.
            time.sleep(0.5)
        finally:
            for node in self._nodes:
                if node.proc is not None:
                    _reap(node.proc)
            if sim is not None:
                _reap(sim)
            recorder.close()
        summary_path = self.out / 'summary.json'
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        return SimRunResult(
            out=self.out,
            messages={t: r.messages for t, r in self._recordings.items()},
            received_at={t: r.times for t, r in self._recordings.items()},
            summary=summary,
            ground_truth=_read_ground_truth(self.out / 'path.csv'),
            usage={n.name: n.usage for n in self._nodes if n.usage is not None},
            exit_codes=exit_codes,
        )

    def _sim_argv(self) -> list[str]:
        argv = [sys.executable, '-m', 'sim', 'run', '--world', self.world,
                '--driver', self.driver, '--duration', str(self.duration),
                '--seed', str(self.seed), '--out', str(self.out)]
        if not self.depth:
            argv.append('--no-depth')
        for topic, count in self.wait_for.items():
            argv += ['--wait-for', f'{topic}={count}']
        return argv + self.sim_args

    def _wait_for_clock(self, sim: subprocess.Popen[bytes], deadline: float) -> None:
        # The simulator logs 'WORLD: running (seed ...' once --wait-for is satisfied and the
        # clock runs.
        log = self.out / 'sim.log'
        while f'{self.world}: running (seed' not in log.read_text(errors='replace'):
            self._check_nodes()
            if sim.poll() is not None:
                msg = f'the simulator exited with {sim.returncode}\n{self._tail("sim")}'
                raise SimRunError(msg)
            if time.monotonic() > deadline:
                msg = f'the clock never started\n{self._tail("sim")}'
                raise SimRunError(msg)
            time.sleep(0.05)

    def _check_nodes(self) -> None:
        for node in self._nodes:
            assert node.proc is not None
            code = node.proc.poll()
            if code is not None and code != 0:
                msg = f'{node.name} exited with {code}\n{self._tail(node.name)}'
                raise SimRunError(msg)

    def _tail(self, name: str) -> str:
        path = self.out / f'{name}.log'
        text = path.read_text(errors='replace') if path.exists() else ''
        return f'--- {path} (tail) ---\n{text[-3000:]}'


class _Recorder:
    """Subscribes (and publishes latched messages) in its own context, spun on a thread."""

    def __init__(self, domain_id: int, recordings: Any, latched: list[tuple[str, Any]],
                 once: list[tuple[str, Any, int]]) -> None:
        # This process joins the run: the same discovery settings as the others.
        self.context = Context()
        # Runs side by side in threads of one process take turns at os.environ.
        with _environ_lock, joining(domain_id):
            rclpy.init(context=self.context, domain_id=domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
            # Unique: runs side by side in one process (rory_eval.harness.fleet) each have a
            # recorder.
            self.node = Node(f'simrun_recorder_{next(_RECORDERS)}', context=self.context)
        self._lock = threading.Lock()
        for rec in recordings:
            self.node.create_subscription(rec.msg_type, rec.topic, self._callback(rec), rec.qos)
        self._publishers = []
        for topic, message in latched:
            pub = self.node.create_publisher(type(message), topic, LATCHED)
            pub.publish(message)
            self._publishers.append(pub)
        volatile = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE)
        self._once = [(self.node.create_publisher(type(message), topic, volatile), message, n)
                      for topic, message, n in once]
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _callback(self, rec: _Recording) -> Any:
        def on_message(msg: Any) -> None:
            now = time.monotonic()
            with self._lock:
                if rec.keep_last:
                    rec.messages[:] = [msg]
                    rec.times[:] = [now]
                else:
                    rec.messages.append(msg)
                    rec.times.append(now)
        return on_message

    def publish_once(self, deadline: float, check: Any) -> None:
        """Send each one-shot message as soon as its readers have matched."""
        for pub, message, subscribers in self._once:
            while pub.get_subscription_count() < subscribers:
                check()
                if time.monotonic() > deadline:
                    msg = f'{pub.topic_name}: {subscribers} readers never matched'
                    raise SimRunError(msg)
                time.sleep(0.02)
            pub.publish(message)

    def _spin(self) -> None:
        while self.context.ok():
            with contextlib.suppress(Exception):
                self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.context.try_shutdown()
        self._thread.join(timeout=2.0)
        # The participant ends with the context's last node, not with its shutdown
        # (tests/sim/conftest.py, Probe.close).
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


def _spawn(argv: list[str], env: dict[str, str], cwd: Path, log: Path) -> subprocess.Popen[bytes]:
    with log.open('wb') as out:
        return subprocess.Popen(argv, env=env, cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)


def _reap(proc: subprocess.Popen[bytes]) -> None:
    """SIGINT, then SIGKILL to the whole session; always waits."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=5)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def _read_ground_truth(path: Path) -> list[tuple[float, float, float, float]]:
    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    header = lines[0].split(',')
    t, x, y, yaw = (header.index(c) for c in ('t', 'x', 'y', 'yaw'))
    rows = []
    for line in lines[1:]:
        if not line or line.startswith('#'):
            continue
        cols = line.split(',')
        rows.append((float(cols[t]), float(cols[x]), float(cols[y]), float(cols[yaw])))
    return rows
