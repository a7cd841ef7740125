"""Recovery across hosts: the integrator scenario with its publisher on another host.

    python -m rory_eval.bench.multihost_bench [--runs 5] [--kill-at 2.5] [--out bench-out/multihost]

Hosts are network namespaces joined by a veth pair (:mod:`rory_eval.harness.hosts`, needs root). The
integrator, its supervisor and an observer run on host ``a``; the count publisher runs on host
``b`` ("across hosts") or on ``a`` beside them ("one host"), alternating run by run so that
machine load affects both alike. Every process speaks UDPv4 only with discovery range SUBNET,
in both layouts: the only difference is the network path of ``/numbers``. Recovery time is the
supervisor's own measure, crash detected -> released (the ``recovered`` event's ``total_ms``),
for RORY with its warm standby (the default), replay paced and fast.

:func:`run_on_hosts` is the scenario itself (``rory_eval.harness.scenario.run`` across
namespaces); the integration test ``tests/integration/test_multihost.py`` uses it too, with a
link outage.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Bool, Int64, String

from rory_eval.harness.hosts import Host, Hosts, netns_available, stop
from rory_eval.harness.scenario import (
    EXAMPLE,
    INTEGRATOR,
    EventsFile,
    EventTracker,
    ScenarioResult,
    prepare,
    scenario_env,
)

PUBLISHER = EXAMPLE / 'count_publisher.py'


@dataclass(frozen=True)
class Outage:
    """The link of the publisher's host goes down for ``seconds``, ``after_respawn`` seconds
    after the supervisor spawned the crashed node's replacement (the recovery is under way)."""

    seconds: float
    after_respawn: float = 0.0


@dataclass
class HostRun:
    """One run across (or on one of) the hosts: the scenario's result and what the link saw."""

    result: ScenarioResult
    layout: str  # 'across hosts' | 'one host'
    published_from: float | None  # wall time number 1 arrived on the node's host
    numbers_seen: list[tuple[float, int]] = field(repr=False)  # (wall time, n) on the node's host
    link_down: float | None = None  # wall times of the outage
    link_up: float | None = None
    link_packets: tuple[int, int] = (0, 0)  # (rx, tx) on the node host's interface, this run

    def seen_between(self, start: float, end: float) -> list[int]:
        """Numbers that arrived on the node's host in [start, end] (wall time)."""
        return [n for t, n in self.numbers_seen if start <= t <= end]

    def timeline(self) -> list[tuple[float, str]]:
        """What happened, seconds after the kill: supervisor states, the link, /numbers gaps."""
        t0 = next((e['t'] for e in self.result.events if e['kind'] == 'exit'), None)
        if t0 is None:
            return []
        out: list[tuple[float, str]] = []
        for e in self.result.events:
            if e['t'] < t0 - 0.001:
                continue
            if e['kind'] == 'state':
                out.append((e['t'] - t0, f"{e['old']} -> {e['new']} ({e.get('reason', '')})"))
            elif e['kind'] in ('spawn', 'hello', 'recovered', 'switched', 'exit', 'error'):
                detail = {k: v for k, v in e.items() if k in (
                    'pid', 'warm', 'total_ms', 'replayed', 'topic', 'message', 'code')}
                out.append((e['t'] - t0, f"{e['kind']} {detail}"))
        if self.link_down is not None and self.link_up is not None:
            out.append((self.link_down - t0, 'link down'))
            out.append((self.link_up - t0, 'link up'))
        prev: tuple[float, int] | None = None
        for t, n in self.numbers_seen:
            if prev is not None and t - prev[0] > 0.2:
                out.append((prev[0] - t0, f'/numbers on host a: last before a gap, {prev[1]}'))
                out.append((t - t0, f'/numbers on host a: first after the gap, {n}'))
            prev = (t, n)
        return sorted(out)


