"""RORY's fixed processes at rest: the supervisor, its zygote and the warm standby, with several
small nodes supervised and no traffic (issue 36).

    python -m rory_eval.bench.rest_bench [--runs 5] [--seconds 30] [--nodes 6] [--domain 7]
                                         [--standbys N] [--no-spare-forks] [--out DIR]

What a robot pays for RORY while nothing happens is its fixed processes: the supervisor (an
interpreter with rclpy, its participant and the ring's readers), the zygote (the fork server)
and the standbys (forks that have made their participants and wait; the pool's default size
for six nodes is 3, ``--standbys`` sets it) with their spare forks (one for each node beyond
the pool, ``--no-spare-forks`` turns them off). Each run starts one
``rory supervise`` config with ``--nodes`` copies of the example integrator (examples/integrator,
instrumented as rory_eval/harness/scenario.py ``prepare`` does), each with its own node name
and remapped topics (``/numbers_<i>``, ``/integrator_<i>/state``) so that the supervisor keeps
a ring reader and a status per node; method rory and the warm standby on, the defaults. Nothing
publishes. After a warm-up (every node RUNNING, every node's standby asked for and the standby
ready, as the supervisor's events and log say, then ``SETTLE`` seconds), the supervisor's tree
is read about once a second over ``--seconds`` (rory_eval/harness/process_usage.py,
``TreeSampler``): CPU in percent of one core over the window and PSS at its end, per role
(supervisor, zygote, standby, nodes), and CPU per kind of thread (its ``steady_threads``, the
window's second half, in the JSON). A thread at rest runs for a few milliseconds a second and
``stat`` counts 10 ms ticks, one tick in 15 s being 0.07 % of a core; so the breakdown of the
supervisor and the standby that the table shows is read from each thread's ``schedstat``
(nanoseconds on the CPU) at the window's two ends. Every run starts fresh processes. Prints a
Markdown table of medians (the fixed processes together, each of them, the nodes) and where the
supervisor's and the standby's CPU goes per thread; writes ``<out>/rest.json``. It judges
nothing: it is a measurement.

PSS splits a page between the processes that map it, so what the fixed processes hold depends
on how many forks of the zygote share its pages (the nodes take their share) and on every other
process on the machine that maps the same shared libraries: another rclpy program run from the
same installation, or any program of the same Python, lowers the figure (by 3-8 MB, seen here).
Each run records those other processes (``other_users``: those that map the supervisor's
libpython or Fast DDS library) and the bench says so when there were any; run it on a machine
where nothing else of Python or ROS runs.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from rory_eval.harness.process_usage import TreeSampler, thread_kind, tree_pids
from rory_eval.harness.scenario import (
    EventsFile,
    EventTracker,
    child_process,
    prepare,
    scenario_env,
)
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime.supervisor.config import DEFAULT_MAX_STANDBYS

FIXED = ('supervisor', 'zygote', 'standby', 'spare')
"""RORY's processes whatever the nodes: the figure of issue 36."""
ROLES = (*FIXED, 'node')
THREAD_ROLES = ('supervisor', 'standby')
"""The roles whose threads are broken down (the zygote is one thread that waits)."""
SETTLE = 10.0  # s after the standby is ready: its participant's first announcements are over
READY_TIMEOUT = 120.0  # s for every node to run and the standby to be ready


def node_name(i: int) -> str:
    """The i-th node's id in the config and its ROS node name (from 1)."""
    return f'integrator_{i}'


def write_config(workdir: Path, nodes: int, standbys: int | None = None,
                 spare_forks: bool = True) -> Path:
    """The integrator instrumented into ``workdir`` and a config with ``nodes`` copies of it,
    each with its own node name and topics, ``standbys`` (None: the default pool) and
    ``spare_forks``; the config's path."""
    path = prepare(workdir, 'rory', interval=None, pace=None)
    config: dict[str, Any] = yaml.safe_load(path.read_text())
    (node,) = config['nodes']
    config['nodes'] = [
        {**node, 'name': node_name(i),
         'command': [*node['command'], '--ros-args', '-r', f'__node:={node_name(i)}',
                     '-r', f'/numbers:=/numbers_{i}',
                     '-r', f'/integrator/state:=/{node_name(i)}/state']}
        for i in range(1, nodes + 1)
    ]
    if standbys is not None:
        config['standbys'] = standbys
    if not spare_forks:
        config['spare_forks'] = False
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def pool_size(nodes: int, standbys: int | None) -> int:
    """The standbys a supervisor of ``nodes`` integrators keeps (config.py,
    ``SupervisorConfig.standby_pool_size``)."""
    return standbys if standbys is not None else max(1, min(DEFAULT_MAX_STANDBYS, nodes))


