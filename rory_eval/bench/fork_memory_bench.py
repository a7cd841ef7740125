"""What RORY's extra processes cost in memory at the least, and what forking would save.

    python -m rory_eval.bench.fork_memory_bench [--target amcl] [--runs 3] [--settle 8]

RORY runs three Python rclpy processes where the bare robot runs one: the node, the supervisor
and the warm standby. Each is measured here doing nothing but exist: it has imported what its
role imports, called ``rclpy.init`` under RORY's DDS profile, and made a node with raw
subscriptions to the target's inputs, spun by an executor. No message flows, so this is the
floor under issue 7's memory goal (+50 MB against the bare node), not the workload's figure
(``overhead_bench`` gives that). Four layouts, alternating run by run:

- ``bare``: one process with the bare node's imports (the target's own foreign imports);
- ``separate``: today's layout, three interpreters started on their own: node and standby with
  the target's imports and RORY's runtime, the supervisor with its own module;
- ``zygote``: one process imports all of that, freezes its objects (``gc.freeze``) and forks the
  three, then waits: a fork server next to the supervisor;
- ``parent``: the same, but the process forks two and becomes the third itself, as a
  supervisor would that forks its node and standby before its own ``rclpy.init``.

Forked children share every page their parent had until one of them writes it (Python's
reference counts write many). PSS splits a shared page between the processes that map it, so
the sum of PSS over a layout's processes is the memory the layout takes.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from rory_eval.harness.process_usage import read_process, tree_pids
from rory_eval.targets import TARGETS

LAYOUTS = ('bare', 'separate', 'zygote', 'parent')
ROLES = ('node', 'supervisor', 'standby')


def _imports(role: str, target: str) -> list[str]:
    """Modules a role imports before ``rclpy.init`` (warm_imports for the target's)."""
    if role == 'supervisor':
        return ['rory_runtime.supervisor.supervisor', 'rory_runtime.supervisor.ring']
    own = ['rory_runtime.node.attach', 'rory_runtime.log'] if role != 'bare' else []
    return [f'@{target}', *own]


def _import_all(names: Sequence[str]) -> None:
    from rory_runtime.standby import Program, warm_imports

    for name in names:
        if name.startswith('@'):
            target = name[1:]
            warm_imports(Program.parse([str(TARGETS[target].node)]))
        else:
            importlib.import_module(name)


def _become_participant(role: str, inputs: Sequence[str]) -> None:
    """rclpy.init, a node with raw subscriptions to the inputs, spun until killed."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import LaserScan

    rclpy.init()
    node = rclpy.create_node(f'fork_bench_{role}_{os.getpid()}')
    for topic in inputs:
        # The type only matters to matching; nobody publishes here.
        node.create_subscription(LaserScan, topic, lambda _m: None, qos_profile_sensor_data,
                                 raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.spin()


def _child(layout: str, role: str, target: str, inputs: Sequence[str]) -> None:
    """Run one process of a layout (and, for the fork layouts, the ones it forks)."""
    if layout in ('bare', 'separate'):
        _import_all(_imports(role, target))
        _become_participant(role, inputs)
        return
    union: list[str] = []
    for r in ROLES:
        union += [n for n in _imports(r, target) if n not in union]
    _import_all(union)
    gc.collect()
    gc.freeze()  # the collector would otherwise write to every shared object's header
    forked = ROLES if layout == 'zygote' else ROLES[::2]  # 'parent' is the supervisor itself
    for r in forked:
        if os.fork() == 0:
            try:
                _become_participant(r, inputs)
            finally:
                os._exit(0)
    if layout == 'parent':
        _become_participant('supervisor', inputs)
    else:
        signal.pause()


def _measure(roots: Sequence[int]) -> list[float]:
    """PSS (MB) of every process in the trees."""
    sizes = []
    for root in roots:
        for pid in tree_pids(root):
            reading = read_process(pid, with_pss=True)
            if reading is not None:
                sizes.append(reading.pss_mb)
    return sizes


def _stop(procs: Sequence[subprocess.Popen[bytes]]) -> None:
    for proc in procs:
        for pid in tree_pids(proc.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    for proc in procs:
        proc.wait()


def run_layout(layout: str, target: str, inputs: Sequence[str], settle: float,
               env: dict[str, str]) -> list[float]:
    """Start a layout, let it settle, and return its processes' PSS (MB)."""
    def start(role: str) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [sys.executable, '-m', 'rory_eval.bench.fork_memory_bench', '--child', layout,
             '--role', role, '--target', target, '--inputs', *inputs], env=env)
    if layout == 'bare':
        procs = [start('bare')]
    elif layout == 'separate':
        procs = [start(role) for role in ROLES]
    else:
        procs = [start('all')]
    try:
        time.sleep(settle)
        for proc in procs:
            if proc.poll() is not None:
                raise RuntimeError(f'{layout}: a process exited early ({proc.returncode})')
        return _measure([p.pid for p in procs])
    finally:
        _stop(procs)


def main(argv: Sequence[str] | None = None) -> int:
    """Run every layout ``--runs`` times, interleaved; print medians."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.fork_memory_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--target', default='amcl', choices=sorted(TARGETS))
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--settle', type=float, default=8.0,
                        help='seconds before measuring (discovery and start-up done)')
    parser.add_argument('--domain', type=int, default=75)
    parser.add_argument('--out', type=Path, default=None, help='write the runs as JSON here')
    parser.add_argument('--child', choices=LAYOUTS, help=argparse.SUPPRESS)
    parser.add_argument('--role', help=argparse.SUPPRESS)
    parser.add_argument('--inputs', nargs='*', default=['/scan', '/odom'], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        _child(args.child, args.role, args.target, args.inputs)
        return 0
    if args.runs < 1 or args.settle <= 0:
        parser.error('--runs must be at least 1 and --settle positive')

    from rory_runtime.dds import fast_rediscovery_env

    env = {**os.environ, 'ROS_DOMAIN_ID': str(args.domain),
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    env.update(fast_rediscovery_env(env))
    runs: dict[str, list[list[float]]] = {layout: [] for layout in LAYOUTS}
    for run in range(args.runs):
        for layout in LAYOUTS:
            sizes = run_layout(layout, args.target, args.inputs, args.settle, env)
            runs[layout].append(sizes)
            print(f'run {run + 1} {layout}: ' + ' + '.join(f'{s:.1f}' for s in sizes)
                  + f' = {sum(sizes):.1f} MB', file=sys.stderr)
    if args.out is not None:
        args.out.write_text(json.dumps(runs, indent=1))
    bare = statistics.median(sum(s) for s in runs['bare'])
    print(f'{args.target}\'s imports, {len(args.inputs)} raw subscriptions, idle; '
          f'medians of {args.runs}')
    print('| layout | processes | PSS (MB) | added to bare (MB) |')
    print('|---|---:|---:|---:|')
    for layout in LAYOUTS:
        total = statistics.median(sum(s) for s in runs[layout])
        count = len(runs[layout][0])
        added = '-' if layout == 'bare' else f'+{total - bare:.0f}'
        print(f'| {layout} | {count} | {total:.0f} | {added} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