class _Observed:
    """What the observer on the node's host wrote: the node's state, /e_stop, /numbers."""

    def __init__(self, path: Path) -> None:
        self.file = EventsFile(path)
        self.ready = False
        self.state: dict[str, Any] = {}
        self.e_stop: list[tuple[float, bool]] = []
        self.numbers: list[tuple[float, int]] = []

    def poll(self) -> None:
        for rec in self.file.poll():
            if rec['k'] == 'ready':
                self.ready = True
            elif rec['k'] == 'state':
                self.state = dict(rec['state'])
            elif rec['k'] == 'n':
                self.numbers.append((float(rec['t']), int(rec['v'])))
            elif rec['k'] == 'e':
                self.e_stop.append((float(rec['t']), bool(rec['v'])))

    @property
    def applied(self) -> list[int]:
        """The node's history as last published."""
        return list(self.state.get('history', []))


def run_on_hosts(
    hosts: Hosts,
    workdir: Path,
    *,
    node_host: Host,
    publisher_host: Host,
    domain_id: int,
    kill_at: float | None,
    count: int = 250,
    rate: float = 50.0,
    interval: float = 2.0,
    pace: str = 'paced',
    warm_standby: bool | None = None,
    outage: Outage | None = None,
    timeout: float = 60.0,
) -> HostRun:
    """The integrator scenario with its publisher on ``publisher_host``; SIGKILL at ``kill_at``.

    The node, its supervisor and the observer run on ``node_host``. Every process is stopped on
    return, also on an error.

    Args:
        hosts: The hosts to run on.
        workdir: Instrumented program, config, store and logs.
        node_host: Where the supervisor (and so the node) and the observer run.
        publisher_host: Where the count publisher runs.
        domain_id: ROS domain of this run.
        kill_at: Seconds after the node applied its first number (None: no crash).
        count: Numbers to publish, at ``rate`` Hz.
        rate: Publishing rate.
        interval: Checkpoint interval (s).
        pace: Replay pace, ``paced`` or ``fast``.
        warm_standby: The supervisor config's setting (None: its default, on).
        outage: Take the publisher host's link down during the recovery.
        timeout: Seconds before the run is abandoned.
    """
    workdir = workdir.resolve()
    method = 'rory'
    config = prepare(workdir, method, interval=interval, pace=pace, warm_standby=warm_standby)
    store = workdir / f'store-{method}'
    # A fresh store and observer file: a follower must not start reading an earlier run's file.
    shutil.rmtree(store, ignore_errors=True)
    (workdir / 'observed.jsonl').unlink(missing_ok=True)
    # Across hosts LOCALHOST would keep discovery on each host. UDPv4 only (scenario_env, by
    # fast_rediscovery_env) in every process, or shared memory would bypass the link.
    env = scenario_env(domain_id, reach='SUBNET')
    assert env['FASTDDS_BUILTIN_TRANSPORTS'] == 'UDPv4'
    python = sys.executable
    observed = _Observed(workdir / 'observed.jsonl')
    events = EventsFile(store / 'events.jsonl')
    tracker = EventTracker()
    deadline = time.monotonic() + timeout
    sup_log = workdir / f'supervisor-{method}.log'
    kills: list[tuple[str, float]] = []
    link: dict[str, float] = {}  # wall times 'down' and 'up'

    def poll() -> None:
        tracker.feed(events.poll())
        observed.poll()

    def check(proc: subprocess.Popen[bytes], what: str) -> None:
        if proc.poll() is not None or time.monotonic() > deadline:
            why = 'exited' if proc.poll() is not None else 'timed out'
            # Taken while every process still runs: the sockets and counters of the moment.
            # (Also in the error: a CI run keeps only what the failure printed.)
            network = hosts.snapshot()
            (workdir / 'network-at-failure.txt').write_text(network)
            raise RuntimeError(f'{what}: {why}\n{sup_log.read_text()[-4000:]}\n'
                               f'# the hosts\' network then\n{network[-8000:]}')

    rx0, tx0 = hosts.interface_packets(node_host)  # the interface outlives a run
    packets = (0, 0)
    observer = hosts.popen(
        node_host, [python, '-m', 'rory_eval.bench.multihost_bench', 'observe', 'observed.jsonl'],
        env=env, cwd=workdir, log=workdir / 'observer.log',
    )
    sup = publisher = None
    try:
        while not observed.ready:
            poll()
            check(observer, 'observer start')
            time.sleep(0.01)
        sup = hosts.popen(
            node_host, [python, '-m', 'rory_runtime.cli', 'supervise', str(config)],
            env=env, cwd=workdir, log=sup_log,
        )
        while tracker.state != 'RUNNING':
            poll()
            check(sup, 'node start')
            time.sleep(0.01)
        # Three readers of /numbers: the node, RORY's ring and the observer.
        publisher = hosts.popen(
            publisher_host, [python, str(PUBLISHER), str(count), str(rate), '3'],
            env=env, cwd=workdir, log=workdir / f'publisher-{method}.log',
        )
        started: float | None = None
        down_at: float | None = None
        while True:
            poll()
            check(sup, 'scenario')
            now = time.monotonic()
            if started is None and observed.applied:
                started = now  # the first number has been applied
            if (kill_at is not None and not kills and started is not None
                    and now - started >= kill_at and tracker.pid is not None):
                os.kill(tracker.pid, signal.SIGKILL)
                kills.append((f'at {kill_at:g} s', now))
            if outage is not None and kills and tracker.first_respawned_at is not None:
                down_at = down_at or tracker.first_respawned_at + outage.after_respawn
                if 'down' not in link and now >= down_at:
                    hosts.link_down(publisher_host)
                    link['down'] = time.time()
                if 'down' in link and 'up' not in link and now >= down_at + outage.seconds:
                    hosts.link_up(publisher_host)
                    link['up'] = time.time()
            # Done: all sent, the node running again, and the last number applied (it applies in
            # order) - or nothing new for a while, when numbers were lost.
            applied = observed.applied
            done = (bool(applied) and applied[-1] == count) or (
                now - max(tracker.running_since, observed.file.changed) > 3.0
            )
            if (publisher.poll() is not None and tracker.state == 'RUNNING'
                    and (kill_at is None or kills) and (outage is None or 'up' in link)
                    and done):
                break
            time.sleep(0.005)
        rx, tx = hosts.interface_packets(node_host)
        packets = (rx - rx0, tx - tx0)
    finally:
        if 'down' in link and 'up' not in link:
            hosts.link_up(publisher_host)
        # The supervisor stops its node; the observer last, so it hears everything before.
        for proc in (publisher, sup, observer):
            if proc is not None:
                stop(proc)
        poll()
    result = ScenarioResult(
        method=method,
        expected=count,
        state=observed.state,
        recoveries=[e for e in events.events if e['kind'] == 'recovered'],
        kills=kills,
        e_stop=observed.e_stop,
        events=events.events,
        log=sup_log.read_text(),
    )
    return HostRun(
        result=result,
        layout='one host' if publisher_host == node_host else 'across hosts',
        published_from=next((t for t, n in observed.numbers if n == 1), None),
        numbers_seen=observed.numbers,
        link_down=link.get('down'),
        link_up=link.get('up'),
        link_packets=packets,
    )