def standby_ready(log: str, pid: int) -> bool:
    """Whether the supervisor's log says standby ``pid`` is ready
    (rory_runtime/supervisor/standby.py, ``_watch_ready``)."""
    return re.search(rf'standby pid {pid} ready in ', log) is not None


def main_thread(pid: int) -> str:
    """The thread kind of ``pid``'s main thread: its process name (a thread started unnamed
    inherits its starter's, so the kind may hold more than the main thread)."""
    try:
        return thread_kind(Path(f'/proc/{pid}/comm').read_text().strip())
    except OSError:
        return ''


Threads = dict[int, tuple[str, int, int]]
"""Per thread id: its kind, nanoseconds on the CPU and times it was run (``schedstat``)."""


def thread_ns(pid: int, *, proc: Path = Path('/proc')) -> Threads:
    """Per thread of ``pid``: its kind, the nanoseconds it has run and how many times it was
    put on a CPU (``schedstat``: exact, where ``stat``'s ticks are 10 ms); empty if the process
    is gone."""
    threads: Threads = {}
    try:
        tasks = list((proc / str(pid) / 'task').iterdir())
    except OSError:
        return threads
    for task in tasks:
        try:
            comm = (task / 'comm').read_text().strip()
            fields = (task / 'schedstat').read_text().split()
            ns, runs = int(fields[0]), int(fields[2])
        except (OSError, ValueError, IndexError):
            continue  # the thread ended
        threads[int(task.name)] = (thread_kind(comm), ns, runs)
    return threads


def per_kind(before: Threads, after: Threads, *, runs: bool = False) -> dict[str, int]:
    """Nanoseconds (or runs) per thread kind from before to after."""
    total: dict[str, int] = {}
    for tid, (kind, ns, count) in after.items():
        _, ns_then, count_then = before.get(tid, (kind, 0, 0))
        grown = count - count_then if runs else ns - ns_then
        total[kind] = total.get(kind, 0) + max(0, grown)
    return total


def thread_shares(before: Threads, after: Threads, seconds: float) -> dict[str, float]:
    """Percent of one core per thread kind between two ``thread_ns`` readings ``seconds``
    apart, largest first; a thread born in between counts from 0, one that ended is left out."""
    shares = {kind: round(100.0 * n / 1e9 / max(seconds, 1e-9), 3)
              for kind, n in per_kind(before, after, runs=False).items()}
    return dict(sorted(shares.items(), key=lambda kv: (-kv[1], kv[0])))


def thread_wakeups(before: Threads, after: Threads, seconds: float) -> dict[str, float]:
    """Times per second each thread kind was put on a CPU between the two readings."""
    return {kind: round(n / max(seconds, 1e-9), 1)
            for kind, n in per_kind(before, after, runs=True).items()}


SHARED = ('/libpython', '/libfastrtps.so')
"""Libraries whose other users on the machine lower the PSS measured here: the interpreter's
and Fast DDS's (a program of the same Python shares the first, one of the same ROS both)."""


def shared_libraries(pid: int, *, proc: Path = Path('/proc')) -> list[str]:
    """The paths of the ``SHARED`` libraries ``pid`` maps (none if it is gone)."""
    try:
        maps = (proc / str(pid) / 'maps').read_text()
    except OSError:
        return []
    paths: list[str] = []
    for line in maps.splitlines():
        parts = line.split(maxsplit=5)
        if len(parts) == 6 and any(name in parts[5] for name in SHARED):
            path = parts[5].strip()
            if path not in paths:
                paths.append(path)
    return paths


