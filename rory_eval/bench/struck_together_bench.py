"""``make bench``: N nodes struck at once, with the standby pool and with one standby.

    python -m rory_eval.bench.struck_together_bench [--runs 3] [--nodes 1 2 3 6]

One bug often takes down every node that reads a message at the same moment (issue 38). Each
run supervises N instrumented integrators (each its own node name and state topic, all reading
/numbers at 50 Hz, method rory) under one ``rory supervise``, waits until the standbys are
ready, SIGKILLs the N node processes in one loop (microseconds apart), and waits until every
node has applied every number. Two configurations, interleaved run by run so that the
machine's load falls on both alike:

* ``pool``: the default pool (``standbys`` unset: one per node, at most 3);
* ``one standby``: ``standbys: 1``, as before the pool.

Per node struck, two times from the kill:

* *recovered*: the supervisor's own measure, crash detected -> released (``recovered``
  event's ``total_ms``);
* *heard*: when a reader of the node's state topic in this process first heard the new
  process (the first state message after its spawn event was read): what the node's consumers
  see. A cold process can be released long before other
  participants have discovered it (docs/performance.md, "Where a slow cold start waits").

The table gives, per N and configuration, the median and the worst over every node struck
in every run, the median of each run's last node back, the warm starts, and the runs that
ended exact (each node applied 1..COUNT once, in order).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rory_eval.harness.scenario import (
    EXAMPLE,
    EventsFile,
    StateReader,
    child_process,
    integrators_config,
    joining,
    scenario_env,
)
from rory_eval.harness.simrun import exit_on_sigterm

COUNT = 250  # 5 s at 50 Hz
RATE = 50.0
KILL_AFTER = 1.5  # s after every node has applied a number and the standbys are ready
CONFIGS = ('pool', 'one standby')


@dataclass
class Strike:
    """One run: N nodes struck together."""

    nodes: int
    config: str
    recovered_ms: dict[str, float] = field(default_factory=dict)
    heard_ms: dict[str, float] = field(default_factory=dict)
    warm: dict[str, bool] = field(default_factory=dict)
    exact: bool = False
    error: str = ''


def strike(nodes: int, config: str, domain_id: int, workdir: Path) -> Strike:
    """Run N integrators, kill them together, wait until all are exact again."""
    names = [f'n{i}' for i in range(nodes)]
    result = Strike(nodes, config)
    path = integrators_config(workdir, names,
                              standbys=1 if config == 'one standby' else None)
    env = scenario_env(domain_id)
    with joining(domain_id):
        reader = StateReader(domain_id, names)
    events = EventsFile(workdir / 'store-rory' / 'events.jsonl')
    pids: dict[str, int] = {}
    respawned: dict[str, float] = {}  # when this process saw each node's next process spawned
    pool = min(3, nodes) if config == 'pool' else 1
    sup_log = workdir / 'supervisor.log'

    def wait_until(what: str, done: Any, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            for ev in events.poll():
                if ev['kind'] == 'spawn':
                    pids[ev['node']] = ev['pid']
                    if ev['incarnation'] > 1:
                        respawned.setdefault(ev['node'], time.monotonic())
            if sup.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f'{what}:\n{sup_log.read_text()[-3000:]}')
            time.sleep(0.005)

    try:
        with child_process([sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(path)],
                           env, workdir, sup_log) as sup:
            wait_until('the nodes never ran', lambda: sum(
                1 for e in events.events if e['kind'] == 'state' and e['new'] == 'RUNNING'
            ) >= nodes, 60.0)
            publisher = [sys.executable, str(EXAMPLE / 'count_publisher.py'), str(COUNT),
                         str(RATE), str(nodes + 1)]  # the nodes and the ring's one reader
            with child_process(publisher, env, workdir, workdir / 'publisher.log') as pub:
                wait_until('no number was applied', lambda: all(
                    reader.state[n].get('count', 0) > 0 for n in names), 30.0)
                wait_until('the standbys were never ready',
                           lambda: sup_log.read_text().count(' ready in ') >= pool, 30.0)
                time.sleep(KILL_AFTER)
                struck_at = time.monotonic()
                for name in names:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pids[name], signal.SIGKILL)
                wait_until('not every node recovered', lambda: len(
                    {e['node'] for e in events.events if e['kind'] == 'recovered'}) == nodes,
                    60.0)
                wait_until('the publisher never finished', lambda: pub.poll() is not None, 60.0)
                wait_until('the nodes never ended exact', lambda: all(
                    reader.state[n].get('count') == COUNT for n in names), 30.0)
        for ev in events.events:
            if ev['kind'] == 'recovered':
                result.recovered_ms[ev['node']] = float(ev['total_ms'])
            if ev['kind'] == 'spawn' and ev['incarnation'] == 2:
                result.warm[ev['node']] = bool(ev['warm'])
        for name in names:
            # The first state from the new process: heard after it was spawned (a message the
            # killed one sent can still arrive just after the kill).
            heard = reader.first_heard_after(name, respawned.get(name, struck_at))
            if heard is not None:
                result.heard_ms[name] = (heard - struck_at) * 1000
        result.exact = all(
            reader.state[n].get('history') == list(range(1, COUNT + 1)) for n in names)
    except RuntimeError as err:
        result.error = str(err).splitlines()[0]
    finally:
        reader.close()
    return result


def _median(values: list[float]) -> str:
    return f'{statistics.median(values):.0f}' if values else '-'


def report(strikes: list[Strike]) -> str:
    """Markdown table per N and configuration."""
    lines = [
        '| N struck | standbys | runs exact | warm starts | recovered median (ms) | worst | '
        'last back, median | heard median (ms) | worst |',
        '|---:|---|---:|---:|---:|---:|---:|---:|---:|',
    ]
    keys = sorted({(s.nodes, s.config) for s in strikes}, key=lambda k: (k[0], k[1] != 'pool'))
    for nodes, config in keys:
        runs = [s for s in strikes if (s.nodes, s.config) == (nodes, config)]
        recovered = [v for s in runs for v in s.recovered_ms.values()]
        heard = [v for s in runs for v in s.heard_ms.values()]
        last = [max(s.recovered_ms.values()) for s in runs if s.recovered_ms]
        warm = sum(v for s in runs for v in s.warm.values())
        struck = sum(len(s.warm) for s in runs)
        pool = 'pool of ' + str(min(3, nodes)) if config == 'pool' else 'one'
        lines.append(
            f'| {nodes} | {pool} | {sum(s.exact for s in runs)}/{len(runs)} | {warm}/{struck} | '
            f'{_median(recovered)} | {max(recovered, default=0):.0f} | {_median(last)} | '
            f'{_median(heard)} | {max(heard, default=0):.0f} |')
    return '\n'.join(lines)


def main() -> None:
    """Run the benchmark."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--nodes', type=int, nargs='+', default=[1, 2, 3, 6])
    parser.add_argument('--out', type=Path, default=Path('bench-out'))
    args = parser.parse_args()
    domain = int(os.environ.get('ROS_DOMAIN_ID', '79'))
    strikes: list[Strike] = []
    began = time.monotonic()
    with tempfile.TemporaryDirectory(prefix='rory-struck-') as tmp:
        for i in range(args.runs):
            for nodes in args.nodes:
                configs = CONFIGS if i % 2 == 0 else tuple(reversed(CONFIGS))
                for config in configs:
                    if nodes == 1 and config == 'one standby':
                        continue  # the same as the pool of one
                    done = strike(nodes, config, domain,
                                  Path(tmp) / f'run{i}-n{nodes}-{config.replace(" ", "-")}')
                    strikes.append(done)
                    print(f'run {i + 1}, {nodes} struck, {config}: '
                          f'{"exact" if done.exact else "NOT EXACT"} '
                          f'recovered {sorted(round(v) for v in done.recovered_ms.values())} ms, '
                          f'heard {sorted(round(v) for v in done.heard_ms.values())} ms, '
                          f'warm {sum(done.warm.values())}/{len(done.warm)}'
                          f'{" " + done.error if done.error else ""}', flush=True)
    table = report(strikes)
    print(f'\n{table}\n\n{len(strikes)} runs in {(time.monotonic() - began) / 60:.1f} min')
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'struck_together.md').write_text(table + '\n')


if __name__ == '__main__':
    main()