# -- the observer (runs inside the node's host) --------------------------------------------------


def observe(out: Path, state_topic: str = INTEGRATOR.state_topic) -> None:
    """Record the node's state, /e_stop and /numbers as they arrive, as JSON lines, until SIGINT.

    A process of its own: the caller's process sits in another network namespace and could not
    hear the node's host.
    """
    stopping = False

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node('multihost_observer')
    with out.open('a', buffering=1) as f:

        def write(kind: str, **fields: Any) -> None:
            f.write(json.dumps({'k': kind, 't': time.time(), **fields}) + '\n')

        last = ['']

        def on_state(msg: Any) -> None:
            if msg.data != last[0]:
                last[0] = msg.data
                write('state', state=json.loads(msg.data))

        def on_e_stop(msg: Any) -> None:
            write('e', v=bool(msg.data))

        def on_number(msg: Any) -> None:
            write('n', v=int(msg.data))

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        # Volatile: matches the node's latched state publisher, as scenario's observer does.
        node.create_subscription(String, state_topic, on_state, QoSProfile(depth=10))
        node.create_subscription(Bool, '/e_stop', on_e_stop, latched)
        # As the node subscribes (reliable): arrival times show when the link carried data.
        node.create_subscription(Int64, '/numbers', on_number, QoSProfile(depth=1000))
        write('ready')
        while not stopping:
            rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_node()
    node.context.try_shutdown()