def other_users(libraries: Sequence[str], ours: set[int], *,
                proc: Path = Path('/proc')) -> dict[int, str]:
    """Processes outside ``ours`` that map any of ``libraries`` (their command lines, cut
    short): they share its pages, and so lower the PSS measured here."""
    users: dict[int, str] = {}
    if not libraries:
        return users
    for entry in proc.iterdir():
        if not entry.name.isdigit() or int(entry.name) in ours:
            continue
        try:
            maps = (entry / 'maps').read_text()
            if not any(library in maps for library in libraries):
                continue
            argv = (entry / 'cmdline').read_bytes().split(b'\0')
        except OSError:
            continue
        users[int(entry.name)] = ' '.join(a.decode(errors='replace') for a in argv if a)[:100]
    return users


def run_once(workdir: Path, domain: int, nodes: int, seconds: float,
             standbys: int | None = None, spare_forks: bool = True) -> dict[str, Any]:
    """One run: start the supervisor with ``nodes`` integrators, wait until all run and the
    standby pool is ready, measure its tree over ``seconds``; usage per role
    (TreeUsage.to_json)."""
    workdir = workdir.resolve()
    # A run of an earlier invocation into the same --out: its events would be read as this one's.
    shutil.rmtree(workdir / 'store-rory', ignore_errors=True)
    config = write_config(workdir, nodes, standbys, spare_forks)
    pool = pool_size(nodes, standbys)
    events = EventsFile(workdir / 'store-rory' / 'events.jsonl')
    names = [node_name(i) for i in range(1, nodes + 1)]
    trackers = {name: EventTracker() for name in names}
    standby_pids: list[int] = []  # every standby pid, in the order the events gave them
    log = workdir / 'supervisor.log'

    def poll() -> list[dict[str, Any]]:
        new = events.poll()
        for ev in new:
            if ev.get('node') in trackers:
                trackers[ev['node']].feed([ev])
                if ev['kind'] == 'standby':
                    standby_pids.append(int(ev['pid']))
        return new

    with child_process([sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
                       scenario_env(domain), workdir, log) as sup:
        deadline = time.monotonic() + READY_TIMEOUT
        while not (all(t.state == 'RUNNING' for t in trackers.values())
                   and len(set(standby_pids)) >= pool
                   and all(standby_ready(log.read_text(), pid) for pid in set(standby_pids))):
            poll()
            if sup.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError('the nodes did not all run with a standby ready:\n'
                                   + log.read_text()[-4000:])
            time.sleep(0.05)
        time.sleep(SETTLE)
        poll()
        watched = {'supervisor': sup.pid, 'standby': standby_pids[-1]}
        sampler = TreeSampler(sup.pid)
        sampler.start()
        opened = time.monotonic()
        before = {role: thread_ns(pid) for role, pid in watched.items()}
        end = opened + seconds
        while time.monotonic() < end:
            time.sleep(1.0)
            sampler.sample()
        after = {role: thread_ns(pid) for role, pid in watched.items()}
        elapsed = time.monotonic() - opened
        threads = {role: thread_shares(before[role], after[role], elapsed) for role in watched}
        wakeups = {role: thread_wakeups(before[role], after[role], elapsed) for role in watched}
        usage = sampler.finish()
        during = poll()
        mains = {role: main_thread(pid) for role, pid in watched.items()}
        others = other_users(shared_libraries(sup.pid), {*tree_pids(sup.pid), os.getpid()})
        if sup.poll() is not None:
            raise RuntimeError(f'the supervisor exited:\n{log.read_text()[-4000:]}')
    kinds: dict[str, int] = {}
    for ev in during:
        kinds[ev['kind']] = kinds.get(ev['kind'], 0) + 1
    roles = usage.to_json()
    counts = {role: roles.get(role, {}).get('processes', 0) for role in ROLES}
    # one for each node beyond the pool (supervisor/standby.py)
    spares = max(0, nodes - pool) if spare_forks else 0
    if counts != {'supervisor': 1, 'zygote': 1, 'standby': pool, 'spare': spares,
                  'node': nodes}:
        raise RuntimeError(f'not the processes of a supervisor at rest: {counts}')
    if kinds.get('spawn') or kinds.get('exit'):
        raise RuntimeError(f'a node started or ended in the window: {kinds}')
    return {'wall_seconds': round(usage.wall_seconds, 2),
            'steady_wall_seconds': round(usage.steady_wall_seconds, 2),
            'standby_pids': sorted(set(standby_pids)), 'pool': pool,
            'main_threads': mains, 'events_in_window': kinds, 'other_users': others,
            'roles': roles, 'threads_percent': threads, 'threads_wakeups': wakeups,
            'fixed': fixed_of(roles)}


def fixed_of(roles: dict[str, dict[str, Any]]) -> dict[str, float]:
    """The fixed processes together: CPU over the window and PSS at its end."""
    return {'cpu_percent': round(sum(roles.get(r, {}).get('cpu_percent', 0.0) for r in FIXED), 2),
            'pss_mb': round(sum(roles.get(r, {}).get('pss_mb', 0.0) for r in FIXED), 1)}


def _spread(values: Sequence[float]) -> dict[str, float]:
    return {'median': statistics.median(values), 'min': min(values), 'max': max(values)}


def summarise(runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Medians over the runs (with min and max): the fixed processes together (the median of
    each run's sum, not the sum of the medians), each role, and the supervisor's and the
    standby's CPU per thread kind over the window (``schedstat``; a kind a run did not show
    counts 0 there) with the median of their sums, and how often each kind ran a second."""
    if not runs:
        raise ValueError('no runs to summarise')
    out: dict[str, Any] = {
        'runs': len(runs),
        'runs_not_alone': sum(1 for r in runs if r.get('other_users')),
        'fixed': {key: _spread([r['fixed'][key] for r in runs])
                  for key in ('cpu_percent', 'pss_mb')},
        'roles': {}, 'threads': {}, 'threads_all': {}, 'wakeups': {},
    }
    for role in ROLES:
        group = [r['roles'].get(role, {}) for r in runs]
        out['roles'][role] = {
            'processes': statistics.median(g.get('processes', 0) for g in group),
            **{key: _spread([g.get(key, 0.0) for g in group])
               for key in ('cpu_percent', 'steady_cpu_percent', 'pss_mb')}}
    for role in THREAD_ROLES:
        per_run = [r.get('threads_percent', {}).get(role, {}) for r in runs]
        kinds = {kind for threads in per_run for kind in threads}
        medians = {kind: statistics.median(t.get(kind, 0.0) for t in per_run) for kind in kinds}
        out['threads'][role] = dict(sorted(medians.items(), key=lambda kv: (-kv[1], kv[0])))
        out['threads_all'][role] = _spread([sum(t.values()) for t in per_run])
        woken = [r.get('threads_wakeups', {}).get(role, {}) for r in runs]
        out['wakeups'][role] = {kind: statistics.median(w.get(kind, 0.0) for w in woken)
                                for kind in medians}
    mains = [r.get('main_threads', {}) for r in runs]
    out['main_threads'] = {role: statistics.mode(m.get(role, '') for m in mains)
                           for role in THREAD_ROLES}
    return out


def _cell(spread: dict[str, float], digits: int, bold: bool = False) -> str:
    median = f'{spread["median"]:.{digits}f}'
    if bold:
        median = f'**{median}**'
    return f'{median} ({spread["min"]:.{digits}f}-{spread["max"]:.{digits}f})'


def table(summary: dict[str, Any]) -> str:
    """Markdown: per process role, CPU and PSS (medians, min-max), then per thread kind of the
    supervisor and the standby."""
    roles = summary['roles']
    nodes = roles['node']['processes']
    lines = [f'Medians of {summary["runs"]} runs (min-max); CPU in % of one core over the window, '
             'PSS at its end.', '',
             '| process | CPU (% of a core) | PSS (MB) |', '|---|---:|---:|',
             f'| **fixed: supervisor + zygote + standbys + spares** | '
             f'{_cell(summary["fixed"]["cpu_percent"], 2, True)} '
             f'| {_cell(summary["fixed"]["pss_mb"], 1, True)} |']
    for role in FIXED:
        lines.append(f'| {role} | {_cell(roles[role]["cpu_percent"], 2)} '
                     f'| {_cell(roles[role]["pss_mb"], 1)} |')
    lines.append(f'| the {nodes:g} nodes (not in the figure) '
                 f'| {_cell(roles["node"]["cpu_percent"], 2)} '
                 f'| {_cell(roles["node"]["pss_mb"], 1)} |')
    lines += ['', 'Per thread kind over the window (schedstat; medians): % of one core, and '
              'how many times a second it ran:', '',
              '| thread | ' + ' | '.join(f'{role} % | runs/s' for role in THREAD_ROLES) + ' |',
              '|---|' + '---:|---:|' * len(THREAD_ROLES)]
    threads, wakeups = summary['threads'], summary['wakeups']
    order: list[str] = []
    for role in THREAD_ROLES:
        order += [kind for kind in threads[role] if kind not in order]
    mains = {kind: role for role, kind in summary.get('main_threads', {}).items() if kind}
    for kind in order:
        cells = [f'{threads[role][kind]:.3f} | {wakeups[role].get(kind, 0.0):.1f}'
                 if kind in threads[role] else '- | -' for role in THREAD_ROLES]
        label = f'`{kind}` (the {mains[kind]}\'s main thread)' if kind in mains else f'`{kind}`'
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    lines.append('| **all threads** | ' + ' | '.join(
        f'**{summary["threads_all"][role]["median"]:.3f}** | '
        f'{sum(wakeups[role].values()):.1f}' for role in THREAD_ROLES) + ' |')
    if summary.get('runs_not_alone'):
        lines += ['', f'Not alone in {summary["runs_not_alone"]} of {summary["runs"]} runs: other '
                  'processes mapped the same Python or DDS library and shared its pages, so PSS '
                  'is lower than alone.']
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the bench; print the table."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.rest_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--seconds', type=float, default=30.0, help='measured window (s)')
    parser.add_argument('--nodes', type=int, default=6, help='integrators supervised')
    parser.add_argument('--domain', type=int, default=7)
    parser.add_argument('--standbys', type=int, default=None,
                        help="the supervisor's standby pool (default: the config's default)")
    parser.add_argument('--no-spare-forks', dest='spare_forks', action='store_false',
                        help='the config says spare_forks: false')
    parser.add_argument('--out', help='keep the runs and rest.json here')
    args = parser.parse_args(argv)
    if args.runs < 1 or args.seconds <= 0 or args.nodes < 1 or (
            args.standbys is not None and args.standbys < 1):
        parser.error('--runs, --nodes and --standbys must be at least 1, --seconds positive')
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-rest-'))
    runs: list[dict[str, Any]] = []
    for i in range(args.runs):
        result = run_once(root / f'run{i}', args.domain, args.nodes, args.seconds,
                          args.standbys, args.spare_forks)
        runs.append(result)
        roles = result['roles']
        print(f'[{i + 1}/{args.runs}] fixed {result["fixed"]["cpu_percent"]:.2f} % of a core, '
              f'{result["fixed"]["pss_mb"]:.1f} MB PSS ('
              + ', '.join(f'{r} {roles[r]["cpu_percent"]:.2f} % {roles[r]["pss_mb"]:.1f} MB'
                          for r in FIXED if r in roles)  # (no spare: none ran)
              + f'); {args.nodes} nodes {roles["node"]["cpu_percent"]:.2f} %, '
              f'{roles["node"]["pss_mb"]:.1f} MB', flush=True)
        if result['other_users']:
            print(f'  not alone: {len(result["other_users"])} other processes map the same '
                  'Python or DDS library and share its pages (PSS lower): '
                  + '; '.join(f'{pid} {cmd[:60]}' for pid, cmd in result['other_users'].items()),
                  flush=True)
    summary = summarise(runs)
    root.mkdir(parents=True, exist_ok=True)
    (root / 'rest.json').write_text(json.dumps(
        {'nodes': args.nodes, 'seconds': args.seconds, 'settle': SETTLE, 'runs': runs,
         'summary': summary}, indent=1))
    print()
    print(table(summary))
    if not args.out:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
