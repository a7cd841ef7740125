"""What a whole stack costs under RORY: the six targets under ONE supervisor against the same
six run bare, side by side in the simulator; then crashes in that stack.

    python -m rory_eval.bench.stack_bench [--runs 3] [--world real_room] [--strike-runs 1]

Each run starts the simulator (depth camera on, the navigator driving to the world's goal on
AMCL's pose) and the six targets: grid_slam, graph_slam, depth_mapper, amcl, lama_local,
navigator. ``bare``: each as its own process, as a user runs them (ROS's default DDS settings:
shared memory and UDPv4 on the host). ``rory``: one ``rory supervise`` config with all six
(method rory, warm standby, RORY's DDS profile: UDPv4 on 127.0.0.1 only, rory_runtime/dds).
The simulator runs with RORY's profile in both and talks to either over UDPv4. Bare and rory
alternate, the order swapped from run to run. CPU is each process tree's *steady* figure (the
second half of the run, every process up) in % of one core, summed; PSS is summed at the end;
the simulator is left out of both.

``--configs`` adds the other configurations, in the order they add mechanisms, so that each
one's cost is read apart (issue 22's goal 3): ``bare_udp`` is the six bare under RORY's DDS
profile (what the profile costs); ``restart`` is the runtime in each node and the
supervisor with nothing kept; ``checkpoint`` adds checkpoints; ``replay`` the write-ahead log
and the supervisor's ring, no checkpoints; ``rory`` both and the warm standby. All configurations
of a run go in turn, the order reversed from run to run.

The strike runs (rory only) SIGKILL each node alone, one after another, then two at once, and
report each recovery's total time and whether it started from the warm standby.

Writes ``<out>/stack.json`` and prints a Markdown table (docs/performance.md, issue 22's stack).
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from rory_eval.bench.light_node_bench import alternating
from rory_eval.harness.simrun import SimRun, exit_on_sigterm, store_events
from rory_eval.harness.stack import GOAL_XY, Strike, Striker, instrument
from rory_eval.targets import TARGETS

STACK = ('grid_slam', 'graph_slam', 'depth_mapper', 'amcl', 'lama_local', 'navigator')
CONFIGS = ('bare', 'bare_udp', 'restart', 'checkpoint', 'replay', 'rory')
"""bare, then in the order they add mechanisms (the module's docstring)."""
PLAIN_DDS: dict[str, str | None] = {
    'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST', 'FASTRTPS_DEFAULT_PROFILES_FILE': None,
    'FASTDDS_DEFAULT_PROFILES_FILE': None, 'FASTDDS_BUILTIN_TRANSPORTS': None}
"""What a user's shell gives a bare node: ROS's defaults on this host."""
LOGGING = frozenset({'replay', 'rory'})
"""The configurations whose supervisor keeps a ring of the nodes' inputs."""
DURATION = 40.0  # sim s: the navigator's 30 s to real_room's goal, and then some
SETTLE = 12.0  # sim s before the first strike: every node up, its first checkpoints, standby
STRIKE_GAP = 4.0  # sim s between strikes: the last recovery done, the standby ready again


def bare_commands(world: str) -> dict[str, list[str]]:
    """Each target's command line as the evaluation runs it (sim time, the world's start)."""
    return {name: TARGETS[name].argv(world) for name in STACK}


def stack_config(world: str, out: Path, method: str = 'rory') -> Path:
    """One supervisor config for the six, each its instrumented copy, /e_stop held."""
    nodes = []
    for name, argv in bare_commands(world).items():
        script = Path(argv[1])
        copy = instrument(name, out.parent / 'instrumented' / name)
        nodes.append({'name': name, 'command': ['python', str(copy / script.name), *argv[2:]],
                      'method': method, **({'replay': 'fast'} if method in LOGGING else {})})
    config = {
        'nodes': nodes,
        'safe_state': [{'topic': '/e_stop', 'type': 'std_msgs/msg/Bool',
                        'hold': {'data': True}, 'release': {'data': False}}],
        'store': str(out / 'store'),
        'prefix_output': True,
    }
    path = out / 'stack.yaml'
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def _readers(config: str) -> dict[str, int]:
    """Subscribers each input has once every process is up: the clock waits for them."""
    # One per node that reads it.
    per_node = Counter(topic for name in STACK for topic in TARGETS[name].inputs)
    # Under rory the supervisor's ring reads each input too, with one reader shared by the
    # nodes that read it (ring.py, SharedReader): n nodes and one ring reader, not 2n, which
    # never appear (the simulator then waits out its --wait-timeout, 30 s, every run).
    return {t: n + (1 if config in LOGGING else 0) for t, n in per_node.items()}


def run_once(config: str, world: str, out: Path, domain: int,
             strikes: Sequence[Strike] = ()) -> dict[str, Any]:
    """One run of the stack, bare or under one supervisor; usage per process tree."""
    from rory_eval.harness.goals import goal_message
    from sim.worlds import get_world

    if out.exists():
        shutil.rmtree(out)
    run = SimRun(world, out, domain_id=domain, duration=DURATION, driver='none',
                 wait_for=_readers(config), sim_args=['--start-delay', '1.0'])
    if config in ('bare', 'bare_udp'):
        for name, argv in bare_commands(world).items():
            run.add_node(name, argv, env=PLAIN_DDS if config == 'bare' else None)
    else:
        run.add_node('supervisor', [sys.executable, '-m', 'rory_runtime.cli', 'supervise',
                                    str(stack_config(world, out, config))])
    spec = get_world(world)
    run.publish_once('/goal_pose', goal_message(world, spec.default_goal),
                     subscribers=2 if config in LOGGING else 1)
    striker = Striker(out / 'sim.log', world, out / 'store', strikes) if strikes else None
    if striker is not None:
        striker.start()
    try:
        result = run.run()
    finally:
        if striker is not None:
            striker.stop()
    trees = {name: usage.tree for name, usage in result.usage.items() if usage.tree is not None}
    roles: dict[str, dict[str, float]] = {}
    for tree in trees.values():
        for role, usage in tree.roles.items():
            entry = roles.setdefault(role, {'cpu_percent': 0.0, 'pss_mb': 0.0, 'processes': 0})
            entry['cpu_percent'] += 100.0 * usage.steady_cpu_seconds / max(
                tree.steady_wall_seconds, 1e-9)
            entry['pss_mb'] += usage.pss_mb
            entry['processes'] += usage.processes
    record: dict[str, Any] = {
        'config': config,
        'cpu_percent': round(sum(t.steady_cpu_percent for t in trees.values()), 2),
        'pss_mb': round(sum(t.pss_mb for t in trees.values()), 1),
        'roles': {r: {k: round(v, 2) for k, v in e.items()} for r, e in roles.items()},
        'goal_reached': bool(result.ground_truth) and _at_goal(world, result.ground_truth),
    }
    if config == 'rory':
        events = store_events(out / 'store')
        warm = {(e['node'], e['incarnation']): e['warm'] for e in events if e['kind'] == 'spawn'}
        record['recoveries'] = [
            {'node': e['node'], 'total_ms': e['total_ms'], 'crashes': e['crashes'],
             'warm': warm.get((e['node'], e['incarnation'])), 't': e['t']}
            for e in events if e['kind'] == 'recovered']
        record['strikes'] = [(t, node) for t, node, _ in (striker.done if striker else [])]
        record['strike_errors'] = striker.errors if striker else []
    return record


def _at_goal(world: str, path: list[tuple[float, float, float, float]]) -> bool:
    import math

    from sim.worlds import get_world

    spec = get_world(world)
    goal = spec.goals[spec.default_goal]
    _, x, y, _ = path[-1]
    return math.hypot(x - goal.x, y - goal.y) <= GOAL_XY


def strike_plan() -> list[Strike]:
    """Each node alone, STRIKE_GAP apart, then amcl and grid_slam together."""
    plan = [Strike(SETTLE + i * STRIKE_GAP, (name,)) for i, name in enumerate(STACK)]
    plan.append(Strike(SETTLE + len(STACK) * STRIKE_GAP, ('amcl', 'grid_slam')))
    return plan


def summarise(runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Medians per configuration, and of the per-pair ratios (each configuration against the
    bare run of the same repetition)."""
    by = {c: [r for r in runs if r['config'] == c] for c in CONFIGS}
    out: dict[str, Any] = {}
    for config, group in by.items():
        if group:
            roles = sorted({role for r in group for role in r['roles']})
            out[config] = {
                'cpu_percent': statistics.median(r['cpu_percent'] for r in group),
                'pss_mb': statistics.median(r['pss_mb'] for r in group),
                'roles': {role: {k: statistics.median(r['roles'].get(role, {}).get(k, 0.0)
                                                      for r in group)
                                 for k in ('cpu_percent', 'pss_mb', 'processes')}
                          for role in roles}}
    for config in CONFIGS[1:]:
        pairs = list(zip(by['bare'], by[config], strict=False))
        if pairs and config in out:
            out[config]['cpu_ratio'] = statistics.median(
                r['cpu_percent'] / b['cpu_percent'] for b, r in pairs)
            out[config]['pss_added_mb'] = statistics.median(
                r['pss_mb'] - b['pss_mb'] for b, r in pairs)
    if 'rory' in out and 'cpu_ratio' in out['rory']:
        out['cpu_ratio'] = out['rory']['cpu_ratio']
        out['pss_added_mb'] = out['rory']['pss_added_mb']
        # The goal: the bare nodes' PSS + 60 MB + 15 MB per node.
        out['pss_budget_mb'] = 60.0 + 15.0 * len(STACK)
    return out


def table(summary: dict[str, Any], runs: int) -> str:
    """Markdown: per configuration and role, CPU and PSS (medians)."""
    lines = ['| configuration | role | processes | CPU (% of a core) | PSS (MB) | vs bare |',
             '|---|---|---:|---:|---:|---|']
    for config in CONFIGS:
        entry = summary.get(config)
        if entry is None:
            continue
        for role, usage in entry['roles'].items():
            lines.append(f'| {config} | {role} | {usage["processes"]:.0f} '
                         f'| {usage["cpu_percent"]:.1f} | {usage["pss_mb"]:.0f} | |')
        versus = (f'{entry["cpu_ratio"]:.2f}x, +{entry["pss_added_mb"]:.0f} MB'
                  if 'cpu_ratio' in entry else '')
        lines.append(f'| {config} | **all** | | **{entry["cpu_percent"]:.1f}** '
                     f'| **{entry["pss_mb"]:.0f}** | {versus} |')
    if 'cpu_ratio' in summary:
        lines += ['', f'rory against bare, medians of {runs} side-by-side pairs: CPU '
                      f'**{summary["cpu_ratio"]:.2f}x** (goal 1.10x), PSS '
                      f'**+{summary["pss_added_mb"]:.0f} MB** (goal +{summary["pss_budget_mb"]:.0f}'
                      ' MB)']
    return '\n'.join(lines)


def strikes_table(records: Sequence[dict[str, Any]]) -> str:
    """Markdown: each recovery of the strike runs, in the order they ended."""
    lines = ['| run | node | struck | start | recovered in (ms) |', '|---|---|---|---|---:|']
    for i, record in enumerate(records):
        together = {n for s in strike_plan() if len(s.nodes) > 1 for n in s.nodes}
        seen: dict[str, int] = {}
        for rec in record['recoveries']:
            node = rec['node']
            seen[node] = seen.get(node, 0) + 1
            how = 'with another' if node in together and seen[node] == 2 else 'alone'
            start = {True: 'warm', False: 'cold'}.get(rec['warm'], '?')
            lines.append(f'| {i + 1} | {node} | {how} | {start} | {rec["total_ms"]:.0f} |')
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the pairs, then the strike runs; print the tables."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.stack_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=3,
                        help='repetitions: each configuration once in each')
    parser.add_argument('--configs', nargs='+', choices=CONFIGS, default=['bare', 'rory'],
                        help='configurations to run (bare is needed for the ratios)')
    parser.add_argument('--strike-runs', type=int, default=1)
    parser.add_argument('--world', default='real_room')
    parser.add_argument('--domain', type=int, default=88)
    parser.add_argument('--out', type=Path, default=Path('bench-out/stack'))
    args = parser.parse_args(argv)
    exit_on_sigterm()
    out = args.out.resolve()
    runs: list[dict[str, Any]] = []
    for i, config in alternating([c for c in CONFIGS if c in args.configs], args.runs):
        began = time.monotonic()
        record = run_once(config, args.world, out / 'runs' / f'{config}-{i}', args.domain)
        runs.append(record)
        print(f'[{i + 1}/{args.runs}] {config}: {record["cpu_percent"]:.1f}% of a core, '
              f'{record["pss_mb"]:.0f} MB PSS, goal '
              f'{"reached" if record["goal_reached"] else "NOT reached"} '
              f'({time.monotonic() - began:.0f} s)', flush=True)
    struck = []
    for i in range(args.strike_runs):
        record = run_once('rory', args.world, out / 'runs' / f'strikes-{i}', args.domain,
                          strikes=strike_plan())
        struck.append(record)
        print(f'[strikes {i + 1}/{args.strike_runs}] {len(record["recoveries"])} recoveries, '
              f'goal {"reached" if record["goal_reached"] else "NOT reached"}'
              f'{"; " + "; ".join(record["strike_errors"]) if record["strike_errors"] else ""}',
              flush=True)
    summary = summarise(runs)
    (out / 'stack.json').write_text(json.dumps({'runs': runs, 'strikes': struck,
                                                'summary': summary}, indent=1))
    print(table(summary, args.runs))
    if struck:
        print()
        print(strikes_table(struck))
    return 0


if __name__ == '__main__':
    sys.exit(main())