# -- the bench -----------------------------------------------------------------------------------

Config = tuple[str, str]
"""(pace, layout)."""


def _ms(values: list[float]) -> str:
    if not values:
        return '- | - | -'
    return f'{statistics.median(values):.0f} | {min(values):.0f} | {max(values):.0f}'


def report(results: dict[Config, list[HostRun]]) -> str:
    """Markdown table: per pace and layout, runs correct, recovery time, what crossed the link."""
    lines = [
        '| replay | publisher | runs correct | recovery median (ms) | min | max | '
        'restart | sync | replay (ms, medians) | packets into host a over the link |',
        '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for (pace, layout), runs in results.items():
        recs = [r.result.recoveries[0] for r in runs if r.result.recoveries]
        steps = [
            f'{statistics.median(float(e[s]) for e in recs):.0f}' if recs else '-'
            for s in ('restart_ms', 'sync_ms', 'replay_ms')
        ]
        correct = sum(r.result.correct for r in runs)
        rx = statistics.median(r.link_packets[0] for r in runs) if runs else 0
        lines.append(
            f'| {pace} | {layout} | {correct}/{len(runs)} | '
            f'{_ms([float(e["total_ms"]) for e in recs])} | {" | ".join(steps)} | {rx:.0f} |'
        )
    return '\n'.join(lines)


def bench(runs: int, kill_at: float, out: Path, domain_id: int) -> str:
    """Run the comparison; returns the Markdown table."""
    ok, why = netns_available()
    if not ok:
        raise SystemExit(f'multihost_bench: {why}')
    paces = ('paced', 'fast')
    layouts = ('across hosts', 'one host')
    results: dict[Config, list[HostRun]] = {(p, lay): [] for p in paces for lay in layouts}
    began = time.monotonic()
    with Hosts(['a', 'b'], tag=f'bench{domain_id}', subnet=domain_id) as hosts:
        a, b = hosts['a'], hosts['b']
        for i in range(runs):
            for pace in paces:
                # Alternate which layout goes first, so neither always runs on a warmer machine.
                order = layouts if i % 2 == 0 else layouts[::-1]
                for layout in order:
                    run = run_on_hosts(
                        hosts, out / f'{pace}-{layout.replace(" ", "-")}',
                        node_host=a, publisher_host=b if layout == 'across hosts' else a,
                        domain_id=domain_id, kill_at=kill_at, count=300, pace=pace,
                    )
                    results[(pace, layout)].append(run)
                    total = run.result.recovery_ms[0] if run.result.recovery_ms else float('nan')
                    print(f'run {i + 1}/{runs} {pace:5} {layout:12} recovered in {total:6.0f} ms, '
                          f'correct={run.result.correct}, link rx {run.link_packets[0]} packets',
                          flush=True)
    text = report(results)
    minutes = (time.monotonic() - began) / 60
    print(f'\nrory, warm standby; SIGKILL {kill_at:g} s in; 300 numbers at 50 Hz; '
          f'{runs} runs per row ({minutes:.1f} min)\n')
    print(text)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'recovery.md').write_text(text + '\n')
    return text


def main() -> None:
    """Run the benchmark (or, as ``observe FILE``, the observer inside a host)."""
    if sys.argv[1:2] == ['observe']:
        observe(Path(sys.argv[2]))
        return
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--kill-at', type=float, default=2.5)
    parser.add_argument('--out', type=Path, default=Path('bench-out') / 'multihost')
    args = parser.parse_args()
    # Any id will do: the hosts' namespaces keep this run's discovery to themselves.
    domain = int(os.environ.get('ROS_DOMAIN_ID', '79'))
    bench(args.runs, args.kill_at, args.out, domain)


if __name__ == '__main__':
    main()
